"""A dyknow manager and an rmw_zenoh implementation it did not write, live on loopback.

The counterparty is zenoh-ros2-sdk (tests/ros2_peer.py, a child process connected to the
manager's endpoint as rmw_zenoh's sessions connect to their router; multicast scouting is off on
both sides). Both directions, ``std_msgs/String`` and ``sensor_msgs/Image``, and discovery: the
SDK's ``ros2 topic info`` reads dyknow's tokens, and dyknow's graph reads the SDK's. Messages
dyknow cannot use are counted and refused, and the unit carries on.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dyknow import Manager
from dyknow.ros2 import Attachment, Ros2Source, data_key, snapshot
from dyknow.ros2.types import TypeSupport
from tests.conftest import REPO, free_port, subprocess_env, wait_until

PEER = Path(__file__).with_name("ros2_peer.py")


class Peer:
    """The SDK in a child process; JSON lines out, stopped by closing its stdin."""

    def __init__(self, *args: str) -> None:
        env = subprocess_env()
        env["GIT_ALLOW_PROTOCOL"] = "file"  # the SDK must never fetch a definition from the network
        env["GIT_TERMINAL_PROMPT"] = "0"
        self.proc = subprocess.Popen(
            [sys.executable, str(PEER), *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=REPO,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.lines.put(json.loads(line))

    def line(self, timeout_s: float = 20.0) -> dict[str, Any]:
        try:
            return self.lines.get(timeout=timeout_s)
        except queue.Empty:
            self.proc.kill()
            stderr = self.proc.stderr.read() if self.proc.stderr else ""
            self.close()
            raise AssertionError(f"no line from the SDK within {timeout_s} s; stderr: {stderr[-2000:]}") from None

    def close(self) -> None:
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture
def ros_manager(make_manager: Callable[..., Manager]) -> tuple[Manager, int]:
    port = free_port()
    return make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=0, ros2_node="dyknow_robot"), port


@pytest.fixture
def peers() -> Iterator[Callable[..., Peer]]:
    started: list[Peer] = []

    def start(*args: str) -> Peer:
        peer = Peer(*args)
        started.append(peer)
        return peer

    yield start
    for peer in started:
        peer.close()


@pytest.mark.process
def test_a_unit_reads_strings_from_the_sdk_learning_the_type(ros_manager: tuple[Manager, int], peers: Callable[..., Peer]) -> None:
    manager, port = ros_manager
    manager.spawn("sink", "listener", bindings={"in": "ros2:/chatter"})
    peer = peers(str(port), "talk", "/chatter", "std_msgs/msg/String")
    assert peer.line() == {"ready": True}
    sink = manager.unit("listener")
    msgs = sink.wait_for(3, timeout_s=20)  # type: ignore[attr-defined]
    assert all(isinstance(m.payload, str) and m.payload.startswith("hello ") for m in msgs)
    # no header stamp in a String: the origin is the SDK's source timestamp, a moment ago
    assert 0 <= time.time_ns() - msgs[0].origin_ns < 20e9
    companion = manager.unit("listener.in.ros2")
    assert isinstance(companion, Ros2Source) and companion.refused == 0 and companion.transport_refused == 0


@pytest.mark.process
def test_a_unit_reads_images_from_the_sdk_as_bgr_frames(ros_manager: tuple[Manager, int], peers: Callable[..., Peer]) -> None:
    manager, port = ros_manager
    manager.spawn("sink", "viewer", bindings={"in": "ros2:/camera/image_raw?type=sensor_msgs/msg/Image"})
    peer = peers(str(port), "talk", "/camera/image_raw", "sensor_msgs/msg/Image")
    assert peer.line() == {"ready": True}
    msg = manager.unit("viewer").wait_for(1, timeout_s=20)[0]  # type: ignore[attr-defined]
    rgb = np.arange(18, dtype=np.uint8).reshape(2, 3, 3)
    assert np.array_equal(msg.payload, rgb[:, :, ::-1])  # rgb8 in, BGR out, as the vision units take frames
    assert msg.origin_ns % 1_000_000_000 == 5  # the origin is the image's header stamp (sec=i, nanosec=5)


@pytest.mark.process
def test_the_sdk_reads_strings_dyknow_publishes(ros_manager: tuple[Manager, int], peers: Callable[..., Peer]) -> None:
    manager, port = ros_manager
    manager.spawn("publisher", "talker", bindings={"out": "ros2:/dyknow_chatter?type=std_msgs/msg/String"})
    peer = peers(str(port), "listen", "/dyknow_chatter", "std_msgs/msg/String")
    assert peer.line() == {"ready": True}
    source = manager.unit("talker")
    deadline = time.monotonic() + 20
    while True:
        source.emit("from dyknow")  # type: ignore[attr-defined]
        try:
            assert peer.lines.get(timeout=0.1) == {"data": "from dyknow"}
            break
        except queue.Empty:
            assert time.monotonic() < deadline, "the SDK received nothing in 20 s"


@pytest.mark.process
def test_the_sdk_reads_images_dyknow_publishes(ros_manager: tuple[Manager, int], peers: Callable[..., Peer]) -> None:
    manager, port = ros_manager
    manager.spawn("publisher", "camera", bindings={"out": "ros2:/dyknow_image?type=sensor_msgs/msg/Image"})
    peer = peers(str(port), "listen", "/dyknow_image", "sensor_msgs/msg/Image")
    assert peer.line() == {"ready": True}
    frame = np.arange(24, dtype=np.uint8).reshape(2, 4, 3)
    deadline = time.monotonic() + 20
    while True:
        manager.unit("camera").emit(frame, origin_ns=1_700_000_000_250_000_000)  # type: ignore[attr-defined]
        try:
            got = peer.lines.get(timeout=0.1)
            break
        except queue.Empty:
            assert time.monotonic() < deadline, "the SDK received nothing in 20 s"
    assert got == {"encoding": "bgr8", "height": 2, "width": 4, "step": 12, "data": list(range(24)), "stamp": [1_700_000_000, 250_000_000]}


@pytest.mark.process
def test_the_sdk_discovers_dyknows_node_and_publisher(ros_manager: tuple[Manager, int], peers: Callable[..., Peer]) -> None:
    manager, port = ros_manager
    manager.spawn("publisher", "talker", bindings={"out": "ros2:/dyknow_chatter?type=std_msgs/msg/String&depth=5"})
    found = peers(str(port), "info", "/dyknow_chatter").line()
    assert ["/dyknow_chatter", ["std_msgs/msg/String"]] in found["topics"]
    types = TypeSupport()
    assert found["publishers"] == [
        {
            "node": "dyknow_robot",
            "namespace": "/",
            "type": "std_msgs/msg/String",
            "hash": types.type_hash("std_msgs/msg/String"),
            "qos": "::,5:,:,:,,",
        }
    ]


@pytest.mark.process
def test_dyknows_graph_shows_the_sdks_publisher(ros_manager: tuple[Manager, int], peers: Callable[..., Peer]) -> None:
    manager, port = ros_manager
    peer = peers(str(port), "talk", "/chatter", "std_msgs/msg/String")
    assert peer.line() == {"ready": True}
    wait_until(lambda: bool(snapshot(manager.session, 0, timeout_s=0.2).publishers("/chatter")), "the SDK's publisher in the graph")
    view = snapshot(manager.session, 0)
    assert view.topics()["/chatter"] == ["std_msgs/msg/String"]
    assert [e.node for e in view.publishers("/chatter")] == ["/sdk_talker"]
    assert "/dyknow_robot" in view.nodes()


def test_undecodable_messages_are_counted_and_refused(ros_manager: tuple[Manager, int]) -> None:
    manager, _port = ros_manager
    manager.spawn("sink", "listener", bindings={"in": "ros2:/chatter?type=std_msgs/msg/String"})
    companion = manager.unit("listener.in.ros2")
    assert isinstance(companion, Ros2Source)
    types = TypeSupport()
    key = data_key(0, "/chatter", "std_msgs/msg/String", types.type_hash("std_msgs/msg/String"))
    good = types.serialize(types.message_class("std_msgs/msg/String")(data="fine"), "std_msgs/msg/String")
    attachment = Attachment(1, time.time_ns(), bytes(16)).encode()
    pub = manager.session.declare_plain_publisher(key)
    try:
        pub.put(good[:-3], attachment)  # truncated CDR
        pub.put(good, b"\x01\x02")  # a malformed attachment
        pub.put(good)  # no attachment at all
        pub.put(b"\x00\x01\x00\x00\xff\xff\xff\x7f", attachment)  # a string said to be 2 GB long
        wait_until(lambda: companion.transport_refused == 4, "four refusals")
        pub.put(good, attachment)
        msg = manager.unit("listener").wait_for(1)[0]  # type: ignore[attr-defined]
    finally:
        pub.undeclare()
    assert msg.payload == "fine"
    assert manager.get_model().units[0].state == "running"


@pytest.mark.process
def test_a_late_sdk_subscriber_gets_a_transient_local_message(ros_manager: tuple[Manager, int], peers: Callable[..., Peer]) -> None:
    manager, port = ros_manager
    manager.spawn("publisher", "latched", bindings={"out": "ros2:/map?type=std_msgs/msg/String&durability=transient_local&depth=1"})
    manager.unit("latched").emit("the map")  # type: ignore[attr-defined]
    peer = peers(str(port), "listen", "/map", "std_msgs/msg/String", "transient_local")  # starts after the message went out
    lines = [peer.line(), peer.line()]  # the SDK asks for history while it starts: the message may come first
    assert {"ready": True} in lines and {"data": "the map"} in lines
