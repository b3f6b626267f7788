"""Incremental monitoring: a :class:`Monitor` turns samples into states and publishes each state's
verdict as soon as it is decided, with memory bounded by the formula's horizon.

The semantics is :mod:`dyknow.reasoning.semantics`'s, exactly: over the same states, the verdicts a
monitor returns are those :func:`~dyknow.reasoning.evaluate` gives that are true or false (tests
compare them on random formulas and traces). A verdict is returned at the first state that decides
it: for a past-only formula at its own state, for a future one at the first state after which no
continuation of the trace could change it. A verdict that is never decided (its window is still
incomplete when the input ends, or an atom reads a malformed value) is never returned.

**Samples to states, and late samples.** ``push(term, t_ns, value)`` hands the monitor one sample.
Samples at one time, from any streams, make one state; a state is *closed* (evaluated) once no
sample for its time can still come, by the monitor's reorder policy with delay ``reorder_ns``
(default 0):

- a state at time t is closed once every stream has sent a sample at or after ``t + reorder_ns``,
  or any stream has sent one after ``t + reorder_ns``;
- a sample at or before the last closed state's time is **late**: it is counted in :attr:`Monitor.late`
  and dropped (it cannot join a state already evaluated, and states are never re-evaluated).

So with delay 0 a one-stream monitor closes each state as its sample arrives (a past verdict comes
out with the sample that decides it), and two streams sampled at one time (outputs of one source,
which carry its origin time) form one state as soon as both have arrived. Samples may arrive out of
order across streams, and within a stream, by up to ``reorder_ns`` of sample time without being
late; the price is that states close ``reorder_ns`` later. A stream sending two samples at one time
with delay 0 has the second counted late (:func:`~dyknow.reasoning.evaluate` would take the second).
``flush()`` closes every buffered state (the end of the input).

**How it stays fast and small.** The formula becomes a tree of nodes evaluated bottom-up at each
state (what to make is worked out once per formula and kept with it, so that a ``foreach``
monitor makes each object's monitor, nodes of its own, in a few microseconds). A node without future operators below it is *synchronous*: its verdict is decided at its
state. Past operators over synchronous operands keep O(1) summaries (the last state where the
operand was true, the last where it was not false, the last break of the ``since`` chain, and a
queue of the states still younger than the interval's lower bound), so ``once[0, inf]`` costs the
same as ``once[0, 1s]``. Future operators (and anything above them) keep the states whose verdicts
are pending and sorted lists of where their operands are true, not false, and so on; each newly
decided operand value resolves exactly the pending states it decides, found by bisection as one
contiguous range. States older than the formula's horizon are dropped: :meth:`Monitor.retained`
says how many are kept.

**Memory, bounded whatever the sample rate.** The horizon bounds the states kept in time, not in
number: a window of a day at a thousand samples a second is 86 million states. So a monitor also
keeps at most ``max_cells`` *cells* (:data:`DEFAULT_MAX_CELLS`; a manager shares
``Limits.max_monitor_cells`` among its monitors): a cell is one node's entry for one retained
state, so at most ``max_cells // nodes`` states (:attr:`Monitor.max_states`, never fewer than
:data:`MIN_STATES`) are retained, buffered for the reorder delay, or wait to enter a past window
(``once[a, b]`` holds the states younger than ``a``). Over it, the oldest are **given up**, a
quarter of the bound at a time, and counted in :attr:`Monitor.given_up`:

- a retained state is dropped: its verdicts still pending stay unknown (never returned), and a
  past window that reaches a state given up is never found false (a term there may have been
  true) nor located by it (its end among them: unknown);
- a state waiting to enter a past window is dropped: the window is never found false while it
  may hold it, unless a false left operand of ``since`` cuts it off;
- a buffered sample's state is closed at once: later samples at its time are late.

So the rule stays: **every verdict returned is evaluate()'s**; over the bound, fewer are
returned (tests run random formulas with the fewest cells against evaluate()). A cell costs 12 to
50 bytes as measured interpreted and 21 to 73 compiled (``tracemalloc``, when each state index a
list held was an int object of its own; a state's index and time are now one int object each,
shared by every list that holds them, so no more), and at most about 250 by construction (six
list slots per temporal node and state, each with its int, plus each state's time), so a monitor
keeps at most about ``250 * max_cells`` bytes, besides the payloads its reorder buffer holds.
"""

from __future__ import annotations

import heapq
from collections.abc import Mapping, Sequence
from typing import Any, Final

from dyknow.errors import ClosedError, FormulaError, TagError, did_you_mean
from dyknow.reasoning.aggregates import AggregateValue
from dyknow.reasoning.families import Members
from dyknow.reasoning.future import UntilNode, UntilSync
from dyknow.reasoning.nodes import (
    AND,
    IMPLIES,
    OR,
    ArithValue,
    AtomNode,
    BinaryNode,
    CallValue,
    Condition,
    ConstNode,
    ConstValue,
    EdgeNode,
    IndexValue,
    NotNode,
    PrevNode,
    PrevValue,
    RawStreamValue,
    RobustnessValue,
    Step,
    StreamValue,
    Value,
    VerdictValue,
)
from dyknow.reasoning.past import SinceNode, SinceSync
from dyknow.reasoning.robustness import RNode, RobustnessTree
from dyknow.reasoning.syntax import (
    Aggregate,
    Always,
    And,
    Arith,
    Atom,
    Call,
    Const,
    Eventually,
    Fall,
    Formula,
    Historically,
    Implies,
    Index,
    Neg,
    Node,
    Not,
    Num,
    Once,
    Or,
    Prev,
    Quantifier,
    Rise,
    Since,
    Str,
    Stream,
    Until,
    Var,
    children,
    parse,
    walk,
)
from dyknow.reasoning.timeline import NEVER, Clock, Held
from dyknow.reasoning.values import FALSE, TRUE, UNKNOWN
from dyknow.tags import parse_term

__all__ = ["DEFAULT_MAX_CELLS", "MIN_STATES", "Monitor", "Verdict"]

DEFAULT_MAX_CELLS: Final = 2_000_000
"""The cells a :class:`Monitor` keeps at most unless told otherwise (``dyknow.security.Limits.max_monitor_cells``)."""
MIN_STATES: Final = 16
"""The states a monitor may always keep, however small its share of cells."""


class Verdict:
    """A decided verdict: the state ``state`` (0 for the first) at ``t_ns`` is ``verdict``, decided
    when the state at ``decided_ns`` closed (``decided_ns == t_ns`` for a past-only formula).

    Plain data, compared by value. Not a frozen dataclass, as house style would have it, because
    one is made per state and a frozen dataclass costs five times more to make (590 ns against
    115 ns compiled, measured); its attributes are ``Final``, so read-only where mypyc compiles
    this module (the default install), and to be treated as read-only elsewhere.
    """

    def __init__(self, state: int, t_ns: int, verdict: bool, decided_ns: int, robustness: float | None = None) -> None:
        self.state: Final = state
        self.t_ns: Final = t_ns
        self.verdict: Final = verdict
        self.decided_ns: Final = decided_ns
        #: the state's robustness (a monitor asked for it: ``Monitor(robustness=True)``), None where undefined
        self.robustness: Final = robustness

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Verdict):
            return NotImplemented
        return (self.state, self.t_ns, self.verdict, self.decided_ns, self.robustness) == (
            other.state, other.t_ns, other.verdict, other.decided_ns, other.robustness
        )  # fmt: skip

    def __hash__(self) -> int:
        return hash((self.state, self.t_ns, self.verdict, self.decided_ns))

    def __repr__(self) -> str:
        rob = f", robustness={self.robustness}" if self.robustness is not None else ""
        return f"Verdict(state={self.state}, t_ns={self.t_ns}, verdict={self.verdict}, decided_ns={self.decided_ns}{rob})"

    def to_json(self) -> dict[str, Any]:
        """What a monitor unit publishes: ``{"t", "verdict", "decided_t"}`` in seconds, and the
        exact integer nanoseconds and state index beside them; ``robustness`` when known (an
        infinite one as the strings ``"inf"`` and ``"-inf"``: JSON has no infinities)."""
        out: dict[str, Any] = {
            "t": self.t_ns / 1e9,
            "verdict": self.verdict,
            "decided_t": self.decided_ns / 1e9,
            "t_ns": self.t_ns,
            "decided_ns": self.decided_ns,
            "state": self.state,
        }
        rob = self.robustness
        if rob is not None:
            out["robustness"] = rob if rob - rob == 0.0 else ("inf" if rob > 0 else "-inf")
        return out


def _negated(node: Node) -> bool:
    return isinstance(node, Always | Historically)


class _Entry:
    """One node of a formula's tree as every monitor of it makes it: its operands' entries, how
    far ahead it and they read, the terms it reads (itself or below); a stream's term and
    rawness, or the entry of the same stream made already (one node per term, fields and
    rawness, however often written)."""

    def __init__(self, node: Node, kids: list[int], below: int, horizon: int, reads: list[int]) -> None:
        self.node = node
        self.kids = kids
        self.below = below
        self.horizon = horizon
        self.reads = reads  # (sorted; the windows made from it share the list and never change it)
        self.k = -1
        self.raw = False
        self.same = -1
        self.robustness = False  # robustness(F): a robustness tree of F's own
        # what Monitor._make makes (_describe): a kind, and what the node says of it
        self.op = _VALUE
        self.value: Any = None
        self.lo = 0
        self.hi: int | None = None
        self.two = False  # until, since: with a left operand
        self.negate = False  # always, historically


# the kinds of node an entry makes (_Entry.op)
_VALUE: Final = 0
_VAR: Final = 1
_INDEX: Final = 2
_ARITH: Final = 3
_CALL: Final = 4
_AGGREGATE: Final = 5
_PREV: Final = 6
_EDGE: Final = 7
_ATOM: Final = 8
_CONST: Final = 9
_NOT: Final = 10
_BINARY: Final = 11
_FUTURE: Final = 12
_PAST: Final = 13


def _describe(entry: _Entry, node: Node, raw: set[int]) -> None:
    """Say in ``entry`` what node the syntax ``node`` makes (besides streams and robustness()),
    so that a monitor makes it without looking at the syntax again."""
    if isinstance(node, Num | Str):
        entry.op, entry.value = _VALUE, node.value
    elif isinstance(node, Var):
        entry.op, entry.value = _VAR, node.name
    elif isinstance(node, Index):
        entry.op, entry.raw = _INDEX, id(node) in raw
    elif isinstance(node, Neg):
        entry.op, entry.value = _CALL, "neg"
    elif isinstance(node, Arith):
        entry.op, entry.value = _ARITH, node.op
    elif isinstance(node, Call):
        entry.op, entry.value = _CALL, node.fn
    elif isinstance(node, Aggregate):
        entry.op, entry.value, entry.lo, entry.hi = _AGGREGATE, node.kind, node.interval.lo_ns, node.interval.hi_ns
    elif isinstance(node, Prev):
        entry.op = _PREV
    elif isinstance(node, Rise | Fall):
        entry.op, entry.value = _EDGE, isinstance(node, Rise)
    elif isinstance(node, Atom):
        entry.op, entry.value = _ATOM, node.op
    elif isinstance(node, Const):
        entry.op, entry.value = _CONST, TRUE if node.value else FALSE
    elif isinstance(node, Not):
        entry.op = _NOT
    elif isinstance(node, And | Or | Implies):
        entry.op, entry.value = _BINARY, AND if isinstance(node, And) else OR if isinstance(node, Or) else IMPLIES
    else:
        assert isinstance(node, Eventually | Always | Until | Once | Historically | Since)
        entry.op = _FUTURE if isinstance(node, Eventually | Always | Until) else _PAST
        entry.two = isinstance(node, Until | Since)
        entry.lo, entry.hi, entry.negate = node.interval.lo_ns, node.interval.hi_ns, _negated(node)


class _Plan:
    """What every monitor of one formula works out alike from its tree, once (kept with the
    formula: :meth:`Formula.memo`): the terms, the nodes to make operands first, and the sum of
    the windows' widths. A foreach monitor makes one monitor of its body per object, and walking
    the tree for each was most of what an object cost; each monitor still makes nodes of its own
    (they hold its states), so monitors of one formula share nothing that changes."""

    def __init__(self, formula: Formula) -> None:
        for part in formula.walked:
            if isinstance(part, Quantifier):
                raise FormulaError(
                    f"the formula holds the quantifier '{part.kind} {part.var} in {part.domain}'",
                    where=f"monitor of {str(formula)!r}",
                    expected="a formula whose forall/exists are expanded (dyknow.reasoning.expand); foreach: an ObjectMonitor",
                )
        self.terms: tuple[str, ...] = tuple(str(term) for term in formula.terms)
        self.index = {term: k for k, term in enumerate(self.terms)}
        self.raw = formula.raw
        self.horizon_ns = formula.horizon_ns
        self.widths = sum(
            (n.interval.hi_ns or n.interval.lo_ns) for n in formula.walked if isinstance(n, Historically | Once | Since | Aggregate | Always | Eventually | Until)
        )
        self.entries: list[_Entry] = []
        self.positions: dict[int, int] = {}  # id of a node of the tree -> its entry
        # iterative post-order: formulas may nest deeper than Python's recursion allows
        streams: dict[tuple[int, tuple[str, ...], bool], int] = {}
        stack: list[tuple[Node, bool]] = [(formula.root, False)]
        while stack:
            current, expanded = stack.pop()
            if id(current) in self.positions:
                continue
            kids = children(current)
            if not expanded and kids:
                stack.append((current, True))
                stack.extend((kid, False) for kid in kids)
                continue
            operands = [self.entries[self.positions[id(kid)]] for kid in kids]
            below = max((kid.horizon for kid in operands), default=0)
            own = current.interval.hi_ns or 0 if isinstance(current, Always | Eventually | Until) else 0
            reads: set[int] = set()
            for kid in operands:
                reads.update(kid.reads)
            entry = _Entry(current, [self.positions[id(kid)] for kid in kids], below, below + own, [])
            if isinstance(current, Stream):
                entry.k = self.index[str(current.term)]
                entry.raw = id(current) in self.raw
                reads.add(entry.k)
                entry.same = streams.setdefault((entry.k, current.fields, entry.raw), len(self.entries))
                if entry.same == len(self.entries):
                    entry.same = -1
            elif isinstance(current, Call) and current.fn == "robustness":
                entry.robustness = True
            else:
                _describe(entry, current, self.raw)
            entry.reads = sorted(reads)
            self.positions[id(current)] = len(self.entries)
            self.entries.append(entry)


def _plan(formula: Formula) -> _Plan:
    return _Plan(formula)


class Monitor:
    """Monitors one formula over streams of samples, incrementally (see the module documentation).

    ``formula`` is text or a parsed :class:`~dyknow.reasoning.Formula`; ``reorder_ns`` is how much
    later (in sample time) a sample may come than a newer one and still count. ``push`` a sample,
    get the verdicts it decided; :meth:`flush` at the end of the input. Not thread-safe: one
    caller at a time (a unit's callbacks are).
    """

    def __init__(
        self,
        formula: str | Formula,
        *,
        reorder_ns: int = 0,
        max_cells: int = DEFAULT_MAX_CELLS,
        max_age_ns: Mapping[str, int] | None = None,
        variables: Mapping[str, Any] | None = None,
        robustness: bool = False,
    ) -> None:
        self.formula = parse(formula) if isinstance(formula, str) else formula
        if reorder_ns < 0:
            raise FormulaError(f"reorder_ns is {reorder_ns}", where="Monitor(reorder_ns=...)", expected="0 or more nanoseconds")
        if max_cells < 1:
            raise FormulaError(f"max_cells is {max_cells}", where="Monitor(max_cells=...)", expected="1 or more cells")
        plan = self.formula.memo("monitor plan", _plan)
        assert isinstance(plan, _Plan)
        self.reorder_ns = int(reorder_ns)
        #: the terms as the formula writes them, in order of first appearance (push's ``term``)
        self.terms: tuple[str, ...] = plan.terms
        self._index = dict(plan.index)  # (its own: _term_index adds the other spellings it is pushed)
        self._members: Members | None = None  # a parameterized term's families, once a member is pushed by name
        self._variables: dict[str, Any] = dict(variables or {})
        self._times = Held(len(self.terms))
        self._clock = Clock()
        self._nodes: list[Condition] = []
        self._values: list[Value] = []
        self._steps: list[Step] = []  # every node, operands first: what a state steps through
        self._raw: set[int] = plan.raw  # the ids of the nodes read as they are (tree.raw_reads)
        # the robustness tree beside the verdict nodes, when asked for (dyknow.reasoning.robustness)
        self._robust: RobustnessTree | None = RobustnessTree(0) if robustness else None
        self._rob_wait: list[tuple[int, int, bool, int]] = []  # verdicts decided before their robustness
        root = self._build(plan)
        if not isinstance(root, Condition):  # (the parser makes the root a condition)
            raise FormulaError("the formula is a value, not a condition", where=f"monitor of {str(self.formula)!r}", expected="a condition")
        self._root = root
        span = plan.horizon_ns
        for node in self._nodes:
            if node.need_ns > span:
                span = node.need_ns
        self._span_ns = span
        # stale spans are kept as far back as any bounded window may read, all windows at once
        self._times.keep_ns = self._span_ns + plan.widths
        if self._robust is not None:
            self._robust.keep_ns = self._times.keep_ns + plan.horizon_ns
        # with a future operator somewhere, nodes read their operands' verdicts at older states:
        # every asynchronous node keeps them, and a synchronous one only if an asynchronous
        # and/or/implies reads it at the states its other operand decides later (the temporal
        # nodes read a synchronous operand at its own state only: ``cur``)
        self._history = not all(node.sync for node in self._nodes)
        for node in self._nodes:
            node.history = not node.sync
        for node in self._nodes:
            if isinstance(node, BinaryNode) and not node.sync:
                node.left.history = True
                node.right.history = True
        self._first_step: Step | None = None
        for each in reversed(self._steps):
            each.next_step = self._first_step
            self._first_step = each
        self._single = len(self.terms) == 1
        self._immediate = self._single and self.reorder_ns == 0
        self._held: list[Any] = [None] * len(self.terms)
        self._seen = [False] * len(self.terms)
        self._missing = len(self.terms)
        self._newest = [NEVER] * len(self.terms)
        self._max_t = NEVER
        self._buffer: list[tuple[int, int, int, Any]] = []  # (t, arrival, term, value)
        self._arrivals = 0
        self._states = 0
        self._closed_t = NEVER
        self._closed = False
        self._trim_from = 0
        self._given_up = 0
        self._waiting: list[SinceSync | AggregateValue] = []  # their own count
        for each in self._steps:
            if isinstance(each, SinceSync) or isinstance(each, AggregateValue):
                self._waiting.append(each)
        self._max_states = 0
        self.set_max_cells(max_cells)
        for term, age in (max_age_ns or {}).items():
            self.set_max_age(term, age)
        #: samples dropped because they came at or before the last closed state's time
        self.late = 0

    def set_max_cells(self, max_cells: int) -> None:
        """Keep at most ``max_cells`` cells from now on (a manager shares its monitors' cells out
        as they come and go): ``max_cells // nodes`` states, and never fewer than :data:`MIN_STATES`."""
        holders = len(self._nodes) + sum(1 for node in self._values if isinstance(node, AggregateValue))  # (values keep no states)
        states = max(MIN_STATES, max_cells // holders)
        self._max_states = states
        self._times.max_periods = states
        for node in self._steps:
            node.max_states = states

    @property
    def reach_ns(self) -> int:
        """How far before its newest sample the monitor keeps what its windows may read (the
        outages of its terms included)."""
        return int(self._times.keep_ns)

    def outage(self, term: str, from_ns: int, until_ns: int) -> None:
        """Tell the monitor that ``term`` was stale in the open span ``(from_ns, until_ns)`` before
        its first sample here: what a monitor made late (a ``foreach`` object's, seeded with the
        term's latest sample) cannot see itself, so that a window of its first states that
        reaches back into the outage counts it (the semantics' span rule). In time order, and
        before the term's first sample; else :class:`FormulaError`."""
        k = self._index.get(term)
        if k is None:
            k = self._term_index(term)
        periods = self._times.periods[k]
        if self._times.times[k] != NEVER or (periods and periods[-1][1] > from_ns) or until_ns <= from_ns:
            raise FormulaError(f"an outage of {term!r} from {from_ns} to {until_ns} ns", where=f"monitor of {str(self.formula)!r}",
                               expected="outages in time order, each before the term's first sample")  # fmt: skip
        periods.append((int(from_ns), int(until_ns)))

    def widen(self, reorder_ns: int) -> None:
        """Raise the reorder delay to ``reorder_ns`` (never lower it): states close that much later
        from now on, so samples that much out of order are taken (what is closed stays closed)."""
        if reorder_ns > self.reorder_ns:
            self.reorder_ns = int(reorder_ns)
            self._immediate = False

    def set_max_age(self, term: str, max_age_ns: int | None) -> None:
        """From now on, ``term``'s value is unknown at a state more than ``max_age_ns`` after its
        latest sample (None: no bound; see the semantics' freshness)."""
        k = self._index.get(term)
        if k is None:
            k = self._term_index(term)
        ages = self._times.max_age
        ages[k] = -1 if max_age_ns is None else int(max_age_ns)
        self._times.aged = any(age >= 0 for age in ages)

    # -- building

    def _build(self, plan: _Plan) -> Condition | Value:
        """Make the formula's nodes, operands first, as ``plan`` lists them; the root is the last."""
        built: list[Condition | Value] = []
        robs: list[RNode | None] = []  # a condition's robustness node (when asked for)
        robust = self._robust is not None
        for entry in plan.entries:
            if entry.same >= 0:
                built.append(built[entry.same])  # (stepped already)
                robs.append(None)
                continue
            node = entry.node
            made: Condition | Value
            if entry.k >= 0:
                stream = node
                assert isinstance(stream, Stream)
                made = RawStreamValue(entry.k, stream.fields, self._times) if entry.raw else StreamValue(entry.k, stream.fields, self._times)
            elif entry.robustness:
                call = node
                assert isinstance(call, Call)
                made = self._robustness_value(call.args[0], plan, built)
            else:
                made = self._make(entry, [built[p] for p in entry.kids])
            if isinstance(made, UntilNode) or isinstance(made, UntilSync) or isinstance(made, SinceNode) or isinstance(made, SinceSync) or isinstance(made, AggregateValue):
                made.held = self._times  # its windows ask whether a term below was stale in them
                made.below = entry.reads
            if isinstance(made, Condition):
                if robust:
                    kids = [r for r in (robs[p] for p in entry.kids) if r is not None]
                    robs.append(self._rob_node(node, made, kids, entry.reads))
                else:
                    robs.append(None)
                self._nodes.append(made)
            else:
                robs.append(None)
                self._values.append(made)
            if not isinstance(made, ConstValue):  # (a constant has nothing to step)
                self._steps.append(made)
            built.append(made)
        return built[-1]

    def _robustness_value(self, root: Node, plan: _Plan, built: list[Condition | Value]) -> Value:
        """``robustness(F)``: a robustness tree of F's own, over its verdict nodes (built already)."""
        tree = RobustnessTree(0)
        robs: dict[int, RNode] = {}
        for node in reversed(walk(root)):  # children before parents
            entry = plan.positions[id(node)]
            made = built[entry]
            if isinstance(made, Condition):
                robs[id(node)] = self._rob_node(node, made, [robs[id(k)] for k in children(node) if id(k) in robs], plan.entries[entry].reads, tree)
        tree.keep_ns = sum((n.interval.hi_ns or n.interval.lo_ns) for n in walk(root) if isinstance(n, Historically | Once | Since | Aggregate))
        return RobustnessValue(tree)

    def _rob_node(self, node: Node, made: Condition, kids: list[RNode], below: list[int], tree: RobustnessTree | None = None) -> RNode:
        """The robustness node of a condition (see :mod:`dyknow.reasoning.robustness`)."""
        tree = tree if tree is not None else self._robust
        assert tree is not None
        held = self._times
        if isinstance(node, Atom):
            return tree.atom(made)
        if isinstance(node, Const):
            return tree.const(node.value)
        if isinstance(node, Not):
            return tree.negation(kids[0])
        if isinstance(node, And | Or | Implies):
            return tree.boolean("and" if isinstance(node, And) else "or" if isinstance(node, Or) else "implies", kids[0], kids[1])
        if isinstance(node, Rise | Fall):
            return tree.edge(isinstance(node, Rise), kids[0])
        if isinstance(node, Prev):
            return tree.prev(kids[0])
        if isinstance(node, Always | Eventually | Until | Historically | Once | Since):
            left, right = (kids[0], kids[1]) if isinstance(node, Until | Since) else (None, kids[0])

            def stale(lo: int | None, hi: int, below: list[int] = below) -> bool:
                return held.stale(below, lo, hi)

            return tree.window(
                left, right, node.interval.lo_ns, node.interval.hi_ns,
                future=isinstance(node, Always | Eventually | Until), negate=isinstance(node, Always | Historically), stale=stale,
            )  # fmt: skip
        raise FormulaError(f"no robustness for {type(node).__name__}", where=f"monitor of {str(self.formula)!r}", expected="an STL formula")

    def _value(self, node: Condition | Value) -> Value:
        """An operand as a value: a condition's verdict becomes True, False or unknown."""
        if isinstance(node, Value):
            return node
        made = VerdictValue(node)
        self._values.append(made)
        self._steps.append(made)
        return made

    def _make(self, entry: _Entry, args: list[Condition | Value]) -> Condition | Value:
        """The node of ``entry`` over its operands' nodes ``args`` (what it makes: ``_describe``)."""
        clock = self._clock
        op = entry.op
        if op == _VALUE:
            return ConstValue(entry.value)
        if op == _VAR:
            if entry.value not in self._variables:
                raise FormulaError(f"the variable {entry.value!r} has no value", where=f"monitor of {str(self.formula)!r}",
                                   expected="Monitor(variables={...}) for a quantifier's body")  # fmt: skip
            return ConstValue(self._variables[entry.value])
        if op == _INDEX:
            return IndexValue(self._value(args[0]), [self._value(a) for a in args[1:]], entry.raw)
        if op == _ARITH:
            return ArithValue(entry.value, self._value(args[0]), self._value(args[1]))
        if op == _CALL:  # (a negation too: the call "neg")
            return CallValue(entry.value, [self._value(a) for a in args])
        if op == _AGGREGATE:
            arg = args[0]
            if entry.value == "count":
                assert isinstance(arg, Condition)
                return AggregateValue(entry.value, entry.lo, entry.hi, None, arg)
            return AggregateValue(entry.value, entry.lo, entry.hi, self._value(arg), None)
        if op == _PREV:
            arg = args[0]
            if isinstance(arg, Condition):
                return PrevNode(clock, arg)
            return PrevValue(arg)
        if op == _EDGE:
            arg = args[0]
            assert isinstance(arg, Condition)
            return EdgeNode(clock, entry.value, arg)
        if op == _ATOM:
            return AtomNode(clock, entry.value, self._value(args[0]), self._value(args[1]) if len(args) > 1 else None)
        if op == _CONST:
            return ConstNode(clock, entry.value)
        conds: list[Condition] = []
        for a in args:
            assert isinstance(a, Condition), "the parser makes every operand of a connective a condition"
            conds.append(a)
        if op == _NOT:
            return NotNode(clock, conds[0])
        if op == _BINARY:
            return BinaryNode(clock, entry.value, conds[0], conds[1], entry.horizon)
        left, right = (conds[0], conds[1]) if entry.two else (None, conds[0])
        sync = right.sync and (left is None or left.sync)
        hi = entry.hi
        if op == _FUTURE:
            assert hi is not None
            if sync:
                return UntilSync(clock, left, right, entry.lo, hi, entry.negate, entry.horizon)
            return UntilNode(clock, left, right, entry.lo, hi, entry.negate, entry.horizon, entry.horizon)
        if sync:
            return SinceSync(clock, left, right, entry.lo, hi, entry.negate)
        # it reads back to the window's start (or, unbounded, its end: older states count as one)
        reach = hi if hi is not None else entry.lo
        return SinceNode(clock, left, right, entry.lo, hi, entry.negate, entry.below + reach, entry.below)

    # -- input

    def push(self, term: str, t_ns: int, value: Any) -> list[Verdict]:
        """Hand over one sample of ``term`` (as the formula writes it) at ``t_ns``; returns the
        verdicts decided by the states it closed (often none, or the one of its own state)."""
        k = self._index.get(term)
        if k is None:
            if self._members is None:
                self._members = Members(self.formula.terms)
            member = self._members.find(term)
            if member is not None:  # SpeedLimit(z1) of SpeedLimit(State(r).zone): its family's value then
                if t_ns <= self._closed_t and not self._closed:  # late: dropped, and its family never holds it
                    self.late += 1
                    return []
                return self.push_index(member[0], t_ns, self._members.value(member[0], member[1], t_ns, value))
            k = self._term_index(term)
        return self.push_index(k, t_ns, value)

    def _term_index(self, term: str) -> int:
        try:
            k = self._index.get(str(parse_term(term)))
        except TagError:
            k = None
        if k is None:
            raise FormulaError(
                f"the formula does not mention the term {term!r}",
                where=f"monitor of {str(self.formula)!r}",
                expected="one of " + ", ".join(repr(t) for t in self.terms) + did_you_mean(term, self.terms),
            )
        self._index[term] = k
        return k

    def push_index(self, k: int, t_ns: int, value: Any) -> list[Verdict]:
        """:meth:`push` with the term given by its position in :attr:`terms` (saves a lookup)."""
        if self._closed:
            raise ClosedError("the monitor is closed", where=f"monitor of {str(self.formula)!r}", expected="push before close()")
        if t_ns <= self._closed_t:
            self.late += 1
            return []
        out: list[Verdict] = []
        boxed: Any = t_ns  # (compiled: one int object for every list that keeps the time)
        if self._immediate:  # one stream, no delay: every sample on time closes its state at once
            self._closed_t = t_ns
            self._max_t = t_ns
            self._held[0] = value
            self._times.sample(0, t_ns, boxed)
            if self._missing:
                self._seen[0] = True
                self._missing = 0
            self._state(t_ns, out, boxed)
            return out
        if t_ns > self._newest[k]:
            self._newest[k] = boxed
        if t_ns > self._max_t:
            self._max_t = t_ns
        buffer = self._buffer
        if not buffer and self._ready(t_ns):  # the common case: in order, nothing to wait for
            self._closed_t = t_ns
            self._hold(k, value, t_ns, boxed)
            if not self._missing:
                self._state(t_ns, out, boxed)
            return out
        self._arrivals += 1
        heapq.heappush(buffer, (t_ns, self._arrivals, k, value))
        while buffer and self._ready(buffer[0][0]):
            self._close_first(out)
        while len(buffer) > self._max_states:  # over the memory bound: close the earliest state early
            self._given_up += 1
            self._close_first(out)
        return out

    def push_all(self, t_ns: int, values: Sequence[Any]) -> list[Verdict]:
        """One sample of every term at ``t_ns`` (``values`` in :attr:`terms` order): a synchronized
        record, such as a row of a log; the same as pushing them one by one, in one call."""
        if len(values) != len(self.terms):
            raise FormulaError(
                f"{len(values)} values for {len(self.terms)} terms",
                where="Monitor.push_all",
                expected="one value per term: " + ", ".join(self.terms),
            )
        if self._closed:
            raise ClosedError("the monitor is closed", where=f"monitor of {str(self.formula)!r}", expected="push before close()")
        if t_ns <= self._closed_t:
            self.late += len(values)
            return []
        newest = self._newest
        boxed: Any = t_ns  # (compiled: one int object for every list that keeps the time)
        buffer = self._buffer
        count = len(newest)
        if not buffer:  # then every sample so far is at or before the last closed state: before t_ns
            for k in range(count):
                newest[k] = boxed
            self._max_t = t_ns
        else:
            for k in range(count):
                if t_ns > newest[k]:
                    newest[k] = boxed
            if t_ns > self._max_t:
                self._max_t = t_ns
        out: list[Verdict] = []
        # (every term's newest sample is at t_ns or after now: without a delay the state is ready)
        if not buffer and (self.reorder_ns == 0 or self._ready(t_ns)):
            self._closed_t = t_ns
            if self._missing:
                for k in range(count):
                    self._hold(k, values[k], t_ns, boxed)
            else:  # (indexed, not enumerate(): compiled, that makes no tuple per value)
                held = self._held
                times = self._times
                if times.aged:
                    for k in range(count):
                        held[k] = values[k]
                        times.sample(k, t_ns, boxed)
                else:  # (no term with a maximum age: a sample's time is all there is to keep)
                    latest = times.times
                    if isinstance(values, tuple):  # (compiled: a tuple's items read natively)
                        for k in range(count):
                            held[k] = values[k]
                            latest[k] = boxed
                    else:
                        for k in range(count):
                            held[k] = values[k]
                            latest[k] = boxed
            if not self._missing:
                self._state(t_ns, out, boxed)
            return out
        for k, value in enumerate(values):
            self._arrivals += 1
            heapq.heappush(buffer, (t_ns, self._arrivals, k, value))
        while buffer and self._ready(buffer[0][0]):
            self._close_first(out)
        while len(buffer) > self._max_states:
            self._given_up += 1
            self._close_first(out)
        return out

    def flush(self) -> list[Verdict]:
        """Close every buffered state now (the input ended, or its delay is known to have passed);
        returns the verdicts that decided. Samples at or before the newest time are late after it."""
        out: list[Verdict] = []
        while self._buffer:
            self._close_first(out)
        if self._rob_wait:  # (their windows never complete: no robustness)
            out.extend(Verdict(state, t_ns, verdict, decided_ns, None) for state, t_ns, verdict, decided_ns in self._rob_wait)
            self._rob_wait = []
        return out

    def close(self) -> list[Verdict]:
        """:meth:`flush`, then refuse further samples; safe twice (the second returns nothing)."""
        if self._closed:
            return []
        out = self.flush()
        self._closed = True
        return out

    def _ready(self, t: int) -> bool:
        """Whether no sample at ``t`` can still come, by the reorder policy."""
        delay = self.reorder_ns
        if self._max_t - delay > t:
            return True
        if self._single:
            return self._newest[0] - delay >= t
        return min(self._newest) - delay >= t

    def _close_first(self, out: list[Verdict]) -> None:
        """Close the earliest buffered state: hold its samples' values (in arrival order), evaluate it."""
        buffer = self._buffer
        t = buffer[0][0]
        boxed: Any = t
        self._closed_t = t
        while buffer and buffer[0][0] == t:
            _t, _arrival, k, value = heapq.heappop(buffer)
            self._hold(k, value, t, boxed)
        if not self._missing:  # states start when every stream has a value
            self._state(t, out, boxed)

    def _hold(self, k: int, value: Any, t: int, boxed: Any) -> None:
        """Hold term ``k``'s value at ``t`` (``boxed``: the same int as an object)."""
        self._held[k] = value
        self._times.sample(k, t, boxed)
        if not self._seen[k]:
            self._seen[k] = True
            self._missing -= 1

    def _state(self, t: int, out: list[Verdict], boxed: Any) -> None:
        """Evaluate the state at ``t`` (``boxed``: the same int as an object): every node
        bottom-up; collect the root's decided verdicts."""
        n = self._states
        self._states = n + 1
        held = self._held
        history = self._history
        if history:
            clock = self._clock
            clock.times.append(boxed)
            number: Any = n  # (boxed once: the lists that hold state n share it)
            clock.idx.append(number)
        if n == 0:
            self._times.first_t = t
        step = self._first_step
        while step is not None:
            step.step(n, t, held)
            step = step.next_step
        root = self._root
        robust = self._robust
        if robust is not None:
            robust.step(n, t)
            first = len(out)
        if root.sync:
            value = root.cur
            if value != UNKNOWN:
                out.append(Verdict(n, t, value == TRUE, t))
        if history:
            count = root.nev
            if count and not root.sync:
                clock = self._clock
                base = clock.base
                if count == 1:  # (the common case, without a new list)
                    i: int = root.events[0]
                    out.append(Verdict(i, clock.times[i - base], root.vals[i - base] == TRUE, t))
                else:
                    events: list[int] = root.events[:count]
                    events.sort()
                    for i in events:
                        out.append(Verdict(i, clock.times[i - base], root.vals[i - base] == TRUE, t))
            self._trim(t)
        if robust is not None:
            self._with_robustness(out, first, t)
            robust.trim(t)

    def _with_robustness(self, out: list[Verdict], first: int, t: int) -> None:
        """Give the verdicts decided now their robustness; hold those whose robustness is not
        known yet (a future window not complete), and give out the held ones now known."""
        robust = self._robust
        assert robust is not None
        decided = out[first:]
        del out[first:]
        waiting = self._rob_wait
        waiting.extend((v.state, v.t_ns, v.verdict, v.decided_ns) for v in decided)
        still: list[tuple[int, int, bool, int]] = []
        for state, t_ns, verdict, decided_ns in waiting:
            known, rob = robust.get(state)
            if known:
                out.append(Verdict(state, t_ns, verdict, decided_ns if decided_ns >= t else t, rob))
            else:
                still.append((state, t_ns, verdict, decided_ns))
        self._rob_wait = still

    def _trim(self, t: int) -> None:
        """Drop states older than the formula needs (in batches, so it costs O(1) per state)."""
        clock = self._clock
        times = clock.times
        edge = t - self._span_ns
        k = self._trim_from
        while k < len(times) - 1 and times[k] < edge:
            k += 1
        self._trim_from = k
        if k >= 64 and k * 2 >= len(times):
            self._drop(k)
        if len(times) > self._max_states:  # over the memory bound: give up the oldest states
            k = min(len(times) - self._max_states + self._max_states // 4, len(times) - 1)
            needed = k - self._trim_from  # (those before _trim_from are older than the formula reads)
            if needed > 0:
                clock.given_up_t = times[k - 1]
                self._given_up += needed
            self._drop(k)

    def _drop(self, k: int) -> None:
        """Drop the ``k`` oldest retained states."""
        clock = self._clock
        del clock.times[:k]
        del clock.idx[:k]
        for node in self._nodes:
            del node.vals[:k]
        clock.base += k
        self._trim_from = 0
        for node in self._nodes:
            node.prune(clock.base)

    # -- introspection

    @property
    def states(self) -> int:
        """How many states have been closed and evaluated."""
        return self._states

    @property
    def closed_ns(self) -> int | None:
        """The time of the last closed state (samples at or before it are late), or None."""
        return None if self._closed_t == NEVER else self._closed_t

    @property
    def given_up(self) -> int:
        """How many states the memory bound gave up: dropped while the formula still needed them,
        or closed before the reorder delay passed (see the module documentation)."""
        return self._given_up + sum(node.given_up for node in self._waiting)

    @property
    def max_states(self) -> int:
        """The states (and buffered samples) it keeps at most: its cells over its nodes."""
        return self._max_states

    def retained(self) -> int:
        """How many states (and buffered samples) the monitor keeps: bounded by the formula's
        horizon whatever the length of the input (every node keeps at most a few entries per
        retained state, plus a constant). States are dropped in batches of at least 64."""
        return len(self._clock.times) + len(self._buffer)
