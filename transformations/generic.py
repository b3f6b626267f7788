"""Generic units: a periodic source and a relay. The quick start, tests and benchmarks use them."""

from __future__ import annotations

from dyknow import Message, Unit

__all__ = ["PeriodicSource", "Relay"]


class PeriodicSource(Unit):
    """Publishes a payload of ``payload_size`` bytes on ``out`` at ``rate_hz``.

    Each message is stamped with its origin time when published. With ``count`` > 0 it stops
    after that many messages.
    """

    def setup(self) -> None:
        rate = float(self.params.get("rate_hz", 10.0))
        if rate <= 0:
            raise ValueError(f"param rate_hz must be positive; got {rate}")
        size = int(self.params.get("payload_size", 16))
        if size < 0:
            raise ValueError(f"param payload_size must be >= 0; got {size}")
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
    """Republishes every message from ``in`` on ``out`` unchanged (its origin time included)."""

    def on_message(self, port: str, msg: Message) -> None:
        self.publish("out", msg.payload)
