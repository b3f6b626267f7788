"""What the monitor units of one manager share: :class:`MonitorBudget` (its bounds, cells and formula nodes)."""

from __future__ import annotations

import threading
from typing import Protocol

from dyknow.errors import AccessError, FormulaError
from dyknow.reasoning.syntax import Formula
from dyknow.security import Limits

__all__ = ["MonitorBudget"]


class _Shared(Protocol):
    """What a budget shares cells with: a monitor, or an object monitor."""

    formula: Formula

    def set_max_cells(self, max_cells: int) -> None: ...


class MonitorBudget:
    """What the monitor units of one manager share: its :class:`~dyknow.security.Limits`; the
    cells ``limits.max_monitor_cells``, divided evenly among the monitors running; and at most
    ``limits.max_monitor_nodes`` formula nodes in all, which bounds what every sample costs the
    manager. Thread-safe. The manager hands its budget to each :class:`FormulaMonitor` before
    ``setup()``.

    **Per caller.** A monitor joins for an *account*: None for the manager's own (its Python API,
    the requirements of its specs, the trials of its adaptations), else the caller's
    (:meth:`dyknow.model.Owner.account`: its certificate's name when its calls are signed, else
    its client). One caller's monitors and requirements hold at most
    ``limits.monitor_nodes_caller_share`` of the nodes, and the callers together at most what
    ``limits.monitor_nodes_reserved_share`` leaves: that reserve stays for the manager's own
    watches, so no caller, nor all of them, can leave a spec's requirement unwatched. Past a
    caller's bound, :class:`~dyknow.errors.AccessError` names the account, what it holds and
    the bound; past the manager's, :class:`~dyknow.errors.FormulaError` as before.

    A monitor takes its share of cells itself (:meth:`take_share`) before each sample and each
    flush: a share only bounds the states a monitor stores next, and it stores states only then.
    Joining and leaving touch no other monitor, so they cost the same beside 10 monitors or 10,000
    (telling every monitor its new share on each join made spawning N monitors cost N²/2 calls:
    7.5 s of the 17 s that 1,000 spawns took beside 2,300 monitors, ``benchmarks/overload.py``)."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self._lock = threading.Lock()
        self._monitors: dict[_Shared, tuple[int, str | None]] = {}  # -> its formula's nodes, its account
        self._accounts: dict[str, int] = {}  # a caller's account -> the nodes of its monitors
        #: the formula nodes of the monitors running
        self.nodes = 0
        #: of those, the nodes that callers' monitors hold (the manager's own hold the rest)
        self.caller_nodes = 0
        #: counts the joins and leaves: a monitor whose last look saw another takes its share again
        self.generation = 0

    def check(self, *formulas: Formula, account: str | None = None) -> None:
        """Raise when monitors of ``formulas`` for ``account`` would take the manager's monitors
        past ``limits.max_monitor_nodes`` (:class:`~dyknow.errors.FormulaError`), or the
        caller's past its share (:class:`~dyknow.errors.AccessError`): what :meth:`join` checks."""
        with self._lock:
            self._check(sum(f.nodes for f in formulas), account, len(formulas))

    def join(self, monitor: _Shared, account: str | None = None) -> None:
        """Count ``monitor`` in for ``account`` (None: the manager's own), or raise as
        :meth:`check` does; every monitor's share of cells shrinks to fit it, from its next
        sample on. Costs the same however many monitors run."""
        nodes = monitor.formula.nodes
        with self._lock:
            self._check(nodes, account)
            self._monitors[monitor] = (nodes, account)
            self.nodes += nodes
            if account is not None:
                self._accounts[account] = self._accounts.get(account, 0) + nodes
                self.caller_nodes += nodes
            self.generation += 1

    def leave(self, monitor: _Shared) -> None:
        """Count ``monitor`` out (safe twice); the others' shares grow, from their next sample on."""
        with self._lock:
            entry = self._monitors.pop(monitor, None)
            if entry is None:
                return
            nodes, account = entry
            self.nodes -= nodes
            if account is not None:
                left = self._accounts.get(account, 0) - nodes
                if left > 0:
                    self._accounts[account] = left
                else:
                    self._accounts.pop(account, None)  # (an account without monitors costs nothing)
                self.caller_nodes -= nodes
            self.generation += 1

    def held(self, account: str) -> int:
        """The formula nodes the monitors of ``account`` hold now."""
        with self._lock:
            return self._accounts.get(account, 0)

    @property
    def caller_bounds(self) -> tuple[int, int]:
        """``(per caller, all callers)``: the nodes one caller's monitors may hold, and those
        all callers' may hold together (the rest of ``limits.max_monitor_nodes`` is reserved)."""
        limits = self.limits
        bound = limits.max_monitor_nodes
        callers = bound - min(bound, max(0, int(bound * limits.monitor_nodes_reserved_share)))
        return min(callers, max(0, int(bound * limits.monitor_nodes_caller_share))), callers

    def take_share(self, monitor: _Shared, seen: int) -> int:
        """Give ``monitor`` its share of cells now when monitors joined or left since it last
        looked (``seen``: the :attr:`generation` it saw then, -1 at first); returns the generation
        to pass next time. One comparison when nothing changed: monitors call it per sample."""
        generation = self.generation
        if generation != seen:
            # read after the generation: a join in between makes the next call look again
            monitor.set_max_cells(self.share)
        return generation

    def _check(self, nodes: int, account: str | None, count: int = 1) -> None:
        """(under the lock) A caller's own bound first, then all callers', then the manager's."""
        bound = self.limits.max_monitor_nodes
        these = "this formula has" if count == 1 else "these formulas have"
        if account is not None:
            per_caller, callers = self.caller_bounds
            own = self._accounts.get(account, 0)
            if own + nodes > per_caller:
                raise AccessError(
                    f"the monitors and requirements of {account} hold {own:,} formula nodes, and {these} {nodes:,}",
                    where="monitor",
                    expected=f"at most {per_caller:,} nodes a caller (Limits.monitor_nodes_caller_share of the manager's "
                    f"{bound:,}): release some of the caller's monitors or requirements first",
                )
            if self.caller_nodes + nodes > callers:
                raise AccessError(
                    f"the callers' monitors and requirements hold {self.caller_nodes:,} formula nodes, and {these} {nodes:,}",
                    where="monitor",
                    expected=f"at most {callers:,} nodes for all callers together: the other {bound - callers:,} of the "
                    f"manager's {bound:,} are kept for its own requirements (Limits.monitor_nodes_reserved_share); "
                    "try again once monitors are released",
                )
        if self.nodes + nodes > bound:
            raise FormulaError(
                f"the manager's monitors hold {self.nodes:,} formula nodes, and {these} {nodes:,}",
                where="monitor",
                expected=f"at most {bound:,} nodes in all (Limits.max_monitor_nodes): release monitors or requirements first",
            )

    @property
    def share(self) -> int:
        """The cells each monitor running may keep now (all of them, when none runs)."""
        return self.limits.max_monitor_cells // max(1, len(self._monitors))

    @property
    def running(self) -> int:
        """How many monitors share the cells."""
        return len(self._monitors)
