"""A unit's ports: each input's bounded queue, counters and senders, each output's sequence and publisher.

An input port queues what its unit has not handled yet (keep-last by default, like a Zenoh ring
channel; or drop-new) and counts drops, so a slow unit never blocks its upstream; what to do
with each message (run the unit now, forward it, queue it, shed it) is its unit's job's
(:class:`~dyknow.proxy.job.UnitJob`). Every message handed to a unit is counted with its age
since origin and its time since the previous hop, in this process's clock (:func:`arrived`).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Final, Protocol

from dyknow.clocks import CLOCKS
from dyknow.errors import BindingError, did_you_mean
from dyknow.message import CLOCK_ID, Message, new_id
from dyknow.stats import PortCounters

if TYPE_CHECKING:
    from dyknow.transport import LivelinessToken, Publisher

__all__ = ["InputPort", "OutputPort", "PortJob", "arrived", "no_port", "uncertainty_us"]

log = logging.getLogger(__name__)

# An input port follows the sequence numbers of at most this many senders at once.
_MAX_SENDERS: Final = 64


class PortJob(Protocol):
    """What an input port needs of its unit's job (:class:`~dyknow.proxy.job.UnitJob`): it hands
    over the messages that come from other processes."""

    def deliver_remote(self, port: InputPort, msg: Message) -> None:
        """Run the unit on ``msg`` (from another process, on ``port``) now, or queue it; quick."""
        ...

    def forward_wire(self, port: InputPort, data: Any, header: bytes) -> bool:
        """Pass a message from another process on as it came, before it is decoded (True), or
        leave it to :meth:`deliver_remote` (False)."""
        ...


class InputPort:
    """An input port: its key, its bounded queue, its counters."""

    __slots__ = ("counters", "depth", "forward", "job", "keep_last", "key", "name", "queue", "senders")

    def __init__(self, job: PortJob, name: str, key: str, depth: int, keep_last: bool) -> None:
        self.job = job
        self.name = name
        self.key = key
        self.depth = depth
        self.keep_last = keep_last
        # keep-last: the deque's maxlen drops the oldest; drop-new: push() refuses when full
        # each queued message with its arrival number among all the unit's inputs: a unit of
        # several takes them in the order they came (a formula monitor reads its streams in time
        # order), not port by port
        self.queue: deque[tuple[int, Message]] = deque(maxlen=depth if keep_last else None)
        self.counters = PortCounters()
        self.forward: OutputPort | None = None  # the unit's forward_to: dyknow publishes there itself
        self.senders: dict[int, int] = {}  # source -> the last seq seen from it (messages from other processes)

    def track(self, source: int, seq: int) -> None:
        """Follow ``source``'s sequence numbers: a gap is messages it sent that never arrived
        (dropped by its Zenoh publisher under congestion, or on the way), counted as ``lost``.
        A number at or below the last one is a sender that started over: no gap."""
        if source == 0:
            return
        senders = self.senders
        last = senders.get(source)
        if last is None:
            if len(senders) >= _MAX_SENDERS:
                senders.clear()  # bounded: senders come and go (a rebinding draws a new source)
        elif seq > last + 1:
            self.counters.lost += seq - last - 1
        senders[source] = seq

    def deliver_remote(self, msg: Message) -> None:
        """A message from another process, on Zenoh's receiving thread: the unit's job runs a unit
        proven quick and free right here (no thread hand-off), queues it for the unit's lane otherwise."""
        self.job.deliver_remote(self, msg)

    def forward_wire(self, data: Any, header: bytes) -> bool:
        """A message from another process, before it is decoded: a unit that only forwards
        passes it on as it came when it is free (True); False hands it to :meth:`deliver_remote`."""
        if self.forward is None or self.queue:
            return False
        return self.job.forward_wire(self, data, header)

    def reject(self, unit: str, reason: str, *, expected: bool = False) -> None:
        """Count and log an unusable message (``expected``: at INFO) of ``unit``; the unit carries on."""
        counters = self.counters
        counters.rejected += 1
        counters.last_rejection = reason
        # log the first few, then every 100th, so a stream of bad frames does not flood the log
        if counters.rejected <= 3 or counters.rejected % 100 == 0:
            level = logging.INFO if expected else logging.WARNING
            log.log(level, "unit %r rejected a message on %r (%d so far): %s", unit, self.name, counters.rejected, reason)

    def push(self, msg: Message, arrival: int = 0) -> bool:
        """Queue ``msg`` (``arrival``: its number among the unit's arrivals), counting a drop when
        the queue is full: keep-last drops the oldest, drop-new refuses ``msg`` (False). Any
        thread; never blocks."""
        q = self.queue
        if len(q) >= self.depth:
            self.counters.dropped += 1
            if not self.keep_last:
                return False  # drop-new: keep what is queued
            # keep-last: the deque's maxlen drops the oldest on append
        q.append((arrival, msg))
        return True


class OutputPort:
    """An output port: its key, sequence number, local targets and Zenoh publisher."""

    __slots__ = ("counters", "key", "name", "publisher", "seq", "source", "targets", "token")

    def __init__(self, name: str, key: str) -> None:
        self.name = name
        self.key = key
        self.seq = 0
        self.source = new_id()  # the id readers follow its seq by (drawn again when it is rebound)
        self.counters = PortCounters()
        self.targets: tuple[InputPort, ...] = ()
        self.publisher: Publisher | None = None
        # announces on the port's key that its producer lives (others watch it to notice a crash)
        self.token: LivelinessToken | None = None


def arrived(counters: PortCounters, nbytes: int, now: int, origin_ns: int, origin_clock: int, send_ns: int, send_clock: int) -> None:
    """Count one message handed to a unit, its age and hop in this process's clock: times of
    another clock corrected by its offset (dyknow.clocks), or left out when it is not known. A
    corrected figure below zero (the estimate off by less than its uncertainty, on a hop shorter
    than that) counts as zero: a message never arrives before it was sent."""
    if origin_clock == CLOCK_ID and send_clock == CLOCK_ID:
        counters.arrived(nbytes, now - origin_ns, now - send_ns)
        return
    current = CLOCKS.current
    origin_offset = current.get(origin_clock)
    send_offset = current.get(send_clock)
    if origin_offset is None or send_offset is None:
        counters.arrived_unknown(nbytes)
        CLOCKS.missing(origin_clock if origin_offset is None else send_clock)  # estimated on demand
        return
    counters.clocks = (origin_clock, send_clock)
    age, hop = now - origin_ns + origin_offset, now - send_ns + send_offset
    counters.arrived(nbytes, age if age > 0 else 0, hop if hop > 0 else 0)


def uncertainty_us(clocks: tuple[int, int]) -> float:
    """How far the offsets of ``clocks`` may be off now (µs; 0 for this process's own)."""
    worst = 0
    for clock in clocks:
        if clock != 0 and clock != CLOCK_ID:
            worst = max(worst, CLOCKS.uncertainty(clock) or 0)
    return round(worst / 1000, 1)


def no_port(unit: str, port: str, direction: str, ports: Mapping[str, object]) -> BindingError:
    """The error for a port ``unit`` does not have (``direction``: "input", "output" or "" for either)."""
    kind = f"{direction} port" if direction else "port"
    names = ", ".join(repr(p) for p in ports) or "none"
    return BindingError(f"no {kind} {port!r}", where=f"unit {unit!r}", expected=f"one of {names}{did_you_mean(port, ports)}")
