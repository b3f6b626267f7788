"""The M of MAPE-K: the :class:`Monitor` turns what happens (a unit failed or was destroyed, a deadline
passed or was met again, a measurement, a back-off ended, a suspect's trial is due or overdue) into
:class:`Symptom` s for the loop; a :class:`Judge` turns the verdicts of requirements watched over
one configuration into one symptom: they held for the dwell time, or one was false.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from dyknow.adaptation.knowledge import DEFAULT_DWELL_S, Knowledge
from dyknow.adaptation.runtime import DeadlinePort
from dyknow.model import UnitEvent
from dyknow.reasoning.progression import Verdict

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs


@dataclass(frozen=True, slots=True)
class Symptom:
    """Something the monitor saw. ``fault`` symptoms break configurations; others are opportunities."""

    # "failed", "destroyed", "stalled", "resumed", "measurement", "retry", "library",
    # "peer-found", "peer-lost", "peer-changed" (another manager came, went or changed),
    # "peer-trusted" (a manager that came back after losses has held through its probation),
    # "requirement" (a formula a request requires was false), "trial-due" (a suspect's back-off
    # ended: try it in the shadow), "trial-held" / "trial-failed" (a trial's requirements held
    # for the dwell time / one was false, or none was decided in time), "held" (the requirements
    # of a request degraded in place held for the dwell time)
    kind: str
    time_ns: int
    unit: str | None = None
    label: str | None = None
    measure: str | None = None
    detail: str = ""
    manager: str | None = None
    deferred: bool = False  # an opportunity taken after the dwell time
    raised_ns: int = 0  # a deferred opportunity: when it arose (time_ns is when it is taken)
    request: str | None = None  # "requirement": the key of the request whose requirement was false
    # ("unit" and "label": the unit and transformation whose spec's requirement it was, if one's)
    state_ns: int = 0  # "requirement": the time of the state the false verdict is about
    trial: int = 0  # "trial-*": the trial's number (a symptom of an earlier trial is stale)

    def cause(self) -> str:
        """What an adaptation's event and log line give as its cause: what happened, and whether
        the opportunity waited for the dwell time."""
        return self.what() + (", after the dwell time" if self.deferred else "")

    def what(self) -> str:
        """What happened, in words."""
        if self.kind == "failed":
            return f"unit {self.unit!r} failed: {self.detail}"
        if self.kind == "destroyed":
            return f"unit {self.unit!r} was destroyed"
        if self.kind == "stalled":
            return f"unit {self.unit!r} stalled: {self.detail}"
        if self.kind == "measurement":
            return f"measurement {self.detail}"
        if self.kind == "retry":
            return f"retry: {self.detail}"
        if self.kind == "resumed":
            return f"unit {self.unit!r} resumed"
        if self.kind == "peer-lost":
            return f"manager {self.manager!r} was lost"
        if self.kind == "peer-found":
            return f"manager {self.manager!r} was found"
        if self.kind == "requirement" and self.label is not None:
            return f"requirement of {self.label} violated: {self.detail}"
        if self.kind == "requirement":
            return f"requirement violated: {self.detail}"
        if self.kind == "peer-trusted":
            return f"manager {self.manager!r} is trusted again: {self.detail}"
        if self.kind == "trial-held":
            return f"{self.detail} in the shadow (trial {self.trial})"
        if self.kind == "trial-failed":
            return f"trial {self.trial} of {self.label} failed: {self.detail}"
        if self.kind == "held":
            return f"requirement held again: {self.detail}"
        if self.kind == "peer-changed":
            return f"manager {self.manager!r} changed: {self.detail}" if self.detail else f"manager {self.manager!r} changed"
        return self.detail or self.kind


#: How long past the dwell time a trial may run without its requirements decided (then it failed).
TRIAL_TIMEOUT_NS = 30_000_000_000


# ---------------------------------------------------------------------------- monitor

#: A tick this much later than the one before (the loop ticks every 20 ms) means this process was
#: starved (its threads not run: a loaded machine, a long pause): a unit found silent then is judged
#: at the next tick instead, once its own thread, starved too, had its turn. Without it a healthy
#: camera of a loaded manager was marked stalled, its 200 Hz frames "silent" past a 100 ms deadline,
#: and the requests using it degraded (issue 43). Ticks starved one after the other are judged.
STARVED_NS = 100_000_000


class Monitor:
    """Turns unit events, deadlines, measurements and timers into symptoms for the loop.

    ``deadline_ports()`` lists the ports to watch (the runtime's :meth:`Runtime.deadline_ports`).
    """

    def __init__(self, deadline_ports: Callable[[], list[DeadlinePort]], knowledge: Knowledge, report: Callable[[Symptom], None]) -> None:
        self._deadline_ports = deadline_ports
        self._knowledge = knowledge
        self._report = report
        # (unit, port) -> (count, changed at ns, started_ns of the unit instance counted)
        self._seen: dict[tuple[str, str], tuple[int, int, int]] = {}
        self._last_tick_ns = 0
        self._starved = False  # whether the last tick came late

    def unit_event(self, event: UnitEvent) -> None:
        """A unit failed or was destroyed: a symptom."""
        if event.kind in ("failed", "destroyed"):
            self._report(Symptom(event.kind, event.time_ns, unit=event.unit, label=event.label, detail=event.error or ""))

    def measurement(self, name: str, value: float | str, now_ns: int) -> None:
        """A measurement arrived: remember it and report it."""
        self._knowledge.measurements[name] = value
        self._report(Symptom("measurement", now_ns, measure=name, detail=f"{name} = {value!r}"))

    def tick(self, now_ns: int, dwell_ns: int = int(DEFAULT_DWELL_S * 1e9)) -> None:
        """Check deadlines, back-offs and probations (called every few milliseconds by the loop)."""
        knowledge = self._knowledge
        starved = self._last_tick_ns != 0 and now_ns - self._last_tick_ns > STARVED_NS
        judge = not starved or self._starved  # (see STARVED_NS)
        self._last_tick_ns, self._starved = now_ns, starved
        for label, entry in knowledge.backoff.items():
            if entry[0] <= now_ns and not entry[2]:
                entry[2] = True  # announce each retry once; the back-off doubles if it fails again
                self._report(Symptom("retry", now_ns, label=label, detail=f"back-off of {label} ended"))
        for manager, back in knowledge.returned.items():
            until, penalty = knowledge.probation(manager, now_ns, dwell_ns)
            if not back[1] and until <= now_ns and penalty is not None:
                back[1] = True  # announce it once
                hold = round((until - back[0]) / 1e9, 1)
                losses = f"{penalty.relapses} loss{'es' if penalty.relapses > 1 else ''}"
                damped = "" if until <= back[0] + dwell_ns else ", too close together: held back until their penalty decayed"
                why = f"back for its probation of {hold:g} s ({losses}{damped})"
                self._report(Symptom("peer-trusted", now_ns, manager=manager, detail=why))
        for request in knowledge.requests.values():
            for suspect in request.suspects.values():
                if not suspect.announced and suspect.next_trial_ns <= now_ns and request.trial is None and request.state == "active":
                    suspect.announced = True  # announce it once; the loop schedules the next
                    self._report(
                        Symptom("trial-due", now_ns, label=suspect.label, request=request.key, detail=f"back-off of {suspect.label} ended")
                    )
            trial = request.trial
            if trial is not None and not trial.overdue and now_ns - trial.started_ns > dwell_ns + TRIAL_TIMEOUT_NS:
                trial.overdue = True  # announce it once
                why = f"its requirements were not decided within {(dwell_ns + TRIAL_TIMEOUT_NS) / 1e9:g} s"
                self._report(Symptom("trial-failed", now_ns, label=trial.label, request=request.key, detail=why, trial=trial.serial))
        ports = self._deadline_ports()
        for name, label, port, deadline_ns, count, started_ns in (
            (p.unit, p.label, p.port, p.deadline_ns, p.messages, p.started_ns) for p in ports
        ):
            seen = self._seen.get((name, port))
            if seen is not None and seen[2] != started_ns:
                seen = None  # a new unit under the same name (respawned): its own count and clock
            if seen is None or count != seen[0]:
                self._seen[(name, port)] = (count, now_ns if seen is not None else max(now_ns, started_ns), started_ns)
                if name in knowledge.stalled and seen is not None:
                    knowledge.stalled.discard(name)
                    self._report(Symptom("resumed", now_ns, unit=name, label=label, detail=f"{name}.{port} publishes again"))
                continue
            if name not in knowledge.stalled and now_ns - seen[1] > deadline_ns and judge:
                knowledge.stalled.add(name)
                silent_ms = (now_ns - seen[1]) / 1e6
                self._report(
                    Symptom(
                        "stalled",
                        now_ns,
                        unit=name,
                        label=label,
                        detail=f"{name}.{port} silent for {silent_ms:.0f} ms (deadline {deadline_ns / 1e6:g} ms)",
                    )
                )
        live = {(p.unit, p.port) for p in ports}
        for gone in [k for k in self._seen if k not in live]:
            del self._seen[gone]
        if knowledge.stalled:  # a stalled unit destroyed meanwhile is forgotten
            knowledge.stalled.intersection_update(p.unit for p in ports)

    def watched(self) -> int:
        """How many (unit, port) deadlines the monitor follows."""
        return len(self._seen)

    def watches(self, unit: str) -> bool:
        """Whether the monitor follows a deadline of ``unit``."""
        return any(name == unit for name, _ in list(self._seen))


# ---------------------------------------------------------------------------- judging a configuration


class Judge:
    """Follows the verdicts of ``formulas`` watched over one configuration and reports once.

    ``report("held", formula)`` once every formula's verdicts have been true over at least
    ``hold_ns`` of state time (from its first true verdict to its latest, none false between);
    unknown verdicts count for nothing. A false verdict either reports ``("failed", formula)``
    (``strict``: a trial in the shadow fails at once) or starts that formula's time over (a
    request degraded in place must hold for ``hold_ns`` in a row). Verdicts come on the monitors'
    threads: the judge only keeps two times per formula and reports through the loop's queue.
    """

    def __init__(self, formulas: Iterable[str], hold_ns: int, report: Callable[[str, str], None], *, strict: bool) -> None:
        self._held: dict[str, list[int]] = {f: [] for f in formulas}  # formula -> [first true ns, latest true ns], or []
        self._hold_ns = hold_ns
        self._report = report
        self._strict = strict
        self._lock = threading.Lock()
        self.done = False

    @property
    def formulas(self) -> tuple[str, ...]:
        """The formulas it judges."""
        return tuple(self._held)

    def verdict(self, formula: str, verdict: Verdict) -> None:
        """One verdict of ``formula`` (any other formula's is ignored)."""
        value: bool | None = verdict.verdict
        if value is None:  # (a verdict not decided counts for nothing)
            return
        with self._lock:
            held = self._held.get(formula)
            if held is None or self.done:
                return
            if value is False:
                if self._strict:
                    self.done = True
                else:
                    held.clear()
                    return
                outcome = "failed"
            else:
                if held:
                    held[1] = max(held[1], verdict.t_ns)
                else:
                    held.extend((verdict.t_ns, verdict.t_ns))
                if not all(h and h[1] - h[0] >= self._hold_ns for h in self._held.values()):
                    return
                self.done = True
                outcome = "held"
        self._report(outcome, formula)
