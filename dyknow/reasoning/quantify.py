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

:func:`expand_quantifiers` is the rewriting alone (what ``forall`` and ``exists`` mean, as
:mod:`dyknow.reasoning.semantics` states it): :func:`~dyknow.reasoning.evaluate` applies it to a
whole formula, :func:`expand` to each monitor's body.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

from dyknow.errors import DyKnowError, FormulaError
from dyknow.reasoning.syntax import (
    Aggregate,
    Always,
    And,
    Arith,
    Atom,
    Call,
    Const,
    Eventually,
    Formula,
    Historically,
    Implies,
    Index,
    Node,
    Num,
    Once,
    Or,
    Quantifier,
    Since,
    Str,
    Stream,
    Until,
    Var,
    check_formula,
    children,
    walk,
)
from dyknow.reasoning.tree import family_term, is_family
from dyknow.security import Limits
from dyknow.tags import Term

__all__ = ["expand", "expand_quantifiers", "rename", "replace_var"]


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
            names = tuple(env.get(a, a) for a in node.term.args)
            term = family_term(node.term.functor, names) if is_family(node.term) else Term(node.term.functor, names)
            return Stream(term, node.fields)
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
    if isinstance(node, Index):
        assert isinstance(args[0], Stream)  # (a stream rebuilt is a stream)
        return Index(args[0], tuple(args[1:]), node.param)
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


def replace_var(root: Node, var: str, node: Node) -> Node:
    """``root`` with the variable ``var``, where it is a value, replaced by ``node`` (a
    ``foreach`` variable by its stream's field, to compute it from the object's samples)."""
    memo: dict[int, Node] = {}
    for here in reversed(walk(root)):
        args = [memo[id(kid)] for kid in children(here)]
        if isinstance(here, Var) and here.name == var:
            memo[id(here)] = node
        else:
            memo[id(here)] = _rebuild(here, args, {}) if args else here
    return memo[id(root)]


def rename(root: Node, var: str, name: str) -> Node:
    """``root`` with the variable ``var`` renamed ``name`` where it is a value (``foreach``'s body
    read alone, its variable the object's placeholder)."""
    memo: dict[int, Node] = {}
    for node in reversed(walk(root)):
        args = [memo[id(kid)] for kid in children(node)]
        if isinstance(node, Var) and node.name == var:
            memo[id(node)] = Var(name)
        else:
            memo[id(node)] = _rebuild(node, args, {}) if args else node
    return memo[id(root)]
