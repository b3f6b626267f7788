"""Warm standby: a request keeps its next-best configuration running and switches onto it by
moving its anchor only. The paper's scenario with real units, over real Zenoh sessions."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from dyknow import Client, Manager, Message, ServiceError, UnitError, UnitEvent
from dyknow.adaptation import ANCHOR_LABEL, WARM_ANCHOR_SPEC, AdaptationEvent
from dyknow.testing import CAMERA_IDS, SCENARIO_SPECS, Sink, Source
from tests.conftest import REPO, ManagerProcess, run_cli, wait_until

ONTOLOGY = REPO / "specs" / "dyknow.ttl"
BOTTOM, TOP, CEILING = CAMERA_IDS["bottom"], CAMERA_IDS["top"], CAMERA_IDS["ceiling"]
TAG = "BallPosition(field)"
ROBOT_CHAIN = {"robot-camera", "subsampler(bottom)", "ball-detector(bottom)", "localization(bottom)", "tracker"}
TOP_CHAIN = {"top-camera", "subsampler(top)", "ball-detector(top)", "localization(top)", "tracker"}
CEILING_CHAIN = {"ceiling-camera", "subsampler(ceiling)", "ball-detector(ceiling)", "localization(ceiling)", "tracker"}

# A third camera between the robot's (priority 1, needs battery) and the ceiling's (priority 10):
# after the battery runs low there is still a next-best configuration to stand by.
TOP_CAMERA = """<transformation><label>top-camera</label><source>dyknow.testing:Camera</source>
  <params><param name="camera">top</param><param name="rate_hz" type="float">200</param></params>
  <ports><port type="out" deadline-ms="100">out</port></ports>
  <tags><tag port="out">RawImage(top)</tag></tags><priority>5</priority></transformation>"""


class Journal:
    """Unit and adaptation events of one manager, in the order they happened."""

    def __init__(self, manager: Manager) -> None:
        self.entries: list[UnitEvent | AdaptationEvent] = []
        self._cond = threading.Condition()
        manager.on_unit_event(self._add)
        manager.on_adaptation(self._add)

    def _add(self, event: UnitEvent | AdaptationEvent) -> None:
        with self._cond:
            self.entries.append(event)
            self._cond.notify_all()

    def adapted(self, count: int = 1, timeout_s: float = 10.0) -> AdaptationEvent:
        """The ``count``-th "adapted" event, once it happened."""
        with self._cond:
            ok = self._cond.wait_for(lambda: len(self._adaptations("adapted")) >= count, timeout_s)
            assert ok, f"no {count} adaptations within {timeout_s} s: {self.entries}"
            return self._adaptations("adapted")[count - 1]

    def _adaptations(self, kind: str) -> list[AdaptationEvent]:
        return [e for e in self.entries if isinstance(e, AdaptationEvent) and e.kind == kind]

    def spawned_before(self, event: AdaptationEvent, since: int) -> list[str]:
        """Units spawned from entry ``since`` up to ``event``."""
        with self._cond:
            upto = next(i for i, e in enumerate(self.entries) if e is event)
            return [e.unit for e in self.entries[since:upto] if isinstance(e, UnitEvent) and e.kind == "spawned"]


@pytest.fixture
def robot(make_manager: Callable[..., Manager]) -> Iterator[Manager]:
    yield make_manager(specs=[SCENARIO_SPECS, REPO / "specs" / "generic.xml"], ontology=[ONTOLOGY], dwell_s=0.3)


def consume(manager: Manager, key: str, label: str = "consumer") -> Sink:
    manager.spawn(label, "consumer", bindings={"in": key})
    consumer = manager.unit("consumer")
    assert isinstance(consumer, Sink)
    return consumer


def the_request(manager: Manager) -> Any:
    (info,) = manager.requests()
    return info


def anchor_config(manager: Manager) -> dict[str, str]:
    anchor = next(u for u in manager.get_model().units if u.label == ANCHOR_LABEL)
    return manager.get_config(anchor.name)


def started(manager: Manager) -> dict[str, int]:
    return {u.name: u.started_ns for u in manager.get_model().units}


def test_warm_standby_units_are_spawned_listed_and_not_forwarded(robot: Manager) -> None:
    key = robot.request(TAG, standby="warm")
    info = the_request(robot)
    assert info.standby_mode == "warm" and set(info.labels) == ROBOT_CHAIN
    assert set(info.standby_labels) == CEILING_CHAIN and info.standby_reason is None
    running = {u.name: u for u in robot.get_model().units}
    assert set(info.standby) <= set(running) and not set(info.standby) & set(info.units)  # its own units
    model = robot.get_model().to_dict()["requests"][0]
    assert model["standby_mode"] == "warm" and model["standby"] == list(info.standby)
    config = anchor_config(robot)
    tracker = next(n for n in info.standby if running[n].label == "tracker")
    assert config["standby"] == running[tracker].bindings["out"] != config["in"]

    consumer = consume(robot, key)
    consumer.wait_for(50)
    assert {m.payload["camera"] for m in consumer.messages} == {BOTTOM}  # only the active configuration
    wait_until(lambda: robot.get_statistics(tracker).ports[-1].messages > 10, "the standby's tracker at work")


def test_a_battery_fault_moves_the_anchor_onto_the_standby_and_plans_the_next(robot: Manager) -> None:
    robot.add_transformation(TOP_CAMERA)
    journal = Journal(robot)
    key = robot.request(TAG, standby="warm")
    consumer = consume(robot, key)
    consumer.wait_until(lambda m: m.payload["camera"] == BOTTOM)
    before = the_request(robot)
    assert set(before.standby_labels) == TOP_CHAIN  # the next best: the top camera, not the ceiling
    standby_key = anchor_config(robot)["standby"]
    times = started(robot)
    mark = len(journal.entries)

    robot.measure("battery", 0.1)  # below the robot camera's constraint
    switch = journal.adapted()
    assert switch.standby and switch.cause == "measurement battery = 0.1"
    assert set(switch.old) == ROBOT_CHAIN and set(switch.new) == TOP_CHAIN
    assert journal.spawned_before(switch, mark) == []  # nothing spawned for the switch
    msg = consumer.wait_until(lambda m: m.payload["camera"] == TOP)
    assert msg.key == key
    after = the_request(robot)
    assert after.units == before.standby and anchor_config(robot)["in"] == standby_key
    assert all(started(robot)[n] == times[n] for n in after.units)  # the same units, not new ones

    # then a new standby: the ceiling (the robot camera is out while the battery is low)
    wait_until(lambda: set(the_request(robot).standby_labels) == CEILING_CHAIN, "the next standby")
    # the broken configuration goes (its teardown may finish after the standby is planned)
    wait_until(lambda: not {"robot-camera", "subsampler-bottom"} & set(started(robot)), "the robot camera's units gone")
    assert anchor_config(robot)["standby"] != standby_key

    # the battery recovers: back to the robot camera (after the dwell); what it leaves stands by
    top_units = {n for n in after.units if "top" in n}
    robot.measure("battery", 0.9)
    back = journal.adapted(2)
    assert set(back.new) == ROBOT_CHAIN and back.cause.startswith("measurement battery = 0.9")
    consumer.wait_until(lambda m: m.payload["camera"] == BOTTOM)
    wait_until(lambda: set(the_request(robot).standby_labels) == TOP_CHAIN, "the old configuration standing by")
    kept = {n: started(robot)[n] for n in top_units if n in started(robot)}
    assert kept == {n: times[n] for n in top_units}  # its camera, subsampler, detector, localization kept running
    # the ceiling stood by; no longer needed, it goes (its teardown may finish after the new standby is planned)
    wait_until(lambda: not {n for n in started(robot) if "ceiling" in n}, "the ceiling's units gone")


def test_a_destroyed_unit_switches_onto_the_standby_and_the_preferred_one_returns(robot: Manager) -> None:
    journal = Journal(robot)
    key = robot.request(TAG, standby="warm")
    consumer = consume(robot, key)
    consumer.wait_until(lambda m: m.payload["camera"] == BOTTOM)
    robot.destroy("robot-camera")
    switch = journal.adapted()
    assert switch.standby and switch.cause == "unit 'robot-camera' was destroyed" and set(switch.new) == CEILING_CHAIN
    consumer.wait_until(lambda m: m.payload["camera"] == CEILING)
    # the robot camera can simply run again: it stands by, and is preferred after the dwell time
    back = journal.adapted(2)
    assert back.standby and set(back.new) == ROBOT_CHAIN and "after the dwell time" in back.cause
    consumer.wait_until(lambda m: m.payload["camera"] == BOTTOM)
    wait_until(lambda: set(the_request(robot).standby_labels) == CEILING_CHAIN, "the ceiling standing by again")


def test_a_failed_standby_unit_is_replaced_without_touching_the_stream(robot: Manager) -> None:
    journal = Journal(robot)
    robot.request(TAG, standby="warm")
    info = the_request(robot)
    robot.destroy(next(n for n in info.standby if n.startswith("subsampler")))
    wait_until(lambda: len(the_request(robot).standby) == 5 and "subsampler-ceiling" in started(robot), "a new standby unit")
    assert the_request(robot).units == info.units
    assert not [e for e in journal.entries if isinstance(e, AdaptationEvent)]  # the active configuration never moved


def test_release_tears_the_standby_down_too(robot: Manager) -> None:
    key = robot.request(TAG, standby="warm")
    assert len(robot.get_model().units) == 11  # the anchor, five active and five standing by
    robot.release(key)
    assert robot.get_model().units == () and robot.requests() == []


def test_a_shared_request_asked_warm_gets_a_standby_on_the_same_key(robot: Manager) -> None:
    key = robot.request(TAG)
    assert the_request(robot).standby_mode == "none" and the_request(robot).standby == ()
    assert "standby" not in anchor_config(robot)
    consumer = consume(robot, key)
    assert robot.request(TAG, standby="warm") == key
    info = the_request(robot)
    assert info.references == 2 and info.standby_mode == "warm" and set(info.standby_labels) == CEILING_CHAIN
    consumer.wait_until(lambda m: m.payload["camera"] == BOTTOM)  # still flowing, through the new anchor
    robot.release(key)
    robot.release(key)
    assert {u.name for u in robot.get_model().units} == {"consumer"}


def test_no_alternative_means_no_standby_and_says_why(robot: Manager) -> None:
    robot.remove_transformation("ceiling-camera")
    robot.request(TAG, standby="warm")
    info = the_request(robot)
    assert info.standby == () and info.standby_reason is not None and "no standby for BallPosition(field)" in info.standby_reason


def test_the_anchor_forwards_the_standby_latest_message_when_it_takes_over(manager: Manager) -> None:
    """The anchor keeps the standby's latest message and forwards it at once when ``in`` moves onto it."""
    manager.spawn("publisher", "active", bindings={"out": "t/active"})
    manager.spawn("publisher", "standby", bindings={"out": "t/standby"})
    manager.spawn(WARM_ANCHOR_SPEC, "anchor", bindings={"in": "t/active", "standby": "t/standby", "out": "t/key"})
    out = consume(manager, "t/key", "sink")
    active, standby = manager.unit("active"), manager.unit("standby")
    assert isinstance(active, Source) and isinstance(standby, Source)
    standby.emit("s1")
    standby.emit("s2")
    active.emit("a1")
    assert [m.payload for m in out.wait_for(1)] == ["a1"]  # the standby is kept, not forwarded
    manager.set_config("anchor", {"in": "t/standby", "standby": "t/idle"})
    msgs: list[Message] = out.wait_for(2)
    assert [m.payload for m in msgs] == ["a1", "s2"]  # the latest one, at once
    active.emit("a2")
    standby.emit("s3")
    assert [m.payload for m in out.wait_for(3)] == ["a1", "s2", "s3"]


def test_bad_standby_values_are_refused_naming_the_field_before_anything_changes(robot: Manager) -> None:
    for bad in ("hot", "WARM", 3, ""):
        with pytest.raises(UnitError, match=r"field 'standby': got .*; expected one of 'none', 'warm'"):
            robot.request(TAG, standby=bad)  # type: ignore[arg-type]
    with pytest.raises(UnitError, match=r"did you mean 'warm'"):
        robot.request(TAG, standby="warn")
    with Client(robot.name, connect=robot.endpoints) as client:
        with pytest.raises(UnitError, match="field 'standby'"):
            client.request(TAG, standby="hot")
        with pytest.raises(ServiceError) as refused:
            client.call_manager(robot.name, "request", {"tag": TAG, "standby": "hot"})  # straight to the service
        assert "field 'standby': got 'hot'; expected one of 'none', 'warm'" in str(refused.value)
        with pytest.raises(ServiceError, match="field 'standby'"):
            client.call_manager(robot.name, "request", {"tag": TAG, "standby": None})
        assert client.get_model()["units"] == [] and robot.requests() == []
        key = client.request(TAG, standby="warm")  # and a good one over the service
    assert the_request(robot).standby_mode == "warm" and key == the_request(robot).key


@pytest.mark.process
def test_the_cli_requests_a_warm_standby_from_a_manager_process(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process("--specs", str(SCENARIO_SPECS), "--ontology", str(ONTOLOGY), "--dwell", "0.3")
    bad = run_cli("request", TAG, "--standby", "hot", *proc.client_args())
    assert bad.returncode == 2 and "--standby" in bad.stderr and "'none', 'warm'" in bad.stderr
    result = run_cli("request", TAG, "--standby", "warm", *proc.client_args(), "--json")
    assert result.returncode == 0, result.stderr
    reply = json.loads(result.stdout)
    assert reply["standby"] == "warm" and reply["key"] == f"dyknow/{proc.name}/requests/{TAG}"
    model = json.loads(run_cli("model", *proc.client_args(), "--json").stdout)
    (request,) = model["requests"]
    assert request["standby_mode"] == "warm" and set(request["standby_labels"]) == CEILING_CHAIN
    assert set(request["standby"]) <= {u["name"] for u in model["units"]}

    assert run_cli("measure", "battery=0.1", *proc.client_args()).returncode == 0

    def switched() -> bool:
        events = json.loads(run_cli("adaptations", *proc.client_args(), "--json").stdout)
        return any(e["kind"] == "recovered" and e["standby"] for e in events)

    wait_until(switched, "the switch onto the standby, reported")
    text = run_cli("adaptations", *proc.client_args()).stdout
    assert "(onto the warm standby)" in text and "measurement battery = 0.1" in text


def test_a_warm_standby_on_other_managers_takes_over_when_the_active_one_is_lost() -> None:
    """The loop alone, against the stand-in runtime: the standby runs on another manager, spawned
    there; losing the active configuration's manager only moves the anchor."""
    from dataclasses import replace

    from dyknow import Port, Tag, TransformationSpec
    from dyknow.adaptation import AdaptationLoop
    from dyknow.federation import Summary
    from tests.test_adaptation import StandInRuntime

    def camera(label: str, priority: int) -> TransformationSpec:
        return TransformationSpec(
            label, "dyknow.testing:Source", ports=(Port("out", "out"),), tags=(Tag("out", "Image"),), priority=priority
        )

    runtime = StandInRuntime([])
    runtime.peer_summaries = {
        "robot": Summary("robot", "robot-host", 1, "r1", (camera("front-camera", 1),)),
        "field": Summary("field", "field-host", 1, "f1", (camera("back-camera", 2),)),
    }
    events: list[AdaptationEvent] = []
    loop = AdaptationLoop(runtime, dwell_s=60)
    loop.on_event(events.append)
    try:
        loop.request("Image", standby="warm")
        (info,) = loop.requests()
        assert info.labels == ("front-camera@robot",) and info.standby_labels == ("back-camera@field",)
        assert ("spawn", "field", "back-camera") in runtime.remote_calls
        anchor = next(u for u in runtime.units() if u.label == ANCHOR_LABEL)
        assert runtime.get_config(anchor.name)["standby"] == "dyknow/field/back-camera/out"

        calls = len(runtime.remote_calls)
        robot = runtime.peer_summaries.pop("robot")
        loop.peer_changed("lost", "robot")
        wait_until(lambda: any(e.kind == "adapted" for e in events), "the switch")
        (switch,) = [e for e in events if e.kind == "adapted"]
        assert switch.standby and switch.new == ("back-camera@field",)
        assert runtime.get_config(anchor.name)["in"] == "dyknow/field/back-camera/out"
        assert not [c for c in runtime.remote_calls[calls:] if c[0] == "spawn"]  # nothing spawned to switch
        assert loop.requests()[0].standby == ()  # nothing else to stand by with

        runtime.peer_summaries["robot"] = replace(robot, library="r2", units=())  # it comes back: it stands by
        loop.peer_changed("found", "robot")
        wait_until(lambda: loop.requests()[0].standby_labels == ("front-camera@robot",), "the robot standing by")
    finally:
        loop.close()
