"""The synthetic scene: deterministic frames, ground truth, homographies; and its source unit."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import spawn_chain, vision_manager
from transformations.scene import (
    BALL_RADIUS_M,
    CAMERAS,
    FIELD_LENGTH_M,
    FIELD_WIDTH_M,
    Scene,
    field_to_image,
    image_to_field,
    project,
)
from transformations.sources import SyntheticScene

W, H = 640, 480


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


def visible_times(scene: Scene, camera: str, count: int) -> list[int]:
    """``count`` times spread over one lap when ``camera`` sees the whole ball."""
    step = scene.period_ns // 2000
    times = [t for t in range(0, scene.period_ns, step) if (b := scene.ball_in_image(camera, t, W, H)) and b.complete]
    assert times, f"the {camera} camera never sees the ball"
    return times[:: max(1, len(times) // count)][:count]


def test_rendering_is_deterministic_for_a_seed_and_time() -> None:
    t = 1_234_567_890_123
    a, b = Scene(seed=7), Scene(seed=7)
    for camera in CAMERAS:
        frame = a.render(camera, t, W, H, noise=2.0)
        assert frame.shape == (H, W, 3) and frame.dtype == np.uint8
        assert np.array_equal(frame, b.render(camera, t, W, H, noise=2.0))
    assert not np.array_equal(a.render("ceiling", t, W, H), Scene(seed=8).render("ceiling", t, W, H))


def test_the_ball_stays_on_the_field_and_its_velocity_is_the_derivative() -> None:
    scene = Scene(seed=3, period_s=10.0)
    dt = 1_000_000  # 1 ms
    for t in range(0, scene.period_ns, scene.period_ns // 200):
        ball = scene.ball_at(t)
        assert abs(ball.x) < FIELD_LENGTH_M / 2 and abs(ball.y) < FIELD_WIDTH_M / 2
        later = scene.ball_at(t + dt)
        assert later.x - ball.x == pytest.approx(ball.vx * dt / 1e9, abs=1e-5)
        assert later.y - ball.y == pytest.approx(ball.vy * dt / 1e9, abs=1e-5)
    a, b = scene.ball_at(17), scene.ball_at(5 * scene.period_ns + 17)  # periodic, exactly
    assert (a.x, a.y, a.vx, a.vy) == (b.x, b.y, b.vx, b.vy)


@pytest.mark.parametrize("camera", CAMERAS)
def test_homographies_map_the_ball_centre_both_ways(camera: str) -> None:
    scene = Scene(seed=1)
    to_image, to_field = field_to_image(camera, W, H), image_to_field(camera, W, H)
    for t in visible_times(scene, camera, 5):
        ball = scene.ball_at(t)
        seen = scene.ball_in_image(camera, t, W, H)
        assert seen is not None
        uv, depth = project(camera, W, H, np.array([[ball.x, ball.y, BALL_RADIUS_M]]))
        assert depth[0] > 0 and uv[0] == pytest.approx([seen.x, seen.y], abs=1e-6)
        mapped = cv2.perspectiveTransform(np.array([[[ball.x, ball.y]]]), to_image)[0, 0]
        assert mapped == pytest.approx([seen.x, seen.y], abs=1e-6)
        back = cv2.perspectiveTransform(np.array([[[seen.x, seen.y]]]), to_field)[0, 0]
        assert back == pytest.approx([ball.x, ball.y], abs=1e-9)


def test_the_robot_cameras_see_the_ball_from_the_robot_and_the_ceiling_sees_it_always() -> None:
    scene = Scene(seed=0)
    step = scene.period_ns // 1000
    seen = {c: sum(bool(scene.ball_in_image(c, t, W, H)) for t in range(0, scene.period_ns, step)) for c in CAMERAS}
    assert seen["ceiling"] == 1000
    assert 0 < seen["bottom"] < seen["top"] < 1000
    # the bottom camera looks down, close to the robot: the ball looks big there
    bottom = scene.ball_in_image("bottom", visible_times(scene, "bottom", 1)[0], W, H)
    ceiling = scene.ball_in_image("ceiling", 0, W, H)
    assert bottom is not None and ceiling is not None and bottom.radius > 3 * ceiling.radius


def test_the_rendered_ball_is_where_the_ground_truth_says() -> None:
    scene = Scene(seed=2)
    for camera in CAMERAS:
        t = visible_times(scene, camera, 1)[0]
        truth = scene.ball_in_image(camera, t, W, H)
        assert truth is not None
        hsv = cv2.cvtColor(scene.render(camera, t, W, H), cv2.COLOR_BGR2HSV)
        green = cv2.inRange(hsv, np.array([45, 80, 80]), np.array([85, 255, 255]))
        ys, xs = np.nonzero(green)
        assert math.hypot(xs.mean() - truth.x, ys.mean() - truth.y) < max(1.0, 0.1 * truth.radius)
        assert math.sqrt(len(xs) / math.pi) == pytest.approx(truth.radius, rel=0.15)


def test_any_image_size_works_and_bad_arguments_are_refused() -> None:
    scene = Scene()
    assert scene.render("top", 0, 160, 120).shape == (120, 160, 3)
    with pytest.raises(ValueError, match="unknown camera 'side'; expected one of bottom, top, ceiling"):
        scene.render("side", 0, W, H)
    with pytest.raises(ValueError, match=rf"^image size: got 0x{H}; expected a positive width and height$"):
        field_to_image("top", 0, H)
    with pytest.raises(ValueError, match="^period_s: got 0; expected a positive number"):
        Scene(period_s=0)


def test_the_scene_unit_publishes_frames_whose_ground_truth_is_their_origin_time(vision: Manager) -> None:
    unit, sink = spawn_chain(vision, "synthetic-scene(ceiling)", "scene", params={"rate_hz": 100, "width": 320, "height": 240})
    assert isinstance(unit, SyntheticScene)
    messages = sink.wait_for(3)
    for msg in messages[:3]:
        assert msg.payload.shape == (240, 320, 3) and msg.payload.dtype == np.uint8
        assert not msg.payload.flags.writeable
        assert np.array_equal(msg.payload, unit.render(msg.origin_ns))
        truth = unit.scene.ball_in_image("ceiling", msg.origin_ns, 320, 240)
        assert truth is not None and truth.complete


def test_the_scene_unit_refuses_an_unknown_camera(vision: Manager) -> None:
    info = vision.spawn("synthetic-scene(top)", "scene", params={"camera": "side"})
    assert info.state == "failed"
    assert "param 'camera': got 'side'; expected one of 'bottom', 'top', 'ceiling'" in (info.error or "")
