"""The monitor's aggregates of a past window: count, sum, avg, min, max, rate and integral.

Each costs O(1) amortized per state, its sums kept exact. A node kind of
:mod:`dyknow.reasoning.progression`'s monitor, on :class:`~dyknow.reasoning.nodes.Value`; what
each aggregate means is the semantics' (exactly).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from dyknow.reasoning.nodes import Condition, Value
from dyknow.reasoning.timeline import Held
from dyknow.reasoning.values import TRUE, UNKNOWN, UNKNOWN_VALUE, arith

__all__ = ["AggregateValue"]


class _Total:
    """The exact sum of numbers as the semantics defines it (``exact_sum``), kept as values come
    and go: the ``int`` s summed exactly, and every value as a float in Shewchuk's partials
    (non-overlapping floats whose sum is exact), so taking a value out is adding its negative
    and loses nothing. Rounded once, when read."""

    __slots__ = ("floats", "huge", "ints", "partials")

    def __init__(self) -> None:
        self.ints = 0  # the sum of the int values
        self.floats = 0  # how many values are floats
        self.huge = 0  # ints too large for a float
        self.partials: list[float] = []

    def add(self, x: Any, sign: int) -> None:
        if type(x) is int:
            self.ints += sign * x
            try:
                f = float(x)
            except OverflowError:
                self.huge += sign
                return
        else:
            self.floats += sign
            f = float(x)
        self._add(f if sign > 0 else -f)

    def _add(self, x: float) -> None:
        partials = self.partials
        i = 0
        for y in partials:
            if abs(x) < abs(y):
                x, y = y, x
            hi = x + y
            lo = y - (hi - x)
            if lo:
                partials[i] = lo
                i += 1
            x = hi
        del partials[i:]
        partials.append(x)

    def value(self, extra: Sequence[Any] = ()) -> Any:
        """The sum, with ``extra`` numbers added (not kept); unknown when not finite."""
        if self.floats == 0 and all(type(x) is int for x in extra):
            total: Any = self.ints
            for x in extra:
                total += x
            return total
        if self.huge or any(type(x) is int and abs(x) > 1 << 1023 for x in extra):
            return UNKNOWN_VALUE
        try:
            result = math.fsum([*self.partials, *(float(x) for x in extra)])
        except OverflowError:
            return UNKNOWN_VALUE
        return result if result - result == 0.0 else UNKNOWN_VALUE


def _number(x: Any) -> bool:
    kind = type(x)
    return kind is int or kind is float


class AggregateValue(Value):
    """``count``, ``sum``, ``avg``, ``min``, ``max``, ``rate`` and ``integral`` of a past window, in
    O(1) amortized per state: the states younger than ``lo`` wait in ``pending``, the window's in
    ``entries`` (a bounded window only); running totals, monotonic queues for ``min``/``max``, the
    window's ends for ``rate``, and for ``integral`` the exact sum of the pieces between entries,
    the entry before the window and the state after it for the pieces cut by the span's ends."""

    def __init__(self, kind: str, lo_ns: int, hi_ns: int | None, arg: Value | None, cond: Condition | None) -> None:
        super().__init__()
        self.kind = kind
        self.lo = lo_ns
        self.bounded = hi_ns is not None
        self.hi = hi_ns if hi_ns is not None else 0
        self.arg = arg
        self.cond = cond
        self.pending: list[tuple[int, Any]] = []
        self.phead = 0
        self.entries: list[tuple[int, Any]] = []
        self.ehead = 0
        self.count = 0  # entries in the window
        self.true = 0  # count: entries true
        self.bad = 0  # entries that are unknown (count) or not numbers (the others)
        self.total = _Total()
        self.extreme: list[tuple[int, Any]] = []  # min/max: a monotonic queue of (time, value)
        self.xhead = 0
        self.first: tuple[int, Any] | None = None  # the oldest entry (rate, unbounded)
        self.last: tuple[int, Any] | None = None  # the newest entry
        self.before: tuple[int, Any] | None = None  # the entry that left the window last (integral)
        self.pieces_bad = 0  # integral: pieces between entries whose value is not a number
        self.lost_t = -(2**62)  # the newest state given up (over max_states) and what may hide behind it
        self.held: Held | None = None  # the staleness of the terms below (set by the monitor)
        self.below: list[int] = []
        self.first_t = -(2**62)  # the first state's time (an unbounded window's start)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        value = self.arg.val if self.arg is not None else self.cond.cur  # type: ignore[union-attr]
        if n == 0:
            self.first_t = t
        if self.lo == 0:
            self.enter(t, value)
        else:
            pending = self.pending
            pending.append((t, value))
            edge = t - self.lo
            head = self.phead
            while head < len(pending) and pending[head][0] <= edge:
                self.enter(*pending[head])
                head += 1
            if head > 64 and head * 2 > len(pending):
                del pending[:head]
                head = 0
            if len(pending) - head > self.max_states:  # over the memory bound: give up the oldest
                cut = len(pending) - self.max_states + self.max_states // 4
                self.lost_t = max(self.lost_t, pending[cut - 1][0])
                self.given_up += cut - head
                del pending[:cut]
                head = 0
            self.phead = head
        if self.bounded:
            self.leave(t - self.hi)
        self.val = self.result(t)

    def enter(self, t: int, value: Any) -> None:
        kind = self.kind
        self.count += 1
        if kind == "count":
            if value == UNKNOWN:
                self.bad += 1
            elif value == TRUE:
                self.true += 1
        elif not _number(value):
            self.bad += 1
        elif kind == "sum" or kind == "avg":
            self.total.add(value, 1)
        elif kind == "min" or kind == "max":
            extreme = self.extreme
            keep_min = kind == "min"
            while len(extreme) > self.xhead and (extreme[-1][1] >= value if keep_min else extreme[-1][1] <= value):
                extreme.pop()
            extreme.append((t, value))
        if kind == "integral" and self.last is not None:
            t0, v0 = self.last
            if _number(v0):
                self.total.add(v0 * (t - t0), 1)
            else:
                self.pieces_bad += 1
        if self.first is None:
            self.first = (t, value)
        self.last = (t, value)
        if self.bounded:
            self.entries.append((t, value))
            if len(self.entries) - self.ehead > self.max_states:  # over the memory bound: give up the oldest
                cut = len(self.entries) - self.max_states + self.max_states // 4
                self.lost_t = max(self.lost_t, self.entries[cut - 1][0])
                self.given_up += cut - self.ehead
                while self.ehead < cut:
                    self.drop()

    def leave(self, edge: int) -> None:
        """Entries older than ``edge`` leave the window."""
        entries = self.entries
        while self.ehead < len(entries) and entries[self.ehead][0] < edge:
            self.drop()
        if self.ehead > 64 and self.ehead * 2 > len(entries):
            del entries[: self.ehead]
            self.ehead = 0

    def drop(self) -> None:
        """The oldest entry leaves the window."""
        entries = self.entries
        t, value = entries[self.ehead]
        self.ehead += 1
        kind = self.kind
        self.count -= 1
        if kind == "count":
            if value == UNKNOWN:
                self.bad -= 1
            elif value == TRUE:
                self.true -= 1
        elif not _number(value):
            self.bad -= 1
        elif kind == "sum" or kind == "avg":
            self.total.add(value, -1)
        elif kind == "min" or kind == "max":
            extreme = self.extreme
            if self.xhead < len(extreme) and extreme[self.xhead][0] == t:
                self.xhead += 1
                if self.xhead > 64 and self.xhead * 2 > len(extreme):
                    del extreme[: self.xhead]
                    self.xhead = 0
        if kind == "integral" and self.ehead < len(entries):
            t1 = entries[self.ehead][0]
            if _number(value):
                self.total.add(value * (t1 - t), -1)
            else:
                self.pieces_bad -= 1
        self.before = (t, value)
        self.first = entries[self.ehead] if self.ehead < len(entries) else None
        if self.first is None:
            self.last = None

    def result(self, t: int) -> Any:
        kind = self.kind
        start = t - self.hi if self.bounded else -(2**62)
        if self.lost_t > -(2**62) and self.lost_t >= start:
            return UNKNOWN_VALUE  # a state given up may be in the window
        held = self.held
        if held is not None and held.stale(self.below, start if self.bounded else None, t - self.lo):
            return UNKNOWN_VALUE  # a term below was stale in the window
        if kind == "integral":
            return self.integral(t, start)
        if self.bad and kind != "rate":
            return UNKNOWN_VALUE
        if kind == "count":
            return self.true
        if kind == "sum":
            return self.total.value()
        if kind == "avg":
            return arith("/", self.total.value(), self.count) if self.count else UNKNOWN_VALUE
        if kind == "min" or kind == "max":
            return self.extreme[self.xhead][1] if self.xhead < len(self.extreme) else UNKNOWN_VALUE
        # rate
        first, last = self.first, self.last
        if first is None or last is None or first[0] == last[0]:
            return UNKNOWN_VALUE
        if not _number(first[1]) or not _number(last[1]):
            return UNKNOWN_VALUE
        return arith("/", arith("-", last[1], first[1]), (last[0] - first[0]) / 1e9)

    def integral(self, t: int, start: int) -> Any:
        right = t - self.lo
        nxt = self.pending[self.phead][0] if self.phead < len(self.pending) else t  # the state after the window
        extra: list[Any] = []
        first, last = self.first, self.last
        if last is None:  # no state in the window: one piece spans it, the last to leave
            before = self.before
            if before is None:
                return 0
            d = right - max(start, before[0])
            if d <= 0:
                return 0
            if not _number(before[1]):
                return UNKNOWN_VALUE
            return arith("/", before[1] * d, 1e9)
        if self.pieces_bad:
            return UNKNOWN_VALUE
        assert first is not None
        before = self.before
        if before is not None and first[0] > start:  # the piece cut by the span's start
            if not _number(before[1]):
                return UNKNOWN_VALUE
            extra.append(before[1] * (first[0] - max(start, before[0])))
        d = min(nxt, right) - last[0]  # the piece cut by the span's end
        if d > 0:
            if not _number(last[1]):
                return UNKNOWN_VALUE
            extra.append(last[1] * d)
        total = self.total.value(extra)
        return arith("/", total, 1e9) if total is not UNKNOWN_VALUE else UNKNOWN_VALUE
