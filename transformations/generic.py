"""Generic units: a periodic source and a relay. The quick start, tests and benchmarks use them."""

from __future__ import annotations

import threading

from dyknow import Message, Unit
from transformations.errors import ParamError

__all__ = ["PeriodicSource", "Relay", "RemoteStream"]


class PeriodicSource(Unit):
    """Publishes a payload of ``payload_size`` bytes on ``out`` at ``rate_hz``.

    Each message is stamped with its origin time when published. With ``count`` > 0 it stops
    after that many messages.
    """

    def setup(self) -> None:
        """Check the params and start the timer."""
        rate = float(self.params.get("rate_hz", 10.0))
        if rate <= 0:
            raise ParamError(f"got {rate}", where="param 'rate_hz'", expected="a positive number")
        size = int(self.params.get("payload_size", 16))
        if size < 0:
            raise ParamError(f"got {size}", where="param 'payload_size'", expected="a whole number >= 0")
        self._payload = bytes(size)
        self._left = int(self.params.get("count", 0)) or -1
        self._timer = self.create_timer(1.0 / rate, self._tick)

    def _tick(self) -> None:
        if self._left == 0:
            self._timer.cancel()
            return
        self._left -= 1
        self.publish("out", self._payload)


class Relay(Unit):
    """Republishes every message from any input on ``out`` unchanged (its origin time included).

    dyknow forwards them itself (``forward_to``): no Python of the unit runs per message.
    """

    forward_to = "out"


class RemoteStream(Unit):
    """Brings a stream published by another process within the planner's reach.

    Its input follows the ``key`` param (a key expression published elsewhere); its output carries
    the tags its spec gives. It watches the producers' liveliness on that key: when the last one
    vanishes (the process crashed or was killed), or none shows up within ``grace_s`` seconds of
    start, the unit fails, so a manager adapting a request around it switches to an alternative.
    """

    def setup(self) -> None:
        """Subscribe to the remote key and watch its producer's liveliness."""
        key = str(self.params["key"])
        self.set_config({"in": key})
        self._alive = 0
        self._seen = threading.Event()
        self.watch_liveliness(key, self._liveliness)
        grace = float(self.params.get("grace_s", 1.0))
        self._grace = self.create_timer(grace, self._check_seen)

    def _liveliness(self, key: str, alive: bool) -> None:
        if alive:
            self._alive += 1
            self._seen.set()
        else:
            self._alive = max(0, self._alive - 1)
            if self._alive == 0:
                self.fail(f"the producer of {self.params['key']!r} is gone ({key} vanished)")

    def _check_seen(self) -> None:
        self._grace.cancel()
        if not self._seen.is_set():
            self.fail(f"no producer of {self.params['key']!r} within {self.params.get('grace_s', 1.0)} s")

    def on_message(self, port: str, msg: Message) -> None:
        """Publish the remote payload on ``out``."""
        self.publish("out", msg.payload)
