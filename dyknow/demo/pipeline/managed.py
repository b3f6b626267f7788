"""The pipeline robot managed by dyknow: its modes chosen from the visibility and the thrusters' health.

``python -m dyknow.demo.pipeline.managed [--speed K] [--seed N] [--script FILE] [--mission-s S]``
starts the robot of :mod:`dyknow.demo.pipeline.robot` (a child process, the same options) and a
manager with :data:`PIPELINE_SPEC` (``pipeline.xml`` beside this file) on the same DDS domain
(``--ros2-domain``, else ``ROS_DOMAIN_ID``, else 0). The manager

- takes the measure ``visibility`` from the robot's ``/water_visibility`` (:data:`VISIBILITY_FEED`)
  and each thruster's ``thruster_N`` from the level of its status on ``/diagnostics``, read by a
  unit ``thruster-health(thruster_N)`` (a :class:`~dyknow.ros2.diagnostics.DiagnosticsSource`) of
  the same manager whose output is bound to ``pipeline/thruster_N`` (:func:`thruster_key`);
- requests ``Mode(search)``, ``Mode(follow)`` and ``Mode(motion)`` (:data:`REQUESTS`, the motion
  last: the motion controller's activation starts the mission's clock), so the planner chooses
  the spiral's altitude from the visibility, and normal or degraded motion with thruster
  recovery from the thrusters' health, and the adaptation loop switches as they change.

At the end of the mission it prints the robot's measures beside the no-adaptation baseline's
(:mod:`dyknow.demo.pipeline.baseline`, run after it with the same options; ``--no-baseline`` skips
it), as a table, or as one JSON line with ``--json``: ``{"managed": {...}, "baseline": {...},
"switches": [...]}``. Logs go to stderr.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from dyknow.demo.pipeline import robot
from dyknow.errors import DyKnowError

__all__ = ["PIPELINE_SPEC", "REQUESTS", "THRUSTER_UNITS", "VISIBILITY_FEED", "Mission", "main", "manage", "robot_env", "thruster_key"]

#: The spec dyknow manages the robot with.
PIPELINE_SPEC = Path(__file__).with_name("pipeline.xml")
#: The measure ``visibility``'s stream.
VISIBILITY_FEED = f"ros2dds:{robot.VISIBILITY_TOPIC}?type=std_msgs/msg/Float64#data"
#: The thrusters' health units: label -> the measure it feeds.
THRUSTER_UNITS = {f"thruster-health(thruster_{n})": f"thruster_{n}" for n in range(1, 7)}
#: The requests, in order (the motion last: it starts the mission's clock).
REQUESTS = ("Mode(search)", "Mode(follow)", "Mode(motion)")
_MEASURES = ("time_to_find_s", "distance_inspected_m", "thruster_faults", "thruster_recoveries", "time_stopped_s", "mission_s")


def thruster_key(measure: str) -> str:
    """The Zenoh key the health unit of thruster ``measure`` (``thruster_3``) publishes on."""
    return f"pipeline/{measure}"


def robot_env(domain: int) -> dict[str, str]:
    """The environment of the robot's process: DDS domain ``domain``, Fast DDS, this host only,
    dyknow's Fast DDS profile (unless ``FASTDDS_DEFAULT_PROFILES_FILE`` is set)."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(Path(__file__).parents[2] / "ros2" / "fastdds_profile.xml"))
    return env


class Mission:
    """One run of the robot as a child process (``role`` robot or baseline); a context manager
    that kills it on exit if still running."""

    def __init__(
        self, domain: int, args: Sequence[str], role: str = "robot", *, prefix: Sequence[str] = (), env: Mapping[str, str] | None = None
    ) -> None:
        """``prefix``: what runs the robot's command line (another host's, for example:
        :meth:`dyknow.testing.hosts.Hosts.argv`); ``env``: variables over :func:`robot_env`'s."""
        command = [*prefix, sys.executable, "-m", f"dyknow.demo.pipeline.{role}", *args]
        self.role = role
        self.proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=None, text=True, env={**robot_env(domain), **(env or {})})

    def __enter__(self) -> Mission:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def finish(self, timeout_s: float | None = None, *, terminate: bool = False) -> dict[str, Any]:
        """Its measures (after SIGTERM with ``terminate``); raises DyKnowError if it failed."""
        if terminate and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.close()
            raise DyKnowError(f"the {self.role} did not end within {timeout_s} s", where="dyknow.demo.pipeline.managed") from None
        lines = [line for line in out.splitlines() if line.startswith("{")]
        if self.proc.returncode != 0 or not lines:
            raise DyKnowError(f"the {self.role} exited with {self.proc.returncode} and no measures (its log is above)", where="dyknow.demo.pipeline.managed")
        measures: dict[str, Any] = json.loads(lines[-1])
        return measures

    def close(self) -> None:
        """Kill it if still running."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate(timeout=10)


def manage(manager: Any, *, wait_s: float = 30.0) -> None:
    """Make ``manager`` (with :data:`PIPELINE_SPEC` loaded, on the robot's DDS domain) manage the
    robot: the thrusters' health units and the measures' feeds, then, once the first visibility
    arrived (within ``wait_s``), the requests of :data:`REQUESTS`."""
    for label, measure in THRUSTER_UNITS.items():
        manager.spawn(label, label.replace("(", "-").rstrip(")"), bindings={"out": thruster_key(measure)})
        manager.measure_from(measure, f"{thruster_key(measure)}#level")
    manager.measure_from("visibility", VISIBILITY_FEED)
    deadline = time.monotonic() + wait_s
    while "visibility" not in manager.measurements:
        if time.monotonic() > deadline:
            raise DyKnowError(f"no visibility on {robot.VISIBILITY_TOPIC} within {wait_s} s", where="dyknow.demo.pipeline.managed",
                              expected="the robot running on the manager's DDS domain")  # fmt: skip
        time.sleep(0.05)
    for tag in REQUESTS:
        manager.request(tag)


def _table(managed: Mapping[str, Any], baseline: Mapping[str, Any] | None) -> str:
    rows = [("measure", "dyknow", "baseline")]
    for key in _MEASURES:
        rows.append((key, str(managed.get(key)), "-" if baseline is None else str(baseline.get(key))))
    width = [max(len(r[i]) for r in rows) for i in range(3)]
    return "\n".join("  ".join(cell.ljust(width[i]) for i, cell in enumerate(row)).rstrip() for row in rows)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the robot managed by dyknow, then the baseline; print their measures side by side."""
    parser = robot.argument_parser("python -m dyknow.demo.pipeline.managed")
    parser.description = "The pipeline robot managed by dyknow (pipeline.xml), beside the no-adaptation baseline."
    parser.add_argument("--ros2-domain", type=int, default=None, help="the DDS domain (default ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--dwell-s", type=float, default=2.0, help="the adaptation loop's dwell time, real seconds (default 2)")
    parser.add_argument("--listen", action="append", default=None, metavar="ENDPOINT", help="the manager's Zenoh endpoint (default: the manager's)")
    parser.add_argument("--no-baseline", action="store_true", help="do not run the baseline after")
    parser.add_argument("--json", action="store_true", help="print one JSON line instead of a table")
    options, args = robot.parse_args(argv, parser)
    try:
        options.load_script()
        domain = args.ros2_domain if args.ros2_domain is not None else int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    except (DyKnowError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    robot_args = ["--speed", str(options.speed), "--seed", str(options.seed), "--mission-s", str(options.mission_s)]
    if options.recovery_s is not None:
        robot_args += ["--recovery-s", str(options.recovery_s)]
    if options.script:
        robot_args += ["--script", options.script]
    stopping = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.set())
    from dyknow import Manager

    switches: list[dict[str, Any]] = []
    try:
        with Mission(domain, robot_args) as mission:
            with Manager("pipeline", specs=[PIPELINE_SPEC], ros2_domain=domain, dwell_s=args.dwell_s, listen=args.listen) as manager:
                manager.on_adaptation(lambda e: switches.append({"new": sorted(e.new), "cause": e.cause}) if e.kind == "adapted" else None)
                manage(manager)
                while mission.proc.poll() is None and not stopping.is_set():
                    time.sleep(0.2)
                managed = mission.finish(timeout_s=60, terminate=stopping.is_set())
        baseline = None
        if not args.no_baseline and not stopping.is_set():
            with Mission(domain, robot_args, role="baseline") as run:
                while run.proc.poll() is None and not stopping.is_set():
                    time.sleep(0.2)
                baseline = run.finish(timeout_s=60, terminate=stopping.is_set())
    except DyKnowError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps({"managed": managed, "baseline": baseline, "switches": switches}), flush=True)
    else:
        print(_table(managed, baseline))
        print(f"{len(switches)} mode switch(es) after the first modes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
