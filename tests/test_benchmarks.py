"""Smoke runs of the benchmarks: they still work and keep their output contract (no timing asserts)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO, subprocess_env


def test_chain_benchmark_smoke(tmp_path: Path) -> None:
    out, png = tmp_path / "chain.json", tmp_path / "chain.png"
    result = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "chain.py"), "--smoke", "--hops", "1,3", "--json", str(out), "--plot", str(png)],
        capture_output=True, text=True, timeout=600, env=subprocess_env(), cwd=REPO,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    data = json.loads(out.read_text())
    assert {"cpu", "cores", "python", "zenoh"} <= set(data["machine"])
    rows = data["results"]
    variants = {"dyknow-inproc", "zenoh-session", "dyknow-process", "zenoh-process", "python-call"}
    assert {(r["variant"], r["hops"], r["mode"]) for r in rows} == {
        (v, h, m) for v in variants for h in (1, 3) for m in ("back-to-back", "paced")
    }
    for row in rows:
        assert row["messages"] > 0 and row["rate_hz"] == (0 if row["mode"] == "back-to-back" else 200)
        assert 0 < row["per_hop_median_us"] <= row["last_hop_median_us"] <= row["last_hop_p99_us"]
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert "per-hop p50" in result.stdout
