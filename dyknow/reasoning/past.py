"""The monitor's past temporal nodes: ``since``, ``once`` and ``historically``.

A node kind of :mod:`dyknow.reasoning.progression`'s monitor. A past window is complete at its
state, so its verdict waits only for operands decided later: over operands decided at their
state it keeps O(1) summaries (:class:`SinceSync`), else sorted positions
(:class:`SinceNode`, on :class:`~dyknow.reasoning.windows.Temporal`).
"""

from __future__ import annotations

from typing import Any

from dyknow.reasoning.nodes import Condition
from dyknow.reasoning.timeline import NEVER, Clock, bisect_right
from dyknow.reasoning.values import FALSE, TRUE, UNKNOWN
from dyknow.reasoning.windows import NONE, Temporal, pred

__all__ = ["SinceNode", "SinceSync"]


class SinceSync(Condition):
    """``left since[a,b] right`` (``once`` without left; ``historically`` with both negations) over
    synchronous operands, in O(1) per state: the last entered state where right is true and where
    it is not false, the last state where left is not true and where it is false, and the states
    younger than ``a`` waiting to enter the window."""

    def __init__(self, clock: Clock, left: Condition | None, right: Condition, lo_ns: int, hi_ns: int | None, negate: bool) -> None:
        super().__init__(clock, True, 0)
        self.left = left
        self.right = right
        self.lo_ns = lo_ns
        self.bounded = hi_ns is not None
        self.hi_ns = hi_ns if hi_ns is not None else 0
        self.negate = negate  # historically: not once not
        self.last_true = NONE  # index and time of the last entered state where right is true
        self.last_true_t = NEVER
        self.last_nf = NONE  # ... where right is not false
        self.last_nf_t = NEVER
        self.break_nt = NONE  # the last state where left is not true / is false
        self.break_f = NONE
        self.waiting: list[tuple[int, int, int]] = []  # (index, time, right) younger than lo_ns
        self.head = 0
        self.lost = NONE  # the newest waiting state given up (over max_states) and its time
        self.lost_t = NEVER
        self.given_up = 0

    def stale_window(self, n: int, t: int) -> bool:
        return _past_stale(self, t, self.lo_ns, self.hi_ns if self.bounded else None)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        if self.first_t == NEVER:
            self.first_t = t
        psi = self.right.cur
        if self.negate:
            psi = 2 - psi
        left = self.left
        if left is not None:
            phi = left.cur
            if phi != TRUE:
                self.break_nt = n
                if phi == FALSE:
                    self.break_f = n
        if self.lo_ns == 0:
            if psi == TRUE:
                self.last_true = n
                self.last_true_t = t
            if psi != FALSE:
                self.last_nf = n
                self.last_nf_t = t
        else:
            waiting = self.waiting
            waiting.append((n, t, psi))
            edge = t - self.lo_ns
            head = self.head
            while head < len(waiting) and waiting[head][1] <= edge:
                j, tj, value = waiting[head]
                head += 1
                if value == TRUE:
                    self.last_true = j
                    self.last_true_t = tj
                if value != FALSE:
                    self.last_nf = j
                    self.last_nf_t = tj
            if head > 64 and head * 2 > len(waiting):
                del waiting[:head]
                head = 0
            if len(waiting) - head > self.max_states:  # give up the oldest: they may hide a term
                cut = len(waiting) - self.max_states + self.max_states // 4
                self.lost, self.lost_t = waiting[cut - 1][0], waiting[cut - 1][1]
                self.given_up += cut - head
                del waiting[:cut]
                head = 0
            self.head = head
        oldest = t - self.hi_ns if self.bounded else NEVER
        if self.last_true >= self.break_nt and self.last_true != NONE and self.last_true_t >= oldest:
            value = TRUE
        elif self.last_nf >= self.break_f and self.last_nf != NONE and self.last_nf_t >= oldest:
            value = UNKNOWN
        elif self.lost != NONE and self.lost_t >= oldest and self.lost >= self.break_f:
            value = UNKNOWN  # all known terms are false, but one given up may be in the window
        elif self.held is not None and self.stale_window(n, t):
            value = UNKNOWN  # a term below was stale in the window: an outage is no violation
        else:
            value = FALSE
        if self.negate:
            value = 2 - value
        self.cur = value
        if self.history:
            self.vals.append(value)


def _past_stale(node: Condition, t: int, lo_ns: int, hi_ns: int | None) -> bool:
    """Whether a term below ``node`` was stale in the past window ``[t - hi, t - lo]`` of the state at ``t``."""
    held = node.held
    if held is None or not held.aged:
        return False
    if node.first_t == NEVER:
        node.first_t = t
    # (an unbounded window reads from the first state: lo None, which also finds spans pruned)
    return held.stale(node.below, t - hi_ns if hi_ns is not None else None, t - lo_ns)


class SinceNode(Temporal):
    """``left since[a,b] right`` (``once``, ``historically``) over asynchronous operands: a state's
    window is in the past, so it is complete at once, but operands there may still be pending."""

    def __init__(
        self, clock: Clock, left: Condition | None, right: Condition, lo_ns: int, hi_ns: int | None, negate: bool, need_ns: int, retire_ns: int
    ) -> None:
        super().__init__(clock, left, right, lo_ns, hi_ns if hi_ns is not None else 0, negate, need_ns, retire_ns)
        self.bounded = hi_ns is not None

    def stale_at(self, i: int) -> bool:
        return _past_stale(self, self.clock.at(i), self.lo_ns, self.hi_ns if self.bounded else None)

    def window(self, i: int) -> tuple[int, int]:
        clock = self.clock
        ti = clock.at(i)
        first = clock.first_at_or_after(ti - self.hi_ns) if self.bounded else NONE
        return first, clock.last_at_or_before(ti - self.lo_ns)

    def check(self, i: int) -> int:
        """The verdict at i from what is known now (UNKNOWN: not decided)."""
        clock = self.clock
        if clock.given_up_t != NEVER and clock.at(i) - self.lo_ns < clock.times[0]:
            return UNKNOWN  # the window ends among states given up: where exactly is lost with them
        first, last = self.window(i)
        k = bisect_right(self.right_t, last)
        if k:
            j = self.right_t[k - 1]
            chain = pred(self.left_nt, i + 1) if self.left is not None else NONE
            if j >= first and j >= chain:
                return TRUE
        k = bisect_right(self.right_nf, last)
        cut = pred(self.left_f, i + 1) if self.left is not None else NONE
        if k == 0 or self.right_nf[k - 1] < max(first, cut):
            given_up = clock.given_up_t
            if given_up != NEVER and cut < clock.base and (not self.bounded or given_up >= clock.at(i) - self.hi_ns):
                return UNKNOWN  # a state given up may be a term of the window, and not false
            return FALSE
        return UNKNOWN

    def step(self, n: int, t: int, held: list[Any]) -> None:
        if self.first_t == NEVER:
            self.first_t = t
        self.nev = 0  # (a parent reads the events during this state only)
        self.vals.append(UNKNOWN)
        self.record_new(n)
        value = self.check(n)
        pending = self.pending
        if value == FALSE and self.stale_at(n):
            pending.skip.append(1)  # unknown for good: a term below was stale in the window
        elif value != UNKNOWN:
            pending.skip.append(1)
            self.decide(n, value)
        else:
            pending.skip.append(0)
        left_t, left_f, right_t, right_f = self.operand_events()
        if left_t or left_f or right_t or right_f:
            # an operand decided at k can only change verdicts at k and after (windows and
            # chains end at their state): check those still pending
            first = min(left_t + left_f + right_t + right_f)
            i = pending.next_pending(first)
            while i <= n:
                value = self.check(i)
                if value != UNKNOWN:
                    self.resolve_one(i, value)
                i = pending.next_pending(i + 1)
        pending.retire(t - self.retire_ns)
        self.cur = self.vals[-1]
