"""The executor: the threads that run the callbacks of a manager's units.

Why it looks like this: handing a message from one Python thread to another costs 20-40 µs on a
small machine, far more than the rest of a hop. So the units of a manager share one *lane*, a
ready queue served by one thread that runs each unit's pending callbacks back to back: a message
that flows through a chain of fast units never changes thread, and a hop costs a few microseconds.

Isolation still holds, by two rules:

1. A unit whose callbacks are slow (moving average above ``slow_callback_s``) is moved to a lane
   of its own, with its own thread, as soon as that callback returns.
2. A watchdog thread notices a callback that has held the shared lane for longer than
   ``stall_budget_s`` and hands the shared lane to a fresh thread at once; when the slow callback
   finally returns, its thread stays with that unit as the unit's own lane.

So a slow unit delays the others (its upstream among them) at most once, by about the stall
budget, and never again (an idle watchdog polls slowly, then sleeps; the shared lane wakes it when work
arrives). Units that declare ``dedicated_thread = True`` get their own lane from
the start. A unit's callbacks never run concurrently: each job carries a lock and runs on one
thread at a time.

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
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Final, Protocol

from dyknow.errors import ClosedError

__all__ = ["Executor", "Job", "Lane", "Timer", "Worker"]

log = logging.getLogger(__name__)

_STOP: Final = object()
_WAKE: Final = object()
_NEVER: Final = 1 << 62  # next_due_ns of a lane without timers
_IDLE_POLL_S = 0.1  # the watchdog's slowest poll; past it, it sleeps until the shared lane wakes


class Job(Protocol):
    """What the executor schedules: one unit's inputs, timers and control calls."""

    lane: Lane
    scheduled: bool
    name: str

    def run(self, worker: Worker) -> None:
        """Handle what is pending for the job."""
        ...

    def run_timer(self, timer: Timer, worker: Worker) -> None:
        """Fire one tick of ``timer``."""
        ...


class Timer:
    """A periodic timer whose callback runs on its job's lane. ``cancel()`` stops it."""

    __slots__ = ("_executor", "callback", "cancelled", "job", "next_ns", "overruns", "period_ns")

    def __init__(self, executor: Executor, job: Job, period_ns: int, callback: Callable[[], None], first_ns: int | None = None) -> None:
        self._executor = executor
        self.job = job
        self.period_ns = period_ns
        self.callback = callback
        self.next_ns = time.monotonic_ns() + (period_ns if first_ns is None else first_ns)
        self.cancelled = False
        self.overruns = 0

    def cancel(self) -> None:
        """Stop the timer; safe twice, from any thread."""
        self.cancelled = True


class Lane:
    """A ready queue and a timer heap, served by one worker thread at a time."""

    def __init__(self, executor: Executor, name: str, shared: bool) -> None:
        self.executor = executor
        self.name = name
        self.shared = shared
        self.ready: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.put = self.ready.put
        self._timers: list[tuple[int, int, Timer]] = []
        self._timer_lock = threading.Lock()
        self.next_due_ns = _NEVER  # when the earliest timer is due (monotonic clock)
        self.worker: Worker | None = None

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
            if job_lane is not self:  # its unit moved to a lane of its own
                job_lane.add_timer(timer)
                continue
            timer.job.run_timer(timer, worker)
            if timer.cancelled:
                continue
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


_tie = itertools.count()


class Worker:
    """A thread serving one lane. ``busy_since_ns``/``busy_job`` tell the watchdog what it runs."""

    def __init__(self, lane: Lane) -> None:
        self.lane = lane
        self.busy_since_ns = 0
        self.busy_job: Job | None = None
        self.released = False  # set by the watchdog: our lane went to another thread
        self.stuck_job: Job | None = None  # the job whose callback we were stuck in
        self.active = True  # False while the thread sleeps waiting for work or a timer
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
                due = lane.next_due_ns
                self.active = False  # about to sleep
                try:
                    if due == _NEVER:
                        job = get()
                    else:
                        wait = (due - monotonic_ns()) / 1e9
                        job = get(timeout=wait) if wait > 0 else None
                except queue.Empty:
                    job = None
                yielded_ns = monotonic_ns()
                # Awake (work, a timer, or a new timer to wait for). A watchdog asleep until
                # the shared lane wakes watches from now. ``active`` is set before the check and
                # the watchdog sets ``sleeping`` before it reads ``active``: one sees the other.
                self.active = True
                if executor.sleeping and lane.shared:
                    executor.wake_watchdog()
            if job is _STOP:
                return
            if lane.next_due_ns <= monotonic_ns():
                lane.fire_due(self)
            if job is None or job is _WAKE:
                pass
            elif job.lane is not lane:  # moved to a lane of its own while queued here
                job.lane.put(job)
            else:
                if executor.dozing and lane.shared:  # the watchdog polls slowly: it watches from now
                    executor.wake_watchdog()
                job.run(self)
            if self.released:
                stuck, self.stuck_job, self.released = self.stuck_job, None, False
                own = lane.executor._own_lane(stuck, self) if stuck is not None else None
                if own is None:
                    return
                lane = own
                get, get_nowait = lane.ready.get, lane.ready.get_nowait


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


class Executor:
    """The lanes and threads of one manager.

    ``stall_budget_s``: how long one callback may hold the shared lane before the watchdog hands
    the lane to a new thread. ``slow_callback_s``: a unit whose callbacks take longer than this on
    average moves to a lane of its own.
    """

    def __init__(self, name: str, *, stall_budget_s: float = 0.02, slow_callback_s: float = 0.002) -> None:
        self.name = name
        self.stall_budget_ns = int(stall_budget_s * 1e9)
        self.slow_callback_ns = int(slow_callback_s * 1e9)
        self._lock = threading.Lock()
        self._closed = False
        self._own: dict[int, Lane] = {}  # id(job) -> its own lane
        self.shared = Lane(self, f"{name}-shared", shared=True)
        Worker(self.shared).start()
        self._stop = threading.Event()
        self._poke = threading.Event()  # wakes a dozing watchdog (set by close, too)
        self.dozing = False  # the watchdog polls slowly: the shared lane was idle
        self.sleeping = False  # the watchdog waits to be woken: the shared lane sleeps, without timers
        self._watchdog = threading.Thread(target=self._watch, name=f"dyknow-{name}-watchdog", daemon=True)
        self._watchdog.start()

    # -- lanes

    def lane_for(self, job: Job, *, dedicated: bool) -> Lane:
        """The lane a new job starts on: the shared one, or its own."""
        if self._closed:
            raise ClosedError("the executor is closed", where=f"manager {self.name!r}")
        if not dedicated:
            return self.shared
        with self._lock:
            lane = Lane(self, f"{self.name}-{job.name}", shared=False)
            self._own[id(job)] = lane
        Worker(lane).start()
        return lane

    def isolate(self, job: Job) -> None:
        """Move a job from the shared lane to a lane of its own (from the job's own callback thread)."""
        if job.lane is not self.shared or self._closed:
            return
        with self._lock:
            lane = Lane(self, f"{self.name}-{job.name}", shared=False)
            self._own[id(job)] = lane
        Worker(lane).start()
        self._move(job, lane)

    def _own_lane(self, job: Job, worker: Worker) -> Lane | None:
        """Give ``job`` a lane of its own served by ``worker`` (the thread it got stuck on).

        None when the job is gone meanwhile (destroyed, or the executor closed): the thread ends.
        """
        with self._lock:
            if self._closed or not getattr(job, "alive", True):
                return None
            lane = Lane(self, f"{self.name}-{job.name}", shared=False)
            self._own[id(job)] = lane
        worker.lane = lane
        lane.worker = worker
        worker.thread.name = f"dyknow-{lane.name}"
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
        """The job is gone: stop its own lane, if it had one, and drop its timers."""
        self.shared.take_timers_of(job)
        with self._lock:
            lane = self._own.pop(id(job), None)
        if lane is not None:
            lane.take_timers_of(job)
            lane.put(_STOP)

    def lanes(self) -> int:
        """How many lanes (so threads serving units) there are: the shared one and the units' own."""
        with self._lock:
            return 1 + len(self._own)

    def timers(self) -> int:
        """How many timers are scheduled on all lanes (cancelled ones leave at their next tick)."""
        with self._lock:
            lanes = [self.shared, *self._own.values()]
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
        Where the platform cannot tell, every tick counts.
        """
        interval_s = max(0.001, self.stall_budget_ns / 4e9)
        interval_ns = int(interval_s * 1e9)
        watched: tuple[int, object] | None = None
        evidence_ns = 0
        cpu_before = 0
        idle_before = 0.0
        # While the lane stays idle the watchdog polls less and less often (up to 10 times a
        # second); once the lane's thread sleeps with no timer to fire, the watchdog sleeps too,
        # until that thread wakes (see Worker._serve). So an idle manager costs nothing.
        pause_s = interval_s
        shared = self.shared
        while True:
            timeout_s: float | None = pause_s
            if pause_s >= _IDLE_POLL_S:
                self.sleeping = True  # before reading the worker's state: see Worker._serve
                worker = shared.worker
                if worker is not None and not worker.active and shared.next_due_ns == _NEVER:
                    timeout_s = None
                else:
                    self.sleeping = False
            if self._poke.wait(timeout_s):
                self._poke.clear()
                pause_s = interval_s
            self.sleeping = False
            if self._stop.is_set():
                return
            self.dozing = False
            worker = shared.worker
            if worker is None:
                continue
            since, job = worker.busy_since_ns, worker.busy_job
            if not since or job is None:
                watched = None
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
                watched = None
                self._hand_over(worker, job)

    def _hand_over(self, stuck: Worker, job: Job) -> None:
        with self._lock:
            if self._closed or self.shared.worker is not stuck:
                return
            stuck.stuck_job = job
            stuck.released = True
            fresh = Worker(self.shared)
        log.warning(
            "unit %r held the shared thread of manager %r for over %.0f ms; it now runs on its own thread",
            job.name,
            self.name,
            self.stall_budget_ns / 1e6,
        )
        mark = getattr(job, "on_isolated", None)
        if mark is not None:
            mark(f"a callback held the shared thread for over {self.stall_budget_ns / 1e6:.0f} ms")
        fresh.start()

    # -- lifecycle

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop every lane and join their threads (bounded by ``timeout_s``); safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            lanes = [self.shared, *self._own.values()]
            self._own.clear()
        self._stop.set()
        self._poke.set()
        for lane in lanes:
            lane.put(_STOP)
        deadline = time.monotonic() + timeout_s
        for lane in lanes:
            worker = lane.worker
            if worker is not None and worker.thread is not threading.current_thread():
                worker.thread.join(max(0.0, deadline - time.monotonic()))
                if worker.thread.is_alive():
                    log.warning("thread %s did not stop within %.1f s; leaving it", worker.thread.name, timeout_s)
        self._watchdog.join(max(0.0, deadline - time.monotonic()))
