"""The pipeline robot as real ROS 2 nodes (rclpy, its default DDS middleware), to be managed from outside.

One process, one multithreaded rclpy executor (a service is answered while the simulation runs):

- ``/water_visibility`` publishes the visibility (``std_msgs/msg/Float64``, in [0, 1]) on
  :data:`VISIBILITY_TOPIC` at 10 Hz;
- ``/thruster_monitor`` publishes :data:`DIAGNOSTICS_TOPIC` (``diagnostic_msgs/msg/DiagnosticArray``,
  one status per thruster named ``thruster_monitor: thruster_N``, level OK or ERROR) at 2 Hz and at
  once on a change, and serves ``/thruster_monitor/fail`` (``std_srvs/srv/SetBool``: ``data: true``
  fails the first working thruster);
- the lifecycle nodes ``/spiral_search`` (parameter ``spiral_altitude``), ``/follow_pipeline``
  (``follow_altitude``), ``/motion_controller`` (``max_speed``, ``degraded``) and
  ``/recover_thrusters``, each also with SUAVE's ``system_mode_marker``; they start unconfigured, and
  only an active node acts (see :mod:`dyknow.demo.pipeline.world` for what each does);
- ``/pipeline_simulation`` runs :class:`~dyknow.demo.pipeline.world.World` and publishes
  :data:`FOUND_TOPIC` (``std_msgs/msg/Bool``, 2 Hz and on a change) and :data:`POSE_TOPIC`
  (``geometry_msgs/msg/PoseStamped``, 10 Hz, z the altitude).

The mission clock starts when ``/motion_controller`` first becomes active and runs ``--speed``
times real time until ``--mission-s`` simulated seconds; then, or on SIGINT or SIGTERM, the robot
prints the mission's measures (:class:`~dyknow.demo.pipeline.world.Measures`) as one JSON line and
exits. Fault messages and service answers are not sped up: they happen in real time.

Unless ``FASTDDS_DEFAULT_PROFILES_FILE`` is set, the robot takes dyknow's Fast DDS profile
(``dyknow/ros2/fastdds_profile.xml``: type propagation off, which Cyclone DDS readers such as
dyknow's need for some types; that file says which). rclpy is imported only by :func:`run` (it comes with
dyknow's test extra, not with dyknow).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dyknow.demo.pipeline.world import STEP_S, THRUSTERS, Controls, Measures, Script, World
from dyknow.errors import DyKnowError

__all__ = [
    "DIAGNOSTICS_TOPIC",
    "FAIL_SERVICE",
    "FOUND_TOPIC",
    "LIFECYCLE_NODES",
    "POSE_TOPIC",
    "VISIBILITY_TOPIC",
    "Options",
    "argument_parser",
    "main",
    "parse_args",
    "run",
    "running",
    "stop",
]

VISIBILITY_TOPIC = "/water_visibility"
DIAGNOSTICS_TOPIC = "/diagnostics"
FOUND_TOPIC = "/pipeline/found"
POSE_TOPIC = "/auv/pose"
FAIL_SERVICE = "/thruster_monitor/fail"
#: The lifecycle nodes and their parameters with their defaults.
LIFECYCLE_NODES: dict[str, dict[str, float | bool | str]] = {
    "spiral_search": {"spiral_altitude": 1.0, "system_mode_marker": "__DEFAULT__"},
    "follow_pipeline": {"follow_altitude": 1.0, "system_mode_marker": "__DEFAULT__"},
    "motion_controller": {"max_speed": 1.0, "degraded": False, "system_mode_marker": "__DEFAULT__"},
    "recover_thrusters": {"system_mode_marker": "__DEFAULT__"},
}
#: Parameters with a range: name -> (lowest, highest).
_RANGES = {"spiral_altitude": (0.1, 10.0), "follow_altitude": (0.1, 10.0), "max_speed": (0.0, 10.0)}
_TICK_S = 0.05  # real seconds between two steps of the simulation


@dataclass(frozen=True, slots=True)
class Options:
    """How to run the robot: the speed-up of the mission's clock, the seed of the noise, the
    script (None: the default one) and the mission's length in simulated seconds."""

    speed: float = 1.0
    seed: int = 0
    script: str | None = None
    mission_s: float = 300.0
    recovery_s: float | None = None  # (None: the script's)

    def load_script(self) -> Script:
        """The mission's script, seeded (its recovery time ``recovery_s`` unless None)."""
        script = Script(seed=self.seed) if self.script is None else Script.load(self.script, seed=self.seed)
        return script if self.recovery_s is None else dataclasses.replace(script, recovery_s=self.recovery_s)


def argument_parser(prog: str = "python -m dyknow.demo.pipeline.robot") -> argparse.ArgumentParser:
    """The command line's parser: ``--speed K --seed N --script FILE --mission-s S --recovery-s S``."""
    parser = argparse.ArgumentParser(prog=prog, description="An underwater robot inspecting a pipeline, as ROS 2 nodes (after SUAVE).")
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per real second (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the visibility's noise (default 0)")
    parser.add_argument("--script", help="a JSON file: visibility steps, noise, thruster faults, ... (default: the built-in mission)")
    parser.add_argument("--mission-s", type=float, default=300.0, help="the mission's length in simulated seconds (default 300)")
    parser.add_argument("--recovery-s", type=float, default=None,
                        help="how long a failed thruster takes to recover while recovery is active, simulated seconds (default: the script's, 3)")  # fmt: skip
    return parser


def parse_args(argv: Sequence[str] | None = None, parser: argparse.ArgumentParser | None = None) -> tuple[Options, argparse.Namespace]:
    """The options of the command line ``argv`` (:func:`argument_parser`'s unless ``parser``),
    and every argument parsed."""
    parser = parser or argument_parser()
    args = parser.parse_args(argv)
    if not 0 < args.speed <= 1000:
        parser.error(f"--speed {args.speed}: expected a speed-up from more than 0 to 1000")
    if not 0 < args.mission_s <= 86400:
        parser.error(f"--mission-s {args.mission_s}: expected from more than 0 to 86400 simulated seconds")
    if args.recovery_s is not None and not 0 <= args.recovery_s <= 3600:
        parser.error(f"--recovery-s {args.recovery_s}: expected from 0 to 3600 simulated seconds")
    return Options(speed=args.speed, seed=args.seed, script=args.script, mission_s=args.mission_s, recovery_s=args.recovery_s), args


class _Mission:
    """The world behind a lock, the mission's clock and the end of the run."""

    def __init__(self, options: Options, script: Script) -> None:
        self.options = options
        self.world = World(script)
        self.lock = threading.Lock()
        self.started_at: float | None = None  # time.monotonic() when the motion controller first became active
        self.done = threading.Event()


def run(options: Options, *, on_ready: Callable[[Any, Any], None] | None = None) -> Measures:
    """Run the robot until the mission ends or :func:`stop` is asked (SIGINT, SIGTERM in
    :func:`main`); returns the measures. ``on_ready(executor, context)`` is called in a thread
    of its own once every node spins (the baseline brings the nodes up from there)."""
    script = options.load_script()  # a bad script fails before any node exists
    mission = _Mission(options, script)
    os.environ.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(Path(__file__).parents[2] / "ros2" / "fastdds_profile.xml"))
    with warnings.catch_warnings():  # ROS 2's parser (lark 0.12) imports the deprecated sre_parse
        warnings.simplefilter("ignore", DeprecationWarning)
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    nodes: list[Any] = []
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    spinner = threading.Thread(target=executor.spin, name="robot-executor", daemon=True)
    try:
        nodes.extend(_nodes(mission, context))
        for node in nodes:
            executor.add_node(node)
        spinner.start()
        nodes[0].get_logger().info(f"robot up: {len(nodes)} nodes, mission {options.mission_s} s at speed {options.speed}")
        if on_ready is not None:
            threading.Thread(target=on_ready, args=(executor, context), name="robot-on-ready", daemon=True).start()
        _RUNNING.append(mission)
        while not mission.done.wait(0.2):
            pass
    finally:
        if mission in _RUNNING:
            _RUNNING.remove(mission)
        executor.shutdown(timeout_sec=5)
        for node in reversed(nodes):
            node.destroy_node()
        spinner.join(5)
        rclpy.shutdown(context=context)
    with mission.lock:
        return mission.world.measures()


_RUNNING: list[_Mission] = []


def stop() -> None:
    """End the running missions now (what SIGINT and SIGTERM do)."""
    for mission in list(_RUNNING):
        mission.done.set()


def running() -> bool:
    """Whether a mission of :func:`run` is running and not asked to stop."""
    return any(not mission.done.is_set() for mission in list(_RUNNING))


def _nodes(mission: _Mission, context: Any) -> list[Any]:
    """The robot's nodes, the simulation first."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseStamped
    from rcl_interfaces.msg import SetParametersResult
    from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn
    from rclpy.node import Node
    from std_msgs.msg import Bool, Float64
    from std_srvs.srv import SetBool

    world, lock = mission.world, mission.lock

    class Managed(LifecycleNode):  # type: ignore[misc]  # (rclpy has no stubs)
        """A lifecycle node of the robot: acts only while active; its parameters checked."""

        def __init__(self, name: str) -> None:
            super().__init__(name, context=context)
            self.active = False
            for param, default in LIFECYCLE_NODES[name].items():
                self.declare_parameter(param, default)
            self.add_on_set_parameters_callback(self._check)

        def _check(self, params: list[Any]) -> Any:
            for p in params:
                low_high = _RANGES.get(p.name)
                if low_high is not None and isinstance(p.value, float) and not low_high[0] <= p.value <= low_high[1]:
                    return SetParametersResult(successful=False, reason=f"{p.name} = {p.value}: expected from {low_high[0]} to {low_high[1]}")
            return SetParametersResult(successful=True)

        def value(self, param: str) -> Any:
            return self.get_parameter(param).value

        def on_configure(self, state: State) -> TransitionCallbackReturn:
            return TransitionCallbackReturn.SUCCESS

        def on_activate(self, state: State) -> TransitionCallbackReturn:
            self.active = True
            self.get_logger().info("active")
            return super().on_activate(state)

        def on_deactivate(self, state: State) -> TransitionCallbackReturn:
            self.active = False
            self.get_logger().info("inactive")
            return super().on_deactivate(state)

        def on_cleanup(self, state: State) -> TransitionCallbackReturn:
            self.active = False
            return TransitionCallbackReturn.SUCCESS

        def on_shutdown(self, state: State) -> TransitionCallbackReturn:
            self.active = False
            return TransitionCallbackReturn.SUCCESS

        def on_error(self, state: State) -> TransitionCallbackReturn:
            self.active = False
            return TransitionCallbackReturn.SUCCESS

    search, follow, motion, recover = (Managed(name) for name in LIFECYCLE_NODES)

    def controls() -> Controls:
        return Controls(
            motion=motion.active,
            max_speed_m_s=float(motion.value("max_speed")),
            degraded=bool(motion.value("degraded")),
            search=search.active,
            spiral_altitude_m=float(search.value("spiral_altitude")),
            follow=follow.active,
            follow_altitude_m=float(follow.value("follow_altitude")),
            recover=recover.active,
        )

    monitor = Node("thruster_monitor", context=context)
    diagnostics = monitor.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)

    def publish_diagnostics() -> None:
        with lock:
            failed = set(world.failed)
        msg = DiagnosticArray()
        msg.header.stamp = monitor.get_clock().now().to_msg()
        for n in range(1, THRUSTERS + 1):
            bad = n in failed
            msg.status.append(
                DiagnosticStatus(
                    level=DiagnosticStatus.ERROR if bad else DiagnosticStatus.OK,
                    name=f"thruster_monitor: thruster_{n}",
                    message="failed" if bad else "OK",
                    hardware_id=f"auv/thruster_{n}",
                    values=[KeyValue(key="failed", value=str(bad).lower())],
                )
            )
        diagnostics.publish(msg)

    def fail(request: Any, response: Any) -> Any:
        if not request.data:
            response.success, response.message = False, "a thruster recovers only while /recover_thrusters is active"
            return response
        recovering = recover.active
        with lock:
            working = [n for n in range(1, THRUSTERS + 1) if n not in world.failed]
            if working:
                world.fail(working[0], recovering=recovering)
        if not working:
            response.success, response.message = False, "every thruster has failed already"
            return response
        publish_diagnostics()  # the fault's message, at once
        monitor.get_logger().warning(f"thruster_{working[0]} failed (asked)")
        response.success, response.message = True, f"thruster_{working[0]} failed"
        return response

    monitor.create_service(SetBool, FAIL_SERVICE, fail)
    monitor.create_timer(0.5, publish_diagnostics)

    sensor = Node("water_visibility", context=context)
    visibility = sensor.create_publisher(Float64, VISIBILITY_TOPIC, 10)

    def publish_visibility() -> None:
        with lock:
            value = world.visibility
        visibility.publish(Float64(data=value))

    sensor.create_timer(0.1, publish_visibility)

    simulation = Node("pipeline_simulation", context=context)
    found_pub = simulation.create_publisher(Bool, FOUND_TOPIC, 10)
    pose_pub = simulation.create_publisher(PoseStamped, POSE_TOPIC, 10)
    options = mission.options

    def tick() -> None:
        now = time.monotonic()
        given = controls()
        with lock:
            if mission.started_at is None and given.motion:
                mission.started_at = now
                simulation.get_logger().info("mission started")
            if mission.started_at is None:
                return
            was_found = world.found
            target = min(options.mission_s, (now - mission.started_at) * options.speed)
            changes = world.advance(given, target)
            found = world.found
            ended = world.t_s + STEP_S > options.mission_s + 1e-9  # no whole step left
        if changes:
            publish_diagnostics()
            for n, failed in changes:
                simulation.get_logger().warning(f"thruster_{n} {'failed' if failed else 'recovered'}")
        if found != was_found:
            found_pub.publish(Bool(data=found))
        if ended:
            mission.done.set()

    def publish_pose() -> None:
        msg = PoseStamped()
        msg.header.stamp = simulation.get_clock().now().to_msg()
        msg.header.frame_id = "seabed"
        with lock:
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = world.x_m, world.y_m, world.altitude_m
        pose_pub.publish(msg)

    def publish_found() -> None:
        with lock:
            found = world.found
        found_pub.publish(Bool(data=found))

    simulation.create_timer(_TICK_S, tick)
    simulation.create_timer(0.1, publish_pose)
    simulation.create_timer(0.5, publish_found)
    return [simulation, sensor, monitor, search, follow, motion, recover]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the robot; prints the measures as one JSON line at the end."""
    options, _ = parse_args(argv)
    try:
        options.load_script()
    except DyKnowError as exc:  # a bad script: say which file and field, and run nothing
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop())
    measures = run(options)
    print(json.dumps(measures.to_dict()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
