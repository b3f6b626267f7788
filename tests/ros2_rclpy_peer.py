"""A real ROS 2 node: rclpy from the ROS 2 wheels, on its default DDS middleware (rmw_fastrtps_cpp),
run as a child process with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (discovery on loopback).

    python tests/ros2_rclpy_peer.py talk TOPIC TYPE     publish every 20 ms until stdin closes
    python tests/ros2_rclpy_peer.py listen TOPIC TYPE   print each message received, one JSON line
    python tests/ros2_rclpy_peer.py lifecycle NAME [TOPIC]
                                                        a lifecycle node NAME (rclpy.lifecycle), its services
                                                        /NAME/get_state, /NAME/change_state, ...; prints each transition;
                                                        a double parameter "exposure" (0.1); publishes std_msgs/String
                                                        on TOPIC every 20 ms while active; a line "fail" on stdin makes
                                                        it fail a deactivation (ErrorProcessing, then unconfigured), a line
                                                        "stall" makes it stop publishing, a line "die-on-activate" makes
                                                        its next activation end the process (exit status 3, no answer)
    python tests/ros2_rclpy_peer.py call SERVICE TYPE JSON [TIMEOUT]
                                                        an rclpy client calls once (JSON: the request's fields,
                                                        lifecycle_msgs types) and prints {"response": ...} or null

    python tests/ros2_rclpy_peer.py diagnostics-listen  print each diagnostic_msgs/DiagnosticArray on /diagnostics as
                                                        {"statuses": [{"name", "level", "message", "hardware_id", "values"}]}
    python tests/ros2_rclpy_peer.py diagnostics-talk    publish on /diagnostics every 50 ms the statuses of the latest
                                                        stdin line (a JSON list of {"name", "level", "message",
                                                        "hardware_id", "values": {key: value}}), none before the first

Prints {"ready": true} once its publisher, subscription, node or client exists. TYPE: std_msgs/msg/String,
sensor_msgs/msg/Image (a 2 x 3 rgb8 frame of bytes 0..17, stamped sec=i, nanosec=5) or, to talk,
geometry_msgs/msg/TwistStamped (stamped sec=i, nanosec=5; twist.linear.x = i % 2).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
import warnings

with warnings.catch_warnings():  # ROS 2's parser (lark 0.12) imports the deprecated sre_parse
    warnings.simplefilter("ignore", DeprecationWarning)
    import rclpy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String


def out(record: dict[str, object]) -> None:
    print(json.dumps(record), flush=True)


def lifecycle(name: str, closed: threading.Event, commands: list[str], topic: str | None = None) -> None:
    from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn

    class Node(LifecycleNode):
        failing = False
        stalled = False
        dying = False

        def on_configure(self, state: State) -> TransitionCallbackReturn:
            out({"transition": "configure", "exposure": self.get_parameter("exposure").value})
            if topic is not None:
                self.pub = self.create_lifecycle_publisher(String, topic, 10)
            return TransitionCallbackReturn.SUCCESS

        def on_activate(self, state: State) -> TransitionCallbackReturn:
            out({"transition": "activate"})
            if self.dying:  # the process ends mid-transition, as a crash would (it answers nothing)
                os._exit(3)
            return super().on_activate(state)

        def on_deactivate(self, state: State) -> TransitionCallbackReturn:
            out({"transition": "deactivate"})
            if self.failing:
                self.failing = False
                return TransitionCallbackReturn.ERROR  # to ErrorProcessing, then (rclpy's on_error succeeds) unconfigured
            return super().on_deactivate(state)

        def on_cleanup(self, state: State) -> TransitionCallbackReturn:
            out({"transition": "cleanup"})
            return TransitionCallbackReturn.SUCCESS

    node = Node(name)
    node.declare_parameter("exposure", 0.1)
    out({"ready": True})
    i = 0
    while not closed.is_set():
        rclpy.spin_once(node, timeout_sec=0.02)
        while commands:
            command = commands.pop(0)
            if command == "fail":  # an error in a transition: ErrorProcessing, then unconfigured
                node.failing = True
                node.trigger_deactivate()
            elif command == "stall":  # stays active, publishes nothing more
                node.stalled = True
            elif command == "die-on-activate":
                node.dying = True
        if topic is not None and hasattr(node, "pub") and not node.stalled:
            i += 1
            node.pub.publish(String(data=f"{name} {i}"))  # a lifecycle publisher sends only while active
    node.destroy_node()


def call(service: str, srv_type: str, fields: str, timeout_s: float, closed: threading.Event) -> None:
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    cls = {"lifecycle_msgs/srv/GetState": GetState, "lifecycle_msgs/srv/ChangeState": ChangeState}[srv_type]
    node = rclpy.create_node("rclpy_client")
    client = node.create_client(cls, service)
    out({"ready": True})
    request = cls.Request()
    given = json.loads(fields)
    if "transition" in given:
        request.transition = Transition(id=given["transition"]["id"], label=given["transition"].get("label", ""))
    if not client.wait_for_service(timeout_sec=timeout_s):
        out({"response": None, "why": "no service"})
    else:
        out({"service": "found"})
        # the client matched the server, but the server may not know the client's writer yet (a
        # reader drops data from a writer it has not discovered): ask again every half second
        deadline = time.monotonic() + timeout_s
        futures = []
        got = None
        while got is None and time.monotonic() < deadline:
            futures.append(client.call_async(request))
            ask_again = time.monotonic() + 0.5
            while got is None and time.monotonic() < min(ask_again, deadline):
                rclpy.spin_once(node, timeout_sec=0.05)
                got = next((f.result() for f in futures if f.done()), None)
        if got is None:
            out({"response": None, "why": "no answer"})
        elif isinstance(got, GetState.Response):
            out({"response": {"current_state": {"id": got.current_state.id, "label": got.current_state.label}}})
        else:
            out({"response": {"success": got.success}})
    node.destroy_node()


def diagnostics(mode: str, closed: threading.Event, commands: list[str]) -> None:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    node = rclpy.create_node(f"rclpy_{mode.replace('-', '_')}")
    if mode == "diagnostics-listen":

        def received(msg: DiagnosticArray) -> None:
            statuses = [
                {"name": s.name, "level": s.level[0] if isinstance(s.level, bytes) else int(s.level), "message": s.message,
                 "hardware_id": s.hardware_id, "values": {kv.key: kv.value for kv in s.values}}
                for s in msg.status
            ]  # fmt: skip
            out({"statuses": statuses})

        node.create_subscription(DiagnosticArray, "/diagnostics", received, 10)
        out({"ready": True})
        while not closed.is_set():
            rclpy.spin_once(node, timeout_sec=0.05)
    else:
        pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        out({"ready": True})
        statuses: list[DiagnosticStatus] | None = None
        while not closed.is_set():
            while commands:
                given = json.loads(commands.pop(0))
                statuses = [
                    DiagnosticStatus(level=bytes([s["level"]]), name=s["name"], message=s.get("message", ""), hardware_id=s.get("hardware_id", ""),
                                     values=[KeyValue(key=k, value=v) for k, v in s.get("values", {}).items()])
                    for s in given
                ]  # fmt: skip
            if statuses is not None:
                array = DiagnosticArray(status=statuses)
                array.header.stamp = node.get_clock().now().to_msg()
                pub.publish(array)
            rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_node()


def main() -> None:
    if sys.argv[1] in ("diagnostics-listen", "diagnostics-talk"):
        rclpy.init()
        closed = threading.Event()
        commands: list[str] = []

        def read() -> None:
            for line in sys.stdin:
                commands.append(line.strip())
            closed.set()

        threading.Thread(target=read, daemon=True).start()
        diagnostics(sys.argv[1], closed, commands)
        rclpy.shutdown()
        return
    if sys.argv[1] in ("lifecycle", "call"):
        rclpy.init()
        closed = threading.Event()
        commands: list[str] = []

        def read() -> None:
            for line in sys.stdin:
                commands.append(line.strip())
            closed.set()

        threading.Thread(target=read, daemon=True).start()
        if sys.argv[1] == "lifecycle":
            lifecycle(sys.argv[2], closed, commands, sys.argv[3] if len(sys.argv) > 3 else None)
        else:
            call(sys.argv[2], sys.argv[3], sys.argv[4], float(sys.argv[5]) if len(sys.argv) > 5 else 10.0, closed)
        rclpy.shutdown()
        return
    mode, topic, ros_type = sys.argv[1:4]
    rclpy.init()
    node = rclpy.create_node(f"rclpy_{mode}")
    from geometry_msgs.msg import TwistStamped

    cls = {"std_msgs/msg/String": String, "geometry_msgs/msg/TwistStamped": TwistStamped}.get(ros_type, Image)
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
            elif cls is TwistStamped:
                twist = TwistStamped()
                twist.header.stamp.sec, twist.header.stamp.nanosec, twist.header.frame_id = i, 5, "base"
                twist.twist.linear.x = float(i % 2)
                pub.publish(twist)
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
