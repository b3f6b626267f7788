"""Overload: when a manager cannot keep up, it says so and sheds its least important work first.

The executor's watchdog measures the shared lane about every quarter of a second while it works,
at random moments (:class:`~dyknow.executor.Load`): how long a message waits before its unit runs
(the *lag*: in the lane's queue, and for the interpreter lock), how busy its thread was, how much CPU the process used. An
:class:`OverloadGuard` reads those readings and keeps the manager's state:

- **ok -> overloaded**: the lag was over the budget (``lag_budget_s``, default 50 ms) in
  :data:`ENTER_READINGS` readings in a row (about 0.75 s). Queues that grow, and a CPU taken away
  by other processes, both show as lag: it is what a message pays. The manager logs one warning,
  publishes an ``overload`` event (``dyknow/<manager>/events/overload``) and its model says
  ``overloaded``.
- **shedding, one step at a time**: at once, and again after every :data:`STEP_READINGS`
  readings (1 s) of which most were over the budget, or whose mean lag was, the least important
  work is shed one step further (see below). Most, not all: a probe that happens to land between
  two long callbacks reads a short lag, and readings in a row over the budget could then take
  many seconds to come on a busy machine (a step waited over 30 s so).
- **restoring**: after :data:`CLEAR_READINGS` readings (2 s) in a row with the lag under half the
  budget, the last step is undone, the most important shed work first; once nothing is shed and
  the lag is under the budget the state is ``ok`` again (one info line, an event).

**What is shed, in which order.** Every unit has a *priority*, the planner's: its
transformation's ``<priority>`` (lower is more important, default 100; see
:mod:`dyknow.planner`). A unit that serves a request, and the request's anchor, take the
priority of the request when it is more important: the priority of the most important
transformation of its configuration. So a source that feeds an important request is as important
as the request. Units with the same priority form a *tier*. Shedding takes the least important
tier first: its units run at a quarter of their rate (one message in four on each input, one
timer tick in four), then they pause (nothing delivered, no ticks); then the next tier. The most
important tier the manager runs is never shed: a requested stream of high priority keeps its
rate. Protected units are never shed either. A formula monitor (``monitor``) has the priority of
its spec, 100 unless the spec says otherwise, so by default monitors go before the streams of
requests whose transformations have a lower number. What a unit let go is counted on each
input port (``shed``), its rate is in its statistics (``rate``) and its description in the model
says so. A unit spawned while the manager sheds runs at full rate until the next step.

The guard is plain logic over readings: :meth:`OverloadGuard.reading` is called on the
watchdog's thread and acts through the callables it is given.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

from dyknow.executor import Load

__all__ = [
    "CLEAR_READINGS",
    "DEFAULT_LAG_BUDGET_S",
    "ENTER_READINGS",
    "PAUSED",
    "REDUCED",
    "STEP_READINGS",
    "OverloadGuard",
    "OverloadState",
    "describe",
]

log = logging.getLogger(__name__)

#: How long a message may wait on the shared lane before the manager counts as overloaded (s).
DEFAULT_LAG_BUDGET_S: Final = 0.05
#: Readings in a row over the budget before the manager is overloaded (with readings every
#: :data:`~dyknow.executor.LOAD_WINDOW_S`: 0.75 s).
ENTER_READINGS: Final = 3
#: Readings between two shedding steps (1 s), most of them (and the latest) over the budget.
STEP_READINGS: Final = 4
#: Readings in a row under half the budget before one step is undone (2 s).
CLEAR_READINGS: Final = 8
#: A shed tier's first step: one message (and timer tick) in this many.
REDUCED: Final = 4
#: A shed tier's second step: paused.
PAUSED: Final = -1


@dataclass(frozen=True, slots=True)
class OverloadState:
    """What the model says of a manager's load.

    ``state``: ``"ok"`` or ``"overloaded"`` (over the budget, or shedding); ``since_ns``: when
    it became so (wall clock); ``lag_ms``, ``busy``, ``cpu``: the last reading (see
    :class:`~dyknow.executor.Load`); ``lag_budget_ms``: the budget; ``shed``: each shed tier,
    least important first, as ``(priority, rate)`` (rate 0.25, or 0 when paused); ``units_shed``:
    how many units run below their rate.
    """

    state: str
    since_ns: int
    lag_ms: float
    busy: float
    cpu: float
    lag_budget_ms: float
    shed: tuple[tuple[int, float], ...] = ()
    units_shed: int = 0

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (the model's ``executor.overload``, the ``overload`` event)."""
        return {
            "state": self.state,
            "since_ns": self.since_ns,
            "lag_ms": round(self.lag_ms, 3),
            "busy": round(self.busy, 3),
            "cpu": round(self.cpu, 3),
            "lag_budget_ms": self.lag_budget_ms,
            "shed": [{"priority": priority, "rate": rate} for priority, rate in self.shed],
            "units_shed": self.units_shed,
        }


class OverloadGuard:
    """Keeps a manager's overload state from load readings, and sheds by priority.

    ``priorities()``: every unit that may be shed with its priority (see the module
    documentation); ``apply(shed)``: make every unit of each priority in ``shed`` run at that
    setting (:data:`REDUCED` or :data:`PAUSED`) and every other unit at full rate, returning how
    many units it slowed; ``on_change(state, entered)``: the state changed (``entered``: True as
    it becomes overloaded, False as it becomes ok again, None for a step in between);
    ``clock_ns``: the wall clock (for ``since_ns``).
    """

    def __init__(
        self,
        manager: str,
        *,
        lag_budget_s: float = DEFAULT_LAG_BUDGET_S,
        priorities: Callable[[], Sequence[tuple[str, int]]],
        apply: Callable[[Mapping[int, int]], int],
        on_change: Callable[[OverloadState, bool | None], None],
        clock_ns: Callable[[], int],
    ) -> None:
        if not lag_budget_s > 0:
            raise ValueError(f"lag_budget_s: got {lag_budget_s!r}; expected a positive number of seconds")
        self.manager = manager
        self.lag_budget_ns = int(lag_budget_s * 1e9)
        self._priorities = priorities
        self._apply = apply
        self._on_change = on_change
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._over = 0  # readings in a row over the budget
        self._window = 0  # readings since the last step (or since the window began again)
        self._window_over = 0  # of those, over the budget
        self._window_lag_ns = 0  # their lags, summed
        self._under = 0  # readings in a row under half the budget
        self._steps: list[tuple[int, int]] = []  # (priority, setting), in the order taken
        self._units_shed = 0
        self._nothing_left_said = False
        self._last: Load | None = None
        self.state = OverloadState("ok", clock_ns(), 0.0, 0.0, 0.0, lag_budget_s * 1000)

    @property
    def shedding(self) -> bool:
        """Whether any work is shed now (the executor keeps measuring while it is)."""
        return bool(self._steps)

    def reading(self, load: Load) -> None:
        """Take one reading (on the watchdog's thread)."""
        with self._lock:
            self._last = load
            over = load.lag_ns >= self.lag_budget_ns
            clear = load.lag_ns < self.lag_budget_ns // 2
            self._over = self._over + 1 if over else 0
            self._under = self._under + 1 if clear else 0
            overloaded = self.state.state == "overloaded"
            entered: bool | None = None
            changed = False
            if not overloaded:
                if self._over >= ENTER_READINGS:
                    entered, changed = True, True
                    self._step_up()
                    self._over = 0
                    self._window = self._window_over = self._window_lag_ns = 0
            elif self._step_due(over):
                self._over = 0
                changed = self._step_up()
            elif self._under >= CLEAR_READINGS:
                self._under = 0
                if self._steps:
                    self._step_down()
                    changed = True
                if not self._steps and not over:
                    entered, changed = False, True
            if changed:
                self.state = self._state("overloaded" if entered is not False else "ok", keep_since=entered is None)
                state = self.state
            else:
                self.state = self._refresh(self.state)
                return
        self._on_change(state, entered)

    def _step_due(self, over: bool) -> bool:
        """Count this reading in the window since the last step; whether the next step is due:
        :data:`STEP_READINGS` readings or more, most of them over the budget or their mean lag at
        least the budget. A window twice that long without a step begins again (old readings say
        little of now)."""
        self._window += 1
        self._window_over += over
        self._window_lag_ns += self._last.lag_ns if self._last is not None else 0
        if self._window >= STEP_READINGS and (2 * self._window_over > self._window or self._window_lag_ns >= self.lag_budget_ns * self._window):
            self._window = self._window_over = self._window_lag_ns = 0
            return True
        if self._window >= 2 * STEP_READINGS:
            self._window = self._window_over = self._window_lag_ns = 0
        return False

    def _state(self, name: str, *, keep_since: bool) -> OverloadState:
        load = self._last
        since = self.state.since_ns if keep_since else self._clock_ns()
        shed = tuple((priority, 0.0 if setting == PAUSED else 1 / setting) for priority, setting in self._tiers())
        return OverloadState(
            name,
            since,
            load.lag_ns / 1e6 if load is not None else 0.0,
            load.busy if load is not None else 0.0,
            load.cpu if load is not None else 0.0,
            self.lag_budget_ns / 1e6,
            shed,
            self._units_shed,
        )

    def _refresh(self, state: OverloadState) -> OverloadState:
        load = self._last
        if load is None:
            return state
        return OverloadState(
            state.state, state.since_ns, load.lag_ns / 1e6, load.busy, load.cpu, state.lag_budget_ms, state.shed, state.units_shed
        )

    def _tiers(self) -> list[tuple[int, int]]:
        """Each shed priority with its current setting, least important first."""
        settings: dict[int, int] = {}
        for priority, setting in self._steps:
            settings[priority] = setting
        return sorted(settings.items(), key=lambda item: -item[0])

    def _step_up(self) -> bool:
        """Shed one step more; False when nothing is left to shed."""
        present = sorted({priority for _, priority in self._priorities()}, reverse=True)  # least important first
        settings = dict(self._tiers())
        for priority in present[:-1]:  # the most important tier is never shed
            setting = settings.get(priority)
            if setting == PAUSED:
                continue
            self._steps.append((priority, REDUCED if setting is None else PAUSED))
            self._units_shed = self._apply(dict(self._tiers()))
            return True
        if not self._nothing_left_said:
            self._nothing_left_said = True
            log.warning(
                "manager %r is still overloaded with all but its most important work shed (priority %s): it runs what it can",
                self.manager,
                present[-1] if present else "none",
            )
        return False

    def _step_down(self) -> None:
        """Undo the last step (the most important shed work comes back first)."""
        self._steps.pop()
        self._nothing_left_said = False
        self._units_shed = self._apply(dict(self._tiers()))


def describe(state: OverloadState) -> str:
    """One line for a person: ``overloaded (lag 120 ms over 50 ms): priority 100 paused, ...``."""
    if state.state == "ok":
        return f"ok (lag {state.lag_ms:.1f} ms, budget {state.lag_budget_ms:g} ms)"
    tiers = ", ".join(f"priority {p} {'paused' if rate == 0 else f'at {rate:g} of its rate'}" for p, rate in state.shed)
    return f"overloaded (lag {state.lag_ms:.1f} ms, budget {state.lag_budget_ms:g} ms; busy {state.busy:.0%}): " + (
        f"shedding {tiers} ({state.units_shed} units)" if tiers else "nothing shed"
    )

