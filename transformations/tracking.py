"""Tracking: a constant-velocity Kalman filter over ball positions on the field.

:class:`ConstantVelocityKalman` is the filter (numpy, any time step); :class:`Tracker` the unit
that feeds it with localization output and publishes the smoothed track. The filter's state is
``(x, y, vx, vy)``; between measurements the ball is assumed to keep its velocity, with white
acceleration noise of standard deviation ``process_noise`` (m/s^2); measurements are positions
with noise ``measurement_noise`` (m).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from dyknow import Message, Unit
from transformations import params
from transformations.payloads import describe, is_number

__all__ = ["ConstantVelocityKalman", "Tracker"]


class ConstantVelocityKalman:
    """A 2-D constant-velocity Kalman filter with time steps in seconds."""

    def __init__(self, x: float, y: float, *, process_noise: float, measurement_noise: float, initial_speed: float = 2.0) -> None:
        self.state = np.array([x, y, 0.0, 0.0])
        self.covariance = np.diag([measurement_noise**2, measurement_noise**2, initial_speed**2, initial_speed**2])
        self.process_noise = process_noise
        self.measurement_noise = measurement_noise

    def predict(self, dt: float) -> None:
        """Advance the state by ``dt`` seconds (no-op for ``dt <= 0``)."""
        if dt <= 0:
            return
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        # Discrete white-noise acceleration: per axis q * [[dt^4/4, dt^3/2], [dt^3/2, dt^2]].
        q = self.process_noise**2
        pos, cross, vel = dt**4 / 4.0 * q, dt**3 / 2.0 * q, dt**2 * q
        noise = np.array([[pos, 0, cross, 0], [0, pos, 0, cross], [cross, 0, vel, 0], [0, cross, 0, vel]])
        self.state = f @ self.state
        self.covariance = f @ self.covariance @ f.T + noise

    def update(self, x: float, y: float) -> None:
        """Correct the state with a measured position."""
        h = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
        r = np.eye(2) * self.measurement_noise**2
        innovation = np.array([x, y]) - h @ self.state
        s = h @ self.covariance @ h.T + r
        gain = self.covariance @ h.T @ np.linalg.inv(s)
        self.state = self.state + gain @ innovation
        self.covariance = (np.eye(4) - gain @ h) @ self.covariance

    @property
    def position(self) -> tuple[float, float]:
        """The estimated position (x, y) in metres."""
        return float(self.state[0]), float(self.state[1])

    @property
    def velocity(self) -> tuple[float, float]:
        """The estimated velocity (vx, vy) in metres per second."""
        return float(self.state[2]), float(self.state[3])


class Tracker(Unit):
    """Smooths ball positions into a track with a velocity, and bridges missing detections.

    Input ``in``: localization output (``{"frame": "field", "objects": [{"x", "y",
    "confidence"}]}``, any camera). The measurement time is the message's origin time (the
    capture time of the frame). Output ``out``, one message per input while a track exists::

        {"frame": "field", "x": m, "y": m, "vx": m/s, "vy": m/s, "t_ns": ..., "predicted": bool}

    ``predicted`` is true when no object of that message was used (none seen, or none close
    enough to the track): the track is the filter's prediction for ``t_ns``. When no
    measurement was used for ``timeout_s`` the track is dropped (nothing is published) and the
    next object seen starts a new one.

    Params: ``process_noise`` (m/s^2, default 2), ``measurement_noise`` (m, default 0.05),
    ``timeout_s`` (default 1), ``gate_m`` (an object farther than this from the prediction is
    not the tracked ball; 0: no gate; default 1), ``min_confidence`` (default 0).
    """

    def setup(self) -> None:
        """Read the filter's noise, gate and timeout from the params."""
        self.process_noise = params.number(self.params, "process_noise", 2.0, low=0, low_open=True)
        self.measurement_noise = params.number(self.params, "measurement_noise", 0.05, low=0, low_open=True)
        self.timeout_ns = round(params.number(self.params, "timeout_s", 1.0, low=0, low_open=True) * 1e9)
        self.gate_m = params.number(self.params, "gate_m", 1.0, low=0)
        self.min_confidence = params.number(self.params, "min_confidence", 0.0, low=0, high=1)
        self.filter: ConstantVelocityKalman | None = None
        self.last_update_ns = 0
        self.last_t_ns = 0
        self.tracks_started = 0

    def step(self, objects: list[tuple[float, float, float]], t_ns: int) -> dict[str, Any] | None:
        """Feed the objects seen at ``t_ns`` as ``(x, y, confidence)``; the track, or None."""
        candidates = [(x, y) for x, y, c in objects if c >= self.min_confidence]
        kf = self.filter
        if kf is not None:
            kf.predict(max(0, t_ns - self.last_t_ns) / 1e9)
            self.last_t_ns = max(self.last_t_ns, t_ns)
        used = None
        if kf is None:
            if candidates:
                # objects arrive best first: start with the most confident one
                used = candidates[0]
                kf = self.filter = ConstantVelocityKalman(
                    *used, process_noise=self.process_noise, measurement_noise=self.measurement_noise
                )
                self.last_t_ns = t_ns
                self.tracks_started += 1
        elif candidates:
            px, py = kf.position
            nearest = min(candidates, key=lambda p: math.hypot(p[0] - px, p[1] - py))
            if not self.gate_m or math.hypot(nearest[0] - px, nearest[1] - py) <= self.gate_m:
                used = nearest
                kf.update(*used)
        if kf is None:
            return None
        if used is not None:
            self.last_update_ns = max(self.last_update_ns, t_ns)
        elif t_ns - self.last_update_ns > self.timeout_ns:
            self.log.info("ball track lost: no measurement for %.2f s", (t_ns - self.last_update_ns) / 1e9)
            self.filter = None
            return None
        (x, y), (vx, vy) = kf.position, kf.velocity
        return {
            "frame": "field",
            "x": round(x, 4),
            "y": round(y, 4),
            "vx": round(vx, 4),
            "vy": round(vy, 4),
            "t_ns": self.last_t_ns,
            "predicted": used is None,
        }

    def on_message(self, port: str, msg: Message) -> None:
        """Update the filter with the closest plausible position and publish the track; reject malformed input."""
        payload = msg.payload
        problem = _objects_problem(payload)
        if problem is not None:
            self.reject(port, problem)
            return
        objects = [
            (float(o["x"]), float(o["y"]), float(o["confidence"]) if is_number(o.get("confidence")) else 1.0)
            for o in payload["objects"]
        ]
        track = self.step(objects, msg.origin_ns)
        if track is not None:
            self.publish("out", track)


def _objects_problem(payload: Any) -> str | None:
    if not isinstance(payload, Mapping):
        return f"got {describe(payload)}; expected a dict with an 'objects' list"
    frame = payload.get("frame", "field")
    if frame != "field":
        return f"got positions in frame {frame!r}; expected 'field'"
    objects = payload.get("objects")
    if not isinstance(objects, list):
        return (
            f"got a dict without an 'objects' list (keys: {', '.join(map(str, payload)) or 'none'}); expected localization output"
        )
    for o in objects:
        if not isinstance(o, Mapping) or not (is_number(o.get("x")) and is_number(o.get("y"))):
            return f"got an object {o!r}; expected a dict with numeric 'x' and 'y'"
    return None
