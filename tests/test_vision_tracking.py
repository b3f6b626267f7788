"""Tracker: smoothing noisy positions of the synthetic ball, bridging gaps, giving up."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import failure_of, port_stats, publisher, spawn_chain, vision_manager
from transformations.scene import Scene
from transformations.tracking import ConstantVelocityKalman, Tracker


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


STEP_NS = 33_333_333  # 30 fps
NOISE_M = 0.05


def positions(frame: str = "field", *points: tuple[float, float]) -> dict[str, object]:
    return {"camera": "ceiling", "frame": frame, "objects": [{"x": x, "y": y, "confidence": 0.9} for x, y in points]}


def test_the_filter_follows_a_constant_velocity() -> None:
    kf = ConstantVelocityKalman(0.0, 0.0, process_noise=0.5, measurement_noise=0.01)
    for i in range(1, 31):
        kf.predict(0.1)
        kf.update(0.5 * 0.1 * i, -0.2 * 0.1 * i)
    assert kf.velocity == pytest.approx((0.5, -0.2), abs=0.02)
    kf.predict(1.0)
    assert kf.position == pytest.approx((0.5 * 4.0, -0.2 * 4.0), abs=0.05)
    before = kf.state.copy()
    kf.predict(0.0)
    kf.predict(-1.0)
    assert np.array_equal(kf.state, before)


def test_the_tracker_smooths_noisy_positions_and_estimates_the_velocity(vision: Manager) -> None:
    scene = Scene(seed=6)
    rng = np.random.default_rng(0)
    src = publisher(vision)
    _, sink = spawn_chain(vision, "tracker", "trk", inputs={"in": "src/out"}, deep=True)
    t0, n = 40 * scene.period_ns, 90
    raw_errors, truths = [], []
    for i in range(n):
        t = t0 + i * STEP_NS
        ball = scene.ball_at(t)
        x, y = ball.x + rng.normal(0, NOISE_M), ball.y + rng.normal(0, NOISE_M)
        raw_errors.append(math.hypot(x - ball.x, y - ball.y))
        truths.append(ball)
        src.emit(positions("field", (x, y)), origin_ns=t)
        sink.wait_for(i + 1)  # one at a time, as frames come
    tracks = [m.payload for m in sink.messages]
    assert [tr["t_ns"] for tr in tracks] == [b.t_ns for b in truths]
    assert not any(tr["predicted"] for tr in tracks)
    settled = range(30, n)  # after a second of data
    smooth = [math.hypot(tracks[i]["x"] - truths[i].x, tracks[i]["y"] - truths[i].y) for i in settled]
    raw = [raw_errors[i] for i in settled]
    assert np.sqrt(np.mean(np.square(smooth))) < 0.7 * np.sqrt(np.mean(np.square(raw)))
    speed_errors = [math.hypot(tracks[i]["vx"] - truths[i].vx, tracks[i]["vy"] - truths[i].vy) for i in settled]
    assert np.mean(speed_errors) < 0.35  # m/s, from 5 cm position noise
    assert set(tracks[0]) == {"frame", "x", "y", "vx", "vy", "t_ns", "predicted"} and tracks[0]["frame"] == "field"


def test_the_tracker_predicts_through_a_gap_then_gives_up(vision: Manager) -> None:
    src = publisher(vision)
    _, sink = spawn_chain(vision, "tracker", "trk", inputs={"in": "src/out"}, params={"timeout_s": 0.5}, deep=True)
    t = 1_000_000_000_000
    count = 0

    def feed(payload: dict[str, object], expect_output: bool = True) -> None:
        nonlocal t, count
        t += 100_000_000  # 10 Hz
        src.emit(payload, origin_ns=t)
        if expect_output:
            count += 1
            sink.wait_for(count)

    for i in range(20):  # 1 m/s along x
        feed(positions("field", (0.1 * i, 0.0)))
    for _ in range(4):  # 0.4 s without the ball: predicted
        feed(positions("field"))
    gap = [m.payload for m in sink.messages[-4:]]
    assert all(tr["predicted"] for tr in gap)
    assert gap[-1]["x"] == pytest.approx(0.1 * 23, abs=0.1)  # kept rolling at 1 m/s
    feed(positions("field"))  # 0.5 s: still within the timeout
    feed(positions("field"), expect_output=False)  # 0.6 s > timeout: lost, nothing published
    feed(positions("field", (5.0, 1.0)))  # a new track starts where the ball is seen now
    assert len(sink.messages) == count
    restart = sink.messages[-1].payload
    assert (restart["x"], restart["y"], restart["vx"], restart["predicted"]) == (5.0, 1.0, 0.0, False)
    tracker = vision.unit("trk")
    assert isinstance(tracker, Tracker) and tracker.tracks_started == 2


def test_the_gate_ignores_far_outliers(vision: Manager) -> None:
    src = publisher(vision)
    _, sink = spawn_chain(vision, "tracker", "trk", inputs={"in": "src/out"}, params={"gate_m": 0.5}, deep=True)
    for i in range(5):
        src.emit(positions("field", (0.0, 0.0)), origin_ns=(i + 1) * STEP_NS)
        sink.wait_for(i + 1)
    src.emit(positions("field", (2.5, 2.0), (0.02, 0.0)), origin_ns=6 * STEP_NS)
    src.emit(positions("field", (3.0, 0.0)), origin_ns=7 * STEP_NS)
    near, far = (m.payload for m in sink.wait_for(7)[5:7])
    assert near["predicted"] is False and abs(near["x"]) < 0.05  # the near one was used, not the more confident far one
    assert far["predicted"] is True and abs(far["x"]) < 0.05


def test_bad_input_is_rejected_and_bad_params_are_named(vision: Manager) -> None:
    src = publisher(vision)
    _, sink = spawn_chain(vision, "tracker", "trk", inputs={"in": "src/out"})
    bad: list[object] = [positions("image", (1.0, 1.0)), {"detections": []}, "text", {"objects": [{"x": 1}]}]
    for payload in bad:
        src.emit(payload)
    src.emit(positions("field", (1.0, 1.0)))
    sink.wait_for(1)
    stats = port_stats(vision, "trk", "in")
    assert stats.rejected == 4 and "expected a dict with numeric 'x' and 'y'" in (stats.last_rejection or "")
    assert "param 'timeout_s': got 0.0; expected a number > 0" in failure_of(vision, "tracker", "t2", {"timeout_s": 0})
