"""Monitors asked for by meaning: a formula in, the key of its verdicts out (:meth:`Manager.monitor
<dyknow.manager.Manager.monitor>`).

For every term of the formula the manager is asked for a stream of that term, exactly as
:meth:`~dyknow.manager.Manager.request` does (the same semantic matching, ontology subsumption,
priorities and constraints; a term asked for twice shares its stream). A
:class:`~dyknow.reasoning.unit.FormulaMonitor` is spawned on the manager with one input bound to
each term's request key and its ``events`` input to the manager's adaptation events, and publishes
on ``dyknow/<manager>/monitors/<n>`` (:func:`~dyknow.keys.monitor_key`). The adaptation loop keeps
each term's stream flowing on its key as it keeps any request's: when a term's producer fails,
the term is re-planned, the monitor keeps its key, and its next verdict says that a gap occurred
(:meth:`Monitors.adapted`, which the manager calls for each adaptation).

A quantified formula (``forall c in Camera: ...``, :mod:`dyknow.reasoning.quantify`) becomes one
monitor per individual (per tuple, for ``forall a in R: forall b in R: ...``), publishing on
``dyknow/<manager>/monitors/<n>/<individual>`` (``.../<a>/<b>``); the key returned is then
``dyknow/<manager>/monitors/<n>/*`` (``.../*/*``), which a subscriber takes them all by. A
``foreach`` formula is one monitor whose verdicts each name their object (``"object": ...``).
Releasing that key (:meth:`Monitors.release`) destroys the monitors and gives their terms back.

A term may be **bound** to what exists instead (``bindings``: term -> a Zenoh key, ``ros2:/TOPIC``
or ``ros2dds:/TOPIC``, :mod:`dyknow.reasoning.bindings`): it is not requested, and the monitor's
input of that term is bound to the source itself (a ROS 2 topic through a companion
:class:`~dyknow.ros2.bridge.Ros2Source` on the manager's node, which the manager's spawn wires).

A monitor has an owner (:class:`~dyknow.model.Owner`), as a request's reference has: only it
may release the monitor, or an admin who forces it; a client's monitor ends with the client
(:mod:`dyknow.holders`). ``readable(term)`` is asked of every term of every expansion before
anything is requested: a monitor may only read what its caller may read.
"""

from __future__ import annotations

import itertools
import re
import threading
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from dyknow import keys
from dyknow.errors import AccessError, DyKnowError, FormulaError, UnitError
from dyknow.model import LOCAL, Owner, UnitInfo
from dyknow.reasoning.bindings import check_bindings
from dyknow.reasoning.members import RELAY_SPEC
from dyknow.reasoning.quantify import expand
from dyknow.reasoning.tree import is_family, member_arg, member_term
from dyknow.reasoning.unit import VERDICTS_PORT, FormulaMonitor, monitor_spec, term_ports
from dyknow.security import Limits
from dyknow.spec import Param, TransformationSpec
from dyknow.tags import parse_term

__all__ = ["MonitorInfo", "Monitors"]

_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


@dataclass(frozen=True, slots=True)
class MonitorInfo:
    """A monitor a manager was asked for: the key of its verdicts, the formula as asked, and for
    each expansion (one for a plain formula) the individual, the formula, the unit and its key;
    ``terms`` maps each term to the key of the stream that feeds it."""

    key: str
    formula: str
    expansions: tuple[tuple[str | None, str, str, str], ...]  # (individual, formula, unit, verdict key)
    terms: Mapping[str, str] = field(default_factory=dict)
    owner: Owner = LOCAL
    #: what its units found wrong with their data (a field no sample holds, a bound term silent)
    warnings: tuple[str, ...] = ()
    #: the terms bound to what exists, and their sources (also in ``terms``; never requested)
    bound: Mapping[str, str] = field(default_factory=dict)

    @property
    def units(self) -> tuple[str, ...]:
        """The monitor units."""
        return tuple(e[2] for e in self.expansions)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (``get_model``'s ``monitors`` entries)."""
        return {
            "key": self.key,
            "formula": self.formula,
            "terms": dict(self.terms),
            "holder": self.owner.holder,
            "monitors": [{"individual": i, "formula": f, "unit": u, "key": k} for i, f, u, k in self.expansions],
            "warnings": list(self.warnings),
            "bindings": dict(self.bound),
        }


class Monitors:
    """The monitors one manager was asked for. Thread-safe.

    It acts on the manager through the callables it is given: ``request(tag) -> key`` and
    ``release(key)`` (the manager's requests), ``spawn(spec, name, bindings, owner)``,
    ``destroy(name)`` and ``unit(name)`` (its units), ``individuals(class_ref)`` (its ontology;
    None without one), and ``budget(*formulas, account=...)``, which raises when its monitors
    could not take the formulas for that caller (:meth:`dyknow.model.Owner.account`).
    """

    def __init__(
        self,
        manager: str,
        *,
        request: Callable[[str], str],
        release: Callable[[str], object],
        spawn: Callable[[TransformationSpec, str, Mapping[str, str], Owner], UnitInfo],
        destroy: Callable[[str], None],
        unit: Callable[[str], object],
        individuals: Callable[[str], Sequence[str]] | None,
        max_expansions: int,
        limits: Limits | None = None,
        budget: Callable[..., None] | None = None,
    ) -> None:
        self.manager = manager
        self._request = request
        self._release = release
        self._spawn = spawn
        self._destroy = destroy
        self._unit = unit
        self._individuals = individuals
        self._max_expansions = max_expansions
        self._limits = limits  # the bounds every formula is held to before anything is requested
        self._budget = budget  # budget(*formulas, account=...): raises when the manager's monitors could not take them
        self._lock = threading.Lock()
        self._by_key: dict[str, MonitorInfo] = {}
        self._serial = itertools.count(1)
        # a monitor's base key -> its members planned: (member, request key or "" when bound, relay unit, source)
        self._members: dict[str, list[tuple[str, str, str, str]]] = {}
        self._relays = itertools.count(1)
        self._jobs: deque[tuple[Any, ...]] = deque()  # members to plan, in the order their arguments were seen
        self._worker: threading.Thread | None = None

    def add(
        self,
        formula: str,
        *,
        reorder_ms: float = 0.0,
        owner: Owner = LOCAL,
        readable: Callable[[str], None] | None = None,
        bindings: Mapping[str, str] | None = None,
        check_key: Callable[[str, str], object] | None = None,
        readable_source: Callable[[str, str], None] | None = None,
        robustness: bool = False,
    ) -> MonitorInfo:
        """Monitor ``formula`` (see the module documentation) for ``owner``; its :class:`MonitorInfo`.

        ``bindings`` bind terms to what exists (checked by
        :func:`~dyknow.reasoning.bindings.check_bindings`, with ``check_key`` for Zenoh keys;
        ``readable_source(source, term)`` raises when ``owner`` may not read a source), before
        anything is requested.

        Raises :class:`~dyknow.errors.FormulaError` when the formula does not read,
        :class:`~dyknow.errors.AccessError` when ``readable`` refuses a term (before anything
        is requested), :class:`~dyknow.planner.PlanningError` when a term has no stream,
        :class:`~dyknow.errors.AccessError` past ``owner``'s share of the monitors' formula
        nodes, :class:`~dyknow.errors.UnitError` when a monitor unit fails to start (what was
        set up for the others is taken down again, whatever the failure).
        """
        if not isinstance(reorder_ms, int | float) or not reorder_ms >= 0 or reorder_ms > 3_600_000:
            raise UnitError(f"reorder_ms {reorder_ms!r}", where="monitor", expected="0 to 3,600,000 milliseconds")
        expansions = expand(formula, self._individuals, max_expansions=self._max_expansions, limits=self._limits)
        if self._budget is not None:
            self._budget(*(parsed for _, parsed in expansions), account=owner.account())
        if bindings and expansions[0][0] is not None:
            first = next(iter(bindings.items()))
            raise FormulaError(
                "a binding in a formula with forall or exists",
                where=f"binding {str(first[0])[:200]}={str(first[1])[:300]}",
                expected="bindings in formulas without forall or exists (foreach may stay): bind each individual's formula",
            )
        bound = check_bindings(expansions[0][1], bindings, check_key=check_key) if bindings else {}
        if readable_source is not None:
            for bound_term, source in bound.items():
                readable_source(source, bound_term)
        if readable is not None:  # (a parameterized term's members: each as it is planned)
            for text in dict.fromkeys(str(term) for _, parsed in expansions for term in parsed.terms if not is_family(term)):
                if text not in bound:
                    readable(text)
        n = next(self._serial)
        base = keys.monitor_key(self.manager, n)
        quantified = expansions[0][0] is not None
        requested: dict[str, str] = {}
        spawned: list[str] = []
        made: list[tuple[str | None, str, str, str]] = []
        try:
            for individual, parsed in expansions:
                for term in parsed.terms:
                    if str(term) not in requested and str(term) not in bound and not is_family(term):
                        requested[str(term)] = self._request(str(term))
                chunks = [_UNSAFE.sub("_", part) for part in individual.split("/")] if individual is not None else []
                key = "/".join([base, *chunks])
                name = "-".join([f"monitor-{n}", *chunks])
                own = {text: source for text, source in bound.items() if text in map(str, parsed.terms)}
                spec = monitor_spec(parsed, label="formula-monitor", reorder_ms=reorder_ms, bound=own, robustness=robustness)
                families: dict[str, str] = {}  # a parameterized term's family -> the key its members are relayed to
                ports: dict[str, str] = {}
                for text, port in term_ports(parsed).items():
                    if text in requested or text in bound:
                        ports[port] = bound.get(text) or requested[text]
                    else:
                        families[text] = ports[port] = keys.members_key(self.manager, n, next(self._relays))
                ports[VERDICTS_PORT] = key
                started = self._spawn(spec, name, ports, owner)
                spawned.append(name)
                if started.state == "failed":  # (its nodes were taken meanwhile, say): never kept half-made
                    raise UnitError(
                        f"the monitor of {str(parsed)[:200]!r} failed to start: {started.error}",
                        where=f"manager {self.manager!r}",
                        expected="a monitor that can start; nothing of this call was kept",
                    )
                made.append((individual, str(parsed), name, key))
                if families:
                    self._relay_bound(base, name, families, bound, owner, spawned)
                    self._watch(base, name, families, owner, readable)
        except BaseException:
            with self._lock:
                self._members.pop(base, None)
            self._undo(spawned, list(requested.values()))
            raise
        depth = len(expansions[0][0].split("/")) if quantified and expansions[0][0] is not None else 0
        info = MonitorInfo("/".join([base, *["*"] * depth]), formula, tuple(made), {**requested, **bound}, owner, bound=bound)
        with self._lock:
            self._by_key[info.key] = info
        return info

    def release(self, key: str, *, owner: Owner = LOCAL, force: bool = False) -> bool:
        """Destroy the monitor(s) of ``key`` and give their terms back; False when ``key`` is no
        monitor's. :class:`~dyknow.errors.AccessError` when ``owner`` may not release it (it is
        another's, and not forced)."""
        with self._lock:
            info = self._by_key.get(key)
            if info is None:
                return False
            if not force and not owner.holds(info.owner):
                raise AccessError(
                    f"{owner.who()} may not release the monitor on {key!r}: it is {info.owner}'s",
                    where=f"manager {self.manager!r}",
                    expected="a release by the client or caller that asked for it; an admin may force it (release with force)",
                )
            del self._by_key[key]
            members = self._members.pop(_base(key), [])
        self._undo(list(info.units) + [m[2] for m in members], [key for term, key in info.terms.items() if term not in info.bound] + [m[1] for m in members if m[1]])
        return True

    def owner(self, key: str) -> Owner | None:
        """Who asked for the monitor on ``key`` (None: no monitor there)."""
        with self._lock:
            info = self._by_key.get(key)
        return info.owner if info is not None else None

    def adapted(self, key: str, cause: str) -> None:
        """A request's stream on ``key`` was re-planned: the monitors that read it note a gap."""
        for info in self.infos():
            if key in info.terms.values():
                for name in info.units:
                    try:
                        unit = self._unit(name)
                    except DyKnowError:
                        continue
                    if isinstance(unit, FormulaMonitor):
                        unit.adapted(key, cause)

    def __contains__(self, key: object) -> bool:
        with self._lock:
            return key in self._by_key

    def infos(self) -> list[MonitorInfo]:
        """Every monitor, oldest first (with what its units warned of so far)."""
        with self._lock:
            found = list(self._by_key.values())
        out = []
        for info in found:
            with self._lock:
                members = {m[0]: m[3] for m in self._members.get(_base(info.key), [])}
            if members:
                info = replace(info, terms={**info.terms, **members})
            warnings: list[str] = []
            for name in info.units:
                try:
                    unit = self._unit(name)
                except DyKnowError:
                    continue
                if isinstance(unit, FormulaMonitor):
                    warnings.extend(unit.warnings)
            out.append(replace(info, warnings=tuple(warnings)) if warnings else info)
        return out

    # -- parameterized terms: a member per argument seen (dyknow.reasoning.members)

    def _relay_bound(self, base: str, name: str, families: Mapping[str, str], bound: Mapping[str, str], owner: Owner, spawned: list[str]) -> None:
        """Relay the members bound to what exists to their families' keys, from the start."""
        unit = self._unit(name)
        assert isinstance(unit, FormulaMonitor)
        for family, family_key in families.items():
            for term, source in bound.items():
                arg = member_arg(unit.families.ports[unit.terms.index(family)].family, parse_term(term))
                if arg is None:
                    continue
                relay = f"{name}-member-{next(self._relays)}"
                self._spawn(replace(RELAY_SPEC, params=_relay_params(arg, textual=True)), relay, {"in": source, "out": family_key}, owner)
                spawned.append(relay)
                unit.families.seen[family].add(arg)
                with self._lock:
                    self._members.setdefault(base, []).append((term, "", relay, source))

    def _watch(self, base: str, name: str, families: Mapping[str, str], owner: Owner, readable: Callable[[str], None] | None) -> None:
        """Plan a member for each argument the monitor ``name`` sees (on a thread of the
        monitors': planning may spawn units, which the monitor's own thread must not wait for)."""
        unit = self._unit(name)
        assert isinstance(unit, FormulaMonitor)
        with self._lock:
            self._members.setdefault(base, [])

        def found(family: str, arg: str) -> None:
            self._later((base, name, family, families[family], arg, owner, readable))

        unit.families.watch(found)

    def _later(self, job: tuple[Any, ...]) -> None:
        with self._lock:
            self._jobs.append(job)
            if self._worker is not None:
                return
            self._worker = threading.Thread(target=self._work, name=f"dyknow-members-{self.manager}", daemon=True)
        self._worker.start()

    def _work(self) -> None:
        while True:
            with self._lock:
                if not self._jobs:
                    self._worker = None
                    return
                job = self._jobs.popleft()
            self._plan_member(*job)

    def _plan_member(self, base: str, name: str, family: str, family_key: str, arg: str, owner: Owner, readable: Callable[[str], None] | None) -> None:
        """Request member ``arg`` of ``family`` and relay it to ``family_key``; a member that
        cannot be (planned, read by ``owner``) is warned of by the monitor ``name``."""
        with self._lock:
            if base not in self._members:
                return  # released meanwhile
        try:
            unit = self._unit(name)
        except DyKnowError:
            return
        assert isinstance(unit, FormulaMonitor)
        try:
            member = str(member_term(unit.families.ports[unit.terms.index(family)].family, arg))
        except DyKnowError:
            return  # (the unit hands on names only)
        relay = f"{name}-member-{next(self._relays)}"
        key = ""
        try:
            if readable is not None:
                readable(member)
            key = self._request(member)
            self._spawn(replace(RELAY_SPEC, params=_relay_params(arg, textual=False)), relay, {"in": key, "out": family_key}, owner)
        except DyKnowError as exc:
            if key:
                self._undo([relay], [key])
            warning = f"no stream for {member}, the member of {family} its argument named: {exc}; the term stays unknown there"
            unit.call_soon(lambda: unit.warn(warning, term=member))
            return
        with self._lock:
            kept = base in self._members
            if kept:
                self._members[base].append((member, key, relay, key))
        if not kept:  # released while it was planned
            self._undo([relay], [key])

    def _undo(self, units: list[str], requests: list[str]) -> None:
        for name in reversed(units):
            try:
                self._destroy(name)
            except DyKnowError:
                pass  # gone already (the manager is closing, say)
        for key in requests:
            try:
                self._release(key)
            except DyKnowError:
                pass


def _base(key: str) -> str:
    """A monitor's base key: its key without the ``/*`` of a quantified one."""
    while key.endswith("/*"):
        key = key[:-2]
    return key


def _relay_params(arg: str, *, textual: bool) -> tuple[Param, ...]:
    return (Param("arg", "string", arg), Param("textual", "bool", textual))
