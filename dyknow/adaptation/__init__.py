"""Self-adaptation: keep requested streams flowing when resources fail (a MAPE-K loop).

A client asks for information by meaning: ``manager.request("BallPosition(field)")`` returns a key.
Behind the key sits an *anchor*, a relay unit owned by the request whose output is the key; the
planner's configuration feeds the anchor's input. Adapting means wiring a new configuration and
rebinding the anchor's input, so **the requested key never changes** and consumers keep receiving
without resubscribing.

The loop is built from explicit parts, after MAPE-K (Kephart & Chess; RoCS), with the three layers
of Sykes et al.: requests are the goals, this package manages change, the manager and proxies
control the components. Each part is a module of this package:

- :mod:`~dyknow.adaptation.runtime`: what the loop needs of its manager (:class:`Runtime`);
- :mod:`~dyknow.adaptation.knowledge` (K);
- :mod:`~dyknow.adaptation.monitor` (M), with :mod:`~dyknow.adaptation.requirements`, the
  monitor units watching the temporal formulas requests require;
- :mod:`~dyknow.adaptation.analyze` (A);
- :mod:`~dyknow.adaptation.adapt` (P and E for one request: what to plan for, what to do with
  the plan) over :mod:`~dyknow.adaptation.reconfigure` (planning and wiring), with
  :mod:`~dyknow.adaptation.suspects` (requirements that learn, below);
- :mod:`~dyknow.adaptation.requests`: the goals, requests taken and given back by reference;
- :mod:`~dyknow.adaptation.events`: the record of adaptations and their recovery times;
- :mod:`~dyknow.adaptation.anchor`: the unit that holds a request's key;
- :mod:`~dyknow.adaptation.loop`: the loop that runs them, one symptom at a time.

- :class:`Knowledge`: the requests, the latest measurements, failed transformations and their
  back-off, stalled units, and the history of adaptations.
- :class:`Monitor`: turns what happens into :class:`Symptom` s: a unit failed (an exception, or a
  remote producer's liveliness token vanished), a unit was destroyed, an output port with a
  ``deadline-ms`` fell silent (stalled) or spoke again, a measurement arrived, a back-off ended.
- :class:`Analyzer`: which requests a symptom affects, and whether it is a *fault* (the current
  configuration is broken: adapt now) or an *opportunity* (a preferred configuration may be
  available again: adapt, but not more often than the dwell time allows).
- :class:`Reconfigurer` (plan and execute): re-plans with failed and unavailable transformations
  excluded, and the request's suspects (below), and the request's own units set aside so that
  preferences decide, its present configuration winning ties (hysteresis: another of equal cost
  wins only on a manager that carries clearly fewer units, :func:`~dyknow.planner.load_margin`,
  the request's own units not counted, so an idle request never moves for a tie); then changes as
  little as possible: units of the new configuration that already run for the request are kept
  (with their state) and only rebound where their upstream changed; new ones are spawned,
  consumers before producers; the anchor is rebound; units nothing uses any more are destroyed last.

**Requirements that learn.** A requirement's false state moves the request off one of its
transformations, which becomes a *suspect* of the request: avoided by its plans, and tried again
*in the shadow* at each back-off (1 s, doubled after each failed trial, at most
:data:`BACKOFF_MAX_S`): the configuration the request would prefer with it runs beside the active
one, watched by monitors of the requirements over its own output (a :class:`~dyknow.adaptation.monitor.Judge`
follows their verdicts). It fails at a false verdict; once the requirements have held there for the
dwell time, the request moves onto it (only the anchor moves). So a producer that keeps violating
never gets the stream back, and one that is fixed is trusted again within its present back-off plus
the dwell time plus its first verdict. A requirement false with no other configuration leaves the
request running where it is, *degraded in place* (one log line, one event), until its requirements
hold again for the dwell time.

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
request does (after the dwell time), and the configuration it leaves becomes the standby; the
standby never uses a suspect. Releasing the request tears the
standby down too. The model lists the standby's units (:class:`~dyknow.model.RequestInfo`), and
the events of a switch onto the standby say so (``standby``).

Flapping is prevented by a dwell time (an opportunity never switches a request twice within it)
and by flap damping (:mod:`dyknow.adaptation.damping`): each relapse adds to a penalty that decays
with a half-life, as route-flap damping does. A suspect trusted again whose requirement is false
again soon after is not tried again until its penalty decays (at most 15 minutes, :data:`TRIALS`);
a transformation that fails again waits longer (1 s, 2 s, 4 s ... up to 60 s while its failures
come close together, :data:`FAILURES`); a manager that comes back is trusted again by an
opportunity after the dwell time, and when lost again within seconds only once the penalty of its
losses decays (at most 30 s, :data:`LINKS`); a fault or a degraded request uses it at once. So a
link that goes down and up every few seconds moves a request off it, and back only once it holds.
When no configuration exists the request is *degraded*, and recovered later when possible.

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

from dyknow.adaptation.analyze import Analyzer
from dyknow.adaptation.anchor import ANCHOR_LABEL, ANCHOR_SPEC, WARM_ANCHOR_SPEC, RequestAnchor
from dyknow.adaptation.damping import FAILURES, LINKS, TRIALS, Damping, Flaps
from dyknow.adaptation.knowledge import (
    BACKOFF_FIRST_S,
    BACKOFF_MAX_S,
    DEFAULT_DWELL_S,
    FLAP_HOLD_MAX_S,
    FLAP_WINDOW_S,
    AdaptationEvent,
    Knowledge,
)
from dyknow.adaptation.loop import AdaptationLoop
from dyknow.adaptation.monitor import Monitor, Symptom
from dyknow.adaptation.reconfigure import Reconfigurer
from dyknow.adaptation.runtime import DeadlinePort, Runtime

__all__ = [
    "ANCHOR_LABEL",
    "ANCHOR_SPEC",
    "BACKOFF_FIRST_S",
    "BACKOFF_MAX_S",
    "DEFAULT_DWELL_S",
    "FAILURES",
    "FLAP_HOLD_MAX_S",
    "FLAP_WINDOW_S",
    "LINKS",
    "TRIALS",
    "WARM_ANCHOR_SPEC",
    "AdaptationEvent",
    "AdaptationLoop",
    "Analyzer",
    "Damping",
    "DeadlinePort",
    "Flaps",
    "Knowledge",
    "Monitor",
    "Reconfigurer",
    "RequestAnchor",
    "Runtime",
    "Symptom",
]
