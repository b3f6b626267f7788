"""The executor: the threads that run the callbacks of a manager's units.

Why it looks like this: handing a message from one Python thread to another costs 20-40 µs on a
small machine, far more than the rest of a hop. So the units of a manager share one *lane*, a
ready queue served by one thread that runs each unit's pending callbacks back to back: a message
that flows through a chain of fast units never changes thread, and a hop costs a few microseconds.

Isolation still holds, by two rules:

1. A unit whose callbacks are slow (moving average above ``slow_callback_s``) is moved off the
   shared lane as soon as that callback returns. Slow is judged against the machine, not the
   clock alone: once its wall-clock average crosses the line, the unit's next callbacks are
   *probed* (:func:`cpu_mark`, :func:`charged_ns`): only the time that was its own (its thread's
   CPU time, and time it was blocked that neither the run queue nor the process's other threads
   explain) counts. A unit that was slow only because the CPU was taken away stays where it is.
2. A watchdog thread notices a callback that has held the shared lane for longer than
   ``stall_budget_s`` and hands the shared lane to a fresh thread at once; when the slow callback
   finally returns, its thread stays with that unit as the unit's lane.

**A hard bound on threads.** The lanes dyknow makes on its own (the shared one, the lanes of slow
units, the watchdog's fresh threads) are at most ``max_lanes``, whatever the load. Below the bound
a slow unit gets a lane of its own; at the bound it shares the least busy *slow lane* with other
slow units, and the watchdog, instead of starting a thread, makes the least busy slow lane whose
thread is free the new shared lane (the units of the stuck one move there, the stuck unit keeps
the stuck thread). A slow lane whose last unit leaves stops. A thread that never returns from a
callback still counts against the bound until it does. A unit that declares
``dedicated_thread = True`` gets a lane of its own from the start, outside the bound: its author
asked for that thread.

So a slow unit delays the others (its upstream among them) at most once, by about the stall
budget, and never again (an idle watchdog polls slowly, then sleeps; the shared lane wakes it when work
arrives). A unit's callbacks never run concurrently: each job carries a lock and runs on one
thread at a time.

**Load.** While it watches, the watchdog sends a probe through the shared lane about every
:data:`LOAD_WINDOW_S`, at random moments, and reads how long it waited since it was due (the
lane's *lag*: its time in the queue, and the watchdog's own wait for the interpreter lock, which
work pays too), and how busy the lane's thread was; each reading goes to ``on_load`` (the manager's overload guard,
:mod:`dyknow.overload`). :meth:`Executor.lane_infos` describes every lane.

A *job* (a unit's proxy) is anything with the attributes ``lane``, ``scheduled`` and the methods
``run(worker)`` and ``run_timer(timer, worker)``. Deliveries mark a job scheduled and put it on its
lane's ready queue; the job clears the mark when it starts running, so nothing is lost between the
last check and the next delivery.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import os
import queue
import random
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, Protocol

from dyknow.errors import ClosedError

__all__ = [
    "DEFAULT_MAX_LANES",
    "LOAD_WINDOW_S",
    "Executor",
    "Job",
    "Lane",
    "LaneInfo",
    "Load",
    "Timer",
    "Worker",
    "charged_ns",
    "cpu_mark",
]

log = logging.getLogger(__name__)

#: The most lanes (threads serving units) a manager makes on its own, by default: enough to keep
#: a few slow or blocking units apart on a small robot computer, few enough that an overloaded
#: one does not make the load worse with threads (``--max-lanes``).
DEFAULT_MAX_LANES: Final = 16
#: How often the watchdog measures the shared lane's lag and busy time while it watches, on
#: average (s): each gap is drawn between half and one and a half of it.
LOAD_WINDOW_S: Final = 0.25

_STOP: Final = object()
_WAKE: Final = object()
_NEVER: Final = 1 << 62  # next_due_ns of a lane without timers
_FIRST_TICK_RETRY_NS: Final = 1_000_000  # a first tick that found its unit busy is tried again after 1 ms
_IDLE_POLL_S = 0.1  # the watchdog's slowest poll; past it, it sleeps until the shared lane wakes
_LOAD_WINDOW_NS: Final = int(LOAD_WINDOW_S * 1e9)
_BUSY_WINDOW_NS: Final = 1_000_000_000  # a lane's busy fraction is over this long
_SHOWN_NAMES: Final = 50  # a lane description names at most this many of its units

SHARED: Final = "shared"
SLOW: Final = "slow"
DEDICATED: Final = "dedicated"


class Job(Protocol):
    """What the executor schedules: one unit's inputs, timers and control calls."""

    lane: Lane
    scheduled: bool
    name: str

    def run(self, worker: Worker) -> None:
        """Handle what is pending for the job."""
        ...

    def run_timer(self, timer: Timer, worker: Worker) -> bool:
        """Fire one tick of ``timer``; False when it was skipped because the job was busy on
        another thread (its setup, say)."""
        ...


# ---------------------------------------------------------------------------- judging a callback


def _run_delay_ns() -> int:
    """How long the calling thread has waited on a run queue so far (Linux schedstat; 0 elsewhere)."""
    try:
        with open("/proc/thread-self/schedstat", "rb") as stat:
            return int(stat.read().split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def cpu_mark() -> tuple[int, int, int, int]:
    """What :func:`charged_ns` needs, taken on the callback's thread right before it runs:
    the monotonic clock, the thread's and the process's CPU time, the thread's run-queue wait.
    It costs about 15 µs (a read of ``/proc``): only callbacks of units suspected slow pay it."""
    return time.monotonic_ns(), time.thread_time_ns(), time.process_time_ns(), _run_delay_ns()


def charged_ns(mark: tuple[int, int, int, int]) -> int:
    """The part of a callback's time (since ``mark``, on the same thread) that was its own.

    Its thread's CPU time, plus the time it was blocked (sleeping, waiting on I/O) that nothing
    else explains: time the thread waited on the run queue (the CPU was taken away) and CPU time
    the process's other threads used meanwhile (one of them held the interpreter lock, or was
    about to) are not the callback's. So a callback that took 30 ms of wall time because the
    machine was busy, or because another thread of the manager held the interpreter lock, is
    charged what it really used; one that slept or waited on a socket is charged its wait.
    Not excused: time spent waiting for the interpreter lock while its holder was itself
    preempted by other processes (no counter tells it apart from a blocking call).
    """
    start, own0, process0, waited0 = mark
    wall = time.monotonic_ns() - start
    own = time.thread_time_ns() - own0
    others = time.process_time_ns() - process0 - own
    waited = _run_delay_ns() - waited0
    blocked = wall - own - waited - (others if others > 0 else 0)
    return own + (blocked if blocked > 0 else 0)


# ---------------------------------------------------------------------------- timers and lanes


class Timer:
    """A periodic timer whose callback runs on its job's lane. ``cancel()`` stops it."""

    __slots__ = ("_executor", "callback", "cancelled", "fired", "job", "next_ns", "overruns", "period_ns")

    def __init__(self, executor: Executor, job: Job, period_ns: int, callback: Callable[[], None], first_ns: int | None = None) -> None:
        self._executor = executor
        self.job = job
        self.period_ns = period_ns
        self.callback = callback
        self.next_ns = time.monotonic_ns() + (period_ns if first_ns is None else first_ns)
        self.cancelled = False
        self.fired = False  # whether a tick ran yet
        self.overruns = 0

    def cancel(self) -> None:
        """Stop the timer; safe twice, from any thread."""
        self.cancelled = True


class Lane:
    """A ready queue and a timer heap, served by one worker thread at a time.

    ``kind``: ``"shared"`` (the lane the watchdog watches; units start there), ``"slow"`` (units
    moved off the shared lane; several share it once the bound is reached) or ``"dedicated"``
    (one unit that asked for a thread of its own). ``members``: its units (the executor's lock
    guards it).
    """

    def __init__(self, executor: Executor, name: str, kind: str) -> None:
        self.executor = executor
        self.name = name
        self.kind = kind
        self.shared = kind == SHARED
        self.ready: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.put = self.ready.put
        self._timers: list[tuple[int, int, Timer]] = []
        self._timer_lock = threading.Lock()
        self.next_due_ns = _NEVER  # when the earliest timer is due (monotonic clock)
        self.worker: Worker | None = None
        self.members: dict[int, Job] = {}  # id(job) -> job
        self.busy_ns = 0  # time its threads were awake, up to the last time one went to sleep
        self.lag_ns = 0  # how long the last probe waited in the ready queue
        self.probe: _Probe | None = None  # the probe in the queue, if one is
        # the unit whose callback held the shared lane's thread past the stall budget, the lane
        # left to it by the watchdog: no unit is moved here while that callback runs
        self.held: Job | None = None
        now = time.monotonic_ns()
        self._window = (now, 0)  # (start of the busy window, busy_ns then)
        self._busy = 0.0
        self._rolled = False

    def add_timer(self, timer: Timer) -> None:
        """Schedule ``timer`` on this lane and wake its worker."""
        with self._timer_lock:
            heapq.heappush(self._timers, (timer.next_ns, next(_tie), timer))
            self.next_due_ns = self._timers[0][0]
        self.put(_WAKE)  # the worker recomputes how long it may sleep

    def fire_due(self, worker: Worker) -> None:
        """Fire every timer that is due (skipping missed ticks rather than bursting)."""
        now = time.monotonic_ns()
        while True:
            with self._timer_lock:
                if not self._timers or self._timers[0][0] > now:
                    self.next_due_ns = self._timers[0][0] if self._timers else _NEVER
                    return
                _, _, timer = heapq.heappop(self._timers)
            if timer.cancelled:
                continue
            job_lane = timer.job.lane
            if job_lane is not self:  # its unit moved to another lane
                job_lane.add_timer(timer)
                continue
            ran = timer.job.run_timer(timer, worker)
            if timer.cancelled:
                continue
            if not ran and not timer.fired:
                # its first tick found the unit busy (a timer made in setup(), due at once, fires
                # while setup still holds the unit, on a loaded machine): due again shortly, not a
                # period later (a first tick 10 s late, once beside CPU hogs)
                timer.next_ns = time.monotonic_ns() + _FIRST_TICK_RETRY_NS
                with self._timer_lock:
                    heapq.heappush(self._timers, (timer.next_ns, next(_tie), timer))
                continue
            timer.fired = True
            timer.next_ns += timer.period_ns
            now = time.monotonic_ns()
            if timer.next_ns <= now:  # we fell behind: skip the missed ticks rather than burst
                missed = (now - timer.next_ns) // timer.period_ns + 1
                timer.overruns += missed
                timer.next_ns += missed * timer.period_ns
            with self._timer_lock:
                heapq.heappush(self._timers, (timer.next_ns, next(_tie), timer))

    def timer_count(self) -> int:
        """How many timers the lane holds."""
        with self._timer_lock:
            return len(self._timers)

    def take_timers_of(self, job: Job) -> list[Timer]:
        """Remove and return the timers of ``job`` (it moves to another lane)."""
        with self._timer_lock:
            mine = [entry for entry in self._timers if entry[2].job is job]
            if mine:
                self._timers = [entry for entry in self._timers if entry[2].job is not job]
                heapq.heapify(self._timers)
                self.next_due_ns = self._timers[0][0] if self._timers else _NEVER
        return [entry[2] for entry in mine]

    def take_timers_except(self, job: Job) -> list[Timer]:
        """Remove and return every timer but those of ``job`` (the others move to another lane)."""
        with self._timer_lock:
            others = [entry[2] for entry in self._timers if entry[2].job is not job]
            self._timers = [entry for entry in self._timers if entry[2].job is job]
            self.next_due_ns = self._timers[0][0] if self._timers else _NEVER
        return others

    def busy_total_ns(self, now_ns: int) -> int:
        """How long its threads have been awake so far (running callbacks, or waiting for the
        CPU or the interpreter lock to run them)."""
        worker = self.worker
        extra = now_ns - worker.awake_ns if worker is not None and worker.active and worker.lane is self else 0
        return self.busy_ns + (extra if extra > 0 else 0)

    def busy(self, now_ns: int) -> float:
        """The fraction of the last second its thread was awake (0 to 1)."""
        start, at = self._window
        total = self.busy_total_ns(now_ns)
        span = now_ns - start
        if span <= 0:
            return self._busy
        current = min(1.0, max(0.0, (total - at) / span))
        if span >= _BUSY_WINDOW_NS:
            self._busy, self._window, self._rolled = current, (now_ns, total), True
            return current
        return self._busy if self._rolled else current

    def lag(self, now_ns: int) -> int:
        """How long work waits in its queue before it runs: the last probe's wait, or the wait so
        far of the probe still queued, whichever is longer (ns)."""
        probe = self.probe
        pending = now_ns - probe.sent_ns if probe is not None else 0
        return max(self.lag_ns, pending)

    def stuck_ns(self) -> int:
        """How long its thread has been in one callback (0 when it is in none). A callback's start
        is stamped on the wall clock (a unit's job takes it with the message's arrival time), so
        this reads the wall clock too: against the monotonic one it was always negative, and no
        lane was ever stuck (nor shown so)."""
        worker = self.worker
        since = worker.busy_since_ns if worker is not None else 0
        return max(0, time.time_ns() - since) if since else 0


class _Probe:
    """A job that only measures how long it waited in its lane's queue."""

    __slots__ = ("lane", "name", "scheduled", "sent_ns")

    def __init__(self, lane: Lane, sent_ns: int) -> None:
        self.lane = lane
        self.name = "probe"
        self.scheduled = True
        self.sent_ns = sent_ns  # when the watchdog meant to send it (see Executor._watch)

    def run(self, worker: Worker) -> None:
        lane = self.lane
        lane.lag_ns = time.monotonic_ns() - self.sent_ns
        if lane.probe is self:
            lane.probe = None

    def run_timer(self, timer: Timer, worker: Worker) -> bool:
        return True


_tie = itertools.count()


class Worker:
    """A thread serving one lane. ``busy_since_ns``/``busy_job`` tell the watchdog what it runs."""

    def __init__(self, lane: Lane) -> None:
        self.lane = lane
        self.busy_since_ns = 0
        self.busy_job: Job | None = None
        self.released = False  # set by the watchdog: our lane went to another thread
        self.stuck_job: Job | None = None  # the job whose callback we were stuck in
        self.next_lane: Lane | None = None  # the lane reserved for it (and us) by the watchdog
        self.active = True  # False while the thread sleeps waiting for work or a timer
        self.awake_ns = time.monotonic_ns()  # when it last woke up
        self.thread = threading.Thread(target=self._serve, name=f"dyknow-{lane.name}", daemon=True)
        self._native_id = 0
        self._cpu_clock: int | None = None
        lane.worker = self

    def start(self) -> None:
        """Start the worker's thread."""
        self.thread.start()

    def cpu_ns(self) -> int | None:
        """CPU time the thread has used so far (None where the platform cannot tell)."""
        clock = self._cpu_clock
        if clock is None:
            return None
        try:
            return time.clock_gettime_ns(clock)
        except OSError:  # the thread has ended
            return None

    def blocked(self) -> bool:
        """Whether the thread sleeps or waits on I/O right now (Linux; False elsewhere)."""
        try:
            with open(f"/proc/self/task/{self._native_id}/stat", "rb") as stat:
                state = stat.read().rsplit(b")", 1)[1].split()[0]
        except (OSError, IndexError):
            return False
        return state in (b"S", b"D")

    def _serve(self) -> None:
        self._native_id = threading.get_native_id()
        try:
            self._cpu_clock = time.pthread_getcpuclockid(threading.get_ident())
        except (AttributeError, OSError):
            self._cpu_clock = None
        lane = self.lane
        executor = lane.executor
        get, get_nowait = lane.ready.get, lane.ready.get_nowait
        monotonic_ns = time.monotonic_ns
        yielded_ns = monotonic_ns()  # when this thread last let go of the interpreter lock
        self.awake_ns = yielded_ns
        switch_ns = int(sys.getswitchinterval() * 1e9)
        while True:
            # Work queued: take it at once (the hot path); otherwise sleep until the next timer.
            try:
                job = get_nowait()
                # Compiled code never reaches the interpreter's switch points: a lane kept busy
                # by units that run no Python (forwarding units in a cycle, say) would hold the
                # lock for good, and the manager's services and signal handler with it. So
                # after a switch interval of work without a pause, let go of it once: a thread
                # waiting for it takes it then.
                now_ns = monotonic_ns()
                if now_ns - yielded_ns > switch_ns:
                    os.sched_yield()  # lets go of the interpreter lock (like time.sleep(0), which a faked clock breaks)
                    yielded_ns = monotonic_ns()
            except queue.Empty:
                job = None  # (asleep, the thread holds no unit: one destroyed meanwhile goes at once)
                due = lane.next_due_ns
                self.active = False  # about to sleep
                lane.busy_ns += monotonic_ns() - self.awake_ns
                try:
                    if due == _NEVER:
                        job = get()
                    else:
                        wait = (due - monotonic_ns()) / 1e9
                        job = get(timeout=wait) if wait > 0 else None
                except queue.Empty:
                    job = None
                yielded_ns = monotonic_ns()
                self.awake_ns = yielded_ns
                # Awake (work, a timer, or a new timer to wait for). A watchdog asleep until
                # the shared lane wakes watches from now. ``active`` is set before the check and
                # the watchdog sets ``sleeping`` before it reads ``active``: one sees the other.
                self.active = True
                if executor.sleeping and lane.shared:
                    executor.wake_watchdog()
            if job is _STOP:
                lane.busy_ns += monotonic_ns() - self.awake_ns
                return
            if lane.next_due_ns <= monotonic_ns():
                lane.fire_due(self)
            if job is None or job is _WAKE:
                pass
            elif job.lane is not lane:  # moved to another lane while queued here
                job.lane.put(job)
            else:
                if executor.dozing and lane.shared:  # the watchdog polls slowly: it watches from now
                    executor.wake_watchdog()
                job.run(self)
            if self.released:
                stuck, self.stuck_job, self.released = self.stuck_job, None, False
                now_ns = monotonic_ns()
                lane.busy_ns += now_ns - self.awake_ns
                self.awake_ns = now_ns
                own = lane.executor._take_lane(stuck, self) if stuck is not None else None
                if own is None:
                    return
                lane = own
                get, get_nowait = lane.ready.get, lane.ready.get_nowait


#: The watchdog's own random numbers: a library thread never draws from the global ``random``
#: state, which the program around it may have seeded for its own sequence.
_RANDOM = random.Random()


def _reading_gap_ns() -> int:
    """How long until the watchdog's next load reading: :data:`LOAD_WINDOW_S` on average, drawn
    at random between half and one and a half of it (see Executor._watch)."""
    return _LOAD_WINDOW_NS // 2 + int(_RANDOM.random() * _LOAD_WINDOW_NS)


def _machine_idle_s() -> float:
    """Idle time of all CPUs since boot, in seconds (Linux /proc/stat).

    Where it cannot be read, the monotonic clock stands in: the machine then always looks idle.
    """
    try:
        with open("/proc/stat", "rb") as stat:
            fields = stat.readline().split()
        return (int(fields[4]) + int(fields[5])) / os.sysconf("SC_CLK_TCK")  # idle + iowait
    except (OSError, IndexError, ValueError):
        return time.monotonic()


# ---------------------------------------------------------------------------- what it tells


@dataclass(frozen=True, slots=True)
class LaneInfo:
    """One lane as the model shows it: its kind, its units, how busy its thread is.

    ``units``: how many units it runs; ``names``: their names (at most 50; the shared lane's
    are not listed: every unit not named elsewhere runs there). ``busy``: the fraction of the
    last second its thread was awake; ``lag_ms``: how long work last waited in its queue (the
    shared lane only: the watchdog's probe); ``queued``: entries in its queue now; ``stuck_ms``:
    how long its thread has been inside one callback (0: it is not).
    """

    name: str
    kind: str
    units: int
    names: tuple[str, ...]
    busy: float
    lag_ms: float
    queued: int
    stuck_ms: float

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (the model's ``executor.lanes`` entries)."""
        return {
            "name": self.name,
            "kind": self.kind,
            "units": self.units,
            "names": list(self.names),
            "busy": round(self.busy, 3),
            "lag_ms": round(self.lag_ms, 3),
            "queued": self.queued,
            "stuck_ms": round(self.stuck_ms, 1),
        }


@dataclass(frozen=True, slots=True)
class Load:
    """One reading of how well the executor keeps up, taken by the watchdog about every
    :data:`LOAD_WINDOW_S` while it watches (and once more as the shared lane goes idle).

    ``lag_ns``: how long work waits on the shared lane before its unit runs; ``busy``: the
    fraction of the last second the shared lane's thread was awake; ``cpu``: the process's CPU
    time over the window, in cores; ``lanes``/``max_lanes``: the lanes of the bound and the
    bound; ``stuck``: lanes whose thread has been in one callback for over the stall budget.
    """

    time_ns: int
    lag_ns: int
    busy: float
    cpu: float
    lanes: int
    max_lanes: int
    stuck: int


# ---------------------------------------------------------------------------- the executor


class Executor:
    """The lanes and threads of one manager.

    ``stall_budget_s``: how long one callback may hold the shared lane before the watchdog hands
    the lane to another thread. ``slow_callback_s``: a unit whose callbacks take longer than this on
    average (of their own time: see :func:`charged_ns`) moves off the shared lane. ``max_lanes``:
    the most lanes (so threads) it makes on its own (at least 2: the shared lane and one for slow
    units). ``on_load``: called with each :class:`Load` reading, on the watchdog's thread (it
    must return at once).
    """

    def __init__(
        self,
        name: str,
        *,
        stall_budget_s: float = 0.02,
        slow_callback_s: float = 0.002,
        max_lanes: int = DEFAULT_MAX_LANES,
        on_load: Callable[[Load], None] | None = None,
    ) -> None:
        if isinstance(max_lanes, bool) or not isinstance(max_lanes, int) or max_lanes < 2:
            raise ValueError(f"max_lanes: got {max_lanes!r}; expected a whole number of at least 2 (the shared lane and one for slow units)")
        self.name = name
        self.stall_budget_ns = int(stall_budget_s * 1e9)
        self.slow_callback_ns = int(slow_callback_s * 1e9)
        self.max_lanes = max_lanes
        self.on_load = on_load
        self._lock = threading.Lock()
        self._closed = False
        self._serial = itertools.count(1)
        self.shared = Lane(self, f"{name}-shared", SHARED)
        self._lanes: list[Lane] = [self.shared]  # the bounded ones: the shared lane and the slow ones
        self._dedicated: dict[int, Lane] = {}  # id(job) -> its own lane (outside the bound)
        self._leaving: list[Worker] = []  # threads of lanes that stopped, still inside a callback
        self._all_stuck_said = False
        Worker(self.shared).start()
        self._stop = threading.Event()
        self._poke = threading.Event()  # wakes a dozing watchdog (set by close, too)
        self.keep_measuring = False  # the watchdog never sleeps (it polls slowly when idle): load is being shed
        self.dozing = False  # the watchdog polls slowly: the shared lane was idle
        self.sleeping = False  # the watchdog waits to be woken: the shared lane sleeps, without timers
        self._watchdog = threading.Thread(target=self._watch, name=f"dyknow-{name}-watchdog", daemon=True)
        self._watchdog.start()

    # -- lanes

    def _slow_lane(self) -> Lane:
        return Lane(self, f"{self.name}-lane{next(self._serial)}", SLOW)

    def _bounded(self) -> int:
        """Lanes of the bound now, threads still inside a callback of a stopped lane included."""
        self._leaving = [w for w in self._leaving if w.thread.is_alive()]
        return len(self._lanes) + len(self._leaving)

    def lane_for(self, job: Job, *, dedicated: bool) -> Lane:
        """The lane a new job starts on: the shared one, or its own."""
        if self._closed:
            raise ClosedError("the executor is closed", where=f"manager {self.name!r}")
        with self._lock:
            if not dedicated:
                lane = self.shared
                lane.members[id(job)] = job
                return lane
            lane = Lane(self, f"{self.name}-{job.name}", DEDICATED)
            lane.members[id(job)] = job
            self._dedicated[id(job)] = lane
        Worker(lane).start()
        return lane

    def isolate(self, job: Job) -> Lane | None:
        """Move a job from the shared lane to a slow lane (from the job's own callback thread):
        a new one below the bound, the least busy one at it. None when it stays where it is."""
        if job.lane is not self.shared or self._closed:
            return None
        start = False
        with self._lock:
            if self._closed or job.lane is not self.shared or id(job) not in self.shared.members:
                return None  # (released meanwhile: destroyed)
            if self._bounded() < self.max_lanes:
                lane = self._slow_lane()
                self._lanes.append(lane)
                Worker(lane)
                start = True
            else:
                found = self._least_busy_slow(time.monotonic_ns(), free=False)
                if found is None:
                    return None
                lane = found
            self.shared.members.pop(id(job), None)
            lane.members[id(job)] = job
        if start:
            assert lane.worker is not None
            lane.worker.start()
        self._move(job, lane)
        return lane

    def _least_busy_slow(self, now_ns: int, *, free: bool) -> Lane | None:
        """The slow lane with the fewest units, then the least busy; ``free``: only those whose
        thread is not stuck in a callback. Prefers lanes whose thread is not stuck, and never
        takes a lane left to a unit stuck in a callback (:attr:`Lane.held`) while it is. Under the lock."""
        budget = self.stall_budget_ns
        best: Lane | None = None
        best_key: tuple[bool, int, float] | None = None
        for lane in self._lanes:
            if lane.kind != SLOW or lane.worker is None:
                continue
            if lane.held is not None and lane.worker.busy_job is lane.held and lane.worker.busy_since_ns:
                continue  # the callback that got stuck still runs (maybe for ever): a unit moved here would never run
            stuck = lane.stuck_ns() > budget
            if free and stuck:
                continue
            key = (stuck, len(lane.members), lane.busy(now_ns))
            if best_key is None or key < best_key:
                best, best_key = lane, key
        return best

    def _take_lane(self, job: Job, worker: Worker) -> Lane | None:
        """The lane the watchdog reserved for ``job`` and ``worker`` (the thread it got stuck on),
        now that its callback returned. None when the job is gone meanwhile (destroyed, or the
        executor closed): the lane goes and the thread ends."""
        lane = worker.next_lane
        worker.next_lane = None
        with self._lock:
            if lane is None or self._closed:
                return None
            gone = not getattr(job, "alive", True) or id(job) not in lane.members
            if gone:
                lane.members.pop(id(job), None)
                if not lane.members:  # (other slow units may have joined it meanwhile: then it serves them)
                    if lane in self._lanes:
                        self._lanes.remove(lane)
                    return None
        worker.lane = lane
        lane.worker = worker
        worker.thread.name = f"dyknow-{lane.name}"
        if not gone:
            self._move(job, lane)
        return lane

    def _move(self, job: Job, lane: Lane) -> None:
        old = job.lane
        for timer in old.take_timers_of(job):
            lane.add_timer(timer)
        job.lane = lane
        job.scheduled = True
        lane.put(job)  # run whatever arrived meanwhile

    def release(self, job: Job) -> None:
        """The job is gone: drop its timers and its place; a dedicated lane, or a slow lane left
        without units, stops."""
        stops: list[Lane] = []
        with self._lock:
            left: list[Lane] = []  # the lanes it was a member of
            for lane in self._lanes:
                if lane.members.pop(id(job), None) is not None:
                    left.append(lane)
                worker = lane.worker
                if worker is not None and worker.busy_job is job:  # (a worker names the last job it ran: not a gone one)
                    worker.busy_job = None
            dedicated = self._dedicated.pop(id(job), None)
            lane = dedicated if dedicated is not None else job.lane
            lane.members.pop(id(job), None)
            if lane.worker is not None and lane.worker.busy_job is job:
                lane.worker.busy_job = None
            if dedicated is not None:
                stops.append(dedicated)
            # its lane, and a slow lane it was being moved to (isolate() made it a member before
            # the job's lane was set): each slow lane left without units stops
            for slow in [lane, *left]:
                if slow.kind == SLOW and not slow.members and slow in self._lanes:
                    self._lanes.remove(slow)
                    stops.append(slow)
            for stop in stops:
                if stop.worker is not None and stop.worker.busy_since_ns and stop.kind == SLOW:
                    self._leaving.append(stop.worker)  # still inside a callback: it counts until it returns
        self.shared.take_timers_of(job)
        job.lane.take_timers_of(job)
        for stop in stops:
            stop.put(_STOP)

    def lanes(self) -> int:
        """How many lanes (so threads serving units) there are: the shared one, the slow ones and the dedicated ones."""
        with self._lock:
            return len(self._lanes) + len(self._dedicated)

    def threads(self) -> int:
        """The threads of the bound now: its lanes' and those still inside a callback of a stopped lane."""
        with self._lock:
            return self._bounded()

    def lane_infos(self) -> list[LaneInfo]:
        """Every lane: its kind, units, busy fraction, lag, queue and whether its thread is stuck."""
        now = time.monotonic_ns()
        with self._lock:
            lanes = [*self._lanes, *self._dedicated.values()]
            members = [list(lane.members.values()) for lane in lanes]
        infos = []
        for lane, jobs in zip(lanes, members, strict=True):
            names = () if lane.shared else tuple(sorted(job.name for job in jobs)[:_SHOWN_NAMES])
            infos.append(
                LaneInfo(lane.name, lane.kind, len(jobs), names, lane.busy(now), lane.lag(now) / 1e6, lane.ready.qsize(), lane.stuck_ns() / 1e6)
            )
        return infos

    def lane_of(self, job: Job) -> tuple[str, int]:
        """The kind of the job's lane and how many units it runs."""
        lane = job.lane
        return lane.kind, len(lane.members)

    def timers(self) -> int:
        """How many timers are scheduled on all lanes (cancelled ones leave at their next tick)."""
        with self._lock:
            lanes = [*self._lanes, *self._dedicated.values()]
        return sum(lane.timer_count() for lane in lanes)

    def add_timer(self, job: Job, period_s: float, callback: Callable[[], None], first_s: float | None = None) -> Timer:
        """A timer calling ``callback`` every ``period_s`` on the job's lane (first after ``first_s``, default one period)."""
        if period_s <= 0:
            raise ValueError(f"timer period must be positive; got {period_s!r} s")
        if first_s is not None and first_s < 0:
            raise ValueError(f"timer first delay must not be negative; got {first_s!r} s")
        timer = Timer(self, job, int(period_s * 1e9), callback, None if first_s is None else int(first_s * 1e9))
        job.lane.add_timer(timer)
        return timer

    # -- watchdog

    def wake_watchdog(self) -> None:
        """Work starts on the shared lane while the watchdog dozes: it polls at full rate again."""
        self.dozing = False
        self.sleeping = False
        self._poke.set()

    def _watch(self) -> None:
        """Hand the shared lane over when one callback really holds it for the stall budget.

        "Really": a thread the OS merely preempted (a loaded machine) is not the unit's fault and
        a new thread would not help, so a watchdog tick counts towards the budget only when the
        stuck thread either used CPU during it or is blocked (sleeping, waiting on I/O). And when
        the whole machine had no idle moment while the callback ran (overloaded), the budget is
        five times longer: a blocked thread may then just be waiting for the interpreter lock.
        Where the platform cannot tell, every tick counts. It also measures the load (see
        :class:`Load`) every :data:`LOAD_WINDOW_S` while it is awake.
        """
        interval_s = min(LOAD_WINDOW_S / 2, max(0.001, self.stall_budget_ns / 4e9))  # (a long budget: the load is still read)
        interval_ns = int(interval_s * 1e9)
        watched: tuple[int, object] | None = None
        job: Job | None = None  # (dropped before a long sleep: a job released meanwhile is not kept alive by this thread)
        evidence_ns = 0
        cpu_before = 0
        idle_before = 0.0
        load_at = (time.monotonic_ns(), time.process_time_ns())
        # While the lane stays idle the watchdog polls less and less often (up to 10 times a
        # second); once the lane's thread sleeps with no timer to fire, the watchdog sleeps too,
        # until that thread wakes (see Worker._serve). So an idle manager costs nothing.
        # Readings come at random moments between its polls, LOAD_WINDOW_S apart on average: at a
        # fixed pace they would fall at the same point of a periodic load every time (its polls
        # run when the lane's thread lets go of the interpreter lock, mostly as a callback
        # returns) and could read no lag for many seconds on a lane that is nearly always busy.
        pause_s = interval_s
        read_at = load_at[0] + _reading_gap_ns()  # when the next reading is due
        poll_at = 0  # when the next poll is due (0: from now, after pause_s)
        while True:
            shared = self.shared
            now = time.monotonic_ns()
            if poll_at == 0:
                poll_at = now + int(pause_s * 1e9)
                if pause_s >= _IDLE_POLL_S:
                    self.sleeping = True  # before reading the worker's state: see Worker._serve
                    worker = shared.worker
                    if worker is not None and not worker.active and shared.next_due_ns == _NEVER and not self.keep_measuring:
                        poll_at = _NEVER
                        watched = job = None
                        load_at = self._measure(load_at, final=True, probe=False)  # the last reading before it sleeps
                        read_at = load_at[0] + _reading_gap_ns()
                    else:
                        self.sleeping = False
            wake_at = poll_at if poll_at == _NEVER else min(poll_at, read_at)
            poked = self._poke.wait(None if wake_at == _NEVER else max(0.0, (wake_at - now) / 1e9))
            if poked:
                self._poke.clear()
                pause_s = interval_s
            self.sleeping = False
            if self._stop.is_set():
                return
            now = time.monotonic_ns()
            if now >= read_at:
                # The probe is timed from when the reading was due, not from when this thread got
                # to run: the wait for the interpreter lock (or a CPU) is paid by work as well.
                load_at = self._measure(load_at, final=False, probe=pause_s == interval_s or self.keep_measuring, due_ns=now if poked else read_at)
                read_at = load_at[0] + _reading_gap_ns()
            if not poked and now < poll_at:
                continue  # a reading between two polls: the next poll keeps its time
            poll_at = 0
            self.dozing = False
            shared = self.shared
            worker = shared.worker
            if worker is None:
                watched = job = None
                continue
            since, job = worker.busy_since_ns, worker.busy_job
            if not since or job is None:
                watched = job = None
                pause_s = min(_IDLE_POLL_S, pause_s * 2)
                self.dozing = pause_s > interval_s
                continue
            pause_s = interval_s
            cpu_now = worker.cpu_ns()
            if watched != (since, job):  # a new callback: start counting
                watched, evidence_ns, cpu_before, idle_before = (since, job), 0, cpu_now or 0, _machine_idle_s()
                continue
            working = cpu_now is None or cpu_now - cpu_before > interval_ns // 4 or worker.blocked()
            cpu_before = cpu_now or 0
            if working:
                evidence_ns += interval_ns
            budget = self.stall_budget_ns
            if evidence_ns >= budget and _machine_idle_s() <= idle_before:
                budget *= 5  # no idle moment since the callback began: the machine is overloaded
            if evidence_ns >= budget:
                self._hand_over(worker, job)
                watched = job = None

    def _measure(self, since: tuple[int, int], *, final: bool, probe: bool, due_ns: int = 0) -> tuple[int, int]:
        """Take a :class:`Load` reading, hand it to ``on_load``; ``probe``: send the next probe
        (only while the shared lane is busy, as a probe wakes its thread, or while load is shed:
        the guard then needs a fresh lag each time, not the last one again), timed from
        ``due_ns`` (when the reading was due; now if 0 or later)."""
        now, cpu = time.monotonic_ns(), time.process_time_ns()
        shared = self.shared
        with self._lock:
            lanes = self._bounded()
            stuck = sum(1 for lane in self._lanes if lane.stuck_ns() > self.stall_budget_ns)
        span = now - since[0]
        reading = Load(now, shared.lag(now), shared.busy(now), (cpu - since[1]) / span if span > 0 else 0.0, lanes, self.max_lanes, stuck)
        if probe and shared.probe is None:
            sent = _Probe(shared, min(due_ns, now) if due_ns else now)
            shared.probe = sent
            shared.put(sent)
        elif final:
            shared.lag_ns = 0  # idle: nothing waits
        listener = self.on_load
        if listener is not None:
            try:
                listener(reading)
            except Exception:
                log.exception("the load listener of manager %r failed", self.name)
        return now, cpu

    def _hand_over(self, stuck: Worker, job: Job) -> None:
        """The shared lane's thread is stuck in ``job``'s callback: below the bound, a fresh thread
        takes the shared lane and the stuck one stays with the job on a lane reserved for it; at
        the bound, the least busy slow lane whose thread is free becomes the shared lane, the
        other units of the stuck lane move there, and the stuck lane is left to the job."""
        now = time.monotonic_ns()
        moved: list[Job] = []
        with self._lock:
            old = self.shared
            if self._closed or old.worker is not stuck:
                return
            if self._bounded() < self.max_lanes:
                own = self._slow_lane()
                old.members.pop(id(job), None)
                own.members[id(job)] = job
                self._lanes.append(own)
                own.worker = stuck  # (its thread is stuck: no other unit is moved there before it returns)
                own.held = job
                stuck.next_lane = own
                stuck.stuck_job = job
                stuck.released = True
                fresh: Worker | None = Worker(old)
                target = old
            else:
                found = self._least_busy_slow(now, free=True)
                if found is None:
                    if not self._all_stuck_said:
                        self._all_stuck_said = True
                        log.warning(
                            "unit %r holds the shared thread of manager %r, and every other lane's thread is stuck too: with %d lanes, "
                            "its most (max_lanes, --max-lanes), no thread is left to run the other units until one returns",
                            job.name,
                            self.name,
                            self.max_lanes,
                        )
                    return
                target = found
                fresh = None
                old.kind, old.shared = SLOW, False
                target.kind, target.shared = SHARED, True
                for key, member in old.members.items():
                    if member is not job:
                        target.members[key] = member
                        moved.append(member)
                old.members = {id(job): job}
                old.held = job
                target.probe = None
                self.shared = target
        self._all_stuck_said = False
        log.warning(
            "unit %r held the shared thread of manager %r for over %.0f ms; %s",
            job.name,
            self.name,
            self.stall_budget_ns / 1e6,
            "it now runs on a thread of its own" if fresh is not None else f"the other units moved to lane {target.name!r} (at the bound of {self.max_lanes} lanes)",
        )
        mark = getattr(job, "on_isolated", None)
        if mark is not None:
            mark(f"a callback held the shared thread for over {self.stall_budget_ns / 1e6:.0f} ms")
        if fresh is not None:
            fresh.start()
            return
        for timer in old.take_timers_except(job):
            target.add_timer(timer)
        for member in moved:
            member.lane = target
            member.scheduled = True
            target.put(member)

    # -- lifecycle

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop every lane and join their threads (bounded by ``timeout_s``); safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            lanes = [*self._lanes, *self._dedicated.values()]
            workers = [lane.worker for lane in lanes] + self._leaving
            self._dedicated.clear()
        self._stop.set()
        self._poke.set()
        for lane in lanes:
            lane.put(_STOP)
        deadline = time.monotonic() + timeout_s
        for worker in workers:
            if worker is not None and worker.thread is not threading.current_thread() and worker.thread.ident is not None:
                worker.thread.join(max(0.0, deadline - time.monotonic()))
                if worker.thread.is_alive():
                    log.warning("thread %s did not stop within %.1f s; leaving it", worker.thread.name, timeout_s)
        self._watchdog.join(max(0.0, deadline - time.monotonic()))
