"""Clocks of other hosts: how far each peer manager's wall clock is from this process's, and how sure.

Every message's header says whose clock took its times (``origin_clock``, ``send_clock``: the
random :data:`~dyknow.message.CLOCK_ID` of a process). A time from another host's clock is only
comparable with this one's once the offset between the clocks is known: a robot whose clock runs
250 ms ahead made every hop from it read -249 ms. So each manager estimates the offset of every
peer manager's clock, continuously, and every figure that compares times of two clocks
(``hop``, ``latency``) is corrected by it, or left out and counted when it is not known.

**The exchange** (NTP's four timestamps). The estimating side sends ``t1`` (its clock) to the
peer's ``@dyknow/<manager>/clock``; the peer answers ``t2`` (when the request arrived) and ``t3``
(when it answered), both on its clock, and its clock id; the answer arrives at ``t4``. Then::

    offset = ((t2 - t1) + (t3 - t4)) / 2      (peer clock minus this clock)
    delay  = (t4 - t1) - (t3 - t2)            (the round trip, less the peer's own time)

and the offset is exact when the two legs of the trip took as long, off by at most ``delay / 2``
otherwise. Both ends take their times on Zenoh's receiving thread (no thread hand-off inside
them). Request: ``b"DKT1"`` + ``t1`` (i64, little endian); answer: ``b"DKT1"`` + ``t1`` + ``t2``
+ ``t3`` (i64) + the peer's clock id (u32).

**The estimate** (:class:`Estimator`), as NTP and chrony do it: of the last
:data:`SAMPLES` exchanges, only those whose delay is close to the smallest count (a long trip is
an uneven one). Once there are six such spread over 8 s, a least-squares line through them gives
the offset now and the drift (a clock running fast or slow), which carries the offset forward
between exchanges; until then, the exchange with the smallest delay among the latest eight gives
the offset, with no drift. The uncertainty is half the smallest delay, plus 1 ppm of the time
the offset is carried. Exchanges run 8 times in the first half second of a peer, then once a
second.

**What is refused** (counted by reason in :attr:`Estimator.refused`, never mixed into the
estimate): an answer that does not echo the request's ``t1`` (stray or flooded replies), one
whose peer spent negative time (``t3 < t2``) or whose delay is negative or over a second, a peer
clock that went backwards between two exchanges, an offset beyond :data:`MAX_OFFSET_S` (years
off), a clock id other than the one the peer gave first, and, once an estimate stands, an
exchange that disagrees with it by far more than both uncertainties (a single wild answer);
:data:`STEP_AFTER` such answers in a row that agree with each other are taken as a step of the
peer's clock (an NTP correction after a reboot) and start the estimate over. A peer can only
misstate its own clock: the estimate of each clock is its own.

:data:`CLOCKS` is this process's table of clocks, read on the hot path by
:meth:`ClockTable.offset` (a dictionary lookup); a :class:`ClockTracker` keeps it up to date for
the peers it is given. What it cannot give you: absolute time. The estimates say how the clocks
relate, not which one is right; run chrony or PTP where times must be true (a recording compared
with the world, a log read across machines).
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Final

from dyknow.message import CLOCK_ID
from dyknow.transport import Session

__all__ = [
    "CLOCKS",
    "MAX_OFFSET_S",
    "SAMPLES",
    "STEP_AFTER",
    "ClockTable",
    "ClockTracker",
    "Estimate",
    "Estimator",
    "answer",
    "corrected",
    "request",
]

log = logging.getLogger(__name__)

_MAGIC: Final = b"DKT1"
_REQUEST: Final = struct.Struct("<4sq")
_ANSWER: Final = struct.Struct("<4sqqqI")
#: Exchanges the estimate rests on (the last ones: about a minute of them).
SAMPLES: Final = 64
_FIT_SAMPLES: Final = 6  # good exchanges a drift needs ...
_FIT_SPAN_NS: Final = 8_000_000_000  # ... spread over this long
_RECENT: Final = 8  # before a drift is known, the best of the latest exchanges carries the offset
#: An offset beyond this many seconds is refused as absurd (about ten years).
MAX_OFFSET_S: Final = 10 * 366 * 86400.0
#: Wild answers in a row, agreeing with each other, taken as a step of the peer's clock.
STEP_AFTER: Final = 4
_MAX_DELAY_NS: Final = 1_000_000_000
_BURST: Final = 8  # exchanges in a new peer's first half second
_BURST_S: Final = 0.06
_PERIOD_S: Final = 1.0
_MAX_PEERS: Final = 256


def request(t1_ns: int) -> bytes:
    """The payload of a clock exchange's request sent at ``t1_ns``."""
    return _REQUEST.pack(_MAGIC, t1_ns)


def answer(payload: bytes, t2_ns: int) -> tuple[bool, bytes]:
    """The peer's side: the answer to ``payload`` received at ``t2_ns`` (``(ok, reply)``, for a queryable)."""
    if len(payload) != _REQUEST.size or payload[:4] != _MAGIC:
        return False, b'{"error": "ServiceError", "message": "not a clock exchange"}'
    _, t1 = _REQUEST.unpack(payload)
    return True, _ANSWER.pack(_MAGIC, t1, t2_ns, time.time_ns(), CLOCK_ID)


@dataclass(frozen=True, slots=True)
class Estimate:
    """A peer clock's offset from this one (peer minus this, ns) at ``at_ns`` of this clock, and how sure."""

    clock: int
    offset_ns: int
    uncertainty_ns: int
    drift_ppm: float
    samples: int
    at_ns: int

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (µs), as the model shows it."""
        return {
            "clock": f"{self.clock:08x}",
            "offset_us": round(self.offset_ns / 1000, 1),
            "uncertainty_us": round(self.uncertainty_ns / 1000, 1),
            "drift_ppm": round(self.drift_ppm, 2),
            "samples": self.samples,
        }


class Estimator:
    """The offset of one peer's clock, from its exchanges (see the module documentation).

    Not thread-safe: one :class:`ClockTracker` thread feeds it; :meth:`estimate` may be read from
    another thread at any time (it reads an immutable snapshot).
    """

    def __init__(self) -> None:
        self.clock = 0  # the peer's clock id, from its first answer
        self.refused: Counter[str] = Counter()
        self._samples: deque[tuple[int, int, int]] = deque(maxlen=SAMPLES)  # (t of this clock, offset, delay)
        self._last_t2 = 0
        self._wild: list[tuple[int, int, int]] = []
        self._estimate: tuple[int, int, float, int] | None = None  # (at, offset, drift, delay)

    def add(self, t1: int, reply: bytes, t4: int, *, sent_ns: int | None = None) -> bool:
        """Take one exchange: the request carried ``t1``, ``reply`` arrived at ``t4``; False when
        refused (counted). ``sent_ns``: when the request actually left, if measured later than
        ``t1`` (the exchange's own time, closer to the wire: it is used instead)."""
        if len(reply) != _ANSWER.size or reply[:4] != _MAGIC:
            return self._refuse("malformed")
        _, echo, t2, t3, clock = _ANSWER.unpack(reply)
        if echo != t1:
            return self._refuse("not this request")
        if sent_ns is not None and t1 <= sent_ns <= t4:
            t1 = sent_ns
        if self.clock and clock != self.clock:
            return self._refuse("another clock id")
        if t3 < t2:
            return self._refuse("peer time negative")
        delay = (t4 - t1) - (t3 - t2)
        if delay < 0 or delay > _MAX_DELAY_NS:
            return self._refuse("delay out of range")
        offset = ((t2 - t1) + (t3 - t4)) // 2
        if abs(offset) > MAX_OFFSET_S * 1e9:
            return self._refuse("offset absurd")
        if t2 < self._last_t2:
            return self._refuse("peer clock went backwards")
        mid = (t1 + t4) // 2
        current = self.estimate(mid)
        if current is not None and len(self._samples) >= 4:
            tolerance = 4 * (current.uncertainty_ns + delay // 2) + 200_000
            if abs(offset - current.offset_ns) > tolerance:
                self._wild.append((mid, offset, delay))
                agreeing = [w for w in self._wild if abs(w[1] - offset) <= 4 * (w[2] + delay) + 200_000]
                if len(agreeing) < STEP_AFTER:
                    return self._refuse("disagrees with the estimate")
                log.info("the clock %08x stepped by %.3f ms: its estimate starts over", clock, (offset - current.offset_ns) / 1e6)
                self._samples.clear()
                for sample in agreeing[:-1]:
                    self._samples.append(sample)
            self._wild.clear()
        self.clock = self.clock or clock
        self._last_t2 = t2
        self._samples.append((mid, offset, delay))
        self._fit()
        return True

    def _refuse(self, why: str) -> bool:
        self.refused[why] += 1
        return False

    def _fit(self) -> None:
        samples = list(self._samples)
        best = min(samples, key=lambda s: s[2])
        good = [s for s in samples if s[2] <= best[2] * 1.5 + 30_000]
        span = good[-1][0] - good[0][0]
        if len(good) >= _FIT_SAMPLES and span >= _FIT_SPAN_NS:
            # a line through the good exchanges: the offset now and the drift, the noise of
            # single exchanges averaged out
            mean_t = sum(s[0] for s in good) / len(good)
            mean_o = sum(s[1] for s in good) / len(good)
            var = sum((s[0] - mean_t) ** 2 for s in good)
            drift = sum((s[0] - mean_t) * (s[1] - mean_o) for s in good) / var if var > 0 else 0.0
            at = good[-1][0]
            self._estimate = (at, int(mean_o + drift * (at - mean_t)), drift, best[2])
            return
        # not enough yet: the exchange with the smallest delay among the latest few, no drift
        recent = min(samples[-_RECENT:], key=lambda s: s[2])
        self._estimate = (recent[0], recent[1], 0.0, recent[2])

    def estimate(self, at_ns: int | None = None) -> Estimate | None:
        """The offset at ``at_ns`` of this clock (now when None), or None before any exchange."""
        current = self._estimate
        if current is None:
            return None
        at = time.time_ns() if at_ns is None else at_ns
        base, offset, drift, delay = current
        carried = drift * (at - base)
        # the drift's own error grows with the time carried: a conservative 1 ppm of it, at least
        uncertainty = delay // 2 + int(abs(at - base) * 1e-6)
        return Estimate(self.clock, offset + int(carried), uncertainty, drift * 1e6, len(self._samples), at)


class ClockTable:
    """The clocks this process knows: offsets by clock id, for the hot path and for the model.

    :attr:`current` maps clock ids to offsets now (peer minus this, ns), for the hot path: a
    dictionary lookup, kept current by :meth:`refresh` (which a :class:`ClockTracker` calls ten
    times a second) and swapped whole, never changed in place; this process's own clock is 0.
    """

    def __init__(self) -> None:
        self.current: dict[int, int] = {CLOCK_ID: 0}
        self._uncertainty: dict[int, int] = {CLOCK_ID: 0}
        self._estimators: dict[int, Estimator] = {}
        self._lock = threading.Lock()

    def offset(self, clock: int) -> int | None:
        """The offset (peer minus this, ns) of ``clock`` now, or None when it is not known."""
        return self.current.get(clock)

    def uncertainty(self, clock: int) -> int | None:
        """How far the offset of ``clock`` may be off (ns), or None when it is not known."""
        return self._uncertainty.get(clock)

    def register(self, estimator: Estimator) -> None:
        """Keep ``estimator``'s clock in the table (once it has a clock id)."""
        with self._lock:
            if estimator.clock and estimator.clock != CLOCK_ID:
                self._estimators[estimator.clock] = estimator

    def forget(self, estimator: Estimator) -> None:
        """Stop keeping ``estimator``'s clock."""
        with self._lock:
            if self._estimators.get(estimator.clock) is estimator:
                del self._estimators[estimator.clock]
        self.refresh()

    def refresh(self, now_ns: int | None = None) -> None:
        """Carry every estimate forward to now (the drift applied) for :meth:`offset`."""
        now = time.time_ns() if now_ns is None else now_ns
        offsets, uncertainty = {CLOCK_ID: 0}, {CLOCK_ID: 0}
        with self._lock:
            estimators = list(self._estimators.items())
        for clock, estimator in estimators:
            found = estimator.estimate(now)
            if found is not None:
                offsets[clock], uncertainty[clock] = found.offset_ns, found.uncertainty_ns
        self.current, self._uncertainty = offsets, uncertainty  # swapped whole: readers never lock


#: This process's clock table.
CLOCKS: Final = ClockTable()


class _Peer:
    __slots__ = ("estimator", "key", "next_at", "sent")

    def __init__(self, key: str) -> None:
        self.key = key
        self.estimator = Estimator()
        self.sent = 0
        self.next_at = 0.0


class ClockTracker:
    """Keeps :data:`CLOCKS` (or ``table``) up to date for the peers it is given: a thread that runs
    their exchanges (8 in a peer's first half second, then one a second) and refreshes the table
    ten times a second. A context manager; :meth:`close` stops it."""

    def __init__(self, session: Session, table: ClockTable = CLOCKS, *, timeout_s: float = 1.0) -> None:
        self._session = session
        self._table = table
        self._timeout_s = timeout_s
        self._peers: dict[str, _Peer] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dyknow-clocks", daemon=True)
        self._thread.start()

    def track(self, name: str, key: str) -> None:
        """Estimate the clock of peer ``name``, which answers exchanges on ``key``."""
        with self._lock:
            if name not in self._peers and len(self._peers) < _MAX_PEERS:
                self._peers[name] = _Peer(key)

    def untrack(self, name: str) -> None:
        """Stop estimating peer ``name``'s clock (it left); its offset is forgotten."""
        with self._lock:
            peer = self._peers.pop(name, None)
        if peer is not None:
            self._table.forget(peer.estimator)

    def estimates(self) -> dict[str, Estimate]:
        """The current estimate of each peer that has one."""
        with self._lock:
            peers = list(self._peers.items())
        now = time.time_ns()
        found = {name: peer.estimator.estimate(now) for name, peer in peers}
        return {name: e for name, e in found.items() if e is not None}

    def refused(self) -> dict[str, dict[str, int]]:
        """Refused exchanges, by peer and reason."""
        with self._lock:
            return {name: dict(peer.estimator.refused) for name, peer in self._peers.items() if peer.estimator.refused}

    def close(self) -> None:
        """Stop the thread; safe twice."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(2 * self._timeout_s + 1)

    def __enter__(self) -> ClockTracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        refreshed = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                due = [(name, peer) for name, peer in self._peers.items() if peer.next_at <= now]
            for name, peer in due:
                if self._stop.is_set():
                    return
                self._exchange(name, peer)
                peer.sent += 1
                peer.next_at = time.monotonic() + (_BURST_S if peer.sent < _BURST else _PERIOD_S)
            if now - refreshed >= 0.1:
                self._table.refresh()
                refreshed = now
            with self._lock:
                waits = [p.next_at for p in self._peers.values()]
            self._stop.wait(max(0.005, min([0.1, *(w - time.monotonic() for w in waits)])))

    def _exchange(self, name: str, peer: _Peer) -> None:
        try:
            t1 = time.time_ns()
            got = self._session.exchange(peer.key, request(t1), timeout_s=self._timeout_s)
        except Exception as exc:  # a peer that is gone, a closed session: the next round tries again
            log.debug("no clock exchange with %r: %s", name, exc)
            return
        if got is None:
            peer.estimator.refused["no answer"] += 1
            return
        reply, sent, arrived, replies = got
        if replies > 1:
            peer.estimator.refused["extra replies"] += replies - 1
        if peer.estimator.add(t1, reply, arrived, sent_ns=sent):
            self._table.register(peer.estimator)


def corrected(time_ns: int, clock: int, table: ClockTable = CLOCKS) -> int | None:
    """``time_ns`` of ``clock``, as this process's clock would have read it; None when unknown."""
    offset = table.offset(clock)
    return None if offset is None else time_ns - offset
