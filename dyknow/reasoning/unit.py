"""The monitor as a dyknow unit: :class:`FormulaMonitor`, and :func:`monitor_spec`, which builds
its transformation spec for a formula.

A monitor unit has one input port per term of its formula (``t0``, ``t1``, ... in the order the
formula first mentions them, each tagged with its term, so a planner can wire it by meaning) and
one output port, ``verdicts``. Each message's origin time is its
sample time, in this process's clock: a time another host's clock took is corrected by that
clock's estimated offset (:mod:`dyknow.clocks`), so streams from hosts whose clocks differ are
synchronized as they happened (a sample from a clock not known yet is taken as stamped, and
counted in :attr:`FormulaMonitor.unknown_clock`). Each verdict is published as soon as it is
decided (:mod:`dyknow.reasoning.progression`), as JSON::

    {"t": 12.5, "verdict": false, "decided_t": 12.5, "t_ns": 12500000000, "decided_ns": 12500000000, "state": 41}

``t`` and ``decided_t`` are seconds (``t_ns``/``decided_ns`` the exact origin times of the state
and of the state that decided it), ``state`` the state's index since the unit started. A verdict
never decided (still unknown when the unit is destroyed) is never published.

**Bounds.** A monitor unit holds its formula to its manager's :class:`~dyknow.security.Limits`
(:func:`~dyknow.reasoning.check_formula`: nodes, windows, horizon) when it starts, so a formula
that reached the manager in a spec fails the unit, not the manager. Its memory is bounded by its
share of the manager's cells (:class:`MonitorBudget`, ``Limits.max_monitor_cells`` over the
monitors running, re-shared as they come and go; see :mod:`dyknow.reasoning.progression` for what
is given up past it). A sample whose time, on this host's clock, lies further in the future than
the clock's uncertainty plus ``Limits.max_future_ns`` is **refused**, counted as a rejection of
its port (``future: ...``) and in :attr:`FormulaMonitor.future`: taken, it would close every state
before it, and every later sample would be late, so one sample stamped ten years ahead would
blind the monitor for good. Outside a manager (:mod:`dyknow.testing`) the defaults of
:class:`~dyknow.security.Limits` apply.

Gaps: when the stream of a term was re-planned, the manager that runs the monitor tells it
(:meth:`FormulaMonitor.adapted`, with the adaptation event), and the next verdict says so:
``"gap": {"term": "Battery(robot)", "cause": "manager 'robot' was lost"}``.

Params:

- ``formula`` (string): the formula (:mod:`dyknow.reasoning.syntax`);
- ``reorder_ms`` (float, default 0): the reorder delay, in sample time; a sample later than the
  policy allows is counted as a rejection of its port (``late: ...``) and dropped;
- ``flush_ms`` (float, default 0: never): close the buffered states after this much wall time
  without a sample (the end of a replay, a stream that stopped), so their verdicts come out.

Example::

    from dyknow.reasoning import monitor_spec, term_ports

    spec = monitor_spec("historically[0, 2s] Battery(robot) > 0.2")
    manager.add_transformation(spec)
    ports = term_ports(spec)                         # {"Battery(robot)": "t0"}
    manager.spawn(spec.label, "battery-ok", bindings={ports["Battery(robot)"]: "robot/battery"})
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from dyknow.clocks import CLOCKS
from dyknow.errors import FormulaError
from dyknow.message import CLOCK_ID
from dyknow.reasoning.progression import Monitor, Verdict
from dyknow.reasoning.syntax import Formula, check_formula, parse
from dyknow.security import Limits
from dyknow.spec import Param, Port, Tag, TransformationSpec
from dyknow.unit import Unit

if TYPE_CHECKING:
    from dyknow.message import Message

__all__ = ["DEFAULT_QUEUE", "VERDICTS_PORT", "FormulaMonitor", "MonitorBudget", "monitor_spec", "term_ports"]

VERDICTS_PORT: str = "verdicts"
"""The output port on which a monitor unit publishes its verdicts."""

DEFAULT_QUEUE: int = 1024
"""The input queue of a monitor's ports: a burst of samples waits instead of being dropped."""

_SOURCE = "dyknow.reasoning.unit:FormulaMonitor"


def term_ports(formula: str | Formula | TransformationSpec) -> dict[str, str]:
    """Which input port of a monitor takes which term: ``{"Battery(robot)": "t0", ...}``.

    ``formula`` is the formula, or a spec made by :func:`monitor_spec` (its ``formula`` param).
    """
    if isinstance(formula, TransformationSpec):
        text = formula.param_values().get("formula")
        if not isinstance(text, str):
            raise FormulaError(
                f"transformation {formula.label!r} has no formula param", where="term_ports()", expected="a spec from monitor_spec()"
            )
        formula = text
    parsed = parse(formula) if isinstance(formula, str) else formula
    return {str(term): f"t{k}" for k, term in enumerate(parsed.terms)}


def monitor_spec(
    formula: str | Formula,
    *,
    label: str = "formula-monitor",
    reorder_ms: float = 0.0,
    flush_ms: float = 0.0,
    queue: int = DEFAULT_QUEUE,
) -> TransformationSpec:
    """The transformation spec of a monitor of ``formula``: its params, a port per term, ``verdicts``.

    Raises :class:`~dyknow.errors.FormulaError` when the formula does not parse or mentions no term.
    """
    parsed = parse(formula) if isinstance(formula, str) else formula
    if not parsed.terms:
        raise FormulaError(
            "the formula mentions no stream, so it has no states to monitor",
            where=f"monitor_spec({parsed.text!r})",
            expected="a formula over at least one term, such as Battery(robot) > 0.2",
        )
    ports = term_ports(parsed)
    return TransformationSpec(
        label=label,
        source=_SOURCE,
        params=(
            Param("formula", "string", parsed.text),
            Param("reorder_ms", "float", float(reorder_ms)),
            Param("flush_ms", "float", float(flush_ms)),
        ),
        ports=(*(Port(port, "in", queue=queue) for port in ports.values()), Port(VERDICTS_PORT, "out")),
        tags=tuple(Tag(port, term) for term, port in ports.items()),
        description=f"Monitors {parsed}: publishes each state's verdict on {VERDICTS_PORT} as soon as it is decided.",
    )


class MonitorBudget:
    """What the monitor units of one manager share: its :class:`~dyknow.security.Limits`; the
    cells ``limits.max_monitor_cells``, divided evenly among the monitors running (each is told
    its share as monitors join and leave); and at most ``limits.max_monitor_nodes`` formula nodes
    in all, which bounds what every sample costs the manager. Thread-safe. The manager hands its
    budget to each :class:`FormulaMonitor` before ``setup()``."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self._lock = threading.Lock()
        self._monitors: dict[Monitor, int] = {}  # -> its formula's nodes
        #: the formula nodes of the monitors running
        self.nodes = 0

    def check(self, *formulas: Formula) -> None:
        """:class:`~dyknow.errors.FormulaError` when monitors of ``formulas`` would take the
        manager's monitors past ``limits.max_monitor_nodes`` (what :meth:`join` checks)."""
        self._check(sum(f.nodes for f in formulas), self.nodes)

    def join(self, monitor: Monitor) -> None:
        """Count ``monitor`` in (:class:`~dyknow.errors.FormulaError` past the nodes' bound);
        every monitor's share of cells shrinks to fit it."""
        nodes = monitor.formula.nodes
        with self._lock:
            self._check(nodes, self.nodes)
            self._monitors[monitor] = nodes
            self.nodes += nodes
            self._share()

    def leave(self, monitor: Monitor) -> None:
        """Count ``monitor`` out (safe twice); the others' shares grow."""
        with self._lock:
            nodes = self._monitors.pop(monitor, None)
            if nodes is not None:
                self.nodes -= nodes
                self._share()

    def _check(self, nodes: int, held: int) -> None:
        bound = self.limits.max_monitor_nodes
        if held + nodes > bound:
            raise FormulaError(
                f"the manager's monitors hold {held:,} formula nodes, and this formula has {nodes:,}",
                where="monitor",
                expected=f"at most {bound:,} nodes in all (Limits.max_monitor_nodes): release monitors or requirements first",
            )

    @property
    def share(self) -> int:
        """The cells each monitor running may keep now (all of them, when none runs)."""
        return self.limits.max_monitor_cells // max(1, len(self._monitors))

    @property
    def running(self) -> int:
        """How many monitors share the cells."""
        return len(self._monitors)

    def _share(self) -> None:
        share = self.share
        for monitor in self._monitors:
            monitor.set_max_cells(share)


class FormulaMonitor(Unit):
    """A :class:`~dyknow.reasoning.Monitor` as a unit (see the module documentation).

    ``monitor`` is the monitor (its ``late`` count, ``states``, ``retained()``). In the process
    that runs it, :meth:`listen` hands each verdict to a callback too (the adaptation loop does,
    for a request's requirements).
    """

    monitor: Monitor
    _budget: MonitorBudget | None = None

    def use_budget(self, budget: MonitorBudget) -> None:
        """Take the manager's bounds and share of cells (called by the manager before ``setup()``)."""
        self._budget = budget

    def setup(self) -> None:
        """Check the formula against the bounds, check there is a port per term, start the idle
        flush if asked for, and take a share of the cells."""
        reorder_ms = float(self.params.get("reorder_ms", 0.0))
        if not 0 <= reorder_ms <= 3_600_000:
            raise FormulaError(f"reorder_ms is {reorder_ms}", where=f"unit {self.name!r}", expected="0 to 3,600,000 milliseconds")
        budget = self._budget
        limits = budget.limits if budget is not None else Limits()
        formula = check_formula(str(self.params["formula"]), limits)
        self.monitor = Monitor(formula, reorder_ns=round(reorder_ms * 1_000_000), max_cells=budget.share if budget is not None else limits.max_monitor_cells)
        self._future_ns = limits.max_future_ns
        #: samples refused because their time lay in the future (see the module documentation)
        self.future = 0
        self._given_up_logged = 0
        self._ports = {f"t{k}": k for k in range(len(self.monitor.terms))}
        bound = self.get_config()
        missing = [f"{port} for {self.monitor.terms[k]}" for port, k in self._ports.items() if port not in bound]
        if missing or VERDICTS_PORT not in bound:
            raise FormulaError(
                f"the unit lacks ports: {', '.join(missing) or VERDICTS_PORT}",
                where=f"unit {self.name!r}",
                expected="the spec monitor_spec(formula) builds: one input per term and the output 'verdicts'",
            )
        self._last_sample = time.monotonic()
        self._listeners: list[Callable[[Verdict], None]] = []
        self._gap: dict[str, str] | None = None
        self.unknown_clock = 0  # samples stamped by a clock whose offset was not known
        flush_ms = float(self.params.get("flush_ms", 0.0))
        self._flush_s = flush_ms / 1000
        if flush_ms > 0:
            self.create_timer(max(self._flush_s / 2, 0.001), self._flush_if_idle)
        if budget is not None:
            budget.join(self.monitor)  # last: a failed setup() has nothing to give back

    def teardown(self) -> None:
        """Give the monitor's share of cells back."""
        if self._budget is not None:
            self._budget.leave(self.monitor)

    def listen(self, callback: Callable[[Verdict], None]) -> None:
        """Call ``callback(verdict)`` for every verdict from now on, on the unit's thread (it must return at once)."""
        self._listeners.append(callback)

    def on_message(self, port: str, msg: Message) -> None:
        """Push the sample (its origin time, its payload); publish the verdicts it decided."""
        monitor = self.monitor
        late = monitor.late
        t_ns = msg.origin_ns
        if msg.origin_clock != CLOCK_ID:
            offset = CLOCKS.current.get(msg.origin_clock)
            if offset is None:
                self.unknown_clock += 1
            else:
                t_ns -= offset
        now = time.time_ns()
        if t_ns > now + self._future_ns:
            ahead = t_ns - now - (CLOCKS.uncertainty(msg.origin_clock) or 0)
            if ahead > self._future_ns:
                self.future += 1
                self.reject(
                    port,
                    f"future: a sample at {t_ns} ns, {ahead / 1e9:.6g} s ahead of this host's clock beyond its uncertainty "
                    f"(at most {self._future_ns / 1e6:g} ms are taken)",
                )
                return
        verdicts = monitor.push_index(self._ports[port], t_ns, msg.payload)
        if monitor.late != late:  # (expected when a term's producer was switched, or hosts interleave)
            self.reject(
                port,
                f"late: a sample at {t_ns} ns, at or before the last state closed ({monitor.closed_ns} ns; reorder delay {monitor.reorder_ns / 1e6:g} ms)",
                expected=True,
            )
        self._last_sample = time.monotonic()
        for verdict in verdicts:
            self._publish(verdict)
        if monitor.states & 1023 == 0:
            self._report_given_up()

    def _report_given_up(self) -> None:
        """Log, now and then (at 1, 10, 100, ... states), that the memory bound gave states up."""
        given_up = self.monitor.given_up
        if given_up > self._given_up_logged:
            self._given_up_logged = 10 ** len(str(given_up))
            self.log.warning(
                "the memory bound gave up %d states so far (%d kept at most: its share of the manager's cells, "
                "Limits.max_monitor_cells): the verdicts that needed them stay unknown",
                given_up,
                self.monitor.max_states,
            )

    def _publish(self, verdict: Verdict, origin_ns: int | None = None) -> None:
        out = verdict.to_json()
        if self._gap is not None:
            out["gap"], self._gap = self._gap, None
        self.publish(VERDICTS_PORT, out, origin_ns=origin_ns)
        for listener in self._listeners:
            listener(verdict)

    def adapted(self, key: str, cause: str) -> None:
        """The stream on ``key`` was re-planned for ``cause``: when a term reads it, the next
        verdict says a gap occurred (any thread may call it: the manager's adaptation loop does)."""
        bound = self.get_config()
        for port, k in self._ports.items():
            if bound.get(port) == key:
                self._gap = {"term": str(self.monitor.terms[k]), "cause": cause[:500]}

    def _flush_if_idle(self) -> None:
        if time.monotonic() - self._last_sample >= self._flush_s:
            for verdict in self.monitor.flush():
                self._publish(verdict, origin_ns=verdict.decided_ns)
