"""Every image port rejects frames of the wrong shape or type, and its unit keeps running."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import port_stats, publisher, solid, spawn_chain, vision_manager


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


BAD_FRAMES = [
    np.zeros((48, 64, 3), np.float32),  # wrong dtype
    np.zeros((48, 64, 4), np.uint8),  # four channels
    np.zeros((48,), np.uint8),  # one dimension
    np.zeros((0, 64, 3), np.uint8),  # empty
    b"\xff\xd8 jpeg bytes",  # not decoded
    {"width": 64},  # not a frame at all
]

# (label, port, a good frame for the port, the output to wait on, params)
IMAGE_PORTS = [
    ("subsampler(bottom)", "in", solid(), "hsv", {}),
    ("undistort(bottom)", "in", solid(480, 640), "out", {"calibration": "calibration/left_intrinsics.yml"}),
    ("ball-detector(bottom)", "in", solid(), "out", {}),
    ("annotator(bottom)", "image", solid(), "out", {}),
]


@pytest.mark.parametrize(("label", "port", "good", "output", "params"), IMAGE_PORTS, ids=[f"{p[0]}.{p[1]}" for p in IMAGE_PORTS])
def test_a_bad_frame_is_rejected_and_counted(
    vision: Manager,
    data_dir: Path,
    label: str,
    port: str,
    good: np.ndarray,
    output: str,
    params: dict[str, str],
) -> None:
    params = {name: str(data_dir / value) if name == "calibration" else value for name, value in params.items()}
    src = publisher(vision)
    _, sink = spawn_chain(vision, label, "unit", inputs={port: "src/out"}, params=params, sink_port=output, deep=True)
    for i, bad in enumerate(BAD_FRAMES):
        src.emit(bad)
        src.emit(good)
        sink.wait_for(i + 1)  # the good frame came through after the bad one
    stats = port_stats(vision, "unit", port)
    assert stats.rejected == len(BAD_FRAMES)
    assert stats.last_rejection is not None and stats.last_rejection.startswith("got a dict; expected a uint8 array")
    assert vision.get_model().unit("unit").state == "running"
