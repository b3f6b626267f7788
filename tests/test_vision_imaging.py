"""Subsampler (colour spaces, scale) and Undistort, on real frames, through a manager."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from dyknow import Manager
from dyknow.testing import Sink
from tests.vision_support import failure_of, key, port_stats, publisher, read_image, spawn_chain, vision_manager
from transformations.imaging import Undistort, convert, downscale


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


@pytest.fixture
def frame(data_dir: Path) -> np.ndarray:
    return read_image(data_dir / "images" / "ball" / "smarties.png")  # 413 x 356, colourful


def _sink(manager: Manager, name: str, source_key: str) -> Sink:
    manager.spawn("sink", name, bindings={"in": source_key})
    unit = manager.unit(name)
    assert isinstance(unit, Sink)
    return unit


@pytest.mark.parametrize(
    ("space", "code"), [("hsv", cv2.COLOR_BGR2HSV), ("yuv", cv2.COLOR_BGR2YUV), ("grey", cv2.COLOR_BGR2GRAY), ("bgr", None)]
)
@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_subsampler_output_equals_opencv(vision: Manager, frame: np.ndarray, space: str, code: int | None, scale: float) -> None:
    src = publisher(vision)
    vision.spawn("subsampler(bottom)", "sub", params={"scale": scale}, bindings={"in": key(vision, "src", "out")})
    sink = _sink(vision, "sink", key(vision, "sub", space))
    src.emit(frame)
    (msg,) = sink.wait_for(1)
    expected = (
        frame if scale == 1.0 else cv2.resize(frame, (round(413 * scale), round(356 * scale)), interpolation=cv2.INTER_AREA)
    )
    if code is not None:
        expected = cv2.cvtColor(expected, code)
    assert msg.payload.shape == expected.shape and np.array_equal(msg.payload, expected)
    if space == "bgr" and scale == 1.0:
        assert msg.payload is frame  # forwarded as it came, not copied


def test_subsampler_computes_only_what_is_subscribed_and_every_nth(vision: Manager, frame: np.ndarray) -> None:
    src = publisher(vision)
    vision.spawn("subsampler(top)", "sub", params={"every": 2}, bindings={"in": key(vision, "src", "out")})
    sink = _sink(vision, "sink", key(vision, "sub", "grey"))
    for i in range(4):  # one at a time: the input queue keeps only the latest two frames
        src.emit(frame)
        sink.wait_for((i + 2) // 2)
    # frames 1 and 3 give output; 2 and 4 are skipped by ``every`` (no output to wait on)
    counts = {port: port_stats(vision, "sub", port).messages for port in ("in", "bgr", "hsv", "yuv", "grey")}
    assert counts["grey"] == 2 and counts["bgr"] == counts["hsv"] == counts["yuv"] == 0


def test_subsampler_refuses_a_bad_scale(vision: Manager) -> None:
    assert "param 'scale': got 2.0; expected a number > 0 and <= 1" in failure_of(vision, "subsampler(top)", "sub", {"scale": 2})
    assert "param 'every': got 0; expected a whole number >= 1" in failure_of(vision, "subsampler(top)", "sub2", {"every": 0})


def test_convert_and_downscale_helpers(frame: np.ndarray) -> None:
    assert convert(frame, "bgr") is frame and downscale(frame, 1.0) is frame
    assert downscale(frame, 0.001).shape == (1, 1, 3)
    with pytest.raises(ValueError, match="unknown colour space 'lab'"):
        convert(frame, "lab")


def test_undistort_matches_opencv_and_computes_its_maps_once(vision: Manager, data_dir: Path) -> None:
    calibration = data_dir / "calibration" / "left_intrinsics.yml"
    src = publisher(vision)
    unit, sink = spawn_chain(
        vision, "undistort(bottom)", "undist", inputs={"in": "src/out"}, params={"calibration": str(calibration)}
    )
    frames = [read_image(data_dir / "images" / "chessboard" / f"left0{i}.jpg") for i in (1, 2, 3)]
    for i, image in enumerate(frames):  # one at a time: the input queue keeps only the latest two
        src.emit(image)
        messages = sink.wait_for(i + 1)
    storage = cv2.FileStorage(str(calibration), cv2.FILE_STORAGE_READ)
    k, d = storage.getNode("camera_matrix").mat(), storage.getNode("distortion_coefficients").mat()
    for image, msg in zip(frames, messages, strict=True):
        expected = cv2.undistort(image, k, d)
        assert msg.payload.shape == image.shape
        # fixed-point maps (CV_16SC2) against cv2.undistort's float maps: at most a grey level or two
        assert np.mean(np.abs(msg.payload.astype(int) - expected.astype(int))) < 1.0
        assert not np.array_equal(msg.payload, image)
    assert isinstance(unit, Undistort) and unit.maps_computed == 1
    src.emit(cv2.resize(frames[0], (768, 576)))  # another size: new maps, scaled matrix
    sink.wait_for(4)
    assert unit.maps_computed == 2


def test_undistort_rejects_frames_of_another_aspect_ratio(vision: Manager, data_dir: Path) -> None:
    src = publisher(vision)
    params = {"calibration": str(data_dir / "calibration" / "left_intrinsics.yml")}
    _, sink = spawn_chain(vision, "undistort(top)", "undist", inputs={"in": "src/out"}, params=params)
    src.emit(np.zeros((360, 640, 3), np.uint8))
    src.emit(np.zeros((480, 640, 3), np.uint8))
    sink.wait_for(1)
    stats = port_stats(vision, "undist", "in")
    assert stats.rejected == 1 and "frame size 640x360 does not match the calibration" in (stats.last_rejection or "")
    assert vision.get_model().unit("undist").state == "running"


def test_undistort_names_a_bad_calibration_file(vision: Manager, data_dir: Path, tmp_path: Path) -> None:
    error = failure_of(vision, "undistort(top)", "u1", {"calibration": str(data_dir / "calibration" / "calibration.yml")})
    assert "calibration.yml: missing key 'camera_matrix'" in error
    error = failure_of(vision, "undistort(top)", "u2", {"calibration": str(tmp_path / "nope.yml")})
    assert "nope.yml: no such calibration file" in error
    assert "param 'calibration': is empty" in failure_of(vision, "undistort(top)", "u3", {})
