"""The semantic planner: which units, wired how, provide a stream with a requested tag.

``plan("BallPosition(field)", library, ontology, running, unavailable, measurements)`` searches the
AND/OR graph of transformation specs: a tag may have several providers (OR: any spec or running
unit whose output port carries a tag that satisfies it, see :meth:`Ontology.matches`), and a
transformation needs all its tagged inputs (AND). It

- reuses outputs of running, healthy units instead of spawning duplicates;
- skips unavailable transformations, transformations whose constraints the latest measurements
  violate, and running units that failed or stalled;
- never loops on cyclic specs, and stops at a depth limit;
- among complete configurations picks by a documented order: **fewest new units, then the lowest
  total priority of the new units, then labels** (alphabetically), so the result is deterministic.

Input ports without tags are not wired by the planner (they keep their default binding). A new
unit is named after its label (``ball-detector(bottom)`` becomes ``ball-detector-bottom``, with
``-2``, ``-3`` ... when the name is taken) and its output ports get the default keys
``dyknow/<manager>/<unit>/<port>``.

The planner is pure: same inputs, same plan. When nothing fits, :class:`PlanningError` names the
unmet tag and, for each alternative tried, why it was rejected (no provider, unavailable,
constraint violated, cycle, depth limit, failed). It only reads the library, the ontology and a
snapshot of what runs; the manager acts on the plan.

Costs are computed per input and new units that several inputs need are shared (counted once),
so the search is greedy per input; for the libraries this is for (pipelines a few layers deep) it
finds the configuration the order above prefers.
"""

from __future__ import annotations

import re
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from dyknow.errors import DyKnowError, PlanningError
from dyknow.ontology import Ontology
from dyknow.spec import TransformationSpec
from dyknow.tags import Term, local_name, parse_term

__all__ = [
    "Alternative",
    "Connection",
    "Plan",
    "PlannedUnit",
    "Planner",
    "PlanningError",
    "Rejection",
    "RunningUnit",
    "plan",
    "unit_name_for",
]

DEFAULT_MAX_DEPTH = 32


# ---------------------------------------------------------------------------- inputs and outputs


@dataclass(frozen=True, slots=True)
class RunningUnit:
    """A unit that runs now, as the planner sees it: what its output ports carry and where."""

    name: str
    label: str
    outputs: Mapping[str, str]  # output port -> key
    tags: Mapping[str, tuple[str, ...]]  # output port -> tags
    healthy: bool = True  # running and not stalled


@dataclass(frozen=True, slots=True)
class PlannedUnit:
    """A unit of a plan: ``new`` ones are to be spawned with ``bindings`` (every port -> key)."""

    name: str
    label: str
    new: bool
    bindings: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Connection:
    """An output port feeding an input port over ``key``; ports as ``unit.port``."""

    source: str
    target: str
    key: str


@dataclass(frozen=True, slots=True)
class Plan:
    """A configuration that provides ``request`` on ``output_unit.output_port`` (``output_key``)."""

    request: str
    output_unit: str
    output_port: str
    output_key: str
    units: tuple[PlannedUnit, ...]  # producers before consumers
    connections: tuple[Connection, ...]
    cost: tuple[int, int, tuple[str, ...]]  # new units, total priority of new units, their labels

    @property
    def new_units(self) -> tuple[PlannedUnit, ...]:
        return tuple(u for u in self.units if u.new)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form of ``dyknow plan --json``."""
        return {
            "request": self.request,
            "output": {"unit": self.output_unit, "port": self.output_port, "key": self.output_key},
            "units": [{"name": u.name, "label": u.label, "new": u.new} for u in self.units],
            "connections": [{"from": c.source, "to": c.target, "key": c.key} for c in self.connections],
        }


@dataclass(frozen=True, slots=True)
class Alternative:
    """One provider tried for a tag and why it was rejected (``unmet``: the input it could not get)."""

    provider: str  # a transformation label, or "unit NAME" for a running unit
    port: str
    reason: str
    unmet: Rejection | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"provider": self.provider, "port": self.port, "reason": self.reason}
        if self.unmet is not None:
            out["unmet"] = self.unmet.to_dict()
        return out


@dataclass(frozen=True, slots=True)
class Rejection:
    """A tag nothing could provide, with every alternative tried."""

    tag: str
    alternatives: tuple[Alternative, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"tag": self.tag, "alternatives": [a.to_dict() for a in self.alternatives]}

    def lines(self, indent: int = 0) -> list[str]:
        pad = "  " * indent
        if not self.alternatives:
            return [f"{pad}nothing provides {self.tag} (no transformation or running unit has an output port with a matching tag)"]
        out = [f"{pad}nothing can provide {self.tag}:"]
        for alt in self.alternatives:
            out.append(f"{pad}  - {alt.provider} (port {alt.port}): {alt.reason}")
            if alt.unmet is not None:
                out.extend(alt.unmet.lines(indent + 2))
        return out


# ---------------------------------------------------------------------------- search state


@dataclass(frozen=True, slots=True)
class _Source:
    """Where a stream comes from while planning: a new unit (by label) or a running one (by name)."""

    new: bool
    unit: str  # label when new, name when running
    port: str


@dataclass(slots=True)
class _Config:
    """A complete configuration for one tag: new units by label with their input sources."""

    output: _Source
    new: dict[str, dict[str, _Source]]  # label -> input port -> source
    reused: frozenset[str]
    priority: int

    @property
    def cost(self) -> tuple[int, int, tuple[str, ...]]:
        return (len(self.new), self.priority, tuple(sorted(self.new)))


@dataclass(frozen=True, slots=True)
class _Provider:
    spec: TransformationSpec
    port: str
    tags: tuple[Term, ...]  # every tag of the port


_NAME_CHARS = re.compile(r"[^A-Za-z0-9_.-]+")


def unit_name_for(label: str) -> str:
    """The unit name the planner gives a new unit of transformation ``label``."""
    name = _NAME_CHARS.sub("-", label).strip("-.") or "unit"
    return name if name[0].isalnum() or name[0] == "_" else f"u{name}"


# ---------------------------------------------------------------------------- the planner


class Planner:
    """Plans over one library and ontology; indexes the providers once for fast repeated plans."""

    def __init__(
        self,
        specs: Iterable[TransformationSpec],
        ontology: Ontology | None = None,
        *,
        manager: str = "dyknow",
        max_depth: int = DEFAULT_MAX_DEPTH,
    ) -> None:
        self.ontology = ontology if ontology is not None else Ontology.empty()
        self.manager = manager
        self.max_depth = max_depth
        self._specs = {s.label: s for s in specs}
        # functor key -> providers whose output port carries a tag with that functor
        self._providers: dict[str, list[_Provider]] = {}
        for spec in sorted(self._specs.values(), key=lambda s: s.label):
            for port in spec.outputs:
                terms = tuple(parse_term(t) for t in spec.tags_for(port.name))
                for term in terms:
                    self._providers.setdefault(self._functor_key(term.functor), []).append(_Provider(spec, port.name, terms))

    def _functor_key(self, functor: str) -> str:
        iri = self.ontology.resolve(functor)
        return iri if iri is not None else "local:" + local_name(functor)

    def _candidates(self, required: Term) -> list[_Provider]:
        key = self._functor_key(required.functor)
        if key.startswith("local:"):
            found = list(self._providers.get(key, ()))
        else:
            found = []
            for sub in sorted(self.ontology.descendants(key)):
                found.extend(self._providers.get(sub, ()))
        seen: set[tuple[str, str]] = set()
        unique = []
        for p in sorted(found, key=lambda p: (p.spec.label, p.port)):
            if (p.spec.label, p.port) not in seen:
                seen.add((p.spec.label, p.port))
                unique.append(p)
        return unique

    def _satisfies(self, provided: tuple[Term, ...], required: tuple[Term, ...]) -> bool:
        return all(any(self.ontology.matches(p, r) for p in provided) for r in required)

    def plan(
        self,
        request: str,
        running: Iterable[RunningUnit] = (),
        unavailable: Collection[str] = (),
        measurements: Mapping[str, float | str] | None = None,
        *,
        reserved_names: Collection[str] = (),
    ) -> Plan:
        """A configuration providing ``request``; :class:`PlanningError` when none exists.

        ``running``: units whose outputs may be reused. ``unavailable``: transformation labels
        not to use. ``measurements``: the latest value of each measure, checked against the
        specs' constraints. ``reserved_names``: unit names new units must not take.
        """
        try:
            wanted = (parse_term(request),)
        except DyKnowError as exc:
            raise PlanningError(request, None, f"cannot plan {request!r}: {exc}") from exc
        search = _Search(self, tuple(running), frozenset(unavailable), dict(measurements or {}))
        result = search.best(wanted, (), 0)
        if isinstance(result, Rejection):
            raise PlanningError(str(wanted[0]), result)
        taken = set(reserved_names) | {u.name for u in search.running}
        return _materialize(str(wanted[0]), result, self._specs, search.by_name, taken, self.manager)


class _Search:
    """One planning run: memoized best configurations per (tags, path)."""

    def __init__(self, planner: Planner, running: tuple[RunningUnit, ...], unavailable: frozenset[str], measurements: dict[str, Any]) -> None:
        self.planner = planner
        self.running = running
        self.by_name = {u.name: u for u in running}
        self.unavailable = unavailable
        self.measurements = measurements
        self.memo: dict[tuple[tuple[Term, ...], frozenset[str]], _Config | Rejection] = {}
        self.running_terms = [
            (u, port, tuple(parse_term(t) for t in tags)) for u in sorted(running, key=lambda u: u.name) for port, tags in sorted(u.tags.items())
        ]

    def best(self, required: tuple[Term, ...], path: tuple[str, ...], depth: int) -> _Config | Rejection:
        memo_key = (required, frozenset(path))
        found = self.memo.get(memo_key)
        if found is None:
            found = self.memo[memo_key] = self._best(required, path, depth)
        return found

    def _best(self, required: tuple[Term, ...], path: tuple[str, ...], depth: int) -> _Config | Rejection:
        planner = self.planner
        options: list[_Config] = []
        rejected: list[Alternative] = []
        for unit, port, terms in self.running_terms:
            if not planner._satisfies(terms, required):
                continue
            if not unit.healthy:
                rejected.append(Alternative(f"unit {unit.name}", port, "failed or stalled"))
            elif unit.label in self.unavailable:
                rejected.append(Alternative(f"unit {unit.name}", port, f"unavailable ({unit.label} is excluded)"))
            else:
                options.append(_Config(_Source(False, unit.name, port), {}, frozenset({unit.name}), 0))
        for provider in planner._candidates(required[0]):
            if not planner._satisfies(provider.tags, required):
                continue
            spec = provider.spec
            option = self._try(spec, provider.port, path, depth, rejected)
            if option is not None:
                options.append(option)
        if not options:
            return Rejection(" & ".join(str(t) for t in required), tuple(rejected))
        return min(options, key=lambda c: (c.cost, c.output.unit, c.output.port))

    def _try(self, spec: TransformationSpec, port: str, path: tuple[str, ...], depth: int, rejected: list[Alternative]) -> _Config | None:
        label = spec.label
        if label in self.unavailable:
            rejected.append(Alternative(label, port, "unavailable"))
            return None
        for constraint in spec.constraints:
            value = self.measurements.get(constraint.measure)
            if value is not None and not constraint.holds(value):
                rejected.append(
                    Alternative(label, port, f"constraint violated: {constraint.measure} = {value!r}, needs {constraint.op} {constraint.value!r}")
                )
                return None
        if label in path:
            cycle = " -> ".join((*path[path.index(label) :], label))
            rejected.append(Alternative(label, port, f"cycle: {cycle}"))
            return None
        if depth >= self.planner.max_depth:
            rejected.append(Alternative(label, port, f"depth limit ({self.planner.max_depth} transformations deep)"))
            return None
        new: dict[str, dict[str, _Source]] = {label: {}}
        reused: set[str] = set()
        priority = spec.priority
        for inp in spec.inputs:
            tags = spec.tags_for(inp.name)
            if not tags:
                continue  # untagged inputs are not wired by the planner
            sub = self.best(tuple(parse_term(t) for t in tags), (*path, label), depth + 1)
            if isinstance(sub, Rejection):
                rejected.append(Alternative(label, port, f"input {inp.name!r} needs {sub.tag}", sub))
                return None
            new[label][inp.name] = sub.output
            for sub_label, inputs in sub.new.items():
                if sub_label not in new:  # shared: a label several inputs need is spawned once
                    new[sub_label] = inputs
                    priority += self.planner._specs[sub_label].priority
            reused |= sub.reused
        return _Config(_Source(True, label, port), new, frozenset(reused), priority)


def _materialize(
    request: str,
    config: _Config,
    specs: Mapping[str, TransformationSpec],
    running: Mapping[str, RunningUnit],
    taken: set[str],
    manager: str,
) -> Plan:
    """Names, keys and connections for a chosen configuration; producers before consumers."""
    # keep only what the output needs (sharing may leave a duplicate branch behind)
    needed: list[str] = []
    reused: list[str] = []

    def visit(source: _Source) -> None:
        if not source.new:
            if source.unit not in reused:
                reused.append(source.unit)
            return
        if source.unit in needed:
            return
        for _, upstream in sorted(config.new[source.unit].items()):
            visit(upstream)
        needed.append(source.unit)

    visit(config.output)
    names: dict[str, str] = {}
    for label in needed:
        base = unit_name_for(label)
        name, n = base, 1
        while name in taken:
            n += 1
            name = f"{base}-{n}"
        taken.add(name)
        names[label] = name

    def key_of(source: _Source) -> str:
        if source.new:
            return f"dyknow/{manager}/{names[source.unit]}/{source.port}"
        return running[source.unit].outputs[source.port]

    def name_of(source: _Source) -> str:
        return names[source.unit] if source.new else source.unit

    units: list[PlannedUnit] = [PlannedUnit(name, running[name].label, False, dict(running[name].outputs)) for name in sorted(reused)]
    connections: list[Connection] = []
    for label in needed:
        spec = specs[label]
        name = names[label]
        bindings = {p.name: f"dyknow/{manager}/{name}/{p.name}" for p in spec.ports}
        for port, upstream in sorted(config.new[label].items()):
            bindings[port] = key_of(upstream)
            connections.append(Connection(f"{name_of(upstream)}.{upstream.port}", f"{name}.{port}", key_of(upstream)))
        units.append(PlannedUnit(name, label, True, bindings))
    out = config.output
    new_labels = tuple(sorted(needed))
    priority = sum(specs[label].priority for label in needed)
    return Plan(request, name_of(out), out.port, key_of(out), tuple(units), tuple(connections), (len(needed), priority, new_labels))


def plan(
    request_tag: str,
    library: Iterable[TransformationSpec],
    ontology: Ontology | None = None,
    running_model: Iterable[RunningUnit] = (),
    unavailable: Collection[str] = (),
    measurements: Mapping[str, float | str] | None = None,
    *,
    manager: str = "dyknow",
    max_depth: int = DEFAULT_MAX_DEPTH,
) -> Plan:
    """Plan once (see :class:`Planner` to plan repeatedly over the same library)."""
    return Planner(library, ontology, manager=manager, max_depth=max_depth).plan(
        request_tag, running_model, unavailable, measurements
    )
