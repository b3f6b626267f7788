"""The A of MAPE-K: the :class:`Analyzer` says which requests a symptom affects, and whether it is a
fault (the configuration is broken: adapt now) or an opportunity (a preferred configuration may be
available: adapt after the dwell time, which it keeps waiting until then).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

from dyknow.adaptation.knowledge import DEFAULT_DWELL_S, Knowledge, Request, runs_on
from dyknow.adaptation.monitor import Symptom
from dyknow.adaptation.runtime import Runtime
from dyknow.planner import unqualify

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs


# ---------------------------------------------------------------------------- analyzer


class Analyzer:
    """Which requests a symptom affects, and whether they must adapt now (fault) or may (opportunity).

    An opportunity within the dwell time of a request's last change waits (:meth:`wait`) until
    :meth:`due` hands it back.
    """

    def __init__(self, runtime: Runtime, knowledge: Knowledge, *, dwell_ns: int = int(DEFAULT_DWELL_S * 1e9)) -> None:
        self._runtime = runtime
        self._knowledge = knowledge
        self._dwell_ns = dwell_ns
        self._deferred: dict[str, tuple[int, Symptom]] = {}  # request key -> (when, the opportunity)

    def stale(self, symptom: Symptom) -> bool:
        """Whether a unit's failure or destruction is about an earlier unit of that name (one the
        loop replaced since): nothing to do."""
        name, time_ns = symptom.unit, symptom.time_ns
        return any(info.name == name and info.started_ns > time_ns for info in self._runtime.units())

    # -- the dwell time

    def wait(self, request: Request, symptom: Symptom, fault: bool, now_ns: int) -> bool:
        """Whether ``request`` must not adapt to ``symptom`` yet: an opportunity for an active
        request within the dwell time of its last change (the flapping guard). It is then kept
        for when the dwell time is over (the latest one wins, but another manager's routine
        summary does not hide the cause already waiting, nor does a routine measurement hide an
        ended back-off or probation; and a trial that held waits for its turn whatever comes
        meanwhile: taking it plans afresh)."""
        if fault or request.state != "active" or now_ns - request.last_change_ns >= self._dwell_ns:
            return False
        waiting = self._deferred.get(request.key)
        routine = (
            symptom.kind == "peer-changed"
            or (symptom.kind == "measurement" and waiting is not None and waiting[1].kind in ("retry", "peer-trusted"))
            or (waiting is not None and waiting[1].kind == "trial-held")
        )
        if waiting is None or not routine:
            self._deferred[request.key] = (request.last_change_ns + self._dwell_ns, symptom)
        return True

    def defer(self, key: str, due_ns: int, opportunity: Symptom) -> None:
        """Take ``opportunity`` for the request on ``key`` at ``due_ns``."""
        self._deferred[key] = (due_ns, opportunity)

    def forget(self, key: str) -> None:
        """The request on ``key`` is gone: nothing waits for it."""
        self._deferred.pop(key, None)

    def deferring(self) -> bool:
        """Whether an opportunity waits."""
        return bool(self._deferred)

    def due(self, now_ns: int) -> Iterator[tuple[str, Symptom]]:
        """The opportunities due by ``now_ns``, each taken off the waiting ones as it is handed
        back (the request's key, the opportunity as it arose)."""
        for key, (due, opportunity) in list(self._deferred.items()):
            if due <= now_ns:
                del self._deferred[key]
                yield key, opportunity

    # -- which requests

    def affected(self, symptom: Symptom) -> list[tuple[Request, bool]]:
        """``(request, is_fault)`` pairs, in a stable order; a degraded request is always among them."""
        found = self._affected(symptom)
        seen = {id(r) for r, _ in found}
        degraded = [
            (r, False)
            for r in sorted(self._knowledge.requests.values(), key=lambda r: r.key)
            if r.state == "degraded" and id(r) not in seen
        ]
        return found + degraded

    def _affected(self, symptom: Symptom) -> list[tuple[Request, bool]]:
        knowledge = self._knowledge
        requests = sorted(knowledge.requests.values(), key=lambda r: r.key)
        if symptom.kind in ("failed", "destroyed", "stalled"):
            return [(r, True) for r in requests if symptom.unit in r.units or symptom.unit == r.anchor]
        if symptom.kind == "measurement":
            out = []
            for r in requests:
                broken = any(
                    c.measure == symptom.measure and not c.holds(knowledge.measurements[c.measure], held=True)
                    for label in r.units.values()
                    for c in self._constraints(label)
                )
                out.append((r, broken))
            return out
        if symptom.kind == "peer-lost":  # (or a move onto it was interrupted: Adapter.adapt)
            return [(r, True) for r in requests if symptom.manager in r.interrupted or any(runs_on(ref, symptom.manager) for ref in r.units)]
        if symptom.kind == "peer-changed" and symptom.manager is not None:
            return [(r, bool(self.broken_on(r, symptom.manager))) for r in requests]
        return [(r, False) for r in requests]  # resumed, retry, library, peer-found: maybe better now

    def peer_changed(self, symptom: Symptom, manager: str) -> Iterator[tuple[Request, Symptom, bool]]:
        """Another manager's summary changed: ``(request, symptom, is_fault)`` for every request,
        by key, a fault for those it broke (the symptom's detail says how), else an opportunity.

        Lazy, one request after the other adapted: a unit found unhealthy there is recorded
        failed (in the knowledge) just before its own request is handed out.
        """
        if manager not in self._runtime.peers():
            # gone by the time the change is handled (its last summary, then its loss): the loss it is
            symptom = replace(symptom, kind="peer-lost")
        for request in sorted(self._knowledge.requests.values(), key=lambda r: r.key):
            broken = self.broken_on(request, manager)
            for ref, why in broken:
                if "unhealthy" in why:
                    self._knowledge.fail(request.units[ref], symptom.time_ns)
            detail = "; ".join(why for _, why in broken)
            if symptom.kind == "peer-lost":
                detail = ""  # the cause says it: "manager X was lost"
            yield request, (replace(symptom, detail=detail) if broken else symptom), bool(broken)

    def broken_on(self, request: Request, manager: str) -> list[tuple[str, str]]:
        """What breaks ``request`` on another manager, after its summary changed.

        ``(unit, why)`` pairs: a unit it uses there vanished (once seen), is unhealthy, or the
        manager's measurements break a constraint of its transformation.
        """
        summary = self._runtime.peers().get(manager)
        if summary is None:
            return [(ref, f"manager {manager!r} was lost") for ref in request.units if runs_on(ref, manager)]
        there = {u.name: u for u in summary.units}
        specs = {s.label: s for s in summary.specs}
        broken = []
        for ref, label in request.units.items():
            if not runs_on(ref, manager):
                continue
            name, _ = unqualify(ref, "")
            unit = there.get(name)
            if unit is None:
                if ref in self._knowledge.seen:
                    broken.append((ref, f"unit {ref!r} is gone"))
                continue
            self._knowledge.seen.add(ref)
            if not unit.healthy:
                broken.append((ref, f"unit {ref!r} is unhealthy (failed or stalled)"))
                continue
            spec = specs.get(unqualify(label, "")[0])
            for c in spec.constraints if spec is not None else ():
                value = summary.measurements.get(c.measure)
                if value is not None and not c.holds(value, held=True):
                    broken.append((ref, f"unit {ref!r}: measurement {c.measure} = {value!r} on manager {manager!r}"))
        return broken

    def _constraints(self, label: str) -> tuple[Any, ...]:
        library = self._runtime.library
        if "@" in label or label not in library:
            return ()  # another manager's measurements check its transformations (broken_on)
        return library.get(label).constraints
