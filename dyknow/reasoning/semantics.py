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

**Freshness.** A term may be given a maximum age (``max_age``): at a time more than that after the
term's latest sample (its first excepted: there is no state before it), the term is *stale*. At a
stale state its value is unknown; and a window (of a temporal operator or an aggregate) in whose
time span a term read below the operator is stale counts one more unknown term, so a window an
outage of its streams reaches into is never found false (nor an ``always`` true), nor an
aggregate over it known: a failure is not a violation. The span of a future window at state i
is ``[t_i + a, t_i + b]``, of a past one ``[t_i - b, t_i - a]`` (from the first state when ``b``
is ``inf``). A monitor that is told of a gap (its term re-planned) marks each verdict whose window
reaches into it.

**Values.** A stream's value at a state is the payload it holds, down the field path when there is
one (each step needs a JSON object, a ``dict``, holding the field). A value is a *number* (an
``int`` or a ``float``, not a ``bool``, not NaN nor infinite), a *string* (``str``) or a *boolean*
(``bool``); anything else (a missing field, ``null``, a list, an object, NaN) is **unknown**, and
so is the value of a stale term. Constants are what they say; a ``forall``/``exists`` variable is
its individual, a string; a ``foreach`` variable is its object's value.

- ``-x``, ``x + y``, ``x - y``, ``x * y``, ``x / y``, ``abs(x)``, ``min(x, y)``, ``max(x, y)``
  compute as Python does on numbers (``int`` stays exact, ``/`` divides as floats do); unknown
  when an operand is unknown or not a number, when dividing by zero, and when the result is not
  finite.
- ``prev(X)`` is X's value (or verdict) at the previous state; unknown at the first state.
- ``robustness(F)`` is F's robustness at the state (below), unknown where it is undefined; its
  infinities (``true``, a boolean atom) are numbers here.

**Verdicts.** Each state i (time t_i) gets a verdict: true, false or unknown. Connectives are
Kleene's three-valued ones: ``not`` swaps true and false; ``and`` is false if either side is false,
true if both are true, unknown otherwise; ``or`` dually; ``F implies G`` is ``(not F) or G``.

**Atoms.** ``x < y`` (``<=``, ``>``, ``>=``) is true or false when both are numbers, compared as
Python compares numbers; unknown otherwise. ``x == y`` (and ``!=``) is true or false when both are
numbers (``1 == 1.0``), both strings, or both booleans (a condition used as a value is its verdict:
true, false, or unknown); unknown when either is unknown or they are of different kinds. A bare
value read as a condition is itself when it is a boolean, unknown otherwise (``1`` is not true).
``rise(F)`` is ``F and not prev(F)``, ``fall(F)`` is ``not F and prev(F)`` (Kleene: unknown at the
first state unless F is false there, true there respectively). So a malformed message makes its
states unknown for the atoms that read it, never false.

**Windows.** A future operator at state i looks at the states j with t_j - t_i in [a, b], a past
one (and an aggregate) at those with t_i - t_j in [a, b] (``b = inf``: no bound). A future window
is complete once a state at or after t_i + b exists; an incomplete window counts as one more
unknown. A past window is always complete: there is nothing before the first state.

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

**Aggregates** at state i read the states of its past window W (as ``once`` does); each is unknown
when the operand is unknown at a state of W it reads:

- ``count[a,b] F``: how many states of W have F true (an ``int``; 0 for an empty window);
- ``sum[a,b] x``: the sum of x over W: exact when every value is an ``int``, else the exactly
  rounded sum of the values as floats (``math.fsum``); 0 for an empty window; unknown if not finite;
- ``avg[a,b] x``: ``sum / count`` of W's states (``/`` as above); unknown for an empty window;
- ``min[a,b] x``, ``max[a,b] x``: the least and greatest value over W; unknown for an empty window;
- ``rate[a,b] x``: ``(x at W's newest state - x at W's oldest) / (their times apart, in seconds)``;
  it reads those two states only, and is unknown when W has fewer than two;
- ``integral[a,b] x``: the integral of x held from each state to the next (sample and hold) over
  the time span ``[max(t_i - b, t_0), t_i - a]`` (0 when it is empty), in value times seconds: the
  pieces are ``x_j * d_j`` for each state j whose piece ``[t_j, t_{j+1})`` (the last: ``[t_i,
  t_i]``) overlaps the span by ``d_j`` nanoseconds, summed as ``sum`` sums them, then divided by
  ``1e9``. It reads the states whose pieces overlap the span, the one before W's oldest included.

**Quantifiers.** ``forall c in C: F`` is ``F[c:=v1] and ... and F[c:=vn]`` over the individuals of
the class C (the variable replaced where it is a term's argument and where it is a value);
``exists`` is the same with ``or``. ``foreach x in S.f: F`` is one formula per *object*: per value
of ``S.f`` (a string or a number; a sample whose field is anything else belongs to no object; a
sample of ``S`` whose value is a list, a *frame* such as a tracker's tracks, is one sample per
element, all at its time). An
object *lives* from its first sample until more than ``idle`` (ns of sample time) pass before its
next one, which starts a new life: each life is evaluated apart, over states whose times are the
object's samples in the life and the other terms' samples between the life's first sample and
``idle`` after its last; there ``S`` holds the object's own samples only, the other terms their
latest value (from before the life too), and ``x`` is the object's value.

**Robustness** (the space robustness of STL, where a verdict has one): a real number whose sign is
the verdict's where it is not 0. ``x < y`` and ``x <= y`` give ``y - x``, ``x > y`` and ``x >= y``
give ``x - y``, ``x == y`` gives ``-|x - y|`` and ``x != y`` gives ``|x - y|`` on numbers; an atom
on strings or booleans, ``true``, ``false`` and a bare boolean value give ``+inf`` when true and
``-inf`` when false. ``not`` negates; ``and`` is the least, ``or`` the greatest, ``implies``
``max(-l, r)``; ``eventually`` and ``once`` the greatest over the window (``-inf`` over an empty
one), ``always`` and ``historically`` the least (``+inf``); ``until`` and ``since`` the greatest
over j of ``min(r(G at j), the least r(F) over the chain)``; ``rise(F)`` is ``min(r(F), -r(prev
F))``, ``fall(F)`` ``min(-r(F), r(prev F))``. It is undefined (None) where the verdict is unknown,
where a value it needs is undefined, and where a future window it reads is incomplete.

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
- *RTAMT* (0.4.10) in discrete time gives robustness: the same as here on a regular trace whose
  period is the time unit, past the first state (its ``prev`` and ``rise`` assume a value before
  the first sample: ``+inf`` and ``-inf``, where these semantics say unknown). Future operators are
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
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Final

from dyknow.errors import FormulaError, TagError, did_you_mean
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
    parse_value,
    walk,
)
from dyknow.tags import Term, parse_term

__all__ = [
    "FALSE",
    "TRUE",
    "UNKNOWN",
    "UNKNOWN_VALUE",
    "arith",
    "call",
    "compare",
    "evaluate",
    "evaluate_ns",
    "evaluate_objects",
    "evaluate_values",
    "expand_quantifiers",
    "object_key",
    "read",
    "synchronize",
    "truth",
    "verdict_of",
]

FALSE: Final = 0
"""A verdict as an int: false. Kleene's ``and`` is ``min``, ``or`` is ``max``, ``not`` is ``2 - v``."""
UNKNOWN: Final = 1
"""A verdict as an int: unknown (neither true nor false, or not decided yet)."""
TRUE: Final = 2
"""A verdict as an int: true."""


class _Unknown:
    """The one unknown value (a missing field, a value of the wrong kind, a division by zero)."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "UNKNOWN_VALUE"

    def __bool__(self) -> bool:
        return False


UNKNOWN_VALUE: Final = _Unknown()
"""What an expression gives where its value is unknown."""

_INF: Final = math.inf


def verdict_of(value: int) -> bool | None:
    """The verdict as Python sees it: True, False or None for unknown."""
    return True if value == TRUE else False if value == FALSE else None


# ---------------------------------------------------------------------------- values (shared with the monitor)


def read(payload: Any, fields: tuple[str, ...]) -> Any:
    """A stream's value: ``payload`` down ``fields``, as a number, string or boolean; else unknown."""
    value = payload
    for name in fields:
        if type(value) is not dict:
            return UNKNOWN_VALUE
        value = value.get(name, UNKNOWN_VALUE)
    kind = type(value)
    if kind is float:
        return value if value - value == 0.0 else UNKNOWN_VALUE  # NaN and infinities: unknown
    if kind is int or kind is str or kind is bool:
        return value
    if isinstance(value, bool):
        return bool(value)
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        value = float(value)
        return value if value - value == 0.0 else UNKNOWN_VALUE
    if isinstance(value, str):
        return str(value)
    return UNKNOWN_VALUE


def _is_number(value: Any) -> bool:
    kind = type(value)
    return kind is int or kind is float


def arith(op: str, x: Any, y: Any) -> Any:
    """``x OP y`` on numbers (``op`` one of + - * /); unknown otherwise, on division by zero, and
    when the result is not finite."""
    if not _is_number(x) or not _is_number(y):
        return UNKNOWN_VALUE
    if op == "+":
        result = x + y
    elif op == "-":
        result = x - y
    elif op == "*":
        result = x * y
    else:
        if y == 0:
            return UNKNOWN_VALUE
        try:
            result = x / y
        except OverflowError:  # an int too large for a float
            return UNKNOWN_VALUE
    if type(result) is float and result - result != 0.0:
        return UNKNOWN_VALUE
    return result


def call(fn: str, args: Sequence[Any]) -> Any:
    """``abs(x)``, ``min(x, y)``, ``max(x, y)``, ``-x`` (``fn`` "neg") on numbers; unknown otherwise."""
    for x in args:
        if not _is_number(x):
            return UNKNOWN_VALUE
    if fn == "neg":
        return -args[0]
    if fn == "abs":
        return abs(args[0])
    if fn == "min":
        return args[0] if args[0] <= args[1] else args[1]
    return args[0] if args[0] >= args[1] else args[1]


_OPS: Final = ("<", "<=", ">", ">=", "==", "!=")


def compare(op: str, x: Any, y: Any) -> int:
    """The verdict of ``x OP y`` (see the module documentation)."""
    tx, ty = type(x), type(y)
    numbers = (tx is int or tx is float) and (ty is int or ty is float)
    if op == "==" or op == "!=":
        if not numbers and (tx is not ty or (tx is not str and tx is not bool)):
            return UNKNOWN
        same = x == y
        return TRUE if same == (op == "==") else FALSE
    if not numbers:
        return UNKNOWN
    if op == "<":
        holds = x < y
    elif op == "<=":
        holds = x <= y
    elif op == ">":
        holds = x > y
    else:
        holds = x >= y
    return TRUE if holds else FALSE


def margin(op: str, x: Any, y: Any, verdict: int) -> float | None:
    """The robustness of a decided atom ``x OP y`` (see the module documentation)."""
    if verdict == UNKNOWN:
        return None
    tx, ty = type(x), type(y)
    if (tx is int or tx is float) and (ty is int or ty is float):
        try:
            if op == "<" or op == "<=":
                return float(y - x)
            if op == ">" or op == ">=":
                return float(x - y)
            if op == "==":
                return -float(abs(x - y))
            return float(abs(x - y))
        except OverflowError:
            return _INF if verdict == TRUE else -_INF
    return _INF if verdict == TRUE else -_INF


def truth(value: Any) -> int:
    """A value read as a condition: its verdict when it is a boolean, unknown otherwise."""
    if value is True:
        return TRUE
    if value is False:
        return FALSE
    return UNKNOWN


def as_value(verdict: int) -> Any:
    """A verdict used as a value: True, False or unknown."""
    return True if verdict == TRUE else False if verdict == FALSE else UNKNOWN_VALUE


def object_key(value: Any) -> str | None:
    """The object a ``foreach`` field's value names (as verdict keys carry it): a string as is, a
    number as Python writes it; None for anything else (the sample belongs to no object)."""
    kind = type(value)
    if kind is str:
        return str(value)
    if kind is int or (kind is float and value - value == 0.0):
        return repr(value)
    return None


# ---------------------------------------------------------------------------- quantifiers


def expand_quantifiers(
    formula: Formula, individuals: Callable[[str], Sequence[str]] | None, bindings: Mapping[str, str] | None = None
) -> Formula:
    """``formula`` with every ``forall``/``exists`` replaced by the ``and``/``or`` of its body over
    the class's individuals (``foreach`` is left where it is), and the variables of ``bindings``
    (of quantifiers outside it) replaced by their individuals. :class:`FormulaError` when there
    is a ``forall``/``exists`` and no ``individuals``, or a class without one."""
    if not bindings and not any(isinstance(node, Quantifier) and node.kind != "foreach" for node in walk(formula.root)):
        return formula
    if individuals is None and not any(isinstance(node, Quantifier) and node.kind != "foreach" for node in walk(formula.root)):
        individuals = _none
    if individuals is None:
        raise FormulaError("the formula quantifies over an ontology class, and no individuals are given", where="formula",
                           expected="individuals=... (a manager's ontology: --ontology FILE)")  # fmt: skip
    cache: dict[str, list[str]] = {}

    def members(cls: str) -> list[str]:
        if cls not in cache:
            found = list(dict.fromkeys(v.strip() for v in individuals(cls) if isinstance(v, str) and v.strip()))
            if not found:
                raise FormulaError(f"the class {cls!r} has no individuals", where="formula", expected="a class with at least one individual")
            cache[cls] = found
        return cache[cls]

    return Formula.of(_rewrite(formula.root, members, dict(bindings or {})))


def _none(cls: str) -> Sequence[str]:
    return ()


def _rewrite(root: Node, members: Callable[[str], list[str]], bound: dict[str, str]) -> Node:
    """``root`` with static quantifiers expanded and their variables replaced (iteratively)."""
    # post-order over (node, bindings): a quantifier's body is rewritten once per individual
    done: dict[tuple[int, tuple[tuple[str, str], ...]], Node] = {}
    stack: list[tuple[Node, dict[str, str], bool]] = [(root, bound, False)]
    while stack:
        node, env, expanded = stack.pop()
        key = (id(node), tuple(sorted(env.items())))
        if key in done:
            continue
        if isinstance(node, Quantifier) and node.kind != "foreach":
            assert isinstance(node.domain, str)
            envs = [{**env, node.var: value} for value in members(node.domain)]
            keys = [(id(node.body), tuple(sorted(e.items()))) for e in envs]
            if not expanded:
                stack.append((node, env, True))
                stack.extend((node.body, e, False) for e in envs)
                continue
            parts = [done[k] for k in keys]
            joined = parts[0]
            for part in parts[1:]:
                joined = And(joined, part) if node.kind == "forall" else Or(joined, part)
            done[key] = joined
            continue
        kids = children(node)
        if kids and not expanded:
            stack.append((node, env, True))
            stack.extend((kid, env, False) for kid in kids)
            continue
        args = [done[(id(kid), key[1])] for kid in kids]
        done[key] = _rebuild(node, args, env)
    return done[(id(root), tuple(sorted(bound.items())))]


def _rebuild(node: Node, args: list[Node], env: dict[str, str]) -> Node:
    """``node`` with new operands ``args`` and the variables of ``env`` replaced."""
    if isinstance(node, Stream):
        if any(a in env for a in node.term.args):
            return Stream(Term(node.term.functor, tuple(env.get(a, a) for a in node.term.args)), node.fields)
        return node
    if isinstance(node, Var):
        return Str(env[node.name]) if node.name in env else node
    if isinstance(node, Num | Str | Const):
        return node
    if isinstance(node, Atom):
        return Atom(args[0], node.op, args[1] if len(args) > 1 else None)
    if isinstance(node, Arith):
        return Arith(node.op, args[0], args[1])
    if isinstance(node, Call):
        return Call(node.fn, tuple(args))
    if isinstance(node, Aggregate):
        return Aggregate(node.kind, node.interval, args[0])
    if isinstance(node, Quantifier):  # foreach: its stream's args too
        domain = node.domain
        if isinstance(domain, Stream) and any(a in env for a in domain.term.args):
            domain = Stream(Term(domain.term.functor, tuple(env.get(a, a) for a in domain.term.args)), domain.fields)
        return Quantifier(node.kind, node.var, domain, args[0])
    if isinstance(node, Until | Since):
        return type(node)(args[0], args[1], node.interval)
    if isinstance(node, Always | Eventually | Historically | Once):
        return type(node)(node.interval, args[0])
    if isinstance(node, And | Or | Implies):
        return type(node)(args[0], args[1])
    return type(node)(args[0])  # type: ignore[call-arg]  # Not, Neg, Prev, Rise, Fall


# ---------------------------------------------------------------------------- offline evaluation


def synchronize(terms: Sequence[Term], streams: Sequence[Sequence[tuple[int, Any]]]) -> tuple[list[int], list[tuple[Any, ...]]]:
    """The states of streams (one per term, samples ``(t_ns, value)`` in time order): their times
    and the values each holds, from the first time every stream has a value."""
    times, values, _ = _synchronize(streams)
    return times, values


def _synchronize(streams: Sequence[Sequence[tuple[int, Any]]]) -> tuple[list[int], list[tuple[Any, ...]], list[tuple[int, ...]]]:
    """:func:`synchronize`, and for each state the time of each stream's latest sample."""
    merged = sorted((t, k, i) for k, samples in enumerate(streams) for i, (t, _value) in enumerate(samples))
    held: list[Any] = [None] * len(streams)
    when: list[int] = [0] * len(streams)
    seen = [False] * len(streams)
    missing = len(streams)
    times: list[int] = []
    values: list[tuple[Any, ...]] = []
    ages: list[tuple[int, ...]] = []
    position = 0
    while position < len(merged):
        t = merged[position][0]
        while position < len(merged) and merged[position][0] == t:  # one state per distinct time
            _t, k, i = merged[position]
            held[k] = streams[k][i][1]
            when[k] = t
            if not seen[k]:
                seen[k] = True
                missing -= 1
            position += 1
        if missing == 0:
            times.append(t)
            values.append(tuple(held))
            ages.append(tuple(when))
    return times, values, ages


def evaluate(
    formula: str | Formula,
    streams: Mapping[str, Sequence[tuple[float, Any]]],
    *,
    individuals: Callable[[str], Sequence[str]] | None = None,
    max_age: Mapping[str, float] | None = None,
    robustness: bool = False,
) -> list[Any]:
    """Every state's ``(t, verdict)`` for ``formula`` over recorded streams; None is unknown.

    ``streams`` maps each term as the formula writes it (``"Battery(robot)"``; spacing inside a
    term does not matter) to its samples ``(t_seconds, value)`` in time order. Streams the formula
    does not mention are ignored. The times returned are the samples' own. ``individuals(class)``:
    the ontology's individuals, for ``forall``/``exists``; ``max_age``: a term's freshness in
    seconds; ``robustness``: ``(t, verdict, robustness)`` triples instead. A ``foreach`` formula
    goes to :func:`evaluate_objects`. Raises :class:`~dyknow.errors.FormulaError` for a malformed
    formula, a term without a stream, or samples going back in time.
    """
    parsed = expand_quantifiers(parse(formula) if isinstance(formula, str) else formula, individuals)
    _no_foreach(parsed)
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
    ages = {str(parse_term(k)): round(v * 1_000_000_000) for k, v in (max_age or {}).items()}
    out = _evaluate_ns(parsed, as_ns, [str(term) for term in parsed.terms], ages, robustness)
    return [(seconds[row[0]], *row[1:]) for row in out]


def evaluate_ns(
    formula: str | Formula,
    streams: Mapping[str, Sequence[tuple[int, Any]]],
    *,
    individuals: Callable[[str], Sequence[str]] | None = None,
    max_age_ns: Mapping[str, int] | None = None,
    robustness: bool = False,
) -> list[Any]:
    """:func:`evaluate` with integer-nanosecond times (``msg.origin_ns``) in and out (``max_age_ns`` too)."""
    parsed = expand_quantifiers(parse(formula) if isinstance(formula, str) else formula, individuals)
    _no_foreach(parsed)
    ages = {str(parse_term(k)): int(v) for k, v in (max_age_ns or {}).items()}
    return _evaluate_ns(parsed, [list(samples) for samples in _choose(parsed, streams)], [str(term) for term in parsed.terms], ages, robustness)


def evaluate_values(expression: str | Formula, streams: Mapping[str, Sequence[tuple[int, Any]]]) -> list[tuple[int, Any]]:
    """Every state's ``(t_ns, value)`` of an expression (:func:`~dyknow.reasoning.syntax.parse_value`:
    ``avg[0, 1s] Speed(robot)``, ``Pose(robot).x - Goal(robot).x``); unknown values are None, a
    condition's values its verdicts (True, False, None). Times in integer nanoseconds."""
    parsed = parse_value(expression) if isinstance(expression, str) else expression
    chosen = _choose(parsed, streams)
    times, values, latest = _synchronize([list(samples) for samples in chosen])
    index = {term: k for k, term in enumerate(parsed.terms)}
    evaluator = _Evaluator(times, values, latest, index, [-1] * len(parsed.terms), {}, False)
    column, _ = evaluator.node(parsed.root)
    if _is_condition(parsed.root):
        return [(t, verdict_of(v)) for t, v in zip(times, column, strict=True)]
    return [(t, None if v is UNKNOWN_VALUE else v) for t, v in zip(times, column, strict=True)]


def evaluate_objects(
    formula: str | Formula,
    streams: Mapping[str, Sequence[tuple[int, Any]]],
    *,
    idle_ns: int,
    individuals: Callable[[str], Sequence[str]] | None = None,
    max_age_ns: Mapping[str, int] | None = None,
    robustness: bool = False,
) -> dict[str, list[list[Any]]]:
    """A ``foreach`` formula's verdicts per object and life: ``{object: [[(t_ns, verdict), ...]
    per life]}`` (see the module documentation; ``idle_ns`` ends a life), with integer-nanosecond
    times in and out as :func:`evaluate_ns`."""
    parsed = expand_quantifiers(parse(formula) if isinstance(formula, str) else formula, individuals)
    root = parsed.root
    if not isinstance(root, Quantifier) or root.kind != "foreach":
        raise FormulaError("evaluate_objects takes a foreach formula", where="formula", expected="foreach x in Stream.field: ...")
    domain = root.domain
    assert isinstance(domain, Stream)
    inner = Formula.of(_rewrite_var(root.body, root.var))
    body = Formula(inner.text, inner.root, (domain.term, *(t for t in inner.terms if t != domain.term)))  # the object's samples are states
    ages = {str(parse_term(k)): int(v) for k, v in (max_age_ns or {}).items()}
    chosen = dict(zip([str(t) for t in body.terms], _choose(body, streams), strict=True))
    own = chosen[str(domain.term)]
    lives: dict[str, list[list[tuple[int, Any]]]] = {}
    last: dict[str, int] = {}
    for t, sample in own:
        for payload in sample if type(sample) is list else [sample]:  # a frame: a sample per element
            key = object_key(read(payload, domain.fields))
            if key is None:
                continue
            if key not in lives or t - last[key] > idle_ns:
                lives.setdefault(key, []).append([])
            lives[key][-1].append((t, payload))
            last[key] = t
    out: dict[str, list[list[Any]]] = {}
    for key, runs in lives.items():
        for run in runs:
            start, end = run[0][0], run[-1][0] + idle_ns
            picked = []
            for term in body.terms:
                name = str(term)
                if term == domain.term:
                    picked.append(run)
                else:
                    samples = list(chosen[name])
                    before = [s for s in samples if s[0] < start]
                    picked.append(([before[-1]] if before else []) + [s for s in samples if start <= s[0] <= end])
            value = _object_value(run[0][1], domain.fields)
            rows = _evaluate_ns(body, picked, [str(t) for t in body.terms], ages, robustness, {_OBJECT: value}, start)
            out.setdefault(key, []).append(rows)
    return out


_OBJECT = "\x00object"  # the foreach variable, once its body is read alone


def _object_value(payload: Any, fields: tuple[str, ...]) -> Any:
    return read(payload, fields)


def _rewrite_var(root: Node, var: str) -> Node:
    """``root`` with ``var`` renamed to the object's placeholder (the body read alone)."""
    memo: dict[int, Node] = {}
    for node in reversed(walk(root)):
        args = [memo[id(kid)] for kid in children(node)]
        if isinstance(node, Var) and node.name == var:
            memo[id(node)] = Var(_OBJECT)
        else:
            memo[id(node)] = _rebuild(node, args, {}) if args else node
    return memo[id(root)]


def _no_foreach(formula: Formula) -> None:
    if isinstance(formula.root, Quantifier) and formula.root.kind == "foreach":
        raise FormulaError("a foreach formula has verdicts per object", where="formula", expected="evaluate_objects(...)")


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


def _evaluate_ns(
    formula: Formula,
    streams: Sequence[Sequence[tuple[int, Any]]],
    names: list[str],
    ages: Mapping[str, int],
    robustness: bool,
    variables: Mapping[str, Any] | None = None,
    start_ns: int | None = None,
) -> list[Any]:
    for name, samples in zip(names, streams, strict=True):
        for position in range(1, len(samples)):
            if samples[position][0] < samples[position - 1][0]:
                raise FormulaError(
                    f"the samples of {name!r} go back in time at position {position}: {samples[position][0]} ns after {samples[position - 1][0]} ns",
                    where=f"stream {name!r}",
                    expected="samples in time order (equal times are allowed: the later one is the value)",
                )
    times, values, latest = _synchronize(streams)
    if start_ns is not None:  # a foreach life: its states start with the object's first sample
        first = bisect_left(times, start_ns)
        times, values, latest = times[first:], values[first:], latest[first:]
    index = {term: k for k, term in enumerate(formula.terms)}
    max_age = [ages.get(str(term), -1) for term in formula.terms]
    wants = robustness or any(isinstance(n, Call) and n.fn == "robustness" for n in walk(formula.root))
    evaluator = _Evaluator(times, values, latest, index, max_age, dict(variables or {}), wants)
    evaluator.stale = _stale_periods(streams, max_age)
    verdicts, margins = evaluator.node(formula.root)
    if robustness:
        return [(t, verdict_of(v), r) for t, v, r in zip(times, verdicts, margins, strict=True)]
    return [(t, verdict_of(v)) for t, v in zip(times, verdicts, strict=True)]


def _stale_periods(streams: Sequence[Sequence[tuple[int, Any]]], max_age: list[int]) -> list[list[tuple[int, int | None]]]:
    """Per term, the open time spans ``(from, until)`` in which it is stale (``until`` None: from
    its last sample on), given its samples and maximum age (-1: never stale)."""
    out: list[list[tuple[int, int | None]]] = []
    for samples, age in zip(streams, max_age, strict=True):
        periods: list[tuple[int, int | None]] = []
        if age >= 0 and samples:
            times = sorted({t for t, _ in samples})
            for before, after in zip(times, times[1:], strict=False):
                if after - before > age:
                    periods.append((before + age, after))
            periods.append((times[-1] + age, None))
        out.append(periods)
    return out


def stale_in(periods: Sequence[tuple[int, int | None]], lo: int | None, hi: int) -> bool:
    """Whether a stale period (open: ``from < t < until``) holds a time ``t`` of the span ``[lo,
    hi]`` (``lo`` None: no bound)."""
    for start, end in periods:
        first = start + 1 if lo is None else max(start + 1, lo)
        last = hi if end is None else min(end - 1, hi)
        if first <= last:
            return True
    return False


class _Evaluator:
    """Bottom-up evaluation of every node over all states: a condition's verdicts (and robustness),
    a value's values, each as a list."""

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
        self.robust = robustness
        self.n = len(times)

    def node(self, root: Node) -> tuple[list[Any], list[float | None]]:
        """A node's column over all states (a condition's verdicts, a value's values) and its robustness."""
        # iterative post-order: formulas may nest deeper than Python's recursion allows
        done: dict[int, tuple[list[Any], list[float | None]]] = {}
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
                else:
                    out.append(read(self.values[i][k], node.fields))
            return out, none
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
        """Whether one of ``terms`` is stale at a time of ``[lo, hi]`` (from the first state when ``lo`` is None)."""
        first = self.times[0] if self.times else 0
        lo = first if lo is None else max(lo, first)
        return any(stale_in(self.stale[k], lo, hi) for k in terms)

    @staticmethod
    def _unknown_like(node: Node) -> Any:
        return UNKNOWN if _is_condition(node) else UNKNOWN_VALUE

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
        if _is_condition(node):
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
                if not _is_number(x) or not _is_number(y):
                    out.append(UNKNOWN_VALUE)
                    continue
                out.append(arith("/", arith("-", y, x), (self.times[last] - self.times[first]) / 1e9))
                continue
            part = column[first : last + 1] if last >= first else []
            if kind == "count":
                out.append(UNKNOWN_VALUE if any(v == UNKNOWN for v in part) else sum(1 for v in part if v == TRUE))
                continue
            if any(not _is_number(x) for x in part):
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
                if not _is_number(x):
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


def _is_condition(node: Node) -> bool:
    """Whether a node gives verdicts (else values)."""
    if isinstance(node, Prev):
        return _is_condition(node.arg)
    return not isinstance(node, Num | Str | Var | Stream | Neg | Arith | Call | Aggregate)


def exact_sum(values: Sequence[Any]) -> Any:
    """The sum of numbers as the semantics defines it: exact for ``int`` s, else the exactly rounded
    sum of the values as floats (``math.fsum``); unknown when that is not finite."""
    if all(type(x) is int for x in values):
        return sum(values)
    try:
        total = math.fsum(float(x) for x in values)
    except OverflowError:
        return UNKNOWN_VALUE
    return total if total - total == 0.0 else UNKNOWN_VALUE


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
