"""The DyKnow paper's ball-tracking scenario with simple synthetic units (no OpenCV).

A camera publishes tiny frames that carry the ball position; the subsampler, detector,
localization and tracker pass it along, so tests can check the stream end to end while the
planner and the adaptation loop rewire it. ``scenario.xml`` holds their specs.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from dyknow import Message, Unit

SPECS = Path(__file__).with_name("scenario.xml")


class Camera(Unit):
    """Publishes 4x4 frames at ``rate_hz``: pixel [0, 0] is the frame number, [0, 1] the camera id.

    Tests make it misbehave: ``explode()`` raises in the next tick (the unit fails); ``freeze()``
    stops publishing (the stream stalls).
    """

    CAMERA_IDS = {"bottom": 1, "top": 2, "ceiling": 3}

    def setup(self) -> None:
        self.frames = 0
        self._explode = False
        self._frozen = False
        self.create_timer(1.0 / float(self.params.get("rate_hz", 100.0)), self.tick, first_s=0)

    def explode(self) -> None:
        self._explode = True

    def freeze(self) -> None:
        self._frozen = True

    def tick(self) -> None:
        if self._explode:
            raise RuntimeError(f"camera {self.params['camera']} lost its connection")
        if self._frozen:
            return
        self.frames += 1
        frame = np.zeros((4, 4), dtype=np.int64)
        frame[0, 0] = self.frames
        frame[0, 1] = self.CAMERA_IDS[str(self.params["camera"])]
        self.publish("out", frame)


class Subsampler(Unit):
    def on_message(self, port: str, msg: Message) -> None:
        self.publish("hsv", msg.payload)


class Detector(Unit):
    def on_message(self, port: str, msg: Message) -> None:
        frame = msg.payload
        self.publish("out", {"camera": int(frame[0, 1]), "frame": int(frame[0, 0]), "x": 10.0, "y": 20.0})


class Localization(Unit):
    def on_message(self, port: str, msg: Message) -> None:
        d = msg.payload
        self.publish("out", {"camera": d["camera"], "frame": d["frame"], "x": d["x"] / 10, "y": d["y"] / 10})


class Tracker(Unit):
    """Keeps state across reconfigurations: ``count`` only grows."""

    def setup(self) -> None:
        self.count = 0

    def on_message(self, port: str, msg: Message) -> None:
        self.count += 1
        self.publish("out", {**msg.payload, "tracked": self.count})


class Consumer(Unit):
    """Records what arrives on the requested key (tests subscribe with it)."""

    def setup(self) -> None:
        self.received: list[Message] = []
        self._cond = threading.Condition()

    def on_message(self, port: str, msg: Message) -> None:
        with self._cond:
            self.received.append(msg)
            self._cond.notify_all()

    def wait_for(self, predicate, timeout: float = 5.0) -> Message:  # type: ignore[no-untyped-def]
        """Wait for a message arriving from now on that satisfies ``predicate``; returns it."""
        deadline = time.monotonic() + timeout
        with self._cond:
            start = len(self.received)
            while True:
                for msg in self.received[start:]:
                    if predicate(msg):
                        return msg
                start = len(self.received)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no matching message within {timeout} s ({len(self.received)} received)")
                self._cond.wait(left)
