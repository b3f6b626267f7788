"""Zenoh shared memory for large payloads: whether this process can use it, and a session's pool."""

from __future__ import annotations

import logging
import threading
from typing import Any, Final

import zenoh

from dyknow.transport.runtime import error_text

__all__ = ["SHM_POOL_BYTES", "SHM_THRESHOLD", "SharedMemory", "shared_memory_problem"]

log = logging.getLogger(__name__)

# Payloads at least this large go out through Zenoh shared memory (each session reserves a pool
# lazily). It was chosen when an earlier benchmark measured it 4x faster than a plain put; the
# fairer one now (benchmarks/payload.py, every copy inside the figure) finds raw Zenoh's plain put
# faster for a 6 MiB frame with nothing else in flight (1.0 vs 1.5 ms), since the receiver copies a
# shared-memory sample out too. When to use it is an open question (README, Payload sizes).
SHM_THRESHOLD: Final = 64 * 1024
SHM_POOL_BYTES = 96 * 1024 * 1024


def shared_memory_problem(pool_bytes: int = SHM_POOL_BYTES) -> str | None:
    """Why this process could not use Zenoh shared memory for large payloads (a pool of
    ``pool_bytes`` made and a buffer taken from it, as a publisher does), or None when it can.
    Where it cannot, such payloads are copied the ordinary way (dyknow doctor says so)."""
    try:
        provider = zenoh.shm.ShmProvider.default_backend(pool_bytes)
        provider.alloc(SHM_THRESHOLD, zenoh.shm.GarbageCollect())
    except (zenoh.ZError, AttributeError) as exc:
        return error_text(exc)
    return None


class SharedMemory:
    """A session's shared-memory pool for large payloads, created on first use.

    Allocation never blocks: when the pool is full (receivers still hold buffers) the payload
    goes out the ordinary way. Where Zenoh has no shared memory, it is never used.
    """

    def __init__(self) -> None:
        self._provider: Any = None
        self._lock = threading.Lock()
        self._broken = False

    def wrap(self, data: bytes) -> Any:
        """``data`` copied into a shared-memory buffer, or ``data`` itself when that is not possible."""
        provider = self._provider
        if provider is None:
            if self._broken:
                return data
            with self._lock:
                if self._provider is None and not self._broken:
                    try:
                        self._provider = zenoh.shm.ShmProvider.default_backend(SHM_POOL_BYTES)
                    except (zenoh.ZError, AttributeError) as exc:
                        self._broken = True
                        log.info("no Zenoh shared memory here (%s); large payloads are copied", error_text(exc))
                        return data
                provider = self._provider
        try:
            buffer = provider.alloc(len(data), zenoh.shm.GarbageCollect())
        except zenoh.ZError:
            return data  # pool full right now
        buffer[:] = data
        return buffer

