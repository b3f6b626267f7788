"""Robustness, incrementally: the space robustness of :mod:`dyknow.reasoning.semantics` for a
:class:`~dyknow.reasoning.Monitor` asked for it (``Monitor(..., robustness=True)``).

A tree of its own beside the monitor's verdict nodes, stepped after them at each state: each node
keeps its robustness at the states it still needs, and computes a state's as soon as what it reads
is known. An atom's is its margin at its state (read from the atom's operands); ``not``,
``and``, ``or``, ``implies``, ``rise`` and ``fall`` combine their operands' at the state (and the
previous one); a past window (``once``, ``historically``, ``since``) reads back over its window
at its state; a future window (``eventually``, ``always``, ``until``) at the first state its
window is complete. A window in which a term below was stale gives none (None), as the
semantics say.

Cost: O(1) per node and state for the connectives, ``once[a, inf]`` and ``historically[a,
inf]`` (running accumulators), and ``since[0, inf]`` (a recurrence); O(states in the window) per
state for a bounded window, and for ``since[a, inf]`` with ``a > 0``. It is the price of a number
per state instead of a verdict: the monitor's verdicts do not pay it unless asked.
"""

from __future__ import annotations

from typing import Any, Final

from dyknow.reasoning.values import UNKNOWN, margin

__all__ = ["RNode", "RobustnessTree"]

_PENDING: Final = object()  # a state whose robustness is not computed yet
_INF: Final = float("inf")


def _lo(x: float | None, y: float | None) -> float | None:
    return None if x is None or y is None else (x if x <= y else y)


def _hi(x: float | None, y: float | None) -> float | None:
    return None if x is None or y is None else (x if x >= y else y)


def _neg(x: float | None) -> float | None:
    return None if x is None else -x


class _Times:
    """The states the robustness tree still holds: their times, from index ``base``."""

    def __init__(self) -> None:
        self.times: list[int] = []
        self.base = 0

    def at(self, i: int) -> int:
        return self.times[i - self.base]

    @property
    def newest(self) -> int:
        return self.base + len(self.times) - 1


class RNode:
    """A node of the robustness tree: its values per state held (``_PENDING`` until known), and the
    states still pending (a future window completes in order, but its operands may not)."""

    def __init__(self, times: _Times, kids: list[RNode]) -> None:
        self.t = times
        self.kids = kids
        self.vals: list[Any] = []
        self.pending: list[int] = []

    def known(self, i: int) -> bool:
        base = self.t.base
        return i < base or self.vals[i - base] is not _PENDING

    def get(self, i: int) -> float | None:
        base = self.t.base
        if i < base:
            return None
        value = self.vals[i - base]
        return None if value is _PENDING else value  # type: ignore[no-any-return]

    def advance(self, n: int) -> None:
        """Compute what can be computed now that state ``n`` is in."""
        self.vals.append(_PENDING)
        self.pending.append(n)
        still = []
        base = self.t.base
        for i in self.pending:
            if i < base:
                continue  # dropped: no longer asked for
            if self.ready(i):
                self.vals[i - base] = self.compute(i)
            else:
                still.append(i)
        self.pending = still

    def ready(self, i: int) -> bool:
        return all(kid.known(i) for kid in self.kids)

    def compute(self, i: int) -> float | None:
        raise NotImplementedError


class _RAtom(RNode):
    """An atom's margin at its state, from the verdict node's operands as they are right now."""

    def __init__(self, times: _Times, atom: Any) -> None:
        super().__init__(times, [])
        self.atom = atom

    def compute(self, i: int) -> float | None:
        atom = self.atom
        verdict = atom.cur
        if verdict == UNKNOWN:
            return None
        if atom.right is None:
            return _INF if verdict == 2 else -_INF
        return margin(atom.op or "", atom.left.val, atom.right.val, verdict)


class _RConst(RNode):
    def __init__(self, times: _Times, value: bool) -> None:
        super().__init__(times, [])
        self.value = _INF if value else -_INF

    def compute(self, i: int) -> float | None:
        return self.value


class _RPrev(RNode):
    """``prev(F)``: F's at the previous state."""

    def compute(self, i: int) -> float | None:
        return self.kids[0].get(i - 1) if i > 0 and i - 1 >= self.t.base else None


class _RNot(RNode):
    def compute(self, i: int) -> float | None:
        return _neg(self.kids[0].get(i))


class _RBool(RNode):
    """``and`` (least), ``or`` (greatest), ``implies`` (greatest of the negated left and the right)."""

    def __init__(self, times: _Times, kids: list[RNode], kind: str) -> None:
        super().__init__(times, kids)
        self.kind = kind

    def compute(self, i: int) -> float | None:
        x, y = self.kids[0].get(i), self.kids[1].get(i)
        if self.kind == "and":
            return _lo(x, y)
        if self.kind == "implies":
            x = _neg(x)
        return _hi(x, y)


class _REdge(RNode):
    """``rise(F)``: min(r(F), -r(prev F)); ``fall(F)``: min(-r(F), r(prev F))."""

    def __init__(self, times: _Times, kids: list[RNode], rise: bool) -> None:
        super().__init__(times, kids)
        self.rise = rise

    def compute(self, i: int) -> float | None:
        if i == 0 or i - 1 < self.t.base:
            return None
        now, before = self.kids[0].get(i), self.kids[0].get(i - 1)
        return _lo(now, _neg(before)) if self.rise else _lo(_neg(now), before)


class _RWindow(RNode):
    """``left until[a,b] right`` (future) or ``left since[a,b] right`` (past); ``eventually`` and
    ``once`` without left, ``always`` and ``historically`` negated: the greatest over the window's
    states j of ``min(r(right at j), the least r(left) over the chain)``."""

    def __init__(
        self, times: _Times, left: RNode | None, right: RNode, lo: int, hi: int | None, *, future: bool, negate: bool, stale: Any
    ) -> None:
        super().__init__(times, [k for k in (left, right) if k is not None])
        self.left = left
        self.right = right
        self.lo = lo
        self.hi = hi
        self.future = future
        self.negate = negate
        self.stale = stale  # stale(lo, hi) -> bool: a term below was stale in the span
        # unbounded past windows: running accumulators over the states that entered (age >= lo)
        self.entered = -1
        self.acc: float | None = -_INF  # once: the greatest entered; since: A_e of the recurrence

    def rr(self, j: int) -> float | None:
        value = self.right.get(j)
        return _neg(value) if self.negate else value

    def rl(self, j: int) -> float | None:
        return self.left.get(j) if self.left is not None else _INF

    def ready(self, i: int) -> bool:
        times = self.t
        if not self.future:  # what the window reads: right up to its newest state, left up to i
            ti = times.at(i)
            last = i
            while last >= times.base and times.at(last) > ti - self.lo:
                last -= 1
            if self.hi is not None and (last < times.base or times.at(last) < ti - self.hi):
                return True  # an empty window reads nothing
            if last >= times.base and not self.right.known(last):
                return False
            # left along the chains: after the window's oldest state, up to i (none when that is i)
            if self.left is None or last < times.base:
                return True
            if self.hi is None:
                oldest = times.base
            else:
                oldest = last
                while oldest - 1 >= times.base and times.at(oldest - 1) >= ti - self.hi:
                    oldest -= 1
            return oldest >= i or self.left.known(i)
        assert self.hi is not None
        end = times.at(i) + self.hi
        if times.at(times.newest) < end:
            return False  # the window is not complete yet
        last = i
        while last + 1 <= times.newest and times.at(last + 1) <= end:
            last += 1
        if times.at(last) < times.at(i) + self.lo:
            return True  # a complete, empty window reads nothing
        # right up to the window's newest state; left along the chain before it
        return self.right.known(last) and (self.left is None or last == i or self.left.known(last - 1))

    def compute(self, i: int) -> float | None:
        times = self.t
        ti = times.at(i)
        if self.future:
            assert self.hi is not None
            if self.stale(ti + self.lo, ti + self.hi):
                return None
            best: float | None = -_INF
            chain: float | None = _INF
            j = i
            while j <= times.newest and times.at(j) <= ti + self.hi:
                if times.at(j) >= ti + self.lo:
                    best = _hi(best, _lo(self.rr(j), chain))
                chain = _lo(chain, self.rl(j))
                j += 1
            return _neg(best) if self.negate else best
        if self.hi is None:
            return self.unbounded(i, ti)
        if self.stale(ti - self.hi, ti - self.lo):
            return None
        if times.base > 0 and ti - self.hi < times.times[0]:
            return None  # the window reaches states no longer held
        best = -_INF
        chain = _INF
        j = i
        while j >= times.base and times.at(j) >= ti - self.hi:
            if times.at(j) <= ti - self.lo:
                best = _hi(best, _lo(self.rr(j), chain))
            chain = _lo(chain, self.rl(j))
            j -= 1
        return _neg(best) if self.negate else best

    def unbounded(self, i: int, ti: int) -> float | None:
        """``[a, inf]``: the states that entered (age >= a) folded in running order."""
        times = self.t
        while self.entered + 1 <= i and times.at(self.entered + 1) <= ti - self.lo:
            e = self.entered + 1
            if self.left is None:
                self.acc = _hi(self.acc, self.rr(e))
            elif self.entered < 0:  # the first: A_e = r(right at e)
                self.acc = self.rr(e)
            else:  # A_e = max(r(right at e), min(r(left at e), A_{e-1}))
                self.acc = _hi(self.rr(e), _lo(self.rl(e), self.acc))
            self.entered = e
        if self.stale(None, ti - self.lo):
            return None
        result = self.acc
        if self.left is not None and self.entered >= 0:
            for k in range(self.entered + 1, i + 1):  # the chain from the last entered state to now
                result = _lo(result, self.rl(k))
        elif self.left is not None:
            result = -_INF  # nothing entered: an empty window
        return _neg(result) if self.negate else result


class RobustnessTree:
    """The robustness nodes of one monitor, in post-order, and the states they hold (see the
    module documentation). :meth:`step` after the monitor's nodes stepped a state;
    :meth:`trim` drops states older than ``keep_ns`` before the newest."""

    def __init__(self, keep_ns: int) -> None:
        self.times = _Times()
        self.nodes: list[RNode] = []
        self.keep_ns = keep_ns
        self.root: RNode | None = None

    def add(self, node: RNode) -> RNode:
        self.nodes.append(node)
        self.root = node
        return node

    def atom(self, atom: Any) -> RNode:
        return self.add(_RAtom(self.times, atom))

    def const(self, value: bool) -> RNode:
        return self.add(_RConst(self.times, value))

    def prev(self, kid: RNode) -> RNode:
        return self.add(_RPrev(self.times, [kid]))

    def negation(self, kid: RNode) -> RNode:
        return self.add(_RNot(self.times, [kid]))

    def boolean(self, kind: str, left: RNode, right: RNode) -> RNode:
        return self.add(_RBool(self.times, [left, right], kind))

    def edge(self, rise: bool, kid: RNode) -> RNode:
        return self.add(_REdge(self.times, [kid], rise))

    def window(self, left: RNode | None, right: RNode, lo: int, hi: int | None, *, future: bool, negate: bool, stale: Any) -> RNode:
        return self.add(_RWindow(self.times, left, right, lo, hi, future=future, negate=negate, stale=stale))

    def step(self, n: int, t: int) -> None:
        """State ``n`` at ``t`` is in: every node computes what it now can."""
        self.times.times.append(t)
        for node in self.nodes:
            node.advance(n)

    def get(self, i: int) -> tuple[bool, float | None]:
        """``(known, robustness)`` of the root at state ``i`` (a state dropped: known, None)."""
        root = self.root
        if root is None or i < self.times.base:
            return True, None
        return (root.known(i), root.get(i) if root.known(i) else None)

    def trim(self, t: int) -> None:
        """Drop the states older than ``keep_ns`` that every node has computed (in batches)."""
        times = self.times
        edge = t - self.keep_ns
        k = 0
        while k < len(times.times) - 1 and times.times[k] < edge:
            k += 1
        if k >= 64 and k * 2 >= len(times.times):
            del times.times[:k]
            for node in self.nodes:
                del node.vals[:k]
            times.base += k
