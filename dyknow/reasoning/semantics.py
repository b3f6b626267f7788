"""The semantics of temporal formulas, exactly, and :func:`evaluate`, which computes it offline.

This module is the one home of what a formula means; the incremental monitor
(:mod:`dyknow.reasoning.progression`) computes the same verdicts and is tested against
:func:`evaluate`, which is tested against a naive evaluator written from this text.

**States.** The streams a formula mentions are synchronized into states: the sorted distinct
sample times of all of them (a message's time is its header's origin time), starting at the first
time every mentioned stream has a value; each state holds every stream's latest value (sample and
hold). Samples before that first time only set the values held. Two samples of one stream at one
time: the later one in the sequence is the value. Times are integer nanoseconds (float seconds
``t`` are read as ``round(t * 1e9)``). A formula that mentions no stream (``true``) has no states.

**Verdicts.** Each state i (time t_i) gets a verdict: true, false or unknown. Connectives are
Kleene's three-valued ones: ``not`` swaps true and false; ``and`` is false if either side is false,
true if both are true, unknown otherwise; ``or`` dually; ``F implies G`` is ``(not F) or G``.

**Atoms** look at the value a state holds for their stream, down the field path when there is
one (each step needs a JSON object, a ``dict``, holding the field):

- ``stream OP number`` is true or false when the value is an ``int`` or a ``float`` (not a
  ``bool``, not NaN), compared as Python compares numbers; **unknown** otherwise: a missing field,
  a payload that is not an object, a string, ``null``, a boolean.
- a bare ``stream`` is the value when it is a ``bool``, **unknown** otherwise (``1`` is not true).

So a malformed message makes its states unknown for the atoms that read it, never false.

**Windows.** A future operator at state i looks at the states j with t_j - t_i in [a, b], a past
one at those with t_i - t_j in [a, b] (``b = inf``: no bound). A future window is complete once a
state at or after t_i + b exists; an incomplete window counts as one more unknown. A past window is
always complete: there is nothing before the first state.

- ``F until[a,b] G`` at i = OR over j in the window of (G at j AND F at every k with i <= k < j);
- ``F since[a,b] G`` at i = OR over j in the window of (G at j AND F at every k with j < k <= i);
- ``eventually[a,b] F`` = ``true until[a,b] F``, ``always[a,b] F`` = ``not eventually[a,b] not F``,
  ``once[a,b] F`` = ``true since[a,b] F``, ``historically[a,b] F`` = ``not once[a,b] not F``.

OR is true if any term is true, false if all are false, unknown otherwise; AND dually. **An empty
window** (no state in it): OR over nothing is false and AND over nothing is true, as in every
logic with bounded quantifiers: ``once[1s, 2s] p`` is false at a state less than a second after the
first one, ``historically[1s, 2s] p`` is true there. For a future operator this holds once the
window is complete (``eventually[1s, 2s] p`` at a state followed by a gap of three seconds is false);
before that the incomplete window keeps it unknown.

**Decided.** A verdict is decided when it is true or false. Over a longer trace (more states after
the last) a decided verdict never changes: new states only replace the unknown of incomplete
windows, and Kleene's connectives are monotone. That is what lets the monitor publish a verdict as
soon as it is decided and be right. A verdict that stays unknown (an incomplete window at the end
of a recording, an atom on a malformed value) is never published by the monitor.

**Other monitors**, compared in ``tests/test_reasoning_semantics.py`` where they agree:

- *reelay* (past-time only) in discrete time, with one sample per state and intervals counted in
  states, gives the same true/false as these semantics on a regular trace whose period is the
  time unit (``historically[0:2]{x > 3}`` and ``historically[0, 2s] x > 3`` at 1 Hz), including
  the start (empty windows false for ``once``, true for ``historically``). It has no unknown (every
  atom has a value), and its dense-time monitor reads the held value *between* samples, which these
  semantics do not (here only sample times are states), so they differ on irregular traces.
- *RTAMT* (0.4.10) in discrete time gives robustness, not verdicts: its sign is the verdict where
  it is not zero (a value equal to the threshold gives 0, which is neither). Future operators are
  monitored online only after ``pastify()``, which delays every verdict by the formula's horizon;
  its first outputs (the warm-up, for times before the trace) have no counterpart here. Its
  0.4.10 wheel mis-pastifies a future operator under ``->`` (``(x >= 3) -> eventually[0:5](y >= 3)``
  gives ``inf`` on every sample, violations included), and a Boolean combination of operands with
  different horizons (``(x > 3) or eventually[0:2](y > 3)`` disagrees on some states); the past
  form written by hand (``once[2:2](x > 3) or once[0:2](y > 3)``) agrees.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections.abc import Mapping, Sequence
from typing import Any

from dyknow.errors import FormulaError, TagError, did_you_mean
from dyknow.reasoning.syntax import (
    Always,
    And,
    Atom,
    Const,
    Eventually,
    Formula,
    Historically,
    Implies,
    Node,
    Not,
    Once,
    Or,
    Since,
    Until,
    children,
    parse,
)
from dyknow.tags import Term, parse_term

__all__ = ["FALSE", "TRUE", "UNKNOWN", "AtomTest", "evaluate", "evaluate_ns", "synchronize", "verdict_of"]

FALSE: int = 0
"""A verdict as an int: false. Kleene's ``and`` is ``min``, ``or`` is ``max``, ``not`` is ``2 - v``."""
UNKNOWN: int = 1
"""A verdict as an int: unknown (neither true nor false, or not decided yet)."""
TRUE: int = 2
"""A verdict as an int: true."""


def verdict_of(value: int) -> bool | None:
    """The verdict as Python sees it: True, False or None for unknown."""
    return True if value == TRUE else False if value == FALSE else None


_OPS = ("<", "<=", ">", ">=", "==", "!=")


class AtomTest:
    """An atom's verdict (:data:`TRUE`, :data:`FALSE`, :data:`UNKNOWN`) on a held value: the one
    definition of atoms (see the module documentation), which the monitor calls too."""

    def __init__(self, atom: Atom) -> None:
        self.fields: tuple[str, ...] = atom.fields
        self.plain = not atom.fields  # the payload itself, no path into it
        self.comparison = atom.op is not None  # else a boolean stream
        self.op = _OPS.index(atom.op) if atom.op is not None else -1
        self.number = float(atom.number) if atom.number is not None else math.nan

    def verdict(self, value: Any) -> int:
        """The atom's verdict on ``value``, the payload its stream holds."""
        if not self.plain:
            for name in self.fields:
                if type(value) is not dict:
                    return UNKNOWN
                value = value.get(name, None)
        if not self.comparison:
            return TRUE if value is True else FALSE if value is False else UNKNOWN
        kind = type(value)
        if kind is not float and kind is not int:
            if kind is bool or not isinstance(value, (int, float)):
                return UNKNOWN
        if value != value:  # NaN
            return UNKNOWN
        number = self.number
        op = self.op
        if op == 0:
            holds = value < number
        elif op == 1:
            holds = value <= number
        elif op == 2:
            holds = value > number
        elif op == 3:
            holds = value >= number
        elif op == 4:
            holds = value == number
        else:
            holds = value != number
        return TRUE if holds else FALSE


def synchronize(terms: Sequence[Term], streams: Sequence[Sequence[tuple[int, Any]]]) -> tuple[list[int], list[tuple[Any, ...]]]:
    """The states of streams (one per term, samples ``(t_ns, value)`` in time order): their times
    and the values each holds, from the first time every stream has a value."""
    merged = sorted((t, k, i) for k, samples in enumerate(streams) for i, (t, _value) in enumerate(samples))
    held: list[Any] = [None] * len(terms)
    seen = [False] * len(terms)
    missing = len(terms)
    times: list[int] = []
    values: list[tuple[Any, ...]] = []
    position = 0
    while position < len(merged):
        t = merged[position][0]
        while position < len(merged) and merged[position][0] == t:  # one state per distinct time
            _t, k, i = merged[position]
            held[k] = streams[k][i][1]
            if not seen[k]:
                seen[k] = True
                missing -= 1
            position += 1
        if missing == 0:
            times.append(t)
            values.append(tuple(held))
    return times, values


def evaluate(formula: str | Formula, streams: Mapping[str, Sequence[tuple[float, Any]]]) -> list[tuple[float, bool | None]]:
    """Every state's ``(t, verdict)`` for ``formula`` over recorded streams; None is unknown.

    ``streams`` maps each term as the formula writes it (``"Battery(robot)"``; spacing inside a
    term does not matter) to its samples ``(t_seconds, value)`` in time order. Streams the formula
    does not mention are ignored. The times returned are the samples' own. Raises
    :class:`~dyknow.errors.FormulaError` for a malformed formula, a term without a stream, or
    samples going back in time.
    """
    parsed = parse(formula) if isinstance(formula, str) else formula
    chosen = _choose(parsed, streams)
    as_ns: list[list[tuple[int, Any]]] = []
    seconds: dict[int, float] = {}
    for samples in chosen:
        converted = []
        for t, value in samples:
            t_ns = round(t * 1_000_000_000)
            seconds.setdefault(t_ns, t)
            converted.append((t_ns, value))
        as_ns.append(converted)
    return [(seconds[t], verdict) for t, verdict in _evaluate_ns(parsed, as_ns, [str(term) for term in parsed.terms])]


def evaluate_ns(formula: str | Formula, streams: Mapping[str, Sequence[tuple[int, Any]]]) -> list[tuple[int, bool | None]]:
    """:func:`evaluate` with integer-nanosecond times (``msg.origin_ns``) in and out."""
    parsed = parse(formula) if isinstance(formula, str) else formula
    return _evaluate_ns(parsed, [list(samples) for samples in _choose(parsed, streams)], [str(term) for term in parsed.terms])


def _choose(formula: Formula, streams: Mapping[str, Sequence[tuple[Any, Any]]]) -> list[Sequence[tuple[Any, Any]]]:
    by_term: dict[Term, Sequence[tuple[Any, Any]]] = {}
    for key, samples in streams.items():
        try:
            by_term[parse_term(key)] = samples
        except TagError:
            continue  # not a term: cannot be one the formula mentions
    chosen = []
    for term in formula.terms:
        if term not in by_term:
            given = [str(key) for key in streams]
            raise FormulaError(
                f"no samples for the term {str(term)!r} of the formula",
                where="evaluate(streams=...)",
                expected=f"a stream for every term: {', '.join(str(t) for t in formula.terms)}; got {', '.join(given) or 'none'}"
                + did_you_mean(str(term), given),
            )
        chosen.append(by_term[term])
    return chosen


def _evaluate_ns(formula: Formula, streams: Sequence[Sequence[tuple[int, Any]]], names: list[str]) -> list[tuple[int, bool | None]]:
    for name, samples in zip(names, streams, strict=True):
        for position in range(1, len(samples)):
            if samples[position][0] < samples[position - 1][0]:
                raise FormulaError(
                    f"the samples of {name!r} go back in time at position {position}: {samples[position][0]} ns after {samples[position - 1][0]} ns",
                    where=f"stream {name!r}",
                    expected="samples in time order (equal times are allowed: the later one is the value)",
                )
    times, values = synchronize(formula.terms, streams)
    index = {term: k for k, term in enumerate(formula.terms)}
    verdicts = _Evaluator(times, values, index).node(formula.root)
    return [(t, verdict_of(v)) for t, v in zip(times, verdicts, strict=True)]


class _Evaluator:
    """Bottom-up evaluation of every node over all states (each node's verdicts as a list)."""

    def __init__(self, times: list[int], values: list[tuple[Any, ...]], index: Mapping[Term, int]) -> None:
        self.times = times
        self.values = values
        self.index = index

    def node(self, root: Node) -> list[int]:
        # iterative post-order: formulas may nest deeper than Python's recursion allows
        done: dict[int, list[int]] = {}
        stack: list[tuple[Node, bool]] = [(root, False)]
        while stack:
            node, expanded = stack.pop()
            kids = children(node)
            if not expanded and kids:
                stack.append((node, True))
                stack.extend((kid, False) for kid in kids)
                continue
            done[id(node)] = self.apply(node, [done[id(kid)] for kid in kids])
        return done[id(root)]

    def apply(self, node: Node, args: list[list[int]]) -> list[int]:
        n = len(self.times)
        if isinstance(node, Atom):
            test = AtomTest(node)
            k = self.index[node.term]
            return [test.verdict(state[k]) for state in self.values]
        if isinstance(node, Const):
            return [TRUE if node.value else FALSE] * n
        if isinstance(node, Not):
            return [2 - v for v in args[0]]
        if isinstance(node, And):
            return [min(x, y) for x, y in zip(args[0], args[1], strict=True)]
        if isinstance(node, Or):
            return [max(x, y) for x, y in zip(args[0], args[1], strict=True)]
        if isinstance(node, Implies):
            return [max(2 - x, y) for x, y in zip(args[0], args[1], strict=True)]
        if isinstance(node, Eventually):
            return self.until([TRUE] * n, args[0], node.interval.lo_ns, _finite(node.interval.hi_ns))
        if isinstance(node, Always):
            return [2 - v for v in self.until([TRUE] * n, [2 - v for v in args[0]], node.interval.lo_ns, _finite(node.interval.hi_ns))]
        if isinstance(node, Until):
            return self.until(args[0], args[1], node.interval.lo_ns, _finite(node.interval.hi_ns))
        if isinstance(node, Once):
            return self.since([TRUE] * n, args[0], node.interval.lo_ns, node.interval.hi_ns)
        if isinstance(node, Historically):
            return [2 - v for v in self.since([TRUE] * n, [2 - v for v in args[0]], node.interval.lo_ns, node.interval.hi_ns)]
        assert isinstance(node, Since)
        return self.since(args[0], args[1], node.interval.lo_ns, node.interval.hi_ns)

    def until(self, left: list[int], right: list[int], a: int, b: int) -> list[int]:
        """``left until[a,b] right`` at every state, from "next" tables built backwards."""
        times, n = self.times, len(self.times)
        # first k >= i where left is not true / is false; first j >= i where right is true / not false
        next_not_true, next_false, next_true, next_not_false = [n] * (n + 1), [n] * (n + 1), [n] * (n + 1), [n] * (n + 1)
        for i in range(n - 1, -1, -1):
            next_not_true[i] = i if left[i] != TRUE else next_not_true[i + 1]
            next_false[i] = i if left[i] == FALSE else next_false[i + 1]
            next_true[i] = i if right[i] == TRUE else next_true[i + 1]
            next_not_false[i] = i if right[i] != FALSE else next_not_false[i + 1]
        last = times[-1] if times else 0
        out = []
        for i in range(n):
            lo = bisect_left(times, times[i] + a)  # the window is [lo, hi]
            hi = bisect_right(times, times[i] + b) - 1
            if next_true[lo] <= min(hi, next_not_true[i]):
                out.append(TRUE)
                continue
            # false: the window is complete (else its unknown rest is one more term, even when a
            # false left already dooms it) and every term is false: right false up to the first
            # false left, the chain broken after it
            complete = last >= times[i] + b
            out.append(FALSE if complete and next_not_false[lo] > min(hi, next_false[i]) else UNKNOWN)
        return out

    def since(self, left: list[int], right: list[int], a: int, b: int | None) -> list[int]:
        """``left since[a,b] right`` at every state, from "last" tables built forwards."""
        times, n = self.times, len(self.times)
        # last k <= i where left is not true / is false; last j <= i where right is true / not false
        last_not_true, last_false, last_true, last_not_false = [-1] * n, [-1] * n, [-1] * n, [-1] * n
        for i in range(n):
            last_not_true[i] = i if left[i] != TRUE else (last_not_true[i - 1] if i else -1)
            last_false[i] = i if left[i] == FALSE else (last_false[i - 1] if i else -1)
            last_true[i] = i if right[i] == TRUE else (last_true[i - 1] if i else -1)
            last_not_false[i] = i if right[i] != FALSE else (last_not_false[i - 1] if i else -1)
        out = []
        for i in range(n):
            lo = 0 if b is None else bisect_left(times, times[i] - b)  # the window is [lo, hi]
            hi = bisect_right(times, times[i] - a) - 1
            if hi < 0:
                out.append(FALSE)  # no state in the window
                continue
            if last_true[hi] >= max(lo, last_not_true[i]):
                out.append(TRUE)
            elif last_not_false[hi] < max(lo, last_false[i]):
                out.append(FALSE)
            else:
                out.append(UNKNOWN)
        return out


def _finite(hi_ns: int | None) -> int:
    assert hi_ns is not None, "future operators have a finite upper bound (the parser checks it)"
    return hi_ns
