"""What an operator measures of a stream from outside: its rate, the jitter of its intervals, its
message sizes and bandwidth (``dyknow hz``, as ``ros2 topic hz`` and ``ros2 topic bw`` do).

A :class:`StreamMeter` takes each sample's arrival time and size (:meth:`StreamMeter.add`, on
Zenoh's thread: a few list operations) and keeps the last ``window`` of them per key; figures
are computed when asked (:meth:`StreamMeter.figures`). Times are this process's monotonic clock
at arrival, so the figures describe the stream as delivered here (network and scheduling
included), not as published.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

__all__ = ["StreamFigures", "StreamMeter"]


@dataclass(frozen=True, slots=True)
class StreamFigures:
    """One key's figures over its last ``window`` messages (intervals in milliseconds, sizes in
    bytes of payload and attachment as they crossed the network)."""

    key: str
    messages: int  # since the meter started
    window: int  # messages the figures are computed over
    rate_hz: float  # (window - 1) / (last arrival - first arrival)
    interval_min_ms: float
    interval_max_ms: float
    interval_mean_ms: float
    jitter_ms: float  # standard deviation of the intervals
    size_mean_b: float
    size_min_b: int
    size_max_b: int
    bandwidth_bps: float  # bytes a second over the window
    idle_s: float  # since the last message

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (``dyknow hz --json``)."""
        return {
            "key": self.key,
            "messages": self.messages,
            "window": self.window,
            "rate_hz": round(self.rate_hz, 3),
            "interval_ms": {
                "min": round(self.interval_min_ms, 3),
                "max": round(self.interval_max_ms, 3),
                "mean": round(self.interval_mean_ms, 3),
                "std": round(self.jitter_ms, 3),
            },
            "size_bytes": {"mean": round(self.size_mean_b, 1), "min": self.size_min_b, "max": self.size_max_b},
            "bandwidth_bps": round(self.bandwidth_bps, 1),
            "idle_s": round(self.idle_s, 3),
        }

    def __str__(self) -> str:
        return (
            f"{self.key}: {self.rate_hz:.2f} Hz  interval min {self.interval_min_ms:.2f} max {self.interval_max_ms:.2f} "
            f"jitter {self.jitter_ms:.2f} ms  size {_bytes(self.size_mean_b)} (min {_bytes(self.size_min_b)}, max "
            f"{_bytes(self.size_max_b)})  {_bytes(self.bandwidth_bps)}/s  window {self.window}"
        )


def _bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB"):
        if n < 1024 or unit == "MiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    return f"{n:.2f} GiB"


class StreamMeter:
    """Arrival times and sizes of each key's last ``window`` messages (thread-safe)."""

    def __init__(self, window: int = 100) -> None:
        if window < 2:
            raise ValueError(f"window={window}; expected at least 2 messages")
        self.window = window
        self._lock = threading.Lock()
        self._arrivals: dict[str, deque[tuple[int, int]]] = {}
        self._counts: dict[str, int] = {}

    def add(self, key: str, nbytes: int, now_ns: int | None = None) -> None:
        """One message of ``nbytes`` arrived on ``key`` (now, or at ``now_ns`` of the monotonic clock)."""
        now = time.monotonic_ns() if now_ns is None else now_ns
        with self._lock:
            found = self._arrivals.get(key)
            if found is None:
                found = self._arrivals[key] = deque(maxlen=self.window)
            found.append((now, nbytes))
            self._counts[key] = self._counts.get(key, 0) + 1

    def figures(self, now_ns: int | None = None) -> list[StreamFigures]:
        """Every key's figures (keys with at least two messages), by key."""
        now = time.monotonic_ns() if now_ns is None else now_ns
        with self._lock:
            snapshot = {key: list(arrivals) for key, arrivals in self._arrivals.items()}
            counts = dict(self._counts)
        out = []
        for key in sorted(snapshot):
            arrivals = snapshot[key]
            if len(arrivals) < 2:
                continue
            times = [t for t, _ in arrivals]
            sizes = [n for _, n in arrivals]
            intervals = [(b - a) / 1e6 for a, b in zip(times, times[1:], strict=False)]
            mean = sum(intervals) / len(intervals)
            std = math.sqrt(sum((i - mean) ** 2 for i in intervals) / len(intervals))
            span_s = (times[-1] - times[0]) / 1e9
            out.append(
                StreamFigures(
                    key=key,
                    messages=counts[key],
                    window=len(arrivals),
                    rate_hz=(len(arrivals) - 1) / span_s if span_s > 0 else math.inf,
                    interval_min_ms=min(intervals),
                    interval_max_ms=max(intervals),
                    interval_mean_ms=mean,
                    jitter_ms=std,
                    size_mean_b=sum(sizes) / len(sizes),
                    size_min_b=min(sizes),
                    size_max_b=max(sizes),
                    bandwidth_bps=sum(sizes[1:]) / span_s if span_s > 0 else math.inf,
                    idle_s=(now - times[-1]) / 1e9,
                )
            )
        return out

    def counts(self) -> dict[str, int]:
        """Messages seen per key since the start."""
        with self._lock:
            return dict(self._counts)
