"""Localization: detections in pixels to field metres with a known homography."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import failure_of, port_stats, publisher, spawn_chain, vision_manager
from transformations.errors import ParamError
from transformations.localization import format_homography, parse_homography, to_field
from transformations.scene import Scene, field_to_image, image_to_field


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


# 100 px per metre, the field origin at pixel (320, 240), y up: a ceiling camera's map view.
MAP = np.array([[0.01, 0.0, -3.2], [0.0, -0.01, 2.4], [0.0, 0.0, 1.0]])


def detections(*points: tuple[float, float], width: int = 640, height: int = 480) -> dict[str, object]:
    return {
        "camera": "ceiling",
        "width": width,
        "height": height,
        "detections": [{"x": x, "y": y, "radius": 8.0, "confidence": 0.9 - 0.1 * i} for i, (x, y) in enumerate(points)],
    }


def test_a_known_homography_maps_pixels_to_metres(vision: Manager) -> None:
    src = publisher(vision)
    _, sink = spawn_chain(
        vision, "localization(ceiling)", "loc", inputs={"in": "src/out"}, params={"homography": format_homography(MAP)}
    )
    src.emit(detections((320, 240), (420, 140), (120, 440)), origin_ns=123)
    (msg,) = sink.wait_for(1)
    assert msg.origin_ns == 123  # the capture time travels with the data
    assert msg.payload["camera"] == "ceiling" and msg.payload["frame"] == "field"
    objects = msg.payload["objects"]
    assert [(o["x"], o["y"]) for o in objects] == [(0.0, 0.0), (1.0, 1.0), (-2.0, -2.0)]
    assert [o["confidence"] for o in objects] == pytest.approx([0.9, 0.8, 0.7])


def test_detections_of_a_subsampled_stream_are_scaled_to_the_homography_size(vision: Manager) -> None:
    src = publisher(vision)
    params = {"homography": format_homography(MAP), "homography_size": "640x480", "min_confidence": 0.75, "bounds": "-3,-2,3,2"}
    _, sink = spawn_chain(vision, "localization(top)", "loc", inputs={"in": "src/out"}, params=params)
    # at full size (420, 140), (-80, 240) and (0, 0): (1, 1), (-4, 0) off the field, and too low a confidence
    src.emit(detections((210, 70), (-40, 120), (0, 0), width=320, height=240))
    (msg,) = sink.wait_for(1)
    assert [(o["x"], o["y"]) for o in msg.payload["objects"]] == [(1.0, 1.0)]


def test_the_scene_homography_puts_the_ball_where_it_is(vision: Manager) -> None:
    scene = Scene(seed=4)
    t = 7_000_000_000
    truth = scene.ball_in_image("ceiling", t, 320, 240)
    assert truth is not None
    src = publisher(vision)
    _, sink = spawn_chain(vision, "localization(ceiling)", "loc", inputs={"in": "src/out"})  # homography=scene:ceiling
    src.emit(detections((truth.x, truth.y), width=320, height=240))
    (obj,) = sink.wait_for(1)[0].payload["objects"]
    ball = scene.ball_at(t)
    assert (obj["x"], obj["y"]) == pytest.approx((ball.x, ball.y), abs=1e-3)


def test_unusable_payloads_are_rejected_and_the_unit_keeps_running(vision: Manager) -> None:
    src = publisher(vision)
    params = {"homography": format_homography(MAP), "homography_size": "640x480"}
    _, sink = spawn_chain(vision, "localization(top)", "loc", inputs={"in": "src/out"}, params=params)
    bad = [
        np.zeros((4, 4), np.uint8),
        {"objects": []},
        {"detections": [{"x": "left", "y": 3}]},
        {"detections": []},  # no width/height, but homography_size needs them
    ]
    for payload in bad:
        src.emit(payload)
    src.emit(detections((320, 240)))
    sink.wait_for(1)
    stats = port_stats(vision, "loc", "in")
    assert stats.rejected == 4
    assert "expected them to scale pixels" in (stats.last_rejection or "")
    assert vision.get_model().unit("loc").state == "running"


def test_homography_params() -> None:
    h = parse_homography("2, 0, 1,  0 2 1, 0 0 2")
    assert h[2, 2] == 1.0 and h[0, 0] == 1.0
    assert np.allclose(parse_homography(format_homography(image_to_field("top", 640, 480))), image_to_field("top", 640, 480))
    with pytest.raises(ParamError, match="expected 9 numbers separated by commas"):
        parse_homography("1,2,3")
    with pytest.raises(ParamError, match="expected an invertible 3x3 matrix"):
        parse_homography("1,0,0,0,1,0,0,0,0")
    product = image_to_field("top", 640, 480) @ field_to_image("top", 640, 480)
    assert np.allclose(product / product[2, 2], np.eye(3))
    assert np.isnan(to_field(np.array([[1.0, 0, 0], [0, 1, 0], [1, 0, 0]]), np.array([[0.0, 5.0]]))).all()


def test_bad_homography_params_fail_the_unit_by_name(vision: Manager) -> None:
    assert "expected scene:<camera> with camera one of bottom, top, ceiling" in failure_of(
        vision, "localization(top)", "l1", {"homography": "scene:side"}
    )
    assert "expected 'xmin,ymin,xmax,ymax' with xmin < xmax" in failure_of(
        vision, "localization(top)", "l3", {"bounds": "1,1,0,2"}
    )
    assert "param 'homography_size': got '640'; expected an image size such as '640x480'" in failure_of(
        vision, "localization(top)", "l2", {"homography_size": "640"}
    )
