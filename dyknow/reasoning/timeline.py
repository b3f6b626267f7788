"""The timeline a monitor's nodes share: the retained states' times and each term's stale spans.

:class:`Clock` holds the retained states' times and indices, :class:`Held` each term's latest
sample and the spans it was stale in; both are searched by bisection over sorted ints. Part of
the window machinery of :mod:`dyknow.reasoning.progression` (which states how a monitor turns
samples into states); :mod:`~dyknow.reasoning.windows` holds the rest.
"""

from __future__ import annotations

from typing import Any, Final

__all__ = ["NEVER", "Clock", "Held", "bisect_left", "bisect_right"]

# (Final: compiled, a plain module global is a dictionary lookup at every use)
NEVER: Final = -(2**62)  # a time before every sample


def bisect_left(a: list[int], x: int) -> int:
    """Where ``x`` goes in the sorted ``a``, before equal ones (the bisect module's, compiled:
    it compares ints natively, where the module compares objects)."""
    lo = 0
    hi = len(a)
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


def bisect_right(a: list[int], x: int) -> int:
    """Where ``x`` goes in the sorted ``a``, after equal ones."""
    lo = 0
    hi = len(a)
    while lo < hi:
        mid = (lo + hi) >> 1
        if x < a[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


class Clock:
    """The retained states' times, shared by the nodes: ``times[i - base]`` is state i's time,
    and ``idx[i - base]`` is i itself, as the one int object every list that holds state i
    shares (compiled, an int put into a list is boxed: an object made, and freed when the list
    lets it go; one per state made here costs less than one per list and use)."""

    def __init__(self) -> None:
        self.times: list[int] = []
        self.idx: list[Any] = []
        self.base = 0
        self.given_up_t = NEVER  # the newest state dropped before the formula was done with it

    def at(self, i: int) -> int:
        """State ``i``'s time."""
        return self.times[i - self.base]

    def first_at_or_after(self, t: int) -> int:
        """The index of the first retained state at or after ``t``."""
        return bisect_left(self.times, t) + self.base

    def last_at_or_before(self, t: int) -> int:
        """The index of the last retained state at or before ``t`` (``base - 1`` if none)."""
        return bisect_right(self.times, t) - 1 + self.base


class Held:
    """What the stream nodes of a monitor read, and its windows ask: each term's latest sample
    time, its maximum age (-1: no bound) and the time spans it was stale in (open: ``from < t <
    until``; the one it may be stale in now runs from its latest sample's time plus its age),
    shared by the monitor and its nodes. Spans older than ``keep_ns`` before the newest sample
    are dropped, the latest end among them noted in ``pruned_end`` (a window reaching back past
    it, one without a bound or one from the first state, still finds them)."""

    def __init__(self, terms: int) -> None:
        self.times: list[int] = [NEVER] * terms
        self.max_age: list[int] = [-1] * terms
        self.aged = False  # whether some term has a maximum age (else nothing is ever stale)
        self.periods: list[list[tuple[int, int]]] = [[] for _ in range(terms)]
        self.heads: list[int] = [0] * terms
        self.pruned_end: list[int] = [NEVER] * terms
        self.keep_ns = 0
        self.max_periods = 1 << 62
        self.first_t = NEVER  # the first state's time: where a window without a bound starts (the monitor sets it)

    def sample(self, k: int, t: int, boxed: Any) -> None:
        """Term ``k`` had a sample at ``t`` (in time order; ``boxed``: the same int as an object)."""
        age = self.max_age[k]
        if age >= 0 and self.times[k] != NEVER and t - self.times[k] > age + 1:
            last = self.times[k]
            periods = self.periods[k]
            periods.append((last + age, t))
            head = self.heads[k]
            edge = t - self.keep_ns
            while head < len(periods) and (periods[head][1] < edge or len(periods) - head > self.max_periods):
                if periods[head][1] > self.pruned_end[k]:
                    self.pruned_end[k] = periods[head][1]
                head += 1
            if head > 64 and head * 2 > len(periods):
                del periods[:head]
                head = 0
            self.heads[k] = head
        self.times[k] = boxed

    def stale(self, terms: list[int], lo: int | None, hi: int) -> bool:
        """Whether one of ``terms`` is stale at a whole-ns time of ``[lo, hi]`` (``lo`` None: a
        window without a bound, from the first state on). A span that reaches back before the
        first state reaches the outages there too, as the semantics' span rule says."""
        if not self.aged:
            return False
        if lo is None and self.first_t != NEVER:
            lo = self.first_t
        for k in terms:
            age = self.max_age[k]
            if age < 0:
                continue
            pruned = self.pruned_end[k]
            if pruned != NEVER and (lo is None or pruned - 1 >= lo):
                return True  # a span dropped reaches into it (an unbounded window from the first state)
            last = self.times[k]
            if last != NEVER and (last + age + 1 if lo is None else max(last + age + 1, lo)) <= hi:
                return True  # stale since its latest sample
            periods = self.periods[k]
            for index in range(len(periods) - 1, self.heads[k] - 1, -1):
                start, end = periods[index]
                if end - 1 < (lo if lo is not None else NEVER):
                    break  # (older ones end before the span)
                first = start + 1 if lo is None else max(start + 1, lo)
                if first <= min(end - 1, hi):
                    return True
        return False
