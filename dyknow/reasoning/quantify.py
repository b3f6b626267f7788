"""Quantified formulas over the ontology: ``forall c in Camera: always[0, 1s] (Fresh(c) == true)``.

A formula may start with ``forall VAR in CLASS:``. It stands for one formula per individual of the
ontology class ``CLASS`` (as a spec's ``<arg class="...">`` does for templates), with ``VAR``
replaced by the individual wherever it is an argument of a term: ``Fresh(c)`` becomes
``Fresh(top)``, ``Fresh(bottom)``, ... Only term arguments are substituted; ``VAR`` is a name
(letters, digits, ``_``), ``CLASS`` a class reference as specs write it (``Camera``,
``dk:Camera``, ``<http://...#Camera>``). The expansions are bounded like a template's
(``max_expansions``), and an empty class is an error, not an empty monitor.

Its cost is bounded before anything is substituted: the body is checked as any formula is
(:func:`~dyknow.reasoning.check_formula`), and the individuals times the body's nodes may be at
most ``Limits.max_quantified_nodes`` (20,000: 100 cameras under a 200-node body, not 2,000
individuals under a 300-node one, which cost a manager 134 s of CPU).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence

from dyknow.errors import DyKnowError, FormulaError
from dyknow.reasoning.syntax import Formula, check_formula, parse
from dyknow.security import Limits
from dyknow.tags import Term

__all__ = ["expand", "split_quantifier"]

_QUANTIFIER = re.compile(r"\s*forall\s+([A-Za-z_][A-Za-z0-9_]*)\s+in\s+(<[^>\s]+>|[A-Za-z_][\w.-]*(?::[\w.-]+)?)\s*:(.*)\Z", re.DOTALL)


def split_quantifier(text: str) -> tuple[str, str, str] | None:
    """``(var, class, body)`` of a quantified formula, or None for a plain one."""
    if not text.lstrip().startswith("forall"):
        return None
    found = _QUANTIFIER.match(text)
    if found is None:
        raise FormulaError(
            f"a quantifier that does not read: {text[:80]!r}",
            where="formula column 1",
            expected="forall VAR in CLASS: FORMULA, such as forall c in Camera: Fresh(c) == true",
        )
    var, cls, body = found.group(1), found.group(2), found.group(3)
    if not body.strip():
        raise FormulaError("nothing after the quantifier's ':'", where="formula", expected="a formula over the variable")
    return var, cls, body


def _substitute(formula: Formula, var: str, value: str) -> Formula:
    text = str(formula)
    for term in formula.terms:
        if var in term.args:
            replaced = Term(term.functor, tuple(value if a == var else a for a in term.args))
            text = re.sub(r"(?<![\w:.>`])" + re.escape(str(term)) + r"(?![\w])", str(replaced), text)
    return parse(text)


def expand(
    text: str, individuals: Callable[[str], Sequence[str]] | None, *, max_expansions: int, limits: Limits | None = None
) -> list[tuple[str | None, Formula]]:
    """``[(individual, formula), ...]``: one per individual for a quantified formula, else
    ``[(None, formula)]``. :class:`~dyknow.errors.FormulaError` when it does not parse or is
    over ``limits`` (:func:`~dyknow.reasoning.check_formula`; the defaults when None), the
    variable is no term's argument, the class is unknown or empty, it has more individuals than
    ``max_expansions``, or individuals times the body's nodes exceed ``limits.max_quantified_nodes``;
    all before anything is substituted."""
    limits = limits if limits is not None else Limits()
    if not isinstance(text, str):
        raise FormulaError(f"a formula is text, got {type(text).__name__}", where="formula", expected="a str such as 'once[0, 1s] p'")
    split = split_quantifier(text)
    if split is None:
        return [(None, check_formula(text, limits))]
    var, cls, body = split
    try:
        formula = check_formula(body, limits)
    except FormulaError as exc:  # located in the body: say where in the whole text
        if exc.column is None:
            raise
        column = exc.column + len(text) - len(body)
        raise FormulaError(exc.what, where=f"formula column {column}", expected=exc.expected, formula=text, column=column) from None
    if not any(var in term.args for term in formula.terms):
        raise FormulaError(
            f"the variable {var!r} is no term's argument in {str(formula)!r}",
            where="formula",
            expected=f"a term such as Fresh({var}) that it stands in",
        )
    if individuals is None:
        raise FormulaError(f"forall over {cls!r}, but the manager has no ontology", where="formula", expected="a manager started with --ontology FILE")
    try:
        values = list(dict.fromkeys(v.strip() for v in individuals(cls) if isinstance(v, str) and v.strip()))
    except DyKnowError as exc:  # the ontology's own error (an unknown class, with close matches): say it as the formula's
        raise FormulaError(f"forall over {cls!r}: {exc.what}", where="formula", expected=exc.expected) from exc
    if not values:
        raise FormulaError(f"the class {cls!r} has no individuals", where="formula", expected="a class with at least one individual")
    if len(values) > max_expansions:
        raise FormulaError(
            f"forall over {cls!r} expands to {len(values):,} monitors", where="formula", expected=f"at most {max_expansions:,} (--max-expansions)"
        )
    size = formula.nodes
    if len(values) * size > limits.max_quantified_nodes:
        raise FormulaError(
            f"forall over {cls!r} expands to {len(values):,} formulas of {size:,} nodes each: {len(values) * size:,} nodes",
            where="formula",
            expected=f"at most {limits.max_quantified_nodes:,} nodes in all (Limits.max_quantified_nodes): a smaller class or body",
        )
    return [(value, _substitute(formula, var, value)) for value in values]
