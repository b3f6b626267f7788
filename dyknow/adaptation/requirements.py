"""The watches of requirements, the monitor's sensors for temporal formulas: :class:`Requirements`
spawns a monitor unit per formula a request requires (and per requirement of the transformations
serving it, and of a trial in the shadow) and turns their false verdicts into symptoms. A watch
closes its states once its stream has been idle for the reorder delay (``close_idle``), so a
stream that stops just as its requirement turns false is found false then, not at its next sample.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import Protocol

from dyknow.adaptation.events import Journal
from dyknow.adaptation.knowledge import AdaptationEvent, Knowledge, Request, SpecWatch, Trial
from dyknow.adaptation.monitor import Judge, Symptom
from dyknow.adaptation.reconfigure import Reconfigurer
from dyknow.adaptation.runtime import Runtime
from dyknow.errors import DyKnowError, UnitError
from dyknow.model import LOCAL, Owner
from dyknow.reasoning.progression import Verdict
from dyknow.reasoning.syntax import Formula
from dyknow.reasoning.unit import VERDICTS_PORT, FormulaMonitor, monitor_spec, term_ports
from dyknow.spec import TransformationSpec
from dyknow.tags import parse_term

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs

#: How often a requirement of a transformation that could not be watched is tried again.
RETRY_UNWATCHED_NS = 1_000_000_000


class Requester(Protocol):
    """What the watches need of the loop: the streams of a formula's other terms, requested in
    turn, and given back when the watch goes (:class:`~dyknow.adaptation.AdaptationLoop`)."""

    def request(self, tag: str) -> str:
        """Request ``tag``; its key."""
        ...

    def release(self, key: str) -> int:
        """Give back a reference to the request on ``key``."""
        ...


class Requirements:
    """Watches formulas over requests' streams: a monitor unit each, whose false verdicts become
    "requirement" symptoms (reported to the loop through ``report``).

    While a request is degraded in place, the judge :meth:`attach` ed to it sees every verdict of
    its requirements too. Requirements are never left unchecked in silence: a monitor that fails
    to start is an error like any other (:meth:`require`), and a requirement of a transformation
    that cannot be watched refuses a new request or marks a running one (:meth:`watch_specs`).
    ``journal`` records that mark (a "degraded" event, "recovered" once watched).
    """

    def __init__(
        self,
        runtime: Runtime,
        knowledge: Knowledge,
        reconfigurer: Reconfigurer,
        requester: Requester,
        report: Callable[[Symptom], None],
        dwell_ns: int,
        journal: Journal | None = None,
    ) -> None:
        self._runtime = runtime
        self._journal = journal
        self._knowledge = knowledge
        self._reconfigurer = reconfigurer
        self._requester = requester
        self._report = report
        self._dwell_ns = dwell_ns
        self._judges: dict[str, Judge] = {}  # request key -> the judge of a request degraded in place
        # (request key, formula) -> its first false verdict while the call of require() that adds
        # it has not ended: reported once the call took every requirement, dropped when it failed
        self._holding: dict[tuple[str, str], Symptom | None] = {}
        self._holding_lock = threading.Lock()

    # -- a request's own requirements

    def require(self, request: Request, formulas: list[Formula], owner: Owner = LOCAL) -> None:
        """Watch ``formulas`` over ``request``'s stream for ``owner`` (the reference that adds
        them: their nodes count against its share, :class:`~dyknow.reasoning.unit.MonitorBudget`):
        a monitor unit each, whose false verdicts become "requirement" symptoms. A term that is
        the request's tag reads its stream, any other is requested in turn. All or nothing: when
        one cannot be watched (its monitor fails to start, too), those this call set up are taken
        down again before it raises, and what they found changes nothing: a false verdict of one
        of them counts (a symptom) only once the call took every requirement."""
        added: list[str] = []
        held: list[tuple[str, str]] = []
        try:
            for formula in formulas:
                text = str(formula)
                if text in request.watches:
                    continue
                bindings: dict[str, str] = {}
                needs: list[str] = []
                with self._holding_lock:
                    self._holding[(request.key, text)] = None
                held.append((request.key, text))
                try:
                    for term, port in term_ports(formula).items():
                        if term == request.tag:
                            bindings[port] = request.key
                        else:
                            needs.append(self._requester.request(term))
                            bindings[port] = needs[-1]
                    request.watch_count += 1
                    name = f"{request.anchor}-require-{request.watch_count}"
                    bindings[VERDICTS_PORT] = f"{request.key}/requirements/{request.watch_count}"
                    self._start(monitor_spec(formula, label="requirement", close_idle=True), name, bindings, text, owner)
                except BaseException:
                    self.give_back(needs)
                    raise
                self._knowledge.managed.add(name)
                request.watches[text] = (name, tuple(needs))
                added.append(text)
                watcher = self._runtime.unit(name)
                if isinstance(watcher, FormulaMonitor):
                    key = request.key
                    watcher.listen(lambda verdict, text=text, key=key: self._verdict(key, text, verdict))  # type: ignore[misc]
        except BaseException:
            self.unrequire(request, added)
            with self._holding_lock:
                for watch in held:
                    self._holding.pop(watch, None)
            raise
        with self._holding_lock:
            found = [symptom for symptom in (self._holding.pop(watch, None) for watch in held) if symptom is not None]
        for symptom in found:  # (false while the call went on: a fault of the stream as it is now required)
            self._report(symptom)

    def _start(self, spec: TransformationSpec, name: str, bindings: dict[str, str], formula: str, owner: Owner = LOCAL) -> None:
        """Spawn the monitor unit ``name`` of a requirement; one that fails to start (its formula's
        nodes were taken since they were checked, say) is destroyed again and the failure raised,
        so no requirement is ever taken for watched while its monitor does not run."""
        if owner.local:
            info = self._runtime.spawn(spec, name, bindings=bindings)
        else:
            info = self._runtime.spawn(spec, name, bindings=bindings, owner=owner)
        if info.state == "failed":
            try:
                self._runtime.destroy(name)
            except DyKnowError:
                pass  # (gone already)
            raise UnitError(
                f"the monitor of the requirement {formula[:200]!r} failed to start: {info.error}",
                where=f"manager {self._runtime.name!r}",
                expected="a requirement whose monitor can run (release monitors or requirements to free formula nodes)",
            )

    def unrequire(self, request: Request, formulas: Iterable[str]) -> None:
        """Stop watching ``formulas`` over ``request``: their monitors go, their terms are given back."""
        for text in formulas:
            watch = request.watches.pop(text, None)
            if watch is not None:
                self._reconfigurer.cleanup([watch[0]])
                self.give_back(watch[1])

    def give_back(self, needs: Iterable[str]) -> None:
        """Give back the requests of other terms a watch needed (those still open)."""
        for needed in needs:
            if needed in self._knowledge.requests:
                self._requester.release(needed)

    def attach(self, key: str, judge: Judge) -> None:
        """Hand every verdict of the requirements of the request on ``key`` to ``judge`` too."""
        self._judges[key] = judge

    def detach(self, key: str) -> None:
        """No judge for the request on ``key`` any more."""
        self._judges.pop(key, None)

    def _verdict(self, key: str, formula: str, verdict: Verdict, unit: str | None = None, label: str | None = None) -> None:
        """A requirement's verdict (on its monitor's thread): a false one is a symptom; while the
        request is degraded in place, its judge sees them all."""
        judge = self._judges.get(key)
        if judge is not None:
            judge.verdict(formula, verdict)
        if verdict.verdict is False:
            symptom = Symptom("requirement", time.time_ns(), unit=unit, label=label, detail=formula, request=key, state_ns=verdict.t_ns)
            with self._holding_lock:
                if (key, formula) in self._holding:  # (its require() call goes on: held until it ends)
                    if self._holding[(key, formula)] is None:
                        self._holding[(key, formula)] = symptom
                    return
            self._report(symptom)

    # -- the requirements of the transformations serving a request

    def watch_specs(self, request: Request, *, refuse: bool = False) -> None:
        """Watch the requirements of the transformations now serving ``request`` (their specs'),
        and stop watching those of units that no longer do. A term that is one of the unit's
        output tags reads that output; any other is requested in turn. Their monitors are the
        manager's own (its reserve of formula nodes, which no caller can take).

        A requirement that cannot be watched (no formula nodes left, a term without a stream,
        a monitor that fails to start) is never left unchecked in silence. With ``refuse`` (a
        new request) it raises :class:`~dyknow.errors.UnitError` naming the requirement and why
        (the request is then refused). Otherwise the configuration runs on rather than not at
        all, but *unwatched*, visibly: the model shows the request "degraded" with each such
        requirement and why (``unwatched``), one warning and one "degraded" adaptation event say
        so, and it is tried again every second (:meth:`retry_unwatched`); once all are watched,
        a "recovered" event completes that one."""
        planner = self._reconfigurer.planner()
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
            self._reconfigurer.cleanup([watch.monitor])
            for needed in watch.needs:
                if needed in self._knowledge.requests:
                    self._requester.release(needed)
        for ident in [i for i in request.unwatched if i not in wanted]:
            del request.unwatched[ident]
        for (ref, text), label in wanted.items():
            if (ref, text) not in request.spec_watches:
                try:
                    request.spec_watches[(ref, text)] = self._spec_watch(request, ref, label, self._runtime.check_formula(text))
                except DyKnowError as exc:
                    if refuse:
                        raise UnitError(
                            f"the requirement {text[:200]!r} of {label} cannot be watched: {exc}",
                            where=f"request {request.tag} on manager {self._runtime.name!r}",
                            expected="a request whose transformations' requirements can be watched (a stream is never served "
                            "unchecked); try again once monitors or requirements are released",
                        ) from exc
                    if (ref, text) not in request.unwatched:
                        log.warning("cannot watch the requirement %r of %s for %s: %s; it runs unwatched, shown degraded, "
                                    "and is tried again every %g s", text, label, request.tag, exc, RETRY_UNWATCHED_NS / 1e9)  # fmt: skip
                    request.unwatched[(ref, text)] = (label, str(exc)[:1000])
                    continue
                if request.unwatched.pop((ref, text), None) is not None:
                    log.info("the requirement %r of %s for %s is watched now", text, label, request.tag)
        request.unwatched_retry_ns = time.time_ns() + RETRY_UNWATCHED_NS
        self._mark_unwatched(request)

    def retry_unwatched(self, now_ns: int) -> None:
        """Try again to watch the requirements of transformations that could not be watched
        (:meth:`watch_specs`), of each request whose retry is due (every second)."""
        for request in list(self._knowledge.requests.values()):
            if request.unwatched and request.unwatched_retry_ns <= now_ns:
                self.watch_specs(request)

    def _mark_unwatched(self, request: Request) -> None:
        """One "degraded" event when the request's first requirement went unwatched, one
        "recovered" when its last is watched again (or no longer wanted)."""
        event = request.unwatched_event
        if request.unwatched and event is None:
            (ref, formula), (label, why) = next(iter(request.unwatched.items()))
            labels = tuple(sorted(set(request.units.values())))
            detail = f"the requirement {formula!r} of {label} ({ref}) cannot be watched, so the stream is served unchecked: {why}"
            if len(request.unwatched) > 1:
                detail += f" (and {len(request.unwatched) - 1} more)"
            request.unwatched_event = event = AdaptationEvent(
                self._journal.next_id() if self._journal is not None else 0,
                "degraded",
                request.tag,
                request.key,
                f"requirement unwatched: {formula}",
                labels,
                labels,
                time.time_ns(),
                detail=detail,
            )
            if self._journal is not None:
                self._journal.emit(event)
        elif not request.unwatched and event is not None:
            request.unwatched_event = None
            now = time.time_ns()
            recovered = replace(event, kind="recovered", new=tuple(sorted(set(request.units.values()))), recovery_ms=round((now - event.fault_ns) / 1e6, 3))
            if self._journal is not None:
                self._journal.emit(recovered)

    def _unit_bindings(self, ref: str, label: str, formula: Formula) -> tuple[dict[str, str], list[str]]:
        """Where a monitor of a requirement of unit ``ref`` (of transformation ``label``) reads
        each term: a term that is one of the unit's output tags reads that output, a term the spec
        binds (its ``<bindings>``) reads its source, any other is requested in turn. Returns the
        bindings and those requests (given back on a failure)."""
        spec = self._reconfigurer.planner().spec(label)
        outputs = self._reconfigurer.config(ref)
        bound = dict(spec.bindings)
        bindings: dict[str, str] = {}
        needs: list[str] = []
        try:
            for term, port in term_ports(formula).items():
                if term in bound:
                    bindings[port] = bound[term]
                    continue
                produced = [
                    outputs[p.name]
                    for p in spec.outputs
                    if p.name in outputs and term in {str(parse_term(t)) for t in spec.tags_for(p.name)}
                ]
                if produced:
                    bindings[port] = produced[0]
                else:
                    needs.append(self._requester.request(term))
                    bindings[port] = needs[-1]
        except DyKnowError:
            self.give_back(needs)
            raise
        return bindings, needs

    def _spec_watch(self, request: Request, ref: str, label: str, formula: Formula) -> SpecWatch:
        bindings, needs = self._unit_bindings(ref, label, formula)
        try:
            request.spec_watch_count += 1
            n = request.spec_watch_count
            name = f"{request.anchor}-spec-require-{n}"
            key = bindings[VERDICTS_PORT] = f"{request.key}/requirements/spec-{n}"
            self._start(monitor_spec(formula, label="requirement", close_idle=True, bound=self._bound(label, formula)), name, bindings, str(formula))
        except DyKnowError:
            self.give_back(needs)
            raise
        self._knowledge.managed.add(name)
        watcher = self._runtime.unit(name)
        if isinstance(watcher, FormulaMonitor):
            text, rkey = str(formula), request.key
            watcher.listen(lambda verdict, text=text, rkey=rkey, ref=ref, label=label: self._verdict(rkey, text, verdict, ref, label))  # type: ignore[misc]
        return SpecWatch(label, name, key, tuple(needs))

    def _bound(self, label: str, formula: Formula) -> dict[str, str]:
        """The terms of ``formula`` that the spec of ``label`` binds to what exists, and their sources."""
        terms = {str(term) for term in formula.terms}
        return {term: source for term, source in self._reconfigurer.planner().spec(label).bindings if term in terms}

    # -- a trial in the shadow

    def watch_trial(self, request: Request, trial: Trial) -> None:
        """Monitors of the request's requirements over the trial's output (their other terms read
        what the request's own monitors read), and of the trial's new units' own requirements;
        one judge over them all, which reports the trial "held" or "failed". :class:`DyKnowError`
        when one cannot be watched."""
        watched: list[tuple[str, Formula, dict[str, str], dict[str, str]]] = []  # (judge's name of it, formula, bindings, bound terms)
        for text, (monitor, _) in request.watches.items():
            formula = self._runtime.check_formula(text)
            current = self._runtime.get_config(monitor)
            bindings = {port: trial.output_key if term == request.tag else current[port] for term, port in term_ports(formula).items()}
            watched.append((text, formula, bindings, {}))
        planner = self._reconfigurer.planner()
        for unit in trial.plan.new_units:
            ref, label = unit.ref, trial.units.get(unit.ref)
            if label is None:
                continue
            for text in planner.spec(label).requirements:
                formula = self._runtime.check_formula(text)
                bindings, needs = self._unit_bindings(ref, label, formula)
                trial.needs.extend(needs)
                watched.append((f"{text} (of {label})", formula, bindings, self._bound(label, formula)))
        if not watched:
            raise UnitError("no requirement to judge it by", where=f"the trial of {trial.label}")
        key, serial = request.key, trial.serial

        def report(outcome: str, formula: str) -> None:
            detail = f"{trial.label} held its requirements for {self._dwell_ns / 1e9:g} s" if outcome == "held" else f"requirement {formula!r} was false there"
            self._report(Symptom(f"trial-{outcome}", time.time_ns(), label=trial.label, detail=detail, request=key, trial=serial))

        judge = Judge([name for name, _, _, _ in watched], self._dwell_ns, report, strict=True)
        for k, (name, formula, bindings, bound) in enumerate(watched, start=1):
            monitor = f"{request.anchor}-trial-{serial}-{k}"
            bindings[VERDICTS_PORT] = f"{request.key}/trials/{serial}/{k}"
            self._start(monitor_spec(formula, label="requirement", close_idle=True, bound=bound), monitor, bindings, name)  # (one that fails to start is gone)
            self._knowledge.managed.add(monitor)
            trial.monitors.append(monitor)
            watcher = self._runtime.unit(monitor)
            if isinstance(watcher, FormulaMonitor):
                watcher.listen(lambda verdict, name=name: judge.verdict(name, verdict))  # type: ignore[misc]
