"""The pipeline robot managed by dyknow (dyknow.demo.pipeline.managed, pipeline.xml): the spec's
thresholds are the world's, a noisy visibility at a threshold switches the real robot's search once
per crossing, and the demo runs a mission beside the baseline."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import Manager
from dyknow.demo.pipeline.baseline import fixed_mode
from dyknow.demo.pipeline.managed import PIPELINE_SPEC, THRUSTER_UNITS, manage
from dyknow.demo.pipeline.world import DETECT_M_PER_VISIBILITY, Script
from dyknow.spec import load_specs
from tests.conftest import REPO, run_group, subprocess_env
from tests.test_adaptation import Events
from tests.test_pipeline_robot import Robot, need_ros_messages, start_robot
from tests.test_ros2_dds import domain as _domain

domain, start_robot = _domain, start_robot  # the fixtures: a DDS domain of the test's own, the robot as a child process


def test_the_spec_chooses_the_spiral_the_visibility_allows_and_normal_motion_while_every_thruster_is_ok() -> None:
    specs = {s.label: s for s in load_specs([PIPELINE_SPEC])}
    assert set(specs) >= {"search.fd_spiral_high", "search.fd_spiral_medium", "search.fd_spiral_low", "follow.fd_follow_pipeline",
                          "motion.fd_all_thrusters", "motion.fd_recover_thrusters", *THRUSTER_UNITS}  # fmt: skip
    for mode in ("fd_spiral_high", "fd_spiral_medium"):  # chosen where the seabed can be seen from the spiral's altitude
        (target,) = fixed_mode({"f_generate_search_path": mode})
        (constraint,) = specs[f"search.{mode}"].constraints
        assert (constraint.measure, constraint.op, constraint.margin) == ("visibility", ">=", 0.05)
        assert constraint.value == target.parameters["spiral_altitude"] / DETECT_M_PER_VISIBILITY
    assert specs["search.fd_spiral_high"].priority < specs["search.fd_spiral_medium"].priority < specs["search.fd_spiral_low"].priority
    assert not specs["search.fd_spiral_low"].constraints
    normal = specs["motion.fd_all_thrusters"]
    assert sorted((c.measure, c.op, c.value) for c in normal.constraints) == [(f"thruster_{n}", "<", 2.0) for n in range(1, 7)]
    assert normal.priority < specs["motion.fd_recover_thrusters"].priority
    params = {p.name: p.value for p in specs["thruster-health(thruster_3)"].params}
    assert params == {"binding": "ros2dds:/diagnostics", "status": "thruster_monitor: thruster_3"}


# The visibility: 0.9, then hovering at the high spiral's threshold 0.75 (the default mission's noise,
# standard deviation 0.02), 0.6 (below it by more than the margin), and hovering at 0.75 again.
HOVER = {"visibility": [[0, 0.9], [4, 0.75], [14, 0.6], [20, 0.75]], "noise": 0.02, "faults": [], "pipeline_y_m": 1000}
SEED = 31


def test_the_hovering_visibility_crosses_the_threshold_often_but_never_leaves_the_margin() -> None:
    """The premise of the next test, for its seed: the noise is the robot's, fixed per tenth of a second."""
    script = Script(seed=SEED, visibility=tuple((float(t), v) for t, v in HOVER["visibility"]), noise=0.02, faults=())
    hovers = [script.visibility_at(k / 10) for k in [*range(40, 140), *range(200, 300)]]
    assert min(hovers) > 0.70  # the high spiral, once running, is left only below 0.75 - 0.05
    assert 30 <= sum(v >= 0.75 for v in hovers[:100]) <= 70 and 30 <= sum(v >= 0.75 for v in hovers[100:]) <= 70  # crossing all the time
    assert all(0.5 < script.visibility_at(k / 10) < 0.7 for k in range(140, 200))


@pytest.mark.process
def test_a_noisy_visibility_at_the_threshold_switches_the_robots_search_once_per_crossing(
    make_manager: Callable[..., Manager], domain: int, start_robot: Callable[..., Robot], tmp_path: Path
) -> None:
    script = tmp_path / "hover.json"
    script.write_text(json.dumps(HOVER))
    robot = start_robot("--speed", "2", "--seed", str(SEED), "--script", str(script), "--mission-s", "30")
    manager = make_manager(specs=[PIPELINE_SPEC], ros2_domain=domain, dwell_s=0.5)
    events = Events(manager)
    manage(manager, wait_s=60)
    measures = robot.finish(timeout_s=120)
    assert measures["mission_s"] == 30.0 and measures["seed"] == SEED
    (search,) = [m for m in manager.get_model().modes if m["system"] == "f_generate_search_path"]
    assert search["mode"] == "fd_spiral_high", search
    switched = [(e.old, e.new) for e in events.events if e.kind == "adapted" and "measurement visibility" in e.cause]
    searches = [(next(o for o in old if o.startswith("search.")), next(n for n in new if n.startswith("search."))) for old, new in switched]
    assert searches == [("search.fd_spiral_high", "search.fd_spiral_medium"), ("search.fd_spiral_medium", "search.fd_spiral_high")], [
        e.to_dict() for e in events.events
    ]


@pytest.mark.process
def test_the_managed_demo_runs_the_mission_and_the_baseline_and_prints_both(domain: int) -> None:
    need_ros_messages()
    result = run_group(
        [sys.executable, "-m", "dyknow.demo.pipeline.managed", "--speed", "20", "--ros2-domain", str(domain),
         "--listen", "tcp/127.0.0.1:0", "--dwell-s", "0.5", "--json"],
        timeout=600, env=subprocess_env(), cwd=REPO,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    (line,) = result.stdout.splitlines()
    out = json.loads(line)
    managed, baseline = out["managed"], out["baseline"]
    assert baseline["thruster_recoveries"] == 0 and baseline["time_stopped_s"] >= 120  # stopped for good at the first fault
    assert managed["time_to_find_s"] is not None and managed["time_to_find_s"] < baseline["time_to_find_s"]  # searched higher
    assert managed["thruster_faults"] == 2 and managed["thruster_recoveries"] == 2 and managed["time_stopped_s"] < 30
    assert managed["distance_inspected_m"] > baseline["distance_inspected_m"]
    # one switch to the recovery per fault that struck in normal motion (its cause is the
    # measurement that made the loop look: often the thruster's); a fault that struck while
    # recovery was still active (at --speed 20 the faults are 3.5 s apart: the switch back may not
    # have come yet under load) recovers with no switch, or with one if the loop saw it
    recoveries = [s["new"] for s in out["switches"] if "motion.fd_recover_thrusters" in s["new"]]
    assert set(map(tuple, recoveries)) <= {("motion.fd_recover_thrusters",)}, json.dumps(out["switches"])
    assert 2 - managed["faults_while_recovering"] <= len(recoveries) <= 2, json.dumps(out)
