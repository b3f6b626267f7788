"""Self-adaptation: keep requested streams flowing when resources fail (a MAPE-K loop).

A client asks for information by meaning: ``manager.request("BallPosition(field)")`` returns a key.
Behind the key sits an *anchor*, a relay unit owned by the request whose output is the key; the
planner's configuration feeds the anchor's input. Adapting means wiring a new configuration and
rebinding the anchor's input, so **the requested key never changes** and consumers keep receiving
without resubscribing.

The loop is built from explicit parts, after MAPE-K (Kephart & Chess; RoCS), with the three layers
of Sykes et al.: requests are the goals, this module manages change, the manager and proxies
control the components.

- :class:`Knowledge`: the requests, the latest measurements, failed transformations and their
  back-off, stalled units, and the history of adaptations.
- :class:`Monitor`: turns what happens into :class:`Symptom` s: a unit failed (an exception, or a
  remote producer's liveliness token vanished), a unit was destroyed, an output port with a
  ``deadline-ms`` fell silent (stalled) or spoke again, a measurement arrived, a back-off ended.
- :class:`Analyzer`: which requests a symptom affects, and whether it is a *fault* (the current
  configuration is broken: adapt now) or an *opportunity* (a preferred configuration may be
  available again: adapt, but not more often than the dwell time allows).
- :class:`Reconfigurer` (plan and execute): re-plans with failed and unavailable transformations
  excluded and the request's own units set aside so that preferences decide, then changes as little
  as possible: units of the new configuration that already run for the request are kept (with
  their state) and only rebound where their upstream changed; new ones are spawned, consumers
  before producers; the anchor is rebound; units nothing uses any more are destroyed last.

**Warm standby** (``request(tag, standby="warm")``, opt-in per request): besides the active
configuration the request keeps the next-best one running, the configuration the planner would
choose if the active one could not run (planned again with each transformation of the active
configuration that has a replacement excluded, and without the active configuration's units or
anything they feed). Its units run, so their state is built (a tracker has a track), but the anchor
forwards only the active configuration's output; it keeps the standby's latest message. On a fault
the switch only rebinds the anchor onto the standby's output and forwards that latest message at
once, so consumers do not wait up to a frame for the next one (its origin time is older than the
switch, and may be older than the last message the broken configuration sent). A new standby is
then planned, once the new configuration's first message is out (building it takes CPU that
message needs; at most a second later), reusing the healthy units of the old configuration where
it can. When the preferred configuration is allowed again the request returns to it as any
request does (after the dwell time), and the configuration it leaves becomes the standby. Releasing the request tears the
standby down too. The model lists the standby's units (:class:`~dyknow.model.RequestInfo`), and
the events of a switch onto the standby say so (``standby``).

Flapping is prevented by a dwell time (an opportunity never switches a request twice within it),
by exponential back-off for failed transformations (retried after 1 s, 2 s, 4 s ... up to
60 s), and by probation for managers that come back: a manager lost ``n`` times in the last
:data:`FLAP_WINDOW_S` is trusted again by an opportunity only once it has stayed for the dwell
time times ``2 ** (n - 1)`` (at most :data:`FLAP_HOLD_MAX_S`); a fault or a degraded request uses
it at once. So a link that goes down and up every few seconds moves a request off it, and back
only once it holds. When no configuration exists the request is *degraded*, and recovered later when possible.

Every adaptation is an :class:`AdaptationEvent` (cause, old and new configuration, adaptation time
from the fault to the new configuration wired and running) published as JSON on
``dyknow/<manager>/events/adaptation`` and handed to listeners; a second event with the same id
follows with the recovery time, from the fault to the first message on the requested key after it.

Measurements arrive through :meth:`Manager.measure` or as JSON (a number, or ``{"value": x}``) on
``dyknow/measurements/<name>`` or ``dyknow/<manager>/measurements/<name>``.

The loop knows the manager only through :class:`Runtime`, the narrow interface declared here
(look up units, spawn, destroy, rebind, deadline ports, publish an event), which the manager
provides publicly; a test can hand the loop a small stand-in instead.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from dyknow import keys
from dyknow.errors import DyKnowError, PlanningError, ServiceError, UnitError
from dyknow.federation import Summary
from dyknow.library import Library
from dyknow.message import Message
from dyknow.model import RequestInfo, UnitEvent, UnitInfo, check_standby
from dyknow.ontology import Ontology
from dyknow.planner import Plan, PlannedUnit, Planner, RunningUnit, qualify, unqualify
from dyknow.reasoning.progression import Verdict
from dyknow.reasoning.syntax import Formula, parse
from dyknow.reasoning.unit import VERDICTS_PORT, FormulaMonitor, monitor_spec, term_ports
from dyknow.spec import Port, TransformationSpec
from dyknow.tags import parse_term
from dyknow.unit import Unit

__all__ = [
    "ANCHOR_LABEL",
    "ANCHOR_SPEC",
    "WARM_ANCHOR_SPEC",
    "AdaptationEvent",
    "AdaptationLoop",
    "Analyzer",
    "DeadlinePort",
    "Knowledge",
    "Monitor",
    "Reconfigurer",
    "RequestAnchor",
    "Runtime",
    "Symptom",
]

log = logging.getLogger(__name__)

ANCHOR_LABEL = "dyknow-request-anchor"
DEFAULT_DWELL_S = 2.0
BACKOFF_FIRST_S = 1.0
BACKOFF_MAX_S = 60.0
#: A manager's losses count towards its probation for this long.
FLAP_WINDOW_S = 60.0
#: The longest probation of a manager that comes back.
FLAP_HOLD_MAX_S = 30.0
_TICK_S = 0.02  # deadlines, back-offs and deferred opportunities are checked this often
_STANDBY_WAIT_NS = 1_000_000_000  # after a switch, the next standby waits this long at most for the stream
_RECORD_WAIT_S = 1.0  # how long an anchor holds a new configuration's first message for its adaptation's record


# ---------------------------------------------------------------------------- what the loop needs


@dataclass(frozen=True, slots=True)
class DeadlinePort:
    """An output port with a ``deadline-ms`` of a live unit, and how many messages it sent so far.

    ``started_ns`` tells two units spawned under the same name apart.
    """

    unit: str
    label: str
    port: str
    deadline_ns: int
    messages: int
    started_ns: int


class Runtime(Protocol):
    """What the adaptation loop needs of the manager whose requests it keeps flowing.

    :class:`~dyknow.manager.Manager` provides all of it publicly.
    """

    @property
    def name(self) -> str:
        """The manager's name (it appears in keys)."""
        ...

    @property
    def library(self) -> Library:
        """The specs the planner may use."""
        ...

    @property
    def ontology(self) -> Ontology | None:
        """The ontology tags are matched against."""
        ...

    def units(self) -> list[UnitInfo]:
        """A snapshot of every running unit."""
        ...

    def has_unit(self, name: str) -> bool:
        """Whether a unit called ``name`` runs."""
        ...

    def unit(self, name: str) -> Unit:
        """The Python object of running unit ``name``."""
        ...

    def spawn(self, label: str | TransformationSpec, name: str, *, bindings: Mapping[str, str] | None = None) -> UnitInfo:
        """Start a unit of a library label, or of a spec given directly."""
        ...

    def destroy(self, name: str) -> None:
        """Stop unit ``name``."""
        ...

    def get_config(self, name: str) -> dict[str, str]:
        """Port -> key bindings of unit ``name``."""
        ...

    def set_config(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """Rebind ports of unit ``name``."""
        ...

    def deadline_ports(self) -> list[DeadlinePort]:
        """The output ports with a deadline, of every live unit."""
        ...

    def publish_event(self, kind: str, event: Mapping[str, Any]) -> None:
        """Publish an event of ``kind`` (JSON) on the manager's event key."""
        ...

    def peers(self) -> Mapping[str, Summary]:
        """The other managers reachable now, with their last summary (empty when alone)."""
        ...

    def spawn_on(self, manager: str, label: str, name: str, *, bindings: Mapping[str, str]) -> None:
        """Spawn a unit of ``manager``'s library on ``manager``, for a request of this one."""
        ...

    def destroy_on(self, manager: str, name: str) -> None:
        """Destroy a unit this manager spawned on ``manager``."""
        ...

    def set_config_on(self, manager: str, name: str, bindings: Mapping[str, str]) -> None:
        """Rebind ports of a unit on ``manager``."""
        ...

    def changed(self) -> None:
        """Something the other managers see changed (a unit stalled or resumed)."""
        ...


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
class _Request:
    tag: str
    key: str
    anchor: str
    references: int = 1
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
    # formulas the stream must satisfy (a false verdict makes it adapt), their monitor units, and
    # the requests of their other terms
    requirements: tuple[str, ...] = ()
    watchers: list[str] = field(default_factory=list)
    needs: list[str] = field(default_factory=list)
    # the requirements of the transformations in the configuration (their specs'): (unit, formula)
    # -> its watch, kept while the unit serves the request
    spec_watches: dict[tuple[str, str], _SpecWatch] = field(default_factory=dict)
    spec_watch_count: int = 0

    def info(self) -> RequestInfo:
        return RequestInfo(
            self.tag,
            self.key,
            self.state,
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
        )

    def held(self) -> list[str]:
        """Every unit the request holds: its configuration, its standby and spare units."""
        return [*self.units, *self.standby, *self.spare]


@dataclass(frozen=True, slots=True)
class _SpecWatch:
    """A requirement of a transformation's spec, watched while one of its units serves a request:
    the monitor unit, the key of its verdicts, and the requests of its other terms."""

    label: str
    monitor: str
    key: str
    needs: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Symptom:
    """Something the monitor saw. ``fault`` symptoms break configurations; others are opportunities."""

    # "failed", "destroyed", "stalled", "resumed", "measurement", "retry", "library",
    # "peer-found", "peer-lost", "peer-changed" (another manager came, went or changed),
    # "peer-trusted" (a manager that came back after losses has held through its probation),
    # "requirement" (a formula a request requires was false)
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


class Knowledge:
    """What the loop knows: requests, measurements, failures and their back-off, stalls, history."""

    def __init__(self) -> None:
        self.requests: dict[str, _Request] = {}  # by key
        self.measurements: dict[str, float | str] = {}
        # label -> [retry at (ns), current back-off (s), retry announced]
        self.backoff: dict[str, list[Any]] = {}
        self.stalled: set[str] = set()  # unit names
        self.managed: set[str] = set()  # units the loop spawned (it never destroys the others)
        self.remote: dict[str, dict[str, str]] = {}  # name@manager -> bindings, of those on other managers
        self.seen: set[str] = set()  # units of other managers the requests use, once in a summary
        self.history: list[AdaptationEvent] = []
        self.losses: dict[str, list[int]] = {}  # manager -> when it was lost (ns), the last FLAP_WINDOW_S
        self.returned: dict[str, list[int]] = {}  # manager -> [when it came back after a loss (ns), trust announced]

    def unavailable(self, now_ns: int) -> set[str]:
        """Labels in back-off right now."""
        return {label for label, (until, _, _) in self.backoff.items() if until > now_ns}

    def fail(self, label: str, now_ns: int) -> None:
        """A transformation failed: exclude it, for twice as long as last time (1 s, 2 s, ... 60 s)."""
        previous = self.backoff[label][1] if label in self.backoff else BACKOFF_FIRST_S / 2
        delay = min(BACKOFF_MAX_S, previous * 2)
        self.backoff[label] = [now_ns + int(delay * 1e9), delay, False]

    def lost(self, manager: str, now_ns: int) -> None:
        """Another manager was lost: one more loss towards its probation."""
        recent = [t for t in self.losses.get(manager, []) if now_ns - t < FLAP_WINDOW_S * 1e9][-63:]
        self.losses[manager] = [*recent, now_ns]
        self.returned.pop(manager, None)

    def found(self, manager: str, now_ns: int) -> None:
        """Another manager came (back): its probation starts now, if it was lost before."""
        if manager in self.losses:
            self.returned[manager] = [now_ns, False]

    def probation(self, manager: str, now_ns: int, dwell_ns: int) -> tuple[int, int]:
        """Until when (ns) ``manager`` is on probation, and after how many recent losses; (0, 0)
        when it was not lost lately."""
        back = self.returned.get(manager)
        if back is None:
            return 0, 0
        losses = sum(1 for t in self.losses.get(manager, []) if back[0] - t < FLAP_WINDOW_S * 1e9)
        if losses == 0:
            return 0, 0
        hold = min(FLAP_HOLD_MAX_S * 1e9, dwell_ns * 2 ** (losses - 1))
        return back[0] + int(hold), losses

    def on_probation(self, now_ns: int, dwell_ns: int) -> set[str]:
        """The managers an opportunity may not move a request onto yet."""
        return {m for m in self.returned if self.probation(m, now_ns, dwell_ns)[0] > now_ns}

    def users(self, unit: str) -> list[_Request]:
        """The requests whose configuration, warm standby or spare units hold ``unit``."""
        return [r for r in self.requests.values() if unit in r.units or unit in r.standby or unit in r.spare]

    def standing_by(self, unit: str) -> bool:
        """Whether ``unit`` only stands by (a warm standby's or a spare unit): reserved for its request."""
        held = False
        for r in self.requests.values():
            if unit in r.units:
                return False
            held = held or unit in r.standby or unit in r.spare
        return held


# ---------------------------------------------------------------------------- the anchor unit


class RequestAnchor(Unit):
    """Relays a request's configuration onto the request's stable key; reports recoveries.

    After an adaptation the loop tells the anchor which key the new configuration publishes on;
    the first message from that key closes the adaptation with its recovery time.

    The anchor of a warm request (:data:`WARM_ANCHOR_SPEC`) also reads the standby's output on
    port ``standby`` and keeps only the latest message, since the port was last rebound. When
    ``in`` is rebound onto that key (the standby takes over), it forwards that message at once,
    with its own origin time, unless a newer one from that key was forwarded already.
    """

    def setup(self) -> None:
        """Wait for nothing yet."""
        self._waiting: tuple[str, Callable[[int], None]] | None = None
        self._latest: Message | None = None  # the standby's latest message

    def expect(self, key: str, on_first: Callable[[int], None]) -> None:
        """Call ``on_first(arrival_ns)`` for the next message arriving from ``key``."""
        self._waiting = (key, on_first)

    def on_message(self, port: str, msg: Message) -> None:
        """Relay the message onto the request's key; report the first one of a new configuration.

        A message on ``standby`` is only kept (the latest one), not relayed."""
        if port == "standby":
            self._latest = msg
            return
        latest = self._latest
        if latest is not None and latest.key == msg.key:
            self._latest = None  # its configuration is the active one now: this message is newer
        self._first(msg.key)  # before relaying it: see _Recovery
        self.publish("out", msg.payload)

    def on_reconfigure(self, changes: Mapping[str, str]) -> None:
        """When ``in`` moved onto the standby's key, forward the standby's latest message now."""
        latest = self._latest
        if "standby" in changes:
            self._latest = None  # a new standby (or none): what the old one said is not its
        key = changes.get("in")
        if key is not None and latest is not None and latest.key == key:
            self._latest = None
            self._first(key)
            self.publish("out", latest.payload, origin_ns=latest.origin_ns)

    def _first(self, key: str) -> None:
        waiting = self._waiting
        if waiting is not None and key == waiting[0]:
            self._waiting = None
            waiting[1](time.time_ns())


ANCHOR_SPEC = TransformationSpec(
    label=ANCHOR_LABEL,
    source="dyknow.adaptation:RequestAnchor",
    ports=(Port("in", "in", queue=64), Port("out", "out")),
    description="Relays a request's stream onto its stable key (internal to request()).",
)
"""The anchor of a request without a standby."""

WARM_ANCHOR_SPEC = TransformationSpec(
    label=ANCHOR_LABEL,
    source="dyknow.adaptation:RequestAnchor",
    ports=(Port("in", "in", queue=64), Port("standby", "in", queue=1), Port("out", "out")),
    description="Relays a request's stream onto its stable key, and keeps its warm standby's latest message (internal to request()).",
)
"""The anchor of a request with a warm standby: port ``standby`` reads the standby's output."""


# ---------------------------------------------------------------------------- monitor


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
        for label, entry in knowledge.backoff.items():
            if entry[0] <= now_ns and not entry[2]:
                entry[2] = True  # announce each retry once; the back-off doubles if it fails again
                self._report(Symptom("retry", now_ns, label=label, detail=f"back-off of {label} ended"))
        for manager, back in knowledge.returned.items():
            until, losses = knowledge.probation(manager, now_ns, dwell_ns)
            if not back[1] and until <= now_ns:
                back[1] = True  # announce it once
                hold = (until - back[0]) / 1e9
                why = f"back for its probation of {hold:g} s ({losses} loss{'es' if losses > 1 else ''} in the last {FLAP_WINDOW_S:g} s)"
                self._report(Symptom("peer-trusted", now_ns, manager=manager, detail=why))
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
            if name not in knowledge.stalled and now_ns - seen[1] > deadline_ns:
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


# ---------------------------------------------------------------------------- analyzer


class Analyzer:
    """Which requests a symptom affects, and whether they must adapt now (fault) or may (opportunity)."""

    def __init__(self, runtime: Runtime, knowledge: Knowledge) -> None:
        self._runtime = runtime
        self._knowledge = knowledge

    def affected(self, symptom: Symptom) -> list[tuple[_Request, bool]]:
        """``(request, is_fault)`` pairs, in a stable order; a degraded request is always among them."""
        found = self._affected(symptom)
        seen = {id(r) for r, _ in found}
        degraded = [
            (r, False)
            for r in sorted(self._knowledge.requests.values(), key=lambda r: r.key)
            if r.state == "degraded" and id(r) not in seen
        ]
        return found + degraded

    def _affected(self, symptom: Symptom) -> list[tuple[_Request, bool]]:
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
            return [(r, True) for r in requests if any(_on(ref, symptom.manager) for ref in r.units)]
        if symptom.kind == "peer-changed" and symptom.manager is not None:
            return [(r, bool(self.broken_on(r, symptom.manager))) for r in requests]
        return [(r, False) for r in requests]  # resumed, retry, library, peer-found: maybe better now

    def broken_on(self, request: _Request, manager: str) -> list[tuple[str, str]]:
        """What breaks ``request`` on another manager, after its summary changed.

        ``(unit, why)`` pairs: a unit it uses there vanished (once seen), is unhealthy, or the
        manager's measurements break a constraint of its transformation.
        """
        summary = self._runtime.peers().get(manager)
        if summary is None:
            return [(ref, f"manager {manager!r} was lost") for ref in request.units if _on(ref, manager)]
        there = {u.name: u for u in summary.units}
        specs = {s.label: s for s in summary.specs}
        broken = []
        for ref, label in request.units.items():
            if not _on(ref, manager):
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

    def running_model(self, request: _Request | None) -> tuple[list[RunningUnit], set[str]]:
        """Units the plan may reuse (the request's own set aside) and every name in use.

        Names of units on other managers are ``name@manager``. Units another manager spawned
        for its own requests are not reused: that manager takes them down when it likes.
        """
        knowledge = self._knowledge
        own = set()
        if request is not None:
            own = {u for u in request.held() if u in knowledge.managed and all(r is request for r in knowledge.users(u))}
        running: list[RunningUnit] = []
        names: set[str] = set()
        for info in self._runtime.units():
            names.add(info.name)
            if info.name in own or info.label == ANCHOR_LABEL or info.spec is None or knowledge.standing_by(info.name):
                continue
            outputs = {p.name: info.bindings[p.name] for p in info.spec.outputs}
            tags = {p.name: info.spec.tags_for(p.name) for p in info.spec.outputs}
            healthy = info.alive and info.name not in knowledge.stalled
            running.append(RunningUnit(info.name, info.label, outputs, tags, healthy))
        home = self._runtime.name
        for manager, summary in sorted(self._runtime.peers().items()):
            for unit in summary.units:
                ref = qualify(unit.name, manager)
                names.add(ref)
                if ref in own or (unit.owner is not None and unit.owner != home) or knowledge.standing_by(ref):
                    continue
                if unit.owner == home and ref not in knowledge.remote:
                    continue  # ours, but already destroyed (the summary is older) or left by an earlier run

                running.append(unit.running(manager))
        names.update(r for r in knowledge.remote)  # spawned, maybe not in a summary yet
        return running, names

    def plan(
        self,
        request: _Request,
        now_ns: int,
        *,
        exclude: Collection[str] = (),
        avoid: Collection[str] = (),
        managers_excluded: Collection[str] = (),
    ) -> Plan:
        """The preferred configuration for ``request`` now (:class:`PlanningError` when none).

        ``exclude``: transformations not to use besides those in back-off or stalled; ``avoid``:
        running units not to reuse (besides the request's own, which are always set aside);
        ``managers_excluded``: other managers none of whose transformations or units to use,
        except those the request already uses there.
        """
        running, names = self.running_model(request)
        peers = self._runtime.peers()
        kept = set(request.units)
        if avoid:
            running = [u for u in running if u.ref not in avoid]
        if managers_excluded:
            running = [u for u in running if u.ref in kept or not any(_on(u.ref, m) for m in managers_excluded)]
        unavailable = self._knowledge.unavailable(now_ns) | set(exclude)
        used = set(request.units.values())
        for manager in managers_excluded:
            summary = peers.get(manager)
            if summary is not None:
                unavailable |= {qualify(spec.label, manager) for spec in summary.specs} - used
        labels = {info.name: info.label for info in self._runtime.units()}
        stalled_labels = {labels[n] for n in self._knowledge.stalled if n in labels}
        load = {self._runtime.name: len(labels), **{m: s.load for m, s in peers.items()}}
        return self.planner().plan(
            request.tag,
            running,
            unavailable | stalled_labels,
            self._knowledge.measurements,
            reserved_names=names,
            peer_measurements={m: s.measurements for m, s in peers.items()},
            load=load,
        )

    def apply(self, request: _Request, plan: Plan, before_switch: Callable[[str], None] | None = None) -> list[str]:
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
                        self._set_config(actual, changed)
                    built.units[actual] = _label_ref(unit)
                else:
                    bindings = {p: key(k) for p, k in unit.bindings.items()}
                    if unit.remote:
                        knowledge.remote[unit.ref] = bindings
                        knowledge.managed.add(unit.ref)
                        built.spawned.append(unit.ref)
                        runtime.spawn_on(unit.manager, unit.label, unit.name, bindings=bindings)
                    else:
                        info = runtime.spawn(unit.label, unit.name, bindings=bindings)
                        built.spawned.append(unit.name)
                        knowledge.managed.add(unit.name)
                        if info.state == "failed":
                            raise UnitError(f"failed at start: {info.error}", where=f"unit {unit.name!r} ({unit.label})")
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

    def standby_ready(self, request: _Request, now_ns: int) -> bool:
        """Whether the request's warm standby can take over now: all its units healthy, none of its
        transformations in back-off or against the latest measurements."""
        if not request.standby or request.standby_key is None:
            return False
        unavailable = self._knowledge.unavailable(now_ns)
        local = {info.name: info for info in self._runtime.units()}
        for ref, label in request.standby.items():
            name, manager = unqualify(ref, self._runtime.name)
            if manager == self._runtime.name:
                info = local.get(name)
                if info is None or not info.alive or name in self._knowledge.stalled:
                    return False
            elif not self._healthy(ref):
                return False
            if label in unavailable or self.violated(label):
                return False
        return True

    def violated(self, label: str) -> bool:
        """Whether the latest measurements break a constraint of transformation ``label``
        (``label@manager``: that manager's measurements and spec, from its summary)."""
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
            if value is not None and not c.holds(value):
                return True
        return False

    def labels(self, plan: Plan) -> set[str]:
        """Every transformation a plan runs on: its units' and, for running units it reuses, those
        that feed them (as a request records its configuration)."""
        found = {_label_ref(u) for u in plan.units}
        found.update(self._upstream(u.name for u in plan.units if not u.new and not u.remote).values())
        return found

    def plan_standby(self, request: _Request, now_ns: int) -> Plan:
        """The configuration ``request`` would run if its active one could not: planned with each
        transformation of the active configuration that something else can replace excluded, and
        none of the active configuration's units (nor anything they feed) reused. When excluding
        them all leaves nothing, the replacement of one of them that shares the fewest
        transformations with the active configuration. :class:`PlanningError` when there is none.
        """
        avoid = self._downstream(request.units)
        active = sorted(set(request.units.values()))
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

    def wire_standby(self, request: _Request, plan: Plan) -> list[str]:
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

    def drop_standby(self, request: _Request) -> list[str]:
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

    def promote(self, request: _Request, before_switch: Callable[[str], None] | None = None) -> list[str]:
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
        return [n for n in old if n not in request.units and n in knowledge.managed and not knowledge.users(n)]

    def idle_key(self, request: _Request) -> str:
        """Where an anchor's ``standby`` port listens while there is no standby (nothing publishes there)."""
        return keys.default_key(self._runtime.name, request.anchor, "standby")

    def standby_inputs(self, request: _Request, now_ns: int) -> tuple[Any, ...]:
        """What planning the request's standby depends on: the libraries, back-offs and stalls,
        which constraints hold, the units running and the request's own configurations. The same
        inputs give the same standby, so it is not planned again."""
        runtime = self._runtime
        self.planner()
        holds = []
        for label, constraints in self._constrained():
            for c in constraints:
                value = self._knowledge.measurements.get(c.measure)
                holds.append((label, value is None or c.holds(value)))
        return (
            self._planner_version,
            frozenset(self._knowledge.unavailable(now_ns)),
            frozenset(self._knowledge.stalled),
            tuple(holds),
            frozenset((info.name, info.alive) for info in runtime.units()),
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
        units = {info.name: info for info in self._runtime.units() if info.spec is not None and info.label != ANCHOR_LABEL}
        readers: dict[str, list[str]] = {}
        for info in units.values():
            assert info.spec is not None
            for port in info.spec.inputs:
                readers.setdefault(info.bindings[port.name], []).append(info.name)
        found = set(refs)
        todo = [r for r in found if r in units]
        while todo:
            info = units[todo.pop()]
            assert info.spec is not None
            for port in info.spec.outputs:
                for reader in readers.get(info.bindings[port.name], ()):
                    if reader not in found:
                        found.add(reader)
                        todo.append(reader)
        return found

    def _healthy(self, ref: str) -> bool:
        name, manager = unqualify(ref, self._runtime.name)
        if manager == self._runtime.name:
            info = next((i for i in self._runtime.units() if i.name == name), None)
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
        units = {info.name: info for info in self._runtime.units() if info.spec is not None}
        producers: dict[str, list[str]] = {}
        for info in units.values():
            assert info.spec is not None
            for port in info.spec.outputs:
                producers.setdefault(info.bindings[port.name], []).append(info.name)
        found: dict[str, str] = {}
        todo = [n for n in names if n in units]
        while todo:
            info = units[todo.pop()]
            assert info.spec is not None
            for port in info.spec.inputs:
                for producer in producers.get(info.bindings[port.name], ()):
                    if producer not in found and units[producer].label != ANCHOR_LABEL:
                        found[producer] = units[producer].label
                        todo.append(producer)
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
                # replaced already, or lost with its manager: as it should be
                gone = (isinstance(exc, UnitError) and "no unit named" in exc.what) or (
                    isinstance(exc, ServiceError) and exc.details.get("reason") == "gone"
                )
                log.log(logging.DEBUG if gone else logging.WARNING, "could not destroy unit %r after an adaptation: %s", ref, exc)
            self._knowledge.managed.discard(ref)
            self._knowledge.stalled.discard(ref)
            self._knowledge.remote.pop(ref, None)
            self._knowledge.seen.discard(ref)


# ---------------------------------------------------------------------------- the loop


class AdaptationLoop:
    """Runs monitor, analyzer and reconfigurer on a thread of its own, one symptom at a time."""

    def __init__(self, runtime: Runtime, *, dwell_s: float = DEFAULT_DWELL_S) -> None:
        self.runtime = runtime
        self.knowledge = Knowledge()
        self.monitor = Monitor(runtime.deadline_ports, self.knowledge, self._report)
        self.analyzer = Analyzer(runtime, self.knowledge)
        self.reconfigurer = Reconfigurer(runtime, self.knowledge)
        self.dwell_ns = int(dwell_s * 1e9)
        self._lock = threading.RLock()
        self._symptoms: queue.SimpleQueue[Symptom | None] = queue.SimpleQueue()
        self._listeners: list[Callable[[AdaptationEvent], None]] = []
        self._next_id = 1
        self._deferred: dict[str, tuple[int, Symptom]] = {}  # request key -> (when, the opportunity)
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"dyknow-{runtime.name}-adaptation", daemon=True)
        self._thread.start()

    # -- requests

    def request(self, tag: str, *, standby: str | None = None, require: Iterable[str] = ()) -> str:
        """Plan and wire a configuration providing ``tag``; returns its stable key.

        ``standby="warm"`` keeps the next-best configuration running beside it, so that a fault
        only moves the anchor (see the module documentation); ``"none"`` (or None, the default)
        does not. Requesting a tag again shares the request; asking for a warm standby then gives
        the shared request one, which it keeps until it is released. An unknown ``standby`` is a
        :class:`UnitError` naming the allowed values, raised before anything changes.

        ``require``: temporal formulas (:mod:`dyknow.reasoning`) the stream must satisfy; a term
        that is ``tag`` reads the request's own stream, any other is requested in turn. A state
        a requirement finds false is a fault: the request moves to the next-best configuration
        (the cause names the formula), unless the present one has not run for the dwell time
        yet. A formula that does not read is a :class:`~dyknow.errors.FormulaError`, raised
        before anything changes.
        """
        mode = check_standby(standby)
        runtime = self.runtime
        canonical = str(parse_term(tag))
        key = keys.request_key(runtime.name, canonical)
        formulas = [parse(text) for text in require]
        with self._lock:
            existing = self.knowledge.requests.get(key)
            if existing is not None:
                existing.references += 1
                if mode == "warm" and existing.standby_mode != "warm":
                    self._warm_up(existing)
                self._require(existing, [f for f in formulas if str(f) not in existing.requirements])
                return key
            now = time.time_ns()
            request = _Request(canonical, key, anchor=self._anchor_name(canonical), standby_mode=mode)
            plan = self.reconfigurer.plan(request, now)  # PlanningError: nothing fits, nothing changes
            self._spawn_anchor(request, plan.output_key)
            self.knowledge.requests[key] = request
            try:
                self.reconfigurer.apply(request, plan)
            except DyKnowError:
                del self.knowledge.requests[key]
                self.reconfigurer.cleanup([request.anchor])
                raise
            request.last_change_ns = time.time_ns()
            self._report(Symptom("spawned", request.last_change_ns, unit=request.anchor))  # start ticking
            log.info("request %s on %s: %s", canonical, key, ", ".join(sorted(set(request.units.values()))))
            if mode == "warm":
                self._maintain_standby(request, time.time_ns())
            try:
                self._require(request, formulas)
            except DyKnowError:
                self.release(key)
                raise
            self._watch_specs(request)
            return key

    def _require(self, request: _Request, formulas: list[Formula]) -> None:
        """Watch ``formulas`` over ``request``'s stream: a monitor unit each, whose false
        verdicts become "requirement" symptoms (see :meth:`request`)."""
        for formula in formulas:
            bindings: dict[str, str] = {}
            for term, port in term_ports(formula).items():
                if term == request.tag:
                    bindings[port] = request.key
                else:
                    needed = self.request(term)
                    request.needs.append(needed)
                    bindings[port] = needed
            n = len(request.requirements)
            name = f"{request.anchor}-require-{n + 1}"
            bindings[VERDICTS_PORT] = f"{request.key}/requirements/{n + 1}"
            self.runtime.spawn(monitor_spec(formula, label="requirement"), name, bindings=bindings)
            self.knowledge.managed.add(name)
            request.watchers.append(name)
            request.requirements = (*request.requirements, str(formula))
            watcher = self.runtime.unit(name)
            if isinstance(watcher, FormulaMonitor):
                text, key = str(formula), request.key
                watcher.listen(lambda verdict, text=text, key=key: self._verdict(key, text, verdict))  # type: ignore[misc]

    def _verdict(self, key: str, formula: str, verdict: Verdict, unit: str | None = None, label: str | None = None) -> None:
        """A requirement's verdict (on its monitor's thread): a false one is a symptom."""
        if verdict.verdict is False:
            symptom = Symptom("requirement", time.time_ns(), unit=unit, label=label, detail=formula, request=key, state_ns=verdict.t_ns)
            self._report(symptom)

    def _watch_specs(self, request: _Request) -> None:
        """Watch the requirements of the transformations now serving ``request`` (their specs'),
        and stop watching those of units that no longer do. A term that is one of the unit's
        output tags reads that output; any other is requested in turn. A requirement that cannot
        be watched is logged, and the configuration runs unwatched rather than not at all."""
        planner = self.reconfigurer.planner()
        wanted: dict[tuple[str, str], str] = {}  # (unit, formula) -> label
        for ref, label in request.units.items():
            try:
                spec = planner.spec(label)
            except (KeyError, DyKnowError):
                continue  # (a unit of a transformation no library holds any more: nothing to watch)
            for formula in spec.requirements:
                wanted[(ref, formula)] = label
        for ident in [i for i in request.spec_watches if i not in wanted]:
            watch = request.spec_watches.pop(ident)
            self.reconfigurer.cleanup([watch.monitor])
            for needed in watch.needs:
                if needed in self.knowledge.requests:
                    self.release(needed)
        for (ref, text), label in wanted.items():
            if (ref, text) not in request.spec_watches:
                try:
                    request.spec_watches[(ref, text)] = self._spec_watch(request, ref, label, parse(text))
                except DyKnowError as exc:
                    log.warning("cannot watch the requirement %r of %s for %s: %s", text, label, request.tag, exc)

    def _spec_watch(self, request: _Request, ref: str, label: str, formula: Formula) -> _SpecWatch:
        spec = self.reconfigurer.planner().spec(label)
        outputs = self.reconfigurer.config(ref)
        bindings: dict[str, str] = {}
        needs: list[str] = []
        try:
            for term, port in term_ports(formula).items():
                produced = [
                    outputs[p.name]
                    for p in spec.outputs
                    if p.name in outputs and term in {str(parse_term(t)) for t in spec.tags_for(p.name)}
                ]
                if produced:
                    bindings[port] = produced[0]
                else:
                    needs.append(self.request(term))
                    bindings[port] = needs[-1]
            request.spec_watch_count += 1
            n = request.spec_watch_count
            name = f"{request.anchor}-spec-require-{n}"
            key = bindings[VERDICTS_PORT] = f"{request.key}/requirements/spec-{n}"
            self.runtime.spawn(monitor_spec(formula, label="requirement"), name, bindings=bindings)
        except DyKnowError:
            for needed in needs:
                self.release(needed)
            raise
        self.knowledge.managed.add(name)
        watcher = self.runtime.unit(name)
        if isinstance(watcher, FormulaMonitor):
            text, rkey = str(formula), request.key
            watcher.listen(lambda verdict, text=text, rkey=rkey, ref=ref, label=label: self._verdict(rkey, text, verdict, ref, label))  # type: ignore[misc]
        return _SpecWatch(label, name, key, tuple(needs))

    def _warm_up(self, request: _Request) -> None:
        """A shared request asked for a warm standby: a new anchor that can hold one, then the standby."""
        request.standby_mode = "warm"
        self.reconfigurer.cleanup([request.anchor])
        request.anchor = self._anchor_name(request.tag)
        self._spawn_anchor(request, request.output_key or f"{request.key}/none")
        self._maintain_standby(request, time.time_ns())

    def _spawn_anchor(self, request: _Request, input_key: str) -> None:
        bindings = {"in": input_key, "out": request.key}
        spec = ANCHOR_SPEC
        if request.standby_mode == "warm":
            spec = WARM_ANCHOR_SPEC
            if request.standby_key is not None:
                bindings["standby"] = request.standby_key
        self.runtime.spawn(spec, request.anchor, bindings=bindings)
        self.knowledge.managed.add(request.anchor)

    def release(self, key: str) -> int:
        """Drop one reference to a request; the last one tears down what only it used. Returns
        the references that remain (0: the request is gone)."""
        with self._lock:
            request = self.knowledge.requests.get(key)
            if request is None:
                known = ", ".join(sorted(self.knowledge.requests)) or "none"
                raise UnitError(
                    f"no request on key {key!r}", where=f"manager {self.runtime.name!r}", expected=f"one of the active requests: {known}"
                )
            request.references -= 1
            if request.references > 0:
                return request.references
            del self.knowledge.requests[key]
            self._deferred.pop(key, None)
            orphans = [n for n in request.held() if n in self.knowledge.managed and not self.knowledge.users(n)]
            watches = list(request.spec_watches.values())
            self.reconfigurer.cleanup([*request.watchers, *(w.monitor for w in watches), request.anchor, *orphans])
            for needed in [*request.needs, *(n for w in watches for n in w.needs)]:
                if needed in self.knowledge.requests:
                    self.release(needed)
            return 0

    def requests(self) -> list[RequestInfo]:
        """The active requests, by key. Never waits for a request being planned or adapted (the
        model's readers call it): ``list()`` of a dict's values is one step for other threads."""
        requests = list(self.knowledge.requests.values())
        return [r.info() for r in sorted(requests, key=lambda r: r.key)]

    def _anchor_name(self, tag: str) -> str:
        base = "request-" + "".join(c if c.isalnum() or c in "_-." else "-" for c in tag).strip("-")
        name, n = base, 1
        while self.runtime.has_unit(name):
            n += 1
            name = f"{base}-{n}"
        return name

    # -- measurements and events

    def measure(self, name: str, value: float | str) -> None:
        """Record the latest value of a measure; requests whose constraints it breaks adapt."""
        self.monitor.measurement(name, value, time.time_ns())

    def library_changed(self) -> None:
        """New or removed specs may offer better configurations (or a way out of degradation)."""
        self._report(Symptom("library", time.time_ns(), detail="the library changed"))

    def peer_changed(self, kind: str, manager: str) -> None:
        """Another manager was "found", "lost" or "changed" its summary: requests may adapt.

        A lost manager is a fault for the requests that used its units; a found or changed one
        an opportunity (a changed one is a fault when a unit a request uses there went or broke).
        """
        self._report(Symptom(f"peer-{kind}", time.time_ns(), manager=manager))

    def on_event(self, listener: Callable[[AdaptationEvent], None]) -> Callable[[], None]:
        """Call ``listener(event)`` for every adaptation event; returns a function that removes it."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener) if listener in self._listeners else None

    def history(self) -> list[AdaptationEvent]:
        """Every adaptation so far, oldest first (each with its recovery time once recovered);
        a copy taken without waiting for an adaptation in progress."""
        return list(self.knowledge.history)

    def _emit(self, event: AdaptationEvent) -> None:
        history = self.knowledge.history
        for i in range(len(history) - 1, -1, -1):  # a recovery completes its adaptation's entry
            if history[i].id == event.id:
                history[i] = event
                break
        else:
            history.append(event)
        try:
            self.runtime.publish_event("adaptation", event.to_dict())
        except DyKnowError as exc:
            log.warning("could not publish adaptation event: %s", exc)
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception:
                log.exception("adaptation listener failed")

    # -- the loop

    def _report(self, symptom: Symptom) -> None:
        if not self._closed:
            self._symptoms.put(symptom)

    def unit_event(self, event: UnitEvent) -> None:
        """Told by the manager that a unit was spawned, failed or was destroyed."""
        if event.kind == "spawned":
            self._report(Symptom("spawned", event.time_ns, unit=event.unit))  # may bring deadlines to watch
        elif event.unit in self.knowledge.managed or self.knowledge.users(event.unit):
            self.monitor.unit_event(event)
        elif event.kind == "destroyed" and self.monitor.watches(event.unit):
            self._report(Symptom("spawned", event.time_ns, unit=event.unit))  # a tick forgets its deadlines

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the loop's thread (waiting up to ``timeout_s``) and destroy what its requests run
        on other managers; safe twice."""
        if self._closed:
            return
        self._closed = True
        self._symptoms.put(None)
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        with self._lock:
            self.reconfigurer.cleanup(list(self.knowledge.remote))

    def _busy(self) -> bool:
        """Whether anything needs the periodic tick: requests, deadlines, back-offs, deferrals."""
        knowledge = self.knowledge
        return bool(knowledge.requests or knowledge.backoff or self._deferred or self.runtime.deadline_ports())

    def _run(self) -> None:
        while True:
            try:
                # an idle manager sleeps until something happens (a spawn wakes it, see unit_event)
                symptom = self._symptoms.get(timeout=_TICK_S) if self._busy() else self._symptoms.get()
            except queue.Empty:
                symptom = None
                if self._closed:
                    return
            if self._closed:
                return
            try:
                with self._lock:
                    now = time.time_ns()
                    changed = symptom is not None
                    if symptom is not None:
                        self._handle(symptom)
                    self.monitor.tick(now, self.dwell_ns)
                    for key, (due, opportunity) in list(self._deferred.items()):
                        if due <= now:
                            del self._deferred[key]
                            changed = True
                            request = self.knowledge.requests.get(key)
                            if request is not None:  # timed from now: the wait was our choice, not the fault's
                                waited = replace(opportunity, time_ns=now, deferred=True, raised_ns=opportunity.time_ns)
                                self._adapt(request, waited, fault=False)
                    # after the switches, and once their stream flows again: standbys follow what changed
                    for request in sorted(self.knowledge.requests.values(), key=lambda r: r.key):
                        if request.standby_mode == "warm" and (changed or request.standby_due) and request.standby_after_ns <= now:
                            request.standby_due = False
                            self._maintain_standby(request, time.time_ns())
            except Exception:
                log.exception("adaptation loop error (it keeps running)")

    def _handle(self, symptom: Symptom) -> None:
        if symptom.kind in ("spawned", "recovered"):
            return  # only wakes the loop up (for a tick: deadlines to watch, or to forget; a standby to build)
        if symptom.kind in ("failed", "destroyed") and symptom.unit is not None and self._later_unit(symptom.unit, symptom.time_ns):
            return  # about an earlier unit of that name (one the loop replaced since): nothing to do
        knowledge = self.knowledge
        if symptom.kind in ("failed", "stalled") and symptom.label and symptom.label != ANCHOR_LABEL:
            knowledge.fail(symptom.label, symptom.time_ns)
        if symptom.kind in ("stalled", "resumed"):
            self.runtime.changed()  # the other managers see it in this manager's summary
        if symptom.kind == "peer-lost" and symptom.manager is not None:
            knowledge.lost(symptom.manager, symptom.time_ns)
        if symptom.kind == "peer-found" and symptom.manager is not None:
            knowledge.found(symptom.manager, symptom.time_ns)
        if symptom.kind == "peer-changed" and symptom.manager is not None:
            self._peer_changed(symptom, symptom.manager)
            return
        if symptom.kind == "requirement":
            self._violated(symptom)
            return
        for request, fault in self.analyzer.affected(symptom):
            if symptom.unit is not None and symptom.unit == request.anchor:
                self._reanchor(request, symptom)
                continue
            self._adapt(request, symptom, fault)

    def _violated(self, symptom: Symptom) -> None:
        """A requirement was false: move the request to the next-best configuration.

        Not when the present configuration has run less than the dwell time (its first states
        are judged partly on what the one before delivered), nor when it is degraded. The next
        best is the cheapest plan without one of the present configuration's transformations;
        that transformation is put in back-off (so the request returns to it later, and leaves it
        again, for twice as long, if the requirement fails again)."""
        request = self.knowledge.requests.get(symptom.request or "")
        if request is None or request.state != "active" or symptom.state_ns < request.last_change_ns + self.dwell_ns:
            return
        now = time.time_ns()
        if symptom.unit is not None:  # a transformation's own requirement: that transformation goes
            label = request.units.get(symptom.unit)
            if label is None or label != symptom.label:
                return  # (the unit no longer serves the request: a verdict that was on its way)
            try:
                self.reconfigurer.plan(request, now, exclude={label})
            except PlanningError:
                log.info("requirement %r of %s is false, and no configuration without it provides %s", symptom.detail, label, request.tag)
                return
            self.knowledge.fail(label, now)
            self._adapt(request, symptom, fault=True)
            return
        best: tuple[tuple[Any, ...], str] | None = None
        for label in sorted(set(request.units.values())):
            try:
                plan = self.reconfigurer.plan(request, now, exclude={label})
            except PlanningError:
                continue
            if best is None or plan.cost < best[0]:
                best = (plan.cost, label)
        if best is None:
            log.info("requirement %r of %s is false, and no other configuration provides it", symptom.detail, request.tag)
            return
        self.knowledge.fail(best[1], now)
        self._adapt(request, symptom, fault=True)

    def _later_unit(self, name: str, time_ns: int) -> bool:
        """Whether the unit now named ``name`` started after ``time_ns``."""
        return any(info.name == name and info.started_ns > time_ns for info in self.runtime.units())

    def _peer_changed(self, symptom: Symptom, manager: str) -> None:
        """Another manager's summary changed: a fault for requests it broke, else an opportunity."""
        if manager not in self.runtime.peers():
            # gone by the time the change is handled (its last summary, then its loss): the loss it is
            symptom = replace(symptom, kind="peer-lost")
        for request in sorted(self.knowledge.requests.values(), key=lambda r: r.key):
            broken = self.analyzer.broken_on(request, manager)
            for ref, why in broken:
                if "unhealthy" in why:
                    self.knowledge.fail(request.units[ref], symptom.time_ns)
            detail = "; ".join(why for _, why in broken)
            if symptom.kind == "peer-lost":
                detail = ""  # the cause says it: "manager X was lost"
            self._adapt(request, replace(symptom, detail=detail) if broken else symptom, bool(broken))

    def _reanchor(self, request: _Request, symptom: Symptom) -> None:
        """The anchor itself went: put a new one on the same key."""
        self.reconfigurer.cleanup([request.anchor])
        request.anchor = self._anchor_name(request.tag)
        self._spawn_anchor(request, request.output_key or f"{request.key}/none")

    def _adapt(self, request: _Request, symptom: Symptom, fault: bool) -> None:
        now = time.time_ns()
        if not fault and request.state == "active" and now - request.last_change_ns < self.dwell_ns:
            # flapping guard: take the opportunity when the dwell time is over (the latest one wins,
            # but another manager's routine summary does not hide the cause already waiting, nor
            # does a routine measurement hide an ended back-off or probation)
            waiting = self._deferred.get(request.key)
            routine = symptom.kind == "peer-changed" or (symptom.kind == "measurement" and waiting is not None and waiting[1].kind in ("retry", "peer-trusted"))
            if waiting is None or not routine:
                self._deferred[request.key] = (request.last_change_ns + self.dwell_ns, symptom)
            return
        old_labels = tuple(sorted(set(request.units.values())))
        cause = _cause(symptom)
        warm = request.standby_mode == "warm"
        if fault and warm and self.reconfigurer.standby_ready(request, now):
            self._take_standby(request, symptom, old_labels, fault)  # no planning on the way: the standby is ready
            return
        # an opportunity does not move an active request onto a manager on probation (it came
        # back from a loss lately); a fault or a degraded request takes what works
        # (as of when the opportunity arose: a return seen then is not trusted by it, even later)
        at = min(now, symptom.raised_ns or symptom.time_ns)
        wary = self.knowledge.on_probation(at, self.dwell_ns) if not fault and request.state == "active" else set()
        try:
            plan = self.reconfigurer.plan(request, now, managers_excluded=wary)
        except PlanningError as exc:
            if fault or request.state == "degraded":
                self._degrade(request, symptom, old_labels, str(exc))
            return
        if not fault and request.state == "active" and _same(request, plan):
            return  # already the preferred configuration
        if warm and self.reconfigurer.standby_ready(request, now) and self.reconfigurer.labels(plan) == set(request.standby.values()):
            self._take_standby(request, symptom, old_labels, fault)  # the standby is what the planner prefers now
            return
        recovery = _Recovery(self)
        try:
            orphans = self.reconfigurer.apply(request, plan, recovery.arm(request))
        except DyKnowError as exc:
            log.warning("adaptation of %s failed: %s", request.tag, exc)
            self._degrade(request, symptom, old_labels, f"could not wire the new configuration: {exc}")
            return
        self._adapted(request, symptom, cause, old_labels, orphans, recovery, standby=False, fault=fault)

    def _adapted(
        self,
        request: _Request,
        symptom: Symptom,
        cause: str,
        old_labels: tuple[str, ...],
        orphans: list[str],
        recovery: _Recovery,
        *,
        standby: bool,
        fault: bool = False,
    ) -> int:
        """The new configuration is wired: record it, tell the listeners, let go of what it left;
        returns when it was wired (ns). One log line says what was rebuilt and why: a warning
        after a fault (something broke), else information (a better configuration came back)."""
        wired = time.time_ns()
        request.last_change_ns = wired
        event = AdaptationEvent(
            self._next_id,
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
        self._next_id += 1
        self._emit(event)
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
        self._watch_specs(request)
        return wired

    def _take_standby(self, request: _Request, symptom: Symptom, old_labels: tuple[str, ...], fault: bool) -> None:
        """Switch ``request`` onto its warm standby (only the anchor moves), then, after a fault,
        come back to the planner's preferred configuration after the dwell time if it differs."""
        recovery = _Recovery(self)
        try:
            orphans = self.reconfigurer.promote(request, recovery.arm(request))
        except DyKnowError as exc:
            log.warning("switching %s onto its standby failed: %s", request.tag, exc)
            self._degrade(request, symptom, old_labels, f"could not switch onto the standby: {exc}")
            return
        wired = self._adapted(request, symptom, _cause(symptom), old_labels, orphans, recovery, standby=True, fault=fault)
        if fault:
            try:
                preferred = self.reconfigurer.plan(request, time.time_ns())
            except PlanningError:
                return
            if not _same(request, preferred):  # e.g. a destroyed unit that can simply be spawned again
                self._deferred[request.key] = (
                    wired + self.dwell_ns,
                    Symptom("preferred", wired, detail="the preferred configuration can run again"),
                )

    def _leave(self, request: _Request, orphans: list[str]) -> None:
        """Units a switch left behind: a warm request keeps the healthy ones for its next standby
        (planned right after), the others are destroyed."""
        if request.standby_mode != "warm":
            self.reconfigurer.cleanup(orphans)
            return
        live = {info.name: info.label for info in self.runtime.units() if info.alive}
        for name in orphans:
            if name in live and name not in self.knowledge.stalled:
                request.spare[name] = live[name]  # local units only: remote ones are cheap to ask for again
        self.reconfigurer.cleanup([n for n in orphans if n not in request.spare])

    def _maintain_standby(self, request: _Request, now: int) -> None:
        """Keep a warm request's standby what the planner would switch to: plan it when what it
        depends on changed, rebuild it (reusing what fits) when it differs or broke, drop it
        when there is none; spare units nothing took are destroyed."""
        if self.knowledge.requests.get(request.key) is not request:
            return
        reconfigurer = self.reconfigurer
        if request.state != "active":
            spare, request.spare = list(request.spare), {}
            reconfigurer.cleanup([n for n in spare if not self.knowledge.users(n)])
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
            reconfigurer.cleanup([n for n in spare if not self.knowledge.users(n)])
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

    def _degrade(self, request: _Request, symptom: Symptom, old: tuple[str, ...], why: str) -> None:
        was = request.state
        request.state = "degraded"
        request.reason = why
        if was != "degraded":
            event = AdaptationEvent(
                self._next_id, "degraded", request.tag, request.key, _cause(symptom), old, (), symptom.time_ns, detail=why
            )
            self._next_id += 1
            self._emit(event)
            # one line; the planner's whole explanation at debug level (and in the event's detail, dyknow plan)
            head = ": ".join(line.strip().rstrip(":") for line in why.splitlines()[:2])  # "cannot plan T: nothing can provide T"
            log.warning(
                "request %s is degraded (%s): %s (the planner's reasons: its event, or dyknow plan)", request.tag, _cause(symptom), head
            )
            log.debug("request %s is degraded: %s", request.tag, why)
        self._watch_specs(request)


class _Recovery:
    """Waits for the first message of a new configuration on the request's key.

    Armed before the anchor switches (so that first message cannot slip by). That message may
    reach the anchor before the loop has recorded the adaptation: the anchor then holds it until
    the adaptation is in the history (at most :data:`_RECORD_WAIT_S`, in practice microseconds),
    so whoever sees the stream change finds the adaptation that changed it in
    ``get_adaptations``.
    """

    def __init__(self, loop: AdaptationLoop) -> None:
        self._loop = loop
        self._lock = threading.Lock()
        self._arrival_ns: int | None = None
        self._event: AdaptationEvent | None = None
        self._request: _Request | None = None
        self._recorded = threading.Event()

    def arm(self, request: _Request) -> Callable[[str], None]:
        self._request = request
        if request.standby_mode == "warm":  # the next standby: once the stream flows again (at most a second from now)
            request.standby_due = True
            request.standby_after_ns = time.time_ns() + _STANDBY_WAIT_NS

        def before_switch(output_key: str) -> None:
            anchor = self._loop.runtime.unit(request.anchor)
            if isinstance(anchor, RequestAnchor):
                anchor.expect(output_key, self._arrived)

        return before_switch

    def _arrived(self, arrival_ns: int) -> None:  # on the anchor's thread, before it relays the message
        self._recorded.wait(_RECORD_WAIT_S)
        with self._lock:
            self._arrival_ns = arrival_ns
            event = self._event
        request = self._request
        if request is not None and request.standby_due:  # the stream flows again: the standby may be built now
            request.standby_after_ns = 0
            self._loop._report(Symptom("recovered", arrival_ns, detail=f"{request.tag} flows again"))
        if event is not None:
            self._finish(event, arrival_ns)

    def adapted(self, event: AdaptationEvent) -> None:
        """The adaptation is in the history: the anchor may relay the new configuration."""
        self._recorded.set()
        with self._lock:
            self._event = event
            arrival = self._arrival_ns
        if arrival is not None:
            self._finish(event, arrival)

    def _finish(self, event: AdaptationEvent, arrival_ns: int) -> None:
        done = replace(event, kind="recovered", recovery_ms=round((arrival_ns - event.fault_ns) / 1e6, 3))

        def emit() -> None:  # not on the anchor's thread: listeners and Zenoh may take a moment
            with self._loop._lock:
                self._loop._emit(done)

        threading.Thread(target=emit, name="dyknow-recovery", daemon=True).start()


def _same(request: _Request, plan: Plan) -> bool:
    """Whether the request already runs this configuration (same labels and reused units)."""
    current = sorted(request.units.values())
    return current == sorted(_label_ref(u) for u in plan.units)


def _label_ref(unit: PlannedUnit) -> str:
    """A planned unit's transformation as the request records it: ``label``, or ``label@manager``."""
    return qualify(unit.label, unit.manager) if unit.remote else unit.label


def _on(ref: str, manager: str | None) -> bool:
    """Whether a unit reference (``name@manager``) is on ``manager``."""
    return manager is not None and ref.endswith(f"@{manager}")


def _cause(symptom: Symptom) -> str:
    return _what(symptom) + (", after the dwell time" if symptom.deferred else "")


def _what(symptom: Symptom) -> str:
    if symptom.kind == "failed":
        return f"unit {symptom.unit!r} failed: {symptom.detail}"
    if symptom.kind == "destroyed":
        return f"unit {symptom.unit!r} was destroyed"
    if symptom.kind == "stalled":
        return f"unit {symptom.unit!r} stalled: {symptom.detail}"
    if symptom.kind == "measurement":
        return f"measurement {symptom.detail}"
    if symptom.kind == "retry":
        return f"retry: {symptom.detail}"
    if symptom.kind == "resumed":
        return f"unit {symptom.unit!r} resumed"
    if symptom.kind == "peer-lost":
        return f"manager {symptom.manager!r} was lost"
    if symptom.kind == "peer-found":
        return f"manager {symptom.manager!r} was found"
    if symptom.kind == "requirement" and symptom.label is not None:
        return f"requirement of {symptom.label} violated: {symptom.detail}"
    if symptom.kind == "requirement":
        return f"requirement violated: {symptom.detail}"
    if symptom.kind == "peer-trusted":
        return f"manager {symptom.manager!r} is trusted again: {symptom.detail}"
    if symptom.kind == "peer-changed":
        return f"manager {symptom.manager!r} changed: {symptom.detail}" if symptom.detail else f"manager {symptom.manager!r} changed"
    return symptom.detail or symptom.kind
