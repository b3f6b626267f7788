"""For the temporal reasoning tests: a naive evaluator written from the semantics' text, and
Hypothesis strategies for formulas and irregular traces.

The naive evaluator shares no code with :mod:`dyknow.reasoning.semantics`: it reads the
definitions literally (every window enumerated, every AND and OR over explicit lists of Python
``True``/``False``/``None``, every aggregate recomputed from the window's states, every integral
from its pieces), quadratic and slow, which is the point.
"""

from __future__ import annotations

import json
import math
import random
from collections.abc import Mapping, Sequence
from fractions import Fraction
from typing import Any

from hypothesis import strategies as st

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
    Interval,
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
)
from dyknow.reasoning.tree import family_term, is_family, member_arg
from dyknow.tags import Term

Verdict = bool | None


class _U:
    def __repr__(self) -> str:
        return "U"


U = _U()  # an unknown value, the naive evaluator's own


def k_or(terms: Sequence[Verdict]) -> Verdict:
    """Kleene OR: true if any is true, false if all are false (so false over nothing)."""
    if any(v is True for v in terms):
        return True
    if all(v is False for v in terms):
        return False
    return None


def k_and(terms: Sequence[Verdict]) -> Verdict:
    """Kleene AND: false if any is false, true if all are true (so true over nothing)."""
    if any(v is False for v in terms):
        return False
    if all(v is True for v in terms):
        return True
    return None


def k_not(v: Verdict) -> Verdict:
    """Kleene NOT."""
    return None if v is None else not v


def is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def naive_read(payload: Any, fields: Sequence[str]) -> Any:
    """A stream's value from the text: down the fields through dicts; a number (not NaN nor
    infinite), a string or a boolean; else unknown."""
    value = payload
    for name in fields:
        if not isinstance(value, dict) or name not in value:
            return U
        value = value[name]
    if isinstance(value, bool) or isinstance(value, str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else U
    return U


def naive_read_raw(payload: Any, fields: Sequence[str]) -> Any:
    """A stream's payload down the fields as it is (objects and arrays too), for lookups and dist."""
    value = payload
    for name in fields:
        if not isinstance(value, dict) or name not in value:
            return U
        value = value[name]
    return value


def naive_lookup(container: Any, key: Any) -> Any:
    """``container[key]`` from the text: an object's member by a string, or by a number's key
    (its canonical text, as object identity has it); an array's element by a whole number from 0."""
    if isinstance(key, bool) or not (isinstance(key, str) or (is_number(key) and math.isfinite(key))):
        return U
    if isinstance(container, dict):
        name = key if isinstance(key, str) else naive_object_key(key)
        return container[name] if name in container else U
    if isinstance(container, list) and is_number(key) and Fraction(key).denominator == 1 and 0 <= key < len(container):
        return container[int(key)]
    return U


def naive_function(fn: str, xs: Sequence[Any]) -> Any:
    """sqrt, hypot and pow from the text: in floats; unknown unless the result is a finite real number."""
    if not all(is_number(x) for x in xs):
        return U
    try:
        floats = [float(x) for x in xs]
        if fn == "sqrt":
            if floats[0] < 0:
                return U
            result: Any = math.sqrt(floats[0])
        elif fn == "hypot":
            result = math.hypot(floats[0], floats[1])
        else:
            result = floats[0] ** floats[1]  # (Python's own power, not math.pow: a complex result for a root of a negative number)
    except (OverflowError, ZeroDivisionError, ValueError):
        return U
    return result if isinstance(result, float) and math.isfinite(result) else U


def naive_distance(p: Any, q: Any) -> Any:
    """dist from the text: objects with x and y (and z on both or neither) or arrays of one length."""
    if isinstance(p, dict) and isinstance(q, dict):
        names = ["x", "y", "z"] if ("z" in p or "z" in q) else ["x", "y"]
        if not all(name in p and name in q for name in names):
            return U
        a, b = [p[name] for name in names], [q[name] for name in names]
    elif isinstance(p, list) and isinstance(q, list) and len(p) == len(q) >= 1:
        a, b = p, q
    else:
        return U
    if not all(is_number(x) for x in [*a, *b]):
        return U
    try:
        result = math.hypot(*[float(x) - float(y) for x, y in zip(a, b, strict=True)])
    except OverflowError:
        return U
    return result if math.isfinite(result) else U


def naive_compare(op: str, x: Any, y: Any) -> Verdict:
    if op in ("==", "!="):
        if is_number(x) and is_number(y):
            same = x == y
        elif isinstance(x, str) and isinstance(y, str):
            same = x == y
        elif isinstance(x, bool) and isinstance(y, bool):
            same = x == y
        else:
            return None
        return same if op == "==" else not same
    if not (is_number(x) and is_number(y)):
        return None
    return {"<": x < y, "<=": x <= y, ">": x > y, ">=": x >= y}[op]


def naive_arith(op: str, x: Any, y: Any) -> Any:
    if not (is_number(x) and is_number(y)):
        return U
    if op == "/" and y == 0:
        return U
    try:
        result = {"+": lambda: x + y, "-": lambda: x - y, "*": lambda: x * y, "/": lambda: x / y}[op]()
    except OverflowError:
        return U
    if isinstance(result, float) and not math.isfinite(result):
        return U
    return result


def naive_sum(values: Sequence[Any]) -> Any:
    """Exact for ints; else the exactly rounded sum as floats (fractions, rounded once)."""
    if all(isinstance(v, int) for v in values):
        return sum(values)
    from fractions import Fraction

    try:
        exact = sum((Fraction(float(v)) for v in values), Fraction(0))
        total = float(exact)
    except OverflowError:
        return U
    return total if math.isfinite(total) else U


def naive_states(terms: Sequence[Term], streams: Sequence[Sequence[tuple[int, Any]]]) -> tuple[list[int], list[list[Any]], list[list[int]]]:
    """States from the definition: distinct times from the first time all streams have a value,
    each holding every stream's latest value (the later sample wins at equal times), and the
    time of each stream's latest sample."""
    if not streams or any(not s for s in streams):
        return [], [], []
    start = max(s[0][0] for s in streams)
    times = sorted({t for s in streams for t, _ in s if t >= start})
    held = [[[v for t, v in s if t <= now][-1] for s in streams] for now in times]
    when = [[[t for t, _ in s if t <= now][-1] for s in streams] for now in times]
    return times, held, when


def naive_evaluate_ns(
    formula: Formula,
    streams: Mapping[Term, Sequence[tuple[int, Any]]],
    *,
    max_age: Mapping[Term, int] | None = None,
    variables: Mapping[str, Any] | None = None,
    robustness: bool = False,
    start_ns: int | None = None,
) -> list[Any]:
    """Every state's (t_ns, verdict), or (t_ns, verdict, robustness), straight from the definitions."""
    terms = list(formula.terms)
    given = dict(streams)
    for term in terms:  # a parameterized term's family: a sample at each of its members' (their values are read below)
        if is_family(term) and term not in given:
            given[term] = sorted(((t, None) for member, samples in streams.items() if member_arg(term, member) is not None for t, _ in samples),
                                 key=lambda s: s[0])  # fmt: skip
    times, held, when = naive_states(terms, [given[t] for t in terms])
    if start_ns is not None:
        keep = [i for i, t in enumerate(times) if t >= start_ns]
        times, held, when = [times[i] for i in keep], [held[i] for i in keep], [when[i] for i in keep]
    n = len(times)
    ages = dict(max_age or {})
    names = dict(variables or {})
    sample_times = {term: sorted({t for t, _ in given[term]}) for term in terms}

    def terms_below(node: Node) -> set[Term]:
        found: set[Term] = set()
        todo = [node]
        while todo:
            here = todo.pop()
            if isinstance(here, Stream):
                found.add(here.term)
            for name in ("arg", "left", "right", "body"):
                child = getattr(here, name, None)
                if child is not None and not isinstance(child, str):
                    todo.append(child)
            todo.extend(getattr(here, "args", ()) if isinstance(here, Call) else ())
            if isinstance(here, Index):
                todo.extend([here.stream, *here.keys])
        return found

    def stale_somewhere(node: Node, lo: int | None, hi: int) -> bool:
        """Whether a term below ``node`` is stale at some whole ns of [lo, hi] (lo None: from the
        first state; a span reaching back before the first state reaches the outages there)."""
        lo = times[0] if lo is None else lo
        for term in terms_below(node):
            if term not in ages:
                continue
            ts = sample_times[term]
            # staleness grows between samples: the first stale time after a sample s is s + age + 1
            for tau in {lo, *(s + ages[term] + 1 for s in ts)}:
                if lo <= tau <= hi:
                    latest = [t for t in ts if t <= tau]
                    if latest and tau - latest[-1] > ages[term]:
                        return True
        return False
    memo: dict[tuple[int, int], Any] = {}
    rmemo: dict[tuple[int, int], float | None] = {}

    def value(node: Node, i: int) -> Any:
        key = (id(node), i)
        if key not in memo:
            memo[key] = compute(node, i)
        return memo[key]

    def as_value(node: Node, i: int) -> Any:
        """A node's value; a condition's verdict as True/False (unknown: U)."""
        v = value(node, i)
        if is_condition(node):
            return U if v is None else v
        return v

    def window_past(interval: Interval, i: int) -> list[int]:
        a, b = interval.lo_ns, interval.hi_ns
        return [j for j in range(n) if a <= times[i] - times[j] and (b is None or times[i] - times[j] <= b)]

    def until(left: Node | None, right: Node, interval: Interval, i: int, negate: bool = False, owner: Node | None = None) -> Verdict:
        a, b = interval.lo_ns, interval.hi_ns
        assert b is not None
        terms_: list[Verdict] = []
        if owner is not None and stale_somewhere(owner, times[i] + a, times[i] + b):
            terms_.append(None)  # an outage in the window: one more unknown
        for j in range(n):
            if a <= times[j] - times[i] <= b:
                chain = [True if left is None else value(left, k) for k in range(i, j)]
                right_j = k_not(value(right, j)) if negate else value(right, j)
                terms_.append(k_and([right_j, *chain]))
        if times[-1] < times[i] + b:  # incomplete window: one more unknown
            terms_.append(None)
        return k_or(terms_)

    def since(left: Node | None, right: Node, interval: Interval, i: int, negate: bool = False, owner: Node | None = None) -> Verdict:
        terms_: list[Verdict] = []
        a, b = interval.lo_ns, interval.hi_ns
        if owner is not None and stale_somewhere(owner, None if b is None else times[i] - b, times[i] - a):
            terms_.append(None)  # an outage in the window: one more unknown
        for j in window_past(interval, i):
            chain = [True if left is None else value(left, k) for k in range(j + 1, i + 1)]
            right_j = k_not(value(right, j)) if negate else value(right, j)
            terms_.append(k_and([right_j, *chain]))
        return k_or(terms_)

    def aggregate(node: Aggregate, i: int) -> Any:
        kind = node.kind
        lo_, hi_ = node.interval.lo_ns, node.interval.hi_ns
        if stale_somewhere(node, None if hi_ is None else times[i] - hi_, times[i] - lo_):
            return U
        if kind == "integral":
            lo, hi = node.interval.lo_ns, node.interval.hi_ns
            start = times[0] if hi is None else max(times[0], times[i] - hi)
            end = times[i] - lo
            if end <= start:
                return 0
            pieces = []
            for j in range(i + 1):
                piece_end = times[j + 1] if j < i else times[i]
                overlap = min(piece_end, end) - max(times[j], start)
                if overlap > 0:
                    x = value(node.arg, j)
                    if not is_number(x):
                        return U
                    pieces.append(x * overlap)
            total = naive_sum(pieces)
            return naive_arith("/", total, 1e9)
        states = window_past(node.interval, i)
        if kind == "rate":
            if len(states) < 2:
                return U
            x, y = value(node.arg, states[0]), value(node.arg, states[-1])
            return naive_arith("/", naive_arith("-", y, x), (times[states[-1]] - times[states[0]]) / 1e9)
        if kind == "count":
            verdicts = [value(node.arg, j) for j in states]
            return U if any(v is None for v in verdicts) else sum(1 for v in verdicts if v is True)
        xs = [value(node.arg, j) for j in states]
        if any(not is_number(x) for x in xs):
            return U
        if kind == "sum":
            return naive_sum(xs)
        if kind == "avg":
            return naive_arith("/", naive_sum(xs), len(xs)) if xs else U
        if not xs:
            return U
        return min(xs) if kind == "min" else max(xs)

    def raw(node: Node, i: int) -> Any:
        """What a lookup looks into and dist measures: a stream's payload (down its fields) or a
        lookup's member as they are; any other operand's value."""
        if isinstance(node, Stream):
            k = terms.index(node.term)
            if node.term in ages and times[i] - when[i][k] > ages[node.term]:
                return U
            return naive_read_raw(held[i][k], node.fields)
        if isinstance(node, Index) and node.param >= 0:  # SpeedLimit(State(r).zone): the member its argument names, held then
            family = node.stream.term
            if family in ages and times[i] - when[i][terms.index(family)] > ages[family]:
                return U
            latest: dict[str, Any] = {}
            for member, samples in streams.items():
                arg = member_arg(family, member)
                before = [v for t, v in samples if t <= times[i]]
                if arg is not None and before:
                    latest[arg] = before[-1]
            found = naive_lookup(latest, value(node.keys[0], i))
            for key in node.keys[1:]:
                found = naive_lookup(found, value(key, i))
            return found
        if isinstance(node, Index):
            found = raw(node.stream, i)
            for key in node.keys:
                found = naive_lookup(found, value(key, i))
            return found
        return value(node, i)

    def compute(node: Node, i: int) -> Any:
        if isinstance(node, Num | Str):
            return node.value
        if isinstance(node, Var):
            return names.get(node.name, U)
        if isinstance(node, Const):
            return node.value
        if isinstance(node, Stream):
            return naive_read(raw(node, i), ())
        if isinstance(node, Neg):
            x = value(node.arg, i)
            return -x if is_number(x) else U
        if isinstance(node, Arith):
            return naive_arith(node.op, value(node.left, i), value(node.right, i))
        if isinstance(node, Call) and node.fn == "robustness":
            r = rob(node.args[0], i)
            return U if r is None else r
        if isinstance(node, Index):
            return naive_read(raw(node, i), ())
        if isinstance(node, Call) and node.fn == "dist":
            return naive_distance(raw(node.args[0], i), raw(node.args[1], i))
        if isinstance(node, Call) and node.fn in ("sqrt", "hypot", "pow"):
            return naive_function(node.fn, [value(a, i) for a in node.args])
        if isinstance(node, Call):
            xs = [value(a, i) for a in node.args]
            if not all(is_number(x) for x in xs):
                return U
            return abs(xs[0]) if node.fn == "abs" else min(xs) if node.fn == "min" else max(xs)
        if isinstance(node, Prev):
            if i == 0:
                return None if is_condition(node.arg) else U
            return value(node.arg, i - 1)
        if isinstance(node, Aggregate):
            return aggregate(node, i)
        if isinstance(node, Atom):
            x = as_value(node.left, i)
            if node.op is None:
                return x if isinstance(x, bool) else None
            assert node.right is not None
            return naive_compare(node.op, x, as_value(node.right, i))
        if isinstance(node, Rise):
            return k_and([value(node.arg, i), k_not(value(node.arg, i - 1) if i else None)])
        if isinstance(node, Fall):
            return k_and([k_not(value(node.arg, i)), value(node.arg, i - 1) if i else None])
        if isinstance(node, Not):
            return k_not(value(node.arg, i))
        if isinstance(node, And):
            return k_and([value(node.left, i), value(node.right, i)])
        if isinstance(node, Or):
            return k_or([value(node.left, i), value(node.right, i)])
        if isinstance(node, Implies):
            return k_or([k_not(value(node.left, i)), value(node.right, i)])
        if isinstance(node, Until):
            return until(node.left, node.right, node.interval, i, owner=node)
        if isinstance(node, Since):
            return since(node.left, node.right, node.interval, i, owner=node)
        if isinstance(node, Eventually):
            return until(None, node.arg, node.interval, i, owner=node)
        if isinstance(node, Once):
            return since(None, node.arg, node.interval, i, owner=node)
        if isinstance(node, Always):
            return k_not(until(None, node.arg, node.interval, i, negate=True, owner=node))  # not eventually not
        assert isinstance(node, Historically)
        return k_not(since(None, node.arg, node.interval, i, negate=True, owner=node))  # not once not

    # -- robustness, from its definitions (None: undefined)

    def rob(node: Node, i: int) -> float | None:
        key = (id(node), i)
        if key not in rmemo:
            rmemo[key] = robust(node, i) if value(node, i) is not None else None
        return rmemo[key]

    def lo_(xs: Sequence[float | None]) -> float | None:
        return None if any(x is None for x in xs) else min(xs, default=math.inf)  # type: ignore[type-var]

    def hi_(xs: Sequence[float | None]) -> float | None:
        return None if any(x is None for x in xs) else max(xs, default=-math.inf)  # type: ignore[type-var]

    def robust(node: Node, i: int) -> float | None:
        if isinstance(node, Const):
            return math.inf if node.value else -math.inf
        if isinstance(node, Atom):
            x = as_value(node.left, i)
            verdict = value(node, i)
            if node.op is None:
                return math.inf if verdict else -math.inf
            y = as_value(node.right, i)  # type: ignore[arg-type]
            if is_number(x) and is_number(y):
                d = float(y - x) if node.op in ("<", "<=") else float(x - y)
                return {"<": d, "<=": d, ">": d, ">=": d, "==": -abs(float(x - y)), "!=": abs(float(x - y))}[node.op]
            return math.inf if verdict else -math.inf
        if isinstance(node, Not):
            r = rob(node.arg, i)
            return None if r is None else -r
        if isinstance(node, And):
            return lo_([rob(node.left, i), rob(node.right, i)])
        if isinstance(node, Or):
            return hi_([rob(node.left, i), rob(node.right, i)])
        if isinstance(node, Implies):
            left = rob(node.left, i)
            return hi_([None if left is None else -left, rob(node.right, i)])
        if isinstance(node, Rise | Fall):
            if i == 0:
                return None
            now, before = rob(node.arg, i), rob(node.arg, i - 1)
            if now is None or before is None:
                return None
            return min(now, -before) if isinstance(node, Rise) else min(-now, before)
        if isinstance(node, Eventually | Always | Until):
            a, b = node.interval.lo_ns, node.interval.hi_ns
            assert b is not None
            if times[-1] < times[i] + b or stale_somewhere(node, times[i] + a, times[i] + b):
                return None  # an incomplete window, or one with an outage
            left = node.left if isinstance(node, Until) else None
            right = node.right if isinstance(node, Until) else node.arg
            sign = -1.0 if isinstance(node, Always) else 1.0
            best: list[float | None] = []
            for j in range(n):
                if a <= times[j] - times[i] <= b:
                    chain = [math.inf if left is None else rob(left, k) for k in range(i, j)]
                    r = rob(right, j)
                    best.append(lo_([None if r is None else sign * r, *chain]))
            out = hi_(best)
            return None if out is None else sign * out
        if isinstance(node, Once | Historically | Since):
            a, b = node.interval.lo_ns, node.interval.hi_ns
            if stale_somewhere(node, None if b is None else times[i] - b, times[i] - a):
                return None  # a window with an outage
            left = node.left if isinstance(node, Since) else None
            right = node.right if isinstance(node, Since) else node.arg
            sign = -1.0 if isinstance(node, Historically) else 1.0
            best = []
            for j in window_past(node.interval, i):
                chain = [math.inf if left is None else rob(left, k) for k in range(j + 1, i + 1)]
                r = rob(right, j)
                best.append(lo_([None if r is None else sign * r, *chain]))
            out = hi_(best)
            return None if out is None else sign * out
        raise AssertionError(f"no robustness for {type(node).__name__}")

    if robustness:
        return [(times[i], value(formula.root, i), rob(formula.root, i)) for i in range(n)]
    return [(times[i], value(formula.root, i)) for i in range(n)]


def is_condition(node: Node) -> bool:
    if isinstance(node, Prev):
        return is_condition(node.arg)
    return not isinstance(node, Num | Str | Var | Stream | Index | Neg | Arith | Call | Aggregate)


# -- strategies

TERMS = (Term("p"), Term("Battery", ("robot",)), Term("q"))
MS = 1_000_000  # traces are in milliseconds: times and bounds are small multiples of it


def streams(terms: Sequence[Term]) -> st.SearchStrategy[Stream]:
    return st.builds(Stream, st.sampled_from(list(terms)), st.sampled_from([(), (), ("v",)]))


def values(terms: Sequence[Term], depth: int = 2) -> st.SearchStrategy[Node]:
    """Expressions over ``terms``: streams, constants, arithmetic, abs/min/max, prev, aggregates."""
    leaves: st.SearchStrategy[Node] = st.one_of(
        streams(terms), streams(terms), st.builds(Num, st.sampled_from([0, 1, 2, 2.5, -1, 0.5]))
    )
    if depth == 0:
        return leaves
    inner = values(terms, depth - 1)
    return st.one_of(
        leaves,
        leaves,
        st.builds(lambda x, c: Call("robustness", (Atom(x, "<", Num(c)),)), inner, st.sampled_from([0, 1, 2.5])),
        st.builds(Arith, st.sampled_from(["+", "-", "*", "/"]), inner, inner),
        st.builds(Neg, inner),
        st.builds(lambda fn, x, y: Call(fn, (x,) if fn == "abs" else (x, y)), st.sampled_from(["abs", "min", "max"]), inner, inner),
        st.builds(Prev, inner),
        st.builds(Aggregate, st.sampled_from(["sum", "avg", "min", "max", "rate", "integral"]), intervals(future=False), inner),
    )


def atoms(terms: Sequence[Term], *, rich: bool = False) -> st.SearchStrategy[Node]:
    """Comparisons (a stream with a constant; with ``rich``, any two expressions, strings and
    booleans too) and boolean atoms over ``terms``."""
    ops = st.sampled_from(["<", "<=", ">", ">=", "==", "!="])
    simple = st.builds(Atom, streams(terms), ops, st.builds(Num, st.sampled_from([0.0, 1.0, 2.0, 2.5])))
    boolean = st.builds(Atom, streams(terms))
    if not rich:
        return st.one_of(simple, simple, boolean)
    two = st.builds(Atom, values(terms), ops, values(terms))
    eq = st.sampled_from(["==", "!="])
    text = st.builds(Atom, streams(terms), eq, st.builds(Str, st.sampled_from(["x", "manual"])))
    truth = st.builds(Atom, streams(terms), eq, st.builds(Const, st.booleans()))
    return st.one_of(simple, two, two, boolean, text, truth)


def intervals(*, future: bool) -> st.SearchStrategy[Interval]:
    """Small intervals in ms, 0 included; past ones may be unbounded."""

    def build(lo: int, width: int, unbounded: bool) -> Interval:
        return Interval(lo * MS, None if (unbounded and not future) else (lo + width) * MS)

    return st.builds(build, st.integers(0, 4), st.integers(0, 5), st.booleans())


def _trees(terms: Sequence[Term], depth: int, *, past: bool, future: bool, rich: bool) -> st.SearchStrategy[Node]:
    """Trees exactly ``depth`` deep along their leftmost deepest path; the other operands shallower."""
    leaves = st.one_of(atoms(terms, rich=rich), atoms(terms, rich=rich), atoms(terms, rich=rich), st.builds(Const, st.booleans()))
    if depth == 0:
        return leaves
    deep = _trees(terms, depth - 1, past=past, future=future, rich=rich)
    any_ = st.one_of(leaves, deep) if depth == 1 else st.one_of(leaves, _trees(terms, depth - 2, past=past, future=future, rich=rich), deep)
    options: list[st.SearchStrategy[Node]] = [
        st.builds(Not, deep),
        st.builds(And, deep, any_),
        st.builds(Or, any_, deep),
        st.builds(Implies, deep, any_),
    ]
    if future:
        options += [
            st.builds(Always, intervals(future=True), deep),
            st.builds(Eventually, intervals(future=True), deep),
            st.builds(Until, deep, any_, intervals(future=True)),
            st.builds(Until, any_, deep, intervals(future=True)),
        ]
    if past:
        options += [
            st.builds(Historically, intervals(future=False), deep),
            st.builds(Once, intervals(future=False), deep),
            st.builds(Since, deep, any_, intervals(future=False)),
            st.builds(Since, any_, deep, intervals(future=False)),
        ]
    if rich and not future:  # edges and counts read decided values of the past
        options += [
            st.builds(Rise, deep),
            st.builds(Fall, deep),
            st.builds(lambda iv, x, op, c: Atom(Aggregate("count", iv, x), op, Num(c)), intervals(future=False), deep, st.sampled_from(["<", ">=", "=="]), st.sampled_from([0, 1, 2])),
            st.builds(lambda x, y: Atom(Prev(Not(x)), "==", y), deep, st.builds(Const, st.booleans())),  # (prev of a bare stream reads its value)
        ]
    return st.one_of(*options)


def formulas(
    terms: Sequence[Term] = TERMS, *, past: bool = True, future: bool = True, max_depth: int = 4, rich: bool = False
) -> st.SearchStrategy[Formula]:
    """Random formulas over ``terms``, 0 to ``max_depth`` operators deep, with every connective and
    the temporal operators asked for, nested in any order; ``rich``: expressions, strings,
    booleans, edges, aggregates and counts too (edges and counts only where no future operator
    is asked for: their operands may not look ahead)."""
    by_depth = [_trees(terms, depth, past=past, future=future, rich=rich) for depth in range(max_depth + 1)]
    return st.integers(0, max_depth).flatmap(lambda depth: by_depth[depth]).map(Formula.of)


VALUES: st.SearchStrategy[Any] = st.one_of(
    st.sampled_from([0, 1, 2, 3, 2.5, 1.0, -1.5]),
    st.sampled_from([0, 1, 2, 3]),
    st.booleans(),
    st.booleans(),
    st.builds(lambda v: {"v": v}, st.one_of(st.sampled_from([0, 1, 2, 3, 0.5]), st.booleans(), st.sampled_from(["x", "manual"]))),
    st.sampled_from([None, "x", "manual", {"w": 1}, float("nan")]),  # unknown for every comparison with a number
)


NUMBERS: st.SearchStrategy[Any] = st.one_of(
    st.sampled_from([0, 1, 2, 3, -2, 7]),
    st.sampled_from([0.5, 2.5, -1.5, 1e-3, 3.25, 0.1]),
    st.builds(lambda v: {"v": v}, st.sampled_from([0, 1, 2, 0.5, -1.5, 0.1])),
    st.builds(lambda v: {"v": v}, st.sampled_from([0, 1, 2, 0.5, -1.5, 0.1])),
)
"""Mostly numbers, at the payload and in the field ``v``: aggregates over them are often decided."""
MOSTLY_NUMBERS: st.SearchStrategy[Any] = st.one_of(NUMBERS, NUMBERS, NUMBERS, NUMBERS, NUMBERS, NUMBERS, NUMBERS, NUMBERS, NUMBERS, VALUES)


@st.composite
def traces(draw: st.DrawFn, terms: Sequence[Term], *, max_samples: int = 30, numeric: bool = False) -> dict[Term, list[tuple[int, Any]]]:
    """Irregular samples (ns, value) per term: gaps of 0 to 4 ms, shared times across streams,
    now and then two samples of one stream at one time (``numeric``: mostly numbers)."""
    pool = MOSTLY_NUMBERS if numeric else VALUES
    out: dict[Term, list[tuple[int, Any]]] = {}
    for term in terms:
        t = draw(st.integers(0, 3))
        samples = []
        for _ in range(draw(st.integers(4, max_samples))):
            samples.append((t * MS, draw(pool)))
            t += draw(st.sampled_from([0, 1, 1, 1, 1, 2, 3, 4]))
        out[term] = samples
    return out


def long_trace(terms: Sequence[Term], seed: int, samples: int = 400) -> dict[Term, list[tuple[int, Any]]]:
    """A long irregular trace from a seed (drawing hundreds of samples through Hypothesis is slow):
    long enough that the monitor drops old states many times over."""
    rng = random.Random(seed)
    pool = [0, 1, 2, 3, 2.5, -1.5, True, False, {"v": 1}, {"v": 3}, {"v": True}, {"v": "x"}, "manual", None]
    out: dict[Term, list[tuple[int, Any]]] = {}
    for term in terms:
        t = rng.randrange(4)
        trace = []
        for _ in range(samples):
            trace.append((t * MS, rng.choice(pool)))
            t += rng.choice([0, 1, 1, 1, 2, 3])
        out[term] = trace
    return out


def seconds(trace: Mapping[Term, Sequence[tuple[int, Any]]]) -> dict[str, list[tuple[float, Any]]]:
    """A trace keyed by term text with times in float seconds, as :func:`evaluate` takes it."""
    return {str(term): [(t / 1e9, v) for t, v in samples] for term, samples in trace.items()}


def naive_object_key(value: str | int | float) -> str:
    """The key of the object a string or a finite number names, from the semantics' text (JSON's
    identity: a number is one value however written, a string never a number), by way of the
    json module: a number's key is its value's text (an integer as one, and a float whose value is
    an integer below 2**53), a string's
    the string itself unless it is the key of the number JSON reads it as (or starts with a double
    quote), then its JSON text."""
    if isinstance(value, str):
        if value.startswith('"'):  # (else the string '"1"' would share the string "1"'s key)
            return json.dumps(value, ensure_ascii=False)
        try:
            read = json.loads(value)
        except ValueError:
            return value
        is_number = isinstance(read, (int, float)) and not isinstance(read, bool) and math.isfinite(read)
        return json.dumps(value, ensure_ascii=False) if is_number and naive_object_key(read) == value else value
    if isinstance(value, int):
        return str(value)
    exact = Fraction(value)
    if exact.denominator == 1 and abs(exact) < 2**53:
        return str(exact.numerator)
    return repr(value)


def naive_evaluate_objects(
    var: str, domain: Stream, body: Formula, streams: Mapping[Term, Sequence[tuple[int, Any]]], idle_ns: int,
    max_age: Mapping[Term, int] | None = None,
) -> dict[str, list[list[tuple[int, Verdict]]]]:
    """A foreach formula per object and life, from the text: an object is a string or number the
    domain field names; a life runs while its samples come at most ``idle_ns`` apart; over a life
    the domain stream is the object's samples, the other terms their samples up to ``idle_ns``
    after its last (their values and outages from before the life too), the variable the
    object's value; states from the life's first sample."""
    own = streams[domain.term]
    objects: dict[str, list[list[tuple[int, Any]]]] = {}
    last_seen: dict[str, int] = {}
    first_value: dict[str, Any] = {}
    for t, payload in own:
        v = naive_read(payload, domain.fields)
        if isinstance(v, bool) or not (isinstance(v, str) or is_number(v)):
            continue
        key = naive_object_key(v)
        if key not in objects or t - last_seen[key] > idle_ns:
            objects.setdefault(key, []).append([])
        objects[key][-1].append((t, payload))
        last_seen[key] = t
        first_value.setdefault(key, v)
    terms = [domain.term, *(t for t in body.terms if t != domain.term)]
    formula = Formula(body.text, body.root, tuple(terms))
    out: dict[str, list[list[tuple[int, Verdict]]]] = {}
    for key, lives in objects.items():
        for life in lives:
            start, end = life[0][0], life[-1][0] + idle_ns
            picked: dict[Term, list[tuple[int, Any]]] = {domain.term: life}
            for term in terms[1:]:  # every sample before the life too: their outages there count
                if is_family(term):  # a parameterized term's members, each as a stream
                    picked.update({m: [s for s in samples if s[0] <= end] for m, samples in streams.items() if member_arg(term, m) is not None})
                    continue
                picked[term] = [s for s in streams[term] if s[0] <= end]
            value = naive_read(life[0][1], domain.fields)
            out.setdefault(key, []).append(naive_evaluate_ns(formula, picked, variables={var: value}, start_ns=start, max_age=max_age))
    return out


# -- lookups, functions and points (their own terms and payloads: objects, arrays, keys of every kind)

LIMITS, ZONE, P, Q = Term("Limits", ("floor",)), Term("Zone", ("r",)), Term("P", ("a",)), Term("Q", ("b",))
LOOKUP_TERMS = (LIMITS, ZONE, P, Q)

_LIMITS = [
    {"a": 1.0, "b": 2, "3": 0.5, "1": 4, "home": {"x": 1, "y": 1}, "speed": 9, "by_zone": {"a": {"speed": 1.5}, "b": {"speed": 0.5}, "1": {"speed": 3}},
     "open": {"a": True, "b": False, "3": True, "1": False}},
    {"a": 0.5, "b": {"speed": 3}, "2": -1, "home": [2, 2], "by_zone": {"a": {"speed": 2}, "3": {"speed": 0.25}, "b": {"speed": 1}},
     "open": {"a": False, "b": True, "2": True, "3": 1}},
    {"a": True, "b": "fast", "3": None, "home": {"x": 1, "y": 1, "z": 1}},
    [0.5, 2, 3.5, "x", {"speed": 1}],
    [],
    {"A": 1},
    None,
    3,
]
_ZONES = ["a", "b", "3", "1", "2", 3, 3.0, 1, 0, 2.0, 2.5, -1, -4, 0.25, 1e200, True, None, "speed", "home",
          {"v": "a"}, {"v": 1}, {"v": 3.0}, {"v": [1]}]  # fmt: skip
_POINTS = [
    {"x": 0, "y": 0}, {"x": 3, "y": 4}, {"x": 1, "y": 2, "z": 2}, {"x": 1.5, "y": -2, "w": 7}, [1, 2], [1, 2, 3], [0.5], [],
    {"x": "a", "y": 1}, {"x": True, "y": 0}, None, 5, {"position": {"x": 1, "y": 1}}, {"x": 1e308, "y": 0}, {"x": -1e308, "y": 0},
    {"x": 2, "y": 2, "position": [4, 6]},
]  # fmt: skip
# mostly payloads a lookup finds something in, so that many verdicts are decided
_POOLS = {LIMITS: _LIMITS[:2] * 6 + _LIMITS, ZONE: ["a", "b", "3", 3, 1, 2.0, 0.25, {"v": "a"}, {"v": "b"}, {"v": 3}, {"v": 1.0}] * 4 + _ZONES, P: _POINTS[:4] * 4 + _POINTS[5:8] + _POINTS, Q: _POINTS[:4] * 4 + _POINTS}


@st.composite
def lookup_traces(draw: st.DrawFn, terms: Sequence[Term], *, max_samples: int = 20) -> dict[Term, list[tuple[int, Any]]]:
    """Irregular samples (ns, value) of the lookup terms, each from its own pool of payloads."""
    out: dict[Term, list[tuple[int, Any]]] = {}
    for term in terms:
        t = draw(st.integers(0, 3))
        samples = []
        for _ in range(draw(st.integers(3, max_samples))):
            samples.append((t * MS, draw(st.sampled_from(_POOLS[term]))))
            t += draw(st.sampled_from([0, 1, 1, 1, 2, 3]))
        out[term] = samples
    return out


_KEYS: st.SearchStrategy[Node] = st.one_of(
    st.just(Stream(ZONE)), st.just(Stream(ZONE, ("v",))), st.builds(Str, st.sampled_from(["a", "b", "home"])), st.builds(Num, st.sampled_from([3, 1, 2.0, 0, -1]))
)


def lookup_values() -> st.SearchStrategy[Node]:
    """Lookups (keys of streams, strings and numbers, chained, after a field path), sqrt, hypot,
    pow and dist over the lookup terms."""
    key = _KEYS
    lookup = st.one_of(
        st.builds(lambda k: Index(Stream(LIMITS), (k,)), key),
        st.builds(lambda k: Index(Stream(LIMITS, ("by_zone",)), (k, Str("speed"))), key),
        st.builds(lambda k, j: Index(Stream(LIMITS), (k, j)), key, key),
    )
    number = st.one_of(lookup, st.just(Stream(ZONE)), st.just(Stream(P, ("x",))), st.builds(Num, st.sampled_from([-1, 0, 0.5, 2, 3])))
    point = st.one_of(st.just(Stream(P)), st.just(Stream(Q)), st.just(Stream(P, ("position",))), st.just(Index(Stream(LIMITS), (Str("home"),))),
                      st.builds(lambda k: Index(Stream(LIMITS), (k,)), key))  # fmt: skip
    return st.one_of(
        lookup,
        lookup,
        st.builds(lambda x: Call("sqrt", (x,)), number),
        st.builds(lambda x, y: Call("hypot", (x, y)), number, number),
        st.builds(lambda x, y: Call("pow", (x, y)), number, number),
        st.builds(lambda p, q: Call("dist", (p, q)), point, point),
        st.builds(lambda p, q: Arith("+", Call("dist", (p, q)), Num(1)), point, point),
    )


def lookup_formulas(*, future: bool = True) -> st.SearchStrategy[Formula]:
    """Atoms over :func:`lookup_values` (with a constant, with each other, ``==`` with a string),
    alone or under one connective, temporal operator or aggregate."""
    ops = st.sampled_from(["<", "<=", ">", ">=", "==", "!="])
    values_ = lookup_values()
    atom = st.one_of(
        st.builds(Atom, values_, ops, st.builds(Num, st.sampled_from([0, 0.5, 1, 2, 5]))),
        st.builds(Atom, values_, ops, values_),
        st.builds(lambda k: Atom(Index(Stream(LIMITS), (k,)), "==", Str("fast")), _KEYS),
        st.builds(Atom, st.builds(lambda k: Index(Stream(LIMITS, ("open",)), (k,)), _KEYS)),  # a bare boolean member
    )
    past = [
        st.builds(Historically, intervals(future=False), atom),
        st.builds(Once, intervals(future=False), atom),
        st.builds(lambda kind, iv, v, c: Atom(Aggregate(kind, iv, v), ">", Num(c)), st.sampled_from(["max", "avg", "sum"]),
                  intervals(future=False), values_, st.sampled_from([0, 1, 2])),  # fmt: skip
    ]
    ahead = [st.builds(Always, intervals(future=True), atom), st.builds(Eventually, intervals(future=True), atom)] if future else []
    tree = st.one_of(atom, atom, st.builds(Not, atom), st.builds(And, atom, atom), st.builds(Or, atom, atom), *past, *ahead)
    return tree.map(Formula.of)


# -- parameterized terms: Limit(Zone(r)), Limit(Zone(r).v).speed (a family of members Limit(a), Limit(b), ...)

LIMIT = family_term("Limit", ("*",))
MEMBERS = (Term("Limit", ("a",)), Term("Limit", ("b",)), Term("Limit", ("home",)), Term("Limit", ("speed",)))
_MEMBER_VALUES = [1.0, 0.5, 2, 3, 0, 1.5] * 3 + [{"speed": 1.5}, {"speed": 1}, {"speed": 0.5, "x": 1, "y": 1}, {"x": 0, "y": 4}, True, "fast", None, [1, 2]]
_MEMBER_ZONES = ["a", "b", "home", "speed"] * 3 + [{"v": "a"}, {"v": "b"}, {"v": "home"}, "zz", 3, None]
_ARGUMENTS: st.SearchStrategy[Node] = st.sampled_from([Stream(ZONE), Stream(ZONE), Stream(ZONE, ("v",))])


@st.composite
def family_traces(draw: st.DrawFn, *, max_samples: int = 15) -> dict[Term, list[tuple[int, Any]]]:
    """Irregular samples of Zone(r), P(a) and some of Limit's members (none, at times: then
    every lookup is unknown), each member's values from a pool of numbers, objects and junk."""
    out: dict[Term, list[tuple[int, Any]]] = {}
    chosen = [m for m in MEMBERS if draw(st.sampled_from([True, True, True, False]))]
    for term in [ZONE, P, *chosen]:  # (no member at all, sometimes: every lookup unknown)
        t = draw(st.integers(0, 4))
        samples = []
        for _ in range(draw(st.integers(1 if term in MEMBERS else 3, max_samples))):
            pool = _MEMBER_ZONES if term == ZONE else _POOLS[term] if term in _POOLS else _MEMBER_VALUES
            samples.append((t * MS, draw(st.sampled_from(pool))))
            t += draw(st.sampled_from([0, 1, 1, 2, 3]))
        out[term] = samples
    return out


def family_formulas(*, future: bool = True) -> st.SearchStrategy[Formula]:
    """Atoms over a parameterized term (alone, with a field after it, as a point of dist, beside
    another stream), alone or under one connective, temporal operator or aggregate."""
    ops = st.sampled_from(["<", "<=", ">", ">=", "==", "!="])
    member = st.builds(lambda k: Index(Stream(LIMIT), (k,), 0), _ARGUMENTS)
    field = st.builds(lambda k: Index(Stream(LIMIT), (k, Str("speed")), 0), _ARGUMENTS)
    value = st.one_of(member, member, field)
    atom = st.one_of(
        st.builds(Atom, value, ops, st.builds(Num, st.sampled_from([0, 0.5, 1, 2]))),
        st.builds(Atom, value, ops, st.just(Stream(P, ("x",)))),
        st.builds(lambda v: Atom(v, "==", Str("fast")), value),
        st.builds(Atom, member),  # a bare boolean member
        st.builds(lambda v: Atom(Call("dist", (v, Stream(P))), "<", Num(3)), member),
    )
    past = [
        st.builds(Historically, intervals(future=False), atom),
        st.builds(Once, intervals(future=False), atom),
        st.builds(lambda kind, iv, v: Atom(Aggregate(kind, iv, v), ">", Num(1)), st.sampled_from(["max", "avg", "min"]),
                  intervals(future=False), value),  # fmt: skip
    ]
    ahead = [st.builds(Always, intervals(future=True), atom), st.builds(Eventually, intervals(future=True), atom)] if future else []
    tree = st.one_of(atom, atom, st.builds(Not, atom), st.builds(And, atom, atom), st.builds(Or, atom, atom), *past, *ahead)
    return tree.map(Formula.of)
