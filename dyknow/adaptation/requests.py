"""The requests, the loop's goals: :class:`Requests` takes a request (planned, wired, anchored on its
stable key, its requirements watched) and gives it back, one reference of one owner at a time; the
last reference tears down what only the request used.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable

from dyknow import keys
from dyknow.adaptation.adapt import Adapter
from dyknow.adaptation.analyze import Analyzer
from dyknow.adaptation.anchor import anchor_name, spawn_anchor
from dyknow.adaptation.knowledge import Knowledge, Request
from dyknow.adaptation.monitor import Symptom
from dyknow.adaptation.reconfigure import MAX_START_FAILURES, Reconfigurer, StartFailed
from dyknow.adaptation.requirements import Requirements
from dyknow.adaptation.runtime import Runtime
from dyknow.errors import AccessError, PlanningError, UnitError
from dyknow.model import LOCAL, Owner, RequestInfo, check_standby
from dyknow.reasoning.families import refuse_families
from dyknow.reasoning.unit import term_ports
from dyknow.tags import parse_term

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs


class Requests:
    """Takes and gives back the requests the loop keeps flowing (under the loop's ``lock``: one
    change at a time, with the adaptations)."""

    def __init__(
        self,
        runtime: Runtime,
        knowledge: Knowledge,
        analyzer: Analyzer,
        reconfigurer: Reconfigurer,
        requirements: Requirements,
        adapter: Adapter,
        report: Callable[[Symptom], None],
        lock: threading.RLock,
    ) -> None:
        self._runtime = runtime
        self._knowledge = knowledge
        self._analyzer = analyzer
        self._reconfigurer = reconfigurer
        self._requirements = requirements
        self._adapter = adapter
        self._report = report
        self._lock = lock

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
        """Plan and wire a configuration providing ``tag``; returns its stable key.

        ``standby="warm"`` keeps the next-best configuration running beside it, so that a fault
        only moves the anchor (see the package documentation); ``"none"`` (or None, the default)
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
        back; the monitors of the requirements it adds count against its share of the formula
        nodes, :class:`~dyknow.reasoning.unit.MonitorBudget`). ``readable(tag)`` raises when the
        owner may not read the stream of a tag: it is asked of ``tag`` and of every term of every
        formula before anything is planned. A requirement of a transformation of the chosen
        configuration that cannot be watched refuses the request (:class:`UnitError` naming it
        and why). When the call fails, nothing of it remains.

        ``max_references``: the most references the caller that ``owner`` is may hold on the
        request (:meth:`~dyknow.model.Owner.same_caller`); one more is an :class:`AccessError`
        naming the request and the bound, and the others' references still go through (None:
        unbounded, the manager's own API).
        """
        mode = check_standby(standby)
        runtime = self._runtime
        canonical = str(parse_term(tag))
        key = keys.request_key(runtime.name, canonical)
        formulas = [runtime.check_formula(text) for text in require]  # (bounded before anything is requested)
        for formula in formulas:
            refuse_families(formula, "a request's requirement")
        texts = tuple(dict.fromkeys(str(f) for f in formulas))
        if readable is not None:
            readable(canonical)
            for formula in formulas:
                for term in term_ports(formula):
                    if term != canonical:
                        readable(term)
        with self._lock:
            existing = self._knowledge.requests.get(key)
            if existing is not None:
                if max_references is not None:
                    self._check_share(existing, owner, max_references)
                self._requirements.require(existing, [f for f in formulas if str(f) not in existing.watches], owner)  # (undoes itself when it fails)
                existing.owners.append((owner, texts))
                if mode == "warm" and existing.standby_mode != "warm":
                    self._warm_up(existing)
                return key
            request = Request(canonical, key, anchor=anchor_name(runtime, canonical), standby_mode=mode, owners=[(owner, texts)])
            failed: list[StartFailed] = []
            while True:  # a transformation that fails at start is in back-off: the next plan leaves it out
                try:
                    plan = self._reconfigurer.plan(request, time.time_ns())  # PlanningError: nothing fits, nothing changes
                except PlanningError:
                    if failed:
                        raise failed[-1] from None  # what failed says more than "nothing fits" without it
                    raise
                spawn_anchor(runtime, self._knowledge, request, plan.output_key)
                self._knowledge.requests[key] = request
                try:
                    self._reconfigurer.apply(request, plan)
                    break
                except BaseException as exc:
                    del self._knowledge.requests[key]
                    self._reconfigurer.cleanup([request.anchor])
                    if not isinstance(exc, StartFailed) or len(failed) >= MAX_START_FAILURES:
                        raise
                    log.warning("request %s: %s; planning again without %s", canonical, exc, exc.label)
                    failed.append(exc)
            request.last_change_ns = time.time_ns()
            self._report(Symptom("spawned", request.last_change_ns, unit=request.anchor))  # start ticking
            log.info("request %s on %s: %s", canonical, key, ", ".join(sorted(set(request.units.values()))))
            if mode == "warm":
                self._adapter.maintain_standby(request, time.time_ns())
            try:
                self._requirements.require(request, formulas, owner)
                self._requirements.watch_specs(request, refuse=True)  # (a new stream is never served unchecked)
            except BaseException:
                self.release(key, force=True)
                raise
            return key

    def _check_share(self, request: Request, owner: Owner, max_references: int) -> None:
        """Refuse one more reference of ``owner``'s caller to ``request`` when it holds
        ``max_references`` already: no caller fills a shared request for the others."""
        taken = sum(1 for other, _ in request.owners if owner.same_caller(other))
        if taken >= max_references:
            raise AccessError(
                f"{owner.who()} holds {taken} references to the request on {request.key!r} already, its most",
                where=f"manager {self._runtime.name!r}",
                expected=(
                    f"at most {max_references} references per caller on one request (Limits.max_references_per_caller): "
                    "release one first (dyknow release KEY), or share one reference among the caller's clients"
                ),
            )

    def _warm_up(self, request: Request) -> None:
        """A shared request asked for a warm standby: a new anchor that can hold one, then the standby."""
        request.standby_mode = "warm"
        self._reconfigurer.cleanup([request.anchor])
        request.anchor = anchor_name(self._runtime, request.tag)
        spawn_anchor(self._runtime, self._knowledge, request, request.output_key or f"{request.key}/none")
        self._adapter.maintain_standby(request, time.time_ns())

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

    def infos(self) -> list[RequestInfo]:
        """The active requests, by key. Never waits for a request being planned or adapted (the
        model's readers call it): ``list()`` of a dict's values is one step for other threads."""
        requests = list(self._knowledge.requests.values())
        return [r.info() for r in sorted(requests, key=lambda r: r.key)]

    def _known(self, key: str) -> Request:
        request = self._knowledge.requests.get(key)
        if request is None:
            known = ", ".join(sorted(self._knowledge.requests)) or "none"
            raise UnitError(f"no request on key {key!r}", where=f"manager {self._runtime.name!r}", expected=f"one of the active requests: {known}")
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
            where=f"manager {self._runtime.name!r}",
            expected="a release by the client or caller that requested it; an admin may force it (release with force, dyknow release KEY --force)",
        )

    def _drop(self, request: Request, dropped: list[tuple[Owner, tuple[str, ...]]]) -> int:
        for entry in dropped:
            request.owners.remove(entry)
        if request.owners:
            still = request.required()
            self._requirements.unrequire(request, [text for _, texts in dropped for text in texts if text not in still])
            return request.references
        key = request.key
        self._adapter.suspects.end_trial(request)
        del self._knowledge.requests[key]
        self._analyzer.forget(key)
        self._adapter.suspects.settle(key)
        orphans = [n for n in request.held() if n in self._knowledge.managed and not self._knowledge.users(n)]
        watches = list(request.spec_watches.values())
        self._reconfigurer.cleanup([*(w[0] for w in request.watches.values()), *(w.monitor for w in watches), request.anchor, *orphans])
        self._requirements.give_back([*(n for w in request.watches.values() for n in w[1]), *(n for w in watches for n in w.needs)])
        return 0
