"""The proxy of a unit: binds its named ports to Zenoh key expressions and runs its callbacks.

One proxy per running unit. It

- binds every port to a key expression (by default ``dyknow/<manager>/<unit>/<port>``) and can
  rebind any subset of them atomically while the unit runs (``set_config``), without restarting
  the unit or touching the other ports;
- delivers messages: to local input ports through the manager's :class:`~dyknow.bus.LocalBus` by
  reference (no copy, no serialization), and to and from other processes through Zenoh;
- queues each input in a bounded queue (keep-last by default, like a Zenoh ring channel; or
  drop-new) and counts drops, so a slow unit never blocks its upstream;
- measures every message at every input port (age since origin, time since the previous hop) and
  counts messages and bytes per port (``get_statistics``);
- isolates failures: an exception in ``setup``, a callback or ``run`` marks the unit failed, with
  its error and traceback, and the rest of the manager carries on.

It is also the executor's *job* for the unit (see :mod:`dyknow.executor`) and the unit's
:class:`~dyknow.unit.UnitRuntime`: the proxy owns the wiring, handing itself to the unit through
:func:`dyknow.unit.attach` when it is created.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

import numpy as np

from dyknow import keys
from dyknow.bus import cycle_error
from dyknow.clocks import CLOCKS
from dyknow.errors import BindingError, UnitError, did_you_mean
from dyknow.executor import charged_ns, cpu_mark
from dyknow.message import CLOCK_ID, MAX_FORWARDS, Message, check_payload, new_id, payload_nbytes, reheader
from dyknow.stats import PortCounters, PortStatistics
from dyknow.transport import check_key_expr
from dyknow.unit import Unit, attach

if TYPE_CHECKING:
    from dyknow.bus import LocalBus
    from dyknow.executor import Executor, Lane, Timer, Worker
    from dyknow.receiver import Receiver
    from dyknow.spec import TransformationSpec
    from dyknow.transport import LivelinessSubscriber, LivelinessToken, Publisher, Session

__all__ = ["DEFAULT_QUEUE_DEPTH", "InputPort", "OutputPort", "Proxy", "UnitState", "UnitStatistics"]

log = logging.getLogger(__name__)

# The names the message path uses are Final: compiled (see setup.py), a Final name is a C constant
# rather than a lookup in the module's dictionary on every message.
time_ns: Final = time.time_ns
get_ident: Final = threading.get_ident

#: Messages an input port holds before it drops (the oldest, with the keep-last policy).
DEFAULT_QUEUE_DEPTH = 8

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


class InputPort:
    """An input port: its key, its bounded queue, its counters."""

    __slots__ = ("counters", "depth", "forward", "job", "keep_last", "key", "name", "queue", "senders")

    def __init__(self, job: Proxy, name: str, key: str, depth: int, keep_last: bool) -> None:
        self.job = job
        self.name = name
        self.key = key
        self.depth = depth
        self.keep_last = keep_last
        # keep-last: the deque's maxlen drops the oldest; drop-new: deliver() refuses when full
        self.queue: deque[Message] = deque(maxlen=depth if keep_last else None)
        self.counters = PortCounters()
        self.forward: OutputPort | None = None  # the unit's forward_to: dyknow publishes there itself
        self.senders: dict[int, int] = {}  # source -> the last seq seen from it (messages from other processes)

    def track(self, source: int, seq: int) -> None:
        """Follow ``source``'s sequence numbers: a gap is messages it sent that never arrived
        (dropped by its Zenoh publisher under congestion, or on the way), counted as ``lost``.
        A number at or below the last one is a sender that started over: no gap."""
        if source == 0:
            return
        senders = self.senders
        last = senders.get(source)
        if last is None:
            if len(senders) >= _MAX_SENDERS:
                senders.clear()  # bounded: senders come and go (a rebinding draws a new source)
        elif seq > last + 1:
            self.counters.lost += seq - last - 1
        senders[source] = seq

    def deliver_remote(self, msg: Message) -> None:
        """A message from another process, on Zenoh's receiving thread: run a unit proven quick
        and free right here (no thread hand-off), queue it for the unit's lane otherwise."""
        self.track(msg.source, msg.seq)
        if self.job.shed and self.job.shedding(self):
            return
        if self.forward is not None:
            if self.queue or not self.job.forward_now(self, msg, None):
                self.deliver(msg)
        elif self.queue or not self.job.run_inline(self, msg, None):
            self.deliver(msg)

    def forward_wire(self, data: Any, header: bytes) -> bool:
        """A message from another process, before it is decoded: a unit that only forwards
        passes it on as it came when it is free (True); False hands it to :meth:`deliver_remote`."""
        if self.forward is None or self.queue or self.job.shed:
            return False
        return self.job.forward_wire(self, data, header)

    def deliver_local(self, msg: Message, publisher: Proxy) -> None:
        """A message from a unit of this manager, on the publisher's thread: run a unit proven
        quick and free right here, depth-first like a function call (no queue, no lane), queue
        it otherwise or when ``_MAX_DEPTH`` units already run nested on this thread."""
        if self.job.shed and self.job.shedding(self):
            return
        if self.queue or publisher.inline_depth >= _MAX_DEPTH:
            self.deliver(msg)
        elif self.forward is not None:
            if not self.job.forward_now(self, msg, publisher):
                self.deliver(msg)
        elif not self.job.run_inline(self, msg, publisher):
            self.deliver(msg)

    def deliver(self, msg: Message) -> None:
        """Queue ``msg`` and make sure the unit will run. Any thread; never blocks."""
        q = self.queue
        if len(q) >= self.depth:
            self.counters.dropped += 1
            if not self.keep_last:
                return  # drop-new: keep what is queued
            # keep-last: the deque's maxlen drops the oldest on append
        q.append(msg)
        job = self.job
        if not job.scheduled:
            job.scheduled = True
            job.lane.put(job)


# A unit runs on Zenoh's receiving thread once it has handled this many messages on the port and
# its callbacks average under _INLINE_BUDGET_NS, on the shared lane (not isolated).
_PROVEN: Final = 8
_INLINE_BUDGET_NS: Final = 200_000
# At most this many units run nested on one thread (a chain of local units handing on inline);
# the next one is queued for its lane, which starts over: the stack stays shallow.
_MAX_DEPTH: Final = 64
# An input port follows the sequence numbers of at most this many senders at once.
_MAX_SENDERS: Final = 64
# A unit whose callbacks average over the slow line is probed this many callbacks (their own
# time measured: dyknow.executor.charged_ns) before it moves; a probe that finds 5 times the
# line decides at once.
_PROBES: Final = 3
_NO_MARK: Final = (0, 0, 0, 0)


def _arrived(counters: PortCounters, nbytes: int, now: int, origin_ns: int, origin_clock: int, send_ns: int, send_clock: int) -> None:
    """Count one message handed to a unit, its age and hop in this process's clock: times of
    another clock corrected by its offset (dyknow.clocks), or left out when it is not known. A
    corrected figure below zero (the estimate off by less than its uncertainty, on a hop shorter
    than that) counts as zero: a message never arrives before it was sent."""
    if origin_clock == CLOCK_ID and send_clock == CLOCK_ID:
        counters.arrived(nbytes, now - origin_ns, now - send_ns)
        return
    current = CLOCKS.current
    origin_offset = current.get(origin_clock)
    send_offset = current.get(send_clock)
    if origin_offset is None or send_offset is None:
        counters.arrived_unknown(nbytes)
        CLOCKS.missing(origin_clock if origin_offset is None else send_clock)  # estimated on demand
        return
    counters.clocks = (origin_clock, send_clock)
    age, hop = now - origin_ns + origin_offset, now - send_ns + send_offset
    counters.arrived(nbytes, age if age > 0 else 0, hop if hop > 0 else 0)


def _uncertainty_us(clocks: tuple[int, int]) -> float:
    """How far the offsets of ``timeline`` may be off now (µs; 0 for this process's own)."""
    worst = 0
    for clock in clocks:
        if clock != 0 and clock != CLOCK_ID:
            worst = max(worst, CLOCKS.uncertainty(clock) or 0)
    return round(worst / 1000, 1)


class OutputPort:
    """An output port: its key, sequence number, local targets and Zenoh publisher."""

    __slots__ = ("counters", "key", "name", "publisher", "seq", "source", "targets", "token")

    def __init__(self, name: str, key: str) -> None:
        self.name = name
        self.key = key
        self.seq = 0
        self.source = new_id()  # the id readers follow its seq by (drawn again when it is rebound)
        self.counters = PortCounters()
        self.targets: tuple[InputPort, ...] = ()
        self.publisher: Publisher | None = None
        # announces on the port's key that its producer lives (others watch it to notice a crash)
        self.token: LivelinessToken | None = None


@dataclass(frozen=True, slots=True)
class UnitStatistics:
    """What ``get_statistics`` returns for one unit."""

    name: str
    label: str
    state: str
    uptime_s: float
    reconfigurations: int
    ports: tuple[PortStatistics, ...]
    executor: str
    callback_avg_us: float
    error: str | None = None
    traceback: str | None = None
    timer_overruns: int = 0
    #: callbacks found slow by the clock and not by their own time (the machine was busy): kept on their lane
    excused: int = 0
    #: the rate the unit runs at while its manager sheds load: 1 (all), 1/k, or 0 (paused)
    rate: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        """The JSON form that ``get_statistics`` serves."""
        return {
            "name": self.name,
            "label": self.label,
            "state": self.state,
            "uptime_s": round(self.uptime_s, 3),
            "reconfigurations": self.reconfigurations,
            "executor": self.executor,
            "callback_avg_us": round(self.callback_avg_us, 3),
            "timer_overruns": self.timer_overruns,
            "excused": self.excused,
            "rate": self.rate,
            "ports": {p.port: p.to_dict() for p in self.ports},
            "error": self.error,
            "traceback": self.traceback,
        }



_UNIT_LOG = logging.getLogger("dyknow.unit")


class UnitLog(logging.LoggerAdapter):  # type: ignore[type-arg]
    """A unit's logger: the one ``dyknow.unit`` logger, the unit's name in each record (``unit``)
    and in front of its message. No logger per name, so a million spawns leave nothing behind."""

    def __init__(self, logger: logging.Logger, unit: str) -> None:
        super().__init__(logger, {"unit": unit})

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        """Prefix the message with the unit's name and put the name in the record."""
        kwargs["extra"] = {**(kwargs.get("extra") or {}), "unit": self.extra["unit"] if self.extra else None}
        return f"[{kwargs['extra']['unit']}] {msg}", kwargs

class Proxy:
    """Binds one unit's ports to key expressions, delivers its messages and runs its callbacks."""

    def __init__(
        self,
        *,
        name: str,
        spec: TransformationSpec,
        unit: Unit,
        params: Mapping[str, Any],
        bindings: Mapping[str, str],
        session: Session,
        bus: LocalBus,
        receiver: Receiver,
        executor: Executor,
        protected: bool = False,
        queue_depth: int = DEFAULT_QUEUE_DEPTH,
        on_failure: Callable[[Proxy], None] | None = None,
        on_destroy_request: Callable[[Proxy], None] | None = None,
    ) -> None:
        self.name = name
        self.label = spec.label
        self.spec = spec
        self.unit = unit
        self.protected = protected
        self.state = UnitState.STARTING
        self.error: str | None = None
        self.traceback: str | None = None
        self.reconfigurations = 0
        self._isolation: str | None = None  # see the isolation property
        self.started_ns = time_ns()
        self._session = session
        self._bus = bus
        self._receiver = receiver
        self._executor = executor
        self._slow_ns = executor.slow_callback_ns
        self._on_failure = on_failure
        self._on_destroy_request = on_destroy_request
        # executor job state
        self.scheduled = False
        self._lock = threading.Lock()  # held while one of the unit's callbacks runs
        self._config_lock = threading.Lock()
        self._calls: deque[tuple[Callable[[], None], str]] = deque()  # control calls for the unit's lane
        self._current: Message | None = None
        self._current_thread = 0
        self._ewma_ns = 0  # moving average of the unit's callback times
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
        self._timers: list[Timer] = []
        self._stop = threading.Event()
        self._run_thread: threading.Thread | None = None
        self._setup_done = False
        self._watches: list[LivelinessSubscriber] = []

        self._inputs: dict[str, InputPort] = {}
        self._outputs: dict[str, OutputPort] = {}
        for port in spec.ports:
            key = bindings[port.name]
            if port.direction == "in":
                depth = port.queue or queue_depth
                keep_last = (port.policy or "keep-last") == "keep-last"
                self._inputs[port.name] = InputPort(self, port.name, key, depth, keep_last)
            else:
                self._outputs[port.name] = OutputPort(port.name, key)
        self._input_seq = tuple(self._inputs.values())
        self._wire_forwards(type(unit))
        self.check_bindings()  # before anything is declared or started: a refusal changes nothing
        self.lane: Lane = executor.lane_for(self, dedicated=type(unit).dedicated_thread)
        attach(unit, self, name=name, label=spec.label, params=params, log=UnitLog(_UNIT_LOG, name))
        if type(unit).dedicated_thread:
            self.isolation = "the unit asks for a thread of its own (dedicated_thread = True)"

    # ------------------------------------------------------------------ lifecycle

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

    def check_bindings(self) -> None:
        """:class:`BindingError` if the unit's inputs would close a cycle of forwarding units
        (checked again when they attach, atomically: see :class:`~dyknow.bus.LocalBus`)."""
        cycle = self._bus.forwarding_cycle(inputs=self._input_seq)
        if cycle:
            raise cycle_error(cycle)

    def start(self) -> None:
        """Declare the ports, run ``setup()``, then start receiving. Failures mark the unit failed."""
        try:
            for out in self._outputs.values():
                out.publisher = self._session.declare_publisher(out.key)
                out.token = self._session.declare_liveliness_token(keys.port_token(out.key))
            self._bus.attach((), self._outputs.values())
        except Exception as exc:
            self._fail(exc, "binding its output ports")
            return
        with self._lock:
            self._current_thread = get_ident()
            try:
                self.unit.setup()
            except (Exception, SystemExit) as exc:
                self._fail(exc, "setup()")
                return
            finally:
                self._current_thread = 0
            self._setup_done = True
        if self._calls and not self.scheduled:  # queued while setup() held the lock (say, a rebinding)
            self.scheduled = True
            self.lane.put(self)
        try:
            self._receiver.attach(self._input_seq)
            self._bus.attach(self._input_seq, ())
        except Exception as exc:
            self._fail(exc, "binding its input ports")
            return
        if self.state is UnitState.STARTING:
            self.state = UnitState.RUNNING
        if type(self.unit).run is not Unit.run:
            self._run_thread = threading.Thread(target=self._run_loop, name=f"dyknow-{self.name}-run", daemon=True)
            self._run_thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the unit: no more messages, timers or callbacks; then ``teardown()``. Safe twice.

        Waits up to ``timeout_s`` for ``run()`` to return and for a callback in flight.
        """
        if self.state is UnitState.STOPPED:
            return
        self.state = UnitState.STOPPED
        self._stop.set()
        for timer in self._timers:
            timer.cancel()
        self._detach_inputs()
        # run() must be out of the way before teardown() frees what it uses (a video capture, say)
        thread = self._run_thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)
            if thread.is_alive():
                log.warning("unit %r: run() did not return within %.1f s after stop was set", self.name, timeout_s)
        # Wait for a callback in flight (bounded: a stuck unit must not hang its manager).
        got = self._lock.acquire(timeout=timeout_s) if self._current_thread != get_ident() else False
        try:
            if self._setup_done:
                self._setup_done = False
                try:
                    self.unit.teardown()
                except Exception as exc:
                    log.warning("unit %r: teardown() failed: %s", self.name, exc)
                    self.error = self.error or f"teardown(): {type(exc).__name__}: {exc}"
        finally:
            if got:
                self._lock.release()
        self._bus.detach((), self._outputs.values())
        for out in self._outputs.values():
            for entity in (out.publisher, out.token):
                if entity is not None:
                    entity.undeclare()
        for watch in self._watches:
            watch.undeclare()
        self._executor.release(self)

    def _detach_inputs(self) -> None:
        self._bus.detach(self._input_seq, ())
        self._receiver.detach(self._input_seq)
        for inp in self._input_seq:
            inp.queue.clear()

    def _fail(self, exc: BaseException, where: str) -> None:
        if self.state in (UnitState.FAILED, UnitState.STOPPED):
            return
        self.state = UnitState.FAILED
        self.error = f"{where}: {type(exc).__name__}: {exc}"
        self.traceback = "".join(traceback.format_exception(exc))
        frames = traceback.extract_tb(exc.__traceback__)  # where it was raised: the file and line of the unit's code
        at = f" at {frames[-1].filename}:{frames[-1].lineno} in {frames[-1].name}" if frames else ""
        log.error("unit %r (%s) failed in %s: %s: %s%s (dyknow stats %s shows the traceback)", self.name, self.label, where,
                  type(exc).__name__, exc, at, self.name)  # fmt: skip
        self._stop.set()
        for timer in self._timers:
            timer.cancel()
        self._detach_inputs()
        if self._on_failure is not None:
            try:
                self._on_failure(self)
            except Exception:
                log.exception("failure listener of unit %r failed", self.name)

    def on_isolated(self, reason: str) -> None:
        """Told by the executor that the unit now has a thread of its own, and why."""
        self.isolation = reason

    def request_destroy(self) -> None:
        """The unit asks to be destroyed: at once, or after its current callback returns."""
        if self.protected:
            raise UnitError("the unit is protected: a protected unit cannot be destroyed, not even by itself", where=f"unit {self.name!r}")
        if self._current_thread == get_ident():
            self._destroy_requested = True
        elif self._on_destroy_request is not None:
            self._on_destroy_request(self)

    def _run_loop(self) -> None:
        try:
            self.unit.run(self._stop)
        except (Exception, SystemExit) as exc:
            if not self._stop.is_set():
                self._fail(exc, "run()")

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
        for port in self._input_seq:
            if port.queue:
                return True
        return False

    def run_inline(self, port: InputPort, msg: Message, publisher: Proxy | None) -> bool:
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
        if self._ewma_ns >= self._inline_ns or port.counters.messages < _PROVEN or self._calls or self._queued():
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
            self._fail(exc, f"on_message({port.name!r})")
        finally:
            self._current = None
            self._current_thread = 0
            self.inline_depth = 0
            self._release()
        # bookkeeping after the callback, off the path of what the unit published
        _arrived(port.counters, msg.nbytes, now, msg.origin_ns, msg.origin_clock, msg.send_ns, msg.send_clock)
        took = time_ns() - now
        self._ewma_ns += (took - self._child_ns - self._ewma_ns) >> 3
        if probing:
            self._probed(charged_ns(mark) - self._child_ns)
        if publisher is not None:
            publisher._child_ns += took
        if self._destroy_requested or self._ewma_ns > self._slow_ns:
            self._after_callbacks()
        return True

    def forward_now(self, port: InputPort, msg: Message, publisher: Proxy | None) -> bool:
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
            self._fail(exc, f"forwarding {port.name!r}")
        finally:
            self.inline_depth = 0
            self._release()
        _arrived(port.counters, msg.nbytes, now, msg.origin_ns, msg.origin_clock, msg.send_ns, msg.send_clock)
        return True

    def forward_wire(self, port: InputPort, data: Any, header: bytes) -> bool:
        """:meth:`forward_now` for a message from another process that was not decoded: its
        payload buffer goes out again under a rewritten header (``data`` and ``header`` as the
        transport received them). Only raw bytes, only to Zenoh: False when the output has local
        readers (they need a :class:`Message`), the payload is of another kind (decoding checks
        it first), or the unit cannot forward right now; the caller then decodes and delivers."""
        out = port.forward
        if out is None or out.targets or self._calls or self._queued() or not self._lock.acquire(False):
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
            self._fail(exc, f"forwarding {port.name!r}")
            return True  # taken, and counted as the unit's failure
        finally:
            self._release()
        _arrived(port.counters, nbytes, now, origin_ns, origin_clock, sent_ns, sent_clock)
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
        self.reject(
            port.name,
            f"a message already passed on by {MAX_FORWARDS} forwarding units was dropped: forwarding units (relays) are bound "
            "into a cycle, probably across managers (each relays the other's output); rebind one of them",
        )

    def _wire_forwards(self, cls: type[Unit]) -> None:
        """Point every input at the ``forward_to`` output of a forwarding unit class (checked here,
        so a class that cannot forward is refused at spawn)."""
        target = cls.forward_to
        if target is None:
            return
        where = f"unit {self.name!r} ({cls.__name__}.forward_to = {target!r})"
        if cls.on_message is not Unit.on_message:
            raise UnitError(
                "the class both forwards its inputs and overrides on_message, which would never run",
                where=where,
                expected=f"either forward_to = None in {cls.__name__} (on_message handles the inputs) or no on_message",
            )
        out = self._outputs.get(target)
        if out is None:
            names = ", ".join(repr(p) for p in self._outputs) or "none"
            raise UnitError(
                f"its spec {self.label!r} has no output port {target!r}",
                where=where,
                expected=f"the spec's outputs ({names}) to include {target!r}{did_you_mean(target, self._outputs)}",
            )
        for port in self._input_seq:
            port.forward = out

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
        if self._destroy_requested or (self.lane.shared and self._ewma_ns > self._slow_ns):
            self._after_callbacks()

    def _drain(self, worker: Worker) -> None:
        on_message = self.unit.on_message
        ports = self._input_seq
        ident = get_ident()
        budget = _BATCH
        more = True
        while more:
            more = False
            for port in ports:
                q = port.queue
                if not q:
                    continue
                msg = q.popleft()
                now = time_ns()
                _arrived(port.counters, msg.nbytes, now, msg.origin_ns, msg.origin_clock, msg.send_ns, msg.send_clock)
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
                    self._fail(exc, f"on_message({port.name!r})" if port.forward is None else f"forwarding {port.name!r}")
                    return
                worker.busy_since_ns = 0
                self._current = None
                self._current_thread = 0
                self._ewma_ns += (time_ns() - now - self._child_ns - self._ewma_ns) >> 3
                if probing:
                    self._probed(charged_ns(mark) - self._child_ns)
                if self.state is not _RUNNING or self._destroy_requested:
                    return
                budget -= 1
                if q:
                    more = True
            if more and budget <= 0:  # let the other units of the lane run, then continue
                self.scheduled = True
                self.lane.put(self)
                return

    def run_timer(self, timer: Timer, worker: Worker) -> None:
        """Fire one timer tick under the unit's lock."""
        if self.shed and self._skip_tick():
            return
        if not self._lock.acquire(False):
            return  # the unit is busy on another thread: skip this tick
        try:
            state = self.state
            if state is _STOPPED or state is _FAILED:
                timer.cancel()
                return
            # STARTING: setup() is done (it ran under this lock), the inputs are being bound: tick
            self._call(timer.callback, worker, "a timer callback")
        finally:
            self._release()
        self._after_callbacks()

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
            self._fail(exc, where)
        finally:
            worker.busy_since_ns = 0
            self._current_thread = 0
            self.inline_depth = 0
        self._ewma_ns += (time_ns() - t0 - self._child_ns - self._ewma_ns) >> 3
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
            if self._on_destroy_request is not None:
                self._on_destroy_request(self)
            return
        lane = self.lane
        if lane.shared and self._ewma_ns > self._slow_ns and self.alive:
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
                log.debug("unit %r: slow by the clock (%.1f ms) but not by its own time (%.2f ms): it stays", self.name, self._ewma_ns / 1e6, own / 1e6)
                self._ewma_ns = own
                return
            self.isolation = f"its callbacks take {self._ewma_ns / 1e6:.1f} ms on average, {own / 1e6:.1f} ms of it their own"
            if self._executor.isolate(self) is None:
                self.isolation = None  # no lane to move to: it stays on the shared lane
                self._ewma_ns = own
                return
            log.info("unit %r moves off the shared thread: %s", self.name, self.isolation)

    def _call_soon(self, fn: Callable[[], None], where: str) -> None:
        """Run ``fn`` on the unit's lane, under its lock, before its next messages (any thread)."""
        self._calls.append((fn, where))
        if not self.scheduled:
            self.scheduled = True
            self.lane.put(self)

    def create_timer(self, period_s: float, callback: Callable[[], None], first_s: float | None = None) -> Timer:
        """A timer calling ``callback`` on the unit's thread every ``period_s`` (cancelled when the unit stops)."""
        timer = self._executor.add_timer(self, period_s, callback, first_s)
        self._timers.append(timer)
        return timer

    # ------------------------------------------------------------------ publishing

    def publish(self, port: str, payload: Any, origin_ns: int | None = None) -> None:
        """Send ``payload`` from output ``port`` to local inputs (by reference) and to Zenoh."""
        out = self._outputs.get(port)
        if out is None:
            raise self._no_port(port, "output", self._outputs)
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
            target.deliver_local(msg, self)
        publisher = out.publisher
        sent = publisher.put(msg) if publisher is not None and publisher.matched else 0
        counters = out.counters  # counted once sent: bookkeeping stays off the message's path
        counters.messages += 1
        nbytes = msg.nbytes or sent
        counters.bytes += nbytes
        if nbytes == 0:
            counters.unsized += 1

    def fail(self, reason: str) -> None:
        """The unit declares itself failed (from any thread): it stops, the manager is told."""
        self._fail(UnitError(reason), "reported by the unit")

    def watch_liveliness(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """Call ``on_change(key, alive)`` as producers on ``key_expr`` appear and vanish (until stop),
        on the unit's lane like its other callbacks."""
        check_key_expr(key_expr, what=f"liveliness watch of unit {self.name!r}")

        def changed(key: str, alive: bool) -> None:  # on Zenoh's thread: hand it to the unit's lane
            if self.alive:
                self._call_soon(lambda: on_change(key, alive), "a liveliness callback")

        self._watches.append(self._session.declare_liveliness_subscriber(key_expr, changed, inline=True))

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the unit's lane like its other callbacks (from any thread); dropped once
        the unit stops."""
        if self.alive:
            self._call_soon(fn, "a call_soon callback")

    def has_subscribers(self, port: str) -> bool:
        """Whether a local input or a remote subscriber receives output ``port`` now."""
        out = self._outputs.get(port)
        if out is None:
            raise self._no_port(port, "output", self._outputs)
        return bool(out.targets) or (out.publisher is not None and out.publisher.matched)

    def reject(self, port: str, reason: str, *, expected: bool = False) -> None:
        """Count and log an unusable input message (``expected``: at INFO); the unit carries on."""
        inp = self._inputs.get(port)
        if inp is None:
            raise self._no_port(port, "input", self._inputs)
        counters = inp.counters
        counters.rejected += 1
        counters.last_rejection = reason
        # log the first few, then every 100th, so a stream of bad frames does not flood the log
        if counters.rejected <= 3 or counters.rejected % 100 == 0:
            level = logging.INFO if expected else logging.WARNING
            log.log(level, "unit %r rejected a message on %r (%d so far): %s", self.name, port, counters.rejected, reason)

    # ------------------------------------------------------------------ proxy services

    def published(self, port: str) -> int:
        """How many messages output ``port`` has published so far."""
        return self._outputs[port].counters.messages

    def get_config(self) -> dict[str, str]:
        """Port -> key expression, for every port."""
        config = {name: p.key for name, p in self._inputs.items()}
        config.update((name, p.key) for name, p in self._outputs.items())
        return {p.name: config[p.name] for p in self.spec.ports}

    def set_config(self, changes: Mapping[str, str]) -> dict[str, str]:
        """Rebind any subset of ports at once, while the unit runs; returns the new config.

        All or nothing: every port and key is checked and every new Zenoh entity declared before
        anything changes. The unit keeps its state and its other ports are not touched.
        """
        with self._config_lock:
            if not self.alive:
                raise UnitError(
                    f"the unit is {self.state.value}, so it cannot be rebound", where=f"unit {self.name!r}", expected="a running unit"
                )
            if not isinstance(changes, Mapping) or not changes:
                raise BindingError(
                    f"set_config got {changes!r}", where=f"unit {self.name!r}", expected="a mapping of port to key expression"
                )
            for port, key in changes.items():
                if port in self._inputs:
                    what = f"unit {self.name!r} input port {port!r}"
                    keys.check_data_key(check_key_expr(key, what=what), what)
                elif port in self._outputs:
                    what = f"unit {self.name!r} output port {port!r}"
                    keys.check_data_key(check_key_expr(key, what=what, concrete=True), what)
                else:
                    raise self._no_port(port, "", {**self._inputs, **self._outputs})
            current = self.get_config()
            effective = {port: key for port, key in changes.items() if current[port] != key}
            if not effective:
                return current
            moves: list[tuple[Any, str]] = [
                (self._inputs[p] if p in self._inputs else self._outputs[p], key) for p, key in effective.items()
            ]
            cycle = self._bus.forwarding_cycle(changes=moves)
            if cycle:
                raise cycle_error(cycle, {id(port): key for port, key in moves})
            new_pubs: dict[str, Publisher] = {}
            new_tokens: dict[str, LivelinessToken] = {}
            try:
                for port, key in effective.items():
                    if port in self._outputs:
                        new_pubs[port] = self._session.declare_publisher(key)
                        new_tokens[port] = self._session.declare_liveliness_token(keys.port_token(key))
                if self.state is UnitState.RUNNING:  # its inputs receive from other processes
                    self._receiver.rebind([(self._inputs[p], key) for p, key in effective.items() if p in self._inputs])
            except Exception:
                for entity in (*new_pubs.values(), *new_tokens.values()):
                    entity.undeclare()
                raise
            try:
                # checks for a cycle again, atomically: another unit may have been rebound meanwhile
                self._bus.rebind(moves)
            except BindingError:
                if self.state is UnitState.RUNNING:
                    self._receiver.rebind([(self._inputs[p], current[p]) for p in effective if p in self._inputs])
                for entity in (*new_pubs.values(), *new_tokens.values()):
                    entity.undeclare()
                raise
            old: list[Any] = []  # entities to undeclare once the switch is done
            for port, pub in new_pubs.items():
                out = self._outputs[port]
                old += [out.publisher, out.token]
                out.publisher = pub
                out.token = new_tokens[port]
                out.source = new_id()  # its seq goes on: readers of the new key must not see a gap
            for entity in old:
                if entity is not None:
                    entity.undeclare()
            self.reconfigurations += 1
            unit = self.unit
            self._call_soon(lambda: unit.on_reconfigure(dict(effective)), "on_reconfigure()")
            return self.get_config()

    def get_statistics(self) -> UnitStatistics:
        """Uptime, reconfigurations, and per-port counts, drops and latency percentiles."""
        ports = [
            (
                self._inputs[p.name].counters.snapshot(
                    p.name, "in", self._inputs[p.name].key, _uncertainty_us(self._inputs[p.name].counters.clocks)
                )
            )
            if p.direction == "in"
            else self._outputs[p.name].counters.snapshot(p.name, "out", self._outputs[p.name].key)
            for p in self.spec.ports
        ]
        return UnitStatistics(
            name=self.name,
            label=self.label,
            state=self.state.value,
            uptime_s=(time_ns() - self.started_ns) / 1e9,
            reconfigurations=self.reconfigurations,
            ports=tuple(ports),
            executor=self.executor_description,
            callback_avg_us=self._ewma_ns / 1000,
            error=self.error,
            traceback=self.traceback,
            timer_overruns=sum(timer.overruns for timer in self._timers),
            excused=self.excused,
            rate=1.0 if self.shed == 0 else (0.0 if self.shed < 0 else 1 / self.shed),
        )

    def queued(self) -> dict[str, int]:
        """How many messages each input port holds, waiting for the unit (dyknow top)."""
        return {name: len(port.queue) for name, port in self._inputs.items()}

    def input_counters(self) -> dict[str, PortCounters]:
        """Each input port's counters, for exporters that keep histograms (dyknow.metrics)."""
        return {name: port.counters for name, port in self._inputs.items()}

    @property
    def executor_description(self) -> str:
        # ``isolation`` is set as soon as the move is decided, even while a slow callback still runs
        """Which thread runs the unit, and why it left the shared one: ``own thread (why)``, or
        ``slow lane shared with N units (why)`` once the manager's bound on lanes is reached."""
        kind, units = self._executor.lane_of(self)
        shed = self.shed
        rate = "" if shed == 0 else (", paused by load shedding" if shed < 0 else f", at 1/{shed} of its rate by load shedding")
        if kind == "shared" and not self.isolation:
            return "shared thread" + rate
        # (on the shared lane with a reason: the watchdog left it the thread it is stuck on)
        where = "own thread" if units <= 1 or kind != "slow" else f"slow lane shared with {units - 1} other units"
        return f"{where} ({self.isolation}){rate}" if self.isolation else where + rate

    def _no_port(self, port: str, direction: str, ports: Mapping[str, object]) -> BindingError:
        kind = f"{direction} port" if direction else "port"
        names = ", ".join(repr(p) for p in ports) or "none"
        return BindingError(f"no {kind} {port!r}", where=f"unit {self.name!r}", expected=f"one of {names}{did_you_mean(port, ports)}")
