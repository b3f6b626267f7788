"""The DyKnow paper's ball-tracking scenario with simple synthetic units (no OpenCV).

A camera publishes tiny frames that carry the frame number and the camera's id; the subsampler,
detector, localization and tracker pass them along, so a test can check the stream end to end
while the planner and the adaptation loop rewire it. :data:`SCENARIO_SPECS` holds their specs
(templates over the ontology class ``dk:Camera``: load ``specs/dyknow.ttl`` with them)::

    from dyknow import Manager, Ontology
    from dyknow.testing import SCENARIO_SPECS

    with Manager("robot", specs=[SCENARIO_SPECS], ontology=Ontology.load(["specs/dyknow.ttl"])) as robot:
        key = robot.request("BallTrack(field)")

Labels: ``robot-camera`` (the bottom camera, priority 1, needs ``battery >= 0.25``),
``ceiling-camera`` (priority 10), ``subsampler(Cam)``, ``ball-detector(Cam)``,
``localization(Cam)``, ``tracker`` and ``consumer`` (a :class:`~dyknow.testing.Sink`).

:data:`SCENARIO_HOSTS` splits the same specs over three managers, for the scenario across hosts
(``dyknow demo --distributed``): ``robot`` (its camera), ``field`` (the ceiling camera) and
``station`` (the processing, and the tracker a user requests).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dyknow.message import Message
from dyknow.unit import Unit

__all__ = ["CAMERA_IDS", "SCENARIO_HOSTS", "SCENARIO_SPECS", "Camera", "Detector", "Localization", "Subsampler", "Tracker"]

#: The scenario's spec file (shipped with the package).
SCENARIO_SPECS = Path(__file__).with_name("scenario.xml")

#: The scenario's specs split over three managers: manager name -> its library.
SCENARIO_HOSTS = {name: Path(__file__).with_name(f"scenario-{name}.xml") for name in ("robot", "field", "station")}

#: The id each camera writes into its frames.
CAMERA_IDS = {"bottom": 1, "top": 2, "ceiling": 3}


class Camera(Unit):
    """Publishes ``size`` x ``size`` frames (default 4, int64) at ``rate_hz``: pixel [0, 0] is the
    frame number, [0, 1] the camera id. A larger ``size`` loads a link (64: 32 KiB a frame).

    Tests make it misbehave: :meth:`explode` makes the next tick raise (the unit fails);
    :meth:`freeze` stops publishing (the stream stalls).
    """

    CAMERA_IDS = CAMERA_IDS

    def setup(self) -> None:
        """Start publishing at once, at ``rate_hz`` (default 100)."""
        self.frames = 0
        self.size = max(2, int(self.params.get("size", 4)))
        self._explode = False
        self._frozen = False
        self.create_timer(1.0 / float(self.params.get("rate_hz", 100.0)), self.tick, first_s=0)

    def explode(self) -> None:
        """Make the next tick raise, as a camera that lost its connection."""
        self._explode = True

    def freeze(self) -> None:
        """Stop publishing while staying alive, as a camera that hangs."""
        self._frozen = True

    def resume(self) -> None:
        """Publish again after :meth:`freeze`."""
        self._frozen = False

    def tick(self) -> None:
        """Publish the next frame."""
        if self._explode:
            raise RuntimeError(f"camera {self.params['camera']} lost its connection")
        if self._frozen:
            return
        self.frames += 1
        frame = np.zeros((self.size, self.size), dtype=np.int64)
        frame[0, 0] = self.frames
        frame[0, 1] = CAMERA_IDS[str(self.params["camera"])]
        self.publish("out", frame)


class Subsampler(Unit):
    """Passes frames on (the paper's colour conversion)."""

    def on_message(self, port: str, msg: Message) -> None:
        """Publish the frame on ``hsv``."""
        self.publish("hsv", msg.payload)


class Detector(Unit):
    """Turns a frame into a detection that names the camera and frame."""

    def on_message(self, port: str, msg: Message) -> None:
        """Publish ``{"camera", "frame", "x", "y"}``."""
        frame = msg.payload
        self.publish("out", {"camera": int(frame[0, 1]), "frame": int(frame[0, 0]), "x": 10.0, "y": 20.0})


class Localization(Unit):
    """Maps a detection to field coordinates."""

    def on_message(self, port: str, msg: Message) -> None:
        """Publish the detection with ``x`` and ``y`` scaled."""
        d = msg.payload
        self.publish("out", {"camera": d["camera"], "frame": d["frame"], "x": d["x"] / 10, "y": d["y"] / 10})


class Tracker(Unit):
    """Keeps state across reconfigurations: ``count`` only grows."""

    def setup(self) -> None:
        """Start counting at zero."""
        self.count = 0

    def on_message(self, port: str, msg: Message) -> None:
        """Publish the position with ``tracked``, the number of positions seen so far."""
        self.count += 1
        self.publish("out", {**msg.payload, "tracked": self.count})
