"""Image preprocessing units: colour conversion and downscaling (Subsampler), undistortion.

Both take BGR camera frames (see :mod:`transformations.payloads`) and publish new frames; neither
writes into the frames it receives.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

from dyknow import Message, Unit
from transformations import params
from transformations.calibration import Calibration, load_calibration
from transformations.errors import CalibrationError, ParamError
from transformations.payloads import frame_problem

__all__ = ["COLOUR_SPACES", "Subsampler", "Undistort", "convert", "downscale"]

COLOUR_SPACES: Final = ("bgr", "hsv", "yuv", "grey")
"""The colour spaces the Subsampler publishes, one output port each."""

_CONVERSIONS: Final = {"hsv": cv2.COLOR_BGR2HSV, "yuv": cv2.COLOR_BGR2YUV, "grey": cv2.COLOR_BGR2GRAY}


def convert(frame: np.ndarray, space: str) -> np.ndarray:
    """A BGR ``frame`` in colour ``space`` (one of :data:`COLOUR_SPACES`).

    HSV is OpenCV's 8-bit HSV: hue 0..179 (degrees / 2), saturation and value 0..255. ``bgr``
    returns the frame itself (no copy).
    """
    if space == "bgr":
        return frame
    code = _CONVERSIONS.get(space)
    if code is None:
        raise ParamError(f"unknown colour space {space!r}", expected=f"one of {', '.join(COLOUR_SPACES)}")
    return cv2.cvtColor(frame, code)


def downscale(frame: np.ndarray, scale: float) -> np.ndarray:
    """``frame`` resized by ``scale`` (area averaging, at least 1 x 1); the frame itself for 1."""
    if scale == 1.0:
        return frame
    height, width = frame.shape[:2]
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)


class Subsampler(Unit):
    """Converts BGR frames to other colour spaces and sizes, as the DyKnow paper's subsampler.

    Input ``in``: BGR frames (H x W x 3 uint8). Outputs ``bgr``, ``hsv``, ``yuv`` (H' x W' x 3)
    and ``grey`` (H' x W'), each frame downscaled by ``scale`` first. Only the outputs someone
    subscribes to are computed. Frames keep their origin time.

    Params: ``scale`` (0 < scale <= 1, default 1), ``every`` (publish every n-th frame, default 1).
    """

    dedicated_thread = True

    def setup(self) -> None:
        """Read the scale and how many frames to skip."""
        self.scale = params.number(self.params, "scale", 1.0, low=0.0, low_open=True, high=1.0)
        self.every = params.whole(self.params, "every", 1, low=1)
        self.seen = 0

    def on_message(self, port: str, msg: Message) -> None:
        """Convert a BGR frame into the colour spaces someone subscribes to; reject what is no colour frame."""
        frame = msg.payload
        problem = frame_problem(frame, "colour")
        if problem is not None:
            self.reject(port, f"{problem} (BGR)")
            return
        self.seen += 1
        if (self.seen - 1) % self.every:
            return
        wanted = [space for space in COLOUR_SPACES if self.has_subscribers(space)]
        if not wanted:
            return
        scaled = downscale(frame, self.scale)
        for space in wanted:
            self.publish(space, convert(scaled, space))


class Undistort(Unit):
    """Removes lens distortion from frames with an OpenCV calibration file.

    Input ``in``: frames (H x W x 3 or H x W uint8). Output ``out``: undistorted frames of the
    same size. The undistortion maps are computed once per frame size (``maps_computed`` counts
    how often) and applied with ``cv2.remap``.

    Params:

    - ``calibration``: path of the calibration file (see :mod:`transformations.calibration`).
      When it records the calibrated image size, frames of another size with the same aspect
      ratio use a scaled camera matrix; other sizes are rejected.
    - ``alpha``: below 0 (default -1) the output keeps the original camera matrix, as
      ``cv2.undistort`` does; from 0 to 1, ``cv2.getOptimalNewCameraMatrix``'s free scaling
      (0: only valid pixels, 1: every source pixel kept).
    """

    path_params = {"calibration": "read"}

    dedicated_thread = True

    def setup(self) -> None:
        """Load the calibration named by the ``calibration`` param."""
        path = params.text(self.params, "calibration", required=True)
        self.calibration: Calibration = load_calibration(path)
        self.alpha = params.number(self.params, "alpha", -1.0, high=1.0)
        self.maps_computed = 0
        self._maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def maps_for(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The remap tables for frames of ``width`` x ``height`` (computed on first use)."""
        maps = self._maps.get((width, height))
        if maps is None:
            cal = self.calibration
            matrix = cal.matrix_for(width, height)
            if self.alpha < 0:
                new_matrix = matrix
            else:
                new_matrix, _roi = cv2.getOptimalNewCameraMatrix(matrix, cal.dist_coeffs, (width, height), self.alpha)
            maps = cv2.initUndistortRectifyMap(matrix, cal.dist_coeffs, None, new_matrix, (width, height), cv2.CV_16SC2)
            self._maps[(width, height)] = maps
            self.maps_computed += 1
        return maps

    def on_message(self, port: str, msg: Message) -> None:
        """Undistort a frame with maps computed once per frame size; reject what is no image."""
        frame = msg.payload
        problem = frame_problem(frame, "any")
        if problem is not None:
            self.reject(port, problem)
            return
        try:
            map1, map2 = self.maps_for(frame.shape[1], frame.shape[0])
        except CalibrationError as exc:
            self.reject(port, str(exc))
            return
        if self.has_subscribers("out"):
            self.publish("out", cv2.remap(frame, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
