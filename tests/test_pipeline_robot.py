"""The pipeline robot (dyknow.demo.pipeline): its simulation and mode file in this process, and the
robot itself as a child process of real rclpy nodes on Fast DDS, driven and read from dyknow's DDS
participant (Cyclone DDS) as a managing system would: lifecycle and parameter services, the
visibility, /diagnostics, a thruster's fault and recovery, the no-adaptation baseline's measures."""

from __future__ import annotations

import importlib.util
import json
import queue
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from dyknow.demo.pipeline import MODES_FILE
from dyknow.demo.pipeline.baseline import BASELINE_MODES, NodeTarget, fixed_mode
from dyknow.demo.pipeline.robot import LIFECYCLE_NODES
from dyknow.demo.pipeline.world import Controls, Script, ScriptError, World
from dyknow.errors import ServiceError
from dyknow.ros2.dds import FASTDDS_PROFILE
from tests.conftest import REPO, subprocess_env, under_ci
from tests.test_ros2_dds import domain as _domain

domain = _domain  # a DDS domain of the test's own

SET_BOOL = "bool data\n---\nbool success\nstring message\n"  # std_srvs/srv/SetBool


def yaml_load(path: Path) -> Any:
    yaml = pytest.importorskip("yaml")  # PyYAML comes with rclpy
    return yaml.safe_load(path.read_text(encoding="utf-8"))


# ------------------------------------------------------------------------------------ in this process


def test_the_simulation_is_deterministic_under_a_seed_and_searching_high_finds_sooner() -> None:
    def mission(altitude: float, seed: int) -> dict[str, Any]:
        world = World(Script(seed=seed, faults=((100.0, 2),), visibility=((0.0, 0.9),), pipeline_y_m=6.0))
        world.advance(Controls(motion=True, search=True, spiral_altitude_m=altitude, follow=True), 150.0)
        return world.measures().to_dict()

    assert mission(1.0, 7) == mission(1.0, 7)
    low, high = mission(1.0, 7), mission(3.0, 7)
    assert low["time_to_find_s"] is not None and high["time_to_find_s"] is not None
    assert high["time_to_find_s"] < low["time_to_find_s"]
    assert low["thruster_faults"] == 1 and low["thruster_recoveries"] == 0 and low["time_stopped_s"] == 50.0
    assert Script(seed=1).visibility_at(12.3) == Script(seed=1).visibility_at(12.3) != Script(seed=2).visibility_at(12.3)


def test_the_pipeline_is_seen_only_from_an_altitude_the_visibility_allows() -> None:
    murky = World(Script(faults=(), visibility=((0.0, 0.3),), noise=0.0))  # the seabed is seen from 1.2 m at most
    murky.advance(Controls(motion=True, search=True, spiral_altitude_m=3.0), 300.0)
    assert murky.measures().time_to_find_s is None
    murky.advance(Controls(motion=True, search=True, spiral_altitude_m=1.0), 600.0)
    assert murky.measures().time_to_find_s is not None


def test_a_failed_thruster_stops_the_robot_unless_degraded_and_recovers_only_while_recovery_is_active() -> None:
    world = World(Script(faults=((1.0, 4),), recovery_s=2.0))
    assert world.advance(Controls(motion=True, search=True), 5.0) == [(4, True)]
    assert world.stopped_s == pytest.approx(4.0) and world.failed == {4}
    x = world.x_m
    world.advance(Controls(motion=True, search=True, degraded=True), 6.0)
    assert world.x_m != x and world.failed == {4}  # thrust reallocated: it moves, the thruster still failed
    assert world.advance(Controls(motion=True, search=True, recover=True), 8.0) == [(4, False)]
    assert world.measures().thruster_recoveries == 1 and world.measures().faults_while_recovering == 0


def test_a_fault_while_recovery_is_active_recovers_with_no_switch_and_is_counted() -> None:
    """What the managed demo's test tells apart: a fault that strikes while recovery is still
    active (the managing system has not switched back yet) needs no switch of its own."""
    world = World(Script(faults=((1.0, 4), (3.0, 2)), recovery_s=0.5))
    assert world.advance(Controls(motion=True, search=True, recover=True), 2.0) == [(4, True), (4, False)]
    assert world.advance(Controls(motion=True, search=True, recover=True), 4.0) == [(2, True), (2, False)]
    assert world.faults_while_recovering == 2 and world.measures().thruster_recoveries == 2
    world = World(Script(faults=((1.0, 4),)))
    world.advance(Controls(motion=True, search=True), 2.0)
    assert world.fail(2, recovering=True) and not world.fail(2, recovering=True)  # asked twice: one fault
    assert (world.faults, world.faults_while_recovering) == (2, 1)


def test_a_script_file_is_read_and_a_bad_one_names_the_file_and_field(tmp_path: Path) -> None:
    good = tmp_path / "mission.json"
    good.write_text(json.dumps({"visibility": [[10, 0.2], [0, 0.8]], "faults": [[5, 6]], "pipeline_y_m": 4}))
    script = Script.load(good, seed=3)
    assert script.visibility == ((0.0, 0.8), (10.0, 0.2)) and script.faults == ((5.0, 6),) and script.seed == 3
    bad = tmp_path / "bad.json"
    for data, field in (({"faults": [[5, 7]]}, "faults[0]"), ({"speed": 2}, "unknown field 'speed'"), ({"noise": "x"}, "noise")):
        bad.write_text(json.dumps(data))
        with pytest.raises(ScriptError, match=rf"bad.json: .*{field.replace('[', '.').replace(']', '.')}"):
            Script.load(bad)


def test_the_mode_file_is_suaves_format_with_default_first_and_the_robots_parameters() -> None:
    modes = yaml_load(MODES_FILE)
    systems = {k: v["ros__parameters"] for k, v in modes.items() if v["ros__parameters"]["type"] == "system"}
    assert list(systems) == ["f_generate_search_path", "f_follow_pipeline", "f_maintain_motion"]
    for name, body in {**systems, **{k: v["ros__parameters"] for k, v in modes.items()}}.items():
        assert next(iter(body["modes"])) == "__DEFAULT__", name
    for system in systems.values():
        assert set(system["parts"].split()) == {part for mode in system["modes"].values() for part in mode}
        assert all(part in LIFECYCLE_NODES for part in system["parts"].split())
    for node, defaults in LIFECYCLE_NODES.items():  # every parameter a mode sets is declared, of its type
        for mode in modes[node]["ros__parameters"]["modes"].values():
            for param, value in mode["ros__parameters"].items():
                assert type(value) is type(defaults[param]), (node, param)
    altitude = {m: fixed_mode({"f_generate_search_path": m})[0].parameters["spiral_altitude"] for m in ("fd_spiral_low", "fd_spiral_medium", "fd_spiral_high")}
    assert altitude == {"fd_spiral_low": 1.0, "fd_spiral_medium": 2.0, "fd_spiral_high": 3.0}
    assert fixed_mode({"f_maintain_motion": "fd_recover_thrusters"}) == [
        NodeTarget("motion_controller", True, {"max_speed": 0.5, "degraded": True}),
        NodeTarget("recover_thrusters", True, {"system_mode_marker": "__DEFAULT__"}),
    ]
    assert [t.node for t in fixed_mode(BASELINE_MODES) if t.active] == ["spiral_search", "follow_pipeline", "motion_controller"]
    with pytest.raises(Exception, match="system 'f_follow_pipeline' has no mode 'fd_fast'; expected one of __DEFAULT__"):
        fixed_mode({"f_follow_pipeline": "fd_fast"})


# ------------------------------------------------------------------------------ the robot, as ROS 2 nodes


def need_ros_messages() -> None:
    """The robot needs diagnostic_msgs and std_srvs for rclpy (dyknow's test extra): required
    under CI, else the test is skipped saying so."""
    missing = [pkg for pkg in ("rclpy", "diagnostic_msgs", "std_srvs") if importlib.util.find_spec(pkg) is None]
    if missing:
        why = f"the pipeline robot needs {', '.join(missing)} for rclpy: pip install -e '.[test]'"
        if under_ci():
            pytest.fail(why)
        pytest.skip(why)


class Robot:
    """``python -m dyknow.demo.pipeline.ROLE ARGS`` in a child process on DDS domain ``domain``."""

    def __init__(self, domain: int, *args: str, role: str = "robot") -> None:
        need_ros_messages()
        env = subprocess_env()
        env.update(
            ROS_DOMAIN_ID=str(domain),
            ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
            RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
            FASTDDS_DEFAULT_PROFILES_FILE=str(FASTDDS_PROFILE),
        )
        command = [sys.executable, "-m", f"dyknow.demo.pipeline.{role}", *args]
        self.proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)

    def finish(self, timeout_s: float = 60.0, *, terminate: bool = False) -> dict[str, Any]:
        """The measures it prints at the end (after SIGTERM with ``terminate``)."""
        if terminate:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, err = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate(timeout=10)
            raise AssertionError(f"the robot did not end within {timeout_s} s: {err[-2000:]}") from None
        assert self.proc.returncode == 0, err[-2000:]
        lines = out.splitlines()
        assert len(lines) == 1, out  # the measures, one JSON line, nothing else on stdout
        measures: dict[str, Any] = json.loads(lines[0])
        return measures

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate(timeout=10)


@pytest.fixture
def start_robot(domain: int) -> Iterator[Callable[..., Robot]]:
    started: list[Robot] = []

    def start(*args: str, role: str = "robot") -> Robot:
        robot = Robot(domain, *args, role=role)
        started.append(robot)
        return robot

    yield start
    for robot in started:
        robot.close()


@pytest.fixture
def participant(domain: int) -> Iterator[Any]:
    from dyknow.ros2.dds import DdsNode

    with DdsNode(domain=domain) as node:
        node.types.register_srv("std_srvs/srv/SetBool", SET_BOOL)
        yield node


def received(participant: Any, topic: str, ros_type: str) -> queue.Queue[Any]:
    """The messages of ``topic`` as they arrive."""
    got: queue.Queue[Any] = queue.Queue()
    participant.create_subscription(topic, ros_type, lambda r: got.put(r.message))
    return got


def levels(got: queue.Queue[Any], until: Callable[[dict[str, int]], bool], timeout_s: float = 30.0) -> dict[str, int]:
    """The thrusters' levels of the first /diagnostics message for which ``until`` holds."""
    while True:
        try:
            msg = got.get(timeout=timeout_s)
        except queue.Empty:
            raise AssertionError("no /diagnostics message as awaited") from None
        found = {status.name: int(status.level) for status in msg.status}
        if until(found):
            return found


@pytest.mark.process
def test_the_robots_lifecycle_nodes_answer_a_managing_client_and_it_prints_measures_on_sigterm(
    start_robot: Callable[..., Robot], participant: Any
) -> None:
    from dyknow.ros2.lifecycle import NodeLifecycle

    robot = start_robot("--speed", "10")
    with NodeLifecycle(participant, "/spiral_search", timeout_s=30) as search:
        assert search.state() == (1, "unconfigured")
        assert search.bring_up({"spiral_altitude": 2.0}) == ["set 1 parameter(s)", "configure", "activate"]
        assert search.state(timeout_s=10) == (3, "active")
        got = participant.create_client("/spiral_search/get_parameters", "rcl_interfaces/srv/GetParameters").call(
            {"names": ["spiral_altitude"]}, timeout_s=10
        )
        assert got.values[0].double_value == 2.0
        with pytest.raises(ServiceError, match=r"refused the parameter spiral_altitude=50.0: spiral_altitude = 50.0: expected from 0.1 to 10.0"):
            search.set_parameters({"spiral_altitude": 50.0})
        with pytest.raises(ServiceError, match="refused the parameter spiral_altitude='high'"):
            search.set_parameters({"spiral_altitude": "high"})  # a string for a double
        assert search.bring_down() and search.state(timeout_s=10) == (2, "inactive")
    with NodeLifecycle(participant, "/recover_thrusters", timeout_s=30) as recover:
        assert recover.state() == (1, "unconfigured")
    measures = robot.finish(terminate=True)  # the motion controller never came up: no mission
    assert measures == {
        "time_to_find_s": None,
        "distance_inspected_m": 0.0,
        "thruster_faults": 0,
        "thruster_recoveries": 0,
        "time_stopped_s": 0.0,
        "mission_s": 0.0,
        "seed": 0,
        "faults_while_recovering": 0,
    }


@pytest.mark.process
def test_the_visibility_and_the_thrusters_diagnostics_arrive_typed(start_robot: Callable[..., Robot], participant: Any) -> None:
    visibility = received(participant, "/water_visibility", "std_msgs/msg/Float64")
    diagnostics = received(participant, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    start_robot("--speed", "10")
    first = [visibility.get(timeout=30).data for _ in range(3)]
    assert all(0.0 <= v <= 1.0 for v in first)
    msg = diagnostics.get(timeout=30)
    assert [s.name for s in msg.status] == [f"thruster_monitor: thruster_{n}" for n in range(1, 7)]
    assert {int(s.level) for s in msg.status} == {0} and msg.status[0].hardware_id == "auv/thruster_1"


@pytest.mark.process
def test_a_thruster_fault_scripted_or_asked_is_an_error_and_recovery_an_ok(
    start_robot: Callable[..., Robot], participant: Any, tmp_path: Path
) -> None:
    from dyknow.ros2.lifecycle import NodeLifecycle

    script = tmp_path / "faults.json"
    script.write_text(json.dumps({"faults": [[1.0, 2]], "recovery_s": 1.0}))
    diagnostics = received(participant, "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    robot = start_robot("--speed", "10", "--script", str(script))
    with NodeLifecycle(participant, "/motion_controller", timeout_s=30) as motion:
        motion.bring_up()  # the mission's clock starts: thruster 2 fails 1 simulated second later
    failed = levels(diagnostics, lambda found: found["thruster_monitor: thruster_2"] == 2)
    assert sorted(name for name, level in failed.items() if level) == ["thruster_monitor: thruster_2"]
    answer = participant.create_client("/thruster_monitor/fail", "std_srvs/srv/SetBool").call({"data": True}, timeout_s=30)
    assert answer.success and answer.message == "thruster_1 failed"
    levels(diagnostics, lambda found: found["thruster_monitor: thruster_1"] == 2 and found["thruster_monitor: thruster_2"] == 2)
    with NodeLifecycle(participant, "/recover_thrusters", timeout_s=30) as recover:
        recover.bring_up()
    levels(diagnostics, lambda found: set(found.values()) == {0})
    measures = robot.finish(terminate=True)
    assert (measures["thruster_faults"], measures["thruster_recoveries"]) == (2, 2)


@pytest.mark.process
def test_the_baseline_runs_a_short_accelerated_mission_in_its_fixed_mode_and_prints_the_measures(
    start_robot: Callable[..., Robot], tmp_path: Path
) -> None:
    mission = {"visibility": [[0, 0.9]], "noise": 0.0, "pipeline_y_m": 3.0, "faults": [[50, 4]]}
    script = tmp_path / "short.json"
    script.write_text(json.dumps(mission))
    robot = start_robot("--speed", "20", "--mission-s", "60", "--script", str(script), role="baseline")
    measures = robot.finish()
    # the same mission simulated here, in the baseline's fixed mode: what rclpy ran is the simulation's
    world = World(Script.from_dict(mission))
    world.advance(Controls(motion=True, search=True, spiral_altitude_m=1.0, follow=True, follow_altitude_m=1.0), 60.0)
    assert measures == world.measures().to_dict()
    assert measures["time_to_find_s"] is not None and measures["distance_inspected_m"] > 0
    assert measures["thruster_faults"] == 1 and measures["thruster_recoveries"] == 0 and measures["time_stopped_s"] == 10.0


def test_the_readmes_baseline_measures_are_the_default_missions() -> None:
    readme = (MODES_FILE.parent / "README.md").read_text(encoding="utf-8")
    shown = json.loads(next(line for line in readme.splitlines() if line.startswith('{"time_to_find_s"')))
    world = World(Script())
    world.advance(Controls(motion=True, search=True, spiral_altitude_m=1.0, follow=True, follow_altitude_m=1.0), 300.0)
    assert shown == world.measures().to_dict()


def test_bad_input_is_refused_before_any_node_exists(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from dyknow.demo.pipeline import baseline, robot

    bad = tmp_path / "mission.json"
    bad.write_text('{"faults": [[10, 9]]}')
    assert robot.main(["--script", str(bad)]) == 2
    assert "mission.json: faults[0] = [10, 9]; expected [time_s >= 0, a thruster from 1 to 6]" in capsys.readouterr().err
    assert baseline.main(["--mode", "f_nope=fd_x"]) == 2
    assert "--mode f_nope=fd_x; expected SYSTEM=MODE with SYSTEM one of f_generate_search_path" in capsys.readouterr().err
    assert baseline.main(["--mode", "f_maintain_motion=fd_fast"]) == 2
    assert "system 'f_maintain_motion' has no mode 'fd_fast'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        robot.main(["--speed", "0"])
    assert "--speed 0.0: expected a speed-up" in capsys.readouterr().err
