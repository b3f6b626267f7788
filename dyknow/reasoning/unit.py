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
that differs from the last one published also carries ``"why"`` (see the param ``explain``). A
verdict never decided (still unknown when the unit is destroyed) is never published.

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

**Many formulas.** One unit may serve several formulas (:func:`monitor_spec` given a mapping
of names to formulas, or a list; the ``formulas`` param, a JSON object, in an XML spec). Its
ports are the terms of them all, each once, in the order they are first mentioned, so a sample
of a term several formulas read is received, decoded and checked once for all of them; each
formula keeps its own monitor (its states are its own terms' samples, as if it ran alone) and
each of its verdicts carries its name: ``"formula": "slow"``. The settings below hold for every
formula; each counts against the manager's node budget, and all are refused together.

**Objects.** A ``foreach`` formula (``foreach t in Track(field).id: ...``) runs as an
:class:`~dyknow.reasoning.objects.ObjectMonitor`: one instance per object, ending ``idle_ms``
after the object's last sample, at most ``max_objects`` at once; each verdict carries its
object: ``"object": "17"``. A message on the quantified stream whose payload is a JSON list is a
*frame* (a tracker's tracks): one sample per element, at the message's time, so a frame of 1,000
objects costs one message, not 1,000.

**Freshness.** A term's value is unknown at a state more than its maximum age after its latest
sample (:mod:`dyknow.reasoning.semantics`). ``max_age_ms`` declares it for every term; 0 (the
default) derives each term's from its measured rate: after its first 20 samples, five times their
median spacing (at least 20 ms; for a ``foreach`` stream, the spacing of each object's samples),
then fixed (logged, and in the unit's ``ages``); a negative
value sets none.

**Gaps.** When the stream of a term was re-planned, the manager that runs the monitor tells it
(:meth:`FormulaMonitor.adapted`, with the adaptation event): the gap runs from the term's last
sample before to its first after, and every verdict whose window reaches into it (from its state
back by the formula's past reach, forward by its horizon) says so:
``"gap": {"term": "Battery(robot)", "cause": "manager 'robot' was lost"}``.

**No silent failure.** A field the formula reads that a term's first 20 samples never hold (a
typo, ``Speed(robot).sped``) is warned about once, naming the field and the fields the samples
did hold: in the log, in :attr:`FormulaMonitor.warnings` (the manager's model shows them with the
monitor) and as a message ``{"warning": "..."}`` on ``verdicts``.

Params:

- ``formula`` (string): the formula (:mod:`dyknow.reasoning.syntax`); or
- ``formulas`` (string): several, a JSON object of names and formulas;
- ``reorder_ms`` (float, default 0) and ``max_reorder_ms`` (float, default 1,000): the least and
  the most reorder delay, in sample time. The delay starts at ``reorder_ms`` and grows, up to
  ``max_reorder_ms``, to twice the disorder the unit has seen: a sample that comes behind the
  newest sample of its ports by more than half the delay raises it (logged at INFO), so streams
  that interleave late (hosts, starved threads) stop losing samples after the first. A sample
  later than the delay allows is dropped, counted as a rejection of its port (``late: ...``),
  and warned about the first time on each port, naming the port and its term (the unit's own
  ports are handed over in the order their messages came, so one process's streams are never
  out of order there);
- ``flush_ms`` (float, default 0: never): close the buffered states after this much wall time
  without a sample (the end of a replay, a stream that stopped), so their verdicts come out;
- ``close_idle`` (bool, default false): close the buffered states once no sample came for the
  reorder delay, in wall time, and at least :data:`IDLE_CLOSE_MIN_S` (checked every
  :data:`IDLE_CHECK_S`): a live stream that stops is
  judged up to its last sample however far the delay grew, as if its time had gone on without
  it (a sample that comes later still is late, as it would be had the stream gone on). The
  requirements of requests are watched so (:mod:`dyknow.adaptation.requirements`): a stream
  that falls silent just as its requirement turns false is found false then, not at its next
  sample;
- ``max_age_ms`` (float, default 0: derived): the terms' freshness (see above);
- ``idle_ms`` (float, default 10,000) and ``max_objects`` (int, default 1,000): a ``foreach``
  formula's object lifetime and cap;
- ``changes_only`` (bool, default false): publish a verdict only when it differs from the last
  one published (an object's, with ``foreach``);
- ``explain`` (bool, default true): a verdict that differs from the last one published (of its
  object, with ``foreach``: its first too) carries ``"why"``: each comparison of the formula as
  written and with its sides' values at the verdict's state, from each term's latest
  :data:`RECENT_SAMPLES` samples (``"Battery(r1) > 0.2: 0.1 > 0.2"``; a side that reads a window is
  ``?``, and ``unknown`` when no kept sample is as old as the state; an object's: its body's, over
  its own among them, its variable as the object); at most 8 at once and then one per 50 ms of
  sample time per formula (:data:`EXPLAIN_BURST`, :data:`EXPLAIN_GAP_NS`); with ``robustness``
  (bool, default false) a formula's change also carries ``"robustness_of"``: each condition
  subformula's robustness (:func:`~dyknow.reasoning.explain.robustness_explainer`, over the
  latest :data:`ROBUST_SAMPLES` samples of each term: ``?`` where its windows reach past them);
  an object's change, its body's over the object's own among them
  (:func:`~dyknow.reasoning.explain.object_robustness_explainer`: with many objects on one
  stream, few are kept, so a window over more than the object's latest samples is often ``?``);
- ``bound`` (string): the terms bound to what exists, a JSON object of terms and their sources
  (:mod:`dyknow.reasoning.bindings`): their text samples are read as JSON values, and
- ``quiet_ms`` (float, default 5,000): a bound term without a sample this long after the unit
  started is warned about once, naming its source (a ``{"warning": ...}`` on ``verdicts``, as
  for a field no sample holds); 0: never.

Example::

    from dyknow.reasoning import monitor_spec, term_ports

    spec = monitor_spec("historically[0, 2s] Battery(robot) > 0.2")
    manager.add_transformation(spec)
    ports = term_ports(spec)                         # {"Battery(robot)": "t0"}
    manager.spawn(spec.label, "battery-ok", bindings={ports["Battery(robot)"]: "robot/battery"})
"""

from __future__ import annotations

import json
import statistics
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from dyknow.clocks import CLOCKS
from dyknow.errors import FormulaError
from dyknow.message import CLOCK_ID
from dyknow.reasoning.bindings import sample_value
from dyknow.reasoning.budget import MonitorBudget
from dyknow.reasoning.explain import explainer, object_explainer, object_robustness_explainer, robustness_explainer
from dyknow.reasoning.families import MAX_MEMBERS
from dyknow.reasoning.members import LiveFamilies
from dyknow.reasoning.objects import DEFAULT_IDLE_NS, DEFAULT_MAX_OBJECTS, ObjectMonitor
from dyknow.reasoning.progression import Monitor, Verdict
from dyknow.reasoning.served import EXPLAIN_BURST, Served, push_sample
from dyknow.reasoning.syntax import Formula, Quantifier, Stream, check_formula, parse, walk
from dyknow.reasoning.tree import is_family
from dyknow.reasoning.values import object_key, read
from dyknow.security import Limits
from dyknow.spec import Param, Port, Tag, TransformationSpec
from dyknow.unit import Unit

if TYPE_CHECKING:
    from dyknow.message import Message

__all__ = ["DEFAULT_MAX_REORDER_MS", "DEFAULT_QUEUE", "DEFAULT_QUIET_MS", "IDLE_CHECK_S", "IDLE_CLOSE_MIN_S", "MAX_FORMULAS", "VERDICTS_PORT", "FormulaMonitor", "Formulas", "MonitorBudget", "monitor_spec", "term_ports"]

VERDICTS_PORT: str = "verdicts"
"""The output port on which a monitor unit publishes its verdicts."""

DEFAULT_QUEUE: int = 1024
"""The input queue of a monitor's ports: a burst of samples waits instead of being dropped."""

_SOURCE = "dyknow.reasoning.unit:FormulaMonitor"


Formulas = str | Formula | Mapping[str, str | Formula] | Sequence[str | Formula]
"""What a monitor unit serves: one formula, several by name (``{"slow": "...", ...}``), or several
named by their text (a list)."""

MAX_FORMULAS: int = 1000
"""The most formulas one monitor unit serves (their nodes are bounded besides, with every other
monitor's, by ``Limits.max_monitor_nodes``)."""

_MAX_NAME = 200

DEFAULT_QUIET_MS: float = 5000.0
"""How long a monitor waits for a bound term's first sample before it warns (milliseconds)."""

DEFAULT_MAX_REORDER_MS: float = 1000.0
"""The most a monitor's reorder delay grows to with the disorder it sees (milliseconds): the
most its verdicts may come late for it."""

IDLE_CHECK_S: float = 0.05
"""How often a monitor with ``close_idle`` looks whether its input went idle (seconds)."""

IDLE_CLOSE_MIN_S: float = 0.1
"""The least idle time after which a monitor with ``close_idle`` closes its buffered states
(seconds): another term's sample at the same time (two outputs of one source) may still come."""


def _named(formulas: Formulas, where: str, limits: Limits | None = None) -> list[tuple[str | None, Formula]]:
    """``formulas`` as ``(name, parsed)`` pairs, each held to ``limits`` when given
    (:func:`~dyknow.reasoning.check_formula`); one formula has no name (its verdicts carry none,
    as they always did)."""

    def read(formula: str | Formula) -> Formula:
        if limits is not None:
            return check_formula(formula, limits)
        return parse(formula) if isinstance(formula, str) else formula

    if isinstance(formulas, str | Formula):
        return [(None, read(formulas))]
    if isinstance(formulas, Mapping):
        items = list(formulas.items())
    else:
        items = [(f.text if isinstance(f, Formula) else f, f) for f in formulas]
    expected = 'one formula, or several by name: {"slow": "Speed(robot) < 0.5", "bumps": "count[0, 60s] rise(Bump(robot)) <= 3"}'
    if not items:
        raise FormulaError("no formula given", where=where, expected=expected)
    if len(items) > MAX_FORMULAS:
        raise FormulaError(
            f"{len(items):,} formulas", where=where, expected=f"at most {MAX_FORMULAS:,} formulas a unit (spread them over several)"
        )
    out: list[tuple[str | None, Formula]] = []
    names: set[str] = set()
    for name, formula in items:
        if not isinstance(name, str) or not name.strip() or len(name) > _MAX_NAME or not name.isprintable():
            raise FormulaError(f"a formula named {str(name)[:60]!r}", where=where,
                               expected=f"names of 1 to {_MAX_NAME} printable characters")  # fmt: skip
        if name in names:
            raise FormulaError(f"the formula {name[:60]!r} is given twice", where=where, expected="each formula once, each name once")
        names.add(name)
        if not isinstance(formula, str | Formula):
            raise FormulaError(f"the formula {name[:60]!r} is a {type(formula).__name__}", where=where, expected="its text")
        try:
            out.append((name, read(formula)))
        except FormulaError as exc:  # located in the formula of several
            where_in = f"{where}: formula {name[:60]!r}, {exc.where}"
            raise FormulaError(exc.what, where=where_in, expected=exc.expected, formula=exc.formula, column=exc.column) from None
    return out


def _spec_formulas(spec: TransformationSpec) -> Formulas:
    values = spec.param_values()
    if isinstance(values.get("formulas"), str):
        return _formulas_param(str(values["formulas"]), f"transformation {spec.label!r}")
    text = values.get("formula")
    if not isinstance(text, str):
        raise FormulaError(
            f"transformation {spec.label!r} has no formula param", where="term_ports()", expected="a spec from monitor_spec()"
        )
    return text


def _formulas_param(text: str, where: str) -> dict[str, str]:
    """The ``formulas`` param: a JSON object of names and formulas."""
    expected = 'a JSON object of names and formulas, such as {"slow": "Speed(robot) < 0.5", "fast": "Speed(robot) > 3"}'

    def unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        seen: dict[str, Any] = {}
        for name, value in pairs:
            if name in seen:
                raise FormulaError(f"the name {name[:60]!r} is given twice", where=f"{where}: param formulas", expected=expected)
            seen[name] = value
        return seen

    try:
        named = json.loads(text, object_pairs_hook=unique)
    except (ValueError, RecursionError) as exc:  # (a deeply nested document: refused like any other)
        raise FormulaError(
            f"the param formulas is not JSON ({str(exc)[:200]})", where=f"{where}: param formulas", expected=expected
        ) from None
    if not isinstance(named, dict) or not all(isinstance(v, str) for v in named.values()):
        raise FormulaError(f"the param formulas holds a JSON {type(named).__name__}", where=f"{where}: param formulas", expected=expected)
    return named


def _bound_param(given: object, terms: Sequence[str], where: str) -> dict[str, str]:
    """The ``bound`` param: a JSON object of the unit's terms and their sources."""
    if given is None or given == "":
        return {}
    expected = 'a JSON object of terms of the formula and their sources, such as {"Odom(r1)": "ros2:/r1/odom"}'
    try:
        bound = json.loads(str(given))
    except (ValueError, RecursionError):
        raise FormulaError(f"the param bound is not JSON: {str(given)[:120]!r}", where=where, expected=expected) from None
    if not isinstance(bound, dict) or not all(isinstance(v, str) for v in bound.values()):
        raise FormulaError(f"the param bound holds a JSON {type(bound).__name__}", where=where, expected=expected)
    unknown = [t for t in bound if t not in terms]
    if unknown:
        raise FormulaError(f"the param bound names {unknown[0][:120]!r}, no term of the formula", where=where, expected=expected)
    return bound


def _terms(named: list[tuple[str | None, Formula]]) -> list[str]:
    """The terms of the formulas, each once, in the order they are first mentioned."""
    return list(dict.fromkeys(str(term) for _, formula in named for term in formula.terms))


def term_ports(formula: Formulas | TransformationSpec) -> dict[str, str]:
    """Which input port of a monitor takes which term: ``{"Battery(robot)": "t0", ...}``.

    ``formula`` is the formula (or the formulas, as :func:`monitor_spec` takes them: a term
    several formulas read has one port), or a spec made by :func:`monitor_spec`.
    """
    formulas = _spec_formulas(formula) if isinstance(formula, TransformationSpec) else formula
    return {term: f"t{k}" for k, term in enumerate(_terms(_named(formulas, "term_ports()")))}


def monitor_spec(
    formula: Formulas,
    *,
    label: str = "formula-monitor",
    reorder_ms: float = 0.0,
    max_reorder_ms: float = DEFAULT_MAX_REORDER_MS,
    flush_ms: float = 0.0,
    close_idle: bool = False,
    queue: int = DEFAULT_QUEUE,
    max_age_ms: float = 0.0,
    idle_ms: float = DEFAULT_IDLE_NS / 1e6,
    max_objects: int = DEFAULT_MAX_OBJECTS,
    changes_only: bool = False,
    robustness: bool = False,
    bound: Mapping[str, str] | None = None,
    quiet_ms: float = DEFAULT_QUIET_MS,
) -> TransformationSpec:
    """The transformation spec of a monitor of ``formula``: its params, a port per term, ``verdicts``.

    ``formula`` may be several formulas, served by one unit: a mapping of names to formulas, or
    a list (each named by its text). A term they share has one port, so each sample is delivered
    once for all of them; each verdict carries the name of its formula (``"formula": "slow"``).
    The settings hold for every formula. ``bound``: the terms bound to what exists and their
    sources (:mod:`dyknow.reasoning.bindings`), warned about ``quiet_ms`` after the start when
    silent; ``robustness``: each change also says each subformula's robustness (``robustness_of``).

    Raises :class:`~dyknow.errors.FormulaError` when a formula does not parse or they mention no term.
    """
    named = _named(formula, "monitor_spec()")
    terms = _terms(named)
    text = named[0][1].text if len(named) == 1 else f"{len(named)} formulas"
    if not terms:
        raise FormulaError(
            "the formula mentions no stream, so it has no states to monitor",
            where=f"monitor_spec({text!r})",
            expected="a formula over at least one term, such as Battery(robot) > 0.2",
        )
    ports = {term: f"t{k}" for k, term in enumerate(terms)}
    families = {str(t) for _, parsed in named for t in parsed.terms if is_family(t)}
    if named[0][0] is None:
        what = Param("formula", "string", named[0][1].text)
        described = str(named[0][1])
    else:
        what = Param("formulas", "string", json.dumps({name: parsed.text for name, parsed in named}))
        described = f"{len(named)} formulas ({', '.join(str(name) for name, _ in named[:3])}{', ...' if len(named) > 3 else ''})"
    return TransformationSpec(
        label=label,
        source=_SOURCE,
        params=(
            what,
            Param("reorder_ms", "float", float(reorder_ms)),
            Param("max_reorder_ms", "float", float(max_reorder_ms)),
            Param("flush_ms", "float", float(flush_ms)),
            Param("max_age_ms", "float", float(max_age_ms)),
            Param("idle_ms", "float", float(idle_ms)),
            Param("max_objects", "int", int(max_objects)),
            Param("changes_only", "bool", bool(changes_only)),
            *((Param("robustness", "bool", True),) if robustness else ()),
            *((Param("close_idle", "bool", True),) if close_idle else ()),
            *((Param("bound", "string", json.dumps(dict(bound))), Param("quiet_ms", "float", float(quiet_ms))) if bound else ()),
        ),
        ports=(*(Port(port, "in", queue=queue) for port in ports.values()), Port(VERDICTS_PORT, "out")),
        tags=tuple(Tag(port, term) for term, port in ports.items() if term not in families),  # (a family is no tag)
        description=f"Monitors {described}: publishes each state's verdict on {VERDICTS_PORT} as soon as it is decided.",
    )


_DERIVE_AFTER = 20  # samples a term's freshness and fields are judged from
#: Each term's latest samples a monitor unit keeps to explain a change of a verdict ("why"); and
#: how many changes of one formula it explains: 8 at once, then one per 50 ms of sample time (a
#: verdict that flips at every sample would otherwise cost an evaluation of each comparison per sample).
RECENT_SAMPLES = 8
ROBUST_SAMPLES = 64  # (with the param robustness: enough for the windows of a few seconds at 20 Hz)
EXPLAIN_GAP_NS = 50_000_000
_MIN_AGE_NS = 20_000_000
_MAX_GAPS = 64


class FormulaMonitor(Unit):
    """A :class:`~dyknow.reasoning.Monitor` (or, for ``foreach``, an
    :class:`~dyknow.reasoning.objects.ObjectMonitor`) as a unit (see the module documentation);
    one per formula when the unit serves several.

    ``monitor`` is the monitor of its (first) formula (its ``late`` count, ``states``,
    ``retained()``), ``monitors`` each formula's by name (by its text for a unit of one formula).
    In the process that runs it, :meth:`listen` hands each verdict to a callback too (the
    adaptation loop does, for a request's requirements); :attr:`warnings` says what it found
    wrong with the data.
    """

    monitor: Monitor | ObjectMonitor
    _served: Sequence[Served] = ()  # (set up by setup(); none when it failed first)
    _budget: MonitorBudget | None = None
    _account: str | None = None  # whose share of the budget's nodes its formulas take (None: the manager's own)
    _seen_share = -1  # the budget's generation when the monitors last took their shares
    _full_warned = 0  # the families past MAX_MEMBERS warned of
    _textual: frozenset[int] = frozenset()  # the bound terms' ports (their text samples are read as JSON)
    #: the latest verdict published of each formula (by name; by its text for a unit of one
    #: formula), as published on ``verdicts``: what its ``/diagnostics`` status says (:mod:`dyknow.ros2.diagnostics`)
    latest: dict[str, dict[str, Any]] = {}  # (each unit its own from setup() on)

    def use_budget(self, budget: MonitorBudget, account: str | None = None) -> None:
        """Take the manager's bounds and share of cells, for ``account`` (the caller it is
        spawned for, :meth:`dyknow.model.Owner.account`; None: the manager's own). Called by the
        manager before ``setup()``."""
        self._budget = budget
        self._account = account

    def setup(self) -> None:
        """Check the formulas against the bounds, check there is a port per term, start the idle
        flush if asked for, and take a share of the cells."""
        params = self.params
        where = f"unit {self.name!r}"
        reorder_ms = float(params.get("reorder_ms", 0.0))
        max_reorder_ms = float(params.get("max_reorder_ms", DEFAULT_MAX_REORDER_MS))
        if not 0 <= reorder_ms <= 3_600_000 or not 0 <= max_reorder_ms <= 3_600_000:
            raise FormulaError(f"reorder_ms is {reorder_ms}, max_reorder_ms {max_reorder_ms}", where=where,
                               expected="0 to 3,600,000 milliseconds each")  # fmt: skip
        # the delay grows with the disorder seen, from reorder_ms up to max_reorder_ms (on_message)
        self._reorder_ns = round(reorder_ms * 1_000_000)
        self._max_reorder_ns = max(self._reorder_ns, round(max_reorder_ms * 1_000_000))
        self._newest_ns = -(2**62)
        self._late_warned: set[str] = set()
        budget = self._budget
        limits = budget.limits if budget is not None else Limits()
        given = params.get("formulas")
        if isinstance(given, str) and given:
            if params.get("formula"):
                raise FormulaError("both formula and formulas are given", where=where, expected="one of the two params")
            checked = _named(_formulas_param(given, where), where, limits)
        else:
            checked = _named(str(params["formula"]), where, limits)
        idle_ms = float(params.get("idle_ms", DEFAULT_IDLE_NS / 1e6))
        max_objects = int(params.get("max_objects", DEFAULT_MAX_OBJECTS))
        if not 0 < idle_ms <= 86_400_000 or not 1 <= max_objects <= 1_000_000:
            raise FormulaError(f"idle_ms {idle_ms}, max_objects {max_objects}", where=where,
                               expected="idle_ms in (0, 86,400,000] and max_objects in [1, 1,000,000]")  # fmt: skip
        cells = budget.share if budget is not None else limits.max_monitor_cells
        served: list[Served] = []
        for name, formula in checked:
            root = formula.root
            if isinstance(root, Quantifier) and root.kind == "foreach":
                monitor: Monitor | ObjectMonitor = ObjectMonitor(
                    formula, reorder_ns=self._reorder_ns, max_cells=cells, idle_ns=round(idle_ms * 1e6), max_objects=max_objects
                )
            else:
                monitor = Monitor(formula, reorder_ns=self._reorder_ns, max_cells=cells)
            served.append(Served(name, monitor))
        self._served = served
        self.monitor = served[0].monitor
        self.latest = {}
        #: each formula's monitor, by name (by its text for a unit of one formula)
        self.monitors: dict[str, Monitor | ObjectMonitor] = {s.name or s.monitor.formula.text: s.monitor for s in served}
        #: the terms of the formulas, each once: the unit's ports t0, t1, ... in this order
        self.terms: tuple[str, ...] = tuple(_terms(checked))
        terms = self.terms
        # which monitors read each of the unit's terms, and as which of theirs
        self._readers: list[list[tuple[Served, int]]] = [[] for _ in terms]
        for s in served:
            for local, term in enumerate(s.monitor.terms):
                self._readers[terms.index(term)].append((s, local))
        # the terms a foreach quantifies over: the field naming the object, the cap (its first formula's)
        self._domains: dict[int, tuple[tuple[str, ...], int]] = {}
        for s in served:
            if isinstance(s.monitor, ObjectMonitor):
                self._domains.setdefault(terms.index(str(s.monitor.domain.term)), (s.monitor.domain.fields, s.monitor.max_objects))
        self._future_ns = limits.max_future_ns
        #: samples refused because their time lay in the future (see the module documentation)
        self.future = 0
        self._received = 0
        self._ports = {f"t{k}": k for k in range(len(terms))}
        bound = self.get_config()
        missing = [f"{port} for {terms[k]}" for port, k in self._ports.items() if port not in bound]
        if missing or VERDICTS_PORT not in bound:
            raise FormulaError(
                f"the unit lacks ports: {', '.join(missing) or VERDICTS_PORT}",
                where=where,
                expected="the spec monitor_spec(formula) builds: one input per term and the output 'verdicts'",
            )
        self._last_sample = time.monotonic()
        self._listeners: list[Callable[[Verdict], None]] = []
        self._formula_listeners: list[Callable[[str, Verdict], None]] = []
        self.unknown_clock = 0  # samples stamped by a clock whose offset was not known
        # freshness: declared, derived from each term's first samples, or none
        max_age_ms = float(params.get("max_age_ms", 0.0))
        #: each term's maximum age in ns, as set (declared, or derived once enough samples came)
        self.ages: dict[str, int] = {}
        self._derive = max_age_ms == 0
        if max_age_ms > 0:
            for k in range(len(terms)):
                self._set_age(k, round(max_age_ms * 1e6))
        self._spacing: dict[int, list[int]] = {k: [] for k in range(len(terms))}
        self._object_last: dict[str, int] = {}  # a foreach stream's objects' latest sample times, while deriving
        self._last_t: list[int] = [-(2**62)] * len(terms)
        # gaps a re-plan left: (term, cause, from ns, until ns or None while it lasts)
        self._gaps: list[tuple[str, str, int, int | None]] = []
        # fields the formulas read, per term: judged on the term's first samples
        self._fields: dict[int, set[tuple[str, ...]]] = {}
        for _, formula in checked:
            for node in walk(formula.root):
                stream = (
                    node
                    if isinstance(node, Stream)
                    else (node.domain if isinstance(node, Quantifier) and isinstance(node.domain, Stream) else None)
                )
                if stream is not None and stream.fields:
                    self._fields.setdefault(terms.index(str(stream.term)), set()).add(stream.fields)
        self._held_fields: dict[int, set[tuple[str, ...]]] = {k: set() for k in self._fields}
        self._seen_keys: dict[int, set[str]] = {k: set() for k in self._fields}
        self._samples = [0] * len(terms)
        #: what the monitor found wrong with its data (a field no sample holds), each said once
        self.warnings: list[str] = []
        self._changes_only = bool(params.get("changes_only", False))
        # each term's latest samples, which explain a change of a verdict ("why": each comparison
        # with its sides' values at its state); a few only: payloads may be large
        self._explain, self._robust = bool(params.get("explain", True)), bool(params.get("robustness", False))
        self._recent: list[deque[tuple[int, Any]]] = [deque(maxlen=ROBUST_SAMPLES if self._robust else RECENT_SAMPLES) for _ in terms]
        #: the terms bound to what exists and their sources (:mod:`dyknow.reasoning.bindings`)
        self.bound: dict[str, str] = _bound_param(params.get("bound"), terms, where)
        self._textual = frozenset(terms.index(term) for term in self.bound)
        #: the parameterized terms' families and the arguments seen (:mod:`dyknow.reasoning.members`)
        self.families = LiveFamilies([f for _, f in checked], terms)
        quiet_ms = float(params.get("quiet_ms", DEFAULT_QUIET_MS))
        if self.bound and quiet_ms > 0:
            self._quiet_timer = self.create_timer(quiet_ms / 1000, self._warn_quiet)
        self._quiet_s = quiet_ms / 1000
        flush_ms = float(params.get("flush_ms", 0.0))
        self._flush_s = flush_ms / 1000
        self._close_idle = bool(params.get("close_idle", False))
        self._flushed = True  # nothing buffered since the last flush (no sample yet)
        periods = ([max(self._flush_s / 2, 0.001)] if flush_ms > 0 else []) + ([IDLE_CHECK_S] if self._close_idle else [])
        if periods:
            self.create_timer(min(periods), self._flush_if_idle)
        if budget is not None:  # last: a failed setup() has nothing to give back
            budget.check(*(s.monitor.formula for s in served), account=self._account)
            joined: list[Monitor | ObjectMonitor] = []
            try:
                for s in served:
                    budget.join(s.monitor, self._account)
                    joined.append(s.monitor)
            except BaseException:  # (another monitor joined since the check: none of these stays)
                for monitor in joined:
                    budget.leave(monitor)
                raise

    def teardown(self) -> None:
        """Give the monitors' shares of cells and nodes back, and let go of what they keep (an
        object monitor's instances and ids, the last verdict per object), so the memory is free
        once the unit goes, whoever still holds it (a listener, a model snapshot)."""
        if self._budget is not None:
            for served in self._served:
                self._budget.leave(served.monitor)
        for served in self._served:
            if isinstance(served.monitor, ObjectMonitor):
                served.monitor.discard()
            served.last_published = {}
        self._object_last = {}
        self._listeners = []
        self._formula_listeners = []

    def listen(self, callback: Callable[[Verdict], None]) -> None:
        """Call ``callback(verdict)`` for every verdict from now on, on the unit's thread (it must return at once)."""
        self._listeners.append(callback)

    def listen_formulas(self, callback: Callable[[str, Verdict], None]) -> None:
        """As :meth:`listen`, ``callback(formula, verdict)``: ``formula`` is the verdict's
        formula by name (by its text for a formula without one), as :attr:`latest` keys it."""
        self._formula_listeners.append(callback)

    def _take_shares(self) -> None:
        """Give each monitor its share of cells now when monitors joined or left since the last look
        (one comparison when nothing changed: called per sample)."""
        budget = self._budget
        if budget is not None and budget.generation != self._seen_share:
            generation = budget.generation
            for served in self._served:
                budget.take_share(served.monitor, -1)
            self._seen_share = generation  # (read before the shares: a join in between makes the next call look again)

    def on_message(self, port: str, msg: Message) -> None:
        """Push the sample (its origin time, its payload) to every formula that reads its term;
        publish the verdicts it decided."""
        self._take_shares()
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
        k = self._ports[port]
        behind = self._newest_ns - t_ns
        if behind <= 0:
            self._newest_ns = t_ns
        elif 2 * behind > self._reorder_ns and self._reorder_ns < self._max_reorder_ns:
            self._widen(port, behind)
        payload = msg.payload if k not in self._textual else sample_value(msg.payload)
        if k in self.families.ports:  # a member's sample, relayed: the family's value then
            payload = self.families.value(k, t_ns, payload)
            if payload is None:
                self.reject(port, "not a member's sample: {\"arg\": NAME, \"value\": ...} expected on a family's port")
                return
        if k in self.families.reads:  # an argument reads it: a new value plans a member
            self.families.observe(k, payload)
            if len(self.families.full) > self._full_warned:
                self._full_warned += 1
                self.warn(f"{self.families.full[-1]} has {MAX_MEMBERS} members planned, the most: the values past them stay unknown")
        if k in self._domains and type(payload) is list:
            for item in payload:  # a frame: a sample per element (what the fields and the rate are judged on)
                self._observe(k, t_ns, item)
        else:
            self._observe(k, t_ns, payload)
            if self._explain:
                self._recent[k].append((t_ns, payload))
        quiet = self._changes_only and not (self._listeners or self._formula_listeners)
        decided, late = push_sample(self._readers[k], t_ns, payload, quiet)
        for served, verdict, key in decided:
            self._publish(served, verdict, key)
        if late is not None:  # (expected when a term's producer was switched, or hosts interleave)
            closed = late.closed_ns if isinstance(late, Monitor) else None
            reason = f"late: a sample at {t_ns} ns, at or before the last state closed ({closed} ns; reorder delay {late.reorder_ns / 1e6:g} ms)"
            if port not in self._late_warned:  # once per port: the later ones are counted (rejections)
                self._late_warned.add(port)
                self.log.warning("dropped a sample of %s on port %r as late (%s); the later ones are counted as the port's rejections "
                                 "(the reorder delay grows with the disorder seen, up to max_reorder_ms %g ms)", self.terms[k], port, reason,
                                 self._max_reorder_ns / 1e6)  # fmt: skip
            self.reject(port, reason, expected=True)
        self._last_sample = time.monotonic()
        self._flushed = False
        self._received += 1
        if self._received & 16383 == 0:  # (not monitor.states: an object monitor's sums its instances')
            self._report_given_up()

    def _widen(self, port: str, behind_ns: int) -> None:
        """A sample on ``port`` came ``behind_ns`` behind the newest: raise the reorder delay of
        every formula to twice that (at most max_reorder_ms), so the next ones are taken."""
        delay = min(self._max_reorder_ns, 2 * behind_ns)
        self._reorder_ns = delay
        for served in self._served:
            served.monitor.widen(delay)
        self.log.info("a sample on %r came %g ms behind the newest: reorder delay now %g ms", port, behind_ns / 1e6, delay / 1e6)

    # -- what the samples tell: freshness, fields, the end of a gap

    def _observe(self, k: int, t_ns: int, payload: Any) -> None:
        term = self.terms[k]
        last = self._last_t[k]
        if t_ns > last:
            if self._derive and term not in self.ages:
                spacing = self._spacing[k]
                domain = self._domains.get(k)
                if domain is not None:
                    # each object's instance reads its own samples: the spacing that counts is an
                    # object's, not the stream's (1,000 objects at 20 Hz are 0.05 ms apart on it)
                    fields, max_objects = domain
                    key = object_key(read(payload, fields))
                    if key is not None:
                        previous = self._object_last.get(key)
                        if previous is not None and t_ns > previous:
                            spacing.append(t_ns - previous)
                        if previous is not None or len(self._object_last) < max_objects:
                            self._object_last[key] = t_ns
                elif last > -(2**62):
                    spacing.append(t_ns - last)
                if len(spacing) >= _DERIVE_AFTER:
                    self._object_last.clear()
                    self._set_age(k, max(_MIN_AGE_NS, 5 * int(statistics.median(spacing))))
                    self.log.info("the freshness of %s: %.1f ms (5 times the median spacing of its first %d samples)",
                                  term, self.ages[term] / 1e6, len(spacing))  # fmt: skip
            self._last_t[k] = t_ns
        for index, (gap_term, cause, start, end) in enumerate(self._gaps):
            if end is None and gap_term == term and t_ns > start:
                self._gaps[index] = (gap_term, cause, start, t_ns)
        wanted = self._fields.get(k)
        if wanted is None or self._samples[k] > _DERIVE_AFTER:
            return
        self._samples[k] += 1
        held = self._held_fields[k]
        for path in wanted:
            value = payload
            for name in path:
                if type(value) is not dict:
                    break
                self._seen_keys[k].update(str(key)[:64] for key in list(value)[:32])
                if name not in value:
                    break
                value = value[name]
            else:
                held.add(path)
        if self._samples[k] == _DERIVE_AFTER:
            for path in sorted(wanted - held):
                seen = sorted(self._seen_keys[k])[:12]
                field = ".".join(path)
                warning = (
                    f"none of the first {_DERIVE_AFTER} samples of {term} holds the field {field!r} the formula reads"
                    f" (they hold {', '.join(seen) if seen else 'no fields: not JSON objects'}): its atoms stay unknown"
                )
                self.warn(warning, term=term, field=field, fields_seen=seen)

    def warn(self, warning: str, **about: Any) -> None:
        """Say once what is wrong with the monitor's data or plan: in the log, in :attr:`warnings`
        (its model) and as ``{"warning": ...}`` on ``verdicts`` (on the unit's thread)."""
        if warning in self.warnings:
            return
        self.warnings.append(warning)
        self.log.warning("%s", warning)
        self.publish(VERDICTS_PORT, {"warning": warning, **about})

    def _warn_quiet(self) -> None:
        """Once, ``quiet_ms`` after the start: warn of each bound term no sample came from yet."""
        self._quiet_timer.cancel()
        for term, source in self.bound.items():
            k = self.terms.index(term)
            if self._last_t[k] > -(2**62):
                continue
            warning = (
                f"no sample of {term} from its binding {term}={source} in {self._quiet_s:g} s: its values are unknown"
                " (is anything publishing there? a ROS 2 topic's name, type and domain must match)"
            )
            self.warn(warning, term=term, binding=source)

    def _set_age(self, k: int, age_ns: int) -> None:
        """Term ``k``'s maximum age, for every formula that reads it."""
        self.ages[self.terms[k]] = age_ns
        for served, local in self._readers[k]:
            served.monitor.set_max_age(served.monitor.terms[local], age_ns)

    def _report_given_up(self) -> None:
        """Log, now and then (at 1, 10, 100, ... states), that the memory bound gave states up."""
        for served in self._served:
            given_up = served.monitor.given_up
            if given_up > served.given_up_logged:
                served.given_up_logged = 10 ** len(str(given_up))
                self.log.warning(
                    "the memory bound gave up %d states of %s so far (its share of the manager's cells, "
                    "Limits.max_monitor_cells): the verdicts that needed them stay unknown",
                    given_up,
                    "the formula" if served.name is None else f"the formula {served.name!r}",
                )

    def _publish(self, served: Served, verdict: Verdict, key: str | None = None, origin_ns: int | None = None) -> None:
        if self._changes_only:
            last = served.last_published
            if last.get(key) is verdict.verdict:
                if self._listeners or self._formula_listeners:
                    self._tell(served, verdict)
                return
            last[key] = verdict.verdict
            monitor = served.monitor
            if key is not None and isinstance(monitor, ObjectMonitor) and len(last) > 2 * monitor.max_objects + 16:
                live = set(monitor.objects)  # (ids of objects gone for good: kept, they would grow with every id ever seen)
                served.last_published = {k: v for k, v in last.items() if k in live}
        out = verdict.to_json()
        if served.name is not None:
            out["formula"] = served.name
        if key is not None:
            out["object"] = key
        gap = self._gap_for(served, verdict.t_ns)
        if gap is not None:
            out["gap"] = gap
        if key is None and verdict.verdict is not served.last_verdict:
            served.last_verdict = verdict.verdict
            if self._explain and self._may_explain(served, verdict.t_ns):
                out["why"] = self._why(served, verdict.t_ns)
                if self._robust:
                    out["robustness_of"] = self._why(served, verdict.t_ns, robustness=True)
        elif key is not None and self._explain and isinstance(served.monitor, ObjectMonitor):
            seen = served.object_verdicts
            if key not in seen or seen[key] is not verdict.verdict:  # an object's change: its own samples explain it
                seen[key] = verdict.verdict
                if len(seen) > 2 * served.monitor.max_objects + 16:
                    live = set(served.monitor.objects)  # (as last_published: ids of objects gone for good are dropped)
                    served.object_verdicts = {k: v for k, v in seen.items() if k in live}
                if self._may_explain(served, verdict.t_ns):
                    out["why"] = self._why(served, verdict.t_ns, key)
                    if self._robust:
                        out["robustness_of"] = self._why(served, verdict.t_ns, key, robustness=True)
        self.latest[served.name or served.monitor.formula.text] = out
        self.publish(VERDICTS_PORT, out, origin_ns=origin_ns)
        self._tell(served, verdict)

    def _tell(self, served: Served, verdict: Verdict) -> None:
        for listener in self._listeners:
            listener(verdict)
        if self._formula_listeners:
            formula = served.name or served.monitor.formula.text
            for named in self._formula_listeners:
                named(formula, verdict)

    @staticmethod
    def _may_explain(served: Served, t_ns: int) -> bool:
        """A token bucket over sample time: :data:`EXPLAIN_BURST` explanations at once, then one
        per :data:`EXPLAIN_GAP_NS` (a verdict that flips at every sample costs no more)."""
        gained = max(0, t_ns - served.explained_ns) / EXPLAIN_GAP_NS if served.explained_ns else 0.0
        tokens = min(float(EXPLAIN_BURST), served.explain_tokens + gained)
        served.explained_ns = max(served.explained_ns, t_ns)
        if tokens < 1:
            served.explain_tokens = tokens
            return False
        served.explain_tokens = tokens - 1
        return True

    def _why(self, served: Served, t_ns: int, key: str | None = None, *, robustness: bool = False) -> list[str]:
        """Each comparison of the formula with its sides' values at ``t_ns``, from the terms'
        latest samples (a side that reads a window is ``?``: they are not all kept); for the
        object ``key`` of a ``foreach``, its body's, over the object's own among them;
        ``robustness``: each condition subformula's robustness then, over them all."""
        formula = served.monitor.formula
        samples = {term: [row for row in self._recent[self.terms.index(term)] if robustness or row[0] <= t_ns] for term in map(str, formula.terms)}
        try:
            if robustness:  # (while no term's kept samples dropped one, they are the whole trace the unit saw)
                dropped = any(len(self._recent[self.terms.index(term)]) == ROBUST_SAMPLES for term in samples)
                monitor = served.monitor
                if key is not None and isinstance(monitor, ObjectMonitor):
                    return object_robustness_explainer(formula, samples, idle_ns=monitor.idle_ns, kept=dropped)(key, t_ns)
                return robustness_explainer(formula, samples, kept=dropped)(t_ns)
            if key is not None:
                return object_explainer(formula, samples, current_only=True)(key, t_ns)
            return explainer(formula, samples, current_only=True)(t_ns)
        except Exception:  # (an explanation never stops a verdict)
            self.log.debug("cannot explain a verdict of %s", formula.text, exc_info=True)
            return []

    def _gap_for(self, served: Served, t_ns: int) -> dict[str, str] | None:
        """The gap a verdict at ``t_ns`` reads into, if any: its window runs from ``t_ns`` back by
        its formula's past reach and forward by its horizon (a gap of a term the formula does not
        read counts too: the unit's terms were re-planned together)."""
        if not self._gaps:
            return None
        earliest = -(2**62) if served.reach is None else t_ns - served.reach
        latest = t_ns + served.horizon
        for term, cause, start, end in self._gaps:
            if term in served.monitor.terms and start <= latest and (end is None or end >= earliest):
                return {"term": term, "cause": cause}
        return None

    def adapted(self, key: str, cause: str) -> None:
        """The stream on ``key`` was re-planned for ``cause``: when a term reads it, the verdicts
        whose window reaches into the gap say so (any thread may call it: the manager's
        adaptation loop does)."""
        bound = self.get_config()
        for port, k in self._ports.items():
            if bound.get(port) == key:
                gaps = self._gaps
                gaps.append((self.terms[k], cause[:500], self._last_t[k], None))
                if len(gaps) > _MAX_GAPS:
                    del gaps[0]

    def _flush_if_idle(self) -> None:
        if self._flushed:
            return
        idle = time.monotonic() - self._last_sample
        if (self._flush_s > 0 and idle >= self._flush_s) or (self._close_idle and idle >= max(self._reorder_ns / 1e9, IDLE_CLOSE_MIN_S)):
            self._flushed = True
            self._take_shares()
            for served in self._served:
                monitor = served.monitor
                if isinstance(monitor, ObjectMonitor):
                    for key, verdict in monitor.flush():
                        self._publish(served, verdict, key, origin_ns=verdict.decided_ns)
                else:
                    for verdict in monitor.flush():
                        self._publish(served, verdict, origin_ns=verdict.decided_ns)
