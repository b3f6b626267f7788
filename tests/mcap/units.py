"""Units for the recording tests: a live source of every payload kind (spec: units.xml here)."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from dyknow import Unit

#: The output ports of MixedSource, one per kind of payload the recorder maps differently.
PORTS = ("image", "gray", "depth", "jpeg", "detections", "label", "raw", "matrix")


def frame(i: int, port: str) -> Any:
    """The payload MixedSource publishes on ``port`` in round ``i``."""
    if port == "image":
        image = np.zeros((48, 64, 3), np.uint8)
        image[i % 48, :, :] = (i % 256, 255 - i % 256, 7)
        return image
    if port == "gray":
        return np.full((24, 32), i % 256, np.uint8)
    if port == "depth":
        return np.arange(12 * 16, dtype=np.uint16).reshape(12, 16) + i
    if port == "jpeg":  # a JPEG's first bytes; the recorder and a dyknow replay never decode it
        return b"\xff\xd8\xff\xe0" + bytes([i % 256]) * 40
    if port == "detections":
        return {"frame": i, "balls": [{"x": 1.5 * i, "y": -0.25, "r": 3}], "ok": i % 2 == 0, "note": None}
    if port == "label":
        return f"frame {i}: café"
    if port == "raw":
        return bytes(range(i % 7, i % 7 + 20))
    return np.eye(3) * i


class MixedSource(Unit):
    """Publishes ``count`` rounds, one payload per port (see :func:`frame`), at ``rate_hz``.

    It starts once every port has a subscriber in another process (the recorder), so that no
    message is published before anyone records it; ``published`` keeps (port, payload, origin_ns).
    """

    def setup(self) -> None:
        self.published: list[tuple[str, Any, int]] = []
        self.done = threading.Event()

    def run(self, stop: threading.Event) -> None:
        deadline = time.monotonic() + 20.0
        while not all(self.has_subscribers(p) for p in PORTS):
            if stop.wait(0.01) or time.monotonic() > deadline:
                return
        period = 1.0 / float(self.params.get("rate_hz", 200.0))
        for i in range(int(self.params.get("count", 10))):
            for port in PORTS:
                payload = frame(i, port)
                origin_ns = time.time_ns()
                self.publish(port, payload, origin_ns=origin_ns)
                self.published.append((port, payload, origin_ns))
            if stop.wait(period):
                return
        self.done.set()
