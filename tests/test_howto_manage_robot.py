"""The how-to "Manage a ROS 2 robot" (docs/howto/manage-ros2-robot.md), run as a user would: its
command lines, read from the page, through bash, in order, against the real pipeline robot (rclpy
nodes on Fast DDS, a child process) and a real manager process. Only the DDS domain (the page's
7) and the manager's Zenoh endpoint are the test's own, so it runs beside other tests, and a
service call may wait 30 s, not 5, on a loaded machine (a new DDS participant's discovery, beside
CPU hogs, took up to 6 s)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.conftest import REPO, free_port, subprocess_env
from tests.test_pipeline_robot import need_ros_messages
from tests.test_ros2_dds import domain as _domain

pytestmark = pytest.mark.process  # every test here: see CONTRIBUTING.md, 'Tiers'

domain = _domain  # a DDS domain of the test's own
PAGE = REPO / "docs" / "howto" / "manage-ros2-robot.md"


def page_commands() -> list[str]:
    """The page's shell command lines, in order (continuation lines joined, comments dropped)."""
    lines: list[str] = []
    for block in re.findall(r"```sh\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.DOTALL):
        for line in block.replace("\\\n", " ").splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                lines.append(" ".join(line.split()))
    return lines


class Shell:
    """Runs the page's lines as bash would, in the page's environment: the venv's ``python`` and
    ``dyknow`` first on PATH, the exports the page makes (its domain replaced by the test's), every
    ``dyknow`` command given the test's Zenoh endpoint."""

    def __init__(self, domain: int, endpoint: str, cwd: Path) -> None:
        self.env = subprocess_env()
        self.env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + self.env.get("PATH", "")
        self.domain, self.endpoint, self.cwd = domain, endpoint, cwd
        self.background: list[subprocess.Popen[str]] = []
        self.ended: dict[int, str] = {}  # background command (from 1) -> how it ended before it was stopped

    def adapted(self, line: str) -> str:
        line = re.sub(r"\bROS_DOMAIN_ID=\d+", f"ROS_DOMAIN_ID={self.domain}", line)
        if line.startswith("dyknow manager "):
            return line.replace("dyknow manager ", f"dyknow manager --listen {self.endpoint} ", 1)
        if line.startswith("dyknow ros2 call "):
            line += " --timeout 30"
        return line.replace("--manager auv", f"--manager auv --connect {self.endpoint}")

    def export(self, line: str) -> None:
        for pair in self.adapted(line).split()[1:]:
            name, _, value = pair.partition("=")
            self.env[name] = value

    def run(self, line: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
        done = subprocess.run(["bash", "-c", self.adapted(line)], capture_output=True, text=True, env=self.env, cwd=self.cwd, timeout=timeout_s)
        return done

    def ok(self, line: str, timeout_s: float = 60.0) -> str:
        done = self.run(line, timeout_s)
        assert done.returncode == 0, f"{line}\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}\n{self.logs()}"
        return done.stdout

    def start(self, line: str) -> subprocess.Popen[str]:
        """Start ``line`` in the background, its output in a log file of its own (:meth:`logs`)."""
        command = "exec " + self.adapted(line).removesuffix("&").strip()
        log = self.cwd / f"background-{len(self.background) + 1}.log"
        with log.open("w") as out:
            proc = subprocess.Popen(["bash", "-c", command], stdout=out, stderr=subprocess.STDOUT, text=True, env=self.env, cwd=self.cwd,
                                    start_new_session=True)  # fmt: skip
        self.background.append(proc)
        return proc

    def logs(self) -> str:
        """The last lines each background command wrote (for a failure's message), once stopped:
        a manager stuck when asked to stop prints every thread's stack first."""
        self.close()
        tails = []
        for n in range(1, len(self.background) + 1):
            lines = (self.cwd / f"background-{n}.log").read_text(errors="replace").splitlines()
            how = self.ended.get(n, f"stopped, status {self.background[n - 1].returncode}")
            tails.append(f"--- background {n} ({how}; {len(lines)} lines), the last 150:\n" + "\n".join(lines[-150:]))
        return "\n".join(tails)

    def until(self, line: str, seen: Callable[[str], bool], what: str, timeout_s: float = 90.0) -> str:
        """Run ``line`` again until its output shows ``what``."""
        deadline = time.monotonic() + timeout_s
        while True:
            done = self.run(line)
            if done.returncode == 0 and seen(done.stdout):
                return done.stdout
            if time.monotonic() > deadline:
                raise AssertionError(f"{what}: not within {timeout_s} s; {line!r} said {done.stdout[-2000:]} {done.stderr[-2000:]}\n{self.logs()}")
            time.sleep(0.3)

    def close(self) -> None:
        for n, proc in enumerate(self.background, 1):
            if proc.poll() is not None and n not in self.ended:  # (ended by itself: a crash says how here)
                self.ended[n] = f"ended by itself with status {proc.returncode}"
        for proc in reversed(self.background):
            if proc.poll() is None:
                if proc is not self.background[0]:  # (a dyknow manager: its threads' stacks first, in case it is stuck)
                    proc.send_signal(signal.SIGUSR1)
                    time.sleep(0.5)
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=10)


@pytest.fixture
def shell(domain: int, tmp_path: Path) -> Iterator[Shell]:
    need_ros_messages()
    running = Shell(domain, f"tcp/127.0.0.1:{free_port()}", tmp_path)
    try:
        yield running
    finally:
        running.close()


def test_the_page_lists_the_walkthrough_a_user_types() -> None:
    """The premise of the next test: the page's lines, in the order it runs them."""
    lines = page_commands()
    assert lines[0].startswith("export ROS_DOMAIN_ID=7") and lines[1] == "python -m dyknow.demo.pipeline.robot --mission-s 600 --recovery-s 30"
    assert [line.split()[1] for line in lines if line.startswith("dyknow ")] == [
        "ros2", "ros2", "validate", "manager", "request", "request", "request", "model", "ros2", "adaptations", "ros2", "release",
    ]  # fmt: skip
    assert lines[-1] == "python -m dyknow.demo.pipeline.managed --speed 10 --seed 1"  # (run whole by test_pipeline_managed)


def test_the_walkthrough_manages_the_robot_as_the_page_says(shell: Shell) -> None:
    lines = iter(page_commands())
    # 1. the robot
    shell.export(next(lines))
    robot = shell.start(next(lines))
    # 2. look at it: the nodes are up, unconfigured
    shell.export(next(lines))
    listing = next(lines)
    shell.until(listing, lambda out: "/water_visibility" in out and "/spiral_search/change_state" in out, "the robot's topics and services")
    said = shell.ok(next(lines))
    assert "response (" in said and '"label": "unconfigured"' in said, said
    # 3. the spec, checked
    shell.ok(next(lines))
    # 4. a manager beside it, and the thrusters' health units
    manager = shell.start(next(lines))
    shell.ok(next(lines), timeout_s=120)
    # 5. the modes asked for
    for _ in range(3):
        shell.ok(next(lines))
    model = next(lines)
    text = shell.until(model, lambda out: "system f_maintain_motion in mode fd_all_thrusters" in out, "the motion's mode")
    assert re.search(r"system f_generate_search_path in mode fd_spiral_(medium|high) ", text), text  # (0.6, or 0.9 after 40 s)
    assert "system f_follow_pipeline in mode fd_follow_pipeline" in text, text
    # 6. a thruster broken: degraded motion with recovery, then back to normal
    shell.ok(next(lines))
    adaptations = next(lines)
    shell.until(adaptations, lambda out: "-> " in out and "motion.fd_recover_thrusters" in out.split("-> ")[-1], "the switch to recovery")
    degraded = next(lines)
    answer = json.loads(shell.until(degraded, lambda out: json.loads(out)["response"]["values"][0]["bool_value"] is True, "the motion controller degraded"))
    assert answer["response"]["values"][0]["byte_array_value"] == []  # (small arrays listed, as ros2 service call prints them)
    shell.until(model, lambda out: "system f_maintain_motion in mode fd_all_thrusters" in out, "the motion back to normal after the recovery", timeout_s=120)
    # 8. released: the motion's nodes deactivated, not destroyed
    shell.ok(next(lines))
    get_state = "dyknow ros2 call /motion_controller/get_state lifecycle_msgs/srv/GetState --dds --json"  # (the page says it)
    shell.until(get_state, lambda out: json.loads(out)["response"]["current_state"]["label"] == "inactive", "the motion controller deactivated")
    assert next(lines) == "kill %1"
    manager.send_signal(signal.SIGTERM)
    assert manager.wait(timeout=60) == 0, shell.logs()
    robot.send_signal(signal.SIGTERM)
    assert robot.wait(timeout=60) == 0, shell.logs()
    measures = json.loads(next(line for line in (shell.cwd / "background-1.log").read_text().splitlines()[::-1] if line.startswith("{")))
    assert measures["thruster_faults"] >= 1, measures
