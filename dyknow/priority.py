"""A process's scheduling priority (its *niceness*): how a manager keeps its turn on a busy CPU.

On a CPU shared with other heavy work, a manager's threads wait for their turn like any other
process: with two busy processes per core beside it, the hop of its most important stream went
from under half a millisecond to 4 to 7 at the 99th percentile (``python benchmarks/overload.py``),
although the manager itself had CPU to spare. Load shedding cannot help there (the manager is not
overloaded: the machine is); the operating system's scheduler can. A manager given precedence
over the other work (``dyknow manager --nice -20``, or -10 for less) wakes as soon as a message
is due, and the other processes run in what it leaves, which on a robot computer is most of the
time.

Linux's niceness belongs to each thread, and a thread inherits its creator's: :func:`set_nice`
sets it on every thread the process has and those it starts later (Zenoh's included) inherit
it. Raising a priority (a niceness under 0) needs ``CAP_SYS_NICE`` or a ``nice`` resource limit
(``RLIMIT_NICE``) that allows it; a refusal is a :class:`PriorityError` that says which.
"""

from __future__ import annotations

import errno
import os
from typing import Final

__all__ = ["MAX_NICE", "MIN_NICE", "PriorityError", "current_nice", "set_nice"]

#: The most precedence a niceness gives (Linux: -20) and the least (19).
MIN_NICE: Final = -20
MAX_NICE: Final = 19


class PriorityError(RuntimeError):
    """The operating system refused the niceness asked for; the message says how to allow it."""


def current_nice() -> int:
    """The niceness of the process's main thread (which every thread started after
    :func:`set_nice` shares)."""
    return os.getpriority(os.PRIO_PROCESS, os.getpid())


def _threads() -> list[int]:
    try:
        return [int(tid) for tid in os.listdir("/proc/self/task")]
    except OSError:  # no /proc: the process, as the platform defines it
        return [0]


def set_nice(value: int) -> None:
    """Give every thread of this process the niceness ``value`` (``MIN_NICE`` to ``MAX_NICE``;
    lower runs first); threads started afterwards inherit it.

    Raises :class:`ValueError` for a value out of range and :class:`PriorityError` when the
    operating system refuses (raising a priority takes ``CAP_SYS_NICE`` or ``RLIMIT_NICE``); on a
    refusal no thread is left changed.
    """
    if isinstance(value, bool) or not isinstance(value, int) or not MIN_NICE <= value <= MAX_NICE:
        raise ValueError(f"nice: got {value!r}; expected a whole number from {MIN_NICE} (most precedence) to {MAX_NICE}")
    before = os.getpriority(os.PRIO_PROCESS, 0)
    done: list[int] = []
    try:
        for tid in _threads():
            try:
                os.setpriority(os.PRIO_PROCESS, tid, value)
            except ProcessLookupError:  # the thread ended meanwhile
                continue
            done.append(tid)
    except PermissionError as error:
        for tid in done:
            try:
                os.setpriority(os.PRIO_PROCESS, tid, before)
            except OSError:
                pass  # (lowering a priority back to where it was is allowed; a thread that ended is gone)
        limit = _nice_limit(before)
        raise PriorityError(
            f"nice {value}: the operating system refused ({errno.errorcode.get(error.errno or 0, error.errno)}): raising a process's "
            f"priority above nice {limit} needs CAP_SYS_NICE: run it as root, give it the capability (systemd: Nice={value} or "
            f"AmbientCapabilities=CAP_SYS_NICE), or allow it in the 'nice' resource limit (limits.conf: '<user> - nice {value}'); "
            f"or leave --nice out to run at the default priority"
        ) from None


def _nice_limit(current: int) -> int:
    """The lowest niceness this process may take without ``CAP_SYS_NICE`` (``RLIMIT_NICE``
    allows down to ``20 - limit``; without it, none lower than ``current``)."""
    import resource

    try:
        soft, _hard = resource.getrlimit(resource.RLIMIT_NICE)
    except (AttributeError, OSError, ValueError):
        return current
    if soft == resource.RLIM_INFINITY:
        return MIN_NICE
    return min(current, max(MIN_NICE, 20 - soft)) if soft > 0 else current
