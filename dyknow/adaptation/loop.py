"""The loop itself: :class:`AdaptationLoop` runs the steps on a thread of its own, one symptom at a
time: what the monitor saw updates the knowledge, the analyzer says which requests it affects, and
the adapter plans and executes; between symptoms it ticks (deadlines, back-offs, opportunities
waiting for the dwell time, standbys to build).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import replace

from dyknow.adaptation.adapt import Adapter
from dyknow.adaptation.analyze import Analyzer
from dyknow.adaptation.anchor import ANCHOR_LABEL
from dyknow.adaptation.damping import Flaps
from dyknow.adaptation.events import Journal
from dyknow.adaptation.knowledge import DEFAULT_DWELL_S, AdaptationEvent, Knowledge
from dyknow.adaptation.monitor import Monitor, Symptom
from dyknow.adaptation.reconfigure import Reconfigurer
from dyknow.adaptation.requests import Requests
from dyknow.adaptation.requirements import Requirements
from dyknow.adaptation.runtime import Runtime
from dyknow.model import LOCAL, Owner, RequestInfo, UnitEvent

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs

_TICK_S = 0.02  # deadlines, back-offs and deferred opportunities are checked this often


class AdaptationLoop:
    """Runs monitor, analyzer and adapter on a thread of its own, one symptom at a time.

    Its parts share the :class:`Knowledge` and the loop's lock: a request taken or given back
    (:meth:`request`, :meth:`release`) waits for the adaptation in progress, and the other way
    round.
    """

    def __init__(self, runtime: Runtime, *, dwell_s: float = DEFAULT_DWELL_S, damping: Flaps | None = None) -> None:
        self.runtime = runtime
        self.knowledge = Knowledge(damping)
        self.dwell_ns = int(dwell_s * 1e9)
        self._lock = threading.RLock()
        self._symptoms: queue.SimpleQueue[Symptom | None] = queue.SimpleQueue()
        self._closed = False
        self.monitor = Monitor(runtime.deadline_ports, self.knowledge, self._report)
        self.analyzer = Analyzer(runtime, self.knowledge, dwell_ns=self.dwell_ns)
        self.reconfigurer = Reconfigurer(runtime, self.knowledge)
        self._journal = Journal(runtime, self.knowledge, self._lock)
        # (the loop itself requests the other terms of a requirement's formula, and gives them back)
        self._requirements = Requirements(runtime, self.knowledge, self.reconfigurer, self, self._report, self.dwell_ns, self._journal)
        self._adapter = Adapter(
            runtime, self.knowledge, self.analyzer, self.reconfigurer, self._requirements, self._journal, self._report, self.dwell_ns
        )
        self._requests = Requests(
            runtime, self.knowledge, self.analyzer, self.reconfigurer, self._requirements, self._adapter, self._report, self._lock
        )
        self._thread = threading.Thread(target=self._run, name=f"dyknow-{runtime.name}-adaptation", daemon=True)
        self._thread.start()

    # -- requests

    def request(
        self,
        tag: str,
        *,
        standby: str | None = None,
        require: Iterable[str] = (),
        owner: Owner = LOCAL,
        readable: Callable[[str], None] | None = None,
        max_references: int | None = None,
    ) -> str:
        """Plan and wire a configuration providing ``tag``; returns its stable key
        (:meth:`Requests.request <dyknow.adaptation.requests.Requests.request>` says how)."""
        return self._requests.request(tag, standby=standby, require=require, owner=owner, readable=readable, max_references=max_references)

    def release(self, key: str, *, owner: Owner = LOCAL, force: bool = False) -> int:
        """Give back one reference of ``owner`` to a request (``force``: every reference); the
        references that remain (:meth:`Requests.release <dyknow.adaptation.requests.Requests.release>`)."""
        return self._requests.release(key, owner=owner, force=force)

    def release_holder(self, key: str, holder: str) -> int:
        """Give back every reference the client ``holder`` took to the request on ``key`` (it is
        gone: :mod:`dyknow.holders`); the references that remain."""
        return self._requests.release_holder(key, holder)

    def requests(self) -> list[RequestInfo]:
        """The active requests, by key (never waits for a request being planned or adapted)."""
        return self._requests.infos()

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
        return self._journal.on_event(listener)

    def history(self) -> list[AdaptationEvent]:
        """Every adaptation so far, oldest first (each with its recovery time once recovered);
        a copy taken without waiting for an adaptation in progress."""
        return self._journal.history()

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

    # -- the loop

    def _report(self, symptom: Symptom) -> None:
        if not self._closed:
            self._symptoms.put(symptom)

    def _busy(self) -> bool:
        """Whether anything needs the periodic tick: requests, deadlines, back-offs, deferrals."""
        knowledge = self.knowledge
        return bool(knowledge.requests or knowledge.backoff or self.analyzer.deferring() or self.runtime.deadline_ports())

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
                    self._requirements.retry_unwatched(now)  # (requirements of transformations not watched yet: every second)
                    for key, opportunity in self.analyzer.due(now):
                        changed = True
                        request = self.knowledge.requests.get(key)
                        if request is not None:  # timed from now: the wait was our choice, not the fault's
                            waited = replace(opportunity, time_ns=now, deferred=True, raised_ns=opportunity.time_ns)
                            self._adapter.adapt(request, waited, fault=False)
                    # after the switches, and once their stream flows again: standbys follow what changed
                    for request in sorted(self.knowledge.requests.values(), key=lambda r: r.key):
                        if request.standby_mode == "warm" and (changed or request.standby_due) and request.standby_after_ns <= now:
                            request.standby_due = False
                            self._adapter.maintain_standby(request, time.time_ns())
            except Exception:
                log.exception("adaptation loop error (it keeps running)")

    def _handle(self, symptom: Symptom) -> None:
        """One symptom, in the order of the steps: the knowledge takes in what it says, then the
        analyzer finds the requests it affects and the adapter adapts each (a requirement's
        verdicts and the trials in the shadow go to the suspects)."""
        if symptom.kind in ("spawned", "recovered"):
            return  # only wakes the loop up (for a tick: deadlines to watch, or to forget; a standby to build)
        if symptom.kind in ("failed", "destroyed") and symptom.unit is not None and self.analyzer.stale(symptom):
            return  # about an earlier unit of that name (one the loop replaced since): nothing to do
        knowledge = self.knowledge
        adapter = self._adapter
        if symptom.kind in ("failed", "stalled") and symptom.label and symptom.label != ANCHOR_LABEL:
            knowledge.fail(symptom.label, symptom.time_ns)
        if symptom.kind in ("stalled", "resumed"):
            self.runtime.changed()  # the other managers see it in this manager's summary
        if symptom.kind == "peer-lost" and symptom.manager is not None:
            knowledge.lost(symptom.manager, symptom.time_ns)
        if symptom.kind == "peer-found" and symptom.manager is not None:
            knowledge.found(symptom.manager, symptom.time_ns)
        if symptom.kind == "peer-changed" and symptom.manager is not None:
            for request, seen, fault in self.analyzer.peer_changed(symptom, symptom.manager):
                adapter.adapt(request, seen, fault)
            return
        if symptom.kind == "requirement":
            adapter.suspects.violated(symptom)
            return
        if symptom.kind in ("trial-due", "trial-held", "trial-failed", "held"):
            adapter.suspects.judged(symptom)
            return
        if symptom.kind in ("failed", "destroyed", "stalled") and symptom.unit is not None:
            adapter.suspects.unit_lost(symptom)
        for request, fault in self.analyzer.affected(symptom):
            if symptom.unit is not None and symptom.unit == request.anchor:
                adapter.reanchor(request)
                continue
            adapter.adapt(request, symptom, fault)
