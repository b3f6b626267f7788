"""Smoke run of benchmarks/adaptation_vision.py: it still works and keeps its output contract (no timing asserts)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, run_group, subprocess_env, undocumented

SCRIPT = REPO / "benchmarks" / "adaptation_vision.py"
FIGURES = {"p50", "p90", "p99", "max"}
METRICS = {"first_message_ms", "fresh_frame_ms", "adaptation_ms"}


@pytest.mark.process
def test_adaptation_vision_benchmark_smoke(tmp_path: Path) -> None:
    out = tmp_path / "adaptation-vision.json"
    result = run_group(
        [sys.executable, str(SCRIPT), "--smoke", "--json", str(out)],
        timeout=600, env=subprocess_env(), cwd=REPO,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    data = json.loads(out.read_text())
    assert {"cpu", "cores", "python", "zenoh"} <= set(data["machine"])
    assert data["request"] == "BallTrack(field)" and data["rate_hz"] == 20 and data["target_ms"] == 50
    assert set(data["results"]) == {"none", "warm"}
    for mode, row in data["results"].items():
        assert row["cpu_s_per_s"] > 0
        for direction in ("fault", "return"):
            switches = row[direction]
            assert switches["switches"] == data["switches"] == 2
            assert METRICS <= set(switches) and all(set(switches[m]) == FIGURES for m in METRICS)
            assert isinstance(switches["target_met"], bool)
            assert METRICS <= set(row["cold"][direction]) and row["cold"][direction]["processes"] == 2
        # the fault goes onto the standby only with one; the return never can (the battery was low)
        assert row["fault"]["via_standby"] == (2 if mode == "warm" else 0) and row["return"]["via_standby"] == 0
    assert "ceiling-camera" in data["results"]["warm"]["standing_by"] and data["results"]["none"]["standing_by"] == []
    assert "target p99 <= 50 ms (one frame period at 20 Hz)" in result.stdout
    assert "REAL vision pipeline" in result.stdout and "CPU" in result.stdout


def test_the_benchmark_documents_every_public_name() -> None:
    assert undocumented(SCRIPT, REPO / "benchmarks" / "adaptation.py") == []
