"""The P and E of MAPE-K: the :class:`Reconfigurer` plans a request's configuration (failed,
unavailable and stalled transformations excluded, and those its requirements found false; the
request's own units set aside so that preferences decide, its present configuration winning ties)
and moves the running system to it changing little: kept units rebound, new ones spawned consumers
first, the anchor rebound, what nothing uses destroyed last. It also plans and builds the warm
standby, and the trial of a suspect transformation in the shadow.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from dyknow import keys
from dyknow.adaptation.anchor import ANCHOR_LABEL
from dyknow.adaptation.index import RunningIndex
from dyknow.adaptation.knowledge import Knowledge, Request, Trial, runs_on
from dyknow.adaptation.runtime import Runtime
from dyknow.errors import DyKnowError, PlanningError, ServiceError, UnitError
from dyknow.planner import Plan, PlannedUnit, Planner, RunningUnit, qualify, unqualify
from dyknow.spec.model import MODE_UNIT_SOURCE

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs

_DISCOVERY_ROUNDS = 16  # libraries read one after the other for a plan (a chain of 16 managers)

#: What a call on another manager that failed says when that manager is no longer there
#: (``details["reason"]``, :mod:`dyknow.client`): the link closed during the call, its liveliness
#: token went, it is remembered lost, or it is not among the managers up.
_WENT = frozenset({"link-closed", "gone", "lost", "absent", "no-such-manager"})


class Interrupted(ServiceError):
    """Building a configuration stopped because ``manager`` went away during a call on it (its
    link closed, its liveliness token went): what was built is undone, and the manager's loss is
    on its way to the loop. The message and fields are the failed call's."""

    def __init__(self, manager: str, error: ServiceError) -> None:
        super().__init__(error.what, error.kind, error.details, where=error.where, expected=error.expected)
        self.manager = manager


MAX_START_FAILURES = 8
"""How many providers that fail at start one request or adaptation tries before it gives up."""


class StartFailed(UnitError):
    """A unit of a new configuration failed at start (its ``setup()`` raised: a managed ROS 2
    node that refused a transition or a parameter, say). Its transformation ``label`` is in
    back-off from then on, as for a unit that fails while it runs, so the next plan takes another
    provider; what was built is undone."""

    def __init__(self, label: str, what: str, *, where: str) -> None:
        super().__init__(what, where=where)
        self.label = label


@contextmanager
def _calling(manager: str) -> Iterator[None]:
    """A call on another manager: its failure as that manager went away is :class:`Interrupted`."""
    try:
        yield
    except ServiceError as exc:
        if exc.kind is None and exc.details.get("reason") in _WENT:
            raise Interrupted(manager, exc) from exc
        raise


# ---------------------------------------------------------------------------- plan and execute


@dataclass(slots=True)
class _Built:
    """What :meth:`Reconfigurer.build` did: the configuration's units, its output key, and what to undo."""

    units: dict[str, str] = field(default_factory=dict)  # unit -> label, as a request records them
    output_key: str = ""
    spawned: list[str] = field(default_factory=list)
    rebound: list[tuple[str, dict[str, str]]] = field(default_factory=list)  # (unit, its bindings before)


class Reconfigurer:
    """Plans a request's configuration and moves the running system to it, changing little.

    Units of other managers (known from their summaries) are reused by key like local ones; new
    ones are spawned through their manager's spawn service and tracked as ``name@manager``.
    """

    def __init__(self, runtime: Runtime, knowledge: Knowledge) -> None:
        self._runtime = runtime
        self._knowledge = knowledge
        self._planner: Planner | None = None
        self._planner_version: tuple[Any, ...] = ()
        self._constraints: list[tuple[str, tuple[Any, ...]]] = []
        self._constraints_version: Any = None
        self.index = RunningIndex(runtime)  # what runs here, by tag and by key (refreshed before each use)

    def _local(self) -> RunningIndex:
        """The index of this manager's units, brought up to date."""
        self.index.refresh()
        return self.index

    def planner(self) -> Planner:
        """The planner over the current libraries (rebuilt when one of them or the ontology changed)."""
        runtime = self._runtime
        peers = runtime.peers()
        version = (runtime.library.version, id(runtime.ontology), tuple(sorted((m, s.library) for m, s in peers.items())))
        if self._planner is None or self._planner_version != version:
            self._planner = Planner(
                runtime.library.specs(), runtime.ontology, manager=runtime.name, peers={m: s.specs for m, s in peers.items()}
            )
            self._planner_version = version
        return self._planner

    def discover(self, tag: str) -> None:
        """Follow the managers that offer what ``tag`` could need: the tags of its graph over
        the libraries known, asked for (one query per tag not asked about yet) until no new
        library brings a new tag. A plan then weighs its candidate providers, not the fleet."""
        for _ in range(_DISCOVERY_ROUNDS):
            if not self._runtime.discover(self.planner().running_keys(tag), need=tag):
                return

    def running_model(self, request: Request | None) -> tuple[list[RunningUnit], Collection[str]]:
        """Units the plan may reuse (the request's own set aside) and every name in use.

        Names of units on other managers are ``name@manager``. Units another manager spawned
        for its own requests are not reused: that manager takes them down when it likes. With a
        request, only the local units whose tags could serve it are looked at (the index), so
        the cost does not grow with the units running; the names are then a live view.
        """
        knowledge = self._knowledge
        own = self._own(request)
        running: list[RunningUnit] = []
        index = self._local()
        local = index.serving(self.planner().running_keys(request.tag)) if request is not None else list(index.units.values())
        for info in local:
            if info.name in own or info.label == ANCHOR_LABEL or info.spec is None or knowledge.standing_by(info.name):
                continue
            outputs = {p.name: info.bindings[p.name] for p in info.spec.outputs}
            tags = {p.name: info.spec.tags_for(p.name) for p in info.spec.outputs}
            healthy = info.alive and info.name not in knowledge.stalled
            running.append(RunningUnit(info.name, info.label, outputs, tags, healthy))
        home = self._runtime.name
        names = _Names(index.units)
        for manager, summary in sorted(self._runtime.peers().items()):
            for unit in summary.units:
                ref = qualify(unit.name, manager)
                names.add(ref)
                if ref in own or (unit.owner is not None and unit.owner != home) or knowledge.standing_by(ref):
                    continue
                if unit.owner == home and ref not in knowledge.remote:
                    continue  # ours, but already destroyed (the summary is older) or left by an earlier run

                running.append(unit.running(manager))
        # spawned, maybe not in a summary yet; one its manager's summary no longer shows is gone
        # (destroyed there as that manager lost this one, say), and its name free for its successor
        names.update(ref for ref in knowledge.remote if ref not in knowledge.seen)
        return running, names

    def _own(self, request: Request | None) -> set[str]:
        """The units only ``request`` holds (its configuration, standby and spare units)."""
        knowledge = self._knowledge
        if request is None:
            return set()
        return {u for u in request.held() if u in knowledge.managed and all(r is request for r in knowledge.users(u))}

    def load(self, request: Request | None = None) -> dict[str, int]:
        """Units per manager, as the planner weighs them for ``request``: what each runs (this
        manager's units, the others' from their summaries, plus what this manager spawned there
        that their summaries do not show yet), without the units only ``request`` holds. A
        configuration is never judged worse for carrying the request it serves."""
        runtime = self._runtime
        home = runtime.name
        own = self._own(request)
        local = self._local().units  # the index: no walk over every unit
        load = {home: len(local) - sum(1 for name in own if name in local)}
        for manager, summary in runtime.peers().items():
            shown = {qualify(unit.name, manager) for unit in summary.units}
            pending = sum(1 for ref in self._knowledge.remote if runs_on(ref, manager) and ref not in shown and ref not in self._knowledge.seen)
            load[manager] = summary.load - len(shown & own) + pending
        return load

    def plan(
        self,
        request: Request,
        now_ns: int,
        *,
        exclude: Collection[str] = (),
        avoid: Collection[str] = (),
        managers_excluded: Collection[str] = (),
        trying: Collection[str] = (),
    ) -> Plan:
        """The preferred configuration for ``request`` now (:class:`PlanningError` when none).

        ``exclude``: transformations not to use besides those in back-off or stalled, and the
        request's suspects (those its requirements found false) other than ``trying``; ``avoid``:
        running units not to reuse (besides the request's own, which are always set aside);
        ``managers_excluded``: other managers none of whose transformations or units to use,
        except those the request already uses there.

        The request's configuration (and its standby's) is preferred: another of equal cost
        replaces it only when its manager carries clearly fewer units (:func:`~dyknow.planner.load_margin`),
        the request's own units not counted (:meth:`load`), so an opportunity moves a request for
        a strict improvement, never for a tie.
        """
        self.discover(request.tag)
        running, names = self.running_model(request)
        peers = self._runtime.peers()
        kept = set(request.units)
        if avoid:
            running = [u for u in running if u.ref not in avoid]
        if managers_excluded:
            running = [u for u in running if u.ref in kept or not any(runs_on(u.ref, m) for m in managers_excluded)]
        unavailable = self._knowledge.unavailable(now_ns) | set(exclude) | (set(request.suspects) - set(trying))
        used = set(request.units.values())
        for manager in managers_excluded:
            summary = peers.get(manager)
            if summary is not None:
                unavailable |= {qualify(spec.label, manager) for spec in summary.specs} - used
        units = self._local().units
        stalled_labels = {units[n].label for n in self._knowledge.stalled if n in units}
        return self.planner().plan(
            request.tag,
            running,
            unavailable | stalled_labels,
            self._knowledge.measurements,
            reserved_names=names,
            peer_measurements={m: s.measurements for m, s in peers.items()},
            load=self.load(request),
            prefer={*request.units.values(), *request.standby.values()},
        )

    def apply(self, request: Request, plan: Plan, before_switch: Callable[[str], None] | None = None) -> list[str]:
        """Make ``plan`` run for ``request``; returns units to destroy once the switch is done.

        ``before_switch(output_key)`` runs right before the anchor is rebound to the new output.
        """
        knowledge = self._knowledge
        # keep the request's own healthy units that the new configuration needs (same label, same manager)
        own_by_label: dict[str, str] = {}
        for ref, label in request.units.items():
            if ref in knowledge.managed and self._healthy(ref):
                own_by_label.setdefault(label, ref)
        built = self.build(plan, own_by_label)
        try:
            if before_switch is not None:
                before_switch(built.output_key)
            if self._runtime.get_config(request.anchor)["in"] != built.output_key:
                self._runtime.set_config(request.anchor, {"in": built.output_key})
        except DyKnowError:
            self.undo(built)
            raise
        old = request.units
        request.units = built.units
        request.plan = plan
        request.output_key = built.output_key
        request.state = "active"
        request.reason = None
        request.in_place = False
        return [n for n in old if n not in built.units and n in knowledge.managed and not knowledge.users(n)]

    def build(self, plan: Plan, pool: Mapping[str, str]) -> _Built:
        """Spawn and rebind so that ``plan`` runs, keeping units of ``pool`` (label -> unit) for
        planned units of the same label; consumers are spawned before producers. On a failure
        what was done is undone and the error raised."""
        runtime = self._runtime
        knowledge = self._knowledge
        home = runtime.name
        pool = dict(pool)
        rename: dict[str, str] = {}  # planned unit -> the kept unit (refs)
        for unit in plan.new_units:
            if _label_ref(unit) in pool:
                rename[unit.ref] = pool.pop(_label_ref(unit))

        def key(k: str) -> str:
            # keys of planned units that are kept: the kept unit's actual output key
            for planned, actual in rename.items():
                name, manager = unqualify(planned, home)
                prefix = keys.unit_prefix(manager, name)
                if k.startswith(prefix):
                    return self._config(actual)[k[len(prefix) :]]
            return k

        built = _Built()
        try:
            for unit in reversed(plan.new_units):  # consumers first: nothing a producer sends is lost
                if unit.ref in rename:
                    actual = rename[unit.ref]
                    spec = self.planner().spec(_label_ref(unit))
                    wanted = {p.name: key(unit.bindings[p.name]) for p in spec.inputs if spec.tags_for(p.name)}
                    current = self._config(actual)
                    changed = {p: k for p, k in wanted.items() if current[p] != k}
                    if changed:
                        built.rebound.append((actual, {p: current[p] for p in changed}))
                        with _calling(unqualify(actual, home)[1]):
                            self._set_config(actual, changed)
                    built.units[actual] = _label_ref(unit)
                else:
                    bindings = {p: key(k) for p, k in unit.bindings.items()}
                    if unit.remote:
                        knowledge.remote[unit.ref] = bindings
                        knowledge.managed.add(unit.ref)
                        knowledge.seen.discard(unit.ref)  # a new unit under a name used before: in no summary yet
                        built.spawned.append(unit.ref)
                        with _calling(unit.manager):
                            runtime.spawn_on(unit.manager, unit.label, unit.name, bindings=bindings)
                    else:
                        info = runtime.spawn(unit.label, unit.name, bindings=bindings)
                        built.spawned.append(unit.name)
                        knowledge.managed.add(unit.name)
                        if info.state == "failed":
                            knowledge.fail(_label_ref(unit), time.time_ns())
                            raise StartFailed(_label_ref(unit), f"failed at start: {info.error}", where=f"unit {unit.name!r} ({unit.label})")
                    built.units[unit.ref] = _label_ref(unit)
            for unit in plan.units:
                if not unit.new:
                    built.units[unit.ref] = _label_ref(unit)
            built.units.update(self._upstream(u.name for u in plan.units if not u.new and not u.remote))
            built.output_key = key(plan.output_key)
        except DyKnowError:
            self.undo(built)
            raise
        return built

    def undo(self, built: _Built) -> None:
        """Take back what :meth:`build` did: destroy what it spawned, rebind the kept units as they were."""
        self.cleanup(built.spawned)  # leave nothing half-built behind, and the kept units as they were
        for ref, before in reversed(built.rebound):
            try:
                self._set_config(ref, before)
            except DyKnowError as exc:
                log.warning("could not rebind unit %r back after a failed adaptation: %s", ref, exc)

    # -- the warm standby

    def standby_ready(self, request: Request, now_ns: int) -> bool:
        """Whether the request's warm standby can take over now: all its units healthy, none of its
        transformations in back-off or against the latest measurements."""
        if not request.standby or request.standby_key is None:
            return False
        unavailable = self._knowledge.unavailable(now_ns)
        local = self._local().units
        for ref, label in request.standby.items():
            name, manager = unqualify(ref, self._runtime.name)
            if manager == self._runtime.name:
                info = local.get(name)
                if info is None or not info.alive or name in self._knowledge.stalled:
                    return False
            elif not self._healthy(ref):
                return False
            if label in unavailable or label in request.suspects or self.violated(label):
                return False
        return True

    def violated(self, label: str) -> bool:
        """Whether the latest measurements break a constraint of transformation ``label``, which
        runs (so its constraints keep their margins) (``label@manager``: that manager's
        measurements and spec, from its summary)."""
        name, manager = unqualify(label, self._runtime.name)
        if manager == self._runtime.name:
            library = self._runtime.library
            spec = library.get(name) if name in library else None
            measurements: Mapping[str, float | str] = self._knowledge.measurements
        else:
            summary = self._runtime.peers().get(manager)
            spec = next((s for s in summary.specs if s.label == name), None) if summary is not None else None
            measurements = summary.measurements if summary is not None else {}
        for c in spec.constraints if spec is not None else ():
            value = measurements.get(c.measure)
            if value is not None and not c.holds(value, held=True):
                return True
        return False

    def labels(self, plan: Plan) -> set[str]:
        """Every transformation a plan runs on: its units' and, for running units it reuses, those
        that feed them (as a request records its configuration)."""
        found = {_label_ref(u) for u in plan.units}
        found.update(self._upstream(u.name for u in plan.units if not u.new and not u.remote).values())
        return found

    def plan_standby(self, request: Request, now_ns: int) -> Plan:
        """The configuration ``request`` would run if its active one could not: planned with each
        transformation of the active configuration that something else can replace excluded, and
        none of the active configuration's units (nor anything they feed) reused. When excluding
        them all leaves nothing, the replacement of one of them that shares the fewest
        transformations with the active configuration. :class:`PlanningError` when there is none.
        """
        avoid = self._downstream(request.units)
        active = sorted(set(request.units.values()))
        library = self._runtime.library
        modes = [label for label in active if label in library and library.get(label).source == MODE_UNIT_SOURCE]
        if modes:  # a standby mode would switch the system's nodes beside the active mode
            raise PlanningError(request.tag, None, f"no standby for {request.tag}: {modes[0]} is a system's mode, and two modes of one system cannot run at once")
        alone: dict[str, Plan] = {}  # label -> the plan without it
        for label in active:
            try:
                alone[label] = self.plan(request, now_ns, exclude={label}, avoid=avoid)
            except PlanningError:
                continue
        if not alone:
            raise PlanningError(
                request.tag, None, f"no standby for {request.tag}: nothing provides it without one of {', '.join(active) or 'its units'}"
            )
        try:
            return self.plan(request, now_ns, exclude=set(alone), avoid=avoid)
        except PlanningError:
            shared = set(active)
            return min(alone.values(), key=lambda p: (len(shared & {_label_ref(u) for u in p.units}), p.cost))

    def wire_standby(self, request: Request, plan: Plan) -> list[str]:
        """Make ``plan`` the request's warm standby, keeping its standby's and spare units of the
        same transformations, and point the anchor's ``standby`` port at it; returns the units
        nothing holds any more (to destroy)."""
        knowledge = self._knowledge
        pool: dict[str, str] = {}
        for ref, label in [*request.standby.items(), *request.spare.items()]:
            if ref in knowledge.managed and self._healthy(ref):
                pool.setdefault(label, ref)
        built = self.build(plan, pool)
        try:
            if self._runtime.get_config(request.anchor).get("standby") != built.output_key:
                self._runtime.set_config(request.anchor, {"standby": built.output_key})
        except DyKnowError:
            self.undo(built)
            raise
        old = [*request.standby, *request.spare]
        request.standby, request.standby_plan, request.standby_key = built.units, plan, built.output_key
        request.spare = {}
        return [n for n in old if n not in built.units and n in knowledge.managed and not knowledge.users(n)]

    def drop_standby(self, request: Request) -> list[str]:
        """The request stands by with nothing: the anchor's ``standby`` port goes idle; returns
        the units nothing holds any more (to destroy)."""
        knowledge = self._knowledge
        if request.standby and self._runtime.has_unit(request.anchor):
            try:
                self._runtime.set_config(request.anchor, {"standby": self.idle_key(request)})
            except DyKnowError as exc:
                log.warning("could not unbind the standby of %s: %s", request.tag, exc)
        old = [*request.standby, *request.spare]
        request.standby, request.standby_plan, request.standby_key = {}, None, None
        request.spare = {}
        return [n for n in old if n in knowledge.managed and not knowledge.users(n)]

    def promote(self, request: Request, before_switch: Callable[[str], None] | None = None) -> list[str]:
        """Switch ``request`` onto its warm standby: only the anchor moves (its ``standby`` port
        goes idle until the next standby). Returns the units of the configuration it left that
        nothing holds any more."""
        knowledge = self._knowledge
        assert request.standby_key is not None
        if before_switch is not None:
            before_switch(request.standby_key)
        self._runtime.set_config(request.anchor, {"in": request.standby_key, "standby": self.idle_key(request)})
        old = request.units
        request.units, request.plan, request.output_key = request.standby, request.standby_plan, request.standby_key
        request.standby, request.standby_plan, request.standby_key = {}, None, None
        request.state = "active"
        request.reason = None
        request.in_place = False
        return [n for n in old if n not in request.units and n in knowledge.managed and not knowledge.users(n)]

    # -- a suspect's trial in the shadow

    def wire_trial(self, request: Request, plan: Plan, label: str, serial: int, now_ns: int) -> Trial:
        """Run ``plan`` (the configuration the request would prefer with its suspect ``label``)
        beside the active one, reusing nothing the request holds; the anchor does not see it."""
        built = self.build(plan, {})
        return Trial(serial, label, plan, built.units, built.output_key, now_ns)

    def drop_trial(self, request: Request) -> list[str]:
        """The request's trial ends: returns its units nothing else holds (to destroy, with its monitors)."""
        trial, request.trial = request.trial, None
        if trial is None:
            return []
        knowledge = self._knowledge
        return [n for n in trial.units if n in knowledge.managed and not knowledge.users(n)]

    def promote_trial(self, request: Request, before_switch: Callable[[str], None] | None = None) -> list[str]:
        """Switch ``request`` onto its trial's configuration (it held): only the anchor moves.
        Returns the units of the configuration it left that nothing holds any more."""
        knowledge = self._knowledge
        trial = request.trial
        assert trial is not None
        if before_switch is not None:
            before_switch(trial.output_key)
        self._runtime.set_config(request.anchor, {"in": trial.output_key})
        old = request.units
        request.units, request.plan, request.output_key, request.trial = trial.units, trial.plan, trial.output_key, None
        request.state, request.reason, request.in_place = "active", None, False
        return [n for n in old if n not in request.units and n in knowledge.managed and not knowledge.users(n)]

    def idle_key(self, request: Request) -> str:
        """Where an anchor's ``standby`` port listens while there is no standby (nothing publishes there)."""
        return keys.default_key(self._runtime.name, request.anchor, "standby")

    def standby_inputs(self, request: Request, now_ns: int) -> tuple[Any, ...]:
        """What planning the request's standby depends on: the libraries, back-offs and stalls,
        which constraints hold, the units running and the request's own configurations. The same
        inputs give the same standby, so it is not planned again."""
        runtime = self._runtime
        self.planner()
        holds = []
        for label, constraints in self._constrained():
            for c in constraints:
                value = self._knowledge.measurements.get(c.measure)
                holds.append((label, value is None or c.holds(value), value is None or c.holds(value, held=True)))
        return (
            self._planner_version,
            frozenset(self._knowledge.unavailable(now_ns)),
            frozenset(self._knowledge.stalled),
            tuple(holds),
            frozenset((info.name, info.alive) for info in self._local().units.values()),
            tuple(sorted((m, s.version, s.library) for m, s in runtime.peers().items())),
            tuple(sorted(request.units.items())),
            tuple(sorted(request.standby.items())),
        )

    def _constrained(self) -> list[tuple[str, tuple[Any, ...]]]:
        library = self._runtime.library
        if self._constraints_version != library.version:
            self._constraints = [(s.label, s.constraints) for s in library.specs() if s.constraints]
            self._constraints_version = library.version
        return self._constraints

    def _downstream(self, refs: Iterable[str]) -> set[str]:
        """The given units and every local unit they feed, transitively (anchors aside)."""
        index = self._local()
        units = index.units
        found = set(refs)
        todo = [r for r in found if r in units and units[r].spec is not None and units[r].label != ANCHOR_LABEL]
        while todo:
            info = units[todo.pop()]
            assert info.spec is not None
            for port in info.spec.outputs:
                for reader in index.readers(info.bindings[port.name]):
                    if reader.name not in found and reader.spec is not None and reader.label != ANCHOR_LABEL:
                        found.add(reader.name)
                        todo.append(reader.name)
        return found

    def _healthy(self, ref: str) -> bool:
        name, manager = unqualify(ref, self._runtime.name)
        if manager == self._runtime.name:
            info = self._local().units.get(name)
            return info is not None and info.alive and name not in self._knowledge.stalled
        summary = self._runtime.peers().get(manager)
        if summary is None:
            return False
        for unit in summary.units:
            if unit.name == name:
                return unit.healthy
        return ref not in self._knowledge.seen  # spawned and not in a summary yet

    def config(self, ref: str) -> dict[str, str]:
        """The bindings (port -> key) of the unit ``ref``, here or on another manager."""
        return self._config(ref)

    def _config(self, ref: str) -> dict[str, str]:
        name, manager = unqualify(ref, self._runtime.name)
        if manager == self._runtime.name:
            return self._runtime.get_config(name)
        return dict(self._knowledge.remote[ref])

    def _set_config(self, ref: str, bindings: Mapping[str, str]) -> None:
        name, manager = unqualify(ref, self._runtime.name)
        if manager == self._runtime.name:
            self._runtime.set_config(name, bindings)
        else:
            self._runtime.set_config_on(manager, name, bindings)
            self._knowledge.remote[ref].update(bindings)

    def _upstream(self, names: Iterable[str]) -> dict[str, str]:
        """Every running unit that feeds the given ones, transitively: a reused unit needs them."""
        index = self._local()
        units = index.units
        found: dict[str, str] = {}
        todo = [n for n in names if n in units and units[n].spec is not None]
        while todo:
            info = units[todo.pop()]
            assert info.spec is not None
            for port in info.spec.inputs:
                for producer in index.producers(info.bindings[port.name]):
                    if producer.name not in found and producer.label != ANCHOR_LABEL and producer.spec is not None:
                        found[producer.name] = producer.label
                        todo.append(producer.name)
        return found

    def cleanup(self, names: Iterable[str]) -> None:
        """Destroy the given units (those the loop spawned, here or elsewhere) and forget them."""
        home = self._runtime.name
        for ref in names:
            name, manager = unqualify(ref, home)
            try:
                if manager == home:
                    if self._runtime.has_unit(name):
                        self._runtime.destroy(name)
                elif manager in self._runtime.peers():  # a lost manager took its units with it
                    self._runtime.destroy_on(manager, name)
            except DyKnowError as exc:
                # replaced already, or lost with its manager (however the call said it went): as it should be
                gone = (isinstance(exc, UnitError) and "no unit named" in exc.what) or (
                    isinstance(exc, ServiceError) and exc.kind is None and exc.details.get("reason") in _WENT
                )
                log.log(logging.DEBUG if gone else logging.WARNING, "could not destroy unit %r after an adaptation: %s", ref, exc)
            self._knowledge.managed.discard(ref)
            self._knowledge.stalled.discard(ref)
            self._knowledge.remote.pop(ref, None)
            self._knowledge.seen.discard(ref)


def is_current(request: Request, plan: Plan) -> bool:
    """Whether the request already runs this configuration (same labels and reused units)."""
    current = sorted(request.units.values())
    return current == sorted(_label_ref(u) for u in plan.units)


def _label_ref(unit: PlannedUnit) -> str:
    """A planned unit's transformation as the request records it: ``label``, or ``label@manager``."""
    return qualify(unit.label, unit.manager) if unit.remote else unit.label


class _Names(Collection[str]):
    """Every unit name in use, for the planner's choice of new names: the local units (a live
    view of the index) and those of other managers (``name@manager``)."""

    def __init__(self, local: Mapping[str, object]) -> None:
        self._local = local
        self._elsewhere: set[str] = set()

    def add(self, ref: str) -> None:
        self._elsewhere.add(ref)

    def update(self, refs: Iterable[str]) -> None:
        self._elsewhere.update(refs)

    def __contains__(self, ref: object) -> bool:
        return ref in self._local or ref in self._elsewhere

    def __iter__(self) -> Iterator[str]:
        yield from self._local
        yield from self._elsewhere

    def __len__(self) -> int:
        return len(self._local) + len(self._elsewhere)
