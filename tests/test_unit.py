"""The Unit base class: its hooks, its services and how dyknow wires it (dyknow.unit.attach)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping

import pytest

from dyknow import Manager, Message, Unit, UnitError
from dyknow.testing import UnitHarness

SPEC = """<transformation><label>hooks</label><source>tests.test_unit:Hooks</source>
  <params><param name="listen_on" type="string">elsewhere/in</param></params>
  <ports><port type="in">in</port><port type="out">out</port></ports></transformation>"""


class Hooks(Unit):
    """Records which hook ran, with what the unit knew at the time."""

    calls: list[str] = []

    def setup(self) -> None:
        Hooks.calls = [f"setup {self.name} {self.label} {dict(self.params)} {self.log.name} {self.log.extra}"]
        self.reconfigured = threading.Event()
        self.bound_at_setup = self.set_config({"in": str(self.params["listen_on"])})  # a key given as a param

    def on_message(self, port: str, msg: Message) -> None:
        Hooks.calls.append(f"message {port} {msg.payload!r} subscribers={self.has_subscribers('out')}")
        if msg.payload == "bad":
            self.reject(port, "bad payload")
            return
        self.publish("out", msg.payload)

    def on_reconfigure(self, changes: Mapping[str, str]) -> None:
        Hooks.calls.append(f"reconfigure {dict(changes)}")
        self.reconfigured.set()

    def teardown(self) -> None:
        Hooks.calls.append("teardown")


def test_hooks_run_in_order_with_the_attributes_set_before_setup() -> None:
    with UnitHarness(SPEC, name="h") as harness:
        unit = harness.unit
        assert isinstance(unit, Hooks)
        assert unit.bound_at_setup["in"] == "elsewhere/in"
        harness.manager.set_config("h", {"in": "testing/h/in/in"})  # back to the harness's feed
        assert unit.reconfigured.wait(5)
        harness.send("in", "hello")
        harness.send("in", "bad")
        harness.send("in", "again")
        assert [m.payload for m in harness.wait_for("out", 2)] == ["hello", "again"]
        assert harness.statistics().ports[0].rejected == 1
    assert Hooks.calls == [
        "setup h hooks {'listen_on': 'elsewhere/in'} dyknow.unit {'unit': 'h'}",  # one logger; the unit in the record
        "reconfigure {'in': 'elsewhere/in'}",
        "reconfigure {'in': 'testing/h/in/in'}",
        "message in 'hello' subscribers=True",
        "message in 'bad' subscribers=True",
        "message in 'again' subscribers=True",
        "teardown",
    ]


class Dedicated(Unit):
    """Asks for a thread of its own."""

    dedicated_thread = True

    def on_message(self, port: str, msg: Message) -> None:
        self.publish("out", threading.current_thread().name)


def test_a_dedicated_unit_runs_on_its_own_thread() -> None:
    spec = SPEC.replace("hooks", "dedicated").replace("tests.test_unit:Hooks", "tests.test_unit:Dedicated")
    with UnitHarness(spec) as harness:
        assert harness.info.executor == "own thread (the unit asks for a thread of its own (dedicated_thread = True))"
        harness.send("in", 1)
        assert harness.wait_for("out", 1)[0].payload == "dyknow-testing-unit"  # the lane named after the unit


def test_fail_from_another_thread_marks_the_unit_failed() -> None:
    with UnitHarness(SPEC) as harness:
        failed = threading.Event()
        harness.manager.on_unit_event(lambda event: failed.set() if event.kind == "failed" else None)
        threading.Thread(target=harness.unit.fail, args=("the sensor is gone",)).start()
        assert failed.wait(5)
        assert harness.info.state == "failed" and harness.info.error == "reported by the unit: UnitError: the sensor is gone"


def test_spawning_many_names_leaves_no_logger_behind(make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture) -> None:
    """One ``dyknow.unit`` logger for all units, the unit's name in each record: names do not accumulate."""
    import logging

    manager = make_manager()
    manager.spawn("relay", "warm-up")
    before = len(logging.Logger.manager.loggerDict)
    for i in range(200):
        manager.spawn("relay", f"short-lived-{i}-" + "x" * 60)
        manager.destroy(f"short-lived-{i}-" + "x" * 60)
    assert len(logging.Logger.manager.loggerDict) == before
    unit = manager.unit("warm-up")
    with caplog.at_level(logging.INFO, logger="dyknow.unit"):
        unit.log.info("hello")
    (record,) = [r for r in caplog.records if r.name == "dyknow.unit"]
    assert record.getMessage() == "[warm-up] hello" and record.unit == "warm-up"  # type: ignore[attr-defined]


def test_a_unit_no_manager_runs_answers_introspection() -> None:
    """Its services say how to run it; the lookups of help(), pydoc and copy get AttributeError, not that advice."""
    import copy

    unit = Unit()
    with pytest.raises(UnitError, match="the unit is not running, so it cannot create timer"):
        unit.create_timer(1.0, lambda: None)
    runtime = unit._runtime
    assert not hasattr(runtime, "__objclass__") and not hasattr(runtime, "__wrapped__")
    assert repr(runtime) == "<no runtime: the unit is not running>"
    copy.copy(unit)  # probes __reduce_ex__ and __deepcopy__ on the class, __setstate__ on the copy
