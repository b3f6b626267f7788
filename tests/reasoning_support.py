"""For the temporal reasoning tests: a naive evaluator written from the issue's definitions, and
Hypothesis strategies for formulas and irregular traces.

The naive evaluator shares no code with :mod:`dyknow.reasoning.semantics`: it reads the
definitions literally (every window enumerated, every AND and OR over explicit lists of Python
``True``/``False``/``None``), quadratic and slow, which is the point.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping, Sequence
from typing import Any

from hypothesis import strategies as st

from dyknow.reasoning.syntax import (
    Always,
    And,
    Atom,
    Const,
    Eventually,
    Formula,
    Historically,
    Implies,
    Interval,
    Node,
    Not,
    Once,
    Or,
    Since,
    Until,
)
from dyknow.tags import Term

Verdict = bool | None


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


def naive_atom(atom: Atom, value: Any) -> Verdict:
    """An atom on a held value, from the semantics' text."""
    for name in atom.fields:
        if not isinstance(value, dict) or name not in value:
            return None
        value = value[name]
    if atom.op is None:
        return value if isinstance(value, bool) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        return None
    x, y = value, atom.number
    return {"<": x < y, "<=": x <= y, ">": x > y, ">=": x >= y, "==": x == y, "!=": x != y}[atom.op]


def naive_states(terms: Sequence[Term], streams: Sequence[Sequence[tuple[int, Any]]]) -> tuple[list[int], list[list[Any]]]:
    """States from the definition: distinct times from the first time all streams have a value,
    each holding every stream's latest value (the later sample wins at equal times)."""
    if not streams or any(not s for s in streams):
        return [], []
    start = max(s[0][0] for s in streams)
    times = sorted({t for s in streams for t, _ in s if t >= start})
    held = [[[v for t, v in s if t <= now][-1] for s in streams] for now in times]
    return times, held


def naive_evaluate_ns(formula: Formula, streams: Mapping[Term, Sequence[tuple[int, Any]]]) -> list[tuple[int, Verdict]]:
    """Every state's (t_ns, verdict), straight from the definitions."""
    terms = list(formula.terms)
    times, held = naive_states(terms, [streams[t] for t in terms])
    n = len(times)
    memo: dict[tuple[int, int], Verdict] = {}

    def value(node: Node, i: int) -> Verdict:
        key = (id(node), i)
        if key not in memo:
            memo[key] = compute(node, i)
        return memo[key]

    def target(node: Node, j: int, negate: bool) -> Verdict:
        return k_not(value(node, j)) if negate else value(node, j)

    def until(left: Node | None, right: Node, interval: Interval, i: int, negate: bool = False) -> Verdict:
        a, b = interval.lo_ns, interval.hi_ns
        assert b is not None
        terms_: list[Verdict] = []
        for j in range(n):
            if a <= times[j] - times[i] <= b:
                chain = [True if left is None else value(left, k) for k in range(i, j)]
                terms_.append(k_and([target(right, j, negate), *chain]))
        if times[-1] < times[i] + b:  # incomplete window: one more unknown
            terms_.append(None)
        return k_or(terms_)

    def since(left: Node | None, right: Node, interval: Interval, i: int, negate: bool = False) -> Verdict:
        a, b = interval.lo_ns, interval.hi_ns
        terms_: list[Verdict] = []
        for j in range(n):
            if a <= times[i] - times[j] and (b is None or times[i] - times[j] <= b):
                chain = [True if left is None else value(left, k) for k in range(j + 1, i + 1)]
                terms_.append(k_and([target(right, j, negate), *chain]))
        return k_or(terms_)

    def compute(node: Node, i: int) -> Verdict:
        if isinstance(node, Atom):
            return naive_atom(node, held[i][terms.index(node.term)])
        if isinstance(node, Const):
            return node.value
        if isinstance(node, Not):
            return k_not(value(node.arg, i))
        if isinstance(node, And):
            return k_and([value(node.left, i), value(node.right, i)])
        if isinstance(node, Or):
            return k_or([value(node.left, i), value(node.right, i)])
        if isinstance(node, Implies):
            return k_or([k_not(value(node.left, i)), value(node.right, i)])
        if isinstance(node, Until):
            return until(node.left, node.right, node.interval, i)
        if isinstance(node, Since):
            return since(node.left, node.right, node.interval, i)
        if isinstance(node, Eventually):
            return until(None, node.arg, node.interval, i)
        if isinstance(node, Once):
            return since(None, node.arg, node.interval, i)
        if isinstance(node, Always):
            return k_not(until(None, node.arg, node.interval, i, negate=True))  # not eventually not
        assert isinstance(node, Historically)
        return k_not(since(None, node.arg, node.interval, i, negate=True))  # not once not

    return [(times[i], value(formula.root, i)) for i in range(n)]


# -- strategies

TERMS = (Term("p"), Term("Battery", ("robot",)), Term("q"))
MS = 1_000_000  # traces are in milliseconds: times and bounds are small multiples of it


def atoms(terms: Sequence[Term]) -> st.SearchStrategy[Atom]:
    """Comparisons (on the payload or a field) and boolean atoms over ``terms``."""
    term = st.sampled_from(list(terms))
    fields = st.sampled_from([(), (), ("v",)])
    comparison = st.builds(Atom, term, fields, st.sampled_from(["<", "<=", ">", ">=", "==", "!="]), st.sampled_from([0.0, 1.0, 2.0, 2.5]))
    return st.one_of(comparison, comparison, st.builds(Atom, term, fields))


def intervals(*, future: bool) -> st.SearchStrategy[Interval]:
    """Small intervals in ms, 0 included; past ones may be unbounded."""

    def build(lo: int, width: int, unbounded: bool) -> Interval:
        return Interval(lo * MS, None if (unbounded and not future) else (lo + width) * MS)

    return st.builds(build, st.integers(0, 4), st.integers(0, 5), st.booleans())


def _trees(terms: Sequence[Term], depth: int, *, past: bool, future: bool) -> st.SearchStrategy[Node]:
    """Trees exactly ``depth`` deep along their leftmost deepest path; the other operands shallower."""
    leaves = st.one_of(atoms(terms), atoms(terms), atoms(terms), st.builds(Const, st.booleans()))
    if depth == 0:
        return leaves
    deep = _trees(terms, depth - 1, past=past, future=future)
    any_ = st.one_of(leaves, deep) if depth == 1 else st.one_of(leaves, _trees(terms, depth - 2, past=past, future=future), deep)
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
    return st.one_of(*options)


def formulas(terms: Sequence[Term] = TERMS, *, past: bool = True, future: bool = True, max_depth: int = 4) -> st.SearchStrategy[Formula]:
    """Random formulas over ``terms``, 0 to ``max_depth`` operators deep, with every connective and
    the temporal operators asked for, nested in any order."""
    by_depth = [_trees(terms, depth, past=past, future=future) for depth in range(max_depth + 1)]
    return st.integers(0, max_depth).flatmap(lambda depth: by_depth[depth]).map(Formula.of)


VALUES: st.SearchStrategy[Any] = st.one_of(
    st.sampled_from([0, 1, 2, 3, 2.5, 1.0]),
    st.sampled_from([0, 1, 2, 3]),
    st.booleans(),
    st.booleans(),
    st.builds(lambda v: {"v": v}, st.one_of(st.sampled_from([0, 1, 2, 3]), st.booleans())),
    st.sampled_from([None, "x", {"w": 1}, float("nan")]),  # unknown for every atom
)


@st.composite
def traces(draw: st.DrawFn, terms: Sequence[Term], *, max_samples: int = 30) -> dict[Term, list[tuple[int, Any]]]:
    """Irregular samples (ns, value) per term: gaps of 0 to 4 ms, shared times across streams,
    now and then two samples of one stream at one time."""
    out: dict[Term, list[tuple[int, Any]]] = {}
    for term in terms:
        t = draw(st.integers(0, 3))
        samples = []
        for _ in range(draw(st.integers(4, max_samples))):
            samples.append((t * MS, draw(VALUES)))
            t += draw(st.sampled_from([0, 1, 1, 1, 1, 2, 3, 4]))
        out[term] = samples
    return out


def long_trace(terms: Sequence[Term], seed: int, samples: int = 400) -> dict[Term, list[tuple[int, Any]]]:
    """A long irregular trace from a seed (drawing hundreds of samples through Hypothesis is slow):
    long enough that the monitor drops old states many times over."""
    rng = random.Random(seed)
    pool = [0, 1, 2, 3, 2.5, True, False, {"v": 1}, {"v": 3}, {"v": True}, None]
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
