"""Stand-in units for tests: a sink that records what arrives and a source the test drives."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from dyknow.message import Message
from dyknow.unit import Unit

__all__ = ["Sink", "Source"]


class Sink(Unit):
    """Records every message on any input port; tests wait on it instead of sleeping.

    ``messages`` and ``ports`` grow together (the message, and the port it arrived on).
    """

    def setup(self) -> None:
        """Start with nothing received."""
        self.messages: list[Message] = []
        self.ports: list[str] = []
        self._cond = threading.Condition()

    def on_message(self, port: str, msg: Message) -> None:
        """Record ``msg`` and wake whoever waits."""
        with self._cond:
            self.messages.append(msg)
            self.ports.append(port)
            self._cond.notify_all()

    def wait_for(self, count: int, timeout_s: float = 5.0) -> list[Message]:
        """Wait until ``count`` messages arrived in all; returns every message so far.

        Raises :class:`TimeoutError` saying how many came.
        """
        with self._cond:
            if not self._cond.wait_for(lambda: len(self.messages) >= count, timeout_s):
                raise TimeoutError(f"sink {self.name!r} got {len(self.messages)} of {count} messages within {timeout_s} s")
            return list(self.messages)

    def wait_until(self, predicate: Callable[[Message], bool], timeout_s: float = 5.0) -> Message:
        """Wait for a message arriving from now on for which ``predicate(msg)`` is true; returns it.

        Raises :class:`TimeoutError` when none came within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            start = len(self.messages)
            while True:
                for msg in self.messages[start:]:
                    if predicate(msg):
                        return msg
                start = len(self.messages)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"sink {self.name!r}: no matching message within {timeout_s} s ({len(self.messages)} received)")
                self._cond.wait(left)


class Source(Unit):
    """Publishes what the test hands it, on its output port ``out`` (or any other it declares)."""

    def emit(self, payload: Any, *, port: str = "out", origin_ns: int | None = None) -> None:
        """Publish ``payload`` on ``port`` now, from the caller's thread."""
        self.publish(port, payload, origin_ns=origin_ns)
