"""Clocks that disagree across hosts: the paper's scenario with the robot's wall clock faked.

Three hosts in network namespaces (as in tests/test_hosts.py, on clean links) run a manager each;
the robot's runs under libfaketime with its wall clock 250 ms ahead, 250 ms behind, or running
100 ppm fast (``FAKETIME_DONT_FAKE_MONOTONIC=1``: Zenoh's leases and dyknow's timers run on the
monotonic clock, untouched). The station must show the robot's offset within its stated
uncertainty of the injected one, report no negative hop or age anywhere, and report the
cross-host hop and the ages of the robot's stream as it reports those of the field's camera
(whose clock is the station's) once a cut of the robot's link moved the request there, and so
must a client of the station that corrects its ages by the offsets the station gives it
(``Client.clocks``); the cut and the deadlines must behave as with equal clocks.

The injected offset is known exactly: the robot's manager runs through ``tests.clocked``, which
first prints its wall clock beside the monotonic clock (the machine's, shared by the
namespaces), so the offset at any moment is that line's difference less this process's, grown at
the faked rate. Under ``CI=true`` namespaces and libfaketime are required; elsewhere these tests
skip when they are missing (libfaketime is installed with apt-get when running as root).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dyknow.testing import SCENARIO_HOSTS
from dyknow.testing.hosts import Hosts
from tests.conftest import faked_clock, need_hosts
from tests.test_hosts import BOTTOM, CEILING, ONTOLOGY, PORT, Child, adaptations

pytestmark = pytest.mark.namespaces  # every test here: see CONTRIBUTING.md, 'Tiers'

#: How far the robot's and the field's hop p50s may differ for reasons other than clocks: two
#: cameras on two hosts, on a machine of two cores shared with the rest of the suite. In the
#: first four runs they differed by 3-30 µs (the robot's corrected); the margin leaves room for a
#: loaded machine. Uncorrected, they differ by 250,000 µs. (The ages at the observer are not
#: compared so: they cross every stage, and beside CPU hogs their p50s differed by 1 ms.)
MARGIN_US = 500.0


@pytest.fixture
def clean_hosts() -> Iterator[Hosts]:
    """Three hosts on clean links: a clock exchange's accuracy is the link's evenness."""
    need_hosts()
    with Hosts(["station", "robot", "field"]) as made:
        yield made


@dataclass(frozen=True)
class Skew:
    """A fault of the robot's clock: libfaketime's ``FAKETIME`` and the rate it makes the clock run at."""

    faketime: str
    rate: float


SKEWS = {"ahead": Skew("+0.25", 1.0), "behind": Skew("-0.25", 1.0), "drifting": Skew("+0 x1.0001", 1.0001)}


def injected(clock_line: dict[str, Any], rate: float, at_ns: int) -> int:
    """The robot's clock minus the machine's at ``at_ns`` (the machine's wall clock), from the
    robot's ``clock`` line (see tests/clocked.py), to within half its ``read_ns``."""
    machine = _machine()
    offset_then = clock_line["realtime_ns"] - clock_line["monotonic_ns"] - machine
    then = clock_line["monotonic_ns"] + machine
    return offset_then + round((rate - 1) * (at_ns - then))


def _machine() -> int:
    """The machine's wall clock less its monotonic clock (this process's clocks are the machine's)."""
    readings = []
    for _ in range(5):  # the narrowest of five: a reading this process was preempted in is left out
        before, realtime, after = time.monotonic_ns(), time.time_ns(), time.monotonic_ns()
        readings.append((after - before, realtime - (before + after) // 2))
    return min(readings)[1]


def line_ns(clock_line: dict[str, Any]) -> int:
    """When the robot read its ``clock`` line, on the machine's wall clock."""
    return int(clock_line["monotonic_ns"]) + _machine()


def start(hosts: Hosts, name: str, *extra: str, env: dict[str, str] | None = None) -> tuple[Child, dict[str, Any]]:
    """A manager on host ``name`` (as tests/test_hosts.py starts them), and its clock line."""
    endpoint = f"tcp/{hosts.address(name)}:{PORT}"
    connect = [] if name == "station" else ["--connect", f"tcp/{hosts.address('station')}:{PORT}"]
    child = Child(hosts, name, [
        sys.executable, "-m", "tests.clocked", "manager", "--name", name, "--specs", str(SCENARIO_HOSTS[name]), "--ontology", str(ONTOLOGY),
        "--listen", endpoint, *connect, "--host", f"{name}-host", "--lease-ms", "1000", "--json", *extra,
    ], env)  # fmt: skip
    clock = child.next("clock")
    assert child.next("ready")["endpoints"] == [endpoint]
    return child, clock


def _until(what: str, check: Any, timeout_s: float = 40.0) -> Any:
    """Ask ``check()`` every half second until it returns something (state of other processes, no event to wait on)."""
    deadline = time.monotonic() + timeout_s
    while True:
        found = check()
        if found:
            return found
        assert time.monotonic() < deadline, f"{what} within {timeout_s} s"
        time.sleep(0.5)


def _fill_window() -> None:
    """Let the ports' statistics windows (1,024 messages, 5 s at 200 Hz) fill with what runs now."""
    time.sleep(5.5)


@pytest.mark.parametrize("skew", list(SKEWS.values()), ids=list(SKEWS))
def test_the_station_corrects_the_robots_clock(clean_hosts: Hosts, faketime: Path, skew: Skew) -> None:
    hosts = clean_hosts
    env = faked_clock(faketime, skew.faketime)
    children: list[Child] = []
    try:
        station, _ = start(hosts, "station", "--dwell", "1")
        children.append(station)
        robot, robot_clock = start(hosts, "robot", env=env)
        children.append(robot)
        field, _ = start(hosts, "field")
        children.append(field)
        nominal = {"+0.25": 250_000, "-0.25": -250_000}.get(skew.faketime, 0)
        # what libfaketime was asked for, when the robot started (a drift has grown since, by 1 ms in 10 s:
        # beside CPU hogs the managers took 16 s to start), to within 1 ms and the reading of its clock line
        read_us = robot_clock["read_ns"] / 2000 + 1
        assert abs(injected(robot_clock, skew.rate, line_ns(robot_clock)) / 1000 - nominal) < 1000 + read_us, robot_clock
        observer = Child(
            hosts,
            "station",
            [sys.executable, "-m", "tests.netns_observer", f"tcp/{hosts.address('station')}:{PORT}", "station", "BallTrack(field)"],
        )
        children.append(observer)
        key = observer.next("key")["key"]
        observer.next("camera", camera=BOTTOM)

        def robot_known() -> dict[str, Any] | None:
            clocks = observer.ask("model station")[0]["clocks"]
            found = clocks.get("robot")
            if found is None or found["samples"] < 8 or (skew.rate != 1.0 and found["drift_ppm"] == 0):  # a drift: once a line is fitted
                return None
            return dict(clocks)

        _until("the station's estimate of the robot's clock", robot_known)
        # (the station estimates the robot's clock since the request made them exchange data; the
        # observer looks the station's estimates up once a second: a window with none unknown says it has it)
        _until("the observer to have the robot's clock", lambda: observer.stats()["age_unknown_clock"] == 0)
        observer.stats()  # its window starts now, with the station's offsets (a client's ages: Client.clocks)
        _fill_window()
        robot_window = observer.stats()
        before = time.time_ns()
        clocks = observer.ask("model station")[0]["clocks"]
        after = time.time_ns()
        estimate = clocks["robot"]
        truth = injected(robot_clock, skew.rate, before), injected(robot_clock, skew.rate, after)
        error_us = min(abs(estimate["offset_us"] * 1000 - t) for t in truth) / 1000
        # when, between the two readings, the station took its estimate; how sure the robot's clock line is
        slack_us = abs(truth[1] - truth[0]) / 1000 + robot_clock["read_ns"] / 2000 + 1
        print(f"robot's clock: injected {truth[0] / 1000:.1f} us, estimated {estimate}, error {error_us:.1f} us")
        assert error_us <= estimate["uncertainty_us"] + slack_us, (estimate, truth)
        if skew.rate != 1.0:
            # the fitted drift is as far from the injected 100 ppm as the estimator says it may be: its
            # slope bound (how far the line may tilt, from its exchanges' widths: 206 ppm in a run beside
            # CPU hogs, whose exchanges are wide, where it fitted 188), the growth it carries the offset by
            assert abs(estimate["drift_ppm"] - 100) <= estimate["growth_ppm"], estimate
        assert "field" not in clocks  # no data exchanged with the field yet: its clock is not estimated (on demand, issue 40)

        robot_ports = {p["unit"]: p for p in observer.ask("ports")}
        print(f"with the robot's camera: {robot_ports}")
        for port in robot_ports.values():
            assert port["messages"] > 0 and port["hop_p50_us"] >= 0 and port["latency_p50_us"] >= 0, port  # nothing negative
        assert robot_ports["subsampler(bottom)"]["uncertainty_us"] > 0  # its hop came from the robot's clock, corrected
        states = {u["label"]: u["state"] for u in observer.ask("model robot")[0]["units"]}
        assert states == {"robot-camera": "running"}, states  # its deadline kept: never stalled
        assert [e["cause"] for e in observer.ask("adaptations")] == []  # no stall, no loss: nothing to adapt

        hosts.cut("robot")  # failover as with equal clocks
        observer.next("camera", camera=CEILING, timeout_s=60)
        lost = adaptations(observer, "manager 'robot' was lost", 1)
        assert lost[0]["key"] == key, lost

        def field_known() -> dict[str, Any] | None:  # in use since the failover: estimated from then on
            found = observer.ask("model station")[0]["clocks"].get("field")
            return found if found is not None and found["samples"] >= 8 else None

        field_clock = _until("the station's estimate of the field's clock", field_known)
        assert abs(field_clock["offset_us"]) <= field_clock["uncertainty_us"], field_clock  # equal clocks: 0
        observer.stats()
        _fill_window()
        field_window = observer.stats()
        field_ports = {p["unit"]: p for p in observer.ask("ports")}
        print(f"with the field's camera (equal clocks): {field_ports}")
        for stage in ("subsampler", "ball-detector", "localization"):
            skewed, equal = robot_ports[f"{stage}({'bottom'})"], field_ports[f"{stage}(ceiling)"]
            assert equal["hop_p50_us"] >= 0 and equal["latency_p50_us"] >= 0, equal
            # (the two hops are of two windows 20 s apart: beside CPU hogs one was 277 µs, the other
            # 1,027 µs; the load may double a hop, an uncorrected clock moves it by 250,000 µs)
            bound = skewed["uncertainty_us"] + MARGIN_US + max(skewed["hop_p50_us"], equal["hop_p50_us"])
            assert abs(skewed["hop_p50_us"] - equal["hop_p50_us"]) <= bound, (skewed, equal)
            bound = skewed["uncertainty_us"] + MARGIN_US + max(skewed["latency_p50_us"], equal["latency_p50_us"])
            assert abs(skewed["latency_p50_us"] - equal["latency_p50_us"]) <= bound, (skewed, equal)
        # and the age at a client of the station, corrected by the offsets the station gives it
        print(f"observer's ages: with the robot's camera {robot_window}, with the field's {field_window}")
        assert robot_window["age_unknown_clock"] == 0 and robot_window["by_camera"] == {str(BOTTOM): robot_window["messages"]}
        assert field_window["by_camera"] == {str(CEILING): field_window["messages"]}
        skewed_age, equal_age = robot_window["age_p50_us_corrected"], field_window["age_p50_us_corrected"]
        # an age corrected by an estimate is true within the estimate's uncertainty: never negative beyond it
        assert skewed_age > -robot_window["age_uncertainty_us"] and equal_age > -field_window["age_uncertainty_us"], (
            robot_window,
            field_window,
        )
        # and the correction the client applied is the clock's true offset (injected) within that
        # uncertainty, the drift over half the window and the reading of the robot's clock line (the
        # ages of two windows are not compared: on a busy machine the latency itself differs by ms)
        truth_us = injected(robot_clock, skew.rate, robot_window["middle_ns"]) / 1000
        drift_us = abs(skew.rate - 1) * robot_window["seconds"] * 1e6 / 2
        slack_us = drift_us + robot_clock["read_ns"] / 2000 + 1
        assert abs(robot_window["correction_p50_us"] - truth_us) <= robot_window["age_uncertainty_us"] + slack_us, (robot_window, truth_us)
        assert abs(field_window["correction_p50_us"]) <= field_window["age_uncertainty_us"] + 1, field_window  # equal clocks
        assert all(e["cause"] in ("manager 'robot' was lost",) for e in observer.ask("adaptations") if e["kind"] == "adapted")
    finally:
        for child in reversed(children):
            child.close()
        for child in children:  # what each host said, for a failure's report (pytest shows it then)
            print(f"----- {child.host}\n{child.stderr[-3000:]}")
