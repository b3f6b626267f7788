"""Parameterized terms' families: a stream per value of an argument, read as one stream.

A parameterized term, ``SpeedLimit(State(r).zone)``, names at each state the stream
``SpeedLimit(z)`` of the zone ``z`` the robot is in then. Its *family* ``SpeedLimit(*)``
(:func:`~dyknow.reasoning.tree.family_term`) is one stream whose value is a JSON object of each
*member*'s latest value by its argument (``{"z1": 1.5, "z2": 0.5}``), with a sample at each
member's sample: the term is a lookup into it (:mod:`dyknow.reasoning.semantics` states it).
:func:`family_samples` makes a family's samples from its members' (over a recording, and
:func:`~dyknow.reasoning.semantics.evaluate` given the members' streams); a live monitor
assembles them as its members' samples come (:class:`Family`), planning a member the first time
its argument is seen (:mod:`dyknow.reasoning.monitors`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any

from dyknow.errors import FormulaError, TagError
from dyknow.reasoning.syntax import Formula
from dyknow.reasoning.tree import is_family, member_arg
from dyknow.tags import Term, parse_term

__all__ = ["MAX_MEMBERS", "Family", "Members", "family_samples", "members", "refuse_families"]

MAX_MEMBERS: int = 256
"""The most members a live monitor plans for one family (the values its argument takes): past
that, a new value's member is not planned (warned about once) and the term is unknown there."""

_HISTORY = 8  # each member's latest samples a live family keeps, for a sample that comes out of time order


def members(family: Term, names: Sequence[str]) -> dict[str, str]:
    """Of the terms written in ``names``, those that are members of ``family``: name -> argument."""
    found: dict[str, str] = {}
    for name in names:
        try:
            term = parse_term(name)
        except TagError:
            continue
        arg = member_arg(family, term)
        if arg is not None:
            found[name] = arg
    return found


def family_samples(family: Term, streams: Mapping[str, Sequence[tuple[Any, Any]]]) -> list[tuple[Any, dict[str, Any]]]:
    """The samples of ``family`` made from those of its members in ``streams`` (term -> samples
    ``(t, value)`` in time order): one at each member's sample, its value every member's latest
    value by argument then (a member's several samples at one time: the later one)."""
    assert is_family(family)
    merged = sorted(
        ((t, k, arg, value) for k, (name, arg) in enumerate(members(family, list(streams)).items()) for t, value in streams[name]),
        key=lambda row: (row[0], row[1]),
    )
    held: dict[str, Any] = {}
    out: list[tuple[Any, dict[str, Any]]] = []
    for t, _k, arg, value in merged:
        held[arg] = value
        out.append((t, dict(held)))
    return out


class Family:
    """A live family's value, assembled from its members' samples as they come: :meth:`push`
    gives the family's sample for a member's. A member's sample is put in time order among that
    member's latest few, and the value at its time takes each other member's latest sample at or
    before it, so a sample that comes behind another member's later one gives the value that
    held at its time; the family's samples already handed on are not changed."""

    def __init__(self, family: Term) -> None:
        self.family = family
        self._members: dict[str, deque[tuple[int, Any]]] = {}

    def __len__(self) -> int:
        return len(self._members)

    def push(self, arg: str, t_ns: int, value: Any) -> dict[str, Any]:
        """The family's value at ``t_ns``, with member ``arg``'s sample ``value`` then."""
        own = self._members.get(arg)
        if own is None:
            own = self._members[arg] = deque(maxlen=_HISTORY)
        if not own or own[-1][0] <= t_ns:
            own.append((t_ns, value))
        else:  # behind its own latest: in its place (the oldest goes when full)
            ordered = sorted([*own, (t_ns, value)], key=lambda row: row[0])
            own.clear()
            own.extend(ordered[-_HISTORY:])
        out: dict[str, Any] = {}
        for name, rows in self._members.items():
            if name == arg:
                out[name] = value
                continue
            for t, held in reversed(rows):
                if t <= t_ns:
                    out[name] = held
                    break
        return out


class Members:
    """The families among a formula's ``terms`` (its :attr:`~dyknow.reasoning.syntax.Formula.terms`),
    and each one's value: what lets a monitor be pushed a member's sample by its name
    (``monitor.push("SpeedLimit(z1)", t, 1.5)``)."""

    def __init__(self, terms: Sequence[Term]) -> None:
        self._families = {k: Family(term) for k, term in enumerate(terms) if is_family(term)}
        self._found: dict[str, tuple[int, str] | None] = {}

    def find(self, name: str) -> tuple[int, str] | None:
        """The position of the family ``name`` is a member of, and its argument; None when none."""
        if name in self._found:
            return self._found[name]
        found = None
        try:
            term = parse_term(name)
        except TagError:
            term = None
        if term is not None:
            for k, family in self._families.items():
                arg = member_arg(family.family, term)
                if arg is not None:
                    found = (k, arg)
                    break
        if len(self._found) < 4 * MAX_MEMBERS:
            self._found[name] = found
        return found

    def value(self, k: int, arg: str, t_ns: int, value: Any) -> dict[str, Any]:
        """The value of the family at position ``k`` at ``t_ns``, with member ``arg``'s sample ``value`` then."""
        return self._families[k].push(arg, t_ns, value)


def refuse_families(formula: Formula, what: str) -> None:
    """Refuse ``formula`` when it has a parameterized term: ``what`` (a request's or a spec's
    requirement) reads fixed terms in this version; a monitor plans members
    (:mod:`dyknow.reasoning.members`)."""
    found = next((term for term in formula.terms if is_family(term)), None)
    if found is not None:
        raise FormulaError(
            f"{what} has the parameterized term {found} (its argument computed at each state)",
            where=f"formula {formula.text[:200]!r}",
            expected="a requirement over fixed terms (Limits(floor)[State(r).zone] looks a limit up in one stream); "
            "a monitor (dyknow monitor, Manager.monitor) plans a member per value",
        )
