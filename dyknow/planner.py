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

**Several managers.** Given the libraries of other managers (``peers``) and their running units
(``RunningUnit.manager``), the planner plans over their union. A transformation runs on the
manager whose library holds it. When several hold the same label, the cost decides after the
number of new units and their priority: **the requesting manager first, then one already
running the unit's inputs, then the least loaded** (``load``: units per manager). A request's
current configuration is *preferred* (``prefer``): among options of equal cost its transformations
win, unless another manager carries fewer units than theirs by more than a margin
(:func:`load_margin`: 2 units, or a quarter of the preferred manager's load when that is more),
so a request is never moved for a tie, nor for a difference of a unit or two. Constraints
are checked against the measurements of the manager that would run the unit. Inside the planner
a transformation of another manager is known as ``label@manager`` (as are its running units).

The planner is pure: same inputs, same plan. When nothing fits, :class:`PlanningError` names the
unmet tag and, for each alternative tried, why it was rejected (no provider, unavailable,
constraint violated, cycle, depth limit, failed). It only reads the library, the ontology and a
snapshot of what runs; the manager acts on the plan.

Costs add up over inputs (a unit that two inputs both need counts twice while choosing, and is
spawned once), which makes the search a shortest-path problem on the AND/OR graph: every tag and
every option is looked at once, so a library of thousands of specs plans in milliseconds.
"""

from __future__ import annotations

import difflib
import heapq
import itertools
import re
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from dyknow.errors import DyKnowError, PlanningError
from dyknow.keys import default_key
from dyknow.ontology import Ontology
from dyknow.spec import TransformationSpec
from dyknow.tags import Term, local_name, parse_term

__all__ = [
    "LOAD_MARGIN_UNITS",
    "Alternative",
    "Connection",
    "Plan",
    "PlannedUnit",
    "Planner",
    "PlanningError",
    "Rejection",
    "RunningUnit",
    "load_margin",
    "plan",
    "qualify",
    "unit_name_for",
    "unqualify",
]

DEFAULT_MAX_DEPTH = 32
#: The least difference in load (units) for which a request leaves a preferred manager (see :func:`load_margin`).
LOAD_MARGIN_UNITS = 2


def load_margin(load: int) -> int:
    """By how many units another manager must carry fewer than ``load`` (the preferred one's, the
    request's own units not counted) to win a tie of cost against a preferred transformation:
    :data:`LOAD_MARGIN_UNITS`, or a quarter of ``load`` when that is more."""
    return max(LOAD_MARGIN_UNITS, load // 4)


# ---------------------------------------------------------------------------- inputs and outputs


@dataclass(frozen=True, slots=True)
class RunningUnit:
    """A unit that runs now, as the planner sees it: what its output ports carry and where.

    ``manager`` is None for a unit of the requesting manager, else the manager that runs it.
    """

    name: str
    label: str
    outputs: Mapping[str, str]  # output port -> key
    tags: Mapping[str, tuple[str, ...]]  # output port -> tags
    healthy: bool = True  # running and not stalled
    manager: str | None = None

    @property
    def ref(self) -> str:
        """How the planner refers to the unit: its name, or ``name@manager`` on another manager."""
        return self.name if self.manager is None else qualify(self.name, self.manager)


@dataclass(frozen=True, slots=True)
class PlannedUnit:
    """A unit of a plan: ``new`` ones are to be spawned with ``bindings`` (every port -> key),
    on ``manager`` (which runs it, or already runs it)."""

    name: str
    label: str
    new: bool
    bindings: Mapping[str, str] = field(default_factory=dict)
    manager: str = ""
    remote: bool = False  # on a manager other than the requester

    @property
    def ref(self) -> str:
        """The unit as a plan's requester refers to it: ``name``, or ``name@manager`` elsewhere."""
        return qualify(self.name, self.manager) if self.remote else self.name


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
        """The units the plan spawns, producers first."""
        return tuple(u for u in self.units if u.new)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form of ``dyknow plan --json``."""
        return {
            "request": self.request,
            "output": {"unit": self.output_unit, "port": self.output_port, "key": self.output_key},
            "units": [{"name": u.name, "label": u.label, "new": u.new, "manager": u.manager} for u in self.units],
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
        """The JSON form (``dyknow plan --json``)."""
        out: dict[str, Any] = {"provider": self.provider, "port": self.port, "reason": self.reason}
        if self.unmet is not None:
            out["unmet"] = self.unmet.to_dict()
        return out


@dataclass(frozen=True, slots=True)
class Rejection:
    """A tag nothing could provide, with every alternative tried."""

    tag: str
    alternatives: tuple[Alternative, ...]
    suggestions: tuple[str, ...] = ()  # when nothing has the tag: the closest tags there are

    def to_dict(self) -> dict[str, Any]:
        """The JSON form: the unmet tag and each alternative's reason (and close tags there are)."""
        out: dict[str, Any] = {"tag": self.tag, "alternatives": [a.to_dict() for a in self.alternatives]}
        if self.suggestions:
            out["suggestions"] = list(self.suggestions)
        return out

    def lines(self, indent: int = 0, _seen: set[str] | None = None) -> list[str]:
        """The explanation as indented text; a tag explained once is referred to afterwards."""
        seen = set() if _seen is None else _seen
        pad = "  " * indent
        if not self.alternatives:
            hint = " or ".join(repr(s) for s in self.suggestions)
            hint = f"; did you mean {hint}?" if hint else ""
            return [f"{pad}nothing provides {self.tag} (no transformation or running unit has an output port with a matching tag{hint})"]
        if self.tag in seen:
            return [f"{pad}nothing can provide {self.tag} (see above)"]
        seen.add(self.tag)
        out = [f"{pad}nothing can provide {self.tag}:"]
        for alt in self.alternatives:
            out.append(f"{pad}  - {alt.provider} (port {alt.port}): {alt.reason}")
            if alt.unmet is not None:
                out.extend(alt.unmet.lines(indent + 2, seen))
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
    ref: str  # the label, or label@manager
    spec: TransformationSpec
    port: str
    tags: tuple[Term, ...]  # every tag of the port


def qualify(name: str, manager: str) -> str:
    """A unit or label of another manager, as the planner and the requester refer to it: ``name@manager``."""
    return f"{name}@{manager}"


def unqualify(ref: str, local: str) -> tuple[str, str]:
    """``(name, manager)`` of a reference made by :func:`qualify`; a plain name is ``local``'s."""
    name, sep, manager = ref.rpartition("@")
    return (name, manager) if sep else (ref, local)


_NAME_CHARS = re.compile(r"[^A-Za-z0-9_.-]+")


def unit_name_for(label: str) -> str:
    """The unit name the planner gives a new unit of transformation ``label``."""
    name = _NAME_CHARS.sub("-", label).strip("-.") or "unit"
    return name if name[0].isalnum() or name[0] == "_" else f"u{name}"


# ---------------------------------------------------------------------------- the planner


class Planner:
    """Plans over one library and ontology.

    What does not change between plans is worked out once and kept: which spec ports can provide
    which required tags, and, per request, the graph of everything it could need. A plan then
    only weighs that graph against what runs, what is unavailable and the measurements.
    """

    def __init__(
        self,
        specs: Iterable[TransformationSpec],
        ontology: Ontology | None = None,
        *,
        manager: str = "dyknow",
        max_depth: int = DEFAULT_MAX_DEPTH,
        peers: Mapping[str, Iterable[TransformationSpec]] | None = None,
    ) -> None:
        self.ontology = ontology if ontology is not None else Ontology.empty()
        self.manager = manager
        self.max_depth = max_depth
        # every transformation by the label the planner knows it by: its own, or label@manager
        self._specs = {s.label: s for s in specs}
        self._placement = dict.fromkeys(self._specs, manager)
        for peer, peer_specs in sorted((peers or {}).items()):
            if peer == manager:
                continue
            for s in peer_specs:
                ref = qualify(s.label, peer)
                self._specs[ref] = s
                self._placement[ref] = peer
        # (functor key, arg local names) -> providers whose output port carries such a tag
        self._providers: dict[tuple[str, tuple[str, ...]], list[_Provider]] = {}
        for ref, spec in sorted(self._specs.items()):
            for port in spec.outputs:
                terms = tuple(parse_term(t) for t in spec.tags_for(port.name))
                for term in terms:
                    self._providers.setdefault(self._index_key(term), []).append(_Provider(ref, spec, port.name, terms))
        self._options: dict[Required, tuple[_Option, ...]] = {}  # spec options per required tag
        self._graphs: dict[Required, _Graph] = {}  # per request

    def spec(self, ref: str) -> TransformationSpec:
        """A transformation by the label the planner knows it by (``label`` or ``label@manager``)."""
        return self._specs[ref]

    def close_tags(self, tag: str, running: Iterable[RunningUnit] = ()) -> tuple[str, ...]:
        """The tags the library's outputs (and ``running`` units') carry that are closest to ``tag``."""
        known = {t for s in self._specs.values() for p in s.outputs for t in s.tags_for(p.name)}
        known |= {t for u in running for tags in u.tags.values() for t in tags}
        return tuple(difflib.get_close_matches(tag, sorted(known), n=3, cutoff=0.8))  # (0.6 matched any tag of the same args)

    def _functor_key(self, functor: str) -> str:
        iri = self.ontology.resolve(functor)
        return iri if iri is not None else "local:" + local_name(functor)

    def _index_key(self, term: Term) -> tuple[str, tuple[str, ...]]:
        return self._functor_key(term.functor), tuple(local_name(a) for a in term.args)

    def _functor_keys(self, functor: str) -> frozenset[str]:
        """Every functor key that satisfies ``functor`` (itself and its subclasses)."""
        key = self._functor_key(functor)
        return frozenset((key,)) if key.startswith("local:") else self.ontology.descendants(key)

    def _satisfies(self, provided: tuple[Term, ...], required: tuple[Term, ...]) -> bool:
        return all(any(self.ontology.matches(p, r) for p in provided) for r in required)

    def options(self, required: Required) -> tuple[_Option, ...]:
        """The spec ports that can provide ``required``, by label and port."""
        found = self._options.get(required)
        if found is None:
            candidates: dict[tuple[str, str], _Provider] = {}
            args = tuple(local_name(a) for a in required[0].args)
            for key in self._functor_keys(required[0].functor):
                for provider in self._providers.get((key, args), ()):
                    candidates.setdefault((provider.ref, provider.port), provider)
            result = []
            for (ref, port), provider in sorted(candidates.items()):
                if not self._satisfies(provider.tags, required):
                    continue
                spec = provider.spec
                inputs = tuple((p.name, tuple(parse_term(t) for t in spec.tags_for(p.name))) for p in spec.inputs if spec.tags_for(p.name))
                result.append(_Option(ref, port, True, spec.priority, inputs, spec.constraints, self._placement[ref]))
            found = self._options[required] = tuple(result)
        return found

    def running_keys(self, request: str) -> frozenset[tuple[str, tuple[str, ...]]]:
        """What a running unit's output tag may be to serve ``request`` or anything it could need:
        ``(functor, args)`` by local names (more than :meth:`plan` accepts, never less; it checks
        each unit exactly). A caller that keeps its units indexed so passes :meth:`plan` only
        those, however many run. Empty when ``request`` does not parse (:meth:`plan` says why)."""
        try:
            wanted = (parse_term(request),)
        except DyKnowError:
            return frozenset()
        found = set()
        for required in self.graph(wanted).required:
            args = tuple(local_name(a) for a in required[0].args)
            for key in self._functor_keys(required[0].functor):
                found.add((local_name(key.removeprefix("local:")), args))
        return frozenset(found)

    def graph(self, request: Required) -> _Graph:
        """Everything ``request`` could need, numbered for a fast search (built once per request)."""
        graph = self._graphs.get(request)
        if graph is None:
            graph = self._graphs[request] = _Graph(self, request)
        return graph

    def plan(
        self,
        request: str,
        running: Iterable[RunningUnit] = (),
        unavailable: Collection[str] = (),
        measurements: Mapping[str, float | str] | None = None,
        *,
        reserved_names: Collection[str] = (),
        peer_measurements: Mapping[str, Mapping[str, float | str]] | None = None,
        load: Mapping[str, int] | None = None,
        prefer: Collection[str] = (),
    ) -> Plan:
        """A configuration providing ``request``; :class:`PlanningError` when none exists.

        ``running``: units whose outputs may be reused (those of other managers too).
        ``unavailable``: transformations not to use (``label``, or ``label@manager``).
        ``measurements``: the latest value of each measure of the requesting manager, and
        ``peer_measurements`` those of the others, checked against the constraints of the
        transformations each would run. ``reserved_names``: unit names new units must not take
        (``name`` on the requesting manager, ``name@manager`` on another; only asked whether it
        holds a name, so it may be a live view of what runs). ``load``: units per manager (the least loaded is preferred).
        ``prefer``: transformations (``label``, ``label@manager``) that win ties of cost, unless
        another manager is less loaded by more than :func:`load_margin` (hysteresis: a request's
        current configuration, so that it moves only for a strict improvement).
        """
        try:
            wanted = (parse_term(request),)
        except DyKnowError as exc:
            raise PlanningError(request, None, f"cannot plan {request!r}: {exc}") from exc
        running = tuple(running)
        by_manager = {
            self.manager: dict(measurements or {}),
            **{m: dict(v) for m, v in (peer_measurements or {}).items() if m != self.manager},
        }
        search = _Search(self, self.graph(wanted), running, frozenset(unavailable), by_manager, dict(load or {}), frozenset(prefer))
        search.settle()
        if not search.settled(0):
            raise PlanningError(str(wanted[0]), search.explain())
        home = self.manager
        running_refs = {u.name if (u.manager or home) == home else qualify(u.name, u.manager or home) for u in running}
        assigned: set[str] = set()

        def taken(name: str, where: str) -> bool:
            ref = name if where == home else qualify(name, where)
            return ref in assigned or ref in reserved_names or ref in running_refs

        def take(name: str, where: str) -> None:
            assigned.add(name if where == home else qualify(name, where))

        return _materialize(str(wanted[0]), search.config(), self._specs, self._placement, {u.ref: u for u in running}, (taken, take), home)


Required = tuple[Term, ...]  # the tags one input port requires (all of them)


@dataclass(frozen=True, slots=True)
class _Option:
    """One way to provide a required tag: a spec's port (needing inputs), or a running unit's port."""

    unit: str  # label (new) or running unit name
    port: str
    new: bool
    priority: int = 0
    inputs: tuple[tuple[str, Required], ...] = ()  # (input port, what it requires)
    constraints: tuple[Any, ...] = ()
    manager: str = ""  # which manager would run (or runs) it


class _Graph:
    """The static AND/OR graph below one request: required tags and spec options, numbered.

    ``required[0]`` is the request. ``spec_options[r]`` lists option ids providing required tag
    ``r``; option ``o`` provides ``provides[o]`` and needs ``needs[o]`` (required tag ids).
    """

    def __init__(self, planner: Planner, request: Required) -> None:
        self.required: list[Required] = [request]
        ids = {request: 0}
        self.options: list[_Option] = []
        self.provides: list[int] = []
        self.needs: list[tuple[int, ...]] = []
        self.spec_options: list[list[int]] = []
        todo = 0
        while todo < len(self.required):
            req = self.required[todo]
            mine = []
            for option in planner.options(req):
                needs = []
                for _, needed in option.inputs:
                    if needed not in ids:
                        ids[needed] = len(self.required)
                        self.required.append(needed)
                    needs.append(ids[needed])
                mine.append(len(self.options))
                self.options.append(option)
                self.provides.append(todo)
                self.needs.append(tuple(needs))
            self.spec_options.append(mine)
            todo += 1
        self.ids = ids
        self.waiting: list[list[int]] = [[] for _ in self.required]  # required id -> options needing it
        for o, option_needs in enumerate(self.needs):
            for r in set(option_needs):
                self.waiting[r].append(o)
        self.distinct_needs = [len(set(needs)) for needs in self.needs]


class _Search:
    """One plan over a request's graph: Knuth's generalisation of Dijkstra's algorithm.

    From the sources up: an option's cost is its own (one new unit and its priority; nothing for a
    running unit) plus the costs of what its inputs get; a required tag takes its cheapest option
    once all that option's inputs are settled. Every tag and option is handled once, so cyclic
    specs cannot loop and large libraries plan fast. The cost is (new units, their priority,
    their placement): placement is 0 on the requesting manager, 1 on a manager that runs one of
    the unit's inputs, 2 elsewhere. Ties go to the least loaded manager (a preferred option's
    load counted :func:`load_margin` lower), then to a preferred option, then the lower label,
    then port.
    """

    def __init__(
        self,
        planner: Planner,
        graph: _Graph,
        running: tuple[RunningUnit, ...],
        unavailable: frozenset[str],
        measurements: dict[str, dict[str, Any]],
        load: dict[str, int],
        prefer: frozenset[str] = frozenset(),
    ) -> None:
        self.planner = planner
        self.prefer = prefer
        self.graph = graph
        self.unavailable = unavailable
        self.measurements = measurements  # by manager
        self.load = load
        self.running = running
        n = len(graph.required)
        self.best_cost: list[tuple[int, int, int] | None] = [None] * n
        self.best_depth = [0] * n
        self.best_option: list[_Option | None] = [None] * n
        self.rejected: dict[int, str] = {}  # spec option id -> why
        self.running_options: list[list[tuple[_Option, str | None]]] = [[] for _ in range(n)]
        if running:
            self._match_running()

    def _match_running(self) -> None:
        planner = self.planner
        by_key: dict[str, list[tuple[RunningUnit, str, tuple[Term, ...]]]] = {}
        for unit in sorted(self.running, key=lambda u: u.ref):
            for port, tags in sorted(unit.tags.items()):
                terms = tuple(parse_term(t) for t in tags)
                for term in terms:
                    by_key.setdefault(planner._functor_key(term.functor), []).append((unit, port, terms))
        for r, required in enumerate(self.graph.required):
            keys = planner._functor_keys(required[0].functor)
            seen = set()
            for key in sorted(keys & by_key.keys()):
                for unit, port, terms in by_key[key]:
                    if (unit.ref, port) in seen or not planner._satisfies(terms, required):
                        continue
                    seen.add((unit.ref, port))
                    reason = None
                    label = unit.label if unit.manager is None else qualify(unit.label, unit.manager)
                    if not unit.healthy:
                        reason = "failed or stalled"
                    elif label in self.unavailable:
                        reason = f"unavailable ({label} is excluded)"
                    self.running_options[r].append((_Option(unit.ref, port, False, manager=unit.manager or planner.manager), reason))

    def _why_not(self, option: _Option) -> str | None:
        if option.unit in self.unavailable:
            return "unavailable"
        measured = self.measurements.get(option.manager, {})
        # a running unit, or a transformation of the request's configuration, keeps a constraint's margin (hysteresis)
        held = not option.new or option.unit in self.prefer or qualify(option.unit, option.manager) in self.prefer
        for c in option.constraints:
            value = measured.get(c.measure)
            if value is not None and not c.holds(value, held=held):
                return f"constraint violated: {c.measure} = {value!r}, needs {c.op} {c.value!r}"
        return None

    def settled(self, r: int) -> bool:
        return self.best_cost[r] is not None

    def settle(self) -> None:
        graph = self.graph
        max_depth = self.planner.max_depth
        best_cost, best_depth, best_option = self.best_cost, self.best_depth, self.best_option
        heap: list[tuple[tuple[int, int, int], int, bool, str, str, int, int, int, _Option]] = []
        pending = list(graph.distinct_needs)
        serial = itertools.count()
        home = self.planner.manager
        load = self.load
        prefer = self.prefer

        def push(o: int) -> None:
            option = graph.options[o]
            if option.manager == home:
                placement = 0
            else:  # another manager: better if it runs one of the inputs
                placement = 1 if any(best_option[r].manager == option.manager for r in graph.needs[o]) else 2  # type: ignore[union-attr]
            cost_new, cost_priority, cost_place, depth = 1, option.priority, placement, 1
            for r in graph.needs[o]:
                (n, p, q), d = best_cost[r], best_depth[r]  # type: ignore[misc]
                cost_new, cost_priority, cost_place, depth = cost_new + n, cost_priority + p, cost_place + q, max(depth, d + 1)
            if depth > max_depth:
                self.rejected[o] = f"depth limit ({max_depth} transformations deep)"
                return
            cost = (cost_new, cost_priority, cost_place)
            busy = load.get(option.manager, 0)
            preferred = option.unit in prefer
            if preferred:  # hysteresis: the request's present provider keeps it unless another is clearly less loaded
                busy -= load_margin(busy)
            heapq.heappush(
                heap, (cost, busy, not preferred, option.unit, option.port, next(serial), graph.provides[o], depth, option)
            )

        for o, option in enumerate(graph.options):
            reason = self._why_not(option)
            if reason is not None:
                self.rejected[o] = reason
            elif not graph.needs[o]:
                push(o)
        for r, options in enumerate(self.running_options):
            for option, reason in options:
                if reason is None:
                    heapq.heappush(heap, ((0, 0, 0), 0, False, option.unit, option.port, next(serial), r, 0, option))
        while heap:
            cost, _, _, _, _, _, r, depth, option = heapq.heappop(heap)
            if best_cost[r] is not None:
                continue
            best_cost[r], best_depth[r], best_option[r] = cost, depth, option
            for o in graph.waiting[r]:
                pending[o] -= 1
                if pending[o] == 0 and o not in self.rejected and best_cost[graph.provides[o]] is None:
                    push(o)

    def config(self) -> _Config:
        """The chosen configuration for the (settled) request."""
        graph = self.graph
        new: dict[str, dict[str, _Source]] = {}
        reused: set[str] = set()
        priority = 0

        def source(r: int) -> _Source:
            nonlocal priority
            option = self.best_option[r]
            assert option is not None
            if not option.new:
                reused.add(option.unit)
                return _Source(False, option.unit, option.port)
            if option.unit not in new:
                new[option.unit] = {}
                priority += option.priority
                new[option.unit] = {port: source(graph.ids[needed]) for port, needed in option.inputs}
            return _Source(True, option.unit, option.port)

        output = source(0)
        return _Config(output, new, frozenset(reused), priority)

    def explain(self) -> Rejection:
        """Why nothing provides the request: every option and why it was rejected.

        Each tag is explained once (later mentions refer to it), so even a large library gives a
        short answer; an input that leads back to a tag being explained is reported as a cycle.
        """
        graph = self.graph
        explained: dict[int, Rejection] = {}
        stack: list[tuple[int, str]] = []  # required ids being explained, and the unit that led on

        def tag_of(r: int) -> str:
            return " & ".join(str(t) for t in graph.required[r])

        def why(r: int) -> Rejection:
            alternatives = []
            for option, reason in self.running_options[r]:
                if reason is not None:
                    alternatives.append(Alternative(f"unit {option.unit}", option.port, reason))
            for o in graph.spec_options[r]:
                option = graph.options[o]
                if o in self.rejected:
                    alternatives.append(Alternative(option.unit, option.port, self.rejected[o]))
                    continue
                for (port, _), needed in zip(option.inputs, graph.needs[o], strict=True):
                    if self.settled(needed):
                        continue
                    on_stack = [i for i, (x, _) in enumerate(stack) if x == needed]
                    if on_stack or needed == r:
                        units = [*(u for _, u in stack[on_stack[0] :]), option.unit] if on_stack else [option.unit]
                        alternatives.append(Alternative(option.unit, option.port, "cycle: " + " -> ".join([*units, units[0]])))
                    else:
                        if needed not in explained:
                            stack.append((r, option.unit))
                            explained[needed] = why(needed)
                            stack.pop()
                        alternatives.append(
                            Alternative(option.unit, option.port, f"input {port!r} needs {tag_of(needed)}", explained[needed])
                        )
                    break
            if not alternatives:
                return Rejection(tag_of(r), (), self.planner.close_tags(tag_of(r), self.running))
            return Rejection(tag_of(r), tuple(alternatives))

        return why(0)


def _materialize(
    request: str,
    config: _Config,
    specs: Mapping[str, TransformationSpec],
    placement: Mapping[str, str],
    running: Mapping[str, RunningUnit],
    names_taken: tuple[Callable[[str, str], bool], Callable[[str, str], None]],
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
    names: dict[str, str] = {}  # ref -> name on its manager
    taken, take = names_taken
    for ref in needed:
        where = placement[ref]
        base = unit_name_for(specs[ref].label)
        name, n = base, 1
        while taken(name, where):
            n += 1
            name = f"{base}-{n}"
        take(name, where)
        names[ref] = name

    def key_of(source: _Source) -> str:
        if source.new:
            return default_key(placement[source.unit], names[source.unit], source.port)
        return running[source.unit].outputs[source.port]

    def name_of(source: _Source) -> str:
        if not source.new:
            return source.unit
        where = placement[source.unit]
        return names[source.unit] if where == manager else qualify(names[source.unit], where)

    units: list[PlannedUnit] = []
    for ref in sorted(reused):
        unit = running[ref]
        where = unit.manager or manager
        units.append(PlannedUnit(unit.name, unit.label, False, dict(unit.outputs), where, where != manager))
    connections: list[Connection] = []
    for ref in needed:
        spec = specs[ref]
        name = names[ref]
        where = placement[ref]
        bindings = {p.name: default_key(where, name, p.name) for p in spec.ports}
        for port, upstream in sorted(config.new[ref].items()):
            bindings[port] = key_of(upstream)
            connections.append(
                Connection(f"{name_of(upstream)}.{upstream.port}", f"{name_of(_Source(True, ref, port))}.{port}", key_of(upstream))
            )
        units.append(PlannedUnit(name, spec.label, True, bindings, where, where != manager))
    out = config.output
    new_labels = tuple(sorted(needed))
    priority = sum(specs[ref].priority for ref in needed)
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
    peers: Mapping[str, Iterable[TransformationSpec]] | None = None,
    peer_measurements: Mapping[str, Mapping[str, float | str]] | None = None,
    load: Mapping[str, int] | None = None,
    prefer: Collection[str] = (),
) -> Plan:
    """Plan once (see :class:`Planner` to plan repeatedly over the same libraries)."""
    return Planner(library, ontology, manager=manager, max_depth=max_depth, peers=peers).plan(
        request_tag, running_model, unavailable, measurements, peer_measurements=peer_measurements, load=load, prefer=prefer
    )
