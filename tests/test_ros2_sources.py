"""ROS 2 topics as sources by meaning: a spec tags a ROS 2 topic, the planner plans with it, and
the adaptation loop sees its publishers come and go through rmw_zenoh's liveliness tokens."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest

from dyknow import Manager
from dyknow.ros2 import Ros2Node, Ros2Source, graph, snapshot
from dyknow.ros2.names import HASH_NOT_SUPPORTED, Entity, EntityKind, QoS, publisher_pattern
from dyknow.spec import TransformationSpec
from dyknow.spec.model import Param, Port, Tag
from dyknow.testing import SCENARIO_SPECS, Sink
from dyknow.transport import Session, make_config, open_session
from tests.conftest import UNIT_SPECS, free_port, wait_until
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


def _token(session: Session, domain: int, topic: str, i: int, ros_type: str, type_hash: str) -> object:
    """A publisher's liveliness token and nothing else, as anyone on the network may declare."""
    entity = Entity(domain, f"f{i:031x}", 1, 100 + i, EntityKind.PUBLISHER, "/", f"fake{i}", "/", topic, ros_type, type_hash, QoS())
    return session.declare_liveliness_token(entity.token())


REQUIRING = replace(ROS_CAMERA, label="ros2-camera(flooded)", tags=(Tag("out", "RawImage(flooded)"),))


def test_a_flood_of_tokens_of_other_topics_hides_no_publisher(
    make_manager: Callable[..., Manager], monkeypatch: pytest.MonkeyPatch
) -> None:
    """10,500 fake publisher tokens filled the graph a manager kept (10,000 entries), after which
    a source requiring a publisher failed while a real one was up. A source now watches its
    topic's publishers alone. (Here the graph's bound is 100, so that 150 tokens fill it.) The
    driver's Zenoh id sorts after the fakes' session ids, so that its tokens are never among the
    first the network lists: a bounded view of the whole graph leaves them out."""
    monkeypatch.setattr(graph, "MAX_ENTITIES", 100)
    port = free_port()
    robot = make_manager(specs=[UNIT_SPECS, REQUIRING], listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=26)
    robot.spawn("sink", "early", bindings={"in": "ros2:/elsewhere?type=std_msgs/msg/String"})  # the manager's node watches already
    last = make_config(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"])
    last.insert_json5("id", json.dumps("f" * 32))  # after every fake's "f000...", in any sorted listing
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as attacker,
        Session(last) as session,
    ):
        fakes = [_token(attacker, 26, f"/noise/n{i}", i, "std_msgs/msg/String", HASH_NOT_SUPPORTED) for i in range(150)]
        wait_until(lambda: len(robot.session.alive("@ros2_lv/26/*/*/*/MP/**", timeout_s=0.2)) >= 150, "the flood seen by the manager")
        with Ros2Node(session, "camera_driver", domain=26) as driver:
            driver.create_publisher("/camera/image_raw", "sensor_msgs/msg/Image")
            # the manager sees the real publisher's token (asked on its topic: the whole graph's
            # listing is bounded, and the flood fills it)
            topic = publisher_pattern(26, "/camera/image_raw")
            wait_until(lambda: bool(robot.session.alive(topic, timeout_s=0.2)), "the real publisher up")
            robot.spawn("ros2-camera(flooded)", "camera")
            states = {u.name: u.state for u in robot.get_model().units}
            assert states["camera"] == "running", robot.get_model().to_dict()
            source = robot.unit("camera")
            assert isinstance(source, Ros2Source) and source.publishers == 1
        for token in fakes:
            token.undeclare()  # type: ignore[attr-defined]


def test_fake_tokens_on_the_topic_itself_cannot_make_a_source_fail_while_its_publisher_is_up(
    make_manager: Callable[..., Manager], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tokens of another type never count (their messages could not reach the source); tokens of
    its type over the watch's bound are left out but not forgotten: when the ones kept go, the
    source asks which are up and stays with the real publisher. (The bound here: 5.)"""
    monkeypatch.setattr(graph, "MAX_TOPIC_PUBLISHERS", 5)
    port = free_port()
    robot = make_manager(specs=[REQUIRING], listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=27)
    image = "sensor_msgs/msg/Image"
    image_hash = robot.ros2_node().types.type_hash(image)
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as attacker,
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
        Ros2Node(session, "camera_driver", domain=27) as driver,
    ):
        other_type = [_token(attacker, 27, "/camera/image_raw", i, "std_msgs/msg/String", HASH_NOT_SUPPORTED) for i in range(20)]
        same_type = [_token(attacker, 27, "/camera/image_raw", 100 + i, image, image_hash) for i in range(5)]
        wait_until(lambda: len(snapshot(robot.session, 27, timeout_s=0.2).publishers("/camera/image_raw")) == 25, "the fakes up")
        robot.spawn("ros2-camera(flooded)", "camera")  # the five fakes of its type fill its watch
        source = robot.unit("camera")
        assert isinstance(source, Ros2Source)
        wait_until(lambda: source.publishers == 5, "the fakes of its type kept, the others not counted")
        pub = driver.create_publisher("/camera/image_raw", image)  # left out: the watch is full
        wait_until(lambda: len(snapshot(robot.session, 27, timeout_s=0.2).publishers("/camera/image_raw")) == 26, "the real one up")
        for token in same_type + other_type:
            token.undeclare()  # type: ignore[attr-defined]
        wait_until(lambda: source.publishers == 1, "the real publisher found once the fakes went")
        assert {u.name: u.state for u in robot.get_model().units}["camera"] == "running"
        pub.close()  # the real one goes: now the source has none, and says so
        wait_until(lambda: {u.name: u.state for u in robot.get_model().units}.get("camera") != "running", "the source failed")
