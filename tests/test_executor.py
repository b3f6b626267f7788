"""The executor: shared lane, isolation of slow units, timers, mutual exclusion."""

from __future__ import annotations

import random
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import Manager, Message, Port, TransformationSpec, Unit, default_key
from dyknow.executor import LOAD_WINDOW_S, Executor
from dyknow.testing import Sink, Source
from tests.conftest import subprocess_env, wait_until
from tests.units import Slow


class Busy(Unit):
    """Spins for 5 ms of its thread's CPU time per message: slow enough to earn a thread of its own.
    (CPU time, not the clock's: the executor judges a unit by the time that was its own, and beside
    CPU hogs 5 ms by the clock were often 2 ms of CPU, too little to be moved.)"""

    def on_message(self, port: str, msg: Message) -> None:
        end = time.thread_time() + 0.005
        while time.thread_time() < end:
            pass
        self.publish("out", msg.payload)


class Exclusive(Unit):
    """Checks that its timer and message callbacks never overlap."""

    def setup(self) -> None:
        self.inside = False
        self.overlaps = 0
        self.ticks = 0
        self.messages = 0
        self.create_timer(0.001, self.tick)

    def _enter(self) -> None:
        if self.inside:
            self.overlaps += 1
        self.inside = True
        time.sleep(0.0002)
        self.inside = False

    def tick(self) -> None:
        self._enter()
        self.ticks += 1

    def on_message(self, port: str, msg: Message) -> None:
        self._enter()
        self.messages += 1


class Pass(Unit):
    """Publishes what it receives (in Python: a callback per message, timed like any other)."""

    def on_message(self, port: str, msg: Message) -> None:
        self.publish("out", msg.payload)


class Stuck(Unit):
    """Takes half a millisecond of its thread's CPU time per message (too long to be run on its
    publisher's thread, well under the line for slow), except "stick": it then waits until the test
    lets it go (or forever). (CPU time, not a sleep: waking from a sleep it waits for the interpreter
    lock, which the executor charges to it when the lock's holder is preempted, as beside CPU hogs,
    where a 0.5 ms sleep was charged 3-10 ms and the unit took the one slow lane meant for Busy.)"""

    release = threading.Event()

    def setup(self) -> None:
        self.inside = threading.Event()

    def on_message(self, port: str, msg: Message) -> None:
        if msg.payload == "stick":
            self.inside.set()
            Stuck.release.wait()
            return
        end = time.thread_time() + 0.0005
        while time.thread_time() < end:
            pass


SPECS = """<transformations>
  <transformation><label>busy</label><source>tests.test_executor:Busy</source>
    <ports><port type="in">in</port><port type="out">out</port></ports></transformation>
  <transformation><label>pass</label><source>tests.test_executor:Pass</source>
    <ports><port type="in">in</port><port type="out">out</port></ports></transformation>
  <transformation><label>stuck</label><source>tests.test_executor:Stuck</source>
    <ports><port type="in">in</port><port type="out">out</port></ports></transformation>
  <transformation><label>exclusive</label><source>tests.test_executor:Exclusive</source>
    <ports><port type="in">in</port></ports></transformation>
</transformations>"""


def test_consistently_slow_unit_moves_to_its_own_thread(manager: Manager) -> None:
    manager.add_transformation(SPECS)
    manager.spawn("publisher", "src")
    manager.spawn("busy", "busy", bindings={"in": default_key(manager.name, "src", "out")})
    manager.spawn("sink", "s", bindings={"in": default_key(manager.name, "busy", "out")})
    assert manager.get_model().unit("busy").executor == "shared thread"
    src = manager.unit("src")
    assert isinstance(src, Source)
    sink = manager.unit("s")
    assert isinstance(sink, Sink)
    for i in range(20):
        src.emit(i)
        sink.wait_for(i + 1)
    assert manager.get_model().unit("busy").executor.startswith("own thread (its callbacks take")
    assert manager.get_model().unit("s").executor == "shared thread"


def test_timers_and_messages_never_overlap(manager: Manager) -> None:
    manager.add_transformation(SPECS)
    manager.spawn("publisher", "src")
    manager.spawn("exclusive", "x", bindings={"in": default_key(manager.name, "src", "out")})
    src = manager.unit("src")
    assert isinstance(src, Source)
    emitter = threading.Thread(target=lambda: [src.emit(i) or time.sleep(0.0005) for i in range(300)])
    emitter.start()
    emitter.join()
    x = manager.unit("x")

    def accounted() -> int:  # every message was either handled or dropped by the bounded queue
        return x.messages + manager.get_statistics("x").ports[0].dropped  # type: ignore[attr-defined, no-any-return]

    deadline = time.monotonic() + 5
    while accounted() < 300 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert accounted() == 300
    assert x.overlaps == 0  # type: ignore[attr-defined]
    assert x.ticks > 10 and x.messages > 50  # type: ignore[attr-defined]


def test_a_busy_manager_leaves_the_global_random_state_alone(manager: Manager) -> None:
    """A program that seeds ``random`` for its own sequence keeps it, whatever the managers of its
    process do: the watchdog draws the moments of its load readings from a generator of its own
    (drawn from the global one, they changed a Hypothesis test's draws under it, on a busy machine)."""
    random.seed(50)
    expected = random.getstate()
    manager.spawn("sink", "s", bindings={"in": default_key(manager.name, "src", "out")})
    manager.spawn("periodic-source", "src", params={"rate_hz": 1000, "payload_size": 64})
    sink = manager.unit("s")
    assert isinstance(sink, Sink)
    sink.wait_for(100)  # busy: the watchdog is awake and reading the load
    time.sleep(8 * LOAD_WINDOW_S)  # the window observed: about eight readings
    assert random.getstate() == expected


def test_periodic_source_stops_after_count(manager: Manager) -> None:
    manager.spawn("sink", "s", bindings={"in": default_key(manager.name, "src", "out")})  # consumers first
    manager.spawn("periodic-source", "src", params={"rate_hz": 1000, "count": 25, "payload_size": 3})
    sink = manager.unit("s")
    assert isinstance(sink, Sink)
    got = sink.wait_for(25)
    assert [m.seq for m in got] == list(range(1, 26)) and got[0].payload == b"\x00\x00\x00"
    time.sleep(0.05)  # would-be ticks after the count
    assert len(sink.messages) == 25


def test_close_is_bounded_even_with_a_stuck_unit(make_manager: object) -> None:
    manager = make_manager()  # type: ignore[operator]
    manager.spawn("publisher", "src")
    manager.spawn("slow", "stuck", params={"delay_s": 30.0}, bindings={"in": default_key(manager.name, "src", "out")})
    src = manager.unit("src")
    src.emit(1)
    assert manager.unit("stuck").started.wait(5)
    start = time.monotonic()
    manager.close(timeout_s=1.0)
    assert time.monotonic() - start < 3.0


class FirstTick(Unit):
    def setup(self) -> None:
        self.started_ns = time.monotonic_ns()
        self.first = threading.Event()
        self.at_ns = 0
        self.create_timer(10.0, self.tick, first_s=0)

    def tick(self) -> None:
        self.at_ns = time.monotonic_ns()
        self.first.set()


def test_a_timer_can_fire_at_once(manager: Manager) -> None:
    manager.add_transformation(
        "<transformation><label>first-tick</label><source>tests.test_executor:FirstTick</source>"
        '<ports><port type="out">out</port></ports></transformation>'
    )
    manager.spawn("first-tick", "f")
    unit = manager.unit("f")
    assert isinstance(unit, FirstTick)
    assert unit.first.wait(5)  # a 10 s period, yet the first tick came at once
    assert unit.at_ns - unit.started_ns < 5e9
    with pytest.raises(ValueError, match="must not be negative"):
        unit.create_timer(1.0, lambda: None, first_s=-1)


class SlowSetupFirstTick(FirstTick):
    """Its timer is due at once, and its setup goes on for a while after making it (a loaded
    machine, where setup's thread is preempted there, does the same by chance)."""

    def setup(self) -> None:
        super().setup()
        time.sleep(0.3)  # (setup still holds the unit: the tick due now finds it busy)


def test_a_first_tick_due_while_setup_runs_fires_once_setup_is_done(manager: Manager) -> None:
    """A tick that finds its unit busy is skipped (no burst after a slow callback), but a first
    one is tried again shortly: before, it waited a whole period (10 s here; beside CPU hogs,
    test_a_timer_can_fire_at_once saw no first tick within 5 s)."""
    manager.add_transformation(
        "<transformation><label>slow-first-tick</label><source>tests.test_executor:SlowSetupFirstTick</source>"
        '<ports><port type="out">out</port></ports></transformation>'
    )
    manager.spawn("slow-first-tick", "f")
    unit = manager.unit("f")
    assert isinstance(unit, SlowSetupFirstTick)
    assert unit.first.wait(5)  # a 10 s period: without the retry, the first tick came 10 s on


class Ticker(Unit):
    """Creates a fast timer in setup(); many input ports keep it starting for a while."""

    def setup(self) -> None:
        self.ticks = 0
        self.ticked = threading.Event()
        self.create_timer(0.0005, self.tick, first_s=0)

    def tick(self) -> None:
        self.ticks += 1
        if self.ticks >= 5:
            self.ticked.set()


def test_a_timer_that_fires_while_the_unit_starts_keeps_ticking(manager: Manager) -> None:
    """A timer created in setup() may fire before the inputs are bound; it must not be cancelled then."""
    spec = TransformationSpec(label="ticker", source="tests.test_executor:Ticker", ports=tuple(Port(f"in{i}", "in") for i in range(40)))
    for i in range(5):
        manager.spawn(spec, f"t{i}")
        ticker = manager.unit(f"t{i}")
        assert isinstance(ticker, Ticker)
        assert ticker.ticked.wait(5), f"the timer of t{i} ticked {ticker.ticks} times"


# ---------------------------------------------------------------------- the watchdog of an idle lane


class StuckTick(Unit):
    """Its one timer tick (after 0.3 s) blocks until the test releases it."""

    def setup(self) -> None:
        self.inside = threading.Event()
        self.release = threading.Event()
        self.create_timer(60.0, self.tick, first_s=0.3)

    def tick(self) -> None:
        self.inside.set()
        self.release.wait(10)


def _wakeups(thread_name: str) -> int:
    """How often the thread named ``thread_name`` has been switched in (its context switches)."""
    thread = next(t for t in threading.enumerate() if t.name == thread_name)
    with open(f"/proc/self/task/{thread.native_id}/status") as status:
        return sum(int(line.split()[1]) for line in status if "ctxt_switches" in line)


def _wait_asleep(manager: Manager) -> None:
    """Wait until the manager's watchdog stops waking, then check that it stays asleep."""
    name = f"dyknow-{manager.name}-watchdog"

    def settled() -> bool:
        now = _wakeups(name)
        time.sleep(0.3)
        return _wakeups(name) == now

    wait_until(settled, "the idle watchdog to stop polling", timeout_s=10)
    before = _wakeups(name)
    time.sleep(1.0)
    assert _wakeups(name) == before, "the watchdog of an idle manager woke up"


def test_an_idle_watchdog_sleeps_yet_catches_a_stuck_callback(make_manager: object) -> None:
    """An idle manager's watchdog does not poll at all; the first message to the shared lane
    wakes it, so a callback that then holds the lane is still handed its own thread."""
    manager = make_manager(stall_budget_s=0.02)  # type: ignore[operator]
    manager.spawn("publisher", "src")
    manager.spawn("slow", "stuck", params={"delay_s": 3.0}, bindings={"in": default_key(manager.name, "src", "out")})
    _wait_asleep(manager)
    src, stuck = manager.unit("src"), manager.unit("stuck")
    assert isinstance(src, Source) and isinstance(stuck, Slow)
    src.emit(1)
    assert stuck.started.wait(5)
    wait_until(lambda: manager.get_statistics("stuck").executor.startswith("own thread"), "the stuck unit moved", timeout_s=2)
    assert stuck.handled == 0  # moved while still inside its 3-second callback


def test_an_idle_watchdog_wakes_for_a_new_timer(make_manager: object) -> None:
    """A timer added while the watchdog sleeps keeps it polling: a stuck tick is caught too."""
    manager = make_manager(stall_budget_s=0.02)  # type: ignore[operator]
    manager.add_transformation(
        "<transformation><label>stuck-tick</label><source>tests.test_executor:StuckTick</source>"
        '<ports><port type="out">out</port></ports></transformation>'
    )
    _wait_asleep(manager)
    manager.spawn("stuck-tick", "t")
    unit = manager.unit("t")
    assert isinstance(unit, StuckTick)
    try:
        assert unit.inside.wait(5)
        wait_until(lambda: manager.get_statistics("t").executor.startswith("own thread"), "the stuck tick moved", timeout_s=2)
        assert not unit.release.is_set()
    finally:
        unit.release.set()


SPINNER = """
import functools, time
from dyknow.executor import Executor

executor = Executor("spin")


class Job:
    name = "spinner"
    scheduled = False
    lane = executor.shared


job = Job()
job.run = functools.partial(executor.shared.put, job)  # run(worker) queues the job again, in C
executor.shared.put(job)
started = time.monotonic()
for _ in range(20):
    time.sleep(0.005)
print(f"the main thread ran beside the lane: 20 sleeps in {time.monotonic() - started:.3f} s", flush=True)
job.run = lambda worker: None
executor.close(1.0)
"""


@pytest.mark.process
def test_a_lane_busy_with_code_that_never_reaches_python_lets_other_threads_run(tmp_path: Path) -> None:
    """A job that runs no Python (here: it queues itself again, in C) keeps the lane's compiled
    loop busy without ever reaching one of the interpreter's switch points. The lane lets go of
    the interpreter lock once per switch interval, so the main thread still runs. Before, it
    never got the lock back (a manager with two relays bound into a cycle answered nothing and
    ignored SIGTERM). In a child process, so a regression ends in a timeout, not a hung suite."""
    script = tmp_path / "spinner.py"
    script.write_text(SPINNER)
    try:
        result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60, env=subprocess_env())
    except subprocess.TimeoutExpired:
        pytest.fail("the main thread never ran again while the lane was busy (60 s)")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "the main thread ran beside the lane" in result.stdout


# ---------------------------------------------------------------------------- the bound on threads


def _lane_threads(manager: Manager) -> int:
    """The threads serving the manager's lanes, as Python knows them (by their names)."""
    pattern = re.compile(rf"dyknow-{re.escape(manager.name)}-(shared|lane\d+)")
    return sum(1 for thread in threading.enumerate() if pattern.fullmatch(thread.name) and thread.is_alive())


def _chain(manager: Manager, label: str, count: int) -> tuple[Source, Sink]:
    manager.add_transformation(SPECS)
    manager.spawn("sink", "sink", bindings={"in": default_key(manager.name, f"p{count - 1}", "out")})
    for i in reversed(range(count)):
        upstream = default_key(manager.name, f"p{i - 1}" if i else "src", "out")
        manager.spawn(label, f"p{i}", bindings={"in": upstream})
    manager.spawn("publisher", "src")
    src, sink = manager.unit("src"), manager.unit("sink")
    assert isinstance(src, Source) and isinstance(sink, Sink)
    return src, sink


def test_with_every_callback_slow_the_threads_stay_within_the_bound(make_manager: Callable[..., Manager]) -> None:
    """The line for slow made tiny (1 ns): every callback counts as slow, so every unit of a
    chain of twelve leaves the shared lane once its probe confirms it. With max_lanes=3 the
    manager never runs more than three lanes: the first two slow units get a lane each, the
    others share those two; every message still arrives, in order."""
    manager = make_manager(listen=[], slow_callback_s=1e-9, max_lanes=3)
    src, sink = _chain(manager, "pass", 12)
    lanes, threads = [], []
    for i in range(60):
        src.emit(i)
        sink.wait_for(i + 1)
        lanes.append(manager.load()["threads"])
        threads.append(_lane_threads(manager))
    assert [m.payload for m in sink.messages] == list(range(60))
    assert max(lanes) <= 3 and max(threads) <= 3, (lanes, threads)
    load = manager.load()
    slow = [lane for lane in load["lanes"] if lane["kind"] == "slow"]
    assert len(slow) == 2 and sum(lane["units"] for lane in slow) >= 12  # the twelve, and the sink once it was slow too
    described = [manager.get_statistics(f"p{i}").executor for i in range(12)]
    assert all(d.startswith(("own thread (its callbacks take", "slow lane shared with")) for d in described), described
    assert any(d.startswith("slow lane shared with") for d in described)


def test_the_bound_must_leave_room_for_a_slow_lane() -> None:
    with pytest.raises(ValueError, match="at least 2"):
        Executor("too-few", max_lanes=1)


def test_a_unit_stuck_forever_at_the_bound_does_not_stop_the_others(make_manager: Callable[..., Manager]) -> None:
    """At the bound (max_lanes=2: the shared lane and one slow lane, taken by a slow unit), a unit
    gets stuck in a callback for good. No thread may be added: the watchdog makes the slow lane
    the shared one, moves the other units there, and leaves the stuck lane to the stuck unit.
    Messages keep flowing past it (through a unit beside it), and the manager still runs two lanes."""
    Stuck.release.clear()
    manager = make_manager(listen=[], max_lanes=2, stall_budget_s=0.02)
    manager.add_transformation(SPECS)
    key = default_key(manager.name, "src", "out")
    try:
        manager.spawn("busy", "busy", bindings={"in": key})  # slow: it takes the one slow lane
        manager.spawn("stuck", "stuck", bindings={"in": key})
        manager.spawn("pass", "beside", bindings={"in": key})
        manager.spawn("sink", "sink", bindings={"in": default_key(manager.name, "beside", "out")})
        manager.spawn("sink", "after-busy", bindings={"in": default_key(manager.name, "busy", "out")})
        manager.spawn("publisher", "src")
        src, sink, after_busy = manager.unit("src"), manager.unit("sink"), manager.unit("after-busy")
        assert isinstance(src, Source) and isinstance(sink, Sink) and isinstance(after_busy, Sink)
        for i in range(20):
            src.emit(i)
            sink.wait_for(i + 1)
        try:
            wait_until(lambda: manager.get_statistics("busy").executor.startswith("own thread (its callbacks take"), "the busy unit moved")
        except AssertionError as exc:  # where each unit runs, and why
            raise AssertionError(f"{exc}: {[(u, manager.get_statistics(u).executor) for u in ('busy', 'stuck', 'beside', 'sink')]}") from None
        assert manager.load()["threads"] == 2
        stuck = manager.unit("stuck")
        assert isinstance(stuck, Stuck)
        src.emit("stick")
        assert stuck.inside.wait(10)
        wait_until(lambda: manager.get_statistics("stuck").executor.startswith("own thread (a callback held"), "the stuck unit left alone")
        for i in range(20, 60):
            src.emit(i)
            sink.wait_for(i + 2)  # (the sink got 20, then "stick" passed on by "beside")
        assert [m.payload for m in sink.messages if m.payload != "stick"] == list(range(60))
        load = manager.load()
        assert load["threads"] == 2 and _lane_threads(manager) == 2, load
        kinds = {lane["name"]: lane for lane in load["lanes"]}
        assert sorted(lane["kind"] for lane in kinds.values()) == ["shared", "slow"]
        (left,) = [lane for lane in kinds.values() if lane["kind"] == "slow"]
        assert left["names"] == ["stuck"]
        assert left["stuck_ms"] >= 20, left  # (it was read against another clock: a huge negative number)
        # the busy unit, on the shared lane now, is still slow: it may not be moved onto the lane
        # left to the stuck unit, where it would never run again (it was, beside CPU hogs: that
        # lane was the only slow one); it keeps up on the shared lane
        wait_until(lambda: list(after_busy.messages)[-1].payload == 59, "the busy unit to catch up (it keeps the latest message)")
        for i in range(60, 100):  # (one at a time: it drops what comes faster than it takes)
            seen = len(after_busy.messages)
            src.emit(i)
            try:
                after_busy.wait_for(seen + 1, timeout_s=30)
            except TimeoutError as exc:
                raise AssertionError(f"{exc}: lanes {manager.load()['lanes']}, busy {manager.get_statistics('busy').executor}") from None
        assert [m.payload for m in after_busy.messages][-40:] == list(range(60, 100))
        slow = [lane["names"] for lane in manager.load()["lanes"] if lane["kind"] == "slow"]
        assert manager.load()["threads"] == 2 and slow == [["stuck"]], slow
    finally:
        Stuck.release.set()
