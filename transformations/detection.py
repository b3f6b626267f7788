"""Ball detection on HSV frames: a colour threshold, then round blobs or Hough circles.

:func:`detect_balls` is the algorithm, :class:`BallDetector` the unit that runs it on a stream
(``tools/eval_ball.py`` runs the very same unit over a video). The steps:

1. threshold the HSV frame between ``hsv_lower`` and ``hsv_upper`` (a hue range whose lower
   bound is above its upper bound wraps around 180, for red balls);
2. clean the mask with a morphological opening then closing (elliptic kernel of
   ``morph_kernel`` pixels; 0 or 1 turns it off);
3. ``method=contours`` (default): each outer contour is a candidate; its minimum enclosing
   circle gives the centre and radius; it is kept when the radius is within
   ``[min_radius, max_radius]``, its *circularity* ``4 pi area / perimeter^2`` is at least
   ``min_circularity`` and its *fill* (contour area / enclosing circle area) at least
   ``min_fill``. Confidence is ``sqrt(circularity * fill)``.
   ``method=hough``: ``cv2.HoughCircles`` on the blurred mask (``hough_param1`` is the Canny
   threshold, ``hough_param2`` the accumulator threshold, ``hough_min_dist`` the minimum
   distance between centres); a circle is kept when at least ``min_fill`` of its disc is in
   the mask, and that fraction is its confidence.

Detections are sorted by confidence, best first, at most ``max_detections``.

The defaults find a saturated green ball (OpenCV hue 45..85, i.e. 90..170 degrees) of radius 3
pixels or more: the synthetic scene's ball and ``sim1.mp4``'s, and nothing in ``vtest.avi``
(whose grass reaches hue 43; ``hsv_lower`` 40 would take it for balls). See ``tools/accuracy.py`` for the measured figures and the
params that suit other videos.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any, Final

import cv2
import numpy as np

from dyknow import Message, Unit
from transformations import params
from transformations.errors import ParamError
from transformations.payloads import frame_problem

__all__ = ["METHODS", "BallDetector", "Detection", "DetectorConfig", "detect_balls"]

METHODS: Final = ("contours", "hough")
"""The detection methods: round blobs from contours, or Hough circles."""


_HSV_RANGES = "h in 0..179 (OpenCV's hue: degrees / 2) and s, v in 0..255"


@dataclass(frozen=True, slots=True)
class DetectorConfig:
    """The detector's parameters (see the module documentation); validated when built."""

    hsv_lower: tuple[int, int, int] = (45, 80, 80)
    hsv_upper: tuple[int, int, int] = (85, 255, 255)
    morph_kernel: int = 5
    min_radius: float = 3.0
    max_radius: float = 0.0
    min_circularity: float = 0.5
    min_fill: float = 0.5
    max_detections: int = 5
    method: str = "contours"
    hough_param1: float = 100.0
    hough_param2: float = 12.0
    hough_min_dist: float = 20.0

    def __post_init__(self) -> None:
        for name in ("hsv_lower", "hsv_upper"):
            value = getattr(self, name)
            limits = (179, 255, 255)
            if len(value) != 3 or any(not 0 <= v <= hi for v, hi in zip(value, limits, strict=True)):
                raise ParamError(f"got {value!r}", where=f"param {name!r}", expected=f"'h,s,v' with {_HSV_RANGES}")
        for i, channel in ((1, "saturation"), (2, "value")):
            if self.hsv_lower[i] > self.hsv_upper[i]:
                raise ParamError(
                    f"{channel} {self.hsv_lower[i]} > {self.hsv_upper[i]}",
                    where="params 'hsv_lower'/'hsv_upper'",
                    expected="lower <= upper (only the hue may wrap around)",
                )
        if self.max_radius and self.max_radius < self.min_radius:
            raise ParamError(
                f"got {self.max_radius:g}", where="param 'max_radius'", expected=f"0 (no limit) or >= min_radius {self.min_radius:g}"
            )
        if self.method not in METHODS:
            raise ParamError(f"got {self.method!r}", where="param 'method'", expected=f"one of {', '.join(METHODS)}")

    @classmethod
    def from_params(cls, values: Mapping[str, Any]) -> DetectorConfig:
        """Build from unit params (strings such as ``"45,80,80"`` for the HSV bounds)."""
        defaults = cls()

        def hsv(name: str) -> tuple[int, int, int]:
            raw = values.get(name, ",".join(str(v) for v in getattr(defaults, name)))
            h, s, v = params.numbers(raw, name, 3, low=0, high=255)
            if not all(float(x).is_integer() for x in (h, s, v)) or h > 179:
                raise ParamError(f"got {raw!r}", where=f"param {name!r}", expected=f"whole numbers 'h,s,v' with {_HSV_RANGES}")
            return int(h), int(s), int(v)

        return cls(
            hsv_lower=hsv("hsv_lower"),
            hsv_upper=hsv("hsv_upper"),
            morph_kernel=params.whole(values, "morph_kernel", defaults.morph_kernel, low=0, high=99),
            min_radius=params.number(values, "min_radius", defaults.min_radius, low=0),
            max_radius=params.number(values, "max_radius", defaults.max_radius, low=0),
            min_circularity=params.number(values, "min_circularity", defaults.min_circularity, low=0, high=1),
            min_fill=params.number(values, "min_fill", defaults.min_fill, low=0, high=1),
            max_detections=params.whole(values, "max_detections", defaults.max_detections, low=1),
            method=params.choice(values, "method", METHODS, defaults.method),
            hough_param1=params.number(values, "hough_param1", defaults.hough_param1, low=0, low_open=True),
            hough_param2=params.number(values, "hough_param2", defaults.hough_param2, low=0, low_open=True),
            hough_min_dist=params.number(values, "hough_min_dist", defaults.hough_min_dist, low=0, low_open=True),
        )

    def to_dict(self) -> dict[str, Any]:
        """The config as a dict of plain values."""
        return asdict(self)


@dataclass(frozen=True, slots=True)
class Detection:
    """One ball candidate: centre and radius in pixels, confidence in 0..1."""

    x: float
    y: float
    radius: float
    confidence: float

    def to_dict(self) -> dict[str, float]:
        """The detection as JSON: position and radius in pixels, confidence, rounded."""
        return {
            "x": round(self.x, 2),
            "y": round(self.y, 2),
            "radius": round(self.radius, 2),
            "confidence": round(self.confidence, 3),
        }


def colour_mask(hsv: np.ndarray, config: DetectorConfig) -> np.ndarray:
    """The cleaned binary mask (uint8, 0 or 255) of the pixels within the HSV bounds."""
    lower, upper = np.array(config.hsv_lower, np.uint8), np.array(config.hsv_upper, np.uint8)
    if config.hsv_lower[0] <= config.hsv_upper[0]:
        mask = cv2.inRange(hsv, lower, upper)
    else:  # hue wraps around 180 (reds): two ranges
        high_hues = cv2.inRange(hsv, lower, np.array([179, upper[1], upper[2]], np.uint8))
        low_hues = cv2.inRange(hsv, np.array([0, lower[1], lower[2]], np.uint8), upper)
        mask = cv2.bitwise_or(high_hues, low_hues)
    if config.morph_kernel > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (config.morph_kernel, config.morph_kernel))
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    return mask


def _from_contours(mask: np.ndarray, config: DetectorConfig) -> list[Detection]:
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    # A contour's area is at most that of its enclosing circle, so tiny ones cannot pass.
    min_area = math.pi * config.min_radius**2 * config.min_fill * 0.5
    found = []
    for contour in contours:
        area = cv2.contourArea(contour)
        if area < min_area or len(contour) < 5:
            continue
        (x, y), radius = cv2.minEnclosingCircle(contour)
        if radius < config.min_radius or (config.max_radius and radius > config.max_radius):
            continue
        perimeter = cv2.arcLength(contour, True)
        circularity = min(1.0, 4.0 * math.pi * area / (perimeter * perimeter)) if perimeter > 0 else 0.0
        fill = min(1.0, area / (math.pi * radius * radius)) if radius > 0 else 0.0
        if circularity < config.min_circularity or fill < config.min_fill:
            continue
        found.append(Detection(float(x), float(y), float(radius), math.sqrt(circularity * fill)))
    return found


def _from_hough(mask: np.ndarray, config: DetectorConfig) -> list[Detection]:
    blurred = cv2.GaussianBlur(mask, (0, 0), 2.0)
    circles = cv2.HoughCircles(
        blurred,
        cv2.HOUGH_GRADIENT,
        dp=1.0,
        minDist=config.hough_min_dist,
        param1=config.hough_param1,
        param2=config.hough_param2,
        minRadius=max(0, math.floor(config.min_radius)),
        maxRadius=math.ceil(config.max_radius) if config.max_radius else 0,
    )
    if circles is None:
        return []
    found = []
    height, width = mask.shape
    for x, y, r in circles.reshape(-1, 3):
        if r < config.min_radius or (config.max_radius and r > config.max_radius):
            continue
        x0, y0 = max(0, math.floor(x - r)), max(0, math.floor(y - r))
        x1, y1 = min(width, math.ceil(x + r) + 1), min(height, math.ceil(y + r) + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        disc = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.circle(disc, (round(x - x0), round(y - y0)), max(1, round(r)), 255, -1)
        inside = int(np.count_nonzero(disc))
        covered = int(np.count_nonzero(mask[y0:y1, x0:x1] & disc))
        fill = covered / inside if inside else 0.0
        if fill >= config.min_fill:
            found.append(Detection(float(x), float(y), float(r), fill))
    return found


def detect_balls(hsv: np.ndarray, config: DetectorConfig) -> list[Detection]:
    """The balls in an HSV frame (H x W x 3 uint8), best first (see the module documentation)."""
    mask = colour_mask(hsv, config)
    found = _from_contours(mask, config) if config.method == "contours" else _from_hough(mask, config)
    found.sort(key=lambda d: d.confidence, reverse=True)
    return found[: config.max_detections]


class BallDetector(Unit):
    """Finds a coloured ball in HSV frames.

    Input ``in``: HSV frames (H x W x 3 uint8, OpenCV's hue 0..179). Output ``out``, one message
    per frame (an empty list when there is no ball), with the frame's origin time::

        {"camera": "bottom", "width": W, "height": H,
         "detections": [{"x": px, "y": px, "radius": px, "confidence": 0..1}, ...]}

    sorted by confidence, best first. Params: ``camera`` (the name put in the output) and those
    of :class:`DetectorConfig` (``hsv_lower``/``hsv_upper`` as ``"h,s,v"``, ``morph_kernel``,
    ``min_radius``, ``max_radius`` (0: none), ``min_circularity``, ``min_fill``,
    ``max_detections``, ``method`` and the ``hough_*`` params).
    """

    dedicated_thread = True

    def setup(self) -> None:
        """Read the camera name and the detector's thresholds from the params."""
        self.camera = params.text(self.params, "camera", "")
        self.detector_config = DetectorConfig.from_params(self.params)

    def detect(self, hsv: np.ndarray) -> dict[str, Any]:
        """The output payload for one HSV frame (what ``on_message`` publishes)."""
        height, width = hsv.shape[:2]
        return {
            "camera": self.camera,
            "width": width,
            "height": height,
            "detections": [d.to_dict() for d in detect_balls(hsv, self.detector_config)],
        }

    def on_message(self, port: str, msg: Message) -> None:
        """Detect balls in an HSV frame and publish them (only when someone listens); reject what is no colour frame."""
        problem = frame_problem(msg.payload, "colour")
        if problem is not None:
            self.reject(port, f"{problem} (HSV)")
            return
        if self.has_subscribers("out"):
            self.publish("out", self.detect(msg.payload))
