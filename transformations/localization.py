"""Localization: from detections in a camera's image to positions on the field.

The camera is described by a *homography* from image pixels to field metres, valid for points on
one plane. For a ball, use the plane of its centre (height = ball radius): the detected centre
of the ball then maps to the ball's field position. A homography is the simplest complete
description of a static camera looking at a plane, and it is easy to measure: four or more
image points of known field positions, ``cv2.findHomography(image_points, field_points)``.

For the synthetic scene, ``homography=scene:<camera>`` takes the scene's exact homography
(:func:`transformations.scene.image_to_field`) for the size of the incoming detections.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from dyknow import Message, Unit
from transformations import params
from transformations.errors import ParamError
from transformations.payloads import describe, is_number
from transformations.scene import CAMERAS, image_to_field

__all__ = ["Localization", "format_homography", "parse_homography", "to_field"]


def parse_homography(value: Any, name: str = "homography") -> np.ndarray:
    """A 3x3 homography from 9 numbers, row-major, separated by commas or spaces.

    Refuses singular matrices; normalises so that the last element is 1 when it is not 0.
    """
    h = np.array(params.numbers(value, name, 9), dtype=np.float64).reshape(3, 3)
    if abs(np.linalg.det(h)) < 1e-12:
        raise ParamError(f"got {value!r} (its determinant is 0)", where=f"param {name!r}", expected="an invertible 3x3 matrix")
    return h / h[2, 2] if h[2, 2] != 0 else h


def format_homography(h: np.ndarray) -> str:
    """A homography as the param text :func:`parse_homography` reads (9 numbers, row-major)."""
    return ",".join(f"{v:.10g}" for v in np.asarray(h, dtype=np.float64).reshape(9))


def to_field(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map image points (N x 2) through ``h``; points on the plane's horizon line become NaN.

    A homography cannot tell a pixel above the horizon (whose ray never meets the plane) from
    one below: such pixels map to points behind the camera, usually far away. ``Localization``'s
    ``bounds`` param drops positions off the field.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    mapped = np.column_stack([pts, np.ones(len(pts))]) @ h.T
    w = mapped[:, 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        out: np.ndarray = mapped[:, :2] / w
    out[(np.abs(w[:, 0]) < 1e-12) | ~np.isfinite(out).all(axis=1)] = np.nan
    return out


class Localization(Unit):
    """Converts ball detections in image coordinates to field coordinates.

    Input ``in``: detections as the ``BallDetector`` publishes them
    (``{"camera", "width", "height", "detections": [{"x", "y", "radius", "confidence"}]}``).
    Output ``out``, one message per input, keeping its origin time::

        {"camera": "bottom", "frame": "field",
         "objects": [{"x": m, "y": m, "confidence": 0..1}, ...]}

    in the order of the detections. Params:

    - ``homography``: image -> field, 9 numbers row-major (see :func:`parse_homography`), or
      ``scene:<camera>`` for the synthetic scene's camera;
    - ``homography_size``: the image size (``"WxH"``) the homography was measured at; when
      detections come from frames of another size (a subsampled stream), their pixel
      coordinates are scaled to it first. Empty: use them as they are;
    - ``min_confidence``: detections below it are dropped (default 0);
    - ``bounds``: ``"xmin,ymin,xmax,ymax"`` in metres; positions outside are dropped (a
      reflection, or something above the horizon). Empty (the default): no bounds;
    - ``camera``: the name put in the output when the input names none.

    With ``scene:<camera>``, ``homography_size`` is not needed: the scene's homography is
    computed for the size of the incoming detections.
    """

    def setup(self) -> None:
        """Read the camera, the homography and the field bounds from the params."""
        self.camera = params.text(self.params, "camera", "")
        self.min_confidence = params.number(self.params, "min_confidence", 0.0, low=0, high=1)
        self.homography_size = params.size(self.params.get("homography_size", ""), "homography_size")
        bounds = params.text(self.params, "bounds", "")
        self.bounds = params.numbers(bounds, "bounds", 4) if bounds else None
        if self.bounds is not None and not (self.bounds[0] < self.bounds[2] and self.bounds[1] < self.bounds[3]):
            raise ParamError(
                f"got {bounds!r}", where="param 'bounds'", expected="'xmin,ymin,xmax,ymax' with xmin < xmax and ymin < ymax"
            )
        raw = params.text(self.params, "homography", required=True)
        self._scene_camera: str | None = None
        self._fixed: np.ndarray | None = None
        self._by_size: dict[tuple[int, int], np.ndarray] = {}
        if raw.startswith("scene:"):
            camera = raw.partition(":")[2].strip()
            if camera not in CAMERAS:
                raise ParamError(
                    f"got {raw!r}", where="param 'homography'", expected=f"scene:<camera> with camera one of {', '.join(CAMERAS)}"
                )
            self._scene_camera = camera
        else:
            self._fixed = parse_homography(raw)

    def homography_for(self, width: int | None, height: int | None) -> np.ndarray | str:
        """The image -> field homography for detections in a ``width`` x ``height`` image.

        Returns an explanation (str) instead when the size is needed but unknown.
        """
        if self._fixed is not None and self.homography_size is None:
            return self._fixed
        if width is None or height is None:
            return "detections without 'width' and 'height'; expected them to scale pixels to the homography's image size"
        key = (width, height)
        h = self._by_size.get(key)
        if h is None:
            if self._scene_camera is not None:
                h = image_to_field(self._scene_camera, width, height)
            else:
                assert self._fixed is not None and self.homography_size is not None
                ref_w, ref_h = self.homography_size
                scale = np.diag([ref_w / width, ref_h / height, 1.0])
                h = self._fixed @ scale
            self._by_size[key] = h
        return h

    def localize(self, payload: Mapping[str, Any]) -> dict[str, Any] | str:
        """The output for one detections payload, or why the payload is unusable."""
        detections = payload.get("detections")
        if not isinstance(detections, list):
            return f"got a dict without a 'detections' list (keys: {', '.join(map(str, payload)) or 'none'}); expected detector output"
        width, height = payload.get("width"), payload.get("height")
        sized = width is not None and height is not None
        if sized and not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
            return f"got width={width!r}, height={height!r}; expected positive whole numbers"
        h = self.homography_for(width, height)
        if isinstance(h, str):
            return h
        kept = []
        for d in detections:
            if not isinstance(d, Mapping) or not all(is_number(d.get(k)) for k in ("x", "y")):
                return f"got a detection {d!r}; expected a dict with numeric 'x' and 'y'"
            confidence = float(d["confidence"]) if is_number(d.get("confidence")) else 1.0
            if confidence >= self.min_confidence:
                kept.append((float(d["x"]), float(d["y"]), confidence))
        objects = []
        if kept:
            field = to_field(h, np.array([(x, y) for x, y, _ in kept]))
            for (fx, fy), (_, _, confidence) in zip(field, kept, strict=True):
                if math.isfinite(fx) and math.isfinite(fy) and self._inside(fx, fy):
                    objects.append({"x": round(float(fx), 4), "y": round(float(fy), 4), "confidence": confidence})
        camera = payload.get("camera") or self.camera
        return {"camera": camera, "frame": "field", "objects": objects}

    def _inside(self, x: float, y: float) -> bool:
        if self.bounds is None:
            return True
        xmin, ymin, xmax, ymax = self.bounds
        return xmin <= x <= xmax and ymin <= y <= ymax

    def on_message(self, port: str, msg: Message) -> None:
        """Map the detections to field coordinates and publish them; reject malformed input."""
        payload = msg.payload
        if not isinstance(payload, Mapping):
            self.reject(port, f"got {describe(payload)}; expected a detections dict")
            return
        result = self.localize(payload)
        if isinstance(result, str):
            self.reject(port, result)
            return
        self.publish("out", result)
