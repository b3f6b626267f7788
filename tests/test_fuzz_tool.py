"""tools/fuzz.py as a release engineer runs it: its output contract and exit status (no timings)."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import strategies as st

from dyknow.testing.fuzzing import TARGETS, Property
from tests.test_tools import run_tool
from tools import fuzz


@pytest.mark.process
def test_every_target_reports_its_examples_as_json(data_dir: Path) -> None:
    proc = run_tool("fuzz.py", "--seconds", "3", "--json", data_dir=data_dir, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    reports = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [r["target"] for r in reports] == list(TARGETS)
    for report in reports:
        assert set(report) == {"target", "examples", "elapsed_s", "ok", "failure"}
        assert report["ok"] is True and report["failure"] is None and report["examples"] > 0, report


@pytest.mark.process
def test_the_text_report_has_a_line_per_target_and_a_summary() -> None:
    proc = run_tool("fuzz.py", "--minutes", "0.01", "--targets", "tags,request")
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert [line.split()[0] for line in lines[:2]] == ["tags", "request"]
    assert all(line.split()[2] == "examples" and line.endswith(" ok") for line in lines[:2]), lines
    assert lines[2:] == ["all 2 targets passed"]


@pytest.mark.process
def test_unknown_targets_are_a_usage_error() -> None:
    proc = run_tool("fuzz.py", "--targets", "spec,teleport")
    assert proc.returncode == 2 and "expected a comma-separated list of spec, tags, request, service, mcap" in proc.stderr


def test_a_failure_shows_the_minimal_example_and_fails_the_run(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    def too_big(number: int) -> None:
        assert number < 1000, f"{number} is too big"

    def failing(target: str, data: Path, workdir: Path) -> Iterator[Property]:
        yield Property(target, st.integers(), too_big)

    monkeypatch.setattr(fuzz, "properties", contextlib.contextmanager(failing))
    assert fuzz.main(["--seconds", "1", "--targets", "tags"]) == 1
    out = capsys.readouterr().out
    assert "FAILED" in out.splitlines()[0]
    assert "tags(\n        example=1000,\n    )" in out and "AssertionError: 1000 is too big" in out
    assert out.splitlines()[-1] == "1 of 1 targets failed: tags"
