"""benchmarks/ros2.py runs (a smoke run: 1 s at 10 Hz per variant; no timing asserts)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, dds_domain, run_group, subprocess_env, undocumented


@pytest.mark.process
def test_ros2_benchmark_smoke(tmp_path: Path) -> None:
    out = tmp_path / "ros2.json"
    result = run_group(
        [sys.executable, str(REPO / "benchmarks" / "ros2.py"), "--smoke", "--json", str(out),
         "--domains", ",".join(str(dds_domain()) for _ in range(4))],  # of this test's own: no parallel test joins them
        timeout=300, env=subprocess_env(), cwd=REPO,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    rows = {r["variant"]: r for r in json.loads(out.read_text())["results"]}
    assert set(rows) == {"dyknow-native", "dyknow-zenoh", "dyknow-dds", "rclpy-dds"}
    for row in rows.values():
        assert row["sent"] > 0 and row["received"] > 0 and row["relayed"] > 0, row
        assert row["latency_p50_ms"] > 0 and row["relay_cpu_ms_per_msg"] >= 0
    assert "target: dyknow's DDS relay CPU/msg within 2x rclpy's" in result.stdout


def test_the_benchmark_is_documented() -> None:
    assert undocumented(REPO / "benchmarks" / "ros2.py") == []


@pytest.mark.process
def test_ros2_cloud_benchmark_smoke(tmp_path: Path) -> None:
    out = tmp_path / "ros2-cloud.json"
    result = run_group(
        [sys.executable, str(REPO / "benchmarks" / "ros2_cloud.py"), "--smoke", "--json", str(out)],
        timeout=300, env=subprocess_env(), cwd=REPO,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    rows = {r["variant"]: r for r in json.loads(out.read_text())["results"]}
    assert set(rows) == {"default-bound", "raised-bound"}
    assert rows["default-bound"]["received_bytes"] == 0  # 17 MiB: over the default bound, dropped
    assert rows["raised-bound"]["cloud_bytes"] <= rows["raised-bound"]["received_bytes"] < rows["raised-bound"]["cloud_bytes"] + 4096
    for row in rows.values():
        assert row["manager_cpu_s"] >= 0 and row["get_model_calls"] >= 3
    assert "target: get_model under 500 ms behind a cloud" in result.stdout


def test_the_cloud_benchmark_is_documented() -> None:
    assert undocumented(REPO / "benchmarks" / "ros2_cloud.py") == []
