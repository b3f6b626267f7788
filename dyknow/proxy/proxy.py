"""The proxy of a unit: its lifecycle, its ports bound to key expressions and rebound, its statistics.

The manager makes one per running unit; it is also the unit's :class:`~dyknow.unit.UnitRuntime`,
handed to the unit through :func:`dyknow.unit.attach` when it is created. It makes the unit's
ports (:mod:`~dyknow.proxy.ports`) and its job (:mod:`~dyknow.proxy.job`), which runs the unit's
callbacks, and isolates failures: an exception in ``setup``, a callback or ``run`` marks the unit
failed, with its error and traceback, and the rest of the manager carries on.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from dyknow import keys
from dyknow.bus import cycle_error
from dyknow.errors import BindingError, UnitError, did_you_mean
from dyknow.message import new_id
from dyknow.proxy.job import UnitJob, UnitState
from dyknow.proxy.ports import InputPort, OutputPort, no_port, uncertainty_us
from dyknow.stats import PortCounters, PortStatistics
from dyknow.transport import check_key_expr
from dyknow.unit import Unit, attach

if TYPE_CHECKING:
    from dyknow.bus import LocalBus
    from dyknow.executor import Executor, Timer
    from dyknow.receiver import Receiver
    from dyknow.spec import TransformationSpec
    from dyknow.transport import LivelinessSubscriber, LivelinessToken, Publisher, Session

__all__ = ["DEFAULT_QUEUE_DEPTH", "Proxy", "UnitStatistics"]

log = logging.getLogger(__name__)

time_ns: Final = time.time_ns
get_ident: Final = threading.get_ident

#: Messages an input port holds before it drops (the oldest, with the keep-last policy).
DEFAULT_QUEUE_DEPTH = 8


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
    """Binds one unit's ports to key expressions, delivers its messages and runs its callbacks
    (through its :class:`~dyknow.proxy.job.UnitJob`)."""

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
        self.error: str | None = None
        self.traceback: str | None = None
        self.reconfigurations = 0
        self.started_ns = time_ns()
        self._session = session
        self._bus = bus
        self._receiver = receiver
        self._executor = executor
        self._on_failure = on_failure
        self._config_lock = threading.Lock()
        self._timers: list[Timer] = []
        self._stop = threading.Event()
        self._run_thread: threading.Thread | None = None
        self._watches: list[LivelinessSubscriber] = []
        destroy = None if on_destroy_request is None else (lambda: on_destroy_request(self))
        job = self._job = UnitJob(name, unit, executor, fail=self._fail, destroy=destroy)

        self._inputs: dict[str, InputPort] = {}
        self._outputs: dict[str, OutputPort] = {}
        for port in spec.ports:
            key = bindings[port.name]
            if port.direction == "in":
                depth = port.queue or queue_depth
                keep_last = (port.policy or "keep-last") == "keep-last"
                self._inputs[port.name] = InputPort(job, port.name, key, depth, keep_last)
            else:
                self._outputs[port.name] = OutputPort(port.name, key)
        self._input_seq = tuple(self._inputs.values())
        job.inputs = self._input_seq
        job.outputs = self._outputs
        self._wire_forwards(type(unit))
        self.check_bindings()  # before anything is declared or started: a refusal changes nothing
        job.lane = executor.lane_for(job, dedicated=type(unit).dedicated_thread)
        attach(unit, self, name=name, label=spec.label, params=params, log=UnitLog(_UNIT_LOG, name))
        if type(unit).dedicated_thread:
            job.isolation = "the unit asks for a thread of its own (dedicated_thread = True)"

    # ------------------------------------------------------------------ lifecycle

    @property
    def state(self) -> UnitState:
        """Where the unit is in its lifecycle."""
        return self._job.state

    @property
    def isolation(self) -> str | None:
        """Why the unit got a thread of its own, if it did (it then never leaves it)."""
        return self._job.isolation

    @property
    def alive(self) -> bool:
        """Whether the unit is starting or running."""
        return self._job.alive

    @property
    def shed(self) -> int:
        """Load shedding (set by the manager's overload guard, dyknow.overload): 0 runs at full
        rate; k > 1 lets one message in k through on each input, and one timer tick in k; -1
        pauses it (nothing delivered, no ticks). What it sheds is counted per port."""
        return self._job.shed

    @shed.setter
    def shed(self, setting: int) -> None:
        self._job.shed = setting

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
        job = self._job
        if not job.setup(self.unit.setup):
            return
        try:
            self._receiver.attach(self._input_seq)
            self._bus.attach(self._input_seq, ())
        except Exception as exc:
            self._fail(exc, "binding its input ports")
            return
        if job.state is UnitState.STARTING:
            job.state = UnitState.RUNNING
        if type(self.unit).run is not Unit.run:
            self._run_thread = threading.Thread(target=self._run_loop, name=f"dyknow-{self.name}-run", daemon=True)
            self._run_thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the unit: no more messages, timers or callbacks; then ``teardown()``. Safe twice.

        Waits up to ``timeout_s`` for ``run()`` to return and for a callback in flight.
        """
        job = self._job
        if job.state is UnitState.STOPPED:
            return
        job.state = UnitState.STOPPED
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
        job.teardown(self._teardown, timeout_s)
        self._bus.detach((), self._outputs.values())
        for out in self._outputs.values():
            for entity in (out.publisher, out.token):
                if entity is not None:
                    entity.undeclare()
        for watch in self._watches:
            watch.undeclare()
        self._executor.release(job)

    def _teardown(self) -> None:
        try:
            self.unit.teardown()
        except Exception as exc:
            log.warning("unit %r: teardown() failed: %s", self.name, exc)
            self.error = self.error or f"teardown(): {type(exc).__name__}: {exc}"

    def _detach_inputs(self) -> None:
        self._bus.detach(self._input_seq, ())
        self._receiver.detach(self._input_seq)
        for inp in self._input_seq:
            inp.queue.clear()

    def _fail(self, exc: BaseException, where: str) -> None:
        job = self._job
        if job.state in (UnitState.FAILED, UnitState.STOPPED):
            return
        job.state = UnitState.FAILED
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

    def request_destroy(self) -> None:
        """The unit asks to be destroyed: at once, or after its current callback returns."""
        if self.protected:
            raise UnitError("the unit is protected: a protected unit cannot be destroyed, not even by itself", where=f"unit {self.name!r}")
        self._job.request_destroy()

    def _run_loop(self) -> None:
        try:
            self.unit.run(self._stop)
        except (Exception, SystemExit) as exc:
            if not self._stop.is_set():
                self._fail(exc, "run()")

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

    def create_timer(self, period_s: float, callback: Callable[[], None], first_s: float | None = None) -> Timer:
        """A timer calling ``callback`` on the unit's thread every ``period_s`` (cancelled when the unit stops)."""
        timer = self._executor.add_timer(self._job, period_s, callback, first_s)
        self._timers.append(timer)
        return timer

    # ------------------------------------------------------------------ publishing

    def publish(self, port: str, payload: Any, origin_ns: int | None = None) -> None:
        """Send ``payload`` from output ``port`` to local inputs (by reference) and to Zenoh."""
        self._job.publish(port, payload, origin_ns)

    def fail(self, reason: str) -> None:
        """The unit declares itself failed (from any thread): it stops, the manager is told."""
        self._fail(UnitError(reason), "reported by the unit")

    def watch_liveliness(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """Call ``on_change(key, alive)`` as producers on ``key_expr`` appear and vanish (until stop),
        on the unit's lane like its other callbacks."""
        check_key_expr(key_expr, what=f"liveliness watch of unit {self.name!r}")
        job = self._job

        def changed(key: str, alive: bool) -> None:  # on Zenoh's thread: hand it to the unit's lane
            if job.alive:
                job.call_soon(lambda: on_change(key, alive), "a liveliness callback")

        self._watches.append(self._session.declare_liveliness_subscriber(key_expr, changed, inline=True))

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the unit's lane like its other callbacks (from any thread); dropped once
        the unit stops."""
        if self._job.alive:
            self._job.call_soon(fn, "a call_soon callback")

    def has_subscribers(self, port: str) -> bool:
        """Whether a local input or a remote subscriber receives output ``port`` now."""
        out = self._outputs.get(port)
        if out is None:
            raise no_port(self.name, port, "output", self._outputs)
        return bool(out.targets) or (out.publisher is not None and out.publisher.matched)

    def reject(self, port: str, reason: str, *, expected: bool = False) -> None:
        """Count and log an unusable input message (``expected``: at INFO); the unit carries on."""
        inp = self._inputs.get(port)
        if inp is None:
            raise no_port(self.name, port, "input", self._inputs)
        inp.reject(self.name, reason, expected=expected)

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
                    raise no_port(self.name, port, "", {**self._inputs, **self._outputs})
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
            self._job.call_soon(lambda: unit.on_reconfigure(dict(effective)), "on_reconfigure()")
            return self.get_config()

    def get_statistics(self) -> UnitStatistics:
        """Uptime, reconfigurations, and per-port counts, drops and latency percentiles."""
        ports = [
            (
                self._inputs[p.name].counters.snapshot(
                    p.name, "in", self._inputs[p.name].key, uncertainty_us(self._inputs[p.name].counters.clocks)
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
            callback_avg_us=self._job.ewma_ns / 1000,
            error=self.error,
            traceback=self.traceback,
            timer_overruns=sum(timer.overruns for timer in self._timers),
            excused=self._job.excused,
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
        kind, units = self._executor.lane_of(self._job)
        shed = self.shed
        rate = "" if shed == 0 else (", paused by load shedding" if shed < 0 else f", at 1/{shed} of its rate by load shedding")
        if kind == "shared" and not self.isolation:
            return "shared thread" + rate
        # (on the shared lane with a reason: the watchdog left it the thread it is stuck on)
        where = "own thread" if units <= 1 or kind != "slow" else f"slow lane shared with {units - 1} other units"
        return f"{where} ({self.isolation}){rate}" if self.isolation else where + rate
