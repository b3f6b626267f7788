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
otherwise: whatever the legs took, the true offset lies in ``[t3 - t4, t2 - t1]``. Both ends
take their times on Zenoh's receiving thread (no thread hand-off inside them). The caller also
reads its clock once Zenoh took the request, ``ts`` (``t1 <= ts <= t4``): the request left
between ``t1`` and ``ts``, most likely near ``ts`` (``t1`` counts the call's own cost on the
request's leg alone, which tilted every offset by tens of µs). So the offset taken is
``((t2 - ts) + (t3 - t4)) / 2``, moved into ``[t3 - t4, t2 - t1]`` if it falls outside (a request
that arrived before ``ts`` was read), and the exchange's *width* is twice its distance to the
far end of that interval (``delay`` above when there is no ``ts``): the offset is off by at most
half the width, whatever happened on the way. Request: ``b"DKT1"`` + ``t1`` (i64, little
endian); answer: ``b"DKT1"`` + ``t1`` + ``t2`` + ``t3`` (i64) + the peer's clock id (u32).

**The estimate** (:class:`Estimator`), as NTP and chrony do it: of the last
:data:`SAMPLES` exchanges, only the narrower half count, and any whose width is at most 1.5 times
the smallest plus 30 µs (a long trip may be an uneven one).

- Until there is a line, the offset is one exchange's, carried with no drift. A clock may run up
  to :data:`DRIFT_BOUND_PPM` fast or slow, so an older exchange is worth less: of the latest
  eight, the one with the least ``width / 2 + DRIFT_BOUND_PPM x its age`` is taken.
- Once three good exchanges span a second, a least-squares line through them gives the offset
  and the drift (a clock running fast or slow), which carries the offset forward. Each
  exchange's offset is off by at most half its width and the line is a weighted sum of them, so
  the line is off by at most the sum of those bounds with the weights' sizes, at its end and in
  its slope (the *slope bound*, plus 1 ppm for a drift that is not quite steady); or by one
  good exchange's half width plus how far the line passes from it, grown by the slope bound.
- The uncertainty is the tightest of those bounds of the line and, for each of the latest eight
  exchanges, how far the offset given is from it plus half its width plus
  :data:`DRIFT_BOUND_PPM` of the time since (which holds whatever the line says, for any clock
  within the drift bound).

Exchanges run 8 times in the first half second of a peer, then 3 in a row once a second: the
first of a round after a second idle wakes the path up, and is the slow and uneven one (between
two processes on loopback, 20 rounds: the first was off by 41 µs at the median, its half width
386 µs; the second and third by 8 µs, half widths 126 and 93 µs).

**What is refused** (counted by reason in :attr:`Estimator.refused`, never mixed into the
estimate): an answer that is not one (malformed), one that does not echo the request's ``t1``
(stray replies), one whose peer spent negative time (``t3 < t2``) or whose delay is negative or
over a second, an offset beyond :data:`MAX_OFFSET_S` (years off), a clock id other than the one
the peer gave first (or than the one its summary names, when the tracker was told), replies
beyond the first to one request (a flood: only the first counts), and two kinds of wild answer:
a peer clock that went backwards since the last exchange taken, and, once an estimate stands,
an exchange that disagrees with it by far more than both uncertainties. :data:`STEP_AFTER` wild
answers in a row that agree with each other, the peer's clock running forward among them, are
taken as a step of the peer's clock (an NTP correction, a reboot) and start the estimate over;
the latest :data:`STEP_AFTER` wild answers are all that is kept of them. A peer can only
misstate its own clock: the estimate of each clock is its own, and a clock id two peers claim
is nobody's (:meth:`ClockTable.register`: its offset is not known, counted as "clock id of
another peer").

:data:`CLOCKS` is this process's table of clocks, read on the hot path by
:meth:`ClockTable.offset` (a dictionary lookup); a :class:`ClockTracker` keeps it up to date for
the peers it is given. What it cannot give you: absolute time. The estimates say how the clocks
relate, not which one is right; run chrony or PTP where times must be true (a recording compared
with the world, a log read across machines).
"""

from __future__ import annotations

import logging
import queue
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from typing import Any, Final

from dyknow import keys
from dyknow.message import CLOCK_ID
from dyknow.transport import LivelinessSubscriber, Session

__all__ = [
    "CLOCKS",
    "DRIFT_BOUND_PPM",
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
#: Exchanges the estimate rests on (the last ones: about 40 s of them).
SAMPLES: Final = 128
_FIT_SAMPLES: Final = 3  # good exchanges a drift needs ...
_FIT_SPAN_NS: Final = 1_000_000_000  # ... spread over this long
_RECENT: Final = 8  # the latest exchanges, each a bound on the offset (and before a line, the best carries it)
#: An offset beyond this many seconds is refused as absurd (about ten years).
MAX_OFFSET_S: Final = 10 * 366 * 86400.0
#: Wild answers in a row, agreeing with each other, taken as a step of the peer's clock.
STEP_AFTER: Final = 4
#: How fast or slow a clock may run (ppm) before its drift is measured: a quartz clock is off by
#: 20-50 ppm at most; 100 ppm is 8.6 s a day.
DRIFT_BOUND_PPM: Final = 100.0
_FIT_DRIFT_PPM: Final = 1.0  # a drift that is not quite steady (beyond what the fit's own bound says)
_MAX_DELAY_NS: Final = 1_000_000_000
_BURST: Final = 8  # exchanges in a new peer's first half second
_BURST_S: Final = 0.06
_PERIOD_S: Final = 1.0
_ROUND: Final = 3  # exchanges in a row each period: the first wakes the path up (an exchange after a second idle is slow and uneven)
_MAX_PEERS: Final = 256
_MAX_MISSING: Final = 1024


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
    """A peer clock's offset from this one (peer minus this, ns) at ``at_ns`` of this clock, and how
    sure; ``growth_ppm``: how fast the uncertainty grows when the offset is carried on by its
    drift (:meth:`carried`), as a process that holds no estimator of its own does."""

    clock: int
    offset_ns: int
    uncertainty_ns: int
    drift_ppm: float
    samples: int
    at_ns: int
    growth_ppm: float = 0.0

    def carried(self, at_ns: int) -> tuple[int, int]:
        """``(offset, uncertainty)`` at ``at_ns`` of this clock: the offset carried by the drift."""
        since = at_ns - self.at_ns
        return self.offset_ns + int(self.drift_ppm * 1e-6 * since), self.uncertainty_ns + int(abs(since) * self.growth_ppm * 1e-6)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (µs), as the model shows it."""
        return {
            "clock": f"{self.clock:08x}",
            "offset_us": round(self.offset_ns / 1000, 1),
            "uncertainty_us": round(self.uncertainty_ns / 1000, 1),
            "drift_ppm": round(self.drift_ppm, 2),
            "growth_ppm": round(self.growth_ppm, 2),
            "samples": self.samples,
        }


class Estimator:
    """The offset of one peer's clock, from its exchanges (see the module documentation).

    Not thread-safe: one :class:`ClockTracker` thread feeds it; :meth:`estimate` may be read from
    another thread at any time (it reads an immutable snapshot).
    """

    def __init__(self, clock: int = 0) -> None:
        self.clock = clock  # the peer's clock id: as told (its summary), else from its first answer
        self.refused: Counter[str] = Counter()
        self._samples: deque[tuple[int, int, int]] = deque(maxlen=SAMPLES)  # (t of this clock, offset, width)
        self._last_t2 = 0
        self._wild: deque[tuple[int, int, int, int]] = deque(maxlen=STEP_AFTER)  # (t, offset, width, t2)
        self._estimate: tuple[int, int, float, int, int, float, tuple[tuple[int, int, int], ...]] | None = None
        # (at, offset, drift; the line's bound at, the bound, its growth ppm; the latest exchanges (t, offset, half width))

    def add(self, t1: int, reply: bytes, t4: int, *, sent_ns: int | None = None) -> bool:
        """Take one exchange: the request carried ``t1``, ``reply`` arrived at ``t4``; False when
        refused (counted). ``sent_ns``: this clock read once the request was handed over (``ts``
        in the module documentation; ignored unless ``t1 <= sent_ns <= t4``)."""
        if len(reply) != _ANSWER.size or reply[:4] != _MAGIC:
            return self._refuse("malformed")
        _, echo, t2, t3, clock = _ANSWER.unpack(reply)
        if echo != t1:
            return self._refuse("not this request")
        if self.clock and clock != self.clock:
            return self._refuse("another clock id")
        if t3 < t2:
            return self._refuse("peer time negative")
        delay = (t4 - t1) - (t3 - t2)
        if delay < 0 or delay > _MAX_DELAY_NS:
            return self._refuse("delay out of range")
        low, high = t3 - t4, t2 - t1  # the true offset lies in here, whatever the legs took
        if sent_ns is not None and t1 <= sent_ns <= t4:
            offset = min(high, max(low, ((t2 - sent_ns) + (t3 - t4)) // 2))
        else:
            offset = (low + high) // 2
        width = 2 * max(offset - low, high - offset)  # (the delay, without ts)
        if abs(offset) > MAX_OFFSET_S * 1e9:
            return self._refuse("offset absurd")
        mid = (t1 + t4) // 2
        backwards = t2 < self._last_t2
        current = self.estimate(mid)
        wild = backwards
        if not wild and current is not None and len(self._samples) >= 4:
            wild = abs(offset - current.offset_ns) > 4 * (current.uncertainty_ns + width // 2) + 200_000
        if wild:
            self._wild.append((mid, offset, width, t2))
            if not self._stepped():
                return self._refuse("peer clock went backwards" if backwards else "disagrees with the estimate")
            log.info(
                "the clock %08x stepped by %.3f ms: its estimate starts over", clock, (offset - (current.offset_ns if current else 0)) / 1e6
            )
            self._samples.clear()
            for w_mid, w_offset, w_delay, _ in list(self._wild)[:-1]:
                self._samples.append((w_mid, w_offset, w_delay))
        self._wild.clear()
        self.clock = self.clock or clock
        self._last_t2 = t2
        self._samples.append((mid, offset, width))
        self._fit()
        return True

    def _stepped(self) -> bool:
        """Whether the latest :data:`STEP_AFTER` wild answers agree with each other, the peer's
        clock running forward among them: a step of the peer's clock, not noise or a liar."""
        wild = list(self._wild)
        if len(wild) < STEP_AFTER:
            return False
        last = wild[-1]
        agree = all(abs(w[1] - last[1]) <= 4 * (w[2] + last[2]) + 200_000 for w in wild)
        return agree and all(a[3] <= b[3] for a, b in zip(wild, wild[1:], strict=False))

    def _refuse(self, why: str) -> bool:
        self.refused[why] += 1
        return False

    def _fit(self) -> None:
        samples = list(self._samples)
        recent = tuple((s[0], s[1], s[2] // 2) for s in samples[-_RECENT:])
        newest = samples[-1][0]
        # the drift unknown: of the latest few, the exchange that bounds the offset now the
        # tightest (an older one is worth less), carried with no drift
        t, offset, half = min(recent, key=lambda s: s[2] + (newest - s[0]) * DRIFT_BOUND_PPM * 1e-6)
        self._estimate = (t, offset, 0.0, t, 1 << 62, 0.0, recent)
        widths = sorted(s[2] for s in samples)
        good = [s for s in samples if s[2] <= max(widths[0] * 1.5 + 30_000, widths[len(widths) // 2])]
        if len(good) < _FIT_SAMPLES or good[-1][0] - good[0][0] < _FIT_SPAN_NS:
            return
        # a line through the good exchanges: the offset and the drift, the noise of single
        # exchanges averaged out; its own bound (the module documentation)
        n = len(good)
        mean_t = sum(s[0] for s in good) / n
        mean_o = sum(s[1] for s in good) / n
        var = sum((s[0] - mean_t) ** 2 for s in good)
        drift = sum((s[0] - mean_t) * (s[1] - mean_o) for s in good) / var
        at = good[-1][0]
        slope_ppm = sum(abs(s[0] - mean_t) / var * s[2] / 2 for s in good) * 1e6 + _FIT_DRIFT_PPM
        bounds = [(at, sum(abs(1 / n + (at - mean_t) * (s[0] - mean_t) / var) * s[2] / 2 for s in good))]
        bounds += [(s[0], s[2] / 2 + abs(s[1] - mean_o - drift * (s[0] - mean_t))) for s in good]
        later = newest + 1_000_000_000  # the bound that holds the tightest until the next exchange
        bound_at, bound = min(bounds, key=lambda b: b[1] + (later - b[0]) * slope_ppm * 1e-6)
        self._estimate = (at, int(mean_o + drift * (at - mean_t)), drift, bound_at, int(bound) + 1, slope_ppm, recent)

    def estimate(self, at_ns: int | None = None) -> Estimate | None:
        """The offset at ``at_ns`` of this clock (now when None), or None before any exchange."""
        current = self._estimate
        if current is None:
            return None
        at = time.time_ns() if at_ns is None else at_ns
        base, offset, drift, bound_at, bound, slope_ppm, recent = current
        offset += int(drift * (at - base))
        # the line's own bound, or any recent exchange's with the drift bound for the time since;
        # and how fast the one taken grows (the distance to an exchange grows with the drift)
        uncertainty, growth = bound + int(abs(at - bound_at) * slope_ppm * 1e-6), slope_ppm
        for t, o, half in recent:
            bound_t = abs(offset - o) + half + int(abs(at - t) * DRIFT_BOUND_PPM * 1e-6)
            if bound_t < uncertainty:
                uncertainty, growth = bound_t, DRIFT_BOUND_PPM + abs(drift) * 1e6
        return Estimate(self.clock, offset, uncertainty, drift * 1e6, len(self._samples), at, growth)


class ClockTable:
    """The clocks this process knows: offsets by clock id, for the hot path and for the model.

    :attr:`current` maps clock ids to offsets now (peer minus this, ns), for the hot path: a
    dictionary lookup, kept current by :meth:`refresh` (which a :class:`ClockTracker` calls ten
    times a second) and swapped whole, never changed in place; this process's own clock is 0.
    """

    def __init__(self) -> None:
        self.current: dict[int, int] = {CLOCK_ID: 0}
        self._uncertainty: dict[int, int] = {CLOCK_ID: 0}
        self._claims: dict[int, list[Estimator]] = {}  # clock id -> the estimators of the peers that answer with it
        self._lock = threading.Lock()
        self._missing: dict[int, float] = {}  # clock ids seen in data with no offset known -> when (monotonic)

    def missing(self, clock: int) -> None:
        """Note that data stamped by ``clock`` arrived and its offset is not known (its manager's
        clock is then estimated on demand: :meth:`ClockTracker.reconcile`). Bounded: 1,024 ids."""
        if not clock or clock in self.current:
            return
        seen = self._missing
        if clock in seen or len(seen) < _MAX_MISSING:
            seen[clock] = time.monotonic()

    def unknown(self, within_s: float = 10.0) -> set[int]:
        """The clock ids seen in data within the last ``within_s`` whose offsets are not known."""
        now = time.monotonic()
        found = set()
        for clock, at in list(self._missing.items()):
            if now - at > within_s or clock in self.current:
                self._missing.pop(clock, None)
            else:
                found.add(clock)
        return found

    def offset(self, clock: int) -> int | None:
        """The offset (peer minus this, ns) of ``clock`` now, or None when it is not known."""
        return self.current.get(clock)

    def uncertainty(self, clock: int) -> int | None:
        """How far the offset of ``clock`` may be off (ns), or None when it is not known."""
        return self._uncertainty.get(clock)

    def register(self, estimator: Estimator) -> bool:
        """Keep ``estimator``'s clock in the table (once it has a clock id); False when it cannot.

        A clock id that two peers answer with is nobody's: neither estimate is used for it (its
        offset is not known) while both claim it, and each claim made meanwhile is counted as
        "clock id of another peer" (the ids are random: an honest pair never collides)."""
        clock = estimator.clock
        if not clock or clock == CLOCK_ID:
            return False
        with self._lock:
            claims = self._claims.setdefault(clock, [])
            if estimator not in claims:
                claims.append(estimator)
            if len(claims) == 1:
                return True
        estimator.refused["clock id of another peer"] += 1
        self.refresh()
        return False

    def forget(self, estimator: Estimator) -> None:
        """Stop keeping ``estimator``'s clock."""
        with self._lock:
            claims = self._claims.get(estimator.clock, [])
            if estimator in claims:
                claims.remove(estimator)
            if not claims:
                self._claims.pop(estimator.clock, None)
        self.refresh()

    def refresh(self, now_ns: int | None = None) -> None:
        """Carry every estimate forward to now (the drift applied) for :meth:`offset`."""
        now = time.time_ns() if now_ns is None else now_ns
        offsets, uncertainty = {CLOCK_ID: 0}, {CLOCK_ID: 0}
        with self._lock:
            estimators = [(clock, claims[0]) for clock, claims in self._claims.items() if len(claims) == 1]
        for clock, estimator in estimators:
            found = estimator.estimate(now)
            if found is not None:
                offsets[clock], uncertainty[clock] = found.offset_ns, found.uncertainty_ns
        self.current, self._uncertainty = offsets, uncertainty  # swapped whole: readers never lock


#: This process's clock table.
CLOCKS: Final = ClockTable()


class _Peer:
    __slots__ = ("estimator", "key", "next_at", "pending", "sent")

    def __init__(self, key: str, clock: int) -> None:
        self.key = key
        self.estimator = Estimator(clock)
        self.sent = 0
        self.next_at = 0.0
        self.pending = False  # an exchange is on its way: one at a time per peer


class ClockTracker:
    """Keeps :data:`CLOCKS` (or ``table``) up to date for the peers it is given: a thread that runs
    their exchanges (8 in a peer's first half second, then 3 in a row once a second; one at a time
    per peer, and never waiting on one: a peer that does not answer delays nobody else's) and
    refreshes the table ten times a second. A context manager; :meth:`close` stops it.

    It tracks at most 256 peers. ``in_use()`` names the peers one exchanges data or calls with:
    when the table is full, such a peer takes the place of one that is not, so peers that only
    announce themselves (300 fake managers, say) never leave a real one without an estimate."""

    def __init__(
        self,
        session: Session,
        table: ClockTable = CLOCKS,
        *,
        timeout_s: float = 1.0,
        in_use: Callable[[], Collection[str]] | None = None,
        wanted: Callable[[], Mapping[str, tuple[str, int]]] | None = None,
    ) -> None:
        self._session = session
        self._in_use = in_use  # the peers one exchanges data or calls with: they never go without an estimate
        # on demand: the peers to track (name -> (key, clock id)), asked once a second and at
        # reconcile(); the others are let go
        self._wanted = wanted
        self._reconciled = 0.0
        self._table = table
        self._timeout_s = timeout_s
        self._peers: dict[str, _Peer] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._results: queue.SimpleQueue[tuple[str, _Peer, int, tuple[bytes, int, int, int] | None]] = queue.SimpleQueue()
        self._watch: LivelinessSubscriber | None = None
        self._thread = threading.Thread(target=self._run, name="dyknow-clocks", daemon=True)
        self._thread.start()

    def track(self, name: str, key: str, clock: int = 0) -> None:
        """Estimate the clock of peer ``name``, which answers exchanges on ``key``. ``clock``: its
        clock id when known (a manager's summary names it): answers with another are refused,
        and a new id (the peer restarted under the same name) starts its estimate over."""
        with self._lock:
            known = self._peers.get(name)
            if known is not None and (not clock or known.estimator.clock == clock):
                return
            evicted: _Peer | None = None
            if known is None and len(self._peers) >= _MAX_PEERS:
                used = set(self._in_use()) if self._in_use is not None else set()
                idle = next((n for n in self._peers if n not in used), None) if name in used else None
                if idle is None:
                    log.warning("not estimating the clock of %r: %d peers tracked already", name, _MAX_PEERS)
                    return
                evicted = self._peers.pop(idle)  # a peer in use takes the place of one that is not
            self._peers[name] = _Peer(key, clock)
        if known is not None:
            self._table.forget(known.estimator)
        if evicted is not None:
            self._table.forget(evicted.estimator)
        self._wake.set()

    def follow(self) -> None:
        """Track every manager whose liveliness token appears, and untrack it when its token goes:
        for a process that is no manager (a recorder, a tool). Safe twice."""
        if self._watch is None:
            self._watch = self._session.declare_liveliness_subscriber(keys.managers_pattern(), self._token, inline=True)

    def _token(self, key: str, alive: bool) -> None:
        name = keys.manager_of_token(key)
        if name is None:
            return
        if alive:
            self.track(name, keys.clock_key(name))
        else:
            self.untrack(name)

    def reconcile(self) -> None:
        """Ask ``wanted()`` now (rather than within a second) which peers to track."""
        self._reconciled = 0.0
        self._wake.set()

    def tracked(self) -> set[str]:
        """The peers whose clocks are estimated now."""
        with self._lock:
            return set(self._peers)

    def _reconcile(self) -> None:
        if self._wanted is None:
            return
        try:
            wanted = dict(self._wanted())
        except Exception:  # (the owner's view, read on this thread: a failure skips one round)
            log.exception("which clocks to estimate")
            return
        for name in self.tracked() - set(wanted):
            self.untrack(name)
        for name, (key, clock) in sorted(wanted.items()):
            self.track(name, key, clock)

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
        """Refused exchanges, by peer and reason ("no answer" counts the exchanges that timed out)."""
        with self._lock:
            return {name: dict(peer.estimator.refused) for name, peer in self._peers.items() if peer.estimator.refused}

    def close(self) -> None:
        """Stop the thread (and the watch of :meth:`follow`); safe twice."""
        watch, self._watch = self._watch, None
        if watch is not None:
            watch.undeclare()
        self._stop.set()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(2.0)

    def __enter__(self) -> ClockTracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        refreshed = 0.0
        while not self._stop.is_set():
            self._wake.clear()
            while True:  # what came back, taken on this thread alone (an Estimator is not thread-safe)
                try:
                    name, peer, t1, got = self._results.get_nowait()
                except queue.Empty:
                    break
                self._take(name, peer, t1, got)
            now = time.monotonic()
            if now - self._reconciled >= 1.0:
                self._reconciled = now
                self._reconcile()
            with self._lock:
                due = [(name, peer) for name, peer in self._peers.items() if peer.next_at <= now and not peer.pending]
            for name, peer in due:
                self._send(name, peer)
            if now - refreshed >= 0.1:
                self._table.refresh()
                refreshed = now
            with self._lock:
                waits = [p.next_at for p in self._peers.values() if not p.pending]
            self._wake.wait(max(0.001, min([0.1, *(w - time.monotonic() for w in waits)])))

    def _send(self, name: str, peer: _Peer) -> None:
        peer.sent += 1
        if peer.sent < _BURST:
            peer.next_at = time.monotonic() + _BURST_S
        else:  # the rest of a round right after this one ends, the next round a period later
            peer.next_at = time.monotonic() + (0.0 if (peer.sent - _BURST) % _ROUND else _PERIOD_S)
        t1 = time.time_ns()

        def done(got: tuple[bytes, int, int, int] | None) -> None:  # on a Zenoh thread
            self._results.put((name, peer, t1, got))
            self._wake.set()

        peer.pending = True
        try:
            self._session.exchange(peer.key, request(t1), timeout_s=self._timeout_s, done=done)
        except Exception as exc:  # a closed session, say: the next round tries again
            peer.pending = False
            log.debug("no clock exchange with %r: %s", name, exc)

    def _take(self, name: str, peer: _Peer, t1: int, got: tuple[bytes, int, int, int] | None) -> None:
        with self._lock:  # (the counts are read from other threads)
            peer.pending = False
            estimator = peer.estimator
            if got is None:
                estimator.refused["no answer"] += 1
                return
            reply, sent, arrived, replies = got
            if replies > 1:
                estimator.refused["extra replies"] += replies - 1
            # an answer that came back after the peer left (or was replaced) is not kept
            if estimator.add(t1, reply, arrived, sent_ns=sent) and self._peers.get(name) is peer:
                self._table.register(estimator)


def corrected(time_ns: int, clock: int, table: ClockTable = CLOCKS) -> int | None:
    """``time_ns`` of ``clock``, as this process's clock would have read it; None when unknown."""
    offset = table.offset(clock)
    return None if offset is None else time_ns - offset
