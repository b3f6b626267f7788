"""Giving memory back to the operating system once the units that held much of it are gone.

CPython frees an object's memory when its last reference goes, but the C allocator keeps what
was freed for later use: glibc's ``malloc`` returns a freed block to the system only when it lies
at the top of its heap, so a manager whose formula monitors held 180 MiB of states and object ids
kept its resident size after they were released (issue 51). A :class:`Trimmer` asks glibc to
return every whole free page (``malloc_trim(0)``) a moment after a unit went: at most once per
interval, on a short-lived timer thread, so a burst of releases costs one trim and a trim never
runs on the thread of the call that released. Where there is no ``malloc_trim`` (musl, macOS,
Windows) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import threading
import time
from collections.abc import Callable

__all__ = ["Trimmer", "trim"]

log = logging.getLogger("dyknow.manager")  # (the manager trims)

#: How long after a unit went the trim runs, and the least time between two trims.
TRIM_INTERVAL_S = 1.0


def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, or None where the C library has none."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None)
        function = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_size_t]
    function.restype = ctypes.c_int
    return function


_TRIM = _malloc_trim()


def trim() -> bool:
    """Return the C heap's whole free pages to the operating system now; whether it could
    (False where the C library has no ``malloc_trim``)."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


class Trimmer:
    """Trims (:func:`trim`) ``interval_s`` after :meth:`soon` is first called, and at most once
    per ``interval_s``; :meth:`close` cancels a trim not yet run. Thread-safe."""

    def __init__(self, name: str, interval_s: float = TRIM_INTERVAL_S) -> None:
        self._name = name
        self._interval_s = interval_s
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._closed = False
        #: how many trims ran
        self.trims = 0
        #: how long the last one took, in seconds
        self.last_s = 0.0

    def soon(self) -> None:
        """Trim a moment from now (once, however often it is called meanwhile)."""
        if _TRIM is None:
            return
        with self._lock:
            if self._closed or self._timer is not None:
                return
            timer = self._timer = threading.Timer(self._interval_s, self._run)
            timer.name = f"dyknow-{self._name}-trim"
            timer.daemon = True
            timer.start()

    def _run(self) -> None:
        with self._lock:
            self._timer = None
            if self._closed:
                return
        started = time.perf_counter()
        trim()
        self.last_s = time.perf_counter() - started
        self.trims += 1
        log.debug("manager %r gave freed memory back to the system in %.1f ms", self._name, self.last_s * 1000)

    def close(self) -> None:
        """Cancel a trim not yet run; no trim after this. Safe twice."""
        with self._lock:
            self._closed = True
            timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()
