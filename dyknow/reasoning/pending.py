"""The pending-state forest: which retained states still wait for their verdict.

A future window's node (:class:`~dyknow.reasoning.windows.Temporal`, see
:mod:`dyknow.reasoning.progression`) keeps the states whose verdicts are pending; deciding one,
a run of them or the oldest costs O(1) amortized, whatever the window's length.
"""

from __future__ import annotations

from dyknow.reasoning.timeline import Clock

__all__ = ["PendingForest"]


class PendingForest:
    """Which retained states are pending, as a "next pending" forest over them (a union-find whose
    sets are runs of states no longer pending, each pointing on to the next one that is):
    ``skip[i - base]`` is 0 for a pending state, else how far on the next may be (its node appends
    one entry per new state, 0 or 1, and sets a decided state's to 1).

    Deciding a state, a run or the oldest ones then costs O(1) amortized, whatever the window's
    length; a sorted list of pending states paid a memmove of the whole list to take its oldest
    out (7.6 against 4.5 us per state at a 100 s against a 10 ms window).
    """

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.skip: list[int] = []
        self.head = 0  # no state before this one is pending

    def next_pending(self, i: int) -> int:
        """The first pending state at or after ``i`` (one past the newest when none)."""
        skip = self.skip
        k = i - self.clock.base
        if k < 0:
            k = 0
        end = len(skip)
        j = k
        while j < end:
            d = skip[j]
            if d == 0:
                break
            j += d
        while k < j:  # path compression: what was walked over points at j from now on
            d = skip[k]
            if k + d != j:  # (mostly it does already: compiled, a write boxes an int and swaps objects)
                skip[k] = j - k
            k += d
        return j + self.clock.base

    def done(self, i: int) -> None:
        """State ``i`` is no longer pending (decided, or unknown for good)."""
        self.skip[i - self.clock.base] = 1

    def retire(self, edge: int) -> None:
        """Pending states at or before ``edge``, so old that every state that could decide them is
        in: unknown for good."""
        clock = self.clock
        times = clock.times
        base = clock.base
        skip = self.skip
        k = self.head - base
        if k < 0:
            k = 0
        if k >= len(skip) or times[k] > edge:
            return  # (the common case: no state from head on is that old, pending or not)
        i = self.next_pending(self.head)
        while i - base < len(skip) and times[i - base] <= edge:
            skip[i - base] = 1
            i = self.next_pending(i + 1)
        self.head = i

    def keep_newest(self, count: int) -> None:
        """The monitor dropped the oldest retained states but ``count``: pending ones among them
        were given up before their time (unknown for good); the runs after them keep their lengths."""
        del self.skip[: len(self.skip) - count]
