"""Annotation: detections drawn on frames, for people to look at."""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from dyknow import Message, Unit
from transformations import params
from transformations.payloads import describe, frame_problem, is_number

__all__ = ["Annotator", "draw_detections"]

_BEST = (0, 0, 255)  # red: the most confident detection
_OTHER = (255, 128, 0)  # blue: the other candidates
_TRAIL = (0, 215, 255)  # yellow: where the best detection was in the last frames


def draw_detections(
    frame: np.ndarray,
    detections: list[Mapping[str, Any]],
    *,
    scale: tuple[float, float] = (1.0, 1.0),
    trail: list[tuple[float, float]] | None = None,
) -> np.ndarray:
    """A copy of ``frame`` (BGR or grey) with circles for ``detections`` and a ``trail`` line.

    Detection coordinates are multiplied by ``scale`` (x, y) first, for detections made on a
    resized copy of the frame.
    """
    out = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame.copy()
    sx, sy = scale
    thickness = max(1, round(max(out.shape[:2]) / 320))
    if trail and len(trail) > 1:
        points = np.array([(x * sx, y * sy) for x, y in trail], dtype=np.int32).reshape(-1, 1, 2)
        cv2.polylines(out, [points], False, _TRAIL, thickness, cv2.LINE_AA)
    for rank, d in reversed(list(enumerate(detections))):  # the best is drawn last, on top
        x, y = float(d["x"]) * sx, float(d["y"]) * sy
        radius = (float(d["radius"]) if is_number(d.get("radius")) else 5.0) * (sx + sy) / 2
        colour = _BEST if rank == 0 else _OTHER
        cv2.circle(out, (round(x), round(y)), max(2, round(radius)), colour, thickness, cv2.LINE_AA)
        if is_number(d.get("confidence")):
            label = f"{float(d['confidence']):.2f}"
            cv2.putText(
                out,
                label,
                (round(x + radius + 3), round(y)),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.4 * thickness,
                colour,
                thickness,
                cv2.LINE_AA,
            )
    return out


class Annotator(Unit):
    """Draws the latest detections on every frame.

    Inputs: ``image`` (BGR frames, H x W x 3 uint8, or grey H x W) and ``detections`` (detector
    output, ``{"width", "height", "detections": [{"x", "y", "radius", "confidence"}]}``). Output
    ``out``: for every frame, a BGR copy with the latest detections drawn (the best in red, the
    others in blue, with their confidence) and the trail of the best detection over the last
    ``trail`` detection messages (yellow). Detections made on a resized stream are scaled to the
    frame by their ``width``/``height``. Detections older than ``max_age_s`` (by origin time,
    relative to the frame's) are not drawn.

    Params: ``trail`` (default 30; 0: no trail), ``max_age_s`` (default 0.5).
    """

    dedicated_thread = True

    def setup(self) -> None:
        """Read the trail length and how long a detection stays drawn."""
        self.trail_length = params.whole(self.params, "trail", 30, low=0)
        self.max_age_ns = round(params.number(self.params, "max_age_s", 0.5, low=0, low_open=True) * 1e9)
        self._latest: dict[str, Any] | None = None
        self._latest_ns = 0
        self._trail: deque[tuple[float, float, float, float]] = deque(maxlen=max(1, self.trail_length))

    def on_message(self, port: str, msg: Message) -> None:
        """Remember detections; draw them (and the trail) on each image and publish it."""
        if port == "detections":
            self._on_detections(port, msg)
        else:
            self._on_image(port, msg)

    def _on_detections(self, port: str, msg: Message) -> None:
        payload = msg.payload
        detections = payload.get("detections") if isinstance(payload, Mapping) else None
        if not isinstance(detections, list) or not all(
            isinstance(d, Mapping) and is_number(d.get("x")) and is_number(d.get("y")) for d in detections
        ):
            got = repr(payload)[:120] if isinstance(payload, Mapping) else describe(payload)
            self.reject(port, f"got {got}; expected detector output with a 'detections' list of dicts with numeric 'x' and 'y'")
            return
        self._latest, self._latest_ns = dict(payload), msg.origin_ns
        if detections and self.trail_length:
            width, height = payload.get("width"), payload.get("height")
            best = detections[0]
            self._trail.append((float(best["x"]), float(best["y"]), float(width or 0), float(height or 0)))

    def _on_image(self, port: str, msg: Message) -> None:
        frame = msg.payload
        problem = frame_problem(frame, "any")
        if problem is not None:
            self.reject(port, problem)
            return
        if not self.has_subscribers("out"):
            return
        height, width = frame.shape[:2]
        detections: list[Mapping[str, Any]] = []
        scale = (1.0, 1.0)
        latest = self._latest
        if latest is not None and abs(msg.origin_ns - self._latest_ns) <= self.max_age_ns:
            detections = latest["detections"]
            scale = _scale(latest.get("width"), latest.get("height"), width, height)
        trail = []
        for x, y, src_w, src_h in self._trail:
            sx, sy = _scale(src_w, src_h, width, height)
            trail.append((x * sx, y * sy))
        self.publish("out", draw_detections(frame, list(detections), scale=scale, trail=trail))


def _scale(src_w: Any, src_h: Any, width: int, height: int) -> tuple[float, float]:
    if is_number(src_w) and is_number(src_h) and src_w > 0 and src_h > 0:
        return width / float(src_w), height / float(src_h)
    return 1.0, 1.0
