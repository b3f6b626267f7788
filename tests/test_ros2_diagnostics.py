"""ROS 2's /diagnostics both ways (dyknow.ros2.diagnostics, dyknow.manager.health): the manager's
health received by a real rclpy subscriber on Fast DDS and by zenoh-ros2-sdk on rmw_zenoh, level
changes included (a requirement false, a request degraded, a managed node failed); another node's
statuses, published by a real rclpy node, read as a tagged stream a formula reads; hostile
statuses refused. ROS 2's own diagnostic_msgs (the ros-diagnostic-msgs wheel) is the CDR oracle.
"""

from __future__ import annotations

import json
import queue
import signal
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from dyknow import Manager
from dyknow.errors import BindingError
from dyknow.ros2.diagnostics import (
    DIAGNOSTIC_ARRAY,
    ERROR,
    MAX_MESSAGE_CHARS,
    MAX_VALUES,
    OK,
    STALE,
    WARN,
    DiagnosticStatus,
    read_status,
    read_value,
)
from dyknow.ros2.types import TypeSupport
from dyknow.spec import TransformationSpec, parse_specs
from dyknow.spec.model import Param, Port, Tag
from dyknow.testing import Sink
from tests.conftest import REPO, free_port, subprocess_env
from tests.test_ros2_dds import Rclpy
from tests.test_ros2_dds import domain as _domain
from tests.test_ros2_dds import rclpy_node as _rclpy_node
from tests.test_ros2_live import Peer
from tests.test_ros2_managed import FALLBACK, SINK, ZENOH_NODE, node_spec, transitions
from tests.units import Reading

domain, rclpy_node = _domain, _rclpy_node  # the fixtures of the DDS tests

FORMULA = "Level(tank).id == 2"
DEVICE = TransformationSpec("tank-device", "tests.units:Reading", (Param("id", "int", 2), Param("rate_hz", "float", 20.0)), (Port("out", "out"),))
LEVEL = TransformationSpec(
    "tank-level",
    "transformations.generic:RemoteStream",
    (Param("key", "string", "tank/level"), Param("grace_s", "float", 5.0)),
    (Port("in", "in"), Port("out", "out")),
    (Tag("out", "Level(tank)"),),
)


def health(status: str, *, middleware: str = "ros2dds") -> TransformationSpec:
    """A DiagnosticsSource of the statuses ``status`` names, tagged Health(thruster_1)."""
    return TransformationSpec(
        "thruster-health",
        "dyknow.ros2.diagnostics:DiagnosticsSource",
        (Param("binding", "string", f"{middleware}:/diagnostics"), Param("status", "string", status)),
        (Port("out", "out"),),
        (Tag("out", "Health(thruster_1)"),),
    )


# -- the message, against ROS 2's own


def test_a_status_array_is_the_cdr_rclpy_reads() -> None:
    from dyknow.ros2.convert import to_message

    types = TypeSupport()
    status = DiagnosticStatus("dyknow_robot: requirement always x > 1", ERROR, "false at t=1.5", "robot/req/X", (("formula", "always x > 1"), ("verdict", "false")))
    message = to_message({"status": [status.to_fields()]}, DIAGNOSTIC_ARRAY, types, origin_ns=1_500_000_007)
    with warnings.catch_warnings():  # ROS 2's parser (lark 0.12) imports the deprecated sre_parse with the type support
        warnings.simplefilter("ignore", DeprecationWarning)
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.serialization import deserialize_message, serialize_message

        ros = deserialize_message(types.serialize(message, DIAGNOSTIC_ARRAY), DiagnosticArray)
        theirs = serialize_message(ros)
    (got,) = ros.status
    assert (got.name, got.level, got.message, got.hardware_id) == (status.name, bytes([ERROR]), status.message, status.hardware_id)
    assert [(kv.key, kv.value) for kv in got.values] == list(status.values)
    assert (ros.header.stamp.sec, ros.header.stamp.nanosec) == (1, 500_000_007)
    assert read_status(types.deserialize(theirs, DIAGNOSTIC_ARRAY).status[0]) == status  # and rclpy's bytes read back


@pytest.mark.parametrize(
    ("text", "value"),
    [("12", 12), ("-3", -3), ("0.5", 0.5), ("1e3", 1000.0), (".5", 0.5), ("true", True), ("False", False), ("TRUE", True),
     ("nan", "nan"), ("inf", "inf"), ("1_000", "1_000"), ("12 rpm", "12 rpm"), ("", ""), ("0x10", "0x10")],
)  # fmt: skip
def test_values_read_as_numbers_and_booleans_where_they_read_so(text: str, value: object) -> None:
    got = read_value(text)
    assert got == value and type(got) is type(value)


def test_statuses_over_the_bounds_are_refused_naming_the_field() -> None:
    types = TypeSupport()
    status_cls, kv = types.message_class("diagnostic_msgs/msg/DiagnosticStatus"), types.message_class("diagnostic_msgs/msg/KeyValue")

    def status(name: str = "thrusters: t1", message: str = "", values: int = 0, value: str = "1") -> Any:
        return status_cls(level=bytes([1]), name=name, message=message, hardware_id="", values=[kv(key=f"k{i}", value=value) for i in range(values)])

    with pytest.raises(BindingError, match=r"its message is 4001 characters long.*at most 4000"):
        read_status(status(message="x" * (MAX_MESSAGE_CHARS + 1)))
    with pytest.raises(BindingError, match=r"has 101 values.*at most 100"):
        read_status(status(values=MAX_VALUES + 1))
    with pytest.raises(BindingError, match=r"its name is"):
        read_status(status(name="n" * 5000))
    with pytest.raises(BindingError, match=r"its value 'k0' is"):
        read_status(status(values=1, value="v" * 5000))
    assert read_status(status(values=MAX_VALUES)).level == WARN


def test_the_manager_refuses_an_unknown_diagnostics_middleware(make_manager: Callable[..., Manager]) -> None:
    with pytest.raises(BindingError, match="diagnostics='dds'.*'ros2'.*'ros2dds'"):
        make_manager(diagnostics="dds")


# -- the manager's health, published


class Listener:
    """The arrays a ROS 2 subscriber printed, by status name."""

    def __init__(self, lines: Callable[[float], dict[str, Any]]) -> None:
        self._lines = lines

    def wait(self, name: str, level: int, timeout_s: float = 30.0, message: str = "") -> dict[str, Any]:
        """The first status named ``name`` (a prefix) at ``level`` whose message holds ``message``."""
        deadline = time.monotonic() + timeout_s
        seen: dict[str, Any] = {}
        while time.monotonic() < deadline:
            try:
                line = self._lines(max(0.01, deadline - time.monotonic()))
            except (queue.Empty, AssertionError):
                break
            for status in line.get("statuses", ()):
                if status["name"].startswith(name):
                    seen = status
                    if status["level"] == level and message in status["message"]:
                        return status
        raise AssertionError(f"no status {name!r} at level {level} within {timeout_s} s; last seen: {json.dumps(seen)[:2000]}")


def _tank(manager: Manager) -> Reading:
    manager.spawn("tank-device", "device", bindings={"out": "tank/level"})
    unit = manager.unit("device")
    assert isinstance(unit, Reading)
    return unit


@pytest.mark.process
def test_the_managers_health_reaches_rclpy_over_dds_and_its_levels_follow(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    listener = rclpy_node("diagnostics-listen")
    camera = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    robot = make_manager("robot-1", specs=[DEVICE, LEVEL, node_spec(), FALLBACK, SINK], ros2_domain=domain, dwell_s=0.3, diagnostics="ros2dds")
    statuses = Listener(lambda timeout: listener.lines.get(timeout=timeout))
    device = _tank(robot)
    tank = robot.request("Level(tank)", require=[FORMULA])
    frames = robot.request("Frames(top)")
    transitions(camera, 2)
    # named after the manager's ROS 2 node, as diagnostic_updater names them
    requirement = statuses.wait(f"robot_1: requirement {FORMULA}", OK)
    assert requirement["hardware_id"] == tank and requirement["values"]["formula"] == FORMULA
    assert requirement["values"]["verdict"] == "true" and "t" in requirement["values"] and requirement["values"]["request"] == tank
    assert statuses.wait("robot_1: request Level(tank)", OK)["values"]["state"] == "active"
    node = statuses.wait("robot_1: node /camera_top", OK, message="active")
    assert node["hardware_id"] == "/camera_top"
    # the requirement goes false: nothing else provides the tag, so the request degrades in place
    device.id = 1
    false = statuses.wait(f"robot_1: requirement {FORMULA}", ERROR)
    assert false["values"]["verdict"] == "false" and false["message"].startswith("false at t=")
    assert "degraded" in statuses.wait("robot_1: request Level(tank)", WARN)["message"]
    # the managed node fails: ERROR, kept while the fallback serves its request
    camera.send("fail")
    failed = statuses.wait("robot_1: node /camera_top", ERROR)
    # (the transition seen, or, when the manager's look at the node's state comes first on a loaded machine, its state)
    assert "/camera_top went from active to" in failed["message"] or "/camera_top is unconfigured, not active" in failed["message"], failed
    assert statuses.wait("robot_1: request Frames(top)", OK)["values"]["transformations"] == "frames-fallback"
    # repaired: the requirement holds again
    device.id = 2
    statuses.wait(f"robot_1: requirement {FORMULA}", OK)
    robot.release(frames)


@pytest.mark.process
def test_the_managers_health_reaches_an_rmw_zenoh_subscriber_and_its_levels_follow(make_manager: Callable[..., Manager]) -> None:
    """The same over rmw_zenoh: zenoh-ros2-sdk subscribes, the managed node is the SDK peer's lifecycle node."""
    port = free_port()
    (camera_spec,) = parse_specs(ZENOH_NODE)
    robot = make_manager(
        "robot", listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=0, specs=[DEVICE, LEVEL, camera_spec, FALLBACK], dwell_s=0.3, diagnostics="ros2"
    )
    listener = Peer(str(port), "listen", "/diagnostics", DIAGNOSTIC_ARRAY)
    camera = Peer(str(port), "lifecycle", "camera_top", "/camera_top/frames")
    try:
        assert listener.line() == {"ready": True} and camera.line() == {"ready": True}
        statuses = Listener(listener.line)
        device = _tank(robot)
        robot.request("Level(tank)", require=[FORMULA])
        robot.request("Frames(top)")
        assert [camera.line(), camera.line()] == [{"transition": "configure", "exposure": 0.5}, {"transition": "activate"}]
        statuses.wait(f"robot: requirement {FORMULA}", OK)
        statuses.wait("robot: node /camera_top", OK, message="active")
        device.id = 1
        statuses.wait(f"robot: requirement {FORMULA}", ERROR)
        statuses.wait("robot: request Level(tank)", WARN)
        assert camera.proc.stdin is not None
        camera.proc.stdin.write("fail\n")
        camera.proc.stdin.flush()
        assert "/camera_top went from active to errorprocessing" in statuses.wait("robot: node /camera_top", ERROR)["message"]
    finally:
        camera.close()
        listener.close()


def test_a_status_source_plugs_in_and_a_failing_one_is_left_out(make_manager: Callable[..., Manager]) -> None:
    robot = make_manager("robot")
    mode = DiagnosticStatus(f"{robot.ros2_node_name}: mode", OK, "normal")
    remove = robot.add_status_source(lambda: [mode])
    robot.add_status_source(lambda: 1 / 0)  # type: ignore[arg-type,return-value]
    assert robot.diagnostic_statuses() == [mode]
    remove()
    assert robot.diagnostic_statuses() == []
    twice = robot.add_status_source(lambda: [DiagnosticStatus("robot: thruster", OK, "", "t1"), DiagnosticStatus("robot: thruster", ERROR, "", "t2")])
    assert [s.name for s in robot.diagnostic_statuses()] == ["robot: thruster (t1)", "robot: thruster (t2)"]  # told apart
    twice()
    robot.monitor("Level(tank).id == 2", bindings={"Level(tank)": "tank/nothing"})
    (status,) = robot.diagnostic_statuses()
    assert (status.name, status.level, status.message) == ("robot: monitor Level(tank).id == 2", STALE, "no verdict yet")


# -- other nodes' statuses, read


@pytest.fixture
def talker(rclpy_node: Callable[..., Rclpy]) -> Iterator[Callable[[str], None]]:
    """A real rclpy node publishing /diagnostics: call it with the statuses to publish from now on (a JSON list)."""
    node = rclpy_node("diagnostics-talk")
    yield node.send  # (the rclpy_node fixture stops it)


def _status(name: str, level: int, **values: str) -> dict[str, Any]:
    return {"name": name, "level": level, "message": f"level {level}", "hardware_id": name.split(": ")[-1], "values": values}


@pytest.mark.process
def test_other_nodes_statuses_are_a_tagged_stream_formulas_read(
    make_manager: Callable[..., Manager], domain: int, talker: Callable[[str], None]
) -> None:
    robot = make_manager(specs=[health("thrusters: thruster_1"), SINK], ros2_domain=domain)
    key = robot.request("Health(thruster_1)")
    robot.spawn("sink", "health", bindings={"in": key})
    sink = robot.unit("health")
    assert isinstance(sink, Sink)
    verdicts = robot.monitor("Health(thruster_1).level < 2 and Health(thruster_1).values.rpm > 100")
    robot.spawn("sink", "verdicts", bindings={"in": verdicts})
    judged = robot.unit("verdicts")
    assert isinstance(judged, Sink)
    hostile = {"name": "thrusters: thruster_1", "level": 0, "message": "x" * (MAX_MESSAGE_CHARS + 1)}
    fine = [_status("thrusters: thruster_1", 0, rpm="1200", enabled="True", mode="auto"), _status("thrusters: thruster_2", 2), hostile]
    talker(json.dumps(fine))
    message = sink.wait_until(lambda m: m.payload["name"] == "thrusters: thruster_1", timeout_s=30)
    assert message.payload == {
        "name": "thrusters: thruster_1",
        "level": 0,
        "level_name": "OK",
        "message": "level 0",
        "hardware_id": "thruster_1",
        "values": {"rpm": 1200, "enabled": True, "mode": "auto"},
    }
    judged.wait_until(lambda m: m.payload.get("verdict") is True, timeout_s=30)
    talker(json.dumps([_status("thrusters: thruster_1", 2, rpm="0")]))
    judged.wait_until(lambda m: m.payload.get("verdict") is False, timeout_s=30)
    assert all(m.payload["name"] == "thrusters: thruster_1" for m in sink.messages)  # the other statuses are not this one
    source = robot.unit(next(u.name for u in robot.units() if u.label == "thruster-health"))
    assert source.refused >= 1 and "its message is 4001 characters long" in str(source.last_refusal)  # type: ignore[attr-defined]


def test_a_diagnostics_source_of_another_type_is_refused_at_start(make_manager: Callable[..., Manager]) -> None:
    spec = health("*", middleware="ros2dds")
    spec = TransformationSpec(spec.label, spec.source, (Param("binding", "string", "ros2dds:/diagnostics?type=std_msgs/msg/String"),), spec.ports, spec.tags)
    robot = make_manager(specs=[spec])
    info = robot.spawn("thruster-health", "health")
    assert info.state == "failed" and "names the type std_msgs/msg/String" in str(info.error), info


@pytest.mark.process
def test_dyknow_manager_diagnostics_publishes_on_dds(domain: int, rclpy_node: Callable[..., Rclpy]) -> None:
    """``dyknow manager --diagnostics ros2dds``: its arrays reach rclpy (empty: nothing to say yet)."""
    listener = rclpy_node("diagnostics-listen")
    argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", "diag-cli", "--alone", "--listen", f"tcp/127.0.0.1:{free_port()}",
            "--diagnostics", "ros2dds", "--ros2-domain", str(domain)]  # fmt: skip
    manager = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=REPO)
    try:
        assert listener.lines.get(timeout=30) == {"statuses": []}
    finally:
        manager.send_signal(signal.SIGINT)
        try:
            manager.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            manager.kill()
            manager.communicate()
    assert manager.returncode == 0
