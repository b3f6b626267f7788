"""Whole pipelines through one manager: source -> subsampler -> detector -> localization -> tracker."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import key, spawn_chain, vision_manager
from transformations.localization import format_homography
from transformations.sources import SyntheticScene, VideoSource


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


def test_the_synthetic_ball_is_tracked_on_the_field(vision: Manager) -> None:
    scene_params = {"width": 640, "height": 480, "rate_hz": 30, "seed": 11}
    vision.spawn("synthetic-scene(ceiling)", "cam", params=scene_params)
    vision.spawn("subsampler(ceiling)", "sub", params={"scale": 0.5}, bindings={"in": key(vision, "cam", "out")})
    vision.spawn("ball-detector(ceiling)", "det", bindings={"in": key(vision, "sub", "hsv")})
    vision.spawn("localization(ceiling)", "loc", bindings={"in": key(vision, "det", "out")})
    _, tracks = spawn_chain(vision, "tracker", "trk", inputs={"in": "loc/out"}, deep=True)
    _, annotated = spawn_chain(vision, "annotator(ceiling)", "ann", inputs={"image": "cam/out", "detections": "det/out"})
    messages = tracks.wait_for(20, timeout_s=20)
    camera = vision.unit("cam")
    assert isinstance(camera, SyntheticScene)
    scene = camera.scene
    for msg in messages[5:20]:
        track = msg.payload
        truth = scene.ball_at(msg.origin_ns)  # the capture time of the frame it came from
        assert track["t_ns"] == msg.origin_ns
        assert math.hypot(track["x"] - truth.x, track["y"] - truth.y) < 0.05  # metres; the ball's radius is 4 px here
    frame = annotated.wait_for(1)[0].payload
    assert frame.shape == (480, 640, 3)
    for name in ("cam", "sub", "det", "loc", "trk", "ann"):
        assert vision.get_model().unit(name).state == "running"


def test_a_real_throw_follows_a_parabola(vision: Manager, data_dir: Path) -> None:
    """ball.mp4: a ball thrown straight up; its height over time is a parabola."""
    tuned = {"hsv_lower": "25,18,60", "hsv_upper": "45,255,255", "min_circularity": 0.3, "min_fill": 0.3, "min_radius": 10}
    # stamped with their time in the video: the fit measures the units, not how late a loaded machine published
    video = {"path": str(data_dir / "video" / "ball.mp4"), "rate_hz": 30, "stamp": "video"}
    # Pixels as "field" coordinates (y up), 1 unit = 1 pixel: the tracker's units become px and px/s.
    pixels = format_homography(np.array([[1.0, 0, 0], [0, -1.0, 720.0], [0, 0, 1]]))
    _, detections = spawn_chain(vision, "ball-detector(top)", "det", inputs={"in": "sub/hsv"}, params=tuned, deep=True)
    vision.spawn("localization(top)", "loc", params={"homography": pixels}, bindings={"in": key(vision, "det", "out")})
    _, tracks = spawn_chain(
        vision,
        "tracker",
        "trk",
        inputs={"in": "loc/out"},
        params={"gate_m": 150, "measurement_noise": 5, "process_noise": 3000},
        deep=True,
    )
    vision.spawn("subsampler(top)", "sub", bindings={"in": key(vision, "src", "out")})
    vision.spawn("video-source(top)", "src", params=video)
    source = vision.unit("src")
    assert isinstance(source, VideoSource) and source.finished.wait(20)
    found = [(m.origin_ns, m.payload["detections"][0]) for m in detections.messages if m.payload["detections"]]
    assert len(found) >= 10
    t0 = found[0][0]
    t = np.array([(ns - t0) / 1e9 for ns, _ in found])
    y = np.array([d["y"] for _, d in found])
    a, b, c = np.polyfit(t, y, 2)
    residual = y - np.polyval([a, b, c], t)
    assert a > 0  # image y is down: the ball decelerates going up, then falls
    assert np.sqrt(np.mean(residual**2)) < 0.05 * (y.max() - y.min())
    assert any(not m.payload["predicted"] for m in tracks.messages)
    assert min(m.payload["vy"] for m in tracks.messages) < 0 < max(m.payload["vy"] for m in tracks.messages)  # up, then down
