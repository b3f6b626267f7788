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
state. A node without future operators below it is *synchronous*: its verdict is decided at its
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
import math
from collections.abc import Mapping, Sequence
from typing import Any, Final

from dyknow.errors import ClosedError, FormulaError, TagError, did_you_mean
from dyknow.reasoning.robustness import RNode, RobustnessTree
from dyknow.reasoning.semantics import FALSE, TRUE, UNKNOWN, UNKNOWN_VALUE, arith, as_value, call, compare, read, truth
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
from dyknow.tags import parse_term

__all__ = ["DEFAULT_MAX_CELLS", "MIN_STATES", "Monitor", "Verdict"]

# (Final: compiled, a plain module global is a dictionary lookup at every use)
_NEVER: Final = -(2**62)  # a time before every sample
_NONE: Final = -(2**62)  # "no such state" for the last-position summaries
_AND: Final = 0  # the kinds of a _BinaryNode
_OR: Final = 1
_IMPLIES: Final = 2
_OPS: Final = ("<", ">", "<=", ">=", "==", "!=")  # an atom's comparison, by its code

DEFAULT_MAX_CELLS: Final = 2_000_000
"""The cells a :class:`Monitor` keeps at most unless told otherwise (``dyknow.security.Limits.max_monitor_cells``)."""
MIN_STATES: Final = 16
"""The states a monitor may always keep, however small its share of cells."""


def _bisect_left(a: list[int], x: int) -> int:
    """Where ``x`` goes in the sorted ``a``, before equal ones (the bisect module's, compiled:
    it compares ints natively, where the module compares objects)."""
    lo = 0
    hi = len(a)
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


def _bisect_right(a: list[int], x: int) -> int:
    """Where ``x`` goes in the sorted ``a``, after equal ones."""
    lo = 0
    hi = len(a)
    while lo < hi:
        mid = (lo + hi) >> 1
        if x < a[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


def _drop_before(positions: list[int], head: int, oldest: int) -> int:
    """Move ``head`` past the positions before ``oldest`` and return it; the positions behind it
    are deleted (and it starts over) once they are over 64 and half the list."""
    while head < len(positions) and positions[head] < oldest:
        head += 1
    if head > 64 and head * 2 > len(positions):
        del positions[:head]
        head = 0
    return head


def _insort(a: list[int], x: int, boxed: Any) -> None:
    """Insert ``x`` into the sorted ``a`` (as ``boxed``, the same int as an object)."""
    a.insert(_bisect_right(a, x), boxed)


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


class _Clock:
    """The retained states' times, shared by the nodes: ``times[i - base]`` is state i's time,
    and ``idx[i - base]`` is i itself, as the one int object every list that holds state i
    shares (compiled, an int put into a list is boxed: an object made, and freed when the list
    lets it go; one per state made here costs less than one per list and use)."""

    def __init__(self) -> None:
        self.times: list[int] = []
        self.idx: list[Any] = []
        self.base = 0
        self.given_up_t = _NEVER  # the newest state dropped before the formula was done with it

    def at(self, i: int) -> int:
        return self.times[i - self.base]

    def first_at_or_after(self, t: int) -> int:
        """The index of the first retained state at or after ``t``."""
        return _bisect_left(self.times, t) + self.base

    def last_at_or_before(self, t: int) -> int:
        """The index of the last retained state at or before ``t`` (``base - 1`` if none)."""
        return _bisect_right(self.times, t) - 1 + self.base


class _Step:
    """What a state steps through: a condition's node or a value's (one base, so the monitor's
    loop over them dispatches with one type check, compiled)."""

    max_states: int  # how many states' entries it may keep (the monitor sets it)
    # the next in the order a state steps through (the monitor links them): compiled, walking
    # these costs nothing per node, where taking each from a list[_Step] checks its type
    # (a walk of the class's bases, its class being a subclass)
    next_step: _Step | None = None

    def step(self, n: int, t: int, held: list[Any]) -> None:
        """Evaluate the new state ``n`` at ``t`` (operands have stepped already)."""
        raise NotImplementedError


class _Node(_Step):
    """A node of the monitored formula: its verdict at the newest state (``cur``), at every
    retained state when the formula has asynchronous nodes (``vals``: ``history``), and for an
    asynchronous node the states it decided during the current step (``events``)."""

    def __init__(self, clock: _Clock, sync: bool, need_ns: int) -> None:
        self.clock = clock
        self.cur = UNKNOWN
        self.vals: list[int] = []
        self.history = not sync  # a synchronous node keeps its verdicts only if some node reads them later
        # the states decided during the current step are the first ``nev`` of ``events`` (boxed:
        # the clock's ``idx`` objects); the list is kept from step to step, its entries written
        # over (compiled, a new list per step cost an allocation and a reallocation on its first append)
        self.events: list[Any] = []
        self.nev = 0
        self.sync = sync
        self.need_ns = need_ns  # how far back from the newest state this node reads
        self.max_states = 1 << 62  # how many states' entries it may keep (the monitor sets it)
        self.held: _Held | None = None  # a window's: the staleness of the terms below it
        self.below: list[int] = []
        self.first_t = _NEVER  # the first state's time (where an unbounded past window starts)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        """Evaluate the new state ``n`` at ``t`` (children have stepped already)."""
        raise NotImplementedError

    def event(self, i: Any) -> None:
        """State ``i`` (an int: its ``clock.idx`` object) was decided during this step."""
        c = self.nev
        events = self.events
        if c < len(events):
            events[c] = i
        else:
            events.append(i)
        self.nev = c + 1

    def prune(self, base: int) -> None:
        """States before ``base`` were dropped from ``vals``' front; drop what refers to them."""


class _Value(_Step):
    """A node that gives a value at each state (a stream's, a constant, an expression, an
    aggregate): always decided at its state, so it keeps no history."""

    def __init__(self) -> None:
        self.val: Any = UNKNOWN_VALUE
        self.max_states = 1 << 62
        self.given_up = 0

    def step(self, n: int, t: int, held: list[Any]) -> None:
        """Compute the value at the new state ``n`` at ``t`` (operands have stepped already)."""
        raise NotImplementedError


class _Held:
    """What the stream nodes of a monitor read, and its windows ask: each term's latest sample
    time, its maximum age (-1: no bound) and the time spans it was stale in (open: ``from < t <
    until``; the one it may be stale in now runs from its latest sample's time plus its age),
    shared by the monitor and its nodes. Spans older than ``keep_ns`` before the newest sample
    are dropped, the latest end among them noted in ``pruned_end`` (a window reaching back past
    it, one without a bound or one from the first state, still finds them)."""

    def __init__(self, terms: int) -> None:
        self.times: list[int] = [_NEVER] * terms
        self.max_age: list[int] = [-1] * terms
        self.aged = False  # whether some term has a maximum age (else nothing is ever stale)
        self.periods: list[list[tuple[int, int]]] = [[] for _ in range(terms)]
        self.heads: list[int] = [0] * terms
        self.pruned_end: list[int] = [_NEVER] * terms
        self.keep_ns = 0
        self.max_periods = 1 << 62
        self.first_t = _NEVER  # the first state's time: no window reaches before it (the monitor sets it)

    def sample(self, k: int, t: int, boxed: Any) -> None:
        """Term ``k`` had a sample at ``t`` (in time order; ``boxed``: the same int as an object)."""
        age = self.max_age[k]
        if age >= 0 and self.times[k] != _NEVER and t - self.times[k] > age + 1:
            last = self.times[k]
            periods = self.periods[k]
            periods.append((last + age, t))
            head = self.heads[k]
            edge = t - self.keep_ns
            while head < len(periods) and (periods[head][1] < edge or len(periods) - head > self.max_periods):
                if periods[head][1] > self.pruned_end[k]:
                    self.pruned_end[k] = periods[head][1]
                head += 1
            if head > 64 and head * 2 > len(periods):
                del periods[:head]
                head = 0
            self.heads[k] = head
        self.times[k] = boxed

    def stale(self, terms: list[int], lo: int | None, hi: int) -> bool:
        """Whether one of ``terms`` is stale at a whole-ns time of ``[lo, hi]`` (``lo`` None: no bound),
        from the first state on (there is no state, nor a window, before it)."""
        if not self.aged:
            return False
        if self.first_t != _NEVER and (lo is None or lo < self.first_t):
            lo = self.first_t
        for k in terms:
            age = self.max_age[k]
            if age < 0:
                continue
            pruned = self.pruned_end[k]
            if pruned != _NEVER and (lo is None or pruned - 1 >= lo):
                return True  # a span dropped reaches into it (an unbounded window from the first state)
            last = self.times[k]
            if last != _NEVER and (last + age + 1 if lo is None else max(last + age + 1, lo)) <= hi:
                return True  # stale since its latest sample
            periods = self.periods[k]
            for index in range(len(periods) - 1, self.heads[k] - 1, -1):
                start, end = periods[index]
                if end - 1 < (lo if lo is not None else _NEVER):
                    break  # (older ones end before the span)
                first = start + 1 if lo is None else max(start + 1, lo)
                if first <= min(end - 1, hi):
                    return True
        return False


def _finite_float(x: Any) -> bool:
    """Whether ``x`` is a finite float (a function of its own: compiled, a caller that tested it
    inline would hold ``x`` as a C double and box a new float to store it)."""
    return type(x) is float and x - x == 0.0


class _StreamValue(_Value):
    def __init__(self, k: int, fields: tuple[str, ...], held: _Held) -> None:
        super().__init__()
        self.k = k
        self.fields = fields
        self.held = held

    def step(self, n: int, t: int, held: list[Any]) -> None:
        k = self.k
        if self.held.aged:
            age = self.held.max_age[k]
            if age >= 0 and t - self.held.times[k] > age:
                self.val = UNKNOWN_VALUE  # stale
                return
        value = held[k]
        if not self.fields and _finite_float(value):
            self.val = value  # the common case, without a call (nor, compiled, a new float object)
        else:
            self.val = read(value, self.fields)


class _ConstValue(_Value):
    def __init__(self, value: Any) -> None:
        super().__init__()
        self.val = value

    def step(self, n: int, t: int, held: list[Any]) -> None:
        pass


class _VerdictValue(_Value):
    """A condition used as a value: True, False or unknown."""

    def __init__(self, arg: _Node) -> None:
        super().__init__()
        self.arg = arg

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.val = as_value(self.arg.cur)


class _ArithValue(_Value):
    def __init__(self, op: str, left: _Value, right: _Value) -> None:
        super().__init__()
        self.op = op
        self.left = left
        self.right = right

    def step(self, n: int, t: int, held: list[Any]) -> None:
        x = self.left.val
        y = self.right.val
        op = self.op
        if type(x) is float and type(y) is float:  # the common case, without a call
            if op == "+":
                result = x + y
            elif op == "-":
                result = x - y
            elif op == "*":
                result = x * y
            elif y != 0.0:
                result = x / y
            else:
                self.val = UNKNOWN_VALUE
                return
            self.val = result if result - result == 0.0 else UNKNOWN_VALUE
        else:
            self.val = arith(op, x, y)


class _CallValue(_Value):
    def __init__(self, fn: str, args: list[_Value]) -> None:
        super().__init__()
        self.fn = fn
        self.args = args

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.val = call(self.fn, [a.val for a in self.args])


class _PrevValue(_Value):
    def __init__(self, arg: _Value) -> None:
        super().__init__()
        self.arg = arg
        self.before: Any = UNKNOWN_VALUE

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.val = self.before
        self.before = self.arg.val


class _Total:
    """The exact sum of numbers as the semantics defines it (``exact_sum``), kept as values come
    and go: the ``int`` s summed exactly, and every value as a float in Shewchuk's partials
    (non-overlapping floats whose sum is exact), so taking a value out is adding its negative
    and loses nothing. Rounded once, when read."""

    __slots__ = ("floats", "huge", "ints", "partials")

    def __init__(self) -> None:
        self.ints = 0  # the sum of the int values
        self.floats = 0  # how many values are floats
        self.huge = 0  # ints too large for a float
        self.partials: list[float] = []

    def add(self, x: Any, sign: int) -> None:
        if type(x) is int:
            self.ints += sign * x
            try:
                f = float(x)
            except OverflowError:
                self.huge += sign
                return
        else:
            self.floats += sign
            f = float(x)
        self._add(f if sign > 0 else -f)

    def _add(self, x: float) -> None:
        partials = self.partials
        i = 0
        for y in partials:
            if abs(x) < abs(y):
                x, y = y, x
            hi = x + y
            lo = y - (hi - x)
            if lo:
                partials[i] = lo
                i += 1
            x = hi
        del partials[i:]
        partials.append(x)

    def value(self, extra: Sequence[Any] = ()) -> Any:
        """The sum, with ``extra`` numbers added (not kept); unknown when not finite."""
        if self.floats == 0 and all(type(x) is int for x in extra):
            total: Any = self.ints
            for x in extra:
                total += x
            return total
        if self.huge or any(type(x) is int and abs(x) > 1 << 1023 for x in extra):
            return UNKNOWN_VALUE
        try:
            result = math.fsum([*self.partials, *(float(x) for x in extra)])
        except OverflowError:
            return UNKNOWN_VALUE
        return result if result - result == 0.0 else UNKNOWN_VALUE


def _number(x: Any) -> bool:
    kind = type(x)
    return kind is int or kind is float


class _AggregateValue(_Value):
    """``count``, ``sum``, ``avg``, ``min``, ``max``, ``rate`` and ``integral`` of a past window, in
    O(1) amortized per state: the states younger than ``lo`` wait in ``pending``, the window's in
    ``entries`` (a bounded window only); running totals, monotonic queues for ``min``/``max``, the
    window's ends for ``rate``, and for ``integral`` the exact sum of the pieces between entries,
    the entry before the window and the state after it for the pieces cut by the span's ends."""

    def __init__(self, kind: str, lo_ns: int, hi_ns: int | None, arg: _Value | None, cond: _Node | None) -> None:
        super().__init__()
        self.kind = kind
        self.lo = lo_ns
        self.bounded = hi_ns is not None
        self.hi = hi_ns if hi_ns is not None else 0
        self.arg = arg
        self.cond = cond
        self.pending: list[tuple[int, Any]] = []
        self.phead = 0
        self.entries: list[tuple[int, Any]] = []
        self.ehead = 0
        self.count = 0  # entries in the window
        self.true = 0  # count: entries true
        self.bad = 0  # entries that are unknown (count) or not numbers (the others)
        self.total = _Total()
        self.extreme: list[tuple[int, Any]] = []  # min/max: a monotonic queue of (time, value)
        self.xhead = 0
        self.first: tuple[int, Any] | None = None  # the oldest entry (rate, unbounded)
        self.last: tuple[int, Any] | None = None  # the newest entry
        self.before: tuple[int, Any] | None = None  # the entry that left the window last (integral)
        self.pieces_bad = 0  # integral: pieces between entries whose value is not a number
        self.lost_t = -(2**62)  # the newest state given up (over max_states) and what may hide behind it
        self.held: _Held | None = None  # the staleness of the terms below (set by the monitor)
        self.below: list[int] = []
        self.first_t = -(2**62)  # the first state's time (an unbounded window's start)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        value = self.arg.val if self.arg is not None else self.cond.cur  # type: ignore[union-attr]
        if n == 0:
            self.first_t = t
        if self.lo == 0:
            self.enter(t, value)
        else:
            pending = self.pending
            pending.append((t, value))
            edge = t - self.lo
            head = self.phead
            while head < len(pending) and pending[head][0] <= edge:
                self.enter(*pending[head])
                head += 1
            if head > 64 and head * 2 > len(pending):
                del pending[:head]
                head = 0
            if len(pending) - head > self.max_states:  # over the memory bound: give up the oldest
                cut = len(pending) - self.max_states + self.max_states // 4
                self.lost_t = max(self.lost_t, pending[cut - 1][0])
                self.given_up += cut - head
                del pending[:cut]
                head = 0
            self.phead = head
        if self.bounded:
            self.leave(t - self.hi)
        self.val = self.result(t)

    def enter(self, t: int, value: Any) -> None:
        kind = self.kind
        self.count += 1
        if kind == "count":
            if value == UNKNOWN:
                self.bad += 1
            elif value == TRUE:
                self.true += 1
        elif not _number(value):
            self.bad += 1
        elif kind == "sum" or kind == "avg":
            self.total.add(value, 1)
        elif kind == "min" or kind == "max":
            extreme = self.extreme
            keep_min = kind == "min"
            while len(extreme) > self.xhead and (extreme[-1][1] >= value if keep_min else extreme[-1][1] <= value):
                extreme.pop()
            extreme.append((t, value))
        if kind == "integral" and self.last is not None:
            t0, v0 = self.last
            if _number(v0):
                self.total.add(v0 * (t - t0), 1)
            else:
                self.pieces_bad += 1
        if self.first is None:
            self.first = (t, value)
        self.last = (t, value)
        if self.bounded:
            self.entries.append((t, value))
            if len(self.entries) - self.ehead > self.max_states:  # over the memory bound: give up the oldest
                cut = len(self.entries) - self.max_states + self.max_states // 4
                self.lost_t = max(self.lost_t, self.entries[cut - 1][0])
                self.given_up += cut - self.ehead
                while self.ehead < cut:
                    self.drop()

    def leave(self, edge: int) -> None:
        """Entries older than ``edge`` leave the window."""
        entries = self.entries
        while self.ehead < len(entries) and entries[self.ehead][0] < edge:
            self.drop()
        if self.ehead > 64 and self.ehead * 2 > len(entries):
            del entries[: self.ehead]
            self.ehead = 0

    def drop(self) -> None:
        """The oldest entry leaves the window."""
        entries = self.entries
        t, value = entries[self.ehead]
        self.ehead += 1
        kind = self.kind
        self.count -= 1
        if kind == "count":
            if value == UNKNOWN:
                self.bad -= 1
            elif value == TRUE:
                self.true -= 1
        elif not _number(value):
            self.bad -= 1
        elif kind == "sum" or kind == "avg":
            self.total.add(value, -1)
        elif kind == "min" or kind == "max":
            extreme = self.extreme
            if self.xhead < len(extreme) and extreme[self.xhead][0] == t:
                self.xhead += 1
                if self.xhead > 64 and self.xhead * 2 > len(extreme):
                    del extreme[: self.xhead]
                    self.xhead = 0
        if kind == "integral" and self.ehead < len(entries):
            t1 = entries[self.ehead][0]
            if _number(value):
                self.total.add(value * (t1 - t), -1)
            else:
                self.pieces_bad -= 1
        self.before = (t, value)
        self.first = entries[self.ehead] if self.ehead < len(entries) else None
        if self.first is None:
            self.last = None

    def result(self, t: int) -> Any:
        kind = self.kind
        start = t - self.hi if self.bounded else -(2**62)
        if self.lost_t > -(2**62) and self.lost_t >= start:
            return UNKNOWN_VALUE  # a state given up may be in the window
        held = self.held
        if held is not None and held.stale(self.below, start if self.bounded else None, t - self.lo):
            return UNKNOWN_VALUE  # a term below was stale in the window
        if kind == "integral":
            return self.integral(t, start)
        if self.bad and kind != "rate":
            return UNKNOWN_VALUE
        if kind == "count":
            return self.true
        if kind == "sum":
            return self.total.value()
        if kind == "avg":
            return arith("/", self.total.value(), self.count) if self.count else UNKNOWN_VALUE
        if kind == "min" or kind == "max":
            return self.extreme[self.xhead][1] if self.xhead < len(self.extreme) else UNKNOWN_VALUE
        # rate
        first, last = self.first, self.last
        if first is None or last is None or first[0] == last[0]:
            return UNKNOWN_VALUE
        if not _number(first[1]) or not _number(last[1]):
            return UNKNOWN_VALUE
        return arith("/", arith("-", last[1], first[1]), (last[0] - first[0]) / 1e9)

    def integral(self, t: int, start: int) -> Any:
        right = t - self.lo
        nxt = self.pending[self.phead][0] if self.phead < len(self.pending) else t  # the state after the window
        extra: list[Any] = []
        first, last = self.first, self.last
        if last is None:  # no state in the window: one piece spans it, the last to leave
            before = self.before
            if before is None:
                return 0
            d = right - max(start, before[0])
            if d <= 0:
                return 0
            if not _number(before[1]):
                return UNKNOWN_VALUE
            return arith("/", before[1] * d, 1e9)
        if self.pieces_bad:
            return UNKNOWN_VALUE
        assert first is not None
        before = self.before
        if before is not None and first[0] > start:  # the piece cut by the span's start
            if not _number(before[1]):
                return UNKNOWN_VALUE
            extra.append(before[1] * (first[0] - max(start, before[0])))
        d = min(nxt, right) - last[0]  # the piece cut by the span's end
        if d > 0:
            if not _number(last[1]):
                return UNKNOWN_VALUE
            extra.append(last[1] * d)
        total = self.total.value(extra)
        return arith("/", total, 1e9) if total is not UNKNOWN_VALUE else UNKNOWN_VALUE


class _RobustnessValue(_Value):
    """``robustness(F)`` of a condition decided by its state: its own robustness tree, stepped
    after F's verdict nodes (they are its operands), read at the state."""

    def __init__(self, tree: RobustnessTree) -> None:
        super().__init__()
        self.tree = tree

    def step(self, n: int, t: int, held: list[Any]) -> None:
        tree = self.tree
        tree.step(n, t)
        known, rob = tree.get(n)
        self.val = rob if known and rob is not None else UNKNOWN_VALUE
        tree.trim(t)


def _compare_floats(code: int, x: float, y: float) -> int:
    """``x OP y`` of two floats, the operator by its code in ``_OPS``, as TRUE or FALSE."""
    if code == 0:
        return TRUE if x < y else FALSE
    if code == 1:
        return TRUE if x > y else FALSE
    if code == 2:
        return TRUE if x <= y else FALSE
    if code == 3:
        return TRUE if x >= y else FALSE
    if code == 4:
        return TRUE if x == y else FALSE
    return TRUE if x != y else FALSE


class _AtomNode(_Node):
    """``left OP right`` (or a bare value, ``op`` None): a condition decided at its state."""

    def __init__(self, clock: _Clock, op: str | None, left: _Value, right: _Value | None) -> None:
        super().__init__(clock, True, 0)
        self.op = op
        self.code = _OPS.index(op) if op in _OPS else -1  # (an int: compiled, comparing strs costs calls)
        self.left = left
        self.right = right
        # a number written in the formula (``Speed(r) < 0.5``, the common atom), unboxed once:
        # compiled, reading the constant's float object at every state cost a type check and an unboxing
        self.const = isinstance(right, _ConstValue) and _finite_float(right.val) and self.code >= 0
        self.number = float(right.val) if self.const and right is not None else 0.0

    def step(self, n: int, t: int, held: list[Any]) -> None:
        x = self.left.val
        if self.const and type(x) is float:
            self.cur = value = _compare_floats(self.code, x, self.number)
            if self.history:
                self.vals.append(value)
            return
        op = self.op
        right = self.right
        if right is None:
            value = truth(x)
        else:
            y = right.val
            code = self.code
            if type(x) is float and type(y) is float and code >= 0:  # the common case, without a generic call
                value = _compare_floats(code, x, y)
            else:
                value = compare(op or "", x, y)
        self.cur = value
        if self.history:
            self.vals.append(value)


class _PrevNode(_Node):
    """``prev(F)`` of a condition decided at its state: F's verdict at the previous state."""

    def __init__(self, clock: _Clock, arg: _Node) -> None:
        super().__init__(clock, True, 0)
        self.arg = arg
        self.before = UNKNOWN

    def step(self, n: int, t: int, held: list[Any]) -> None:
        value = self.before
        self.before = self.arg.cur
        self.cur = value
        if self.history:
            self.vals.append(value)


class _EdgeNode(_Node):
    """``rise(F)``: F and not prev(F); ``fall(F)``: not F and prev(F)."""

    def __init__(self, clock: _Clock, rise: bool, arg: _Node) -> None:
        super().__init__(clock, True, 0)
        self.rise = rise
        self.arg = arg
        self.before = UNKNOWN

    def step(self, n: int, t: int, held: list[Any]) -> None:
        now = self.arg.cur
        before = self.before
        self.before = now
        if self.rise:
            value = now if now < 2 - before else 2 - before
        else:
            value = 2 - now if 2 - now < before else before
        self.cur = value
        if self.history:
            self.vals.append(value)


class _ConstNode(_Node):
    def __init__(self, clock: _Clock, value: int) -> None:
        super().__init__(clock, True, 0)
        self.value = value

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.cur = self.value
        if self.history:
            self.vals.append(self.value)


class _NotNode(_Node):
    def __init__(self, clock: _Clock, arg: _Node) -> None:
        super().__init__(clock, arg.sync, arg.need_ns)
        self.arg = arg

    def step(self, n: int, t: int, held: list[Any]) -> None:
        arg = self.arg
        value = 2 - arg.cur
        self.cur = value
        if self.history:
            vals = self.vals
            vals.append(value)
            if not self.sync:
                base = self.clock.base
                arg_vals = arg.vals
                arg_events = arg.events
                count = arg.nev
                for e in range(count):
                    j: int = arg_events[e]
                    vals[j - base] = 2 - arg_vals[j - base]
                self.events = arg_events
                self.nev = count


def _combine(kind: int, x: int, y: int) -> int:
    if kind == _AND:
        return x if x < y else y
    if kind == _OR:
        return x if x > y else y
    x = 2 - x
    return x if x > y else y


class _BinaryNode(_Node):
    """``and``, ``or``, ``implies``: Kleene's min, max and max(not x, y)."""

    def __init__(self, clock: _Clock, kind: int, left: _Node, right: _Node, horizon_ns: int) -> None:
        sync = left.sync and right.sync
        super().__init__(clock, sync, 0 if sync else horizon_ns)
        self.kind = kind
        self.left = left
        self.right = right

    def step(self, n: int, t: int, held: list[Any]) -> None:
        left_node = self.left
        right_node = self.right
        kind = self.kind
        value = _combine(kind, left_node.cur, right_node.cur)
        self.cur = value
        if not self.history:
            return
        vals = self.vals
        vals.append(value)
        if self.sync:
            return
        self.nev = 0  # (a parent reads the events during this state only)
        if value != UNKNOWN:
            self.event(self.clock.idx[-1])
        left_count = left_node.nev
        right_count = right_node.nev
        if not left_count and not right_count:  # (a synchronous operand has none)
            return
        left = left_node.vals
        right = right_node.vals
        base = self.clock.base
        left_events = left_node.events
        for e in range(left_count):
            jb = left_events[e]  # (kept boxed: it goes into events as it is)
            j: int = jb
            if vals[j - base] == UNKNOWN:
                value = _combine(kind, left[j - base], right[j - base])
                if value != UNKNOWN:
                    vals[j - base] = value
                    self.event(jb)
        right_events = right_node.events
        for e in range(right_count):
            jb = right_events[e]
            j = jb
            if vals[j - base] == UNKNOWN:
                value = _combine(kind, left[j - base], right[j - base])
                if value != UNKNOWN:
                    vals[j - base] = value
                    self.event(jb)


class _SinceSync(_Node):
    """``left since[a,b] right`` (``once`` without left; ``historically`` with both negations) over
    synchronous operands, in O(1) per state: the last entered state where right is true and where
    it is not false, the last state where left is not true and where it is false, and the states
    younger than ``a`` waiting to enter the window."""

    def __init__(self, clock: _Clock, left: _Node | None, right: _Node, lo_ns: int, hi_ns: int | None, negate: bool) -> None:
        super().__init__(clock, True, 0)
        self.left = left
        self.right = right
        self.lo_ns = lo_ns
        self.bounded = hi_ns is not None
        self.hi_ns = hi_ns if hi_ns is not None else 0
        self.negate = negate  # historically: not once not
        self.last_true = _NONE  # index and time of the last entered state where right is true
        self.last_true_t = _NEVER
        self.last_nf = _NONE  # ... where right is not false
        self.last_nf_t = _NEVER
        self.break_nt = _NONE  # the last state where left is not true / is false
        self.break_f = _NONE
        self.waiting: list[tuple[int, int, int]] = []  # (index, time, right) younger than lo_ns
        self.head = 0
        self.lost = _NONE  # the newest waiting state given up (over max_states) and its time
        self.lost_t = _NEVER
        self.given_up = 0

    def stale_window(self, n: int, t: int) -> bool:
        return _past_stale(self, t, self.lo_ns, self.hi_ns if self.bounded else None)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        if self.first_t == _NEVER:
            self.first_t = t
        psi = self.right.cur
        if self.negate:
            psi = 2 - psi
        left = self.left
        if left is not None:
            phi = left.cur
            if phi != TRUE:
                self.break_nt = n
                if phi == FALSE:
                    self.break_f = n
        if self.lo_ns == 0:
            if psi == TRUE:
                self.last_true = n
                self.last_true_t = t
            if psi != FALSE:
                self.last_nf = n
                self.last_nf_t = t
        else:
            waiting = self.waiting
            waiting.append((n, t, psi))
            edge = t - self.lo_ns
            head = self.head
            while head < len(waiting) and waiting[head][1] <= edge:
                j, tj, value = waiting[head]
                head += 1
                if value == TRUE:
                    self.last_true = j
                    self.last_true_t = tj
                if value != FALSE:
                    self.last_nf = j
                    self.last_nf_t = tj
            if head > 64 and head * 2 > len(waiting):
                del waiting[:head]
                head = 0
            if len(waiting) - head > self.max_states:  # give up the oldest: they may hide a term
                cut = len(waiting) - self.max_states + self.max_states // 4
                self.lost, self.lost_t = waiting[cut - 1][0], waiting[cut - 1][1]
                self.given_up += cut - head
                del waiting[:cut]
                head = 0
            self.head = head
        oldest = t - self.hi_ns if self.bounded else _NEVER
        if self.last_true >= self.break_nt and self.last_true != _NONE and self.last_true_t >= oldest:
            value = TRUE
        elif self.last_nf >= self.break_f and self.last_nf != _NONE and self.last_nf_t >= oldest:
            value = UNKNOWN
        elif self.lost != _NONE and self.lost_t >= oldest and self.lost >= self.break_f:
            value = UNKNOWN  # all known terms are false, but one given up may be in the window
        elif self.held is not None and self.stale_window(n, t):
            value = UNKNOWN  # a term below was stale in the window: an outage is no violation
        else:
            value = FALSE
        if self.negate:
            value = 2 - value
        self.cur = value
        if self.history:
            self.vals.append(value)


def _past_stale(node: _Node, t: int, lo_ns: int, hi_ns: int | None) -> bool:
    """Whether a term below ``node`` was stale in the past window ``[t - hi, t - lo]`` of the state at ``t``."""
    held = node.held
    if held is None or not held.aged:
        return False
    if node.first_t == _NEVER:
        node.first_t = t
    # (an unbounded window reads from the first state: lo None, which also finds spans pruned)
    return held.stale(node.below, t - hi_ns if hi_ns is not None else None, t - lo_ns)


def _only_new(node: _Node, n: int) -> bool:
    """Whether an operand decided nothing this step but (maybe) the new state ``n`` itself."""
    size = node.nev
    if size == 0:
        return True
    if size > 1:
        return False
    first: int = node.events[0]
    return first == n


def _pred(positions: list[int], below: int) -> int:
    """The last position < ``below``, or _NONE."""
    k = _bisect_left(positions, below)
    return positions[k - 1] if k else _NONE


def _succ(positions: list[int], above: int) -> int:
    """The first position > ``above``, or -1 (none)."""
    k = _bisect_right(positions, above)
    return positions[k] if k < len(positions) else -1


def _remove(positions: list[int], position: int) -> None:
    k = _bisect_left(positions, position)
    if k < len(positions) and positions[k] == position:
        del positions[k]


def _prune_keep_last(positions: list[int], base: int) -> None:
    """Drop positions before ``base`` but the last of them (what "the last before" queries need)."""
    k = _bisect_left(positions, base)
    if k > 1:
        del positions[: k - 1]


class _Temporal(_Node):
    """What the asynchronous temporal nodes share: their operands (left None: ``eventually`` or
    ``once``), the negations that make ``always`` and ``historically``, sorted positions of the
    operands' verdicts, and the sorted pending states."""

    def __init__(
        self, clock: _Clock, left: _Node | None, right: _Node, lo_ns: int, hi_ns: int, negate: bool, need_ns: int, retire_ns: int
    ) -> None:
        super().__init__(clock, False, need_ns)
        self.completed = -1  # every state up to this one has been checked on completing
        self.left = left
        self.right = right
        self.lo_ns = lo_ns
        self.hi_ns = hi_ns
        self.negate = negate
        self.retire_ns = retire_ns  # a pending state this old can no longer be decided: unknown
        # which retained states are pending, as a "next pending" forest over them (a union-find
        # whose sets are runs of states no longer pending, each pointing on to the next one
        # that is): skip[i - base] is 0 for a pending state, else how far on the next may be.
        # Deciding a state, a run or the oldest ones then costs O(1) amortized, whatever the
        # window's length; a sorted list of pending states paid a memmove of the whole list to
        # take its oldest out (7.6 against 4.5 us per state at a 100 s against a 10 ms window)
        self.skip: list[int] = []
        self.head = 0  # no state before this one is pending
        self.left_nt: list[int] = []  # where left is not true (false or undecided)
        self.left_f: list[int] = []  # where left is false
        self.right_t: list[int] = []  # where right (negated for always/historically) is true
        self.right_nf: list[int] = []  # where it is not false
        # what operand_events found this step: where left became true, false, right true, false
        self.found_lt: list[int] = []
        self.found_lf: list[int] = []
        self.found_rt: list[int] = []
        self.found_rf: list[int] = []

    def right_at(self, j: int) -> int:
        value = self.right.vals[j - self.clock.base]
        return 2 - value if self.negate else value

    def decide(self, i: int, value: int) -> None:
        clock = self.clock
        k = i - clock.base
        self.vals[k] = 2 - value if self.negate else value
        self.event(clock.idx[k])

    def record_new(self, n: int) -> tuple[int, int]:
        """Record the operands' verdicts at the new state; returns (left, right)."""
        left = TRUE if self.left is None else self.left.cur
        right = self.right.cur
        if self.negate:
            right = 2 - right
        nb = self.clock.idx[-1]  # (n, boxed once)
        if left != TRUE:
            self.left_nt.append(nb)
            if left == FALSE:
                self.left_f.append(nb)
        if right == TRUE:
            self.right_t.append(nb)
        if right != FALSE:
            self.right_nf.append(nb)
        return left, right

    def operand_events(self) -> tuple[list[int], list[int], list[int], list[int]]:
        """The operands' verdicts decided this step at earlier states, recorded; returns the
        positions where left became true, left false, right true, right false."""
        base = self.clock.base
        newest = base + len(self.clock.times) - 1
        left_t = self.found_lt  # (kept from step to step: compiled, four new lists a step cost more)
        left_f = self.found_lf
        right_t = self.found_rt
        right_f = self.found_rf
        if left_t:
            left_t.clear()
        if left_f:
            left_f.clear()
        if right_t:
            right_t.clear()
        if right_f:
            right_f.clear()
        left = self.left
        if left is not None and not left.sync:
            events = left.events
            for e in range(left.nev):
                kb = events[e]  # (kept boxed: it goes into lists as it is)
                k: int = kb
                if k == newest:
                    continue  # recorded as the new state's
                if left.vals[k - base] == TRUE:
                    _remove(self.left_nt, k)
                    left_t.append(kb)
                else:
                    _insort(self.left_f, k, kb)
                    left_f.append(kb)
        right = self.right
        if not right.sync:
            events = right.events
            for e in range(right.nev):
                jb = events[e]
                j: int = jb
                if j == newest:
                    continue
                if self.right_at(j) == TRUE:
                    _insort(self.right_t, j, jb)
                    right_t.append(jb)
                else:
                    _remove(self.right_nf, j)
                    right_f.append(jb)
        return left_t, left_f, right_t, right_f

    def next_pending(self, i: int) -> int:
        """The first pending state at or after ``i`` (one past the newest when none)."""
        skip = self.skip
        k = i - self.clock.base
        if k < 0:
            k = 0
        end = len(skip)
        j = k
        while j < end:
            d = skip[j]
            if d == 0:
                break
            j += d
        while k < j:  # path compression: what was walked over points at j from now on
            d = skip[k]
            if k + d != j:  # (mostly it does already: compiled, a write boxes an int and swaps objects)
                skip[k] = j - k
            k += d
        return j + self.clock.base

    def done(self, i: int) -> None:
        """State ``i`` is no longer pending (decided, or unknown for good)."""
        self.skip[i - self.clock.base] = 1

    def resolve(self, first: int, last: int, value: int) -> None:
        """Decide every pending state in [first, last] as ``value`` (false: those whose window
        no term below was stale in: the others stay unknown for good)."""
        base = self.clock.base
        skip = self.skip
        newest = base + len(skip) - 1
        if last > newest:
            last = newest
        i = self.next_pending(first)
        while i <= last:
            skip[i - base] = 1
            if value != FALSE or not self.stale_at(i):
                self.decide(i, value)
            i = self.next_pending(i + 1)

    def resolve_one(self, i: int, value: int) -> None:
        self.skip[i - self.clock.base] = 1  # (done(i), inline)
        if value != FALSE or not self.stale_at(i):
            self.decide(i, value)

    def stale_at(self, i: int) -> bool:
        """Whether a term below was stale in the window of state ``i`` (a false verdict there is unknown)."""
        raise NotImplementedError

    def retire(self, now: int) -> None:
        """Pending states so old that every state that could decide them is in: unknown for good."""
        clock = self.clock
        times = clock.times
        base = clock.base
        skip = self.skip
        edge = now - self.retire_ns
        k = self.head - base
        if k < 0:
            k = 0
        if k >= len(skip) or times[k] > edge:
            return  # (the common case: no state from head on is that old, pending or not)
        i = self.next_pending(self.head)
        while i - base < len(skip) and times[i - base] <= edge:
            skip[i - base] = 1
            i = self.next_pending(i + 1)
        self.head = i

    def prune(self, base: int) -> None:
        for positions in (self.left_nt, self.left_f, self.right_t, self.right_nf):
            _prune_keep_last(positions, base)
        # the monitor dropped as many states from vals: pending ones among them were given up
        # before their time (unknown for good); the runs after them keep their lengths
        del self.skip[: len(self.skip) - len(self.vals)]


class _UntilNode(_Temporal):
    """``left until[a,b] right``, ``eventually`` (no left) and ``always`` (negated): states wait in
    pending (``skip``) until a true right with an unbroken left chain decides them true, or their
    window is complete and every term is false."""

    def __init__(
        self, clock: _Clock, left: _Node | None, right: _Node, lo_ns: int, hi_ns: int, negate: bool, need_ns: int, retire_ns: int
    ) -> None:
        super().__init__(clock, left, right, lo_ns, hi_ns, negate, need_ns, retire_ns)
        self.end_at = 0  # the last state of the window completing last (complete's cursor)

    def stale_at(self, i: int) -> bool:
        held = self.held
        if held is None or not held.aged:
            return False
        ti = self.clock.at(i)
        return held.stale(self.below, ti + self.lo_ns, ti + self.hi_ns)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.nev = 0  # (a parent reads the events during this state only)
        self.vals.append(UNKNOWN)
        self.skip.append(0)
        _left, right = self.record_new(n)
        left = self.left
        if (left is None or _only_new(left, n)) and _only_new(self.right, n):  # nothing decided below but the new state
            if right == TRUE:
                self.found_true(n)
        else:
            left_t, left_f, right_t, right_f = self.operand_events()
            if right == TRUE:
                self.found_true(n)
            for j in right_t:
                self.found_true(j)
            for k in left_t:
                self.chain_mended(k)
            if right_f or left_f:
                complete_last = self.clock.last_at_or_before(t - self.hi_ns)  # the newest state whose window is complete
                for j in right_f:
                    self.right_false(j, complete_last)
                for k in left_f:
                    self.left_false(k, complete_last)
        self.complete(t)
        self.retire(t)
        self.cur = self.vals[-1]

    def found_true(self, j: int) -> None:
        """Right is true at j: pending states whose window holds j and whose left chain up to j is
        unbroken are true."""
        clock = self.clock
        tj = clock.at(j)
        last = min(j, clock.last_at_or_before(tj - self.lo_ns)) if self.lo_ns else j  # (times are distinct)
        first = self.first_pending(tj - self.hi_ns, last)
        if first > last:
            return
        if self.left is not None:
            first = max(first, _pred(self.left_nt, j) + 1)
        self.resolve(first, last, TRUE)

    def chain_mended(self, k: int) -> None:
        """Left became true at k: states whose chain broke at k may now reach a true right."""
        clock = self.clock
        reach = clock.at(k) + self.hi_ns
        after = _succ(self.left_nt, k)
        lo = _bisect_right(self.right_t, k)
        while lo < len(self.right_t):
            j = self.right_t[lo]
            if (after != -1 and j > after) or clock.at(j) > reach:
                break
            self.found_true(j)
            lo = _bisect_right(self.right_t, j)

    def first_pending(self, reach: int, last: int) -> int:
        """The first pending state at ``reach`` or after, if it is at or before ``last`` (else
        one past ``last`` or more): walked to from the oldest pending one (few states are
        pending in the common case), else found by bisection."""
        clock = self.clock
        times = clock.times
        base = clock.base
        i = self.next_pending(self.head)
        walked = 0
        while i <= last and times[i - base] < reach:
            walked += 1
            if walked == 8:
                return self.next_pending(clock.first_at_or_after(reach))
            i = self.next_pending(i + 1)
        return i

    def false_if_all_false(self, i: int) -> None:
        """Decide a complete pending state false if every term of its window is false."""
        clock = self.clock
        ti = clock.at(i)
        self.all_false(i, ti, clock.last_at_or_before(ti + self.hi_ns))

    def all_false(self, i: int, ti: int, end: int) -> None:
        """:meth:`false_if_all_false` of state ``i`` at ``ti``, its window's last state ``end``."""
        lo = self.clock.first_at_or_after(ti + self.lo_ns) if self.lo_ns else i  # (times are distinct)
        if self.left is not None:
            k = _bisect_left(self.left_f, i)
            if k < len(self.left_f) and self.left_f[k] < end:
                end = self.left_f[k]  # terms after the first false left are false
        k = _bisect_left(self.right_nf, lo)
        if k == len(self.right_nf) or self.right_nf[k] > end:
            self.resolve_one(i, FALSE)

    def complete(self, t: int) -> None:
        """Pending states whose window became complete with this state: false if all terms are."""
        clock = self.clock
        times = clock.times
        base = clock.base
        edge = t - self.hi_ns
        first = max(self.completed + 1, base)
        last = first - 1  # the newest state whose window is complete: a cursor, O(1) amortized
        while last + 1 - base < len(times) and times[last + 1 - base] <= edge:
            last += 1
        if last < first:
            return
        self.completed = last
        hi_ns = self.hi_ns
        e = self.end_at  # each window's last state: a cursor too (windows complete in order)
        i = self.next_pending(first)
        while i <= last:
            ti = times[i - base]
            reach = ti + hi_ns
            if e < i:
                e = i
            while e + 1 - base < len(times) and times[e + 1 - base] <= reach:
                e += 1
            self.all_false(i, ti, e)
            i = self.next_pending(i + 1)
        self.end_at = e

    def right_false(self, j: int, complete_last: int) -> None:
        """Right became false at j: complete pending states whose window has no other not-false
        term (up to the first false left) are false. With p and s the not-false terms around j,
        they are the states whose first term lies in (p, j] and last in [j, s): one range."""
        clock = self.clock
        tj = clock.at(j)
        lo_ns = self.lo_ns
        last = min(clock.last_at_or_before(tj - lo_ns) if lo_ns else j, complete_last)  # starts by j; complete
        # the first pending state whose window reaches j: walked to from the oldest pending one
        # (few complete states are pending: those waiting for an operand), else found by bisection
        first = self.first_pending(tj - self.hi_ns, last)  # whose window reaches j
        if first > last:
            return  # (the common case: no complete state pending there)
        p = _pred(self.right_nf, j)
        if p >= clock.base:
            first = max(first, clock.first_at_or_after(clock.at(p) - lo_ns + 1) if lo_ns else p + 1)  # starts after p
        if self.left is not None:
            first = max(first, _pred(self.left_f, j) + 1)  # no false left before j cuts the window short of it
        s = _succ(self.right_nf, j)
        if s != -1:
            bound = clock.last_at_or_before(clock.at(s) - self.hi_ns - 1)  # the window ends before s ...
            if self.left is not None:
                bound = max(bound, _pred(self.left_f, s))  # ... or a false left before s ends its terms
            last = min(last, bound)
        self.resolve(first, last, FALSE)

    def left_false(self, k: int, complete_last: int) -> None:
        """Left became false at k: complete pending states before it may now be all false."""
        clock = self.clock
        first = _pred(self.left_f, k) + 1 if _pred(self.left_f, k) != _NONE else clock.base
        last = min(k, complete_last)
        i = self.next_pending(first)
        while i <= last:
            self.false_if_all_false(i)
            i = self.next_pending(i + 1)


class _UntilSync(_Node):
    """``left until[a,b] right`` (``eventually`` without left, ``always`` negated) over synchronous
    operands, in O(1) amortized per state whatever the window's length: the same verdicts as
    :class:`_UntilNode`, at the same states, without its sorted lists and bisections.

    Both operands are decided at their state, so a pending state is decided true only by a true
    right at a state whose left chain from it is unbroken, and false only when its window
    completes. A pending state is *live* while no left from it up to the newest state is
    not true: the live states are one run, from ``live`` to the newest, and a true right at
    the newest state decides them true from the oldest on (as far as it lies in their windows).
    A left not true ends the chains of all of them: they join ``dead``, runs of states only their
    window's completion decides. Windows complete oldest first, so completing one is O(1)
    amortized: cursors move forward through where left is false (which cuts the terms short)
    and where right is not false (one term that is, and the state is not false).
    """

    def __init__(self, clock: _Clock, left: _Node | None, right: _Node, lo_ns: int, hi_ns: int, negate: bool, need_ns: int) -> None:
        super().__init__(clock, False, need_ns)
        self.left = left
        self.right = right
        self.lo_ns = lo_ns
        self.hi_ns = hi_ns
        self.negate = negate
        self.live = 0  # the live states run from it to the newest
        self.dead: list[int] = []  # runs of pending states that are not live: first, last, first, last, ...
        self.dhead = 0
        self.left_f: list[int] = []  # where left is false, from lf_head on
        self.lf_head = 0
        self.right_nf: list[int] = []  # where right (negated for always) is not false, from rnf_head on
        self.rnf_head = 0
        self.lo_at = 0  # the first state of the window completing last (its start: t + a)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.nev = 0  # (a parent reads the events during this state only)
        self.vals.append(UNKNOWN)
        left = self.left
        phi = TRUE if left is None else left.cur
        psi = self.right.cur
        if self.negate:
            psi = 2 - psi
        if phi == FALSE:
            self.left_f.append(self.clock.idx[-1])  # (n, boxed once)
        if psi != FALSE:
            self.right_nf.append(self.clock.idx[-1])
        edge = t - self.hi_ns
        if psi == TRUE:  # a true right decides the live states whose window holds it
            self.complete(n, t, edge - 1)  # (first the windows that ended before this state)
            times = self.clock.times
            base = self.clock.base
            top = t - self.lo_ns
            i = self.live
            while i <= n and times[i - base] <= top:
                self.decide(i, TRUE)
                i += 1
            self.live = i
        self.complete(n, t, edge)  # windows that end by this state
        if phi != TRUE and self.live <= n:  # a left not true ends every live chain
            self.dead.append(self.live)
            self.dead.append(n)
            self.live = n + 1
        self.forget(self.dead[self.dhead] if self.dhead < len(self.dead) else self.live)
        self.cur = self.vals[-1]

    def forget(self, oldest: int) -> None:
        """Drop the positions before ``oldest``, the oldest pending state: no window reads them."""
        if self.left is not None:  # (eventually and always have none)
            self.lf_head = _drop_before(self.left_f, self.lf_head, oldest)
        self.rnf_head = _drop_before(self.right_nf, self.rnf_head, oldest)

    def decide(self, i: int, value: int) -> None:
        clock = self.clock
        k = i - clock.base
        self.vals[k] = 2 - value if self.negate else value
        self.event(clock.idx[k])

    def complete(self, n: int, t: int, upto: int) -> None:
        """Decide the pending states whose window is complete, those at or before ``upto``: false
        if every term is (and no term below was stale in the window), else unknown for good."""
        times = self.clock.times
        base = self.clock.base
        dead = self.dead
        while self.dhead < len(dead):
            i = dead[self.dhead]
            last = dead[self.dhead + 1]
            while i <= last:
                ti = times[i - base]
                if ti > upto:
                    dead[self.dhead] = i
                    if self.dhead > 64 and self.dhead * 2 > len(dead):
                        del dead[: self.dhead]
                        self.dhead = 0
                    return
                self.finish(i, ti, n, t)
                i += 1
            self.dhead += 2
        if dead:
            dead.clear()
        self.dhead = 0
        i = self.live
        while i <= n:
            ti = times[i - base]
            if ti > upto:
                break
            self.finish(i, ti, n, t)
            i += 1
        self.live = i

    def finish(self, i: int, ti: int, n: int, t: int) -> None:
        """State ``i``'s window is complete: false if all its terms are."""
        times = self.clock.times
        base = self.clock.base
        end = n if t <= ti + self.hi_ns else n - 1  # the window's last state
        if self.lo_ns:
            start = ti + self.lo_ns
            k = self.lo_at if self.lo_at > i else i
            while k <= n and times[k - base] < start:
                k += 1
            self.lo_at = k  # the window's first state (past ``end`` when it has none)
        else:
            k = i  # the window starts at the state itself (times are distinct): no time to read
        left_f = self.left_f
        h = self.lf_head
        while h < len(left_f) and left_f[h] < i:
            h += 1
        self.lf_head = h
        if h < len(left_f) and left_f[h] < end:
            end = left_f[h]  # the terms after the first false left are false
        right_nf = self.right_nf
        r = self.rnf_head
        while r < len(right_nf) and right_nf[r] < k:
            r += 1
        self.rnf_head = r
        if r == len(right_nf) or right_nf[r] > end:
            held = self.held
            if held is None or not held.aged or not held.stale(self.below, ti + self.lo_ns, ti + self.hi_ns):
                self.decide(i, FALSE)

    def prune(self, base: int) -> None:
        # pending states before base were given up before their time: unknown for good
        if self.live < base:
            self.live = base
        dead = self.dead
        h = self.dhead
        while h < len(dead) and dead[h + 1] < base:
            h += 2
        if h < len(dead) and dead[h] < base:
            dead[h] = base
        self.dhead = h
        if self.lo_at < base:
            self.lo_at = base


class _SinceNode(_Temporal):
    """``left since[a,b] right`` (``once``, ``historically``) over asynchronous operands: a state's
    window is in the past, so it is complete at once, but operands there may still be pending."""

    def __init__(
        self, clock: _Clock, left: _Node | None, right: _Node, lo_ns: int, hi_ns: int | None, negate: bool, need_ns: int, retire_ns: int
    ) -> None:
        super().__init__(clock, left, right, lo_ns, hi_ns if hi_ns is not None else 0, negate, need_ns, retire_ns)
        self.bounded = hi_ns is not None

    def stale_at(self, i: int) -> bool:
        return _past_stale(self, self.clock.at(i), self.lo_ns, self.hi_ns if self.bounded else None)

    def window(self, i: int) -> tuple[int, int]:
        clock = self.clock
        ti = clock.at(i)
        first = clock.first_at_or_after(ti - self.hi_ns) if self.bounded else _NONE
        return first, clock.last_at_or_before(ti - self.lo_ns)

    def check(self, i: int) -> int:
        """The verdict at i from what is known now (UNKNOWN: not decided)."""
        clock = self.clock
        if clock.given_up_t != _NEVER and clock.at(i) - self.lo_ns < clock.times[0]:
            return UNKNOWN  # the window ends among states given up: where exactly is lost with them
        first, last = self.window(i)
        k = _bisect_right(self.right_t, last)
        if k:
            j = self.right_t[k - 1]
            chain = _pred(self.left_nt, i + 1) if self.left is not None else _NONE
            if j >= first and j >= chain:
                return TRUE
        k = _bisect_right(self.right_nf, last)
        cut = _pred(self.left_f, i + 1) if self.left is not None else _NONE
        if k == 0 or self.right_nf[k - 1] < max(first, cut):
            given_up = clock.given_up_t
            if given_up != _NEVER and cut < clock.base and (not self.bounded or given_up >= clock.at(i) - self.hi_ns):
                return UNKNOWN  # a state given up may be a term of the window, and not false
            return FALSE
        return UNKNOWN

    def step(self, n: int, t: int, held: list[Any]) -> None:
        if self.first_t == _NEVER:
            self.first_t = t
        self.nev = 0  # (a parent reads the events during this state only)
        self.vals.append(UNKNOWN)
        self.record_new(n)
        value = self.check(n)
        if value == FALSE and self.stale_at(n):
            self.skip.append(1)  # unknown for good: a term below was stale in the window
        elif value != UNKNOWN:
            self.skip.append(1)
            self.decide(n, value)
        else:
            self.skip.append(0)
        left_t, left_f, right_t, right_f = self.operand_events()
        if left_t or left_f or right_t or right_f:
            # an operand decided at k can only change verdicts at k and after (windows and
            # chains end at their state): check those still pending
            first = min(left_t + left_f + right_t + right_f)
            i = self.next_pending(first)
            while i <= n:
                value = self.check(i)
                if value != UNKNOWN:
                    self.resolve_one(i, value)
                i = self.next_pending(i + 1)
        self.retire(t)
        self.cur = self.vals[-1]


def _negated(node: Node) -> bool:
    return isinstance(node, Always | Historically)


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
        for part in walk(self.formula.root):
            if isinstance(part, Quantifier):
                raise FormulaError(
                    f"the formula holds the quantifier '{part.kind} {part.var} in {part.domain}'",
                    where=f"monitor of {str(self.formula)!r}",
                    expected="a formula whose forall/exists are expanded (dyknow.reasoning.expand); foreach: an ObjectMonitor",
                )
        self.reorder_ns = int(reorder_ns)
        #: the terms as the formula writes them, in order of first appearance (push's ``term``)
        self.terms: tuple[str, ...] = tuple(str(term) for term in self.formula.terms)
        self._index = {term: k for k, term in enumerate(self.terms)}
        self._variables: dict[str, Any] = dict(variables or {})
        self._times = _Held(len(self.terms))
        self._clock = _Clock()
        self._nodes: list[_Node] = []
        self._values: list[_Value] = []
        self._steps: list[_Step] = []  # every node, operands first: what a state steps through
        # the robustness tree beside the verdict nodes, when asked for (dyknow.reasoning.robustness)
        self._robust: RobustnessTree | None = RobustnessTree(0) if robustness else None
        self._rob_wait: list[tuple[int, int, bool, int]] = []  # verdicts decided before their robustness
        root = self._build(self.formula.root)
        if not isinstance(root, _Node):  # (the parser makes the root a condition)
            raise FormulaError("the formula is a value, not a condition", where=f"monitor of {str(self.formula)!r}", expected="a condition")
        self._root = root
        self._span_ns = max([node.need_ns for node in self._nodes] + [self.formula.horizon_ns])
        # stale spans are kept as far back as any bounded window may read, all windows at once
        self._times.keep_ns = self._span_ns + sum(
            (n.interval.hi_ns or n.interval.lo_ns) for n in walk(self.formula.root) if isinstance(n, Historically | Once | Since | Aggregate | Always | Eventually | Until)
        )
        if self._robust is not None:
            self._robust.keep_ns = self._times.keep_ns + self.formula.horizon_ns
        # with a future operator somewhere, nodes read their operands' verdicts at older states:
        # every asynchronous node keeps them, and a synchronous one only if an asynchronous
        # and/or/implies reads it at the states its other operand decides later (the temporal
        # nodes read a synchronous operand at its own state only: ``cur``)
        self._history = not all(node.sync for node in self._nodes)
        for node in self._nodes:
            node.history = not node.sync
        for node in self._nodes:
            if isinstance(node, _BinaryNode) and not node.sync:
                node.left.history = True
                node.right.history = True
        self._first_step: _Step | None = None
        for each in reversed(self._steps):
            each.next_step = self._first_step
            self._first_step = each
        self._single = len(self.terms) == 1
        self._immediate = self._single and self.reorder_ns == 0
        self._held: list[Any] = [None] * len(self.terms)
        self._seen = [False] * len(self.terms)
        self._missing = len(self.terms)
        self._newest = [_NEVER] * len(self.terms)
        self._max_t = _NEVER
        self._buffer: list[tuple[int, int, int, Any]] = []  # (t, arrival, term, value)
        self._arrivals = 0
        self._states = 0
        self._closed_t = _NEVER
        self._closed = False
        self._trim_from = 0
        self._given_up = 0
        self._waiting: list[_SinceSync | _AggregateValue] = [
            node for node in self._steps if isinstance(node, _SinceSync | _AggregateValue)
        ]  # their own count
        self._max_states = 0
        self.set_max_cells(max_cells)
        for term, age in (max_age_ns or {}).items():
            self.set_max_age(term, age)
        #: samples dropped because they came at or before the last closed state's time
        self.late = 0

    def set_max_cells(self, max_cells: int) -> None:
        """Keep at most ``max_cells`` cells from now on (a manager shares its monitors' cells out
        as they come and go): ``max_cells // nodes`` states, and never fewer than :data:`MIN_STATES`."""
        holders = len(self._nodes) + sum(1 for node in self._values if isinstance(node, _AggregateValue))  # (values keep no states)
        states = max(MIN_STATES, max_cells // holders)
        self._max_states = states
        self._times.max_periods = states
        for node in self._steps:
            node.max_states = states

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

    def _build(self, node: Node) -> _Node | _Value:
        # iterative post-order: formulas may nest deeper than Python's recursion allows
        built: dict[int, _Node | _Value] = {}
        horizons: dict[int, int] = {}
        terms: dict[int, set[int]] = {}  # the terms each node reads, itself or below
        robs: dict[int, RNode] = {}  # a condition's robustness node (when asked for)
        streams: dict[tuple[int, tuple[str, ...]], _StreamValue] = {}  # one per term and fields, however often written
        stack: list[tuple[Node, bool]] = [(node, False)]
        while stack:
            current, expanded = stack.pop()
            if id(current) in built:
                continue
            kids = children(current)
            if not expanded and kids:
                stack.append((current, True))
                stack.extend((kid, False) for kid in kids)
                continue
            args = [built[id(kid)] for kid in kids]
            below = max((horizons[id(kid)] for kid in kids), default=0)
            own = current.interval.hi_ns or 0 if isinstance(current, Always | Eventually | Until) else 0
            horizons[id(current)] = below + own
            reads: set[int] = set()
            for kid in kids:
                reads |= terms[id(kid)]
            if isinstance(current, Stream):
                reads.add(self._index[str(current.term)])
            terms[id(current)] = reads
            made: _Node | _Value
            if isinstance(current, Call) and current.fn == "robustness":
                made = self._robustness_value(current.args[0], built, terms)
            elif isinstance(current, Stream) and (self._index[str(current.term)], current.fields) in streams:
                built[id(current)] = streams[(self._index[str(current.term)], current.fields)]  # (stepped already)
                continue
            else:
                made = self._make(current, args, below, below + own)
            if isinstance(made, _StreamValue):
                streams[(made.k, made.fields)] = made
            if isinstance(made, _UntilNode | _UntilSync | _SinceNode | _SinceSync | _AggregateValue):
                made.held = self._times  # its windows ask whether a term below was stale in them
                made.below = sorted(reads)
            if self._robust is not None and isinstance(made, _Node):
                robs[id(current)] = self._rob_node(current, made, [robs[id(k)] for k in kids if id(k) in robs], sorted(reads))
            if isinstance(made, _Node):
                self._nodes.append(made)
            else:
                self._values.append(made)
            if not isinstance(made, _ConstValue):  # (a constant has nothing to step)
                self._steps.append(made)
            built[id(current)] = made
        return built[id(node)]

    def _robustness_value(self, root: Node, built: Mapping[int, _Node | _Value], terms: Mapping[int, set[int]]) -> _Value:
        """``robustness(F)``: a robustness tree of F's own, over its verdict nodes (built already)."""
        tree = RobustnessTree(0)
        robs: dict[int, RNode] = {}
        for node in reversed(walk(root)):  # children before parents
            made = built[id(node)]
            if isinstance(made, _Node):
                robs[id(node)] = self._rob_node(node, made, [robs[id(k)] for k in children(node) if id(k) in robs], sorted(terms[id(node)]), tree)
        tree.keep_ns = sum((n.interval.hi_ns or n.interval.lo_ns) for n in walk(root) if isinstance(n, Historically | Once | Since | Aggregate))
        return _RobustnessValue(tree)

    def _rob_node(self, node: Node, made: _Node, kids: list[RNode], below: list[int], tree: RobustnessTree | None = None) -> RNode:
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

    def _value(self, node: _Node | _Value) -> _Value:
        """An operand as a value: a condition's verdict becomes True, False or unknown."""
        if isinstance(node, _Value):
            return node
        made = _VerdictValue(node)
        self._values.append(made)
        self._steps.append(made)
        return made

    def _make(self, node: Node, args: list[_Node | _Value], below: int, horizon: int) -> _Node | _Value:
        clock = self._clock
        if isinstance(node, Num | Str):
            return _ConstValue(node.value)
        if isinstance(node, Var):
            if node.name not in self._variables:
                raise FormulaError(f"the variable {node.name!r} has no value", where=f"monitor of {str(self.formula)!r}",
                                   expected="Monitor(variables={...}) for a quantifier's body")  # fmt: skip
            return _ConstValue(self._variables[node.name])
        if isinstance(node, Stream):
            return _StreamValue(self._index[str(node.term)], node.fields, self._times)
        if isinstance(node, Neg):
            return _CallValue("neg", [self._value(args[0])])
        if isinstance(node, Arith):
            return _ArithValue(node.op, self._value(args[0]), self._value(args[1]))
        if isinstance(node, Call):
            return _CallValue(node.fn, [self._value(a) for a in args])
        if isinstance(node, Aggregate):
            arg = args[0]
            if node.kind == "count":
                assert isinstance(arg, _Node)
                return _AggregateValue(node.kind, node.interval.lo_ns, node.interval.hi_ns, None, arg)
            return _AggregateValue(node.kind, node.interval.lo_ns, node.interval.hi_ns, self._value(arg), None)
        if isinstance(node, Prev):
            arg = args[0]
            if isinstance(arg, _Node):
                return _PrevNode(clock, arg)
            return _PrevValue(arg)
        if isinstance(node, Rise | Fall):
            arg = args[0]
            assert isinstance(arg, _Node)
            return _EdgeNode(clock, isinstance(node, Rise), arg)
        if isinstance(node, Atom):
            return _AtomNode(clock, node.op, self._value(args[0]), self._value(args[1]) if len(args) > 1 else None)
        if isinstance(node, Const):
            return _ConstNode(clock, TRUE if node.value else FALSE)
        conds = [a for a in args if isinstance(a, _Node)]
        assert len(conds) == len(args), "the parser makes every operand of a connective a condition"
        if isinstance(node, Not):
            return _NotNode(clock, conds[0])
        if isinstance(node, And | Or | Implies):
            kind = _AND if isinstance(node, And) else _OR if isinstance(node, Or) else _IMPLIES
            return _BinaryNode(clock, kind, conds[0], conds[1], horizon)
        if isinstance(node, Eventually | Always | Until):
            left, right = (conds[0], conds[1]) if isinstance(node, Until) else (None, conds[0])
            hi = node.interval.hi_ns
            assert hi is not None
            if all(arg.sync for arg in conds):
                return _UntilSync(clock, left, right, node.interval.lo_ns, hi, _negated(node), horizon)
            return _UntilNode(clock, left, right, node.interval.lo_ns, hi, _negated(node), horizon, horizon)
        assert isinstance(node, Once | Historically | Since)
        left, right = (conds[0], conds[1]) if isinstance(node, Since) else (None, conds[0])
        hi = node.interval.hi_ns
        if all(arg.sync for arg in conds):
            return _SinceSync(clock, left, right, node.interval.lo_ns, hi, _negated(node))
        # it reads back to the window's start (or, unbounded, its end: older states count as one)
        reach = hi if hi is not None else node.interval.lo_ns
        return _SinceNode(clock, left, right, node.interval.lo_ns, hi, _negated(node), below + reach, below)

    # -- input

    def push(self, term: str, t_ns: int, value: Any) -> list[Verdict]:
        """Hand over one sample of ``term`` (as the formula writes it) at ``t_ns``; returns the
        verdicts decided by the states it closed (often none, or the one of its own state)."""
        k = self._index.get(term)
        if k is None:
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
        return None if self._closed_t == _NEVER else self._closed_t

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
