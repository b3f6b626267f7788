"""The main demo: the DyKnow paper's ball-tracking scenario, running for real.

A robot tracks a ball on a field. A manager holds the vision specs (``specs/vision.xml``) and two
cameras declared the way a robot would declare them: its own camera, preferred but only while the
battery holds (``battery >= 0.25``), and a ceiling camera as the alternative. The demo asks the
planner for ``BallTrack(field)``, the tracked ball position in field coordinates; the planner wires
robot camera -> subsampler -> ball detector -> localization -> tracker and returns a key.

The request carries a requirement, a temporal formula over its own stream (:data:`REQUIREMENT`):
the ball must not be merely predicted for half a second. The robot's camera does not see the
whole field; when the ball stays out of its view, the requirement turns false, and the manager
moves the request to the next-best configuration, the ceiling camera, naming the formula as the
cause; it tries the robot's camera again in the shadow after a back-off (its chain runs beside the
active one, the requirement watched over it) and moves back once the requirement has held there
for the dwell time, that is once the ball has been back in the robot camera's view for 2 s.

The request asks for a warm standby: the next-best configuration (the ceiling camera's chain)
runs beside the active one, so a switch only moves the request's anchor (a few milliseconds
instead of the tens a cold start takes). The demo prints what the standby cost (the process's
CPU with one running and without) beside what it saved (its switches against the cold ones);
``--no-standby`` runs without it.

A simulated battery monitor publishes the battery level on ``dyknow/measurements/battery`` from a
Zenoh session of its own. Midway the battery runs low: the robot camera becomes unavailable and
the manager switches to the ceiling camera; the track keeps flowing on the same key. Later the
battery recovers and the manager switches back. The terminal shows, live, the computation graph,
message rates, per-hop latency, the tracked position beside the ground truth, and every
adaptation with its adaptation and recovery times. At the end the demo writes a report (JSON, a
plot of the track with the adaptations marked, an annotated frame) and says where.

It runs on the synthetic scene by default (no files needed), and on real videos with
``--robot-video PATH --ceiling-video PATH``.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import threading
import time
import weakref
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

from dyknow.adaptation import ANCHOR_LABEL, AdaptationEvent
from dyknow.client import Client
from dyknow.errors import UnitError
from dyknow.manager import Manager
from dyknow.message import Message
from dyknow.resources import specs_dir
from dyknow.spec import Param, Port, TransformationSpec
from dyknow.unit import Unit

__all__ = ["REQUIREMENT", "BallDemo", "Battery", "run_ball_demo"]

REQUEST = "BallTrack(field)"
LOW_BATTERY = 0.25
#: What the demo requires of its track: never only predicted for half a second (the camera must see the ball).
REQUIREMENT = "not historically[0, 500ms] BallTrack(field).predicted"
#: Where on its lap the synthetic ball is when the demo starts (s): the robot's camera loses it
#: about 4 s in, sees it again from about 6.5 s to 8 s, then from about 10.5 s to 24 s (a lap is 20 s).
SCENE_START_S = 15.0


@dataclass(frozen=True, slots=True)
class Battery:
    """The simulated battery: drains, runs low at ``low_at_s``, charges from ``charge_at_s`` on."""

    start: float = 0.6
    low_at_s: float = 10.0
    charge_at_s: float = 14.0
    charge_rate: float = 0.06  # per second

    def level(self, t: float) -> float:
        """The battery level ``t`` seconds into the demo: it drains, then recharges."""
        drain = (self.start - LOW_BATTERY) / self.low_at_s
        if t < self.charge_at_s:
            return max(0.0, self.start - drain * t)
        bottom = max(0.0, self.start - drain * self.charge_at_s)
        return min(1.0, bottom + self.charge_rate * (t - self.charge_at_s))


# A track older than this is reported as lost in the status lines (the tracker sends one per frame).
_STALE_S = 0.5


class TrackLog(Unit):
    """Keeps every track message arriving on the requested key (the demo's consumer)."""

    def setup(self) -> None:
        """Start with an empty log."""
        self.lock = threading.Lock()
        self.track: list[tuple[int, int, dict[str, Any]]] = []  # (arrival ns, origin ns, payload)

    def on_message(self, port: str, msg: Message) -> None:
        """Log the track with its arrival and origin times."""
        if isinstance(msg.payload, dict):
            with self.lock:
                self.track.append((time.time_ns(), msg.origin_ns, msg.payload))


class VerdictLog(Unit):
    """Keeps every verdict of the request's requirement: ``(state time ns, verdict)``."""

    def setup(self) -> None:
        """Start with no verdict."""
        self.lock = threading.Lock()
        self.verdicts: list[tuple[int, bool]] = []

    def on_message(self, port: str, msg: Message) -> None:
        """Log the verdict."""
        if isinstance(msg.payload, dict) and isinstance(msg.payload.get("verdict"), bool):
            with self.lock:
                self.verdicts.append((int(msg.payload["t_ns"]), msg.payload["verdict"]))


class FrameGrab(Unit):
    """Keeps the latest frame arriving on its input (for the report's annotated frame)."""

    def setup(self) -> None:
        """Start with no frame."""
        self.frame: Any = None
        self.got = threading.Event()

    def on_message(self, port: str, msg: Message) -> None:
        """Keep the latest frame."""
        self.frame = msg.payload
        self.got.set()


def camera_specs(
    *, robot_video: str | None, ceiling_video: str | None, rate_hz: float, seed: int, epoch_ns: int = 0
) -> list[TransformationSpec]:
    """The robot's two cameras as ``specs/robot.xml`` declares them, with the demo's rate, seed and
    scene epoch (when the ball's laps start), or reading a video instead of the synthetic scene;
    and the demo's own listeners."""
    from dyknow.spec import load_specs

    videos = {"robot-camera": robot_video, "ceiling-camera": ceiling_video}
    cameras = []
    for spec in load_specs([specs_dir() / "robot.xml"]):
        video = videos.get(spec.label)
        if video is None:
            overrides = {"rate_hz": float(rate_hz), "seed": seed}
            params = tuple(replace(p, value=overrides.get(p.name, p.value)) for p in spec.params)
            cameras.append(replace(spec, params=(*params, Param("epoch_ns", "int", int(epoch_ns)))))
        else:
            params = (Param("path", "string", video), Param("rate_hz", "float", -1.0), Param("loop", "bool", True))
            cameras.append(replace(spec, source="transformations.sources:VideoSource", params=params))
    return [
        *cameras,
        TransformationSpec("track-log", "dyknow.demo.ball:TrackLog", ports=(Port("in", "in", queue=256),)),
        TransformationSpec("verdict-log", "dyknow.demo.ball:VerdictLog", ports=(Port("in", "in", queue=256),)),
        TransformationSpec("frame-grab", "dyknow.demo.ball:FrameGrab", ports=(Port("in", "in", queue=1),)),
    ]


def video_localization(cams: list[str]) -> list[TransformationSpec]:
    """For real videos the scene geometry is unknown: localize in pixels (1 px = 1 cm on the 'field')."""
    from dyknow.spec import load_specs

    out = []
    for spec in load_specs([specs_dir() / "vision.xml"]):
        if spec.label in {f"localization({c})" for c in cams}:
            params = tuple(Param(p.name, p.type, "0.01,0,0,0,0.01,0,0,0,1") if p.name == "homography" else p for p in spec.params)
            out.append(TransformationSpec(**{**{f: getattr(spec, f) for f in spec.__dataclass_fields__}, "params": params}))
    return out


class _CpuShare:
    """The process's CPU (share of one core) while the request had a standby running and while it
    had none, from samples taken along the run (each interval counted by the state at its end)."""

    def __init__(self) -> None:
        self._cpu = {True: 0.0, False: 0.0}
        self._wall = {True: 0.0, False: 0.0}
        self._last = (time.monotonic(), time.process_time())

    def sample(self, standby: bool) -> None:
        """Count the time since the last sample as with (or without) a standby."""
        wall, cpu = time.monotonic(), time.process_time()
        self._wall[standby] += wall - self._last[0]
        self._cpu[standby] += cpu - self._last[1]
        self._last = (wall, cpu)

    def shares(self) -> dict[str, float | None]:
        """``cpu_with_pct`` / ``cpu_without_pct`` (None when no such time) and the seconds of each."""
        out: dict[str, float | None] = {}
        for state, name in ((True, "with"), (False, "without")):
            wall = self._wall[state]
            out[f"cpu_{name}_pct"] = round(100 * self._cpu[state] / wall, 1) if wall >= 0.5 else None
            out[f"seconds_{name}"] = round(wall, 1)
        return out


@dataclass(slots=True)
class _Rates:
    last: dict[str, tuple[float, int]] = field(default_factory=dict)

    def rate(self, name: str, count: int, now: float) -> float:
        previous = self.last.get(name)
        self.last[name] = (now, count)
        if previous is None or now <= previous[0]:
            return 0.0
        return max(0.0, (count - previous[1]) / (now - previous[0]))


class BallDemo:
    """Runs the scenario; ``run()`` returns the report it wrote."""

    def __init__(
        self,
        *,
        duration_s: float = 30.0,
        robot_video: str | None = None,
        ceiling_video: str | None = None,
        rate_hz: float = 20.0,
        out_dir: Path = Path("dyknow-demo-report"),
        battery: Battery | None = None,
        stream: TextIO = sys.stdout,
        live: bool | None = None,
        seed: int = 0,
        ui_port: int | None = None,
        requirement: str | None = REQUIREMENT,
        standby: bool = True,
        ros2: bool = False,
    ) -> None:
        if duration_s <= 0:
            raise ValueError(f"duration must be positive; got {duration_s}")
        for video in (robot_video, ceiling_video):
            if video is not None and not Path(video).is_file():
                raise ValueError(f"{video}: no such video file; expected a video readable by OpenCV")
        self.duration_s = duration_s
        self.robot_video, self.ceiling_video = robot_video, ceiling_video
        self.synthetic = robot_video is None and ceiling_video is None
        if ros2 and robot_video is not None:
            raise ValueError("the ROS 2 variant renders the robot camera itself; expected no robot video with ros2")
        self.ros2 = ros2  # the robot camera is a ROS 2 node, the track goes back to ROS 2 (dyknow.demo.ros2)
        self.rate_hz = rate_hz
        self.out_dir = Path(out_dir)
        scale = duration_s / 30.0  # the battery story fits the duration
        self.battery = battery or Battery(low_at_s=10.0 * scale, charge_at_s=14.0 * scale, charge_rate=0.06 / scale)
        self.stream = stream
        self.live = stream.isatty() if live is None else live
        self.seed = seed
        self.ui_port = ui_port  # serve `dyknow ui` beside the demo on this port (0: any free one)
        self.ui_url: str | None = None
        self.requirement = requirement
        self.standby = standby
        self.events: list[AdaptationEvent] = []
        self._events_lock = threading.Lock()
        self._printed: set[tuple[int, str]] = set()
        self._status_lines = 0  # the live status block at the bottom of the terminal

    # ------------------------------------------------------------------ output

    def _clear_status(self) -> None:
        if self.live and self._status_lines:
            self.stream.write(f"\x1b[{self._status_lines}F\x1b[J")  # up to the block's start, clear below
            self._status_lines = 0

    def say(self, text: str = "") -> None:
        """Print a line (clearing the status line first)."""
        self._clear_status()
        self.stream.write(text + "\n")
        self.stream.flush()

    def _on_adaptation(self, event: AdaptationEvent) -> None:
        with self._events_lock:
            self.events.append(event)

    def _event_line(self, e: AdaptationEvent, specs: dict[str, TransformationSpec] | None = None) -> str:
        if e.kind == "degraded":
            return f">>> request degraded ({e.cause}): {e.detail}"
        old = " -> ".join(x for x in e.old if "camera" in x) or "?"
        new = " -> ".join(x for x in e.new if "camera" in x) or "?"
        times = f"adapted in {e.adaptation_ms:.1f} ms" if e.adaptation_ms is not None else ""
        if e.recovery_ms is not None:
            times += f", stream recovered in {e.recovery_ms:.1f} ms"
        return f">>> adaptation #{e.id}: {_explained(e, specs or {})}: {old} => {new}; {times}"

    # ------------------------------------------------------------------ the run

    def run(self) -> dict[str, Any]:
        """Run the demo; returns the report."""
        from transformations.scene import Scene  # ground truth of the synthetic scene

        specs = [specs_dir() / "vision.xml"]
        epoch_ns = time.time_ns() - round(SCENE_START_S * 1e9)  # the same story every run
        with Manager("demo", specs=specs, ontology=[specs_dir() / "dyknow.ttl"], dwell_s=2.0) as manager:
            cameras = camera_specs(
                robot_video=self.robot_video, ceiling_video=self.ceiling_video, rate_hz=self.rate_hz, seed=self.seed, epoch_ns=epoch_ns
            )
            if self.ros2:
                from dyknow.demo.ros2 import ros2_camera

                cameras = [ros2_camera(s) if s.label == "robot-camera" else s for s in cameras]
                cameras.append(
                    TransformationSpec(
                        "track-to-ros", "dyknow.demo.ros2:TrackToRos", ports=(Port("in", "in", queue=16), Port("out", "out"))
                    )
                )
            for spec in cameras:
                manager.add_transformation(spec)
            if not self.synthetic:
                for spec in video_localization(["top", "ceiling"]):
                    manager.add_transformation(spec)
            manager.on_adaptation(self._on_adaptation)
            specs_by_label = {spec.label: spec for spec in manager.library}
            scene = Scene(seed=self.seed, epoch_ns=epoch_ns) if self.synthetic else None
            source = "the synthetic scene" if self.synthetic else f"videos {self.robot_video} / {self.ceiling_video}"
            self.say(f"dyknow demo: tracking a ball on {source}; manager 'demo' on {', '.join(manager.endpoints)}")
            ui = _UiProcess(manager.endpoints[0], self.ui_port) if self.ui_port is not None else None
            if ui is not None:
                self.ui_url = ui.url
                self.say(f"the interactive tool: open {ui.url} (the View panel shows the cameras)")
            driver = None
            if self.ros2:
                from dyknow.demo.ros2 import CAMERA_TOPIC, TRACK_BINDING, CameraDriver

                driver = CameraDriver(
                    manager.endpoints, Scene(seed=self.seed, epoch_ns=epoch_ns), rate_hz=self.rate_hz, domain=manager.ros2_node().domain
                )
                self.say(f"the robot camera is a ROS 2 node publishing {CAMERA_TOPIC} (sensor_msgs/Image, rmw_zenoh)")
            self.say(f"requesting {REQUEST} from the planner ...")
            t0 = time.monotonic()
            key = manager.request(REQUEST, standby="warm" if self.standby else None, require=[self.requirement] if self.requirement else [])
            if self.ros2:
                manager.spawn("track-to-ros", "track-to-ros", bindings={"in": key, "out": TRACK_BINDING})
                self.say(f"the tracked ball goes back to ROS 2: {TRACK_BINDING}")
            manager.spawn("track-log", "track-log", bindings={"in": key})
            log = manager.unit("track-log")
            assert isinstance(log, TrackLog)
            verdicts: VerdictLog | None = None
            if self.requirement:
                manager.spawn("verdict-log", "verdict-log", bindings={"in": f"{key}/requirements/1"})
                found = manager.unit("verdict-log")
                assert isinstance(found, VerdictLog)
                verdicts = found
            info = next(r for r in manager.requests() if r.key == key)
            self.say(f"planned in {(time.monotonic() - t0) * 1000:.1f} ms: {', '.join(_chain_labels(manager, key))}")
            self.say(f"the tracked position streams on {key}")
            if self.requirement:
                self.say(f"required of it: {self.requirement} (verdicts on {key}/requirements/1)")
            if self.standby:
                self.say("with a warm standby: the next-best configuration runs beside it (--no-standby: without)")
            self.say()
            cpu = _CpuShare()
            battery_trace: list[tuple[float, float]] = []
            self.start_ns = time.time_ns()
            with Client("demo", connect=manager.endpoints) as monitor:  # the battery monitor, elsewhere
                start = time.monotonic()
                rates = _Rates()
                next_show = 0.0
                while (t := time.monotonic() - start) < self.duration_s:
                    level = self.battery.level(t)
                    monitor.session.put("dyknow/measurements/battery", json.dumps({"value": round(level, 3)}))
                    battery_trace.append((t, level))
                    self._print_events(specs_by_label)
                    if t >= next_show:
                        self._show(manager, key, log, scene, rates, t, level, verdicts)
                        next_show += 1.0
                    cpu.sample(any(r.standby for r in manager.requests() if r.key == key))
                    time.sleep(0.25)
            self._print_events(specs_by_label)
            frame = self._annotated_frame(manager, log)
            report = self._report(manager, key, log, scene, battery_trace, frame, info.tag, verdicts, cpu, driver)
            if driver is not None:  # after the report: its publisher gone, the camera's unit fails (as it should)
                driver.close()
            if ui is not None:
                ui.close()
        return report

    def _print_events(self, specs: dict[str, TransformationSpec]) -> None:
        """Print the adaptations not printed yet, each with its recovery time when the stream is
        back; one still recovering is printed anyway before the next status line (which shows
        the new camera already), and its recovery on a line of its own once it comes."""
        with self._events_lock:
            events = list(self.events)
        for e in events:
            if (e.id, e.kind) in self._printed:
                continue
            if e.kind == "adapted":
                done = [x for x in events if x.id == e.id and x.kind == "recovered"]
                self._printed.add((e.id, "adapted"))
                if done:
                    self._printed.add((e.id, "recovered"))
                self.say(self._event_line(done[0] if done else e, specs))
            elif e.kind == "recovered" and e.recovery_ms is not None:
                self._printed.add((e.id, e.kind))
                self.say(f"    (#{e.id}: the stream recovered in {e.recovery_ms:.1f} ms)")
            elif e.kind == "degraded":
                self._printed.add((e.id, e.kind))
                self.say(self._event_line(e, specs))

    def _show(
        self, manager: Manager, key: str, log: TrackLog, scene: Any, rates: _Rates, t: float, level: float, verdicts: VerdictLog | None
    ) -> None:
        chain = _chain(manager, key)
        with log.lock:
            last = log.track[-1] if log.track else None
        camera = next((label for _, label in chain if "camera" in label), "none")
        required = ""
        if verdicts is not None:
            with verdicts.lock:
                held = verdicts.verdicts[-1][1] if verdicts.verdicts else None
                false = sum(1 for _, v in verdicts.verdicts if not v)
            required = f"  requirement: {'holds' if held else 'VIOLATED' if held is False else '(no verdict yet)'}, false in {false} states so far"
        lines = [f"t={t:5.1f}s  battery {level:4.2f}{' (low)' if level < LOW_BATTERY else ''}  camera: {camera}{required}"]
        hops = []
        for name, label in chain:
            try:
                stats = manager.get_statistics(name)
            except UnitError:  # replaced since the chain was read (an adaptation under way): the next line shows the new one
                continue
            ins = [p for p in stats.ports if p.direction == "in"]
            outs = [p for p in stats.ports if p.direction == "out" and p.messages]
            count = outs[0].messages if outs else (ins[0].messages if ins else 0)
            rate = rates.rate(name, count, t)
            hop = f" hop {ins[0].hop.p50_us / 1000:.1f} ms" if ins and ins[0].hop.count else ""
            hops.append(f"{label} [{rate:4.1f}/s{hop}]")
        lines.append("  " + " -> ".join(hops) + f" -> {key}")
        latency = ""
        for unit in manager.get_model().units:  # the request's anchor: the stream as consumers get it
            if unit.label == ANCHOR_LABEL and unit.bindings.get("out") == key:
                try:
                    lat = manager.get_statistics(unit.name).ports[0].latency
                except UnitError:  # (replaced meanwhile)
                    continue
                if lat.count:
                    latency = f"  (camera to key: {lat.p50_us / 1000:.1f} ms p50)"
        if last is not None:
            arrival_ns, origin_ns, p = last
            position = f"ball x={p.get('x', float('nan')):+.2f} y={p.get('y', float('nan')):+.2f} m"
            speed = f" v=({p.get('vx', 0):+.2f},{p.get('vy', 0):+.2f}) m/s"
            truth = ""
            if scene is not None:
                g = scene.ball_at(origin_ns)
                err = math.hypot(p.get("x", 0) - g.x, p.get("y", 0) - g.y) * 100
                truth = f"  truth x={g.x:+.2f} y={g.y:+.2f}  error {err:4.1f} cm"
            age_s = (time.time_ns() - arrival_ns) / 1e9
            if age_s > _STALE_S:  # the tracker dropped the track: the camera has not seen the ball
                state = f"  [track lost {age_s:.1f} s ago: the ball is out of the camera's view]"
            elif p.get("predicted"):
                state = "  [predicted: the ball is not seen right now]"
            else:
                state = ""
            lines.append(f"  {position}{speed}{truth}{latency}{state}")
        else:
            lines.append("  (no track yet)")
        if self.live:
            self._clear_status()
            width = shutil.get_terminal_size((120, 20)).columns
            self.stream.write("\n".join(line[: width - 1] for line in lines) + "\n")
            self.stream.flush()
            self._status_lines = len(lines)
        else:
            self.say("\n".join(lines))

    def _annotated_frame(self, manager: Manager, log: TrackLog) -> Any:
        """Ask the planner for an annotated view of the current camera (it reuses what runs).

        Waits (up to 3 s) for a frame taken while the ball was detected, so the picture shows it.
        """
        chain = _chain(manager, next(r.key for r in manager.requests() if r.tag == REQUEST))
        cam = "top" if any(label == "robot-camera" for _, label in chain) else "ceiling"
        try:
            key = manager.request(f"AnnotatedImage({cam})")
        except Exception as exc:  # a view is a nicety; the demo carries on without it
            self.say(f"(no annotated frame: {exc})")
            return None
        manager.spawn("frame-grab", "frame-grab", bindings={"in": key})
        grab = manager.unit("frame-grab")
        assert isinstance(grab, FrameGrab)
        grab.got.wait(5.0)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            with log.lock:
                seen = bool(log.track) and not log.track[-1][2].get("predicted", True)
            if seen:
                grab.got.clear()
                grab.got.wait(1.0)
                break
            time.sleep(0.05)
        camera = "the robot's camera" if cam == "top" else "the ceiling camera"
        return _captioned(grab.frame, f"dyknow demo, the end of the run: {camera}, as the stream AnnotatedImage({cam}) shows it: "
                          "the ball the detector found circled, with its confidence")  # fmt: skip

    def _report(
        self,
        manager: Manager,
        key: str,
        log: TrackLog,
        scene: Any,
        battery: list[tuple[float, float]],
        frame: Any,
        tag: str,
        verdicts: VerdictLog | None,
        cpu: _CpuShare,
        driver: Any = None,
    ) -> dict[str, Any]:
        from dyknow.demo.report import write_report

        with log.lock:
            track = list(log.track)
        judged: list[tuple[int, bool]] = []
        if verdicts is not None:
            with verdicts.lock:
                judged = list(verdicts.verdicts)
        return write_report(
            self.out_dir,
            start_ns=self.start_ns,
            request=tag,
            key=key,
            track=track,
            scene=scene,
            battery=battery,
            events=list(self.events),
            frame=frame,
            statistics=_statistics(manager),
            say=self.say,
            requirement=self.requirement,
            verdicts=judged,
            standby={"warm": self.standby, **cpu.shares()},
            ros2=driver.summary() if driver is not None else None,
        )


def _captioned(frame: Any, caption: str) -> Any:
    """``frame`` with ``caption`` in a band below it (frame.png says what it shows)."""
    if frame is None:
        return None
    import cv2
    import numpy as np

    height, width = frame.shape[:2]
    words, lines, line = caption.split(), [], ""
    scale = max(0.4, width / 1400)
    for word in words:  # wrap to the frame's width
        trial = f"{line} {word}".strip()
        if cv2.getTextSize(trial, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > width - 16 and line:
            lines.append(line)
            line = word
        else:
            line = trial
    lines.append(line)
    step = int(cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][1] * 1.9)
    band = np.full((step * len(lines) + 10, width, 3), 255, dtype=np.uint8)
    for i, text in enumerate(lines):
        cv2.putText(band, text, (8, step * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, scale, (40, 40, 40), 1, cv2.LINE_AA)
    return np.vstack([frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR), band])


def _explained(e: AdaptationEvent, specs: dict[str, TransformationSpec]) -> str:
    """An adaptation's cause, and for a measurement the constraints it breaks or meets again
    (``battery = 0.386`` alone does not say the robot camera needs ``battery >= 0.25``)."""
    if not e.cause.startswith("measurement "):
        return e.cause
    name, _, raw = e.cause.removeprefix("measurement ").partition(" = ")
    try:
        value: float | str = float(raw.split(",")[0])
    except ValueError:
        return e.cause
    said = []
    for label in dict.fromkeys([*e.old, *e.new]):
        spec = specs.get(label)
        for c in spec.constraints if spec is not None else ():
            if c.measure == name:
                state = "holds again" if c.holds(value) else "broken"
                said.append(f"{label} needs {c.measure} {c.op} {c.value}: {state}")
    return e.cause + (f" ({'; '.join(said)})" if said else "")


def _chain(manager: Manager, key: str) -> list[tuple[str, str]]:
    """The request's units from source to output, (name, label)."""
    request = next((r for r in manager.requests() if r.key == key), None)
    if request is None:
        return []
    order = ["camera", "subsampler", "ball-detector", "localization", "tracker"]
    named = {u.name: u.label for u in manager.get_model().units if u.name in request.units}

    def rank(item: tuple[str, str]) -> int:
        return next((i for i, word in enumerate(order) if word in item[1]), len(order))

    return sorted(named.items(), key=rank)


def _chain_labels(manager: Manager, key: str) -> list[str]:
    return [label for _, label in _chain(manager, key)]


class _UiProcess:
    """``dyknow ui`` as a child process beside the demo (killed on close, or when the demo dies)."""

    def __init__(self, endpoint: str, port: int) -> None:
        argv = [sys.executable, "-m", "dyknow.cli", "ui", "--connect", endpoint, "--port", str(port), "--json"]
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self._finalizer = weakref.finalize(self, _stop, self.proc)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        try:
            self.url = str(json.loads(line)["url"])
        except (ValueError, KeyError) as exc:
            self.close()
            raise RuntimeError(f"dyknow ui did not start (exit code {self.proc.poll()}); is port {port} free?") from exc

    def close(self) -> None:
        """Stop the tool."""
        self._finalizer()


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    if proc.stdout is not None:
        proc.stdout.close()


def run_ball_demo(
    *,
    duration_s: float = 30.0,
    robot_video: str | None = None,
    ceiling_video: str | None = None,
    out_dir: str = "dyknow-demo-report",
    as_json: bool = False,
    ui_port: int | None = None,
    standby: bool = True,
    ros2: bool = False,
) -> int:
    """The ``dyknow demo`` command; returns an exit code."""
    import logging
    import os

    if not os.environ.get("DYKNOW_LOG"):  # the demo prints each adaptation itself (>>>): not twice, as a log warning too
        logging.getLogger("dyknow.adaptation").setLevel(logging.ERROR)
    demo = BallDemo(
        duration_s=duration_s,
        robot_video=robot_video,
        ceiling_video=ceiling_video,
        out_dir=Path(out_dir),
        ui_port=ui_port,
        standby=standby,
        ros2=ros2,
    )
    report = demo.run()
    if as_json:
        print(json.dumps(report["summary"]))
    return 0 if report["summary"]["track_messages"] > 0 else 1


def _statistics(manager: Manager) -> dict[str, Any]:
    """Every running unit's statistics (a unit replaced while they are read is left out)."""
    out: dict[str, Any] = {}
    for unit in manager.get_model().units:
        try:
            out[unit.name] = manager.get_statistics(unit.name).to_dict()
        except UnitError:
            continue
    return out
