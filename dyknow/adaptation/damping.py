"""Flap damping: a penalty per relapse that decays with a half-life, as route-flap damping does
(RFC 2439), for the three kinds of relapse the loop meets: a suspect whose requirement is false
again after it was trusted, a transformation that fails again, and a manager lost again.

Each relapse adds :attr:`Damping.penalty` to the penalty of what relapsed, which halves every
:attr:`Damping.half_life_s`. A penalty above :attr:`Damping.suppress` *suppresses* it until the
penalty has decayed to :attr:`Damping.reuse`; the penalty never exceeds the figure from which that
takes :attr:`Damping.max_hold_s`, so whatever relapsed, once fixed for good, is trusted again at most
``max_hold_s`` after its last relapse. One relapse alone suppresses nothing: a provider that failed
once is tried again at its usual back-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Damping:
    """How one kind of relapse is damped (the figures of :class:`Penalty`)."""

    half_life_s: float
    suppress: float
    reuse: float
    max_hold_s: float
    penalty: float = 1000.0  # added at each relapse

    def __post_init__(self) -> None:
        if not (self.half_life_s > 0 and self.max_hold_s > 0 and self.penalty > 0):
            raise ValueError(f"flap damping needs half_life_s > 0, max_hold_s > 0 and penalty > 0: got {self}")
        if not 0 < self.reuse < self.suppress < self.ceiling:
            raise ValueError(
                f"flap damping needs 0 < reuse < suppress < the ceiling reuse * 2 ** (max_hold_s / half_life_s) "
                f"= {self.ceiling:g} (else nothing is ever suppressed): got {self}"
            )

    @property
    def ceiling(self) -> float:
        """The largest penalty: the one that decays to :attr:`reuse` in :attr:`max_hold_s`."""
        return self.reuse * 2.0 ** (self.max_hold_s / self.half_life_s)

    def decayed(self, value: float, elapsed_ns: int) -> float:
        """``value`` after ``elapsed_ns`` of decay."""
        return value * 2.0 ** (-max(0, elapsed_ns) / (self.half_life_s * 1e9))

    def hold_ns(self, value: float) -> int:
        """How long a penalty of ``value`` takes to decay to :attr:`reuse` (0 when it is there already)."""
        if value <= self.reuse:
            return 0
        return math.ceil(self.half_life_s * 1e9 * math.log2(value / self.reuse))


#: A suspect whose requirement is false again after it was trusted: a second relapse within about
#: ten minutes keeps it out of the stream for up to 15 minutes (a provider that fails 8 s after
#: every start: 3 switches, then none in the first 10 minutes; in the steady state one return
#: every 11.6 minutes at most).
TRIALS = Damping(half_life_s=300.0, suppress=1200.0, reuse=250.0, max_hold_s=900.0)
#: A transformation that fails (its unit raised, stalled, or failed at start) is not suppressed:
#: its back-off is 1 s doubled once per penalty beyond the first (:meth:`Penalty.doublings`, at
#: most 60 s), so it grows while failures come close together and is forgiven as they stop (its
#: suppress and reuse figures are not used; its ceiling, 8 relapses, is past the 60 s cap).
FAILURES = Damping(half_life_s=60.0, suppress=1500.0, reuse=500.0, max_hold_s=240.0)
#: A manager lost again (its link flaps): back from a first loss, it is trusted after the dwell
#: time; lost again within about ten seconds, not before its penalty decays (at most 30 s after
#: its last loss).
LINKS = Damping(half_life_s=10.0, suppress=1500.0, reuse=250.0, max_hold_s=30.0)


@dataclass(frozen=True, slots=True)
class Flaps:
    """The damping of each kind of relapse (a manager's ``damping=``)."""

    trials: Damping = TRIALS
    failures: Damping = FAILURES
    links: Damping = LINKS


class Penalty:
    """The penalty of one thing that relapses (a suspect of a request, a transformation, a manager)."""

    __slots__ = ("_damping", "_value", "last_ns", "relapses", "suppressed")

    def __init__(self, damping: Damping) -> None:
        self._damping = damping
        self._value = 0.0
        self.last_ns = 0  # the last relapse
        self.relapses = 0  # all of them, for the model
        self.suppressed = False  # at the last relapse (see :meth:`suppressed_until`)

    def value(self, now_ns: int) -> float:
        """The penalty now (decayed since the last relapse)."""
        return self._damping.decayed(self._value, now_ns - self.last_ns)

    def relapse(self, now_ns: int) -> float:
        """One more relapse at ``now_ns``: the penalty grows (up to the ceiling). It is suppressed
        when the penalty is above the suppress threshold, or it was suppressed and the penalty had
        not decayed to the reuse threshold yet. Returns the penalty."""
        damping = self._damping
        before = self.value(now_ns)
        self.suppressed = self.suppressed and now_ns < self.suppressed_until()
        self._value = min(damping.ceiling, before + damping.penalty)
        self.last_ns = now_ns
        self.relapses += 1
        self.suppressed = self.suppressed or self._value > damping.suppress
        return self._value

    def suppressed_until(self) -> int:
        """Until when (ns) it is suppressed: when its penalty decays to the reuse threshold; 0 when
        its last relapse did not suppress it."""
        return self.last_ns + self._damping.hold_ns(self._value) if self.suppressed else 0

    def doublings(self, now_ns: int) -> int:
        """How many times a back-off doubles for this penalty: once for each penalty beyond the
        first relapse's, rounded (0 after one relapse, or once the rest has decayed)."""
        return max(0, int(self.value(now_ns) / self._damping.penalty - 0.5))
