"""A real ROS 2 node: rclpy from the ROS 2 wheels, on its default DDS middleware (rmw_fastrtps_cpp),
run as a child process with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (discovery on loopback).

    python tests/ros2_rclpy_peer.py talk TOPIC TYPE     publish every 20 ms until stdin closes
    python tests/ros2_rclpy_peer.py listen TOPIC TYPE   print each message received, one JSON line

Prints {"ready": true} once its publisher or subscription exists. TYPE: std_msgs/msg/String or
sensor_msgs/msg/Image (a 2 x 3 rgb8 frame of bytes 0..17, stamped sec=i, nanosec=5).
"""

from __future__ import annotations

import json
import sys
import threading
import warnings

with warnings.catch_warnings():  # ROS 2's parser (lark 0.12) imports the deprecated sre_parse
    warnings.simplefilter("ignore", DeprecationWarning)
    import rclpy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String


def out(record: dict[str, object]) -> None:
    print(json.dumps(record), flush=True)


def main() -> None:
    mode, topic, ros_type = sys.argv[1:4]
    rclpy.init()
    node = rclpy.create_node(f"rclpy_{mode}")
    cls = String if ros_type == "std_msgs/msg/String" else Image
    closed = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), closed.set()), daemon=True).start()
    if mode == "talk":
        pub = node.create_publisher(cls, topic, 10)
        out({"ready": True})
        i = 0
        while not closed.is_set() and i < 3000:
            i += 1
            if cls is String:
                pub.publish(String(data=f"hello {i}"))
            else:
                msg = Image(height=2, width=3, encoding="rgb8", step=9, data=bytes(range(18)))
                msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = i, 5, "cam"
                pub.publish(msg)
            rclpy.spin_once(node, timeout_sec=0.02)
    else:

        def received(msg: object) -> None:
            if isinstance(msg, String):
                out({"data": msg.data})
            else:
                assert isinstance(msg, Image)
                out({"encoding": msg.encoding, "height": msg.height, "width": msg.width, "step": msg.step, "data": list(msg.data),
                     "stamp": [msg.header.stamp.sec, msg.header.stamp.nanosec]})  # fmt: skip

        node.create_subscription(cls, topic, received, 10)
        out({"ready": True})
        while not closed.is_set():
            rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
