"""ROS 2 topics as sources by meaning: a spec tags a ROS 2 topic, the planner plans with it, and
the adaptation loop sees its publishers come and go through rmw_zenoh's liveliness tokens."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from dyknow import Manager
from dyknow.ros2 import Ros2Node, Ros2Source
from dyknow.spec import TransformationSpec
from dyknow.spec.model import Param, Port, Tag
from dyknow.testing import SCENARIO_SPECS, Sink
from dyknow.transport import open_session
from tests.conftest import free_port, wait_until
from tests.test_adaptation import ONTOLOGY, Events

ROS_CAMERA = TransformationSpec(
    "ros2-camera(bottom)",
    "dyknow.ros2.bridge:Ros2Source",
    (
        Param("binding", "string", "ros2:/camera/image_raw?type=sensor_msgs/msg/Image"),
        Param("require_publisher", "bool", True),  # a producer only while its ROS 2 publisher is there
        Param("wait_s", "float", 0.5),
    ),
    (Port("out", "out"),),
    (Tag("out", "RawImage(bottom)"),),
    priority=0,  # preferred over the scenario's own cameras
)


def test_a_tagged_ros2_topic_is_planned_with_and_left_when_its_publisher_goes(make_manager: Callable[..., Manager]) -> None:
    port = free_port()
    robot = make_manager(
        specs=[SCENARIO_SPECS, ROS_CAMERA], ontology=[ONTOLOGY], dwell_s=0.3, listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=5
    )
    events = Events(robot)
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
        Ros2Node(session, "camera_driver", domain=5) as driver,
    ):
        pub = driver.create_publisher("/camera/image_raw", "sensor_msgs/msg/Image")
        key = robot.request("RawImage(bottom)")
        labels = {u.label for u in robot.get_model().units}
        assert "ros2-camera(bottom)" in labels and "robot-camera" not in labels
        robot.spawn("consumer", "viewer", bindings={"in": key})
        viewer = robot.unit("viewer")
        assert isinstance(viewer, Sink)
        source = next(robot.unit(u.name) for u in robot.get_model().units if u.label == "ros2-camera(bottom)")
        assert isinstance(source, Ros2Source)
        wait_until(lambda: source.publishers == 1, "the driver's publisher seen")
        stop = threading.Event()
        frame = driver.types.message_class("sensor_msgs/msg/Image")

        def drive() -> None:
            data = np.zeros(4 * 4 * 3, np.uint8)
            while not stop.wait(0.02):
                pub.publish(frame(header=_header(driver), height=4, width=4, encoding="rgb8", is_bigendian=0, step=12, data=data))

        thread = threading.Thread(target=drive, daemon=True)
        thread.start()
        try:
            viewer.wait_for(3)
            assert viewer.messages[0].payload.shape == (4, 4, 3)
        finally:
            stop.set()
            thread.join()
        pub.close()  # the driver's publisher goes: its token vanishes
        event = events.wait("adapted")
        assert "ros2-camera(bottom)" in str(event.to_dict())
        wait_until(lambda: "robot-camera" in {u.label for u in robot.get_model().units}, "the robot's own camera instead")
        count = len(viewer.messages)
        viewer.wait_for(count + 3)  # the stream goes on, on the same key
        # the driver publishes again: once the back-off ends, the request is back on the ROS 2 camera
        pub = driver.create_publisher("/camera/image_raw", "sensor_msgs/msg/Image")
        wait_until(
            lambda: any(e.kind == "adapted" and "ros2-camera(bottom)" in e.new for e in events.events),
            "the request back on the ROS 2 camera",
        )
        assert "ros2-camera(bottom)" in {u.label for u in robot.get_model().units}


def _header(node: Ros2Node) -> object:
    types = node.types
    return types.message_class("std_msgs/msg/Header")(
        stamp=types.message_class("builtin_interfaces/msg/Time")(sec=1, nanosec=0), frame_id="cam"
    )
