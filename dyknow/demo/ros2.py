"""The ball demo across the ROS 2 boundary (``dyknow demo --ros2``).

The robot's camera is a ROS 2 node outside the manager, :class:`CameraDriver`: a Zenoh session
of its own speaking rmw_zenoh, publishing ``sensor_msgs/Image`` frames (bgr8, the synthetic
scene, stamped when rendered) on :data:`CAMERA_TOPIC`. The manager knows that camera by its
meaning: the spec ``robot-camera`` (same tag, priority and battery constraint as in
``specs/robot.xml``) is a :class:`~dyknow.ros2.bridge.Ros2Source` of that topic. The tracked ball
goes back to ROS 2 as ``geometry_msgs/PointStamped`` on :data:`TRACK_TOPIC` through
:class:`TrackToRos`, and the driver's node subscribes to it, so the loop closes: the same
planning and adaptation (requirement, battery) run with a ROS 2 producer and a ROS 2 consumer.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from dyknow.message import Message
from dyknow.ros2.node import Received, Ros2Node
from dyknow.spec import Param, TransformationSpec
from dyknow.transport import open_session
from dyknow.unit import Unit

__all__ = ["CAMERA_TOPIC", "TRACK_TOPIC", "CameraDriver", "TrackToRos", "ros2_camera"]

#: Where the ROS 2 camera publishes its frames.
CAMERA_TOPIC = "/robot/camera/image_raw"
#: Where dyknow publishes the tracked ball, for ROS 2.
TRACK_TOPIC = "/ball/track"
#: The binding of the demo's output to ROS 2.
TRACK_BINDING = f"ros2:{TRACK_TOPIC}?type=geometry_msgs/msg/PointStamped&frame_id=field"


def ros2_camera(spec: TransformationSpec) -> TransformationSpec:
    """``spec`` (the robot camera of ``specs/robot.xml``) as a ROS 2 topic: same label, tags,
    priority and constraints, its frames taken from :data:`CAMERA_TOPIC`."""
    binding = Param("binding", "string", f"ros2:{CAMERA_TOPIC}?type=sensor_msgs/msg/Image&depth=2&reliability=best_effort")
    params = (binding, Param("require_publisher", "bool", True))  # a producer while its ROS 2 node publishes
    return replace(spec, source="dyknow.ros2.bridge:Ros2Source", params=params, description="the robot camera, a ROS 2 node")


class TrackToRos(Unit):
    """Turns each track (``{"x", "y", ...}`` in metres on the field) into the fields of a
    ``geometry_msgs/PointStamped`` on ``out``; bound to ROS 2, its stamp is the track's origin."""

    def on_message(self, port: str, msg: Message) -> None:
        """Convert and publish."""
        track = msg.payload
        if isinstance(track, dict) and isinstance(track.get("x"), (int, float)) and isinstance(track.get("y"), (int, float)):
            self.publish("out", {"point": {"x": float(track["x"]), "y": float(track["y"]), "z": 0.0}})
        else:
            self.reject(port, f"not a track: {str(track)[:80]}")


class CameraDriver:
    """A ROS 2 camera node beside the manager (its own Zenoh session, connected to ``connect``):
    renders ``camera``'s view of ``scene`` at ``rate_hz`` on :data:`CAMERA_TOPIC` and listens to
    :data:`TRACK_TOPIC`. A context manager; ``close()`` is safe twice."""

    def __init__(
        self,
        connect: Sequence[str],
        scene: Any,
        *,
        camera: str = "top",
        width: int = 640,
        height: int = 480,
        rate_hz: float = 20.0,
        domain: int = 0,
    ) -> None:
        self.frames = 0
        self.tracks = 0
        self.last_track: tuple[float, float] | None = None
        self.track_latency_ns: list[int] = []
        self._scene, self._camera, self._size, self._period = scene, camera, (width, height), 1.0 / rate_hz
        self._session = open_session(listen=["tcp/127.0.0.1:0"], connect=list(connect))
        try:
            self._node = Ros2Node(self._session, "robot_camera_driver", domain=domain)
            self._image = self._node.types.message_class("sensor_msgs/msg/Image")
            self._pub = self._node.create_publisher(CAMERA_TOPIC, "sensor_msgs/msg/Image")
            self._node.create_subscription(TRACK_TOPIC, "geometry_msgs/msg/PointStamped", self._tracked)
        except BaseException:
            self._session.close()
            raise
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="ros2-camera-driver", daemon=True)
        self._thread.start()

    def _tracked(self, received: Received) -> None:
        point = received.message.point
        stamp = received.message.header.stamp
        with self._lock:
            self.tracks += 1
            self.last_track = (float(point.x), float(point.y))
            self.track_latency_ns.append(received.arrival_ns - (int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)))

    def _run(self) -> None:
        from dyknow.ros2.convert import to_message

        width, height = self._size
        next_at = time.monotonic()
        while not self._stop.is_set():
            stamp = time.time_ns()
            frame = self._scene.render(self._camera, stamp, width, height, 2.0)
            self._pub.publish(to_message(frame, "sensor_msgs/msg/Image", self._node.types, origin_ns=stamp, frame_id="robot_camera"))
            self.frames += 1
            next_at += self._period
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def summary(self) -> dict[str, Any]:
        """What crossed the boundary: frames published, tracks received back, the last one and
        the median age of a track on arrival (from its header stamp: the frame's render time)."""
        with self._lock:
            ages = sorted(self.track_latency_ns)
            return {
                "camera_topic": CAMERA_TOPIC,
                "track_topic": TRACK_TOPIC,
                "frames_published": self.frames,
                "tracks_received": self.tracks,
                "last_track": self.last_track,
                "track_age_ms_p50": round(ages[len(ages) // 2] / 1e6, 2) if ages else None,
            }

    def close(self) -> None:
        """Stop publishing, close the node and the session; safe twice."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self._node.close()
        self._session.close()

    def __enter__(self) -> CameraDriver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
