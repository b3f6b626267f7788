"""System modes (dyknow.ros2.modes): real rclpy lifecycle nodes on Fast DDS (tests/ros2_rclpy_peer.py)
switched between the modes of a system as the planner chooses them from constraints on a measure,
with hysteresis, a switch that fails half-way rolled back, and a node that fails leaving its mode."""

from __future__ import annotations

import random
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from dyknow import Manager
from dyknow.errors import BindingError
from dyknow.ros2.dds import DdsNode
from dyknow.ros2.lifecycle import NodeLifecycle
from dyknow.ros2.modes import SwitchError, switch
from dyknow.spec import TransformationSpec, parse_specs
from dyknow.spec.modefile import Target
from dyknow.spec.model import Port
from dyknow.testing import Source
from tests.conftest import CliProcess, run_cli
from tests.test_adaptation import Events
from tests.test_ros2_dds import Rclpy
from tests.test_ros2_dds import domain as _domain
from tests.test_ros2_dds import rclpy_node as _rclpy_node
from tests.test_ui import browser as _browser
from tests.test_ui import chromium as _chromium
from tests.test_ui import drawn_text, wait_text

domain, rclpy_node, browser, chromium = _domain, _rclpy_node, _browser, _chromium  # the fixtures of the DDS and browser tests

# Two lifecycle nodes (each with a double parameter "exposure", 0.1 at start): the high mode runs the
# search alone at exposure 3, the low one the search at exposure 1 and the follower beside it.
SEARCH = """<system name="search" middleware="dds" timeout-s="15">
  <label>search</label>
  <tags><tag>Mode(search)</tag></tags>
  <mode name="high">
    <priority>1</priority>
    <constraints><constraint measure="visibility" op="&gt;=" value="0.7" margin="0.05"/></constraints>
    <part node="/searcher" state="active"><params><param name="exposure" type="float">3.0</param></params></part>
    <part node="/follower" state="inactive"/>
  </mode>
  <mode name="low">
    <priority>2</priority>
    <part node="/searcher" state="active"><params><param name="exposure" type="float">1.0</param></params></part>
    <part node="/follower" state="active"/>
  </mode>
</system>"""


class Observer:
    """Another client of the nodes (one DDS participant for the whole test): their states and parameters."""

    def __init__(self, domain: int) -> None:
        self.participant = DdsNode(domain=domain)
        self.lifecycles: dict[str, NodeLifecycle] = {}

    def _of(self, node: str) -> NodeLifecycle:
        if node not in self.lifecycles:
            self.lifecycles[node] = NodeLifecycle(self.participant, node, timeout_s=15)
        return self.lifecycles[node]

    def state(self, node: str) -> str:
        return self._of(node).state()[1]

    def exposure(self, node: str) -> object:
        return self._of(node).get_parameters(["exposure"])["exposure"]

    def close(self) -> None:
        for lifecycle in self.lifecycles.values():
            lifecycle.close()
        self.participant.close()


@pytest.fixture
def observer(domain: int) -> Iterator[Observer]:
    seen = Observer(domain)
    yield seen
    seen.close()


def wait_for(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "not within the time"
        time.sleep(0.05)


def in_high_mode(make_manager: Callable[..., Manager], domain: int) -> tuple[Manager, Events]:
    """A manager of SEARCH whose request for Mode(search) took the high mode (visibility 0.9), and its events."""
    robot = make_manager(specs=parse_specs(SEARCH), ros2_domain=domain, dwell_s=0.2)
    events = Events(robot)
    robot.measure("visibility", 0.9)
    robot.request("Mode(search)")
    return robot, events


@pytest.fixture
def nodes(rclpy_node: Callable[..., Rclpy]) -> tuple[Rclpy, Rclpy]:
    return rclpy_node("lifecycle", "searcher"), rclpy_node("lifecycle", "follower")


@pytest.mark.process
def test_the_measure_chooses_the_mode_and_a_switch_sets_parameters_and_states(
    make_manager: Callable[..., Manager], domain: int, nodes: tuple[Rclpy, Rclpy], observer: Observer
) -> None:
    robot, events = in_high_mode(make_manager, domain)
    assert {u.label for u in robot.get_model().units} >= {"search.high"}
    assert (observer.state("/searcher"), observer.state("/follower")) == ("active", "unconfigured")
    assert observer.exposure("/searcher") == 3.0
    (mode,) = robot.get_model().modes
    assert (mode["system"], mode["mode"], mode["transformation"]) == ("search", "high", "search.high")
    assert mode["why"] == "requested Mode(search): the preferred mode whose constraints hold (visibility = 0.9 >= 0.7)", mode
    robot.measure("visibility", 0.67)  # below 0.7, above 0.7 - 0.05: the high mode stays
    robot.measure("visibility", 0.6)  # past the margin: a fault, the low mode at once
    event = events.wait("adapted", timeout_s=30)
    assert "search.high" in event.old and "search.low" in event.new, event.to_dict()
    assert "visibility" in event.cause, event.cause
    assert (observer.state("/searcher"), observer.state("/follower")) == ("active", "active")
    assert observer.exposure("/searcher") == 1.0
    # the model, the metrics and /diagnostics say which mode, and why
    (mode,) = robot.get_model().modes
    assert mode["mode"] == "low" and mode["why"] == event.cause, mode
    assert [(m["system"], m["mode"]) for m in robot.metrics.snapshot()["modes"]] == [("search", "low")]
    (status,) = [s for s in robot.diagnostic_statuses() if s.name.endswith(": system search")]
    assert status.level == 0 and status.message == f"in mode low: {event.cause}" and ("mode", "low") in status.values, status
    robot.measure("visibility", 0.72)  # above the threshold: back to high (an opportunity, after the dwell time)
    event = events.wait("adapted", count=2, timeout_s=30)
    assert "search.low" in event.old and "search.high" in event.new, event.to_dict()
    assert (observer.state("/searcher"), observer.state("/follower")) == ("active", "inactive")  # deactivated, not cleaned up
    assert observer.exposure("/searcher") == 3.0
    robot.release(robot.get_model().requests[0].key)
    wait_for(lambda: observer.state("/searcher") == "inactive")  # the last mode left deactivates its nodes


@pytest.mark.process
def test_a_measure_hovering_at_the_threshold_switches_once_per_crossing(
    make_manager: Callable[..., Manager], domain: int, nodes: tuple[Rclpy, Rclpy], observer: Observer
) -> None:
    robot, events = in_high_mode(make_manager, domain)
    rng = random.Random(53)
    # down through the threshold once, with noise of +-0.04 around each level (inside the margin)
    levels = [0.8, 0.74, 0.7, 0.68, 0.66, 0.62, 0.6]
    crossed = False
    for level in levels:
        for _ in range(10):
            robot.measure("visibility", round(level + rng.uniform(-0.02, 0.02), 3))
            time.sleep(0.01)
        if level <= 0.62 and not crossed:
            events.wait("adapted", timeout_s=30)
            crossed = True
    time.sleep(0.5)  # past the dwell time: a flap would show now
    adapted = [e for e in events.events if e.kind == "adapted"]
    assert len(adapted) == 1, [e.to_dict() for e in adapted]
    assert "search.low" in adapted[0].new


@pytest.mark.process
def test_a_switch_that_fails_half_way_is_rolled_back(domain: int, nodes: tuple[Rclpy, Rclpy]) -> None:
    with DdsNode(domain=domain) as participant:
        lifecycles = {n: NodeLifecycle(participant, n, timeout_s=15) for n in ("/searcher", "/follower")}
        good = {"/searcher": Target("/searcher", "active", None, {"exposure": 2.0}), "/follower": Target("/follower", "inactive")}
        switch(lifecycles, good, where="test")
        assert lifecycles["/searcher"].state()[1] == "active"
        # the follower refuses a string for its double: the searcher's change and activation are undone
        bad = {
            "/follower": Target("/follower", "inactive"),
            "/searcher": Target("/searcher", "active", None, {"exposure": 5.0}),
            "/missing_part": Target("/missing_part", "active"),
        }
        with pytest.raises(SwitchError) as caught:
            switch({**lifecycles, "/missing_part": NodeLifecycle(participant, "/missing_part", timeout_s=1)}, bad, where="mode s.bad")
        assert "reading the states failed" in caught.value.what and "nothing had changed" in caught.value.what, caught.value.what
        assert caught.value.states == {"/follower": "unconfigured", "/searcher": "active", "/missing_part": "unknown (get_state does not answer)"}
        wrong = {"/searcher": Target("/searcher", "active", None, {"exposure": 4.0}), "/follower": Target("/follower", "active", None, {"exposure": "bright"})}
        with pytest.raises(SwitchError) as caught:
            switch(lifecycles, wrong, where="mode s.wrong")
        what = caught.value.what
        assert what.startswith("setting the parameters of /follower failed: the node refused the parameter exposure='bright'"), what
        assert "rolled back" in what and caught.value.states == {"/searcher": "active", "/follower": "unconfigured"}, what
        assert lifecycles["/searcher"].get_parameters(["exposure"]) == {"exposure": 2.0}  # set back
        for lifecycle in lifecycles.values():
            lifecycle.close()


@pytest.mark.process
def test_a_node_that_crashes_mid_switch_is_reported_as_it_is_and_once_restarted_the_next_switch_brings_it_up(
    domain: int, nodes: tuple[Rclpy, Rclpy], rclpy_node: Callable[..., Rclpy]
) -> None:
    """The follower's process ends in the middle of its activation (a crash): the switch fails on
    the call that got no answer, puts the searcher's parameter back, says it could not undo the
    follower's configuration and that the follower does not answer. The node's supervisor starts
    it again, and the next switch to the same mode, with the same clients, configures and
    activates the new process: it gets those two transitions and nothing of the failed switch
    (the requests of a call that went unanswered stayed in the client's writer, and a restarted
    node was given them: it was active before the next switch began)."""
    searcher, follower = nodes
    with DdsNode(domain=domain) as participant:
        lifecycles = {"/searcher": NodeLifecycle(participant, "/searcher", timeout_s=15), "/follower": NodeLifecycle(participant, "/follower", timeout_s=4)}
        switch(lifecycles, {"/searcher": Target("/searcher", "active", None, {"exposure": 2.0}), "/follower": Target("/follower", "inactive")}, where="test")
        both = {"/searcher": Target("/searcher", "active", None, {"exposure": 4.0}), "/follower": Target("/follower", "active")}
        follower.send("die-on-activate")
        with pytest.raises(SwitchError) as caught:
            switch(lifecycles, both, where="mode search.both")
        what = caught.value.what
        assert what.startswith("activating /follower failed: /follower/change_state: no answer in"), what
        assert "the rollback could not clean up /follower" in what, what
        assert caught.value.states == {"/searcher": "active", "/follower": "unknown (get_state does not answer)"}, caught.value.states
        assert follower.proc.wait(timeout=30) == 3
        assert lifecycles["/searcher"].get_parameters(["exposure"]) == {"exposure": 2.0}  # set back
        restarted = rclpy_node("lifecycle", "follower")
        wait_for(lambda: lifecycles["/follower"].state()[1] == "unconfigured", timeout_s=60)  # (the new process answers)
        done = switch(lifecycles, both, where="mode search.both")
        assert done.steps == ["/searcher: set 1 parameter(s)", "/follower: configure", "/follower: activate"], done.steps
        assert lifecycles["/follower"].state()[1] == "active" and lifecycles["/searcher"].get_parameters(["exposure"]) == {"exposure": 4.0}
        assert [restarted.lines.get(timeout=20) for _ in range(2)] == [{"transition": "configure", "exposure": 0.1}, {"transition": "activate"}]
        time.sleep(0.5)  # (nothing more comes: a replayed request would be printed too)
        assert restarted.lines.empty(), restarted.lines.get()
        for lifecycle in lifecycles.values():
            lifecycle.close()


@pytest.mark.process
def test_a_node_that_fails_makes_the_loop_leave_its_mode(
    make_manager: Callable[..., Manager], domain: int, nodes: tuple[Rclpy, Rclpy], observer: Observer
) -> None:
    searcher, follower = nodes
    robot, events = in_high_mode(make_manager, domain)
    searcher.send("fail")  # its deactivation errs: ErrorProcessing, then unconfigured
    event = events.wait("adapted", timeout_s=30)
    assert "search.high" in event.old and "search.low" in event.new, event.to_dict()
    assert "/searcher" in event.cause and "mode search.high needs it active" in event.cause, event.cause
    # the low mode brought the follower up beside the searcher
    assert [follower.lines.get(timeout=20) for _ in range(2)] == [{"transition": "configure", "exposure": 0.1}, {"transition": "activate"}]
    # the failure was passing: once its back-off is over the preferred mode is tried again, and holds
    event = events.wait("adapted", count=2, timeout_s=30)
    assert "search.high" in event.new and "back-off of search.high ended" in event.cause, event.to_dict()
    assert (observer.state("/searcher"), observer.state("/follower")) == ("active", "inactive")
    assert observer.exposure("/searcher") == 3.0


SENSOR = TransformationSpec("sensor", "dyknow.testing:Source", (), (Port("out", "out"),))


@pytest.mark.process
def test_a_measure_fed_from_a_stream_chooses_the_mode(
    make_manager: Callable[..., Manager], domain: int, nodes: tuple[Rclpy, Rclpy]
) -> None:
    robot = make_manager(specs=[*parse_specs(SEARCH), SENSOR], ros2_domain=domain, dwell_s=0.2)
    events = Events(robot)
    robot.spawn("sensor", "sensor", bindings={"out": "sensors/visibility"})  # a unit of the same manager, as a driver's
    sensor = robot.unit("sensor")
    assert isinstance(sensor, Source)
    robot.measure_from("visibility", "sensors/visibility#value")
    assert robot.measure_feeds == {"visibility": "sensors/visibility#value"}
    sensor.emit({"value": 0.9})
    wait_for(lambda: robot.measurements.get("visibility") == 0.9)
    robot.request("Mode(search)")
    sensor.emit({"value": 0.3})
    event = events.wait("adapted", timeout_s=30)
    assert "search.low" in event.new and "visibility" in event.cause, event.to_dict()
    with pytest.raises(BindingError, match="the field 'not a path'"):
        robot.measure_from("visibility", "sensors/visibility#not a path")


@pytest.mark.browser
def test_the_browser_tool_and_dyknow_model_show_the_mode_and_why(
    make_manager: Callable[..., Manager], domain: int, nodes: tuple[Rclpy, Rclpy], cli_process: Callable[..., CliProcess], browser: Any
) -> None:
    robot = make_manager(specs=parse_specs(SEARCH), ros2_domain=domain, listen=["tcp/127.0.0.1:0"])
    robot.measure("visibility", 0.3)
    robot.request("Mode(search)")
    result = run_cli("model", "--connect", robot.endpoints[0], "--manager", robot.name)
    lines = result.stdout
    assert "system search in mode low since " in lines and "(unit search.low): requested Mode(search): the preferred mode" in lines, result
    url = str(cli_process("ui", "--connect", robot.endpoints[0], "--port", "0", "--json").line()["url"])
    browser.get(url)
    wait_text(browser, "modes", "search: low since ")
    line = drawn_text(browser, "#modes li[data-system='search']")
    assert "(manager " in line and "unit search.low): requested Mode(search): the preferred mode whose constraints hold" in line, line
