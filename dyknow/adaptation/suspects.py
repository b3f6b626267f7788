"""Requirements that learn: :class:`Suspects` makes the transformation a false requirement points at
a suspect of its request, tries each suspect again in the shadow after its back-off and trusts it
once the requirements held there, and keeps a request that nothing else can serve running where it
is, degraded in place, until its requirements hold again.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

from dyknow.adaptation.damping import Penalty
from dyknow.adaptation.events import Journal, Recovery
from dyknow.adaptation.knowledge import BACKOFF_MAX_S, AdaptationEvent, Knowledge, Request, Suspect
from dyknow.adaptation.monitor import Judge, Symptom
from dyknow.adaptation.reconfigure import Reconfigurer, is_current
from dyknow.adaptation.requirements import Requirements
from dyknow.adaptation.runtime import Runtime
from dyknow.errors import DyKnowError, PlanningError
from dyknow.planner import Plan

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs


class Adapting(Protocol):
    """What the suspects need of the plan and execute step (:class:`~dyknow.adaptation.adapt.Adapter`)."""

    def adapt(self, request: Request, symptom: Symptom, fault: bool) -> None:
        """Adapt ``request`` to ``symptom`` (now when a fault, else after the dwell time)."""
        ...

    def adapted(
        self,
        request: Request,
        symptom: Symptom,
        cause: str,
        old_labels: tuple[str, ...],
        orphans: list[str],
        recovery: Recovery,
        *,
        standby: bool,
        fault: bool = False,
    ) -> int:
        """The new configuration is wired: record it; returns when it was wired (ns)."""
        ...


class Suspects:
    """The suspects of requests, their trials in the shadow, and requests degraded in place.

    A suspect is avoided by its request's plans (:meth:`Reconfigurer.plan` reads
    :attr:`Request.suspects`) until a trial shows the requirements hold on it.
    """

    def __init__(
        self,
        runtime: Runtime,
        knowledge: Knowledge,
        reconfigurer: Reconfigurer,
        requirements: Requirements,
        journal: Journal,
        adapting: Adapting,
        report: Callable[[Symptom], None],
        dwell_ns: int,
    ) -> None:
        self._runtime = runtime
        self._knowledge = knowledge
        self._reconfigurer = reconfigurer
        self._requirements = requirements
        self._journal = journal
        self._adapting = adapting
        self._report = report
        self._dwell_ns = dwell_ns
        # requests degraded in place: key -> (the judge of their requirements, the "degraded" event)
        self._in_place: dict[str, tuple[Judge, AdaptationEvent]] = {}

    def violated(self, symptom: Symptom) -> None:
        """A requirement was false: move the request to the next-best configuration.

        Not when the present configuration has run less than the dwell time (its first states
        are judged partly on what the one before delivered), nor when it is degraded. The next
        best is the cheapest plan without one of the present configuration's transformations;
        that transformation becomes a *suspect* of the request: its plans avoid it until a trial
        in the shadow shows the requirements hold on it (:meth:`judged`). When no configuration
        without one of them exists, the request runs on, degraded in place (:meth:`hold_in_place`)."""
        request = self._knowledge.requests.get(symptom.request or "")
        if request is None or request.state != "active" or symptom.state_ns < request.last_change_ns + self._dwell_ns:
            return
        now = time.time_ns()
        if symptom.unit is not None:  # a transformation's own requirement: that transformation goes
            label = request.units.get(symptom.unit)
            if label is None or label != symptom.label:
                return  # (the unit no longer serves the request: a verdict that was on its way)
            candidates = [label]
        else:
            candidates = sorted(set(request.units.values()))
        best: tuple[tuple[Any, ...], str] | None = None
        for label in candidates:
            try:
                plan = self._reconfigurer.plan(request, now, exclude={label})
            except PlanningError:
                continue
            if best is None or plan.cost < best[0]:
                best = (plan.cost, label)
        if best is None:
            old = tuple(sorted(set(request.units.values())))
            where = f" of {symptom.label}" if symptom.label is not None else ""
            self.hold_in_place(request, symptom, old, f"its requirement{where} {symptom.detail!r} is false, and no other configuration provides {request.tag}")
            return
        label = best[1]
        penalty = request.penalties.setdefault(label, Penalty(self._knowledge.flaps.trials))
        penalty.relapse(now)
        suspect = request.suspects[label] = Suspect(label, symptom.detail, now, penalty=penalty)
        _reschedule(suspect, now, failed=False)
        if penalty.suppressed:
            log.info(
                "%s relapsed for %s (%d times, penalty %.0f): no trial before %.0f s from now",
                label, request.tag, penalty.relapses, penalty.value(now), (suspect.next_trial_ns - now) / 1e9,
            )  # fmt: skip
        self._adapting.adapt(request, symptom, fault=True)

    # -- trials in the shadow

    def judged(self, symptom: Symptom) -> None:
        """A suspect's trial is due, held or failed; or a request degraded in place holds again."""
        request = self._knowledge.requests.get(symptom.request or "")
        if request is None:
            return
        if symptom.kind == "held":
            self._holds_again(request, symptom)
            return
        trial = request.trial
        if symptom.kind == "trial-due":
            self._start_trial(request, symptom.label or "")
        elif trial is None or trial.serial != symptom.trial:
            return  # (about a trial that ended meanwhile)
        elif symptom.kind == "trial-failed":
            log.info("trial %d of %s for %s in the shadow failed: %s", trial.serial, trial.label, request.tag, symptom.detail)
            self.end_trial(request)
            _reschedule(request.suspects.get(trial.label), time.time_ns(), failed=True)
        else:
            self._adapting.adapt(request, symptom, fault=False)  # "trial-held": an opportunity, taken after the dwell time (trust)

    def unit_lost(self, symptom: Symptom) -> None:
        """A unit failed, stalled or went: a trial it was part of ends, which is not the
        suspect's doing (the same wait again)."""
        for request in list(self._knowledge.requests.values()):
            trial = request.trial
            if trial is not None and symptom.unit in trial.units:
                log.info("trial %d of %s for %s ended: %s", trial.serial, trial.label, request.tag, symptom.what())
                self.end_trial(request)
                _reschedule(request.suspects.get(trial.label), time.time_ns(), failed=False)

    def _start_trial(self, request: Request, label: str) -> None:
        """Run the configuration the request would prefer with its suspect ``label`` in the
        shadow, its requirements watched there by monitors of their own; unless the planner
        would not use the suspect now, or the request is busy (then: the same wait again)."""
        suspect = request.suspects.get(label)
        if suspect is None:
            return
        now = time.time_ns()
        if request.state != "active" or request.trial is not None or request.in_place:
            _reschedule(suspect, now, failed=False)
            return
        try:
            plan = self._reconfigurer.plan(request, now, trying={label})
        except PlanningError:
            _reschedule(suspect, now, failed=False)
            return
        if label not in self._reconfigurer.labels(plan) or is_current(request, plan):
            _reschedule(suspect, now, failed=False)  # the planner would not use it now anyway
            return
        request.trial_count += 1
        try:
            trial = request.trial = self._reconfigurer.wire_trial(request, plan, label, request.trial_count, now)
            self._requirements.watch_trial(request, trial)
        except DyKnowError as exc:
            log.warning("could not try %s for %s in the shadow: %s", label, request.tag, exc)
            self.end_trial(request)
            _reschedule(suspect, now, failed=False, slower=True)
            return
        log.info(
            "trial %d of %s for %s in the shadow: %s (its requirements must hold for %g s there)",
            trial.serial,
            label,
            request.tag,
            ", ".join(sorted(set(trial.units.values()))),
            self._dwell_ns / 1e9,
        )

    def end_trial(self, request: Request) -> None:
        """Take the request's trial down: its monitors, its units nothing else holds, its terms."""
        trial = request.trial
        if trial is None:
            return
        orphans = self._reconfigurer.drop_trial(request)
        self._reconfigurer.cleanup([*trial.monitors, *orphans])
        self._requirements.give_back(trial.needs)

    def trust(self, request: Request, symptom: Symptom) -> None:
        """A trial held (and the dwell time is over): its suspect is trusted again, and the request
        moves onto the trial's configuration (only the anchor moves), if the planner prefers it."""
        trial = request.trial
        if trial is None or trial.serial != symptom.trial:
            return
        request.suspects.pop(trial.label, None)
        now = time.time_ns()
        try:
            plan: Plan | None = self._reconfigurer.plan(request, now)
        except PlanningError:
            plan = None
        if plan is None or self._reconfigurer.labels(plan) != self._reconfigurer.labels(trial.plan):
            log.info("%s is trusted again for %s, but the planner prefers another configuration now", trial.label, request.tag)
            self.end_trial(request)
            self._adapting.adapt(request, replace(symptom, kind="preferred", detail=f"{trial.label} is trusted again"), fault=False)
            return
        old_labels = tuple(sorted(set(request.units.values())))
        monitors, needs = list(trial.monitors), list(trial.needs)
        recovery = Recovery(self._runtime, self._journal, self._report)
        try:
            orphans = self._reconfigurer.promote_trial(request, recovery.arm(request))
        except DyKnowError as exc:
            log.warning("switching %s onto its trial's configuration failed: %s", request.tag, exc)
            self.end_trial(request)
            return
        self._reconfigurer.cleanup(monitors)  # the request's own monitors read its key, which now carries the trial's stream
        self._requirements.give_back(needs)
        self._adapting.adapted(request, symptom, symptom.cause(), old_labels, orphans, recovery, standby=False)

    # -- degraded in place

    def hold_in_place(self, request: Request, symptom: Symptom, old: tuple[str, ...], why: str) -> None:
        """A requirement is false and nothing else provides the tag: the request runs on where it
        is, degraded (one log line and one event, with the formula), until its requirements hold
        there for the dwell time (:meth:`judged`) or another configuration comes."""
        self.end_trial(request)
        request.state, request.reason, request.in_place = "degraded", why, True
        event = AdaptationEvent(
            self._journal.next_id(),
            "degraded",
            request.tag,
            request.key,
            symptom.cause(),
            old,
            tuple(sorted(set(request.units.values()))),
            symptom.time_ns,
            detail=why,
        )
        formulas = [*request.watches, *(formula for _, formula in request.spec_watches)]
        key = request.key
        judge = Judge(formulas, self._dwell_ns, lambda _, formula: self._report(Symptom("held", time.time_ns(), detail=formula, request=key)), strict=False)
        self._in_place[key] = (judge, event)
        self._requirements.attach(key, judge)
        self._journal.emit(event)
        log.warning("request %s is degraded: %s; it runs on %s until its requirements hold again", request.tag, why, ", ".join(event.new) or "nothing")

    def settle(self, key: str) -> None:
        """The request on ``key`` is no longer degraded in place (it moved, degraded otherwise, or went)."""
        self._in_place.pop(key, None)
        self._requirements.detach(key)

    def _holds_again(self, request: Request, symptom: Symptom) -> None:
        """The requirements of a request degraded in place held for the dwell time: it is active
        again (its "degraded" event is completed as "recovered", with the time it took), and
        the suspects it runs on are trusted again."""
        entry = self._in_place.get(request.key)
        if entry is None or not request.in_place or not entry[0].done:
            return
        self.settle(request.key)
        for label in set(request.units.values()):
            request.suspects.pop(label, None)
        now = time.time_ns()
        event = entry[1]
        recovered = replace(event, kind="recovered", new=tuple(sorted(set(request.units.values()))), recovery_ms=round((now - event.fault_ns) / 1e6, 3))
        # in this order: whoever sees the request active (list_requests, on another thread) also
        # finds its "recovered" event and the log line, and listeners see it active
        log.info("request %s is active again: its requirements held for %g s on %s", request.tag, self._dwell_ns / 1e9, ", ".join(recovered.new))
        self._journal.record(recovered)
        request.state, request.reason, request.in_place = "active", None, False
        self._journal.announce(recovered)


def _reschedule(suspect: Suspect | None, now: int, *, failed: bool, slower: bool = False) -> None:
    """The next trial of ``suspect``: after twice the wait when its trial failed (or could not
    start: ``slower``), else after the same wait; and not while its relapses' penalty suppresses
    it (:data:`~dyknow.adaptation.damping.TRIALS`)."""
    if suspect is None:
        return
    if failed:
        suspect.failed += 1
    if failed or slower:
        suspect.backoff_s = min(BACKOFF_MAX_S, suspect.backoff_s * 2)
    suppressed = suspect.penalty.suppressed_until() if suspect.penalty is not None else 0
    suspect.next_trial_ns = max(now + int(suspect.backoff_s * 1e9), suppressed)
    suspect.announced = False
