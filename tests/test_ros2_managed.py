"""Managed ROS 2 nodes (dyknow.ros2.managed, dyknow.ros2.lifecycle): a real rclpy lifecycle node on
Fast DDS (tests/ros2_rclpy_peer.py), chosen by the planner as the provider of a request, brought up
through its lifecycle and parameter services, failed over from, and deactivated when left."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import pytest

from dyknow import Manager
from dyknow.errors import ClosedError, ServiceError
from dyknow.spec import TransformationSpec, parse_specs
from dyknow.spec.model import Param, Port, Tag
from dyknow.testing import Sink
from tests.conftest import free_port
from tests.test_adaptation import Events
from tests.test_ros2_dds import Rclpy
from tests.test_ros2_dds import domain as _domain
from tests.test_ros2_dds import rclpy_node as _rclpy_node
from tests.test_ros2_live import Peer

domain, rclpy_node = _domain, _rclpy_node  # the fixtures of the DDS tests

GET_STATE = "lifecycle_msgs/srv/GetState"
NODE = """<node name="/camera_top" middleware="dds" timeout-s="15">
  <label>camera-top</label>
  <params><param name="exposure" type="float">0.5</param></params>
  <topic type="std_msgs/msg/String">/camera_top/frames</topic>
  <tags><tag>Frames(top)</tag></tags>
  <priority>0</priority>
</node>"""


def node_spec(*extra: Param, node: str = "/camera_top", deadline_ms: float | None = None, timeout_s: float = 15.0) -> TransformationSpec:
    """The spec of the managed lifecycle node ``node`` publishing ``<node>/frames``, tagged Frames(top)."""
    params = (
        Param("node", "string", node),
        Param("binding", "string", f"ros2dds:{node}/frames?type=std_msgs/msg/String"),
        Param("timeout_s", "float", timeout_s),
        Param("wait_s", "float", 20.0),
        Param("poll_s", "float", 0.2),
        *extra,
    )
    return TransformationSpec(
        "camera-top", "dyknow.ros2.managed:ManagedNode", params, (Port("out", "out", deadline_ms),), (Tag("out", "Frames(top)"),), priority=0
    )


FALLBACK = TransformationSpec(
    "frames-fallback",
    "transformations.generic:PeriodicSource",
    (Param("rate_hz", "float", 50.0),),
    (Port("out", "out"),),
    (Tag("out", "Frames(top)"),),
    priority=10,
)
SINK = TransformationSpec("sink", "dyknow.testing:Sink", (), (Port("in", "in"),))


def state_of(domain: int, node: str = "/camera_top") -> str:
    """The node's state as another client sees it."""
    from dyknow.ros2.dds import DdsNode

    with DdsNode(domain=domain) as participant:
        return str(participant.create_client(f"{node}/get_state", GET_STATE).call({}, timeout_s=15).current_state.label)


def consume(manager: Manager, key: str) -> Sink:
    manager.spawn("sink", "sink", bindings={"in": key})
    sink = manager.unit("sink")
    assert isinstance(sink, Sink)
    return sink


def transitions(peer: Rclpy, count: int) -> list[dict[str, Any]]:
    return [peer.lines.get(timeout=20) for _ in range(count)]


@pytest.mark.process
def test_a_chosen_node_is_configured_activated_and_read_then_deactivated_when_left(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    camera = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    (spec,) = parse_specs(NODE)
    robot = make_manager(specs=[spec, FALLBACK, SINK], ros2_domain=domain)
    key = robot.request("Frames(top)")
    assert "camera-top" in {u.label for u in robot.get_model().units}
    assert transitions(camera, 2) == [{"transition": "configure", "exposure": 0.5}, {"transition": "activate"}]  # the parameter first
    assert state_of(domain) == "active"
    sink = consume(robot, key)
    message = sink.wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    assert message.payload.startswith("camera_top ")
    robot.release(key)
    assert camera.lines.get(timeout=20) == {"transition": "deactivate"}
    assert state_of(domain) == "inactive"  # deactivated, never cleaned up nor destroyed
    assert camera.proc.poll() is None


@pytest.mark.process
def test_a_node_that_fails_a_transition_is_failed_over_on_the_same_key(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    camera = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    robot = make_manager(specs=[node_spec(), FALLBACK, SINK], ros2_domain=domain, dwell_s=0.3)
    events = Events(robot)
    key = robot.request("Frames(top)")
    transitions(camera, 2)
    sink = consume(robot, key)
    sink.wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    camera.send("fail")  # its deactivation errs: ErrorProcessing, then unconfigured
    event = events.wait("adapted", timeout_s=30)
    assert "camera-top" in event.old and "frames-fallback" in event.new, event.to_dict()
    assert "/camera_top went from active to deactivating, not active (its transition_event)" in event.cause, event.cause
    sink.wait_until(lambda m: isinstance(m.payload, bytes), timeout_s=10)  # the fallback's, on the same key


@pytest.mark.process
def test_a_node_whose_topic_stalls_is_failed_over(make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]) -> None:
    camera = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    robot = make_manager(specs=[node_spec(deadline_ms=1000), FALLBACK, SINK], ros2_domain=domain, dwell_s=0.3)
    events = Events(robot)
    key = robot.request("Frames(top)")
    transitions(camera, 2)
    consume(robot, key).wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    camera.send("stall")
    event = events.wait("adapted", timeout_s=30)
    assert "camera-top" in event.old and "frames-fallback" in event.new, event.to_dict()
    assert camera.lines.get(timeout=20) == {"transition": "deactivate"}  # left: deactivated
    assert state_of(domain) == "inactive"


@pytest.mark.process
def test_a_parameter_of_the_wrong_type_fails_the_choice_and_another_provider_is_taken(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    robot = make_manager(specs=[node_spec(Param("ros.exposure", "string", "bright")), FALLBACK, SINK], ros2_domain=domain)
    info = robot.spawn("camera-top", "camera")
    assert info.state == "failed"
    assert "refused the parameter exposure='bright'" in str(info.error) and "type" in str(info.error).lower(), info.error
    assert state_of(domain) == "unconfigured"  # nothing done
    robot.destroy("camera", force=True)
    robot.request("Frames(top)")  # the node fails at start, and the request takes the next provider
    labels = {u.label for u in robot.get_model().units}
    assert "frames-fallback" in labels and "camera-top" not in labels, labels


@pytest.mark.process
def test_a_failover_onto_a_node_that_refuses_its_parameter_goes_on_to_the_next_provider(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    top = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    rclpy_node("lifecycle", "camera_side", "/camera_side/frames")
    side = replace(node_spec(Param("ros.exposure", "string", "bright"), node="/camera_side"), label="camera-side", priority=5)
    robot = make_manager(specs=[node_spec(), side, FALLBACK, SINK], ros2_domain=domain, dwell_s=0.3)
    events = Events(robot)
    robot.request("Frames(top)")
    transitions(top, 2)
    top.send("fail")
    event = events.wait("adapted", timeout_s=30)  # camera-side refused its parameter: that choice failed, was undone
    assert event.old == ("camera-top",) and event.new == ("frames-fallback",), event.to_dict()
    assert not [e for e in events.events if e.kind == "degraded"]
    assert "camera-side" not in {u.label for u in robot.get_model().units}  # nothing of it left running


def test_a_node_that_does_not_exist_fails_naming_it_and_the_time_waited(make_manager: Callable[..., Manager], domain: int) -> None:
    robot = make_manager(specs=[node_spec(node="/nobody", timeout_s=0.5)], ros2_domain=domain)
    started = time.monotonic()
    info = robot.spawn("camera-top", "camera")
    assert info.state == "failed"
    assert "ROS 2 node /nobody over DDS: /nobody/get_state: no answer in 0." in str(info.error), info.error
    assert "does not answer, or does not exist" in str(info.error)
    assert time.monotonic() - started < 10


@pytest.mark.process
def test_a_refused_transition_says_which_state_the_node_is_in(domain: int, rclpy_node: Callable[..., Rclpy]) -> None:
    from dyknow.ros2.dds import DdsNode
    from dyknow.ros2.lifecycle import ACTIVATE, NodeLifecycle

    rclpy_node("lifecycle", "camera_top")
    with DdsNode(domain=domain) as participant, NodeLifecycle(participant, "/camera_top", timeout_s=15) as node:
        assert node.state() == (1, "unconfigured")
        with pytest.raises(ServiceError, match=r"refused the transition 'activate'; it is unconfigured; expected configure before activate"):
            node.change(ACTIVATE)
        assert node.bring_up({"exposure": 0.25}) == ["set 1 parameter(s)", "configure", "activate"]
        assert node.bring_up() == []  # active already
        assert node.bring_down() is True
        assert node.state() == (2, "inactive")


# ---------------------------------------------------------------------------- over rmw_zenoh

ZENOH_NODE = """<node name="/camera_top" timeout-s="15">
  <label>camera-top</label>
  <params><param name="exposure" type="float">0.5</param></params>
  <topic type="std_msgs/msg/String">/camera_top/frames</topic>
  <tags><tag>Frames(top)</tag></tags>
  <priority>0</priority>
</node>"""


@pytest.fixture
def sdk_node(make_manager: Callable[..., Manager]) -> Iterator[tuple[Manager, Peer]]:
    """A manager, and a lifecycle node on rmw_zenoh (tests/ros2_peer.py: the SDK has no lifecycle
    node, so the peer answers lifecycle_msgs and rcl_interfaces services itself) connected to it."""
    port = free_port()
    (spec,) = parse_specs(ZENOH_NODE)
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=0, specs=[spec, FALLBACK, SINK], dwell_s=0.3)
    peer = Peer(str(port), "lifecycle", "camera_top", "/camera_top/frames")
    try:
        assert peer.line() == {"ready": True}
        yield robot, peer
    finally:
        peer.close()


@pytest.mark.process
def test_a_node_on_rmw_zenoh_is_brought_up_read_failed_over_and_deactivated(sdk_node: tuple[Manager, Peer]) -> None:
    robot, peer = sdk_node
    events = Events(robot)
    key = robot.request("Frames(top)")
    assert [peer.line(), peer.line()] == [{"transition": "configure", "exposure": 0.5}, {"transition": "activate"}]
    sink = consume(robot, key)
    sink.wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    assert peer.proc.stdin is not None
    peer.proc.stdin.write("fail\n")
    peer.proc.stdin.flush()
    event = events.wait("adapted", timeout_s=30)
    assert event.old == ("camera-top",) and event.new == ("frames-fallback",), event.to_dict()
    assert "/camera_top went from active to errorprocessing, not active (its transition_event)" in event.cause, event.cause
    sink.wait_until(lambda m: isinstance(m.payload, bytes), timeout_s=10)
    # the node is back (unconfigured) and preferred: after its back-off the loop returns to it
    back = events.wait("adapted", count=2, timeout_s=30)
    assert back.new == ("camera-top",), back.to_dict()
    assert [peer.line(), peer.line()] == [{"transition": "configure", "exposure": 0.5}, {"transition": "activate"}]
    robot.release(key)
    assert peer.line() == {"transition": "deactivate"}


@pytest.mark.process
def test_a_node_on_rmw_zenoh_that_vanishes_is_failed_over(sdk_node: tuple[Manager, Peer]) -> None:
    robot, peer = sdk_node
    events = Events(robot)
    key = robot.request("Frames(top)")
    consume(robot, key).wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    peer.proc.kill()  # gone from the graph at once: its tokens go with its session
    event = events.wait("adapted", timeout_s=30)
    assert event.old == ("camera-top",) and event.new == ("frames-fallback",), event.to_dict()
    assert "gone" in event.cause or "vanished" in event.cause, event.cause


def diagnostics(*statuses: tuple[str, int]) -> dict[str, Any]:
    """A diagnostic_msgs/msg/DiagnosticArray's fields: (name, level) per status."""
    return {"status": [{"level": level, "name": name, "message": f"level {level}", "hardware_id": "cam"} for name, level in statuses]}


@pytest.mark.process
def test_an_error_of_the_node_on_diagnostics_is_failed_over(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    """The /diagnostics are published by the test through dyknow's DDS publisher (an rclpy
    publisher of them: tests/test_ros2_diagnostics.py): another node's ERROR and this node's OK
    change nothing; this node's ERROR fails it over."""
    from dyknow.ros2.convert import to_message
    from dyknow.ros2.dds import DdsNode

    camera = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    robot = make_manager(specs=[node_spec(), FALLBACK, SINK], ros2_domain=domain, dwell_s=0.3)
    events = Events(robot)
    key = robot.request("Frames(top)")
    transitions(camera, 2)
    consume(robot, key).wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    with DdsNode(domain=domain) as participant:
        publisher = participant.create_publisher("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
        fine = to_message(diagnostics(("camera_side: frames", 2), ("camera_top: frames", 0)), publisher.ros_type, participant.types, origin_ns=0)
        error = to_message(diagnostics(("camera_top: frames", 2)), publisher.ros_type, participant.types, origin_ns=0)
        deadline = time.monotonic() + 30
        while not events.events and time.monotonic() < deadline:  # until its reader matched ours
            publisher.publish(fine)
            publisher.publish(error)
            time.sleep(0.1)
    event = events.wait("adapted", timeout_s=1)
    assert event.old == ("camera-top",) and event.new == ("frames-fallback",), event.to_dict()
    assert "/diagnostics: camera_top: frames is ERROR: level 2" in event.cause, event.cause


def test_a_diagnostic_status_is_a_nodes_when_it_is_named_after_it() -> None:
    from dyknow.ros2.managed import is_status_of

    assert is_status_of("camera_top: Frame rate", "/camera_top")
    assert is_status_of("/robot/camera_top: Frame rate", "/robot/camera_top")
    assert is_status_of("camera_top", "/robot/camera_top")
    assert not is_status_of("camera_side: Frame rate", "/camera_top")
    assert not is_status_of("camera_top_2: Frame rate", "/camera_top")


@pytest.mark.process
def test_node_lifecycle_over_rmw_zenoh_says_what_was_refused_and_what_was_set(sdk_node: tuple[Manager, Peer]) -> None:
    from dyknow.ros2.lifecycle import ACTIVATE, CLEANUP, CONFIGURE, NodeLifecycle

    robot, peer = sdk_node
    with NodeLifecycle(robot.ros2_node(), "/camera_top", timeout_s=15) as node:
        refused = r"refused the parameter gain=2: parameter 'gain' is not declared; expected .* \(these were set: exposure\)"
        with pytest.raises(ServiceError, match=refused):
            node.set_parameters({"exposure": 0.3, "gain": 2})
        with pytest.raises(ServiceError, match=r"refused the transition 'activate'; it is unconfigured; expected configure before activate"):
            node.change(ACTIVATE)
        assert node.bring_up() == ["configure", "activate"]
        assert [peer.line(), peer.line()] == [{"transition": "configure", "exposure": 0.3}, {"transition": "activate"}]
        assert node.bring_down() is True and node.state() == (2, "inactive")
        assert peer.line() == {"transition": "deactivate"}
    with NodeLifecycle(robot.ros2_node(), "/camera_top", lifecycle=False, timeout_s=15) as plain:  # parameters only
        assert plain.bring_up({"exposure": 0.7}) == ["set 1 parameter(s)"]
        assert plain.bring_down() is False  # nothing to deactivate: not a lifecycle node
    with NodeLifecycle(robot.ros2_node(), "/camera_top", timeout_s=15) as node:
        node.change(CLEANUP)
        node.change(CONFIGURE)
        assert [peer.line(), peer.line()] == [{"transition": "cleanup"}, {"transition": "configure", "exposure": 0.7}]
    with pytest.raises(ClosedError, match="the lifecycle client is closed"):
        node.state()


@pytest.mark.process
def test_two_nodes_specs_of_one_node_share_it_and_the_last_to_leave_deactivates_it(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    camera = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    frames = node_spec()
    texts = replace(frames, label="camera-top-text", tags=(Tag("out", "Text(top)"),))
    robot = make_manager(specs=[frames, texts], ros2_domain=domain)
    first = robot.request("Frames(top)")
    second = robot.request("Text(top)")
    assert transitions(camera, 2) == [{"transition": "configure", "exposure": 0.1}, {"transition": "activate"}]  # once
    robot.release(first)
    assert state_of(domain) == "active"  # the other still reads it
    robot.release(second)
    assert camera.lines.get(timeout=20) == {"transition": "deactivate"}
    assert state_of(domain) == "inactive"


@pytest.mark.process
def test_a_node_that_leaves_the_active_state_unannounced_is_found_by_its_state(sdk_node: tuple[Manager, Peer]) -> None:
    """No transition_event (as if it were lost): the unit's GetState polls find the node unconfigured."""
    robot, peer = sdk_node
    events = Events(robot)
    key = robot.request("Frames(top)")
    consume(robot, key).wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    assert peer.proc.stdin is not None
    peer.proc.stdin.write("quiet-fail\n")
    peer.proc.stdin.flush()
    event = events.wait("adapted", timeout_s=30)
    assert event.new == ("frames-fallback",) and "/camera_top is unconfigured, not active" in event.cause, event.to_dict()


@pytest.mark.process
def test_a_node_that_refuses_activation_is_cleaned_up_and_the_next_provider_taken(sdk_node: tuple[Manager, Peer]) -> None:
    from dyknow.ros2.lifecycle import NodeLifecycle

    robot, peer = sdk_node
    assert peer.proc.stdin is not None
    peer.proc.stdin.write("refuse-activate\n")
    peer.proc.stdin.flush()
    assert peer.line() == {"command": "refuse-activate"}
    robot.request("Frames(top)")  # the node fails at start; the request takes the next provider
    labels = {u.label for u in robot.get_model().units}
    assert "frames-fallback" in labels and "camera-top" not in labels, labels
    assert [peer.line(), peer.line()] == [{"transition": "configure", "exposure": 0.5}, {"transition": "cleanup"}]  # undone
    with NodeLifecycle(robot.ros2_node(), "/camera_top", timeout_s=15) as node:
        assert node.state() == (1, "unconfigured")
        undone = r"refused the transition 'activate'; it is inactive; the configure before it was undone \(cleaned up: unconfigured again\); expected a node whose activation succeeds"
        with pytest.raises(ServiceError, match=undone):
            node.bring_up()


@pytest.mark.process
def test_a_node_on_dds_that_vanishes_is_failed_over_when_its_get_state_goes_unanswered(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    """Killed, a Fast DDS node leaves no trace until its lease ends (20 s): the unit's GetState
    poll, unanswered for its timeout (5 s here), fails it first."""
    camera = rclpy_node("lifecycle", "camera_top", "/camera_top/frames")
    robot = make_manager(specs=[node_spec(timeout_s=5.0), FALLBACK, SINK], ros2_domain=domain, dwell_s=0.3)
    events = Events(robot)
    key = robot.request("Frames(top)")
    consume(robot, key).wait_until(lambda m: str(m.payload).startswith("camera_top "), timeout_s=20)
    camera.proc.kill()
    event = events.wait("adapted", timeout_s=30)
    assert event.old == ("camera-top",) and event.new == ("frames-fallback",), event.to_dict()
    assert "/camera_top vanished: " in event.cause and "/camera_top/get_state: no answer in" in event.cause, event.cause
