"""Overload: the guard's policy over readings, and a real manager that cannot keep up."""

from __future__ import annotations

import ctypes
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence

import pytest

from dyknow import Manager, Unit
from dyknow.executor import Load
from dyknow.overload import CLEAR_READINGS, ENTER_READINGS, PAUSED, REDUCED, STEP_READINGS, OverloadGuard, OverloadState
from dyknow.testing import Sink
from tests.conftest import wait_until

MS = 1_000_000


class _Units:
    """Units by priority, as a manager would give them to its guard, and what the guard set."""

    def __init__(self, priorities: Mapping[str, int]) -> None:
        self.priorities = dict(priorities)
        self.settings: dict[str, int] = dict.fromkeys(priorities, 0)
        self.changes: list[tuple[OverloadState, bool | None]] = []

    def list(self) -> Sequence[tuple[str, int]]:
        return list(self.priorities.items())

    def apply(self, shed: Mapping[int, int]) -> int:
        for name, priority in self.priorities.items():
            self.settings[name] = shed.get(priority, 0)
        return sum(1 for s in self.settings.values() if s)

    def changed(self, state: OverloadState, entered: bool | None) -> None:
        self.changes.append((state, entered))


def _guard(units: _Units) -> OverloadGuard:
    return OverloadGuard("m", lag_budget_s=0.05, priorities=units.list, apply=units.apply, on_change=units.changed, clock_ns=time.time_ns)


def _feed(guard: OverloadGuard, lag_ms: float, readings: int) -> None:
    for _ in range(readings):
        guard.reading(Load(0, int(lag_ms * MS), 1.0, 1.0, 2, 16, 0))


def test_the_guard_sheds_the_least_important_tier_first_and_never_the_most_important() -> None:
    units = _Units({"camera": 1, "detector": 1, "logger": 200, "monitor-1": 100, "monitor-2": 100})
    guard = _guard(units)
    _feed(guard, 60, ENTER_READINGS - 1)
    assert guard.state.state == "ok" and not units.changes  # one reading short
    _feed(guard, 60, 1)
    assert guard.state.state == "overloaded" and units.changes[-1][1] is True
    assert units.settings == {"camera": 0, "detector": 0, "logger": REDUCED, "monitor-1": 0, "monitor-2": 0}
    steps = []
    for _ in range(6):  # still over the budget: one step further each time
        _feed(guard, 60, STEP_READINGS)
        steps.append(dict(units.settings))
    assert steps[0]["logger"] == PAUSED and steps[0]["monitor-1"] == 0
    assert steps[1]["monitor-1"] == steps[1]["monitor-2"] == REDUCED
    assert steps[2]["monitor-1"] == steps[2]["monitor-2"] == PAUSED
    assert all(s["camera"] == s["detector"] == 0 for s in steps)  # the most important tier keeps its rate
    assert guard.state.shed == ((200, 0.0), (100, 0.0)) and guard.state.units_shed == 3
    # The lag falls: the steps are undone, the most important shed work first, one per CLEAR_READINGS.
    _feed(guard, 10, CLEAR_READINGS)
    assert units.settings["monitor-1"] == REDUCED and units.settings["logger"] == PAUSED
    _feed(guard, 10, CLEAR_READINGS)
    assert units.settings["monitor-1"] == 0 and units.settings["logger"] == PAUSED
    assert guard.state.state == "overloaded"
    _feed(guard, 10, 2 * CLEAR_READINGS)
    assert set(units.settings.values()) == {0}
    assert guard.state.state == "ok" and units.changes[-1][1] is False
    assert [entered for _, entered in units.changes].count(True) == 1


def test_a_lag_between_half_the_budget_and_the_budget_neither_sheds_more_nor_restores() -> None:
    units = _Units({"a": 1, "b": 2})
    guard = _guard(units)
    _feed(guard, 60, ENTER_READINGS)
    assert units.settings["b"] == REDUCED
    _feed(guard, 40, 10 * CLEAR_READINGS)
    assert units.settings["b"] == REDUCED and guard.state.state == "overloaded"


def test_a_step_comes_when_most_readings_are_over_though_not_all_in_a_row() -> None:
    """A probe that lands between two long callbacks reads a short lag: readings alternating over
    and under the budget (3 in 4 over) still shed one step per STEP_READINGS readings; fewer than
    half over never does, and nor does a lag between half the budget and the budget restore."""
    units = _Units({"a": 1, "b": 2, "c": 3})
    guard = _guard(units)
    _feed(guard, 60, ENTER_READINGS)
    assert units.settings == {"a": 0, "b": 0, "c": REDUCED}
    for _ in range(STEP_READINGS // 4):
        _feed(guard, 60, 1)
        _feed(guard, 2, 1)
        _feed(guard, 60, 2)
    assert units.settings["c"] == PAUSED and units.settings["b"] == 0
    for _ in range(5 * STEP_READINGS):  # one in three over, the mean under the budget: no step
        _feed(guard, 60, 1)
        _feed(guard, 30, 2)
    assert units.settings == {"a": 0, "b": 0, "c": PAUSED}


class Hog(Unit):
    """Every 2 ms, works 20 ms on the CPU and publishes: more than its lane can give it."""

    def setup(self) -> None:
        self.ticks = 0
        self.create_timer(0.002, self.tick)

    def tick(self) -> None:
        end = time.perf_counter() + 0.02
        while time.perf_counter() < end:
            pass
        self.ticks += 1
        self.publish("out", self.ticks)


class Ticker(Unit):
    """Publishes a count every 20 ms."""

    def setup(self) -> None:
        self.ticks = 0
        self.create_timer(0.02, self.tick)

    def tick(self) -> None:
        self.ticks += 1
        self.publish("out", self.ticks)


SPECS = """<transformations>
  <transformation><label>hog-low</label><source>tests.test_overload:Hog</source><priority>200</priority>
    <ports><port type="out">out</port></ports></transformation>
  <transformation><label>hog-mid</label><source>tests.test_overload:Hog</source><priority>100</priority>
    <ports><port type="out">out</port></ports></transformation>
  <transformation><label>beat-sink</label><source>dyknow.testing:Sink</source><priority>1</priority>
    <ports><port type="in">in</port></ports></transformation>
  <transformation><label>important</label><source>tests.test_overload:Ticker</source><priority>1</priority>
    <ports><port type="out">out</port></ports>
    <tags><tag port="out">Heartbeat(robot)</tag></tags></transformation>
</transformations>"""


_LIBC = ctypes.PyDLL(None)  # (a PyDLL call keeps the interpreter lock)


class Holder(Unit):
    """Every 0.35 s, spends 0.3 s in C without letting go of the interpreter lock, as a library
    that never releases it does: no other thread of the process runs meanwhile."""

    def setup(self) -> None:
        self.create_timer(0.35, self.tick)

    def tick(self) -> None:
        _LIBC.usleep(300_000)


HOLDER_SPECS = """<transformations>
  <transformation><label>holder</label><source>tests.test_overload:Holder</source>
    <ports><port type="out">out</port></ports></transformation>
</transformations>"""


def test_a_callback_that_keeps_the_interpreter_lock_holds_up_work_and_the_manager_sees_it(make_manager: Callable[..., Manager]) -> None:
    """The lane is held 0.3 s of every 0.35 s and the watchdog's thread gets to run only as the
    callback returns, when the lane is free: a probe timed from then read no lag. Timed from when
    its reading was due, it counts what a message arriving then waits, and the manager says it is
    overloaded (it has nothing less important to shed)."""
    manager = make_manager(listen=[], slow_callback_s=10.0, stall_budget_s=30.0)
    manager.add_transformation(HOLDER_SPECS)
    manager.spawn("holder", "holder")
    wait_until(lambda: manager.overload.state == "overloaded", "the manager overloaded", 30)
    assert manager.get_model().executor["overload"]["state"] == "overloaded"


def test_an_overloaded_manager_says_so_and_sheds_the_lowest_priority_first(
    make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture
) -> None:
    """Two hogs keep the shared lane busy (each wants 20 ms of work every 2 ms; no unit ever
    counts as slow, no callback as stuck): a message waits far longer than the 5 ms budget. The
    manager becomes overloaded (model, one warning, an event), sheds the priority-200 hog first
    (a quarter, then paused), then the priority-100 one; the requested heartbeat (priority 1)
    keeps its rate throughout, and its stream is never shed."""
    manager = make_manager(listen=[], slow_callback_s=10.0, stall_budget_s=30.0, overload_lag_s=0.005)
    manager.add_transformation(SPECS)
    events: list[dict[str, object]] = []
    got = threading.Event()

    def on_event(key: str, payload: bytes) -> None:
        events.append(json.loads(payload))
        got.set()

    sub = manager.session.declare_raw_subscriber(f"dyknow/{manager.name}/events/overload", on_event)
    try:
        key = manager.request("Heartbeat(robot)")
        manager.spawn("beat-sink", "beats", bindings={"in": key})
        beats = manager.unit("beats")
        assert isinstance(beats, Sink)
        beats.wait_for(5)
        with caplog.at_level(logging.INFO, logger="dyknow.manager"):
            manager.spawn("hog-low", "low")
            manager.spawn("hog-mid", "mid")
            wait_until(lambda: any(t["priority"] == 100 for e in events for t in e["shed"]), "the priority-100 hog shed too", 30)  # type: ignore[attr-defined]
        assert manager.get_model().executor["overload"]["state"] == "overloaded"
        assert manager.overload.state == "overloaded"
        assert events[0]["state"] == "overloaded" and events[0]["shed"] == [{"priority": 200, "rate": 0.25}]
        # each tier goes to a quarter, then pauses, before the next more important one is touched
        order = [tuple((t["priority"], t["rate"]) for t in e["shed"]) for e in events]  # type: ignore[attr-defined]
        first_mid = next(i for i, tiers in enumerate(order) if any(p == 100 for p, _ in tiers))
        assert order[first_mid] == ((200, 0.0), (100, 0.25)) and ((200, 0.0),) in order[:first_mid]
        assert all(p != 1 for tiers in order for p, _ in tiers)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "is overloaded" in r.getMessage()]
        assert len(warnings) == 1, [r.getMessage() for r in caplog.records]
        # at the default priority, the warning says what answers a CPU taken by other processes
        assert os.getpriority(os.PRIO_PROCESS, os.getpid()) >= 0
        assert "dyknow manager --nice -20 (or -10) gives it precedence" in warnings[0].getMessage()
        # the heartbeat and everything serving its request run at full rate; the hogs do not
        serving = [u.name for u in manager.units() if u.name not in ("low", "mid", "beats")]
        assert serving and all(manager.get_statistics(name).rate == 1.0 for name in serving)
        assert manager.get_statistics("low").rate < 1.0 and "load shedding" in manager.get_statistics("low").executor
        assert all(p.shed == 0 for p in manager.get_statistics("beats").ports)
        before = len(beats.messages)
        beats.wait_for(before + 10)  # still beating
    finally:
        sub.undeclare()
