"""The offline evaluation of a formula: every node over all the states of a trace at once, bottom up.

:class:`Evaluator` computes, for the states :func:`~dyknow.reasoning.semantics.evaluate` made of
the streams, each node's column: a condition's verdicts (and robustness), a value's values. The
connectives, windows, aggregates, freshness and robustness follow the text of
:mod:`dyknow.reasoning.semantics` one for one; the values and atoms at a state are those of
:mod:`dyknow.reasoning.values`, the monitor's own.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Final

from dyknow.errors import FormulaError
from dyknow.reasoning.tree import (
    Aggregate,
    Always,
    And,
    Arith,
    Atom,
    Call,
    Const,
    Eventually,
    Fall,
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
    Rise,
    Since,
    Str,
    Stream,
    Until,
    Var,
    children,
    raw_reads,
    walk,
)
from dyknow.reasoning.values import (
    FALSE,
    TRUE,
    UNKNOWN,
    UNKNOWN_VALUE,
    arith,
    as_value,
    call,
    compare,
    exact_sum,
    is_number,
    lookup,
    margin,
    read,
    read_raw,
    scalar,
    truth,
)
from dyknow.tags import Term

__all__ = ["Evaluator", "is_condition", "stale_in"]

_INF: Final = math.inf


def stale_in(periods: Sequence[tuple[int, int | None]], lo: int | None, hi: int) -> bool:
    """Whether a stale period (open: ``from < t < until``) holds a time ``t`` of the span ``[lo,
    hi]`` (``lo`` None: no bound)."""
    for start, end in periods:
        first = start + 1 if lo is None else max(start + 1, lo)
        last = hi if end is None else min(end - 1, hi)
        if first <= last:
            return True
    return False


class Evaluator:
    """Bottom-up evaluation of every node over all states: a condition's verdicts (and robustness),
    a value's values, each as a list."""

    #: per term, the spans in which it is stale (:func:`stale_in`): set by the caller when a term has a maximum age
    stale: list[list[tuple[int, int | None]]] = []

    def __init__(
        self,
        times: list[int],
        values: list[tuple[Any, ...]],
        latest: list[tuple[int, ...]],
        index: Mapping[Term, int],
        max_age: list[int],
        variables: dict[str, Any],
        robustness: bool,
    ) -> None:
        self.times = times
        self.values = values
        self.latest = latest
        self.index = index
        self.max_age = max_age
        self.variables = variables
        self.raw: set[int] = set()  # the ids of the nodes read as they are (tree.raw_reads), per node()
        self.robust = robustness
        self.n = len(times)

    def node(self, root: Node) -> tuple[list[Any], list[float | None]]:
        """A node's column over all states (a condition's verdicts, a value's values) and its robustness."""
        # iterative post-order: formulas may nest deeper than Python's recursion allows
        done: dict[int, tuple[list[Any], list[float | None]]] = {}
        self.raw = raw_reads(root)
        stack: list[tuple[Node, bool]] = [(root, False)]
        while stack:
            node, expanded = stack.pop()
            if id(node) in done:
                continue
            kids = children(node)
            if not expanded and kids:
                stack.append((node, True))
                stack.extend((kid, False) for kid in kids)
                continue
            done[id(node)] = self.apply(node, [done[id(kid)] for kid in kids])
        verdicts, margins = done[id(root)]
        return verdicts, margins

    def apply(self, node: Node, args: list[tuple[list[Any], list[float | None]]]) -> tuple[list[Any], list[float | None]]:
        n = self.n
        none: list[float | None] = [None] * n
        if isinstance(node, Num | Str):
            return [node.value] * n, none
        if isinstance(node, Var):
            return [self.variables.get(node.name, UNKNOWN_VALUE)] * n, none
        if isinstance(node, Const):
            return [TRUE if node.value else FALSE] * n, [(_INF if node.value else -_INF)] * n
        if isinstance(node, Stream):
            k = self.index[node.term]
            age = self.max_age[k]
            out = []
            for i in range(n):
                if age >= 0 and self.times[i] - self.latest[i][k] > age:
                    out.append(UNKNOWN_VALUE)
                elif id(node) in self.raw:
                    out.append(read_raw(self.values[i][k], node.fields))
                else:
                    out.append(read(self.values[i][k], node.fields))
            return out, none
        if isinstance(node, Index):
            found = list(args[0][0])
            for key in args[1:]:
                found = [lookup(c, k) for c, k in zip(found, key[0], strict=True)]
            return (found if id(node) in self.raw else [scalar(v) for v in found]), none
        if isinstance(node, Neg):
            return [call("neg", [x]) for x in args[0][0]], none
        if isinstance(node, Arith):
            return [arith(node.op, x, y) for x, y in zip(args[0][0], args[1][0], strict=True)], none
        if isinstance(node, Call):
            if node.fn == "robustness":
                return [UNKNOWN_VALUE if r is None else r for r in args[0][1]], none
            columns = [a[0] for a in args]
            return [call(node.fn, [c[i] for c in columns]) for i in range(n)], none
        if isinstance(node, Prev):
            return [args[0][0][i - 1] if i else self._unknown_like(node.arg) for i in range(n)], none
        if isinstance(node, Aggregate):
            out = self.aggregate(node, args[0][0])
            stale = self.stale_terms(node)
            if stale:
                lo, hi = node.interval.lo_ns, node.interval.hi_ns
                for i in range(n):
                    if self.stale_window(stale, None if hi is None else self.times[i] - hi, self.times[i] - lo):
                        out[i] = UNKNOWN_VALUE
            return out, none
        if isinstance(node, Atom):
            return self.atom(node, args)
        if isinstance(node, Rise | Fall):
            return self.edge(isinstance(node, Rise), args[0])
        if isinstance(node, Not):
            v, r = args[0]
            return [2 - x for x in v], [(-x if x is not None else None) for x in r]
        if isinstance(node, And | Or | Implies):
            (lv, lr), (rv, rr) = args
            if isinstance(node, Implies):
                lv, lr = [2 - x for x in lv], [(-x if x is not None else None) for x in lr]
            pick = min if isinstance(node, And) else max
            return [pick(x, y) for x, y in zip(lv, rv, strict=True)], [_pair(pick, x, y) for x, y in zip(lr, rr, strict=True)]
        if isinstance(node, Eventually | Always):
            v, r = args[0]
            neg = isinstance(node, Always)
            hi = node.interval.hi_ns
            assert hi is not None, "future operators have a finite upper bound (the parser checks it)"
            out_v, out_r = self.until([TRUE] * n, _inf_list(n), _flip(v, neg), _negate(r, neg), node.interval.lo_ns, hi, self.stale_terms(node))
            return _flip(out_v, neg), _negate(out_r, neg)
        if isinstance(node, Until):
            (lv, lr), (rv, rr) = args
            hi = node.interval.hi_ns
            assert hi is not None
            return self.until(lv, lr, rv, rr, node.interval.lo_ns, hi, self.stale_terms(node))
        if isinstance(node, Once | Historically):
            v, r = args[0]
            neg = isinstance(node, Historically)
            out_v, out_r = self.since(
                [TRUE] * n, _inf_list(n), _flip(v, neg), _negate(r, neg), node.interval.lo_ns, node.interval.hi_ns, self.stale_terms(node)
            )
            return _flip(out_v, neg), _negate(out_r, neg)
        if isinstance(node, Since):
            (lv, lr), (rv, rr) = args
            return self.since(lv, lr, rv, rr, node.interval.lo_ns, node.interval.hi_ns, self.stale_terms(node))
        raise FormulaError(f"{type(node).__name__} cannot be evaluated here", where="formula", expected="a formula without foreach inside")

    def stale_terms(self, node: Node) -> list[int]:
        """The terms read below ``node`` that may be stale (they have a maximum age)."""
        found = {self.index[n.term] for n in walk(node) if isinstance(n, Stream) and n.term in self.index}
        return sorted(k for k in found if self.max_age[k] >= 0 and k < len(self.stale) and self.stale[k])

    def stale_window(self, terms: list[int], lo: int | None, hi: int) -> bool:
        """Whether one of ``terms`` is stale at a time of ``[lo, hi]`` (from the first state when
        ``lo`` is None; a span reaching back before the first state reaches its outages there)."""
        if lo is None:
            lo = self.times[0] if self.times else 0
        return any(stale_in(self.stale[k], lo, hi) for k in terms)

    @staticmethod
    def _unknown_like(node: Node) -> Any:
        return UNKNOWN if is_condition(node) else UNKNOWN_VALUE

    # -- atoms and edges

    def atom(self, node: Atom, args: list[tuple[list[Any], list[float | None]]]) -> tuple[list[Any], list[float | None]]:
        left = self.as_values(node.left, args[0][0])
        if node.op is None:
            verdicts = [truth(x) for x in left]
            return verdicts, [_sign(v) for v in verdicts]
        assert node.right is not None
        right = self.as_values(node.right, args[1][0])
        verdicts = [compare(node.op, x, y) for x, y in zip(left, right, strict=True)]
        return verdicts, [margin(node.op, x, y, v) for x, y, v in zip(left, right, verdicts, strict=True)]

    @staticmethod
    def as_values(node: Node, column: list[Any]) -> list[Any]:
        """A column of a node as values: a condition's verdicts become booleans (or unknown)."""
        if is_condition(node):
            return [as_value(v) for v in column]
        return column

    def edge(self, rise: bool, arg: tuple[list[Any], list[float | None]]) -> tuple[list[Any], list[float | None]]:
        v, r = arg
        out_v: list[Any] = []
        out_r: list[float | None] = []
        for i in range(self.n):
            now, before = v[i], (v[i - 1] if i else UNKNOWN)
            rn, rb = r[i], (r[i - 1] if i else None)
            if rise:
                out_v.append(min(now, 2 - before))
                out_r.append(_pair(min, rn, (-rb if rb is not None else None)) if out_v[-1] != UNKNOWN else None)
            else:
                out_v.append(min(2 - now, before))
                out_r.append(_pair(min, (-rn if rn is not None else None), rb) if out_v[-1] != UNKNOWN else None)
        return out_v, out_r

    # -- aggregates

    def window(self, i: int, lo_ns: int, hi_ns: int | None) -> tuple[int, int]:
        """The states ``[first, last]`` of the past window of state i (first > last: empty)."""
        times = self.times
        first = 0 if hi_ns is None else bisect_left(times, times[i] - hi_ns)
        last = bisect_right(times, times[i] - lo_ns) - 1
        return first, last

    def aggregate(self, node: Aggregate, column: list[Any]) -> list[Any]:
        kind, lo, hi = node.kind, node.interval.lo_ns, node.interval.hi_ns
        out: list[Any] = []
        for i in range(self.n):
            if kind == "integral":
                out.append(self.integral(i, lo, hi, column))
                continue
            first, last = self.window(i, lo, hi)
            if kind == "rate":
                if last - first < 1:
                    out.append(UNKNOWN_VALUE)
                    continue
                x, y = column[first], column[last]
                if not is_number(x) or not is_number(y):
                    out.append(UNKNOWN_VALUE)
                    continue
                out.append(arith("/", arith("-", y, x), (self.times[last] - self.times[first]) / 1e9))
                continue
            part = column[first : last + 1] if last >= first else []
            if kind == "count":
                out.append(UNKNOWN_VALUE if any(v == UNKNOWN for v in part) else sum(1 for v in part if v == TRUE))
                continue
            if any(not is_number(x) for x in part):
                out.append(UNKNOWN_VALUE)
                continue
            if kind == "sum":
                out.append(exact_sum(part))
            elif kind == "avg":
                out.append(arith("/", exact_sum(part), len(part)) if part else UNKNOWN_VALUE)
            elif kind == "min":
                out.append(min(part) if part else UNKNOWN_VALUE)
            else:
                out.append(max(part) if part else UNKNOWN_VALUE)
        return out

    def integral(self, i: int, lo_ns: int, hi_ns: int | None, column: list[Any]) -> Any:
        times = self.times
        left = times[0] if hi_ns is None else max(times[0], times[i] - hi_ns)
        right = times[i] - lo_ns
        if right <= left:
            return 0
        pieces: list[Any] = []
        j = bisect_right(times, left) - 1  # the state whose piece holds the span's start
        while j <= i and times[j] < right:
            end = times[j + 1] if j < i else times[i]
            d = min(end, right) - max(times[j], left)
            if d > 0:
                x = column[j]
                if not is_number(x):
                    return UNKNOWN_VALUE
                pieces.append(x * d)
            j += 1
        total = exact_sum(pieces)
        return arith("/", total, 1e9)

    # -- temporal operators (verdicts and robustness)

    def until(
        self, left: list[int], left_r: list[float | None], right: list[int], right_r: list[float | None], a: int, b: int, stale: list[int]
    ) -> tuple[list[int], list[float | None]]:
        """``left until[a,b] right`` at every state, from "next" tables built backwards."""
        times, n = self.times, self.n
        next_not_true, next_false, next_true, next_not_false = [n] * (n + 1), [n] * (n + 1), [n] * (n + 1), [n] * (n + 1)
        for i in range(n - 1, -1, -1):
            next_not_true[i] = i if left[i] != TRUE else next_not_true[i + 1]
            next_false[i] = i if left[i] == FALSE else next_false[i + 1]
            next_true[i] = i if right[i] == TRUE else next_true[i + 1]
            next_not_false[i] = i if right[i] != FALSE else next_not_false[i + 1]
        last = times[-1] if times else 0
        out: list[int] = []
        rob: list[float | None] = []
        for i in range(n):
            lo = bisect_left(times, times[i] + a)  # the window is [lo, hi]
            hi = bisect_right(times, times[i] + b) - 1
            complete = last >= times[i] + b
            gap = bool(stale) and self.stale_window(stale, times[i] + a, times[i] + b)
            if next_true[lo] <= min(hi, next_not_true[i]):
                out.append(TRUE)
            elif complete and not gap and next_not_false[lo] > min(hi, next_false[i]):
                out.append(FALSE)
            else:
                out.append(UNKNOWN)
            if not self.robust or out[-1] == UNKNOWN or not complete or gap:
                rob.append(None)
                continue
            best: float | None = -_INF
            chain: float | None = _INF
            for j in range(i, hi + 1):
                if j >= lo:
                    best = _pair(max, best, _pair(min, right_r[j], chain))
                chain = _pair(min, chain, left_r[j])
            rob.append(best)
        return out, rob

    def since(
        self, left: list[int], left_r: list[float | None], right: list[int], right_r: list[float | None], a: int, b: int | None, stale: list[int]
    ) -> tuple[list[int], list[float | None]]:
        """``left since[a,b] right`` at every state, from "last" tables built forwards."""
        times, n = self.times, self.n
        last_not_true, last_false, last_true, last_not_false = [-1] * n, [-1] * n, [-1] * n, [-1] * n
        for i in range(n):
            last_not_true[i] = i if left[i] != TRUE else (last_not_true[i - 1] if i else -1)
            last_false[i] = i if left[i] == FALSE else (last_false[i - 1] if i else -1)
            last_true[i] = i if right[i] == TRUE else (last_true[i - 1] if i else -1)
            last_not_false[i] = i if right[i] != FALSE else (last_not_false[i - 1] if i else -1)
        out: list[int] = []
        rob: list[float | None] = []
        for i in range(n):
            lo = 0 if b is None else bisect_left(times, times[i] - b)  # the window is [lo, hi]
            hi = bisect_right(times, times[i] - a) - 1
            gap = bool(stale) and self.stale_window(stale, None if b is None else times[i] - b, times[i] - a)
            if hi >= 0 and last_true[hi] >= max(lo, last_not_true[i]):
                out.append(TRUE)
            elif gap:
                out.append(UNKNOWN)
            elif hi < 0 or last_not_false[hi] < max(lo, last_false[i]):
                out.append(FALSE)  # (no state in the window: false)
            else:
                out.append(UNKNOWN)
            if not self.robust or out[-1] == UNKNOWN or gap:
                rob.append(None)
                continue
            best: float | None = -_INF
            chain: float | None = _INF
            for j in range(i, lo - 1, -1):
                if j <= hi:
                    best = _pair(max, best, _pair(min, right_r[j], chain))
                chain = _pair(min, chain, left_r[j])
            rob.append(best)
        return out, rob


def is_condition(node: Node) -> bool:
    """Whether a node gives verdicts (else values)."""
    if isinstance(node, Prev):
        return is_condition(node.arg)
    return not isinstance(node, Num | Str | Var | Stream | Index | Neg | Arith | Call | Aggregate)


def _pair(pick: Callable[[float, float], float], x: float | None, y: float | None) -> float | None:
    if x is None or y is None:
        return None
    return pick(x, y)


def _sign(verdict: int) -> float | None:
    return _INF if verdict == TRUE else -_INF if verdict == FALSE else None


def _flip(values: list[int], negate: bool) -> list[int]:
    return [2 - v for v in values] if negate else values


def _negate(values: list[float | None], negate: bool) -> list[float | None]:
    return [(-v if v is not None else None) for v in values] if negate else values


def _inf_list(n: int) -> list[float | None]:
    return [_INF] * n
