"""The A of MAPE-K: the :class:`Analyzer` says which requests a symptom affects, and whether it is a
fault (the configuration is broken: adapt now) or an opportunity (a preferred configuration may be
available: adapt after the dwell time).
"""

from __future__ import annotations

import logging
from typing import Any

from dyknow.adaptation.knowledge import Knowledge, Request, runs_on
from dyknow.adaptation.monitor import Symptom
from dyknow.adaptation.runtime import Runtime
from dyknow.planner import unqualify

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs


# ---------------------------------------------------------------------------- analyzer


class Analyzer:
    """Which requests a symptom affects, and whether they must adapt now (fault) or may (opportunity)."""

    def __init__(self, runtime: Runtime, knowledge: Knowledge) -> None:
        self._runtime = runtime
        self._knowledge = knowledge

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
                    c.measure == symptom.measure and not c.holds(knowledge.measurements[c.measure])
                    for label in r.units.values()
                    for c in self._constraints(label)
                )
                out.append((r, broken))
            return out
        if symptom.kind == "peer-lost":
            return [(r, True) for r in requests if any(runs_on(ref, symptom.manager) for ref in r.units)]
        if symptom.kind == "peer-changed" and symptom.manager is not None:
            return [(r, bool(self.broken_on(r, symptom.manager))) for r in requests]
        return [(r, False) for r in requests]  # resumed, retry, library, peer-found: maybe better now

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
                if value is not None and not c.holds(value):
                    broken.append((ref, f"unit {ref!r}: measurement {c.measure} = {value!r} on manager {manager!r}"))
        return broken

    def _constraints(self, label: str) -> tuple[Any, ...]:
        library = self._runtime.library
        if "@" in label or label not in library:
            return ()  # another manager's measurements check its transformations (broken_on)
        return library.get(label).constraints
