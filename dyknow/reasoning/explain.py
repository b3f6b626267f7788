"""Why a verdict is what it is: each comparison of a formula with its sides' values at a state.

:func:`explainer` is shared by the offline check (``dyknow check``, ``dyknow monitor --mcap
--changes-only``: every sample of the recording at hand) and the monitor unit (the latest few
samples of each term, at each change of a verdict): ``State(r2).speed <= Limits(floor)[State(r2).zone]:
0.9 <= 0.5``.
"""

from __future__ import annotations

import bisect
import json
from collections.abc import Callable, Mapping, Sequence

from dyknow.errors import DyKnowError
from dyknow.reasoning.semantics import evaluate_ns, evaluate_objects_ns, evaluate_values_ns
from dyknow.reasoning.syntax import (
    Always,
    And,
    Atom,
    Const,
    Eventually,
    Fall,
    Formula,
    Historically,
    Implies,
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
    walk,
)
from dyknow.reasoning.values import object_key, read

__all__ = ["MAX_ATOMS", "explainer", "object_explainer", "object_robustness_explainer", "robustness_explainer"]

#: Atoms shown per explanation.
MAX_ATOMS = 8


def explainer(
    formula: Formula,
    samples: Mapping[str, Sequence[tuple[int, object]]],
    *,
    current_only: bool = False,
    bound: Mapping[str, object] | None = None,
) -> Callable[[int], list[str]]:
    """``at(t_ns)``: each atom of ``formula`` (the first :data:`MAX_ATOMS`), as written and with
    its sides' values at ``t_ns`` (a side's latest value then; ``unknown`` when it has none):
    ``State(r2).speed <= Limits(floor)[State(r2).zone]: 0.9 <= 0.5``. ``current_only``: the
    samples are only the latest few (a live monitor's), so a side that reads a window (an
    aggregate, a past operator) is shown as ``?`` rather than computed from part of it.
    ``bound``: the values of variables (a ``foreach`` body's, for one object)."""
    atoms: list[tuple[str, list[Sequence[tuple[int, object]] | str], str]] = []
    for node in walk(formula.root):
        if not isinstance(node, Atom) or len(atoms) >= MAX_ATOMS:
            continue
        sides: list[Sequence[tuple[int, object]] | str] = []
        for side in (node.left, node.right) if node.op is not None else (node.left,):
            assert side is not None
            if isinstance(side, Num | Str | Const):
                sides.append(str(side))
                continue
            if isinstance(side, Var):
                sides.append(_value_at([(0, bound[side.name])], 0) if bound is not None and side.name in bound else "?")
                continue
            alone = Formula.of(side)
            if current_only and (alone.reach_ns != 0 or alone.horizon_ns):
                sides.append("?")
                continue
            try:
                series = evaluate_values_ns(alone, {str(t): samples[str(t)] for t in alone.terms})
            except (DyKnowError, KeyError):  # (a foreach's variable, say: not a value alone)
                sides.append("?")
                continue
            sides.append(series)
        atoms.append((str(node), sides, node.op or ""))

    def at(t_ns: int) -> list[str]:
        out = []
        for text, sides, op in atoms:
            shown = [side if isinstance(side, str) else _value_at(side, t_ns) for side in sides]
            out.append(f"{text}: {f' {op} '.join(shown)}")
        return out

    return at


#: The condition nodes whose robustness :func:`robustness_explainer` says: atoms, connectives,
#: temporal operators (values and quantifiers are not conditions of their own).
_CONDITIONS = (Atom, Not, And, Or, Implies, Always, Eventually, Historically, Once, Until, Since, Rise, Fall)


def robustness_explainer(
    formula: Formula, samples: Mapping[str, Sequence[tuple[int, object]]], *, kept: bool = False
) -> Callable[[int], list[str]]:
    """``at(t_ns)``: the robustness of each subformula of ``formula`` that is a condition (the
    first :data:`MAX_ATOMS`, the whole formula first), at the state ``t_ns``, as
    :func:`~dyknow.reasoning.semantics.evaluate_ns` gives it for that subformula alone over the
    same samples (the quantitative semantics: how far from flipping; ``unknown`` when it has none):
    ``historically[0, 300ms] Seen(floor).speed < 1.5: -0.2``.

    ``kept``: the samples are the latest a live monitor kept, not a whole trace: a subformula
    whose windows at ``t_ns`` reach back before the first state they make (its past reach, and
    a state before for ``prev``), or ahead past the newest sample (its horizon), is ``?``: what it
    reads is not all kept. The others are what the whole trace gives them (without the terms'
    freshness)."""

    def series(node: Node) -> list[tuple[int, object]]:
        own = Formula.of(node)
        alone = Formula(own.text, own.root, formula.terms)  # at the whole formula's states: every term's samples make them
        return [(row[0], row[2]) for row in evaluate_ns(alone, {str(t): samples[str(t)] for t in alone.terms}, robustness=True)]

    return _robustness_rows(formula.root, [samples.get(str(t), ()) for t in formula.terms], series, kept)


def object_robustness_explainer(
    formula: Formula, samples: Mapping[str, Sequence[tuple[int, object]]], *, idle_ns: int, kept: bool = False
) -> Callable[[str, int], list[str]]:
    """``at(object, t_ns)``: as :func:`robustness_explainer`, for one object of a ``foreach``
    formula: each condition subformula of its body (the body first), as
    :func:`~dyknow.reasoning.semantics.evaluate_objects_ns` gives ``foreach x in S: sub`` (at the
    whole formula's states, lives ending ``idle_ns`` after an object's last sample) to the object
    over the same samples. ``kept``: as there, the windows measured from the object's own kept
    samples of the domain's term and the other terms' kept samples."""
    root = _foreach(formula)
    domain = root.domain
    assert isinstance(domain, Stream)
    own, _ = _objects(samples, domain)
    made: dict[str, Callable[[int], list[str]]] = {}

    def at(obj: str, t_ns: int) -> list[str]:
        if obj not in made:
            mine = {**samples, str(domain.term): own.get(obj, [])}

            def series(node: Node) -> list[tuple[int, object]]:
                alone = Formula(str(node), Quantifier("foreach", root.var, domain, node), formula.terms)
                lives = evaluate_objects_ns(alone, mine, idle_ns=idle_ns, robustness=True).get(obj, [])
                return [(row[0], row[2]) for life in lives for row in life]

            made[obj] = _robustness_rows(root.body, [mine.get(str(t), ()) for t in formula.terms], series, kept)
        return made[obj](t_ns)

    return at


def _robustness_rows(
    root: Node, given: Sequence[Sequence[tuple[int, object]]], series_of: Callable[[Node], list[tuple[int, object]]], kept: bool
) -> Callable[[int], list[str]]:
    """``at(t_ns)`` of the robustness explainers: each condition under ``root`` (the first
    :data:`MAX_ATOMS`) with ``series_of(node)``, its robustness at each state; ``given``: each
    term's samples (with ``kept``, the windows they cover)."""
    rows: list[tuple[str, list[tuple[int, object]] | str, int | None, int]] = []
    for node in walk(root):
        if not isinstance(node, _CONDITIONS) or len(rows) >= MAX_ATOMS:
            continue
        try:
            series: list[tuple[int, object]] | str = series_of(node)
        except (DyKnowError, KeyError):  # (a foreach's variable, say: not a condition alone)
            series = "?"
        own = Formula.of(node)
        reach = own.reach_ns
        if reach is not None and any(isinstance(n, Prev | Rise | Fall) for n in walk(node)):
            reach += 1  # (a state before the first it reads)
        rows.append((str(node), series, reach, own.horizon_ns))
    first = max((r[0][0] for r in given), default=None) if all(given) else None  # the first state the kept samples make
    newest = max((r[-1][0] for r in given if r), default=None)

    def covered(reach: int | None, horizon: int, t_ns: int) -> bool:
        if not kept:
            return True
        return first is not None and newest is not None and reach is not None and first <= t_ns - reach and newest >= t_ns + horizon

    def at(t_ns: int) -> list[str]:
        return [
            f"{text}: {'?' if isinstance(series, str) or not covered(reach, horizon, t_ns) else _value_at(series, t_ns, exact=True)}"
            for text, series, reach, horizon in rows
        ]

    return at


def object_explainer(
    formula: Formula, samples: Mapping[str, Sequence[tuple[int, object]]], *, current_only: bool = False
) -> Callable[[str, int], list[str]]:
    """``at(object, t_ns)``: as :func:`explainer` (``current_only`` too), for one object of a
    ``foreach`` formula: its body's atoms over the object's own samples of the domain's term (as
    its monitor reads them), the variable bound to the object's value."""
    root = _foreach(formula)
    domain = root.domain
    assert isinstance(domain, Stream)
    body = Formula.of(root.body)
    own, values = _objects(samples, domain)
    made: dict[str, Callable[[int], list[str]]] = {}

    def at(obj: str, t_ns: int) -> list[str]:
        if obj not in made:
            made[obj] = explainer(body, {**samples, str(domain.term): own.get(obj, [])}, current_only=current_only, bound={root.var: values.get(obj)})
        return made[obj](t_ns)

    return at


def _foreach(formula: Formula) -> Quantifier:
    root = formula.root
    if not isinstance(root, Quantifier) or root.kind != "foreach" or not isinstance(root.domain, Stream):
        raise DyKnowError("an object's explanation takes a foreach formula", where="formula", expected="foreach x in Stream.field: ...")
    return root


def _objects(samples: Mapping[str, Sequence[tuple[int, object]]], domain: Stream) -> tuple[dict[str, list[tuple[int, object]]], dict[str, object]]:
    """Each object's own samples of the domain's term (a frame's elements apart), and its value."""
    own: dict[str, list[tuple[int, object]]] = {}
    values: dict[str, object] = {}
    for t, sample in samples.get(str(domain.term), ()):
        for payload in sample if type(sample) is list else [sample]:
            value = read(payload, domain.fields)
            key = object_key(value)
            if key is not None:
                own.setdefault(key, []).append((t, payload))
                values.setdefault(key, value)
    return own, values


def _value_at(series: Sequence[tuple[int, object]], t_ns: int, *, exact: bool = False) -> str:
    """The latest value of ``series`` at ``t_ns`` (``exact``: the one at ``t_ns`` itself), as
    JSON writes it (``unknown``: none)."""
    k = bisect.bisect_right(series, t_ns, key=lambda row: row[0])
    value = series[k - 1][1] if k and (not exact or series[k - 1][0] == t_ns) else None
    if value is None:
        return "unknown"
    if isinstance(value, float):
        return f"{value:.6g}"
    try:
        text = json.dumps(value, separators=(",", ":"), ensure_ascii=False)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
