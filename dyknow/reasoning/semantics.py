"""The semantics of temporal formulas, exactly, and :func:`evaluate`, which computes it offline.

This module is the one home of what a formula means; the incremental monitor
(:mod:`dyknow.reasoning.progression`) computes the same verdicts and is tested against
:func:`evaluate`, which is tested against a naive evaluator written from this text. The code
that computes it is in parts: the values and atoms at one state in :mod:`dyknow.reasoning.values`
(the monitor calls the same functions; re-exported here), every node over a trace in
:mod:`dyknow.reasoning.evaluator`, the expansion of ``forall`` and ``exists`` in
:mod:`dyknow.reasoning.quantify`; the states, the freshness of terms and the lives of ``foreach``
objects here.

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
is ``inf``). The span is not cut at the first state: a past window of the first states that reaches
back before it reaches the outages there too (a term silent from 1 s to 5 s, with a maximum age of
1 s, makes ``historically[0, 10s] ...`` unknown at a first state at 6 s, not false), and so for
an object's life (``foreach``, below): the other terms' outages before its first sample count.
A monitor that is told of a gap (its term re-planned) marks each verdict whose window reaches
into it.

**The warm-up.** There is no state before the first one: a past window whose span reaches back
before it holds the states from the first on, and one whose span ends before it holds none. So a
past operator's first verdicts are decided over less than its window (``historically[0, 10s] φ``
at 2 s into the trace is φ over those 2 s, ``once[1s, 2s] φ`` at 0.5 s is over no state: false),
and an empty window is what it is anywhere (``once`` false, ``historically`` true, an aggregate
over no sample as the aggregates say). A monitor decides the same, as reelay does (below). The
end is not so: a future window that reaches past the last state is unknown unless the states
there are decide it (``eventually[0, 2s] φ`` true once a state in it holds φ), for states may
still come.

**Time units.** :func:`evaluate` takes and gives float seconds (as ``time.time``); the functions
whose names end in ``_ns`` (:func:`evaluate_ns`, :func:`evaluate_values_ns`,
:func:`evaluate_objects_ns`) integer nanoseconds (as ``time.time_ns``: a message's ``origin_ns``).

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
- ``sqrt(x)``, ``hypot(x, y)`` (``sqrt(x*x + y*y)`` without overflow in between) and ``pow(x,
  y)`` (x to the power y) compute in floating point, as Python's ``math.sqrt``, ``math.hypot``
  and ``math.pow`` on the operands as floats (``pow(2, 3)`` is ``8.0``); unknown when an operand
  is unknown or not a number, and when the result is not a finite real number: ``sqrt`` of a
  negative number, ``pow(0, -1)``, ``pow(-8, 1/3)``, an overflow.
- ``dist(p, q)`` is the Euclidean distance of two points, computed as ``math.hypot`` of their
  coordinates' differences: each point an object with the numbers ``x`` and ``y``, and ``z`` on
  both or on neither (other members are ignored: ``dist(Pose(a).position, Pose(b).position)``),
  or both arrays of numbers of one length (at least one); unknown otherwise, and when it is not
  finite. Its operands are read as they are (objects and arrays), so they are streams, down their
  field paths, or lookups.
- **Lookups.** ``S[k]`` (``Limits(floor)[State(r).zone]``) is a value of stream ``S``'s payload
  (down its field path) by a key ``k`` computed at the state: an object's member by a string, or
  by a number's canonical text (``3`` and ``3.0`` find the member ``"3"``: JSON's keys are
  strings); an array's element by a number whose value is a whole number from 0 (``2`` and
  ``2.0`` alike). Keys chain, each a level down (``S[k1][k2]``), and a field written after a key
  is the key of its name (``Limits(floor)[State(r).zone].speed`` is ``...["speed"]``). The value
  found is read as above (a number, a string or a boolean; an object is unknown, except as an
  operand of ``dist`` or of the next key). Unknown when the key is unknown or of another kind
  (a boolean), when the member is missing or the index out of range, and while ``S`` is stale.
- **Parameterized terms.** ``F(e)`` (``SpeedLimit(State(r).zone)``, other args names) is the
  lookup ``F(*)[e]``: its *family* ``F(*)`` is one stream, with a sample at each sample of each
  of its *members* (the streams ``F(a)``, ``a`` any name, the other args as written), whose value
  then is an object of each member's latest value by its argument (``{"z1": 1.5, "z2": 0.5}``);
  ``e`` at the state is the key, so a string names the member (a number, by its canonical text,
  finds none: no tag's arg is a number) and a field after the term is a key after it
  (``F(e).value`` is ``F(*)[e]["value"]``). The family is a mentioned stream: the states start
  once some member has a sample, and its freshness is the family's (stale while no member has a
  sample within ``max_age``: a member silent while others speak holds its value). Unknown when
  ``e`` is unknown or no string, and when the member named has no sample yet. Live, a monitor
  plans a member the first time its argument is seen, so the member's samples count from then
  on; a recording of the members' keys gives the same verdicts offline
  (:mod:`dyknow.reasoning.families`).
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
element, all at its time). Two values are one object when JSON says they are one value: the same
type (string or number) and value, a number however written (``1``, ``1.0`` and ``1e0`` are one
object; the string ``"1"`` another); past 2**53 an integer and a float are told apart. Verdicts
name an object by its key (:func:`~dyknow.reasoning.values.object_key`: the string, or the
number's canonical text; a string that reads as such a text, or starts with ``"``, as its JSON
text). An
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

from bisect import bisect_left
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from dyknow.errors import FormulaError, TagError, did_you_mean
from dyknow.reasoning.evaluator import Evaluator, is_condition
from dyknow.reasoning.families import family_samples
from dyknow.reasoning.quantify import expand_quantifiers, rename
from dyknow.reasoning.syntax import Aggregate, Call, Formula, Historically, Node, Once, Quantifier, Since, Stream, parse, parse_value, walk
from dyknow.reasoning.tree import is_family
from dyknow.reasoning.values import (  # re-exported (__all__): the monitor, and older code, import them from here
    FALSE,
    TRUE,
    UNKNOWN,
    UNKNOWN_VALUE,
    arith,
    as_value,
    call,
    compare,
    margin,
    object_key,
    read,
    truth,
    verdict_of,
)
from dyknow.tags import Term, parse_term

__all__ = [
    "FALSE",
    "TRUE",
    "UNKNOWN",
    "UNKNOWN_VALUE",
    "arith",
    "as_value",
    "call",
    "compare",
    "evaluate",
    "evaluate_ns",
    "evaluate_objects_ns",
    "evaluate_values_ns",
    "expand_quantifiers",
    "margin",
    "object_key",
    "read",
    "synchronize",
    "truth",
    "verdict_of",
]


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
    goes to :func:`evaluate_objects_ns`. Raises :class:`~dyknow.errors.FormulaError` for a malformed
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
    ages = {_named(k): round(v * 1_000_000_000) for k, v in (max_age or {}).items()}
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
    """:func:`evaluate` with integer-nanosecond times (``msg.origin_ns``) in and out (``max_age_ns`` too):
    every state's ``(t_ns, verdict)``, or ``(t_ns, verdict, robustness)`` with ``robustness``."""
    parsed = expand_quantifiers(parse(formula) if isinstance(formula, str) else formula, individuals)
    _no_foreach(parsed)
    ages = {_named(k): int(v) for k, v in (max_age_ns or {}).items()}
    return _evaluate_ns(parsed, [list(samples) for samples in _choose(parsed, streams)], [str(term) for term in parsed.terms], ages, robustness)


def evaluate_values_ns(expression: str | Formula, streams: Mapping[str, Sequence[tuple[int, Any]]]) -> list[tuple[int, Any]]:
    """Every state's ``(t_ns, value)`` of an expression (:func:`~dyknow.reasoning.syntax.parse_value`:
    ``avg[0, 1s] Speed(robot)``, ``Pose(robot).x - Goal(robot).x``); unknown values are None, a
    condition's values its verdicts (True, False, None). Times in integer nanoseconds."""
    parsed = parse_value(expression) if isinstance(expression, str) else expression
    chosen = _choose(parsed, streams)
    times, values, latest = _synchronize([list(samples) for samples in chosen])
    index = {term: k for k, term in enumerate(parsed.terms)}
    evaluator = Evaluator(times, values, latest, index, [-1] * len(parsed.terms), {}, False)
    column, _ = evaluator.node(parsed.root)
    if is_condition(parsed.root):
        return [(t, verdict_of(v)) for t, v in zip(times, column, strict=True)]
    return [(t, None if v is UNKNOWN_VALUE else v) for t, v in zip(times, column, strict=True)]


def evaluate_objects_ns(
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
        raise FormulaError("evaluate_objects_ns takes a foreach formula", where="formula", expected="foreach x in Stream.field: ...")
    domain = root.domain
    assert isinstance(domain, Stream)
    inner = Formula.of(rename(root.body, root.var, _OBJECT))
    # the object's samples are states, and every other term's the formula reads (as given: a
    # subformula read alone at the whole formula's states keeps the whole formula's terms)
    body = Formula(inner.text, inner.root, (domain.term, *(t for t in dict.fromkeys((*parsed.terms, *inner.terms)) if t != domain.term)))
    ages = {_named(k): int(v) for k, v in (max_age_ns or {}).items()}
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
    reach = _past_reach(body.root)
    times_of = {name: [t for t, _ in samples] for name, samples in chosen.items()}
    for key, runs in lives.items():
        for run in runs:
            start, end = run[0][0], run[-1][0] + idle_ns
            picked = []
            for term in body.terms:
                name = str(term)
                if term == domain.term:
                    picked.append(run)
                else:
                    # the latest value from before the life, and the outages a window of the life's
                    # first states reaches back into: from ``reach`` and the term's age before it
                    cutoff = start - reach - max(ages.get(name, 0), 0)
                    first = max(bisect_left(times_of[name], cutoff) - 1, 0)
                    picked.append([s for s in chosen[name][first:] if s[0] <= end])
            value = _object_value(run[0][1], domain.fields)
            rows = _evaluate_ns(body, picked, [str(t) for t in body.terms], ages, robustness, {_OBJECT: value}, start)
            out.setdefault(key, []).append(rows)
    return out


def _named(term: str) -> str:
    """A term as the formula writes it (``dk:Battery( r )`` is ``Battery(r)``); a family
    (``SpeedLimit(*)``), which no tag reads, as given."""
    try:
        return str(parse_term(term))
    except TagError:
        return term.replace(" ", "")


_OBJECT = "\x00object"  # the foreach variable, once its body is read alone


def _past_reach(root: Node) -> int:
    """How far before a state its past windows reach: the largest finite upper bound of a past
    operator or an aggregate (a window without a bound starts at the first state)."""
    bounds = [n.interval.hi_ns for n in walk(root) if isinstance(n, Historically | Once | Since | Aggregate) and n.interval.hi_ns is not None]
    return max(bounds, default=0)


def _object_value(payload: Any, fields: tuple[str, ...]) -> Any:
    return read(payload, fields)


def _no_foreach(formula: Formula) -> None:
    if isinstance(formula.root, Quantifier) and formula.root.kind == "foreach":
        raise FormulaError("a foreach formula has verdicts per object", where="formula", expected="evaluate_objects_ns(...)")


def _choose(formula: Formula, streams: Mapping[str, Sequence[tuple[Any, Any]]]) -> list[Sequence[tuple[Any, Any]]]:
    by_term: dict[Term, Sequence[tuple[Any, Any]]] = {}
    for key, samples in streams.items():
        try:
            by_term[parse_term(key)] = samples
        except TagError:
            continue  # not a term: cannot be one the formula mentions
    chosen: list[Sequence[tuple[Any, Any]]] = []
    for term in formula.terms:
        if is_family(term):  # a parameterized term's: its members' samples, as one stream
            given_family = streams.get(str(term))
            chosen.append(given_family if given_family is not None else family_samples(term, streams))
            continue
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
    evaluator = Evaluator(times, values, latest, index, max_age, dict(variables or {}), wants)
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
