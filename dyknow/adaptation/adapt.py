"""Plan and execute for one request: the :class:`Adapter` moves a request affected by a symptom to the
configuration the planner prefers (onto its warm standby when that is ready, onto its suspects when
nothing else is left), or marks it degraded; records each adaptation; and keeps a warm request's
standby what the planner would switch to.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from dyknow.adaptation.analyze import Analyzer
from dyknow.adaptation.anchor import anchor_name, spawn_anchor
from dyknow.adaptation.events import Journal, Recovery
from dyknow.adaptation.knowledge import AdaptationEvent, Knowledge, Request, reason_head, runs_on
from dyknow.adaptation.monitor import Symptom
from dyknow.adaptation.reconfigure import MAX_START_FAILURES, Interrupted, Reconfigurer, StartFailed, is_current
from dyknow.adaptation.requirements import Requirements
from dyknow.adaptation.runtime import Runtime
from dyknow.adaptation.suspects import Suspects
from dyknow.errors import DyKnowError, PlanningError
from dyknow.planner import Plan

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs


class Adapter:
    """Adapts one request to one symptom at a time (on the loop's thread, under its lock).

    The planning and wiring are the :class:`Reconfigurer`'s; this decides what to plan for and
    what to do with the plan. Its :attr:`suspects` learn from the requests' requirements.
    """

    def __init__(
        self,
        runtime: Runtime,
        knowledge: Knowledge,
        analyzer: Analyzer,
        reconfigurer: Reconfigurer,
        requirements: Requirements,
        journal: Journal,
        report: Callable[[Symptom], None],
        dwell_ns: int,
    ) -> None:
        self._runtime = runtime
        self._knowledge = knowledge
        self._analyzer = analyzer
        self._reconfigurer = reconfigurer
        self._requirements = requirements
        self._journal = journal
        self._report = report
        self._dwell_ns = dwell_ns
        self._start_failures = 0  # providers that failed at start in the adaptation under way
        self.suspects = Suspects(runtime, knowledge, reconfigurer, requirements, journal, self, report, dwell_ns)

    def adapt(self, request: Request, symptom: Symptom, fault: bool) -> None:
        """Move ``request`` to the configuration the planner prefers after ``symptom``: a fault
        at once, an opportunity once the dwell time is over (:meth:`Analyzer.wait`)."""
        now = time.time_ns()
        if symptom.kind == "peer-lost" and symptom.manager in request.interrupted:
            labels = request.interrupted.pop(symptom.manager)
            if request.state == "active" and not any(runs_on(ref, symptom.manager) for ref in request.units):
                self._failed_over(request, symptom, labels)
                return
            fault = True  # (it ended a move onto that manager: never an opportunity to wait for)
        if self._analyzer.wait(request, symptom, fault, now):
            return
        if symptom.deferred:
            request.interrupted.clear()  # the dwell time since a move was interrupted is over: that manager may serve again
        if symptom.kind == "trial-held":
            self.suspects.trust(request, symptom)
            return
        old_labels = tuple(sorted(set(request.units.values())))
        cause = symptom.cause()
        warm = request.standby_mode == "warm"
        if fault and warm and self._reconfigurer.standby_ready(request, now):
            self._take_standby(request, symptom, old_labels, fault)  # no planning on the way: the standby is ready
            return
        # an opportunity does not move an active request onto a manager on probation (it came
        # back from a loss lately); a fault or a degraded request takes what works
        # (as of when the opportunity arose: a return seen then is not trusted by it, even later)
        at = min(now, symptom.raised_ns or symptom.time_ns)
        wary = self._knowledge.on_probation(at, self._dwell_ns) if not fault and request.state == "active" else set()
        wary |= set(request.interrupted)  # (gone during a move onto it, its loss not taken in yet)
        suspects: list[str] = []  # the suspects a fault falls back on, when nothing else is left
        try:
            plan = self._reconfigurer.plan(request, now, managers_excluded=wary)
        except PlanningError as exc:
            if request.in_place and not fault:
                return  # it runs on where it is, degraded, until something else can provide its tag
            fallback = self._plan_on_suspects(request, now) if fault or request.state == "degraded" else None
            if fallback is None:
                if fault or request.state == "degraded":
                    self._degrade(request, symptom, old_labels, str(exc))
                return
            plan = fallback
            suspects = sorted(set(request.suspects) & self._reconfigurer.labels(plan))
        if not fault and (request.state == "active" or request.in_place) and is_current(request, plan):
            return  # already the preferred configuration (or, degraded in place, the only one)
        if warm and self._reconfigurer.standby_ready(request, now) and self._reconfigurer.labels(plan) == set(request.standby.values()):
            self._take_standby(request, symptom, old_labels, fault)  # the standby is what the planner prefers now
            return
        recovery = Recovery(self._runtime, self._journal, self._report)
        try:
            orphans = self._reconfigurer.apply(request, plan, recovery.arm(request))
        except DyKnowError as exc:
            if isinstance(exc, Interrupted):
                self._interrupted(request, symptom, plan, exc, old_labels, fault)
                return
            if isinstance(exc, StartFailed) and fault and self._start_failures < MAX_START_FAILURES:
                # its transformation is in back-off now: the next plan takes another provider
                log.warning("adaptation of %s: %s; planning again without %s", request.tag, exc, exc.label)
                self._start_failures += 1
                try:
                    self.adapt(request, symptom, fault)
                finally:
                    self._start_failures -= 1
                return
            log.warning("adaptation of %s failed: %s", request.tag, exc)
            self._degrade(request, symptom, old_labels, f"could not wire the new configuration: {exc}")
            return
        self.adapted(request, symptom, cause, old_labels, orphans, recovery, standby=False, fault=fault)
        if suspects:
            formulas = ", ".join(repr(request.suspects[label].formula) for label in suspects)
            why = f"nothing but {', '.join(suspects)} provides {request.tag}, and its requirement {formulas} was false there"
            self.suspects.hold_in_place(request, symptom, old_labels, why)

    def _interrupted(self, request: Request, symptom: Symptom, plan: Plan, exc: Interrupted, old: tuple[str, ...], fault: bool) -> None:
        """A manager went away while ``request`` was being moved onto it (a spawn there in flight,
        say), and the move was undone. Its loss is on its way to the loop (the loop handles one
        symptom at a time): then it is the cause of the request's failover (:meth:`_failed_over`),
        and until then no plan of the request uses that manager. An active request stays on the
        configuration it had, which the undo rebound (its stream moved and came back: opportunities
        wait the dwell time); one whose configuration broke is degraded. The opportunity or fault
        is taken again after the dwell time, that manager back or not (it may not have been lost:
        another link of this manager's closed during the call, say)."""
        now = time.time_ns()
        request.interrupted[exc.manager] = tuple(sorted(self._reconfigurer.labels(plan)))
        self._analyzer.defer(request.key, now + self._dwell_ns, symptom)
        if fault or request.state != "active":
            log.warning("adaptation of %s failed: %s", request.tag, exc)
            self._degrade(request, symptom, old, f"could not wire the new configuration: {exc}")
            return
        request.last_change_ns = now
        log.warning("moving %s (%s) was interrupted, it stays on %s: %s", request.tag, symptom.cause(), ", ".join(old), exc)

    def _failed_over(self, request: Request, symptom: Symptom, labels: tuple[str, ...]) -> None:
        """The loss of a manager ended a move of ``request`` onto it (:meth:`_interrupted`): the
        request is back on the configuration it had (what it still runs), and the loss is the cause
        of that failover, recorded from the configuration the move was building (its stream may
        have carried it: a kept unit that feeds the request's key is rebound first)."""
        recovery = Recovery(self._runtime, self._journal, self._report)
        if request.output_key is not None:
            recovery.arm(request)(request.output_key)
        self.adapted(request, symptom, symptom.cause(), labels, [], recovery, standby=False, fault=True)

    def _plan_on_suspects(self, request: Request, now: int) -> Plan | None:
        """The configuration ``request`` would run with its suspects allowed, when it has any and one exists."""
        if not request.suspects:
            return None
        try:
            return self._reconfigurer.plan(request, now, trying=set(request.suspects))
        except PlanningError:
            return None

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
        """The new configuration is wired: record it, tell the listeners, let go of what it left;
        returns when it was wired (ns). One log line says what was rebuilt and why: a warning
        after a fault (something broke), else information (a better configuration came back)."""
        wired = time.time_ns()
        request.last_change_ns = wired
        request.interrupted.clear()  # (a loss that comes later is not this configuration's concern)
        self.suspects.settle(request.key)  # (a request degraded in place that moved is judged where it went)
        event = AdaptationEvent(
            self._journal.next_id(),
            "adapted",
            request.tag,
            request.key,
            cause,
            old_labels,
            tuple(sorted(set(request.units.values()))),
            symptom.time_ns,
            round((wired - symptom.time_ns) / 1e6, 3),
            standby=standby,
        )
        self._journal.emit(event)
        recovery.adapted(event)
        log.log(
            logging.WARNING if fault else logging.INFO,
            "adapted %s (%s)%s: %s -> %s in %.1f ms",
            request.tag,
            cause,
            " onto its warm standby" if standby else "",
            ", ".join(old_labels),
            ", ".join(event.new),
            event.adaptation_ms,
        )
        self._leave(request, orphans)
        self._requirements.watch_specs(request)
        return wired

    def _take_standby(self, request: Request, symptom: Symptom, old_labels: tuple[str, ...], fault: bool) -> None:
        """Switch ``request`` onto its warm standby (only the anchor moves), then, after a fault,
        come back to the planner's preferred configuration after the dwell time if it differs."""
        recovery = Recovery(self._runtime, self._journal, self._report)
        try:
            orphans = self._reconfigurer.promote(request, recovery.arm(request))
        except DyKnowError as exc:
            log.warning("switching %s onto its standby failed: %s", request.tag, exc)
            self._degrade(request, symptom, old_labels, f"could not switch onto the standby: {exc}")
            return
        wired = self.adapted(request, symptom, symptom.cause(), old_labels, orphans, recovery, standby=True, fault=fault)
        if fault:
            try:
                preferred = self._reconfigurer.plan(request, time.time_ns())
            except PlanningError:
                return
            if not is_current(request, preferred):  # e.g. a destroyed unit that can simply be spawned again
                self._analyzer.defer(
                    request.key, wired + self._dwell_ns, Symptom("preferred", wired, detail="the preferred configuration can run again")
                )

    def _leave(self, request: Request, orphans: list[str]) -> None:
        """Units a switch left behind: a warm request keeps the healthy ones for its next standby
        (planned right after), the others are destroyed."""
        if request.standby_mode != "warm":
            self._reconfigurer.cleanup(orphans)
            return
        live = {info.name: info.label for info in self._runtime.units() if info.alive}
        for name in orphans:
            if name in live and name not in self._knowledge.stalled:
                request.spare[name] = live[name]  # local units only: remote ones are cheap to ask for again
        self._reconfigurer.cleanup([n for n in orphans if n not in request.spare])

    def maintain_standby(self, request: Request, now: int) -> None:
        """Keep a warm request's standby what the planner would switch to: plan it when what it
        depends on changed, rebuild it (reusing what fits) when it differs or broke, drop it
        when there is none; spare units nothing took are destroyed."""
        if self._knowledge.requests.get(request.key) is not request:
            return
        reconfigurer = self._reconfigurer
        if request.state != "active":
            spare, request.spare = list(request.spare), {}
            reconfigurer.cleanup([n for n in spare if not self._knowledge.users(n)])
            return
        inputs = reconfigurer.standby_inputs(request, now)
        if inputs == request.standby_inputs and not request.spare:
            return
        request.standby_inputs = inputs
        try:
            plan = reconfigurer.plan_standby(request, now)
        except PlanningError as exc:
            if request.standby:
                log.info("request %s has no standby any more: %s", request.tag, exc)
            request.standby_reason = str(exc)
            reconfigurer.cleanup(reconfigurer.drop_standby(request))
            return
        if reconfigurer.standby_ready(request, now) and reconfigurer.labels(plan) == set(request.standby.values()):
            spare, request.spare = list(request.spare), {}
            reconfigurer.cleanup([n for n in spare if not self._knowledge.users(n)])
            return
        try:
            orphans = reconfigurer.wire_standby(request, plan)
        except DyKnowError as exc:
            log.warning("could not wire the standby of %s: %s", request.tag, exc)
            request.standby_reason = f"could not wire the standby: {exc}"
            reconfigurer.cleanup(reconfigurer.drop_standby(request))
            return
        request.standby_reason = None
        reconfigurer.cleanup(orphans)
        request.standby_inputs = reconfigurer.standby_inputs(request, time.time_ns())  # its own spawns are no news
        log.info("standby of %s: %s", request.tag, ", ".join(sorted(set(request.standby.values()))))

    def reanchor(self, request: Request) -> None:
        """The anchor itself went: put a new one on the same key."""
        self._reconfigurer.cleanup([request.anchor])
        request.anchor = anchor_name(self._runtime, request.tag)
        spawn_anchor(self._runtime, self._knowledge, request, request.output_key or f"{request.key}/none")

    def _degrade(self, request: Request, symptom: Symptom, old: tuple[str, ...], why: str) -> None:
        was = request.state
        was_in_place = request.in_place
        self.suspects.end_trial(request)
        self.suspects.settle(request.key)
        request.state = "degraded"
        request.reason = why
        request.in_place = False
        if was != "degraded" or was_in_place:
            event = AdaptationEvent(
                self._journal.next_id(), "degraded", request.tag, request.key, symptom.cause(), old, (), symptom.time_ns, detail=why
            )
            self._journal.emit(event)
            # one line; the planner's whole explanation at debug level (and in the event's detail, dyknow plan)
            head = reason_head(why)  # "cannot plan T: nothing can provide T"
            log.warning(
                "request %s is degraded (%s): %s (the planner's reasons: its event, or dyknow plan)", request.tag, symptom.cause(), head
            )
            log.debug("request %s is degraded: %s", request.tag, why)
        self._requirements.watch_specs(request)
