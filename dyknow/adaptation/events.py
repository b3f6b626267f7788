"""The record of adaptations: the :class:`Journal` numbers each :class:`AdaptationEvent`, keeps it in
the history, publishes it and hands it to the listeners; a :class:`Recovery` completes an
adaptation's event with its recovery time, once the new configuration's first message is out.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace

from dyknow.adaptation.anchor import RequestAnchor
from dyknow.adaptation.knowledge import AdaptationEvent, Knowledge, Request
from dyknow.adaptation.monitor import Symptom
from dyknow.adaptation.runtime import Runtime
from dyknow.errors import DyKnowError

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs

_STANDBY_WAIT_NS = 1_000_000_000  # after a switch, the next standby waits this long at most for the stream
_RECORD_WAIT_S = 1.0  # how long an anchor holds a new configuration's first message for its adaptation's record


class Journal:
    """Numbers, keeps and announces the adaptation events.

    The history is the knowledge's (:attr:`Knowledge.history`); ``lock`` is the loop's, which
    every adaptation holds: a recovery completed on another thread takes it too.
    """

    def __init__(self, runtime: Runtime, knowledge: Knowledge, lock: threading.RLock) -> None:
        self._runtime = runtime
        self._knowledge = knowledge
        self._lock = lock
        self._listeners: list[Callable[[AdaptationEvent], None]] = []
        self._next_id = 1

    def next_id(self) -> int:
        """The id of a new event (each adaptation or degradation takes one; its recovery shares it)."""
        taken = self._next_id
        self._next_id += 1
        return taken

    def on_event(self, listener: Callable[[AdaptationEvent], None]) -> Callable[[], None]:
        """Call ``listener(event)`` for every adaptation event; returns a function that removes it."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener) if listener in self._listeners else None

    def history(self) -> list[AdaptationEvent]:
        """Every adaptation so far, oldest first (each with its recovery time once recovered);
        a copy taken without waiting for an adaptation in progress."""
        return list(self._knowledge.history)

    def emit(self, event: AdaptationEvent) -> None:
        """Keep ``event`` in the history, publish it and hand it to the listeners."""
        self.record(event)
        self.announce(event)

    def complete(self, event: AdaptationEvent) -> None:
        """:meth:`emit` from another thread than the loop's (it takes the loop's lock)."""
        with self._lock:
            self.emit(event)

    def record(self, event: AdaptationEvent) -> None:
        """Keep ``event`` in the history (a recovery replaces its adaptation's entry)."""
        history = self._knowledge.history
        for i in range(len(history) - 1, -1, -1):  # a recovery completes its adaptation's entry
            if history[i].id == event.id:
                history[i] = event
                break
        else:
            history.append(event)

    def announce(self, event: AdaptationEvent) -> None:
        """Publish ``event`` and hand it to the listeners."""
        try:
            self._runtime.publish_event("adaptation", event.to_dict())
        except DyKnowError as exc:
            log.warning("could not publish adaptation event: %s", exc)
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception:
                log.exception("adaptation listener failed")


class Recovery:
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

    ``report`` is the loop's queue of symptoms: the stream flowing again wakes it up.
    """

    def __init__(self, runtime: Runtime, journal: Journal, report: Callable[[Symptom], None]) -> None:
        self._runtime = runtime
        self._journal = journal
        self._report = report
        self._lock = threading.Lock()
        self._arrival_ns: int | None = None
        self._event: AdaptationEvent | None = None
        self._request: Request | None = None
        self._recorded = threading.Event()

    def arm(self, request: Request) -> Callable[[str], None]:
        """What to call before the anchor switches onto a new output key."""
        self._request = request
        if request.standby_mode == "warm":  # the next standby: once the stream flows again (at most a second from now)
            request.standby_due = True
            request.standby_after_ns = time.time_ns() + _STANDBY_WAIT_NS

        def before_switch(output_key: str) -> None:
            anchor = self._runtime.unit(request.anchor)
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
            self._report(Symptom("recovered", arrival_ns, detail=f"{request.tag} flows again"))
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
            self._journal.complete(done)

        threading.Thread(target=emit, name="dyknow-recovery", daemon=True).start()
