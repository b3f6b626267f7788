"""Per-port statistics: message and byte counts, drops, and latency percentiles.

Recording is on the hot path, so it is a few integer operations into preallocated ring buffers;
percentiles are computed only when someone asks (``snapshot()``), over the last
:data:`WINDOW` samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

__all__ = ["WINDOW", "LatencySummary", "PortCounters", "PortStatistics", "summarize"]

#: How many recent latency samples percentiles are computed over.
WINDOW: Final = 1024
_MASK: Final = WINDOW - 1


@dataclass(frozen=True, slots=True)
class LatencySummary:
    """Latency percentiles in microseconds over the last ``count`` samples (at most WINDOW)."""

    count: int
    p50_us: float
    p90_us: float
    p99_us: float
    max_us: float

    def to_dict(self) -> dict[str, float]:
        """The JSON form, in microseconds."""
        return {
            "count": self.count,
            "p50_us": round(self.p50_us, 3),
            "p90_us": round(self.p90_us, 3),
            "p99_us": round(self.p99_us, 3),
            "max_us": round(self.max_us, 3),
        }


EMPTY = LatencySummary(0, 0.0, 0.0, 0.0, 0.0)


def summarize(samples_ns: list[int]) -> LatencySummary:
    """Percentiles (nearest rank) of latency samples given in nanoseconds."""
    if not samples_ns:
        return EMPTY
    ordered = sorted(samples_ns)
    n = len(ordered)

    def rank(q: float) -> float:
        return ordered[min(n - 1, max(0, int(q * n + 0.5) - 1))] / 1000.0

    return LatencySummary(n, rank(0.50), rank(0.90), rank(0.99), ordered[-1] / 1000.0)


@dataclass(frozen=True, slots=True)
class PortStatistics:
    """A snapshot of one port's statistics.

    For input ports, ``latency`` is arrival at the unit minus the origin timestamp (end-to-end
    age of the data) and ``hop`` is arrival minus the send timestamp of the previous hop.
    ``dropped`` counts what the port itself dropped (its queue was full); for input ports,
    ``lost`` counts messages another process sent that never arrived (gaps in each sender's
    sequence numbers: its Zenoh publisher drops rather than blocks under congestion).

    Times from another host's clock are corrected by that clock's estimated offset
    (:mod:`dyknow.clocks`) before they count in ``latency`` and ``hop``; ``uncertainty_us`` is
    how far the latest one may be off for it (0 when both times were this process's). A message
    stamped by a clock whose offset is not known yet is counted in ``unknown_clock`` and left out
    of both figures: never shown as if it were true.

    ``bytes`` counts the size of what was encoded or is bytes or an array; a JSON-like value (or
    text) handed between units of one manager by reference is never encoded, so its size is not
    known: such messages are counted in ``unsized`` (their bytes are not in ``bytes``).

    ``shed`` counts the messages an input port let go while its manager shed load
    (:mod:`dyknow.overload`): they never reached the unit, and are not in ``messages``.
    """

    port: str
    direction: str
    key: str
    messages: int
    bytes: int
    dropped: int
    latency: LatencySummary
    hop: LatencySummary
    rejected: int = 0
    last_rejection: str | None = None
    lost: int = 0
    unknown_clock: int = 0
    uncertainty_us: float = 0.0
    unsized: int = 0
    shed: int = 0

    def to_dict(self) -> dict[str, object]:
        """The JSON form (latency and hop only for input ports)."""
        out: dict[str, object] = {
            "direction": self.direction,
            "key": self.key,
            "messages": self.messages,
            "bytes": self.bytes,
            "unsized": self.unsized,
            "dropped": self.dropped,
        }
        if self.direction == "in":
            out["lost"] = self.lost
            out["clock"] = {"unknown": self.unknown_clock, "uncertainty_us": self.uncertainty_us}
            out["shed"] = self.shed
            out["rejected"] = self.rejected
            out["last_rejection"] = self.last_rejection
            out["latency"] = self.latency.to_dict()
            out["hop"] = self.hop.to_dict()
        return out


class PortCounters:
    """Mutable counters of one port, updated on the hot path."""

    __slots__ = (
        "_hop", "_latency", "_n", "bytes", "clocks", "dropped", "last_rejection", "lost", "messages", "rejected", "shed", "unknown_clock",
        "unsized",
    )  # fmt: skip

    def __init__(self) -> None:
        self.messages = 0
        self.bytes = 0
        self.unsized = 0  # messages whose size is not known (JSON-like values passed by reference)
        self.dropped = 0
        self.lost = 0
        self.unknown_clock = 0
        self.clocks = (0, 0)  # the clocks of the latest corrected sample (origin, send); (0, 0): this process's
        self.rejected = 0
        self.shed = 0  # messages let go while the manager shed load
        self.last_rejection: str | None = None
        self._latency = [0] * WINDOW
        self._hop = [0] * WINDOW
        self._n = 0

    def record(self, latency_ns: int, hop_ns: int) -> None:
        """Record one latency sample (age since origin, time since the previous hop)."""
        i = self._n & _MASK
        self._latency[i] = latency_ns
        self._hop[i] = hop_ns
        self._n += 1

    def arrived(self, nbytes: int, latency_ns: int, hop_ns: int) -> None:
        """Count one message handed to a unit (one call on the hot path instead of three)."""
        self.messages += 1
        self.bytes += nbytes
        if nbytes == 0:
            self.unsized += 1
        i = self._n & _MASK
        self._latency[i] = latency_ns
        self._hop[i] = hop_ns
        self._n += 1

    def arrived_unknown(self, nbytes: int) -> None:
        """Count one message handed to a unit whose times come from a clock of unknown offset."""
        self.messages += 1
        self.bytes += nbytes
        if nbytes == 0:
            self.unsized += 1
        self.unknown_clock += 1

    def samples_since(self, start: int) -> tuple[int, list[int], list[int]]:
        """``(n, latencies_ns, hops_ns)``: how many samples were recorded so far, and those recorded
        since the ``start``-th (at most the last :data:`WINDOW`; all of them when ``start`` is past
        ``n``, as for counters made anew). For exporters that keep histograms (dyknow.metrics)."""
        n = self._n
        first = max(0 if start > n else start, n - WINDOW)
        slots = [i & _MASK for i in range(first, n)]
        return n, [self._latency[i] for i in slots], [self._hop[i] for i in slots]

    def snapshot(self, port: str, direction: str, key: str, uncertainty_us: float = 0.0) -> PortStatistics:
        """The counters and percentiles of the last samples, as plain data (``uncertainty_us``:
        what the caller knows of the offsets of :attr:`clocks`)."""
        n = min(self._n, WINDOW)
        return PortStatistics(
            port,
            direction,
            key,
            self.messages,
            self.bytes,
            self.dropped,
            summarize(self._latency[:n]),
            summarize(self._hop[:n]),
            self.rejected,
            self.last_rejection,
            self.lost,
            self.unknown_clock,
            uncertainty_us,
            self.unsized,
            self.shed,
        )
