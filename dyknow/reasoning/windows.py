"""The window machinery of the temporal nodes: sorted position lists, and :class:`Temporal`.

A temporal node whose operands are decided after their state (:class:`Temporal`, the base of
:class:`~dyknow.reasoning.future.UntilNode` and :class:`~dyknow.reasoning.past.SinceNode`)
keeps sorted lists of the positions where they are true, false, ..., searched by bisection and
pruned: each newly decided operand value resolves exactly the pending states it decides, found
as one contiguous range (see :mod:`dyknow.reasoning.progression`). A position is a state's
index (``Clock.idx``'s int object, shared by every list that holds it).
"""

from __future__ import annotations

from typing import Any, Final

from dyknow.reasoning.nodes import Condition
from dyknow.reasoning.pending import PendingForest
from dyknow.reasoning.timeline import Clock, bisect_left, bisect_right
from dyknow.reasoning.values import FALSE, TRUE

__all__ = ["NONE", "Temporal", "drop_before", "insort", "pred", "prune_keep_last", "remove", "succ"]

NONE: Final = -(2**62)  # "no such state" for the last-position summaries


def drop_before(positions: list[int], head: int, oldest: int) -> int:
    """Move ``head`` past the positions before ``oldest`` and return it; the positions behind it
    are deleted (and it starts over) once they are over 64 and half the list."""
    while head < len(positions) and positions[head] < oldest:
        head += 1
    if head > 64 and head * 2 > len(positions):
        del positions[:head]
        head = 0
    return head


def insort(a: list[int], x: int, boxed: Any) -> None:
    """Insert ``x`` into the sorted ``a`` (as ``boxed``, the same int as an object)."""
    a.insert(bisect_right(a, x), boxed)


def pred(positions: list[int], below: int) -> int:
    """The last position < ``below``, or NONE."""
    k = bisect_left(positions, below)
    return positions[k - 1] if k else NONE


def succ(positions: list[int], above: int) -> int:
    """The first position > ``above``, or -1 (none)."""
    k = bisect_right(positions, above)
    return positions[k] if k < len(positions) else -1


def remove(positions: list[int], position: int) -> None:
    """Take ``position`` out of the sorted ``positions``, if it is there."""
    k = bisect_left(positions, position)
    if k < len(positions) and positions[k] == position:
        del positions[k]


def prune_keep_last(positions: list[int], base: int) -> None:
    """Drop positions before ``base`` but the last of them (what "the last before" queries need)."""
    k = bisect_left(positions, base)
    if k > 1:
        del positions[: k - 1]


class Temporal(Condition):
    """What the asynchronous temporal nodes share: their operands (left None: ``eventually`` or
    ``once``), the negations that make ``always`` and ``historically``, sorted positions of the
    operands' verdicts, and the pending states (a :class:`~dyknow.reasoning.pending.PendingForest`)."""

    def __init__(
        self, clock: Clock, left: Condition | None, right: Condition, lo_ns: int, hi_ns: int, negate: bool, need_ns: int, retire_ns: int
    ) -> None:
        super().__init__(clock, False, need_ns)
        self.completed = -1  # every state up to this one has been checked on completing
        self.left = left
        self.right = right
        self.lo_ns = lo_ns
        self.hi_ns = hi_ns
        self.negate = negate
        self.retire_ns = retire_ns  # a pending state this old can no longer be decided: unknown
        self.pending = PendingForest(clock)  # which retained states are pending
        self.left_nt: list[int] = []  # where left is not true (false or undecided)
        self.left_f: list[int] = []  # where left is false
        self.right_t: list[int] = []  # where right (negated for always/historically) is true
        self.right_nf: list[int] = []  # where it is not false
        # what operand_events found this step: where left became true, false, right true, false
        self.found_lt: list[int] = []
        self.found_lf: list[int] = []
        self.found_rt: list[int] = []
        self.found_rf: list[int] = []

    def right_at(self, j: int) -> int:
        value = self.right.vals[j - self.clock.base]
        return 2 - value if self.negate else value

    def decide(self, i: int, value: int) -> None:
        clock = self.clock
        k = i - clock.base
        self.vals[k] = 2 - value if self.negate else value
        self.event(clock.idx[k])

    def record_new(self, n: int) -> tuple[int, int]:
        """Record the operands' verdicts at the new state; returns (left, right)."""
        left = TRUE if self.left is None else self.left.cur
        right = self.right.cur
        if self.negate:
            right = 2 - right
        nb = self.clock.idx[-1]  # (n, boxed once)
        if left != TRUE:
            self.left_nt.append(nb)
            if left == FALSE:
                self.left_f.append(nb)
        if right == TRUE:
            self.right_t.append(nb)
        if right != FALSE:
            self.right_nf.append(nb)
        return left, right

    def operand_events(self) -> tuple[list[int], list[int], list[int], list[int]]:
        """The operands' verdicts decided this step at earlier states, recorded; returns the
        positions where left became true, left false, right true, right false."""
        base = self.clock.base
        newest = base + len(self.clock.times) - 1
        left_t = self.found_lt  # (kept from step to step: compiled, four new lists a step cost more)
        left_f = self.found_lf
        right_t = self.found_rt
        right_f = self.found_rf
        if left_t:
            left_t.clear()
        if left_f:
            left_f.clear()
        if right_t:
            right_t.clear()
        if right_f:
            right_f.clear()
        left = self.left
        if left is not None and not left.sync:
            events = left.events
            for e in range(left.nev):
                kb = events[e]  # (kept boxed: it goes into lists as it is)
                k: int = kb
                if k == newest:
                    continue  # recorded as the new state's
                if left.vals[k - base] == TRUE:
                    remove(self.left_nt, k)
                    left_t.append(kb)
                else:
                    insort(self.left_f, k, kb)
                    left_f.append(kb)
        right = self.right
        if not right.sync:
            events = right.events
            for e in range(right.nev):
                jb = events[e]
                j: int = jb
                if j == newest:
                    continue
                if self.right_at(j) == TRUE:
                    insort(self.right_t, j, jb)
                    right_t.append(jb)
                else:
                    remove(self.right_nf, j)
                    right_f.append(jb)
        return left_t, left_f, right_t, right_f

    def resolve(self, first: int, last: int, value: int) -> None:
        """Decide every pending state in [first, last] as ``value`` (false: those whose window
        no term below was stale in: the others stay unknown for good)."""
        base = self.clock.base
        pending = self.pending
        skip = pending.skip
        newest = base + len(skip) - 1
        if last > newest:
            last = newest
        i = pending.next_pending(first)
        while i <= last:
            skip[i - base] = 1  # (pending.done(i), inline)
            if value != FALSE or not self.stale_at(i):
                self.decide(i, value)
            i = pending.next_pending(i + 1)

    def resolve_one(self, i: int, value: int) -> None:
        self.pending.skip[i - self.clock.base] = 1  # (pending.done(i), inline)
        if value != FALSE or not self.stale_at(i):
            self.decide(i, value)

    def stale_at(self, i: int) -> bool:
        """Whether a term below was stale in the window of state ``i`` (a false verdict there is unknown)."""
        raise NotImplementedError

    def prune(self, base: int) -> None:
        for positions in (self.left_nt, self.left_f, self.right_t, self.right_nf):
            prune_keep_last(positions, base)
        self.pending.keep_newest(len(self.vals))  # (the monitor dropped as many states from vals)
