"""Quantified formulas over the ontology: ``forall c in Camera: always[0, 1s] Fresh(c)``.

``forall VAR in CLASS: F`` and ``exists VAR in CLASS: F`` range over the individuals of the
ontology class ``CLASS`` (as a spec's ``<arg class="...">`` does for templates): the variable
stands in terms' args (``Fresh(c)`` becomes ``Fresh(top)``, ``Fresh(bottom)``, ...) and, used as
a value, is the individual's name (``Fresh(c).camera == c``). ``CLASS`` is a class reference as
specs write it (``Camera``, ``dk:Camera``, ``<http://...#Camera>``).

:func:`expand` turns a formula into the monitors a manager runs:

- the ``forall`` s a formula *starts with* make one monitor per individual (per tuple of
  individuals for ``forall a in Robot: forall b in Robot: ...``), each keyed by its individuals:
  a verdict per robot (per pair);
- every other ``forall`` or ``exists`` (inside an operator, under ``not``, an ``exists`` first) is
  the ``and`` or ``or`` of its body over the individuals, within one monitor:
  ``always[0, 1s] (forall c in Camera: Fresh(c))``;
- a ``foreach`` stays: its monitor makes one instance per object at run time
  (:class:`~dyknow.reasoning.objects.ObjectMonitor`).

An empty class is an error, not an empty monitor. The cost is bounded before anything is
substituted: the body is checked as any formula is (:func:`~dyknow.reasoning.check_formula`),
the monitors are at most ``max_expansions``, and every monitor's nodes after expansion, summed,
at most ``Limits.max_quantified_nodes`` (20,000: 100 cameras under a 200-node body, not 2,000
individuals under a 300-node one, which cost a manager 134 s of CPU), counted from the class
sizes before anything is built.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from dyknow.errors import DyKnowError, FormulaError
from dyknow.reasoning.semantics import expand_quantifiers
from dyknow.reasoning.syntax import Const, Formula, Node, Num, Quantifier, Str, Stream, Var, check_formula, children, walk
from dyknow.security import Limits

__all__ = ["expand"]


def expand(
    text: str | Formula, individuals: Callable[[str], Sequence[str]] | None, *, max_expansions: int, limits: Limits | None = None
) -> list[tuple[str | None, Formula]]:
    """``[(key, formula), ...]``: one per tuple of individuals of the ``forall`` s the formula
    starts with (``key`` their names joined by ``/``), else ``[(None, formula)]``; inner
    quantifiers expanded. :class:`~dyknow.errors.FormulaError` when it does not parse or is over
    ``limits`` (the defaults when None), a class is unknown or empty, or the expansion is over
    ``max_expansions`` monitors or ``limits.max_quantified_nodes`` nodes; all before anything is
    substituted."""
    limits = limits if limits is not None else Limits()
    if not isinstance(text, str | Formula):
        raise FormulaError(f"a formula is text, got {type(text).__name__}", where="formula", expected="a str such as 'once[0, 1s] p'")
    formula = check_formula(text, limits)
    if not any(isinstance(node, Quantifier) and node.kind != "foreach" for node in walk(formula.root)):
        return [(None, formula)]
    if individuals is None:
        cls = next(n.domain for n in walk(formula.root) if isinstance(n, Quantifier) and n.kind != "foreach")
        raise FormulaError(f"forall over {cls!r}, but the manager has no ontology", where="formula", expected="a manager started with --ontology FILE")
    members = _members(individuals)
    # the forall prefix: one monitor per tuple
    prefix: list[Quantifier] = []
    node = formula.root
    while isinstance(node, Quantifier) and node.kind == "forall":
        prefix.append(node)
        node = node.body
    tuples: list[list[str]] = [[]]
    for quantifier in prefix:
        assert isinstance(quantifier.domain, str)
        values = members(quantifier.domain)
        if len(tuples) * len(values) > max_expansions:
            raise FormulaError(
                f"forall over {quantifier.domain!r} expands to {len(tuples) * len(values):,} monitors",
                where="formula",
                expected=f"at most {max_expansions:,} (--max-expansions)",
            )
        tuples = [[*t, v] for t in tuples for v in values]
    per = _expanded_size(node, members)
    size = per * len(tuples)
    if size > limits.max_quantified_nodes:
        what = f"forall over {prefix[0].domain!r}" if len(prefix) == 1 else "the quantifiers"
        raise FormulaError(
            f"{what} expands to {len(tuples):,} formulas of {per:,} nodes each: {size:,} nodes",
            where="formula",
            expected=f"at most {limits.max_quantified_nodes:,} nodes in all (Limits.max_quantified_nodes): a smaller class or body",
        )
    out: list[tuple[str | None, Formula]] = []
    body = Formula.of(node)
    for values in tuples:
        bindings = {quantifier.var: value for quantifier, value in zip(prefix, values, strict=True)}
        out.append(("/".join(values) if prefix else None, expand_quantifiers(body, members, bindings)))
    return out


def _members(individuals: Callable[[str], Sequence[str]]) -> Callable[[str], list[str]]:
    cache: dict[str, list[str]] = {}

    def members(cls: str) -> list[str]:
        if cls not in cache:
            try:
                found = list(dict.fromkeys(v.strip() for v in individuals(cls) if isinstance(v, str) and v.strip()))
            except DyKnowError as exc:  # the ontology's own error (an unknown class, with close matches): say it as the formula's
                raise FormulaError(f"forall over {cls!r}: {exc.what}", where="formula", expected=exc.expected) from exc
            if not found:
                raise FormulaError(f"the class {cls!r} has no individuals", where="formula", expected="a class with at least one individual")
            cache[cls] = found
        return cache[cls]

    return members


def _expanded_size(root: Node, members: Callable[[str], list[str]]) -> int:
    """How many nodes ``root`` has once its quantifiers are expanded (counted, not built)."""
    memo: dict[int, int] = {}
    for node in reversed(walk(root)):
        below = sum(memo[id(kid)] for kid in children(node))
        if isinstance(node, Quantifier) and node.kind != "foreach":
            assert isinstance(node.domain, str)
            n = len(members(node.domain))
            memo[id(node)] = below * n + max(0, n - 1)  # the bodies, and the and/or joining them
        else:
            memo[id(node)] = below + (0 if isinstance(node, Num | Str | Const | Stream | Var) else 1)
    return memo[id(root)]
