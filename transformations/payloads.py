"""The payload contract of the vision units: frames and JSON messages, and how units check them.

Frames
    A frame is a numpy ``uint8`` array, ``H x W x 3`` in the colour space its port's tag names
    (BGR unless the tag says otherwise: ``HSVImage``, ``YUVImage``) or ``H x W`` for grey. Published
    frames are read-only (receivers share them); a unit that needs to draw on one copies it first.

JSON messages
    Detections (``BallDetector``, image pixels), positions (``Localization``, field metres) and
    tracks (``Tracker``) are dicts; each unit's docstring gives its exact shape.

Units check every payload they receive (:func:`frame_problem` for frames, :func:`is_number` for
fields) and ``reject`` the bad ones, so a wrong stream wired to a port is counted in the
statistics instead of crashing the unit.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

__all__ = ["FrameKind", "describe", "frame_problem", "is_number"]

FrameKind = Literal["colour", "grey", "any"]
"""What a port accepts: ``colour`` (H x W x 3), ``grey`` (H x W) or ``any`` of the two."""

_EXPECTED = {
    "colour": "a uint8 array of shape (H, W, 3)",
    "grey": "a uint8 array of shape (H, W)",
    "any": "a uint8 array of shape (H, W, 3) or (H, W)",
}


def describe(payload: Any) -> str:
    """A short description of a payload for messages: arrays by dtype and shape, others by type."""
    if isinstance(payload, np.ndarray):
        return f"a {payload.dtype} array of shape {payload.shape}"
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return f"{len(payload)} bytes"
    return f"a {type(payload).__name__}"


def frame_problem(payload: Any, kind: FrameKind = "colour") -> str | None:
    """Why ``payload`` is not a frame of ``kind``, as ``"got ...; expected ..."``; None if it is one."""
    ok = (
        isinstance(payload, np.ndarray)
        and payload.dtype == np.uint8
        and 0 not in payload.shape
        and ((payload.ndim == 3 and payload.shape[2] == 3 and kind != "grey") or (payload.ndim == 2 and kind != "colour"))
    )
    if ok:
        return None
    return f"got {describe(payload)}; expected {_EXPECTED[kind]}"


def is_number(value: Any) -> bool:
    """Whether ``value`` is a finite int or float (not a bool) as JSON fields must be."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
