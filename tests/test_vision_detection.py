"""BallDetector: synthetic frames against ground truth, real photos, plain frames, params."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import failure_of, publisher, read_image, solid, spawn_chain, vision_manager
from transformations.detection import DetectorConfig, detect_balls
from transformations.errors import ParamError
from transformations.scene import CAMERAS, Scene


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


W, H = 640, 480


def hsv_of(path: Path) -> np.ndarray:
    return cv2.cvtColor(read_image(path), cv2.COLOR_BGR2HSV)


@pytest.mark.parametrize("camera", CAMERAS)
def test_the_default_detector_finds_the_synthetic_ball_at_its_true_position(camera: str) -> None:
    scene = Scene(seed=5)
    step = scene.period_ns // 1500
    times = [t for t in range(0, scene.period_ns, step) if (b := scene.ball_in_image(camera, t, W, H)) and b.complete]
    config = DetectorConfig()
    for t in times[:: max(1, len(times) // 25)]:
        truth = scene.ball_in_image(camera, t, W, H)
        assert truth is not None
        found = detect_balls(cv2.cvtColor(scene.render(camera, t, W, H, noise=2.0), cv2.COLOR_BGR2HSV), config)
        assert len(found) == 1, (camera, t, found)
        assert math.hypot(found[0].x - truth.x, found[0].y - truth.y) < 1.5
        assert found[0].radius == pytest.approx(truth.radius, abs=2.0)
        assert 0.8 < found[0].confidence <= 1.0


def test_hough_circles_find_the_synthetic_ball_too() -> None:
    scene = Scene(seed=5)
    t = next(
        t
        for t in range(0, scene.period_ns, scene.period_ns // 500)
        if (b := scene.ball_in_image("top", t, W, H)) and b.complete and b.radius > 10
    )
    truth = scene.ball_in_image("top", t, W, H)
    assert truth is not None
    (found,) = detect_balls(cv2.cvtColor(scene.render("top", t, W, H), cv2.COLOR_BGR2HSV), DetectorConfig(method="hough"))
    assert math.hypot(found.x - truth.x, found.y - truth.y) < 2.0 and found.radius == pytest.approx(truth.radius, abs=2.5)


def test_no_detection_on_plain_frames_and_on_the_field_without_the_ball(data_dir: Path) -> None:
    config = DetectorConfig()
    for bgr in ((0, 0, 0), (255, 255, 255), (120, 120, 120), (0, 0, 255)):
        assert detect_balls(cv2.cvtColor(solid(H, W, bgr), cv2.COLOR_BGR2HSV), config) == []
    scene = Scene(seed=5)
    t = next(t for t in range(0, scene.period_ns, scene.period_ns // 500) if scene.ball_in_image("top", t, W, H) is None)
    assert detect_balls(cv2.cvtColor(scene.render("top", t, W, H, noise=2.0), cv2.COLOR_BGR2HSV), config) == []
    # grey content in a 3-channel image (a basketball scene): no colour, no ball
    assert detect_balls(hsv_of(data_dir / "images" / "ball" / "basketball1.png"), config) == []


def test_the_green_sweets_among_the_smarties(data_dir: Path) -> None:
    found = detect_balls(hsv_of(data_dir / "images" / "ball" / "smarties.png"), DetectorConfig())
    # two whole green sweets; the third, cut by the image corner, is not round enough to count
    centres = sorted((d.x, d.y) for d in found)
    assert len(centres) == 2
    for (x, y), (ex, ey) in zip(centres, [(268, 117), (388, 170)], strict=True):
        assert math.hypot(x - ex, y - ey) < 3
    assert all(d.radius == pytest.approx(27.5, abs=2.5) for d in found)
    assert found[0].confidence >= found[1].confidence


def test_a_hue_range_that_wraps_around_finds_the_red_sweets(data_dir: Path) -> None:
    hsv = hsv_of(data_dir / "images" / "ball" / "smarties.png")
    config = DetectorConfig(hsv_lower=(170, 120, 70), hsv_upper=(8, 255, 255), max_detections=10)
    red = {(33, 228), (100, 260), (219, 305), (287, 213)}
    found = [(round(d.x), round(d.y)) for d in detect_balls(hsv, config)]
    for x, y in red:
        assert any(math.hypot(x - fx, y - fy) < 4 for fx, fy in found), ((x, y), found)


def test_the_football_in_a_cluttered_photo_with_hough(data_dir: Path) -> None:
    config = DetectorConfig(
        hsv_lower=(20, 80, 150),
        hsv_upper=(35, 255, 255),
        morph_kernel=3,
        min_radius=10,
        max_radius=60,
        min_fill=0.3,
        method="hough",
    )
    found = detect_balls(hsv_of(data_dir / "images" / "ball" / "messi5.jpg"), config)
    assert found and math.hypot(found[0].x - 362, found[0].y - 312) < 10  # the yellow ball by the foot


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"hsv_lower": "40,80"}, "param 'hsv_lower': got '40,80'; expected 3 numbers separated by commas"),
        ({"hsv_upper": "200,255,255"}, "param 'hsv_upper': got '200,255,255'; expected whole numbers 'h,s,v' with h in 0..179"),
        ({"hsv_lower": "40,90,80", "hsv_upper": "80,85,255"}, "saturation 90 > 85; expected lower <= upper"),
        ({"hsv_lower": "40.5,80,80"}, "expected whole numbers 'h,s,v' with h in 0..179 (OpenCV's hue: degrees / 2)"),
        ({"method": "yolo"}, "param 'method': got 'yolo'; expected one of 'contours', 'hough'"),
        ({"min_radius": 10, "max_radius": 5}, "param 'max_radius': got 5; expected 0 (no limit) or >= min_radius 10"),
        ({"min_fill": 1.5}, "param 'min_fill': got 1.5; expected a number >= 0 and <= 1"),
    ],
)
def test_bad_params_are_refused_by_name(params: dict[str, object], message: str) -> None:
    with pytest.raises(ParamError) as info:
        DetectorConfig.from_params(params)
    assert message in str(info.value)


def test_the_unit_publishes_detections_per_frame(vision: Manager) -> None:
    scene = Scene(seed=0)
    t = next(
        t
        for t in range(0, scene.period_ns, scene.period_ns // 500)
        if (b := scene.ball_in_image("ceiling", t, W, H)) and b.complete
    )
    truth = scene.ball_in_image("ceiling", t, W, H)
    assert truth is not None
    src = publisher(vision)
    _, sink = spawn_chain(vision, "ball-detector(ceiling)", "det", inputs={"in": "src/out"})
    src.emit(cv2.cvtColor(scene.render("ceiling", t, W, H), cv2.COLOR_BGR2HSV))
    (msg,) = sink.wait_for(1)
    payload = msg.payload
    assert (payload["camera"], payload["width"], payload["height"]) == ("ceiling", W, H)
    (d,) = payload["detections"]
    assert set(d) == {"x", "y", "radius", "confidence"}
    assert math.hypot(d["x"] - truth.x, d["y"] - truth.y) < 1.5
    src.emit(cv2.cvtColor(solid(H, W), cv2.COLOR_BGR2HSV))
    assert sink.wait_for(2)[1].payload["detections"] == []  # no ball: an empty list, still one message per frame


def test_the_unit_names_a_bad_param(vision: Manager) -> None:
    error = failure_of(vision, "ball-detector(top)", "det", {"hsv_lower": "red"})
    assert "param 'hsv_lower': got 'red'; expected 3 numbers separated by commas" in error
