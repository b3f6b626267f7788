"""Annotator: detections drawn on the frames, scaled from a subsampled stream."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import publisher, solid, spawn_chain, vision_manager
from transformations.annotation import draw_detections


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


def test_the_annotator_draws_the_latest_detections_on_each_frame(vision: Manager) -> None:
    frames = publisher(vision, "frames")
    dets = publisher(vision, "dets")
    _, sink = spawn_chain(vision, "annotator(top)", "ann", inputs={"image": "frames/out", "detections": "dets/out"})
    frame = solid(480, 640)
    # detections made on a half-size stream: (100, 80) there is (200, 160) here
    detection = {"x": 100, "y": 80, "radius": 10, "confidence": 0.9}
    dets.emit({"width": 320, "height": 240, "detections": [detection]}, origin_ns=1_000)
    # The two inputs have queues of their own: the first frame may be handled before the
    # detections; by the second frame they have been.
    frames.emit(frame, origin_ns=1_000)
    sink.wait_for(1)
    frames.emit(frame, origin_ns=2_000)
    out = sink.wait_for(2)[1].payload
    assert out.shape == (480, 640, 3) and out.dtype == np.uint8
    assert out is not frame and np.array_equal(frame, solid(480, 640))  # drawn on a copy
    red = (out[:, :, 2] > 200) & (out[:, :, 0] < 80)
    ys, xs = np.nonzero(red)
    assert abs(xs.mean() - 200) < 25 and abs(ys.mean() - 160) < 25  # a red circle around the detection
    assert np.array_equal(out[0:100, 400:640], frame[0:100, 400:640])  # nothing drawn elsewhere


def test_stale_detections_are_not_drawn_and_grey_frames_come_out_in_colour(vision: Manager) -> None:
    frames = publisher(vision, "frames")
    dets = publisher(vision, "dets")
    _, sink = spawn_chain(
        vision, "annotator(top)", "ann", inputs={"image": "frames/out", "detections": "dets/out"}, params={"max_age_s": 0.1}
    )
    dets.emit({"detections": [{"x": 10, "y": 10, "radius": 5}]}, origin_ns=0)
    grey = np.full((120, 160), 90, np.uint8)
    frames.emit(grey, origin_ns=1_000_000_000)
    sink.wait_for(1)
    frames.emit(grey, origin_ns=1_000_000_000)
    msg = sink.wait_for(2)[1]
    assert msg.payload.shape == (120, 160, 3)
    assert np.all(msg.payload == 90)  # a second after the detections: nothing drawn


def test_draw_detections_draws_a_trail() -> None:
    frame = solid(100, 100, (0, 0, 0))
    out = draw_detections(frame, [], trail=[(10, 10), (90, 90)])
    assert out[50, 50].tolist() != [0, 0, 0] and out[10, 90].tolist() == [0, 0, 0]
