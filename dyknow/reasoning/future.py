"""The monitor's future temporal nodes: ``until``, ``eventually`` and ``always``.

A node kind of :mod:`dyknow.reasoning.progression`'s monitor: a state waits, pending, until an
operand decides it or its window completes. Over operands decided at their state that costs
O(1) amortized per state (:class:`UntilSync`), else the window machinery does it
(:class:`UntilNode`, on :class:`~dyknow.reasoning.windows.Temporal`).
"""

from __future__ import annotations

from typing import Any

from dyknow.reasoning.nodes import Condition
from dyknow.reasoning.timeline import Clock, bisect_left, bisect_right
from dyknow.reasoning.values import FALSE, TRUE, UNKNOWN
from dyknow.reasoning.windows import NONE, Temporal, drop_before, pred, succ

__all__ = ["UntilNode", "UntilSync"]


def _only_new(node: Condition, n: int) -> bool:
    """Whether an operand decided nothing this step but (maybe) the new state ``n`` itself."""
    size = node.nev
    if size == 0:
        return True
    if size > 1:
        return False
    first: int = node.events[0]
    return first == n


class UntilNode(Temporal):
    """``left until[a,b] right``, ``eventually`` (no left) and ``always`` (negated): states wait,
    pending (in ``pending``), until a true right with an unbroken left chain decides them true, or
    their window is complete and every term is false."""

    def __init__(
        self, clock: Clock, left: Condition | None, right: Condition, lo_ns: int, hi_ns: int, negate: bool, need_ns: int, retire_ns: int
    ) -> None:
        super().__init__(clock, left, right, lo_ns, hi_ns, negate, need_ns, retire_ns)
        self.end_at = 0  # the last state of the window completing last (complete's cursor)

    def stale_at(self, i: int) -> bool:
        held = self.held
        if held is None or not held.aged:
            return False
        ti = self.clock.at(i)
        return held.stale(self.below, ti + self.lo_ns, ti + self.hi_ns)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.nev = 0  # (a parent reads the events during this state only)
        self.vals.append(UNKNOWN)
        self.pending.skip.append(0)
        _left, right = self.record_new(n)
        left = self.left
        if (left is None or _only_new(left, n)) and _only_new(self.right, n):  # nothing decided below but the new state
            if right == TRUE:
                self.found_true(n)
        else:
            left_t, left_f, right_t, right_f = self.operand_events()
            if right == TRUE:
                self.found_true(n)
            for j in right_t:
                self.found_true(j)
            for k in left_t:
                self.chain_mended(k)
            if right_f or left_f:
                complete_last = self.clock.last_at_or_before(t - self.hi_ns)  # the newest state whose window is complete
                for j in right_f:
                    self.right_false(j, complete_last)
                for k in left_f:
                    self.left_false(k, complete_last)
        self.complete(t)
        self.pending.retire(t - self.retire_ns)
        self.cur = self.vals[-1]

    def found_true(self, j: int) -> None:
        """Right is true at j: pending states whose window holds j and whose left chain up to j is
        unbroken are true."""
        clock = self.clock
        tj = clock.at(j)
        last = min(j, clock.last_at_or_before(tj - self.lo_ns)) if self.lo_ns else j  # (times are distinct)
        first = self.first_pending(tj - self.hi_ns, last)
        if first > last:
            return
        if self.left is not None:
            first = max(first, pred(self.left_nt, j) + 1)
        self.resolve(first, last, TRUE)

    def chain_mended(self, k: int) -> None:
        """Left became true at k: states whose chain broke at k may now reach a true right."""
        clock = self.clock
        reach = clock.at(k) + self.hi_ns
        after = succ(self.left_nt, k)
        lo = bisect_right(self.right_t, k)
        while lo < len(self.right_t):
            j = self.right_t[lo]
            if (after != -1 and j > after) or clock.at(j) > reach:
                break
            self.found_true(j)
            lo = bisect_right(self.right_t, j)

    def first_pending(self, reach: int, last: int) -> int:
        """The first pending state at ``reach`` or after, if it is at or before ``last`` (else
        one past ``last`` or more): walked to from the oldest pending one (few states are
        pending in the common case), else found by bisection."""
        clock = self.clock
        times = clock.times
        base = clock.base
        pending = self.pending
        i = pending.next_pending(pending.head)
        walked = 0
        while i <= last and times[i - base] < reach:
            walked += 1
            if walked == 8:
                return pending.next_pending(clock.first_at_or_after(reach))
            i = pending.next_pending(i + 1)
        return i

    def false_if_all_false(self, i: int) -> None:
        """Decide a complete pending state false if every term of its window is false."""
        clock = self.clock
        ti = clock.at(i)
        self.all_false(i, ti, clock.last_at_or_before(ti + self.hi_ns))

    def all_false(self, i: int, ti: int, end: int) -> None:
        """:meth:`false_if_all_false` of state ``i`` at ``ti``, its window's last state ``end``."""
        lo = self.clock.first_at_or_after(ti + self.lo_ns) if self.lo_ns else i  # (times are distinct)
        if self.left is not None:
            k = bisect_left(self.left_f, i)
            if k < len(self.left_f) and self.left_f[k] < end:
                end = self.left_f[k]  # terms after the first false left are false
        k = bisect_left(self.right_nf, lo)
        if k == len(self.right_nf) or self.right_nf[k] > end:
            self.resolve_one(i, FALSE)

    def complete(self, t: int) -> None:
        """Pending states whose window became complete with this state: false if all terms are."""
        clock = self.clock
        times = clock.times
        base = clock.base
        edge = t - self.hi_ns
        first = max(self.completed + 1, base)
        last = first - 1  # the newest state whose window is complete: a cursor, O(1) amortized
        while last + 1 - base < len(times) and times[last + 1 - base] <= edge:
            last += 1
        if last < first:
            return
        self.completed = last
        hi_ns = self.hi_ns
        e = self.end_at  # each window's last state: a cursor too (windows complete in order)
        pending = self.pending
        i = pending.next_pending(first)
        while i <= last:
            ti = times[i - base]
            reach = ti + hi_ns
            if e < i:
                e = i
            while e + 1 - base < len(times) and times[e + 1 - base] <= reach:
                e += 1
            self.all_false(i, ti, e)
            i = pending.next_pending(i + 1)
        self.end_at = e

    def right_false(self, j: int, complete_last: int) -> None:
        """Right became false at j: complete pending states whose window has no other not-false
        term (up to the first false left) are false. With p and s the not-false terms around j,
        they are the states whose first term lies in (p, j] and last in [j, s): one range."""
        clock = self.clock
        tj = clock.at(j)
        lo_ns = self.lo_ns
        last = min(clock.last_at_or_before(tj - lo_ns) if lo_ns else j, complete_last)  # starts by j; complete
        # the first pending state whose window reaches j: walked to from the oldest pending one
        # (few complete states are pending: those waiting for an operand), else found by bisection
        first = self.first_pending(tj - self.hi_ns, last)  # whose window reaches j
        if first > last:
            return  # (the common case: no complete state pending there)
        p = pred(self.right_nf, j)
        if p >= clock.base:
            first = max(first, clock.first_at_or_after(clock.at(p) - lo_ns + 1) if lo_ns else p + 1)  # starts after p
        if self.left is not None:
            first = max(first, pred(self.left_f, j) + 1)  # no false left before j cuts the window short of it
        s = succ(self.right_nf, j)
        if s != -1:
            bound = clock.last_at_or_before(clock.at(s) - self.hi_ns - 1)  # the window ends before s ...
            if self.left is not None:
                bound = max(bound, pred(self.left_f, s))  # ... or a false left before s ends its terms
            last = min(last, bound)
        self.resolve(first, last, FALSE)

    def left_false(self, k: int, complete_last: int) -> None:
        """Left became false at k: complete pending states before it may now be all false."""
        clock = self.clock
        first = pred(self.left_f, k) + 1 if pred(self.left_f, k) != NONE else clock.base
        last = min(k, complete_last)
        pending = self.pending
        i = pending.next_pending(first)
        while i <= last:
            self.false_if_all_false(i)
            i = pending.next_pending(i + 1)


class UntilSync(Condition):
    """``left until[a,b] right`` (``eventually`` without left, ``always`` negated) over synchronous
    operands, in O(1) amortized per state whatever the window's length: the same verdicts as
    :class:`UntilNode`, at the same states, without its sorted lists and bisections.

    Both operands are decided at their state, so a pending state is decided true only by a true
    right at a state whose left chain from it is unbroken, and false only when its window
    completes. A pending state is *live* while no left from it up to the newest state is
    not true: the live states are one run, from ``live`` to the newest, and a true right at
    the newest state decides them true from the oldest on (as far as it lies in their windows).
    A left not true ends the chains of all of them: they join ``dead``, runs of states only their
    window's completion decides. Windows complete oldest first, so completing one is O(1)
    amortized: cursors move forward through where left is false (which cuts the terms short)
    and where right is not false (one term that is, and the state is not false).
    """

    def __init__(self, clock: Clock, left: Condition | None, right: Condition, lo_ns: int, hi_ns: int, negate: bool, need_ns: int) -> None:
        super().__init__(clock, False, need_ns)
        self.left = left
        self.right = right
        self.lo_ns = lo_ns
        self.hi_ns = hi_ns
        self.negate = negate
        self.live = 0  # the live states run from it to the newest
        self.dead: list[int] = []  # runs of pending states that are not live: first, last, first, last, ...
        self.dhead = 0
        self.left_f: list[int] = []  # where left is false, from lf_head on
        self.lf_head = 0
        self.right_nf: list[int] = []  # where right (negated for always) is not false, from rnf_head on
        self.rnf_head = 0
        self.lo_at = 0  # the first state of the window completing last (its start: t + a)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.nev = 0  # (a parent reads the events during this state only)
        self.vals.append(UNKNOWN)
        left = self.left
        phi = TRUE if left is None else left.cur
        psi = self.right.cur
        if self.negate:
            psi = 2 - psi
        if phi == FALSE:
            self.left_f.append(self.clock.idx[-1])  # (n, boxed once)
        if psi != FALSE:
            self.right_nf.append(self.clock.idx[-1])
        edge = t - self.hi_ns
        if psi == TRUE:  # a true right decides the live states whose window holds it
            self.complete(n, t, edge - 1)  # (first the windows that ended before this state)
            times = self.clock.times
            base = self.clock.base
            top = t - self.lo_ns
            i = self.live
            while i <= n and times[i - base] <= top:
                self.decide(i, TRUE)
                i += 1
            self.live = i
        self.complete(n, t, edge)  # windows that end by this state
        if phi != TRUE and self.live <= n:  # a left not true ends every live chain
            self.dead.append(self.live)
            self.dead.append(n)
            self.live = n + 1
        self.forget(self.dead[self.dhead] if self.dhead < len(self.dead) else self.live)
        self.cur = self.vals[-1]

    def forget(self, oldest: int) -> None:
        """Drop the positions before ``oldest``, the oldest pending state: no window reads them."""
        if self.left is not None:  # (eventually and always have none)
            self.lf_head = drop_before(self.left_f, self.lf_head, oldest)
        self.rnf_head = drop_before(self.right_nf, self.rnf_head, oldest)

    def decide(self, i: int, value: int) -> None:
        clock = self.clock
        k = i - clock.base
        self.vals[k] = 2 - value if self.negate else value
        self.event(clock.idx[k])

    def complete(self, n: int, t: int, upto: int) -> None:
        """Decide the pending states whose window is complete, those at or before ``upto``: false
        if every term is (and no term below was stale in the window), else unknown for good."""
        times = self.clock.times
        base = self.clock.base
        dead = self.dead
        while self.dhead < len(dead):
            i = dead[self.dhead]
            last = dead[self.dhead + 1]
            while i <= last:
                ti = times[i - base]
                if ti > upto:
                    dead[self.dhead] = i
                    if self.dhead > 64 and self.dhead * 2 > len(dead):
                        del dead[: self.dhead]
                        self.dhead = 0
                    return
                self.finish(i, ti, n, t)
                i += 1
            self.dhead += 2
        if dead:
            dead.clear()
        self.dhead = 0
        i = self.live
        while i <= n:
            ti = times[i - base]
            if ti > upto:
                break
            self.finish(i, ti, n, t)
            i += 1
        self.live = i

    def finish(self, i: int, ti: int, n: int, t: int) -> None:
        """State ``i``'s window is complete: false if all its terms are."""
        times = self.clock.times
        base = self.clock.base
        end = n if t <= ti + self.hi_ns else n - 1  # the window's last state
        if self.lo_ns:
            start = ti + self.lo_ns
            k = self.lo_at if self.lo_at > i else i
            while k <= n and times[k - base] < start:
                k += 1
            self.lo_at = k  # the window's first state (past ``end`` when it has none)
        else:
            k = i  # the window starts at the state itself (times are distinct): no time to read
        left_f = self.left_f
        h = self.lf_head
        while h < len(left_f) and left_f[h] < i:
            h += 1
        self.lf_head = h
        if h < len(left_f) and left_f[h] < end:
            end = left_f[h]  # the terms after the first false left are false
        right_nf = self.right_nf
        r = self.rnf_head
        while r < len(right_nf) and right_nf[r] < k:
            r += 1
        self.rnf_head = r
        if r == len(right_nf) or right_nf[r] > end:
            held = self.held
            if held is None or not held.aged or not held.stale(self.below, ti + self.lo_ns, ti + self.hi_ns):
                self.decide(i, FALSE)

    def prune(self, base: int) -> None:
        # pending states before base were given up before their time: unknown for good
        if self.live < base:
            self.live = base
        dead = self.dead
        h = self.dhead
        while h < len(dead) and dead[h + 1] < base:
            h += 2
        if h < len(dead) and dead[h] < base:
            dead[h] = base
        self.dhead = h
        if self.lo_at < base:
            self.lo_at = base
