"""The K of MAPE-K: what the loop knows. The requests (each a :class:`Request`: its configuration,
standby, requirements and their watches, the transformations its requirements found false and their
trials in the shadow), the latest measurements, failed transformations and their back-off, stalled
units, managers lost and on probation, and the history of adaptations (:class:`AdaptationEvent`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

from dyknow.adaptation.damping import LINKS, Flaps, Penalty
from dyknow.model import Owner, RequestInfo
from dyknow.planner import Plan

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs

#: How long a request keeps a configuration before an opportunity may switch it (s).
DEFAULT_DWELL_S = 2.0
BACKOFF_FIRST_S = 1.0
BACKOFF_MAX_S = 60.0
#: A manager lost this recently whose return the loop has not heard of yet is held back (its
#: summary can reach the planner first).
FLAP_WINDOW_S = 60.0
#: The longest probation of a manager that comes back (after the dwell time), by default.
FLAP_HOLD_MAX_S = LINKS.max_hold_s


# ---------------------------------------------------------------------------- events and state


@dataclass(frozen=True, slots=True)
class AdaptationEvent:
    """One adaptation of one request (``kind``: "adapted", "degraded" or "recovered").

    ``standby`` is true when the switch only moved the request onto its warm standby.
    """

    id: int
    kind: str
    request: str
    key: str
    cause: str
    old: tuple[str, ...]  # labels of the units of the configuration before
    new: tuple[str, ...]  # and after (empty when degraded)
    fault_ns: int
    adaptation_ms: float | None = None
    recovery_ms: float | None = None
    detail: str | None = None
    standby: bool = False

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (events on ``dyknow/<manager>/events/adaptation`` and ``get_adaptations``)."""
        return {
            "id": self.id,
            "kind": self.kind,
            "request": self.request,
            "key": self.key,
            "cause": self.cause,
            "old": list(self.old),
            "new": list(self.new),
            "fault_ns": self.fault_ns,
            "adaptation_ms": self.adaptation_ms,
            "recovery_ms": self.recovery_ms,
            "detail": self.detail,
            "standby": self.standby,
        }


@dataclass(slots=True)
class Suspect:
    """A transformation a requirement of the request found false: the request's plans avoid it
    until a trial in the shadow shows that the requirements hold on it (:mod:`dyknow.adaptation.suspects`).

    ``backoff_s`` is the wait before the next trial (1 s, doubled after each failed trial, at
    most :data:`BACKOFF_MAX_S`), ``next_trial_ns`` when it is due.
    """

    label: str
    formula: str  # the requirement that was false
    since_ns: int
    backoff_s: float = BACKOFF_FIRST_S
    next_trial_ns: int = 0
    failed: int = 0  # trials in which a requirement was false again
    announced: bool = False  # the monitor said the trial is due
    penalty: Penalty | None = None  # its relapses in this request (kept once it is trusted again)

    def info(self, trial: Trial | None, in_place: bool) -> dict[str, Any]:
        """The JSON form of the model (``RequestInfo.suspects``)."""
        state = "in place" if in_place else "running" if trial is not None and trial.label == self.label else "waiting"
        return {
            "transformation": self.label,
            "formula": self.formula,
            "since_ns": self.since_ns,
            "trial": state,
            "failed_trials": self.failed,
            "backoff_s": self.backoff_s,
            "next_trial_ns": self.next_trial_ns,
            "relapses": self.penalty.relapses if self.penalty is not None else 1,
            "penalty": round(self.penalty.value(time.time_ns())) if self.penalty is not None else None,
        }


@dataclass(slots=True)
class Trial:
    """The configuration a request would prefer with its suspect ``label``, run in the shadow: its
    units run and its output is watched by monitors of the request's requirements (and of its new
    units' own), but the anchor does not forward it."""

    serial: int
    label: str
    plan: Plan
    units: dict[str, str]  # unit -> label, as a request records its configuration
    output_key: str
    started_ns: int
    monitors: list[str] = field(default_factory=list)
    needs: list[str] = field(default_factory=list)  # requests its monitors' other terms needed
    overdue: bool = False  # the monitor said it ran too long undecided


@dataclass(slots=True)
class Request:
    tag: str
    key: str
    anchor: str
    # its references: who took each, and the requirements that reference added (formulas)
    owners: list[tuple[Owner, tuple[str, ...]]] = field(default_factory=list)
    state: str = "active"
    plan: Plan | None = None
    # the configuration: unit -> label; a unit or label of another manager as ``name@manager``
    units: dict[str, str] = field(default_factory=dict)
    output_key: str | None = None
    last_change_ns: int = 0
    reason: str | None = None  # why it is degraded
    standby_mode: str = "none"
    # the warm standby, like the configuration: unit -> label, its plan and output key
    standby: dict[str, str] = field(default_factory=dict)
    standby_plan: Plan | None = None
    standby_key: str | None = None
    standby_reason: str | None = None  # why there is none
    standby_inputs: tuple[Any, ...] | None = None  # what the standby was last planned from
    # healthy units a switch left behind, kept until the next standby is planned (it may reuse them)
    spare: dict[str, str] = field(default_factory=dict)
    # after a switch the next standby waits for the new configuration's first message (or this time):
    # building it takes CPU the first message needs
    standby_after_ns: int = 0
    standby_due: bool = False
    # formulas the stream must satisfy (a false verdict makes it adapt): formula -> its watch (the
    # monitor unit, the requests of its other terms), kept while a reference requires it
    watches: dict[str, tuple[str, tuple[str, ...]]] = field(default_factory=dict)
    watch_count: int = 0
    # the requirements of the transformations in the configuration (their specs'): (unit, formula)
    # -> its watch, kept while the unit serves the request
    spec_watches: dict[tuple[str, str], SpecWatch] = field(default_factory=dict)
    spec_watch_count: int = 0
    # those that could not be watched: (unit, formula) -> (label, why), tried again from
    # unwatched_retry_ns on; the "degraded" event that said so, completed once all are watched
    unwatched: dict[tuple[str, str], tuple[str, str]] = field(default_factory=dict)
    unwatched_retry_ns: int = 0
    unwatched_event: AdaptationEvent | None = None
    # transformations its requirements found false, avoided by its plans until a trial clears them
    suspects: dict[str, Suspect] = field(default_factory=dict)
    # the relapses of each transformation its requirements found false, trusted again or not
    penalties: dict[str, Penalty] = field(default_factory=dict)
    trial: Trial | None = None  # the one running in the shadow
    trial_count: int = 0
    # degraded in place: a requirement is false and nothing else provides the tag, so the request
    # runs on (marked degraded) until its requirements hold again or an alternative comes
    in_place: bool = False
    # moves onto another manager that went away during a call on it (undone): that manager -> the
    # transformations the move was building; its loss, when the loop takes it in, is the cause of
    # the request's failover from them (its plans avoid that manager until then)
    interrupted: dict[str, tuple[str, ...]] = field(default_factory=dict)

    @property
    def references(self) -> int:
        """How many references it has."""
        return len(self.owners)

    @property
    def requirements(self) -> tuple[str, ...]:
        """The formulas its stream must satisfy, in the order they were required."""
        return tuple(self.watches)

    def required(self) -> set[str]:
        """The formulas some reference still requires."""
        return {formula for _, formulas in self.owners for formula in formulas}

    def info(self) -> RequestInfo:
        holders: dict[str, int] = {}
        for owner, _ in self.owners:
            if owner.holder is not None:
                holders[owner.holder] = holders.get(owner.holder, 0) + 1
        return RequestInfo(
            self.tag,
            self.key,
            "degraded" if self.unwatched else self.state,  # (a stream served unchecked is never shown active)
            self.references,
            tuple(self.units),
            tuple(sorted(set(self.units.values()))),
            self.standby_mode,
            tuple(self.standby),
            tuple(sorted(set(self.standby.values()))),
            self.standby_reason if self.standby_mode == "warm" and not self.standby else None,
            self.requirements,
            tuple(
                {"formula": formula, "transformation": watch.label, "unit": ref, "key": watch.key}
                for (ref, formula), watch in self.spec_watches.items()
            ),
            holders,
            suspects=tuple(suspect.info(self.trial, self.in_place and suspect.label in self.units.values()) for suspect in self.suspects.values()),
            unwatched=tuple(
                {"formula": formula, "transformation": label, "unit": ref, "why": why}
                for (ref, formula), (label, why) in self.unwatched.items()
            ),
            reason=reason_head(self.reason) if self.state == "degraded" and self.reason else self._unwatched_reason(),
        )

    def _unwatched_reason(self) -> str | None:
        """Why a request served unchecked shows degraded (its first requirement not watched), or None."""
        for (_, formula), (label, why) in self.unwatched.items():
            more = f" (and {len(self.unwatched) - 1} more)" if len(self.unwatched) > 1 else ""
            return f"the requirement {formula!r} of {label} is not watched{more}: {why}"
        return None

    def held(self) -> list[str]:
        """Every unit the request holds: its configuration, its standby, spare and trial units."""
        return [*self.units, *self.standby, *self.spare, *(self.trial.units if self.trial is not None else ())]

    def holds_aside(self, unit: str) -> bool:
        """Whether ``unit`` is one the request holds beside its configuration (standby, spare, trial)."""
        return unit in self.standby or unit in self.spare or (self.trial is not None and unit in self.trial.units)


@dataclass(frozen=True, slots=True)
class SpecWatch:
    """A requirement of a transformation's spec, watched while one of its units serves a request:
    the monitor unit, the key of its verdicts, and the requests of its other terms."""

    label: str
    monitor: str
    key: str
    needs: tuple[str, ...] = ()


class Knowledge:
    """What the loop knows: requests, measurements, failures and their back-off, stalls, history."""

    def __init__(self, flaps: Flaps | None = None) -> None:
        self.flaps = flaps if flaps is not None else Flaps()
        self.requests: dict[str, Request] = {}  # by key
        self.measurements: dict[str, float | str] = {}
        # label -> [retry at (ns), current back-off (s), retry announced]
        self.backoff: dict[str, list[Any]] = {}
        self.failures: dict[str, Penalty] = {}  # label -> its failures' penalty
        self.stalled: set[str] = set()  # unit names
        self.managed: set[str] = set()  # units the loop spawned (it never destroys the others)
        self.remote: dict[str, dict[str, str]] = {}  # name@manager -> bindings, of those on other managers
        # units of other managers the requests use, once in a summary (or their manager lost since):
        # one its manager's summary does not show then is gone
        self.seen: set[str] = set()
        self.history: list[AdaptationEvent] = []
        self.losses: dict[str, Penalty] = {}  # manager -> its losses' penalty
        self.returned: dict[str, list[int]] = {}  # manager -> [when it came back after a loss (ns), trust announced]

    def unavailable(self, now_ns: int) -> set[str]:
        """Labels in back-off right now."""
        return {label for label, (until, _, _) in self.backoff.items() if until > now_ns}

    def fail(self, label: str, now_ns: int) -> None:
        """A transformation failed: exclude it for its back-off, 1 s doubled once for each penalty
        of its recent failures beyond this one (1 s, 2 s, 4 s ... 60 s while they come close
        together; back to 1 s as they stop: :data:`~dyknow.adaptation.damping.FAILURES`)."""
        penalty = self.failures.setdefault(label, Penalty(self.flaps.failures))
        penalty.relapse(now_ns)
        delay = min(BACKOFF_MAX_S, BACKOFF_FIRST_S * 2 ** penalty.doublings(now_ns))
        self.backoff[label] = [now_ns + int(delay * 1e9), delay, False]

    def lost(self, manager: str, now_ns: int) -> None:
        """Another manager was lost: one more relapse towards its probation. Its summary when it
        is back accounts for every unit spawned there: one it does not show is gone (:attr:`seen`)."""
        self.losses.setdefault(manager, Penalty(self.flaps.links)).relapse(now_ns)
        self.returned.pop(manager, None)
        self.seen.update(ref for ref in self.remote if runs_on(ref, manager))

    def found(self, manager: str, now_ns: int) -> None:
        """Another manager came (back): its probation starts now, if it was lost before."""
        if manager in self.losses:
            self.returned[manager] = [now_ns, False]

    def probation(self, manager: str, now_ns: int, dwell_ns: int) -> tuple[int, Penalty | None]:
        """Until when (ns) ``manager`` is on probation, and the penalty of its losses; (0, None)
        when it is not back from a loss. A manager back from a loss is on probation for the dwell
        time from its return, and while its losses' penalty suppresses it
        (:data:`~dyknow.adaptation.damping.LINKS`: lost again within about ten seconds)."""
        back = self.returned.get(manager)
        penalty = self.losses.get(manager)
        if back is None or penalty is None:
            return 0, None
        return max(back[0] + dwell_ns, penalty.suppressed_until()), penalty

    def on_probation(self, now_ns: int, dwell_ns: int) -> set[str]:
        """The managers an opportunity may not move a request onto yet: those back for less than
        their probation, and those lost lately whose return has not been taken in yet (its summary
        reaches the planner before the loop hears that it came back)."""
        held = {m for m in self.returned if self.probation(m, now_ns, dwell_ns)[0] > now_ns}
        window = FLAP_WINDOW_S * 1e9
        return held | {m for m, penalty in self.losses.items() if m not in self.returned and now_ns - penalty.last_ns < window}

    def users(self, unit: str) -> list[Request]:
        """The requests whose configuration, warm standby, spare or trial units hold ``unit``."""
        return [r for r in self.requests.values() if unit in r.units or r.holds_aside(unit)]

    def standing_by(self, unit: str) -> bool:
        """Whether ``unit`` only stands by (a warm standby's, a spare or a trial's unit): reserved for its request."""
        held = False
        for r in self.requests.values():
            if unit in r.units:
                return False
            held = held or r.holds_aside(unit)
        return held


def reason_head(why: str) -> str:
    """The first two lines of why a request is degraded, on one line (``cannot plan T: nothing
    can provide T``): what a log line, the model and the tools show; the planner's whole
    explanation is in the "degraded" event's detail (and ``dyknow plan``)."""
    return ": ".join(line.strip().rstrip(":") for line in why.splitlines()[:2])


def runs_on(ref: str, manager: str | None) -> bool:
    """Whether a unit reference (``name@manager``) is on ``manager``."""
    return manager is not None and ref.endswith(f"@{manager}")
