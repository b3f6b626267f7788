"""A unit's executor job: its callbacks run under its lock, on its lane or inline, timed, moved when slow, shed.

One job per running unit, the unit's side of :mod:`dyknow.executor`: the executor puts it on a
lane and a lane's thread runs it (:meth:`UnitJob.run`: control calls, then the messages its input
ports queued, a batch at a time). A unit proven quick and free runs on the thread that delivers
a message instead (Zenoh's receiving thread, or the thread of the local unit that published it),
with no hand-off. Each callback runs under the unit's lock and is timed: a unit whose callbacks
turn slow, by their own time, moves off the shared lane. A unit that sets ``forward_to`` runs no
Python per message: its job publishes what arrives itself. Under load the manager sheds the
least important units (``shed``). Everything a unit publishes leaves through :meth:`UnitJob.publish`.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Final, cast

import numpy as np

from dyknow.errors import UnitError
from dyknow.executor import charged_ns, cpu_mark
from dyknow.message import CLOCK_ID, MAX_FORWARDS, Message, check_payload, payload_nbytes, reheader
from dyknow.proxy.ports import InputPort, OutputPort, arrived, no_port

if TYPE_CHECKING:
    from dyknow.executor import Executor, Lane, Timer, Worker
    from dyknow.unit import Unit

__all__ = ["UnitJob", "UnitState"]

log = logging.getLogger(__name__)

# The names the message path uses are Final: compiled (see setup.py), a Final name is a C constant
# rather than a lookup in the module's dictionary on every message.
time_ns: Final = time.time_ns
get_ident: Final = threading.get_ident

# How many messages one run of a unit handles before it yields the lane to the others.
_BATCH: Final = 64


class UnitState(enum.StrEnum):
    """Lifecycle of a unit: starting -> running -> (failed) -> stopped."""

    STARTING = "starting"
    RUNNING = "running"
    FAILED = "failed"
    STOPPED = "stopped"


# Aliases for the message path: a constant rather than an enum class attribute looked up each time.
_RUNNING: Final = UnitState.RUNNING
_STOPPED: Final = UnitState.STOPPED
_FAILED: Final = UnitState.FAILED

# A unit runs on Zenoh's receiving thread once it has handled this many messages on the port and
# its callbacks average under _INLINE_BUDGET_NS, on the shared lane (not isolated).
_PROVEN: Final = 8
_INLINE_BUDGET_NS: Final = 200_000
# At most this many units run nested on one thread (a chain of local units handing on inline);
# the next one is queued for its lane, which starts over: the stack stays shallow.
_MAX_DEPTH: Final = 64
# A unit whose callbacks average over the slow line is probed this many callbacks (their own
# time measured: dyknow.executor.charged_ns) before it moves; a probe that finds 5 times the
# line decides at once.
_PROBES: Final = 3
_NO_MARK: Final = (0, 0, 0, 0)


class UnitJob:
    """What the executor runs for one unit: its callbacks, under its lock, on its lane or inline.

    Its :class:`~dyknow.proxy.Proxy` makes it, and gives it the unit's ports (:attr:`inputs`,
    :attr:`outputs`), its lane and its :attr:`state`. ``fail(exc, where)`` marks the unit failed
    (a callback raised); ``destroy()`` destroys it (the unit asked to be).
    """

    lane: Lane  # the lane that runs it (set by its proxy, then moved by the executor)

    def __init__(
        self, name: str, unit: Unit, executor: Executor, *, fail: Callable[[BaseException, str], None], destroy: Callable[[], None] | None
    ) -> None:
        self.name = name
        self.unit = unit
        self.state = UnitState.STARTING
        self.inputs: tuple[InputPort, ...] = ()  # the unit's ports, set by its proxy
        self.outputs: dict[str, OutputPort] = {}
        self._executor = executor
        self._slow_ns = executor.slow_callback_ns
        self._fail_unit = fail
        self._destroy_unit = destroy
        self._isolation: str | None = None  # see the isolation property
        self.scheduled = False
        self._arrival = 0  # the messages queued so far, over all the inputs (their order: _drain)
        self._lock = threading.Lock()  # held while one of the unit's callbacks runs
        self._calls: deque[tuple[Callable[[], None], str]] = deque()  # control calls for the unit's lane
        self._current: Message | None = None
        self._current_thread = 0
        self.ewma_ns = 0  # moving average of the unit's callback times
        self._probe_left = 0  # callbacks still to probe for their own time before it may move
        self._probe_sum = 0  # the own time of the callbacks probed so far, and how many
        self._probe_n = 0
        self.excused = 0  # times its callbacks were slow by the clock only
        # Load shedding (set by the manager's overload guard, dyknow.overload): 0 runs at full
        # rate; k > 1 lets one message in k through on each input, and one timer tick in k;
        # -1 pauses it (nothing delivered, no ticks). What it sheds is counted per port.
        self.shed = 0
        self._shed_n = 0
        # time spent in the current callback by units it ran inline (they count as their own)
        self._child_ns = 0
        self.inline_depth = 0  # while it runs inline: how many units run nested on the thread
        self._inline_ns = _INLINE_BUDGET_NS  # -1 once isolated: never on Zenoh's thread again
        self._destroy_requested = False
        self._setup_done = False

    # ------------------------------------------------------------------ state

    @property
    def isolation(self) -> str | None:
        """Why the unit got a thread of its own, if it did (it then never leaves it)."""
        return self._isolation

    @isolation.setter
    def isolation(self, reason: str | None) -> None:
        # Every move off the shared lane sets a reason (the executor tells on_isolated()); a unit
        # off the shared lane never runs on Zenoh's receiving thread (see run_inline).
        self._isolation = reason
        self._inline_ns = _INLINE_BUDGET_NS if reason is None else -1

    @property
    def alive(self) -> bool:
        """Whether the unit is starting or running."""
        return self.state in (UnitState.STARTING, UnitState.RUNNING)

    def on_isolated(self, reason: str) -> None:
        """Told by the executor that the unit now has a thread of its own, and why."""
        self.isolation = reason

    def setup(self, setup: Callable[[], None]) -> bool:
        """Run the unit's ``setup`` under its lock, its first callback; False when it raised (the
        unit failed). Control calls queued meanwhile are then scheduled."""
        with self._lock:
            self._current_thread = get_ident()
            try:
                setup()
            except (Exception, SystemExit) as exc:
                self._fail_unit(exc, "setup()")
                return False
            finally:
                self._current_thread = 0
            self._setup_done = True
        if self._calls and not self.scheduled:  # queued while setup() held the lock (say, a rebinding)
            self.scheduled = True
            self.lane.put(self)
        return True

    def teardown(self, teardown: Callable[[], None], timeout_s: float) -> None:
        """Run the unit's ``teardown`` under its lock if its setup ran, once the callback in flight
        returned (waiting up to ``timeout_s``)."""
        # Wait for a callback in flight (bounded: a stuck unit must not hang its manager).
        got = self._lock.acquire(timeout=timeout_s) if self._current_thread != get_ident() else False
        try:
            if self._setup_done:
                self._setup_done = False
                teardown()
        finally:
            if got:
                self._lock.release()

    def request_destroy(self) -> None:
        """Destroy the unit: after its current callback returns when asked from it, else at once."""
        if self._current_thread == get_ident():
            self._destroy_requested = True
        elif self._destroy_unit is not None:
            self._destroy_unit()

    # ------------------------------------------------------------------ delivering

    def deliver_remote(self, port: InputPort, msg: Message) -> None:
        """A message from another process, on Zenoh's receiving thread: run a unit proven quick
        and free right here (no thread hand-off), queue it for the unit's lane otherwise."""
        port.track(msg.source, msg.seq)
        if self.shed and self.shedding(port):
            return
        if port.forward is not None:
            if port.queue or not self.forward_now(port, msg, None):
                self.deliver(port, msg)
        elif port.queue or not self.run_inline(port, msg, None):
            self.deliver(port, msg)

    def deliver_local(self, port: InputPort, msg: Message, publisher: UnitJob) -> None:
        """A message from a unit of this manager, on the publisher's thread: run a unit proven
        quick and free right here, depth-first like a function call (no queue, no lane), queue
        it otherwise or when ``_MAX_DEPTH`` units already run nested on this thread."""
        if self.shed and self.shedding(port):
            return
        if port.queue or publisher.inline_depth >= _MAX_DEPTH:
            self.deliver(port, msg)
        elif port.forward is not None:
            if not self.forward_now(port, msg, publisher):
                self.deliver(port, msg)
        elif not self.run_inline(port, msg, publisher):
            self.deliver(port, msg)

    def deliver(self, port: InputPort, msg: Message) -> None:
        """Queue ``msg`` on ``port`` and make sure the unit will run. Any thread; never blocks."""
        self._arrival += 1
        if port.push(msg, self._arrival) and not self.scheduled:
            self.scheduled = True
            self.lane.put(self)

    # ------------------------------------------------------------------ executor job

    def run(self, worker: Worker) -> None:
        """Handle what is pending: control calls, then messages (a batch, then yield the lane)."""
        self.scheduled = False
        if not self._lock.acquire(False):
            return  # running on another thread right now; it drains before releasing, or reschedules
        self.run_locked(worker)

    def _release(self) -> None:
        """Release the lock an inline run took; a message queued meanwhile (its lane found the
        unit busy, and left it to whoever held the lock) is scheduled again, or it would wait
        for the next message."""
        self._lock.release()
        if self.scheduled:
            return
        if self._calls or self._queued():
            self.scheduled = True
            self.lane.put(self)

    def _queued(self) -> bool:
        """Whether a message waits for the lane in any input port's queue: a message run on the
        caller's thread now would overtake it (a unit reading several streams, such as a formula
        monitor, would see them out of their arrival order, by as much as its lane is starved)."""
        for port in self.inputs:
            if port.queue:
                return True
        return False

    def run_inline(self, port: InputPort, msg: Message, publisher: UnitJob | None) -> bool:
        """Handle ``msg`` on the calling thread (Zenoh's receiving thread, or the thread of the
        local ``publisher`` that sent it) when the unit is proven quick (``_PROVEN`` messages on
        the port, callbacks averaging under ``_INLINE_BUDGET_NS``, on the shared lane), running,
        free and has nothing pending; False when it is not (the caller queues the message for the
        lane). This saves a thread hand-off per message from another process (the lane's thread
        would need the interpreter lock the receiving thread just held), and a trip through the
        lane per local hop. A unit that turns slow here holds its caller up once: its average then
        rules it out, and it moves to a thread of its own. A unit never proven quick (a slow first
        callback) never runs here. The time it takes is its own, not the publisher's.
        """
        if self.ewma_ns >= self._inline_ns or port.counters.messages < _PROVEN or self._calls or self._queued():
            return False
        if not self._lock.acquire(False):
            return False
        if self.state is not _RUNNING:
            self._lock.release()
            return False
        now = time_ns()
        self._current = msg
        self._current_thread = get_ident()
        self._child_ns = 0
        self.inline_depth = publisher.inline_depth + 1 if publisher is not None else 1
        probing = self._probe_left
        mark = cpu_mark() if probing else _NO_MARK
        try:
            self.unit.on_message(port.name, msg)
        except (Exception, SystemExit) as exc:
            self._current = None
            self._fail_unit(exc, f"on_message({port.name!r})")
        finally:
            self._current = None
            self._current_thread = 0
            self.inline_depth = 0
            self._release()
        # bookkeeping after the callback, off the path of what the unit published
        arrived(port.counters, msg.nbytes, now, msg.origin_ns, msg.origin_clock, msg.send_ns, msg.send_clock)
        took = time_ns() - now
        self.ewma_ns += (took - self._child_ns - self.ewma_ns) >> 3
        if probing:
            self._probed(charged_ns(mark) - self._child_ns)
        if publisher is not None:
            publisher._child_ns += took
        if self._destroy_requested or self.ewma_ns > self._slow_ns:
            self._after_callbacks()
        return True

    def forward_now(self, port: InputPort, msg: Message, publisher: UnitJob | None) -> bool:
        """Publish ``msg`` on the port's ``forward`` output on the calling thread (the unit's
        ``forward_to``: no callback of the unit runs). Under the unit's lock like a callback, so
        it never runs beside one; False when the unit is busy, has control calls pending or is
        not running (the caller queues the message for the lane, which forwards it in turn)."""
        if self._calls or self._queued() or not self._lock.acquire(False):
            return False
        if self.state is not _RUNNING:
            self._lock.release()
            return False
        self.inline_depth = publisher.inline_depth + 1 if publisher is not None else 1
        now = time_ns()
        try:
            self._forward(port, msg, now)
        except Exception as exc:
            self._fail_unit(exc, f"forwarding {port.name!r}")
        finally:
            self.inline_depth = 0
            self._release()
        arrived(port.counters, msg.nbytes, now, msg.origin_ns, msg.origin_clock, msg.send_ns, msg.send_clock)
        return True

    def forward_wire(self, port: InputPort, data: Any, header: bytes) -> bool:
        """:meth:`forward_now` for a message from another process that was not decoded: its
        payload buffer goes out again under a rewritten header (``data`` and ``header`` as the
        transport received them). Only raw bytes, only to Zenoh: False when the output has local
        readers (they need a :class:`Message`), the payload is of another kind (decoding checks
        it first), or the unit cannot forward right now or sheds its load; the caller then decodes
        and delivers."""
        out = port.forward
        if out is None or self.shed or out.targets or self._calls or self._queued() or not self._lock.acquire(False):
            return False
        try:
            if self.state is not _RUNNING:
                return False
            now = time_ns()
            wire = reheader(header, out.seq + 1, now, out.source)
            if wire is None:
                return False
            attachment, origin_ns, origin_clock, sent_ns, sent_clock, sender, sender_seq, encoding, forwards = wire
            port.track(sender, sender_seq)
            if forwards >= MAX_FORWARDS:
                self._looped(port)
                return True
            out.seq += 1
            nbytes = len(data)
            publisher = out.publisher
            if publisher is not None and publisher.matched:
                publisher.put_wire(data, attachment, encoding)
            counters = out.counters
            counters.messages += 1
            counters.bytes += nbytes
        except Exception as exc:
            self._fail_unit(exc, f"forwarding {port.name!r}")
            return True  # taken, and counted as the unit's failure
        finally:
            self._release()
        arrived(port.counters, nbytes, now, origin_ns, origin_clock, sent_ns, sent_clock)
        return True

    def _forward(self, port: InputPort, msg: Message, now: int) -> None:
        """Send ``msg`` on as it came (payload, origin, wire form) from the port's ``forward`` output,
        unless :data:`~dyknow.message.MAX_FORWARDS` forwarding units passed it on already."""
        out = port.forward
        assert out is not None
        if msg.forwards >= MAX_FORWARDS:
            self._looped(port)
            return
        out.seq += 1
        self._send(
            out, Message(msg.payload, out.seq, msg.origin_ns, now, out.key, msg.nbytes, msg.wire, out.source, msg.origin_clock, CLOCK_ID, msg.forwards + 1)
        )

    def _looped(self, port: InputPort) -> None:
        """A message to forward that went through too many forwarding units: dropped, said why."""
        port.reject(
            self.name,
            f"a message already passed on by {MAX_FORWARDS} forwarding units was dropped: forwarding units (relays) are bound "
            "into a cycle, probably across managers (each relays the other's output); rebind one of them",
        )

    def run_locked(self, worker: Worker) -> None:
        """``run`` once the unit's lock is held; releases it."""
        lock = self._lock
        try:
            while self._calls:
                fn, where = self._calls.popleft()
                self._call(fn, worker, where)
            if self.state is UnitState.RUNNING:
                # a callback run from the lane is the first unit nested on its thread: what it
                # publishes runs inline at most _MAX_DEPTH - 1 deeper
                self.inline_depth = 1
                self._drain(worker)
        finally:
            self.inline_depth = 0
            lock.release()
        if self._destroy_requested or (self.lane.shared and self.ewma_ns > self._slow_ns):
            self._after_callbacks()

    def _drain(self, worker: Worker) -> None:
        """Hand the queued messages to the unit, in the order they came over all its inputs
        (the earliest arrival first: a unit reading several streams sees them as they came, not
        port by port), a batch at a time."""
        on_message = self.unit.on_message
        ports = self.inputs
        single = len(ports) == 1
        ident = get_ident()
        budget = _BATCH
        while True:
            port: InputPort | None = None
            if single:
                port = ports[0] if ports[0].queue else None
            else:
                first = 0
                for candidate in ports:
                    queued = candidate.queue
                    if queued and (port is None or queued[0][0] < first):
                        port, first = candidate, queued[0][0]
            if port is None:
                return
            msg = port.queue.popleft()[1]
            now = time_ns()
            arrived(port.counters, msg.nbytes, now, msg.origin_ns, msg.origin_clock, msg.send_ns, msg.send_clock)
            self._current = msg
            self._current_thread = ident
            worker.busy_job = self
            worker.busy_since_ns = now
            self._child_ns = 0
            probing = self._probe_left
            mark = cpu_mark() if probing else _NO_MARK
            try:
                if port.forward is None:
                    on_message(port.name, msg)
                else:
                    self._forward(port, msg, now)
            except (Exception, SystemExit) as exc:
                worker.busy_since_ns = 0
                self._current = None
                self._fail_unit(exc, f"on_message({port.name!r})" if port.forward is None else f"forwarding {port.name!r}")
                return
            worker.busy_since_ns = 0
            self._current = None
            self._current_thread = 0
            self.ewma_ns += (time_ns() - now - self._child_ns - self.ewma_ns) >> 3
            if probing:
                self._probed(charged_ns(mark) - self._child_ns)
            if self.state is not _RUNNING or self._destroy_requested:
                return
            budget -= 1
            if budget <= 0:
                if self._queued():  # let the other units of the lane run, then continue
                    self.scheduled = True
                    self.lane.put(self)
                return

    def run_timer(self, timer: Timer, worker: Worker) -> bool:
        """Fire one timer tick under the unit's lock; False when the unit was busy on another
        thread (the tick skipped; a first tick is tried again shortly: ``dyknow.executor.Lane.fire_due``)."""
        if self.shed and self._skip_tick():
            return True
        if not self._lock.acquire(False):
            return False  # the unit is busy on another thread: skip this tick
        try:
            state = self.state
            if state is _STOPPED or state is _FAILED:
                timer.cancel()
                return True
            # STARTING: setup() is done (it ran under this lock), the inputs are being bound: tick
            self._call(timer.callback, worker, "a timer callback")
        finally:
            self._release()
        self._after_callbacks()
        return True

    def _call(self, fn: Callable[[], None], worker: Worker, where: str) -> None:
        self._current = None
        self._current_thread = get_ident()
        worker.busy_job = self
        t0 = time_ns()
        worker.busy_since_ns = t0
        self._child_ns = 0
        self.inline_depth = 1  # as in run_locked: the first unit nested on the lane's thread
        probing = self._probe_left
        mark = cpu_mark() if probing else _NO_MARK
        try:
            fn()
        except (Exception, SystemExit) as exc:
            self._fail_unit(exc, where)
        finally:
            worker.busy_since_ns = 0
            self._current_thread = 0
            self.inline_depth = 0
        self.ewma_ns += (time_ns() - t0 - self._child_ns - self.ewma_ns) >> 3
        if probing:
            self._probed(charged_ns(mark) - self._child_ns)

    def _probed(self, own_ns: int) -> None:
        """One probed callback took ``own_ns`` of its own time (see :meth:`_after_callbacks`)."""
        self._probe_sum += own_ns if own_ns > 0 else 0
        self._probe_n += 1
        self._probe_left -= 1
        if own_ns >= 5 * self._slow_ns:
            self._probe_left = 0  # clearly slow: no need to wait for more

    def shedding(self, port: InputPort) -> bool:
        """Whether the message just arriving on ``port`` is shed (see ``shed``); counts it."""
        shed = self.shed
        if shed > 0:
            self._shed_n += 1
            if self._shed_n % shed == 0:
                return False
        elif shed == 0:
            return False
        port.counters.shed += 1
        return True

    def _skip_tick(self) -> bool:
        shed = self.shed
        if shed > 0:
            self._shed_n += 1
            return self._shed_n % shed != 0
        return shed < 0

    def _after_callbacks(self) -> None:
        if self._destroy_requested:
            self._destroy_requested = False
            if self._destroy_unit is not None:
                self._destroy_unit()
            return
        lane = self.lane
        if lane.shared and self.ewma_ns > self._slow_ns and self.alive:
            # Slow by the clock: probe its next callbacks for their own time before moving it
            # (a callback is slow by the clock alone when the CPU was taken away from it).
            if self._probe_n == 0:
                if self._probe_left == 0:
                    self._probe_left = _PROBES
                return
            if self._probe_left > 0:
                return
            own = self._probe_sum // self._probe_n
            self._probe_sum = self._probe_n = 0
            if own <= self._slow_ns:
                self.excused += 1
                log.debug("unit %r: slow by the clock (%.1f ms) but not by its own time (%.2f ms): it stays", self.name, self.ewma_ns / 1e6, own / 1e6)
                self.ewma_ns = own
                return
            self.isolation = f"its callbacks take {self.ewma_ns / 1e6:.1f} ms on average, {own / 1e6:.1f} ms of it their own"
            if self._executor.isolate(self) is None:
                self.isolation = None  # no lane to move to: it stays on the shared lane
                self.ewma_ns = own
                return
            log.info("unit %r moves off the shared thread: %s", self.name, self.isolation)

    def call_soon(self, fn: Callable[[], None], where: str) -> None:
        """Run ``fn`` on the unit's lane, under its lock, before its next messages (any thread)."""
        self._calls.append((fn, where))
        if not self.scheduled:
            self.scheduled = True
            self.lane.put(self)

    # ------------------------------------------------------------------ publishing

    def publish(self, port: str, payload: Any, origin_ns: int | None = None) -> None:
        """Send ``payload`` from output ``port`` to local inputs (by reference) and to Zenoh."""
        out = self.outputs.get(port)
        if out is None:
            raise no_port(self.name, port, "output", self.outputs)
        state = self.state
        if state is _STOPPED or state is _FAILED:
            raise UnitError(f"the unit is {self.state.value}, so it can no longer publish", where=f"unit {self.name!r}")
        now = time_ns()
        wire = None
        origin_clock = CLOCK_ID
        current = self._current
        if current is not None and self._current_thread == get_ident():
            if origin_ns is None:
                origin_ns = current.origin_ns
                origin_clock = current.origin_clock
            if payload is current.payload:
                wire = current.wire  # forwarding a payload received from Zenoh: reuse its encoding
        elif origin_ns is None:
            origin_ns = now
        kind = type(payload)
        if kind is bytes:
            nbytes = len(payload)
        elif kind is np.ndarray or isinstance(payload, np.ndarray):
            payload.flags.writeable = False  # receivers share this very array
            nbytes = payload.nbytes
        else:
            check_payload(payload)
            nbytes = payload_nbytes(payload)
        out.seq += 1
        self._send(out, Message(payload, out.seq, origin_ns, now, out.key, nbytes, wire, out.source, origin_clock, CLOCK_ID))

    def _send(self, out: OutputPort, msg: Message) -> None:
        """Hand ``msg`` to the local readers of ``out`` (by reference) and to Zenoh, then count it."""
        for target in out.targets:
            cast(UnitJob, target.job).deliver_local(target, msg, self)  # (a port's job is always a UnitJob)
        publisher = out.publisher
        sent = publisher.put(msg) if publisher is not None and publisher.matched else 0
        counters = out.counters  # counted once sent: bookkeeping stays off the message's path
        counters.messages += 1
        nbytes = msg.nbytes or sent
        counters.bytes += nbytes
        if nbytes == 0:
            counters.unsized += 1
