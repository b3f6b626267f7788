"""The loop itself: :class:`AdaptationLoop` runs monitor, analyzer and reconfigurer on a thread of its
own, one symptom at a time; it owns the requests' lifecycle (request, release, requirements and
their watches), the dwell time against flapping, the warm standby's upkeep, the trials in the
shadow of transformations a requirement found false, and each adaptation's record (its recovery
time).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import Any

from dyknow import keys
from dyknow.adaptation.analyze import Analyzer
from dyknow.adaptation.anchor import ANCHOR_LABEL, ANCHOR_SPEC, WARM_ANCHOR_SPEC, RequestAnchor
from dyknow.adaptation.knowledge import (
    BACKOFF_FIRST_S,
    BACKOFF_MAX_S,
    DEFAULT_DWELL_S,
    AdaptationEvent,
    Knowledge,
    Request,
    SpecWatch,
    Suspect,
    Trial,
)
from dyknow.adaptation.monitor import Judge, Monitor, Symptom
from dyknow.adaptation.reconfigure import Reconfigurer, is_current
from dyknow.adaptation.runtime import Runtime
from dyknow.errors import AccessError, DyKnowError, PlanningError, UnitError
from dyknow.model import LOCAL, Owner, RequestInfo, UnitEvent, check_standby
from dyknow.planner import Plan
from dyknow.reasoning.progression import Verdict
from dyknow.reasoning.syntax import Formula
from dyknow.reasoning.unit import VERDICTS_PORT, FormulaMonitor, monitor_spec, term_ports
from dyknow.tags import parse_term

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs

_TICK_S = 0.02  # deadlines, back-offs and deferred opportunities are checked this often
_STANDBY_WAIT_NS = 1_000_000_000  # after a switch, the next standby waits this long at most for the stream
_RECORD_WAIT_S = 1.0  # how long an anchor holds a new configuration's first message for its adaptation's record


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
        # requests degraded in place: key -> (the judge of their requirements, the "degraded" event)
        self._in_place: dict[str, tuple[Judge, AdaptationEvent]] = {}
        self._closed = False
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
    ) -> str:
        """Plan and wire a configuration providing ``tag``; returns its stable key.

        ``standby="warm"`` keeps the next-best configuration running beside it, so that a fault
        only moves the anchor (see the module documentation); ``"none"`` (or None, the default)
        does not. Requesting a tag again shares the request (one more reference); asking for a
        warm standby then gives the shared request one, which it keeps until it is released.
        An unknown ``standby`` is a :class:`UnitError` naming the allowed values, raised before
        anything changes.

        ``require``: temporal formulas (:mod:`dyknow.reasoning`) the stream must satisfy; a term
        that is ``tag`` reads the request's own stream, any other is requested in turn. A state
        a requirement finds false is a fault: the request moves to the next-best configuration
        (the cause names the formula), unless the present one has not run for the dwell time
        yet. A formula that does not read is a :class:`~dyknow.errors.FormulaError`, raised
        before anything changes. The requirements belong to the reference: they go when it is
        released, unless another reference requires them too.

        ``owner``: who takes the reference (:class:`~dyknow.model.Owner`; only it may give it
        back). ``readable(tag)`` raises when the owner may not read the stream of a tag: it is
        asked of ``tag`` and of every term of every formula before anything is planned. When the
        call fails, nothing of it remains.
        """
        mode = check_standby(standby)
        runtime = self.runtime
        canonical = str(parse_term(tag))
        key = keys.request_key(runtime.name, canonical)
        formulas = [runtime.check_formula(text) for text in require]  # (bounded before anything is requested)
        texts = tuple(dict.fromkeys(str(f) for f in formulas))
        if readable is not None:
            readable(canonical)
            for formula in formulas:
                for term in term_ports(formula):
                    if term != canonical:
                        readable(term)
        with self._lock:
            existing = self.knowledge.requests.get(key)
            if existing is not None:
                self._require(existing, [f for f in formulas if str(f) not in existing.watches])  # (undoes itself when it fails)
                existing.owners.append((owner, texts))
                if mode == "warm" and existing.standby_mode != "warm":
                    self._warm_up(existing)
                return key
            now = time.time_ns()
            request = Request(canonical, key, anchor=self._anchor_name(canonical), standby_mode=mode, owners=[(owner, texts)])
            plan = self.reconfigurer.plan(request, now)  # PlanningError: nothing fits, nothing changes
            self._spawn_anchor(request, plan.output_key)
            self.knowledge.requests[key] = request
            try:
                self.reconfigurer.apply(request, plan)
            except BaseException:
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
            except BaseException:
                self.release(key, force=True)
                raise
            self._watch_specs(request)
            return key

    def _require(self, request: Request, formulas: list[Formula]) -> None:
        """Watch ``formulas`` over ``request``'s stream: a monitor unit each, whose false
        verdicts become "requirement" symptoms (see :meth:`request`). All or nothing: when one
        cannot be watched, those this call set up are taken down again before it raises."""
        added: list[str] = []
        try:
            for formula in formulas:
                text = str(formula)
                if text in request.watches:
                    continue
                bindings: dict[str, str] = {}
                needs: list[str] = []
                try:
                    for term, port in term_ports(formula).items():
                        if term == request.tag:
                            bindings[port] = request.key
                        else:
                            needs.append(self.request(term))
                            bindings[port] = needs[-1]
                    request.watch_count += 1
                    name = f"{request.anchor}-require-{request.watch_count}"
                    bindings[VERDICTS_PORT] = f"{request.key}/requirements/{request.watch_count}"
                    self.runtime.spawn(monitor_spec(formula, label="requirement"), name, bindings=bindings)
                except BaseException:
                    self._give_back(needs)
                    raise
                self.knowledge.managed.add(name)
                request.watches[text] = (name, tuple(needs))
                added.append(text)
                watcher = self.runtime.unit(name)
                if isinstance(watcher, FormulaMonitor):
                    key = request.key
                    watcher.listen(lambda verdict, text=text, key=key: self._verdict(key, text, verdict))  # type: ignore[misc]
        except BaseException:
            self._unrequire(request, added)
            raise

    def _unrequire(self, request: Request, formulas: Iterable[str]) -> None:
        """Stop watching ``formulas`` over ``request``: their monitors go, their terms are given back."""
        for text in formulas:
            watch = request.watches.pop(text, None)
            if watch is not None:
                self.reconfigurer.cleanup([watch[0]])
                self._give_back(watch[1])

    def _give_back(self, needs: Iterable[str]) -> None:
        for needed in needs:
            if needed in self.knowledge.requests:
                self.release(needed)

    def _verdict(self, key: str, formula: str, verdict: Verdict, unit: str | None = None, label: str | None = None) -> None:
        """A requirement's verdict (on its monitor's thread): a false one is a symptom; while the
        request is degraded in place, its judge sees them all."""
        in_place = self._in_place.get(key)
        if in_place is not None:
            in_place[0].verdict(formula, verdict)
        if verdict.verdict is False:
            symptom = Symptom("requirement", time.time_ns(), unit=unit, label=label, detail=formula, request=key, state_ns=verdict.t_ns)
            self._report(symptom)

    def _watch_specs(self, request: Request) -> None:
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
                    request.spec_watches[(ref, text)] = self._spec_watch(request, ref, label, self.runtime.check_formula(text))
                except DyKnowError as exc:
                    log.warning("cannot watch the requirement %r of %s for %s: %s", text, label, request.tag, exc)

    def _unit_bindings(self, ref: str, label: str, formula: Formula) -> tuple[dict[str, str], list[str]]:
        """Where a monitor of a requirement of unit ``ref`` (of transformation ``label``) reads
        each term: a term that is one of the unit's output tags reads that output, any other is
        requested in turn. Returns the bindings and those requests (given back on a failure)."""
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
        except DyKnowError:
            self._give_back(needs)
            raise
        return bindings, needs

    def _spec_watch(self, request: Request, ref: str, label: str, formula: Formula) -> SpecWatch:
        bindings, needs = self._unit_bindings(ref, label, formula)
        try:
            request.spec_watch_count += 1
            n = request.spec_watch_count
            name = f"{request.anchor}-spec-require-{n}"
            key = bindings[VERDICTS_PORT] = f"{request.key}/requirements/spec-{n}"
            self.runtime.spawn(monitor_spec(formula, label="requirement"), name, bindings=bindings)
        except DyKnowError:
            self._give_back(needs)
            raise
        self.knowledge.managed.add(name)
        watcher = self.runtime.unit(name)
        if isinstance(watcher, FormulaMonitor):
            text, rkey = str(formula), request.key
            watcher.listen(lambda verdict, text=text, rkey=rkey, ref=ref, label=label: self._verdict(rkey, text, verdict, ref, label))  # type: ignore[misc]
        return SpecWatch(label, name, key, tuple(needs))

    def _warm_up(self, request: Request) -> None:
        """A shared request asked for a warm standby: a new anchor that can hold one, then the standby."""
        request.standby_mode = "warm"
        self.reconfigurer.cleanup([request.anchor])
        request.anchor = self._anchor_name(request.tag)
        self._spawn_anchor(request, request.output_key or f"{request.key}/none")
        self._maintain_standby(request, time.time_ns())

    def _spawn_anchor(self, request: Request, input_key: str) -> None:
        bindings = {"in": input_key, "out": request.key}
        spec = ANCHOR_SPEC
        if request.standby_mode == "warm":
            spec = WARM_ANCHOR_SPEC
            if request.standby_key is not None:
                bindings["standby"] = request.standby_key
        self.runtime.spawn(spec, request.anchor, bindings=bindings)
        self.knowledge.managed.add(request.anchor)

    def release(self, key: str, *, owner: Owner = LOCAL, force: bool = False) -> int:
        """Give back one reference of ``owner`` to a request (``force``: every reference, whoever
        took it); the requirements it alone added go with it, and the last one tears down what
        only the request used. Returns the references that remain (0: the request is gone).

        :class:`UnitError` when there is no request on ``key``; :class:`AccessError` when
        ``owner`` holds none of its references (:meth:`dyknow.model.Owner.holds`).
        """
        with self._lock:
            request = self._known(key)
            if force:
                dropped = list(request.owners)
            else:
                dropped = [request.owners[self._pick(request, owner)]]
            return self._drop(request, dropped)

    def release_holder(self, key: str, holder: str) -> int:
        """Give back every reference the client ``holder`` took to the request on ``key`` (it is
        gone: :mod:`dyknow.holders`); the references that remain."""
        with self._lock:
            request = self._known(key)
            return self._drop(request, [entry for entry in request.owners if entry[0].holder == holder])

    def _known(self, key: str) -> Request:
        request = self.knowledge.requests.get(key)
        if request is None:
            known = ", ".join(sorted(self.knowledge.requests)) or "none"
            raise UnitError(f"no request on key {key!r}", where=f"manager {self.runtime.name!r}", expected=f"one of the active requests: {known}")
        return request

    def _pick(self, request: Request, owner: Owner) -> int:
        """Which of ``request``'s references a release by ``owner`` gives back: its own exact one
        (the newest), else one it may give back, kept ones first; :class:`AccessError` when none."""
        entries = list(enumerate(request.owners))[::-1]
        for i, (taken, _) in entries:
            if taken == owner:
                return i
        allowed = [(i, taken) for i, (taken, _) in entries if owner.holds(taken)]
        for i, taken in allowed:
            if taken.holder is None and not taken.local:
                return i
        if allowed:
            return allowed[0][0]
        holders = sorted({str(taken) for taken, _ in request.owners})
        raise AccessError(
            f"{owner.who()} holds no reference to the request on {request.key!r} (its references: {', '.join(holders) or 'none'})",
            where=f"manager {self.runtime.name!r}",
            expected="a release by the client or caller that requested it; an admin may force it (release with force, dyknow release KEY --force)",
        )

    def _drop(self, request: Request, dropped: list[tuple[Owner, tuple[str, ...]]]) -> int:
        for entry in dropped:
            request.owners.remove(entry)
        if request.owners:
            still = request.required()
            self._unrequire(request, [text for _, texts in dropped for text in texts if text not in still])
            return request.references
        key = request.key
        self._end_trial(request)
        del self.knowledge.requests[key]
        self._deferred.pop(key, None)
        self._in_place.pop(key, None)
        orphans = [n for n in request.held() if n in self.knowledge.managed and not self.knowledge.users(n)]
        watches = list(request.spec_watches.values())
        self.reconfigurer.cleanup([*(w[0] for w in request.watches.values()), *(w.monitor for w in watches), request.anchor, *orphans])
        self._give_back([*(n for w in request.watches.values() for n in w[1]), *(n for w in watches for n in w.needs)])
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
        self._record(event)
        self._announce(event)

    def _record(self, event: AdaptationEvent) -> None:
        """Keep ``event`` in the history (a recovery replaces its adaptation's entry)."""
        history = self.knowledge.history
        for i in range(len(history) - 1, -1, -1):  # a recovery completes its adaptation's entry
            if history[i].id == event.id:
                history[i] = event
                break
        else:
            history.append(event)

    def _announce(self, event: AdaptationEvent) -> None:
        """Publish ``event`` and hand it to the listeners."""
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
        if symptom.kind in ("trial-due", "trial-held", "trial-failed", "held"):
            self._judged(symptom)
            return
        if symptom.kind in ("failed", "destroyed", "stalled") and symptom.unit is not None:
            for request in list(knowledge.requests.values()):
                trial = request.trial
                if trial is not None and symptom.unit in trial.units:  # not the suspect's doing: the same wait again
                    log.info("trial %d of %s for %s ended: %s", trial.serial, trial.label, request.tag, _what(symptom))
                    self._end_trial(request)
                    self._reschedule(request.suspects.get(trial.label), time.time_ns(), failed=False)
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
        that transformation becomes a *suspect* of the request: its plans avoid it until a trial
        in the shadow shows the requirements hold on it (:meth:`_judged`). When no configuration
        without one of them exists, the request runs on, degraded in place (:meth:`_hold_in_place`)."""
        request = self.knowledge.requests.get(symptom.request or "")
        if request is None or request.state != "active" or symptom.state_ns < request.last_change_ns + self.dwell_ns:
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
                plan = self.reconfigurer.plan(request, now, exclude={label})
            except PlanningError:
                continue
            if best is None or plan.cost < best[0]:
                best = (plan.cost, label)
        if best is None:
            old = tuple(sorted(set(request.units.values())))
            where = f" of {symptom.label}" if symptom.label is not None else ""
            self._hold_in_place(request, symptom, old, f"its requirement{where} {symptom.detail!r} is false, and no other configuration provides {request.tag}")
            return
        request.suspects[best[1]] = Suspect(best[1], symptom.detail, now, next_trial_ns=now + int(BACKOFF_FIRST_S * 1e9))
        self._adapt(request, symptom, fault=True)

    # -- suspects: their trials in the shadow, and requests degraded in place

    def _judged(self, symptom: Symptom) -> None:
        """A suspect's trial is due, held or failed; or a request degraded in place holds again."""
        request = self.knowledge.requests.get(symptom.request or "")
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
            self._end_trial(request)
            self._reschedule(request.suspects.get(trial.label), time.time_ns(), failed=True)
        else:
            self._adapt(request, symptom, fault=False)  # "trial-held": an opportunity, taken after the dwell time (_trust)

    def _reschedule(self, suspect: Suspect | None, now: int, *, failed: bool, slower: bool = False) -> None:
        """The next trial of ``suspect``: after twice the wait when its trial failed (or could not
        start: ``slower``), else after the same wait."""
        if suspect is None:
            return
        if failed:
            suspect.failed += 1
        if failed or slower:
            suspect.backoff_s = min(BACKOFF_MAX_S, suspect.backoff_s * 2)
        suspect.next_trial_ns = now + int(suspect.backoff_s * 1e9)
        suspect.announced = False

    def _start_trial(self, request: Request, label: str) -> None:
        """Run the configuration the request would prefer with its suspect ``label`` in the
        shadow, its requirements watched there by monitors of their own; unless the planner
        would not use the suspect now, or the request is busy (then: the same wait again)."""
        suspect = request.suspects.get(label)
        if suspect is None:
            return
        now = time.time_ns()
        if request.state != "active" or request.trial is not None or request.in_place:
            self._reschedule(suspect, now, failed=False)
            return
        try:
            plan = self.reconfigurer.plan(request, now, trying={label})
        except PlanningError:
            self._reschedule(suspect, now, failed=False)
            return
        if label not in self.reconfigurer.labels(plan) or is_current(request, plan):
            self._reschedule(suspect, now, failed=False)  # the planner would not use it now anyway
            return
        request.trial_count += 1
        try:
            trial = request.trial = self.reconfigurer.wire_trial(request, plan, label, request.trial_count, now)
            self._watch_trial(request, trial)
        except DyKnowError as exc:
            log.warning("could not try %s for %s in the shadow: %s", label, request.tag, exc)
            self._end_trial(request)
            self._reschedule(suspect, now, failed=False, slower=True)
            return
        log.info(
            "trial %d of %s for %s in the shadow: %s (its requirements must hold for %g s there)",
            trial.serial,
            label,
            request.tag,
            ", ".join(sorted(set(trial.units.values()))),
            self.dwell_ns / 1e9,
        )

    def _watch_trial(self, request: Request, trial: Trial) -> None:
        """Monitors of the request's requirements over the trial's output (their other terms read
        what the request's own monitors read), and of the trial's new units' own requirements;
        one judge over them all. :class:`DyKnowError` when one cannot be watched."""
        watched: list[tuple[str, Formula, dict[str, str]]] = []  # (judge's name of it, formula, bindings)
        for text, (monitor, _) in request.watches.items():
            formula = self.runtime.check_formula(text)
            current = self.runtime.get_config(monitor)
            bindings = {port: trial.output_key if term == request.tag else current[port] for term, port in term_ports(formula).items()}
            watched.append((text, formula, bindings))
        planner = self.reconfigurer.planner()
        for unit in trial.plan.new_units:
            ref, label = unit.ref, trial.units.get(unit.ref)
            if label is None:
                continue
            for text in planner.spec(label).requirements:
                formula = self.runtime.check_formula(text)
                bindings, needs = self._unit_bindings(ref, label, formula)
                trial.needs.extend(needs)
                watched.append((f"{text} (of {label})", formula, bindings))
        if not watched:
            raise UnitError("no requirement to judge it by", where=f"the trial of {trial.label}")
        key, serial = request.key, trial.serial

        def report(outcome: str, formula: str) -> None:
            detail = f"{trial.label} held its requirements for {self.dwell_ns / 1e9:g} s" if outcome == "held" else f"requirement {formula!r} was false there"
            self._report(Symptom(f"trial-{outcome}", time.time_ns(), label=trial.label, detail=detail, request=key, trial=serial))

        judge = Judge([name for name, _, _ in watched], self.dwell_ns, report, strict=True)
        for k, (name, formula, bindings) in enumerate(watched, start=1):
            monitor = f"{request.anchor}-trial-{serial}-{k}"
            bindings[VERDICTS_PORT] = f"{request.key}/trials/{serial}/{k}"
            self.runtime.spawn(monitor_spec(formula, label="requirement"), monitor, bindings=bindings)
            self.knowledge.managed.add(monitor)
            trial.monitors.append(monitor)
            watcher = self.runtime.unit(monitor)
            if isinstance(watcher, FormulaMonitor):
                watcher.listen(lambda verdict, name=name: judge.verdict(name, verdict))  # type: ignore[misc]

    def _end_trial(self, request: Request) -> None:
        """Take the request's trial down: its monitors, its units nothing else holds, its terms."""
        trial = request.trial
        if trial is None:
            return
        orphans = self.reconfigurer.drop_trial(request)
        self.reconfigurer.cleanup([*trial.monitors, *orphans])
        self._give_back(trial.needs)

    def _trust(self, request: Request, symptom: Symptom) -> None:
        """A trial held (and the dwell time is over): its suspect is trusted again, and the request
        moves onto the trial's configuration (only the anchor moves), if the planner prefers it."""
        trial = request.trial
        if trial is None or trial.serial != symptom.trial:
            return
        request.suspects.pop(trial.label, None)
        now = time.time_ns()
        try:
            plan: Plan | None = self.reconfigurer.plan(request, now)
        except PlanningError:
            plan = None
        if plan is None or self.reconfigurer.labels(plan) != self.reconfigurer.labels(trial.plan):
            log.info("%s is trusted again for %s, but the planner prefers another configuration now", trial.label, request.tag)
            self._end_trial(request)
            self._adapt(request, replace(symptom, kind="preferred", detail=f"{trial.label} is trusted again"), fault=False)
            return
        old_labels = tuple(sorted(set(request.units.values())))
        monitors, needs = list(trial.monitors), list(trial.needs)
        recovery = _Recovery(self)
        try:
            orphans = self.reconfigurer.promote_trial(request, recovery.arm(request))
        except DyKnowError as exc:
            log.warning("switching %s onto its trial's configuration failed: %s", request.tag, exc)
            self._end_trial(request)
            return
        self.reconfigurer.cleanup(monitors)  # the request's own monitors read its key, which now carries the trial's stream
        self._give_back(needs)
        self._adapted(request, symptom, _cause(symptom), old_labels, orphans, recovery, standby=False)

    def _hold_in_place(self, request: Request, symptom: Symptom, old: tuple[str, ...], why: str) -> None:
        """A requirement is false and nothing else provides the tag: the request runs on where it
        is, degraded (one log line and one event, with the formula), until its requirements hold
        there for the dwell time (:meth:`_holds_again`) or another configuration comes."""
        self._end_trial(request)
        request.state, request.reason, request.in_place = "degraded", why, True
        event = AdaptationEvent(
            self._next_id, "degraded", request.tag, request.key, _cause(symptom), old, tuple(sorted(set(request.units.values()))), symptom.time_ns, detail=why
        )
        self._next_id += 1
        formulas = [*request.watches, *(formula for _, formula in request.spec_watches)]
        key = request.key
        judge = Judge(formulas, self.dwell_ns, lambda _, formula: self._report(Symptom("held", time.time_ns(), detail=formula, request=key)), strict=False)
        self._in_place[key] = (judge, event)
        self._emit(event)
        log.warning("request %s is degraded: %s; it runs on %s until its requirements hold again", request.tag, why, ", ".join(event.new) or "nothing")

    def _holds_again(self, request: Request, symptom: Symptom) -> None:
        """The requirements of a request degraded in place held for the dwell time: it is active
        again (its "degraded" event is completed as "recovered", with the time it took), and
        the suspects it runs on are trusted again."""
        entry = self._in_place.get(request.key)
        if entry is None or not request.in_place or not entry[0].done:
            return
        del self._in_place[request.key]
        for label in set(request.units.values()):
            request.suspects.pop(label, None)
        now = time.time_ns()
        event = entry[1]
        recovered = replace(event, kind="recovered", new=tuple(sorted(set(request.units.values()))), recovery_ms=round((now - event.fault_ns) / 1e6, 3))
        # in this order: whoever sees the request active (list_requests, on another thread) also
        # finds its "recovered" event and the log line, and listeners see it active
        log.info("request %s is active again: its requirements held for %g s on %s", request.tag, self.dwell_ns / 1e9, ", ".join(recovered.new))
        self._record(recovered)
        request.state, request.reason, request.in_place = "active", None, False
        self._announce(recovered)

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

    def _reanchor(self, request: Request, symptom: Symptom) -> None:
        """The anchor itself went: put a new one on the same key."""
        self.reconfigurer.cleanup([request.anchor])
        request.anchor = self._anchor_name(request.tag)
        self._spawn_anchor(request, request.output_key or f"{request.key}/none")

    def _adapt(self, request: Request, symptom: Symptom, fault: bool) -> None:
        now = time.time_ns()
        if not fault and request.state == "active" and now - request.last_change_ns < self.dwell_ns:
            # flapping guard: take the opportunity when the dwell time is over (the latest one wins,
            # but another manager's routine summary does not hide the cause already waiting, nor
            # does a routine measurement hide an ended back-off or probation)
            waiting = self._deferred.get(request.key)
            # (and a trial that held waits for its turn whatever comes meanwhile: taking it plans afresh)
            routine = (
                symptom.kind == "peer-changed"
                or (symptom.kind == "measurement" and waiting is not None and waiting[1].kind in ("retry", "peer-trusted"))
                or (waiting is not None and waiting[1].kind == "trial-held")
            )
            if waiting is None or not routine:
                self._deferred[request.key] = (request.last_change_ns + self.dwell_ns, symptom)
            return
        if symptom.kind == "trial-held":
            self._trust(request, symptom)
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
        suspects: list[str] = []  # the suspects a fault falls back on, when nothing else is left
        try:
            plan = self.reconfigurer.plan(request, now, managers_excluded=wary)
        except PlanningError as exc:
            if request.in_place and not fault:
                return  # it runs on where it is, degraded, until something else can provide its tag
            fallback = self._plan_on_suspects(request, now) if fault or request.state == "degraded" else None
            if fallback is None:
                if fault or request.state == "degraded":
                    self._degrade(request, symptom, old_labels, str(exc))
                return
            plan = fallback
            suspects = sorted(set(request.suspects) & self.reconfigurer.labels(plan))
        if not fault and (request.state == "active" or request.in_place) and is_current(request, plan):
            return  # already the preferred configuration (or, degraded in place, the only one)
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
        if suspects:
            formulas = ", ".join(repr(request.suspects[label].formula) for label in suspects)
            why = f"nothing but {', '.join(suspects)} provides {request.tag}, and its requirement {formulas} was false there"
            self._hold_in_place(request, symptom, old_labels, why)

    def _plan_on_suspects(self, request: Request, now: int) -> Plan | None:
        """The configuration ``request`` would run with its suspects allowed, when it has any and one exists."""
        if not request.suspects:
            return None
        try:
            return self.reconfigurer.plan(request, now, trying=set(request.suspects))
        except PlanningError:
            return None

    def _adapted(
        self,
        request: Request,
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
        self._in_place.pop(request.key, None)  # (a request degraded in place that moved is judged where it went)
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

    def _take_standby(self, request: Request, symptom: Symptom, old_labels: tuple[str, ...], fault: bool) -> None:
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
            if not is_current(request, preferred):  # e.g. a destroyed unit that can simply be spawned again
                self._deferred[request.key] = (
                    wired + self.dwell_ns,
                    Symptom("preferred", wired, detail="the preferred configuration can run again"),
                )

    def _leave(self, request: Request, orphans: list[str]) -> None:
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

    def _maintain_standby(self, request: Request, now: int) -> None:
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

    def _degrade(self, request: Request, symptom: Symptom, old: tuple[str, ...], why: str) -> None:
        was = request.state
        was_in_place = request.in_place
        self._end_trial(request)
        self._in_place.pop(request.key, None)
        request.state = "degraded"
        request.reason = why
        request.in_place = False
        if was != "degraded" or was_in_place:
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
    ``get_adaptations``. Not so when the new configuration keeps the unit that feeds the anchor
    (the key does not change): that unit is rebound first (consumers first, so nothing is lost),
    and what the new producers send can reach the request's key while the loop is still
    building, up to the build's time (milliseconds; a remote spawn's round trip) before the
    record. Holding the anchor over the build would block its lane for that long.
    """

    def __init__(self, loop: AdaptationLoop) -> None:
        self._loop = loop
        self._lock = threading.Lock()
        self._arrival_ns: int | None = None
        self._event: AdaptationEvent | None = None
        self._request: Request | None = None
        self._recorded = threading.Event()

    def arm(self, request: Request) -> Callable[[str], None]:
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
    if symptom.kind == "trial-held":
        return f"{symptom.detail} in the shadow (trial {symptom.trial})"
    if symptom.kind == "trial-failed":
        return f"trial {symptom.trial} of {symptom.label} failed: {symptom.detail}"
    if symptom.kind == "held":
        return f"requirement held again: {symptom.detail}"
    if symptom.kind == "peer-changed":
        return f"manager {symptom.manager!r} changed: {symptom.detail}" if symptom.detail else f"manager {symptom.manager!r} changed"
    return symptom.detail or symptom.kind
