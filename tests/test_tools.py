"""The command-line tools as a user runs them: calibrate.py, eval_ball.py, accuracy.py.

These check real-data behaviour: the calibration against OpenCV's reference, and the ball
detector's recall and false detections on the shared videos.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tests.conftest import REPO, subprocess_env, undocumented, wait_until
from transformations.calibration import load_calibration

TOOLS = REPO / "tools"


def run_tool(
    script: str, *args: str | Path, data_dir: Path | None = None, timeout: float = 120
) -> subprocess.CompletedProcess[str]:
    env = subprocess_env()
    if data_dir is not None:
        env["DYKNOW_DATA"] = str(data_dir)
    return subprocess.run(
        [sys.executable, str(TOOLS / script), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        cwd=REPO,
        check=False,
    )


def json_of(proc: subprocess.CompletedProcess[str]) -> Any:
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


# ---------------------------------------------------------------------------------- calibrate.py


@pytest.mark.process
def test_calibrate_matches_the_reference_calibration(data_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "left.yml"
    result = json_of(
        run_tool("calibrate.py", data_dir / "images" / "chessboard", "--pattern", "9x6", "--square", "0.025", "-o", out, "--json")
    )
    assert list(result) == ["images", "boards_found", "rms_px", "camera_matrix", "dist_coeffs"]
    assert (result["images"], result["boards_found"]) == (13, 13)
    assert result["rms_px"] == pytest.approx(0.41, abs=0.03)
    k = np.array(result["camera_matrix"])
    assert k.shape == (3, 3) and len(result["dist_coeffs"]) == 5
    reference = load_calibration(data_dir / "calibration" / "left_intrinsics.yml").camera_matrix
    for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)):
        assert k[i, j] == pytest.approx(reference[i, j], rel=0.02)
    # the file is a regular OpenCV calibration file, and says what the JSON says
    storage = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert np.allclose(storage.getNode("camera_matrix").mat(), k)
    assert storage.getNode("distortion_coefficients").mat().reshape(-1).tolist() == pytest.approx(result["dist_coeffs"])
    assert (storage.getNode("image_width").real(), storage.getNode("image_height").real()) == (640, 480)
    assert storage.getNode("rms").real() == pytest.approx(result["rms_px"])
    storage.release()
    assert load_calibration(out).image_size == (640, 480)


@pytest.mark.process
def test_calibrate_prints_a_summary_without_json(data_dir: Path, tmp_path: Path) -> None:
    proc = run_tool("calibrate.py", data_dir / "images" / "chessboard", "--pattern", "9x6", "-o", tmp_path / "left.xml")
    assert proc.returncode == 0, proc.stderr
    assert "boards found: 13/13" in proc.stdout and "written:" in proc.stdout
    assert load_calibration(tmp_path / "left.xml").camera_matrix[0, 0] == pytest.approx(536, rel=0.02)


def _folder(tmp_path: Path, data_dir: Path, *names: str) -> Path:
    folder = tmp_path / "shots"
    folder.mkdir()
    for name in names:
        shutil.copy(next(data_dir.glob(f"images/*/{name}")), folder / name)
    return folder


@pytest.mark.process
@pytest.mark.parametrize(
    ("setup", "message"),
    [
        (lambda t, d: t / "missing", "no such folder"),
        (lambda t, d: _folder(t, d), "has no images"),
        (lambda t, d: _folder(t, d, "basketball1.png", "basketball2.png"), "no 9x6 chessboard found in any of the 2 images"),
        (lambda t, d: _folder(t, d, "left01.jpg"), None),  # filled with a corrupt image below
    ],
    ids=["missing-folder", "no-images", "no-board", "corrupt-image"],
)
def test_calibrate_errors_are_one_clear_line(
    tmp_path: Path, data_dir: Path, setup: Callable[[Path, Path], Path], message: str | None
) -> None:
    folder = setup(tmp_path, data_dir)
    if message is None:
        (folder / "left02.jpg").write_bytes(b"garbage, not a jpeg" * 10)
        message = f"{folder / 'left02.jpg'}: cannot decode the image"
    proc = run_tool("calibrate.py", folder, "--pattern", "9x6", "-o", tmp_path / "out.yml", "--json")
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith("calibrate.py: error: ") and message in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


@pytest.mark.process
def test_calibrate_refuses_a_bad_pattern(tmp_path: Path, data_dir: Path) -> None:
    proc = run_tool("calibrate.py", data_dir / "images" / "chessboard", "--pattern", "nine", "-o", tmp_path / "o.yml")
    assert proc.returncode == 2 and "expected inner corners as COLSxROWS, such as 9x6" in proc.stderr


# ---------------------------------------------------------------------------------- eval_ball.py


def _check_contract(result: dict[str, Any], frames: int) -> list[dict[str, float]]:
    assert list(result) == ["frames", "detections"]
    assert result["frames"] == frames and len(result["detections"]) == frames
    hits = []
    for i, d in enumerate(result["detections"]):
        if d is not None:
            assert list(d) == ["frame", "x", "y", "radius"] and d["frame"] == i
            hits.append(d)
    return hits


@pytest.mark.process
def test_eval_ball_finds_the_ball_in_sim1(data_dir: Path) -> None:
    hits = _check_contract(json_of(run_tool("eval_ball.py", data_dir / "video" / "sim1.mp4", "--json")), 243)
    assert len(hits) / 243 >= 0.95
    assert all(13 <= d["radius"] <= 17 for d in hits)  # the same ball throughout (radius about 15 px)


@pytest.mark.process
def test_eval_ball_sees_no_ball_in_vtest(data_dir: Path) -> None:
    hits = _check_contract(json_of(run_tool("eval_ball.py", data_dir / "video" / "vtest.avi", "--json")), 795)
    assert len(hits) / 795 <= 0.01


@pytest.mark.process
def test_eval_ball_takes_param_overrides_and_spec_labels(data_dir: Path) -> None:
    video = data_dir / "video" / "ball.mp4"
    default = _check_contract(json_of(run_tool("eval_ball.py", video, "--spec", "ball-detector(ceiling)", "--json")), 60)
    tuned_args = [
        "--param",
        "hsv_lower=25,18,60",
        "--param",
        "hsv_upper=45,255,255",
        "--param",
        "min_circularity=0.3",
        "--param",
        "min_fill=0.3",
    ]
    tuned = _check_contract(json_of(run_tool("eval_ball.py", video, *tuned_args, "--json")), 60)
    assert len(tuned) > 3 * len(default)
    assert all(15 <= d["frame"] <= 45 for d in tuned[1:-1])  # the throw happens in the middle of the clip


@pytest.mark.process
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["video/missing.mp4"], "eval_ball.py: error: {data}/video/missing.mp4: no such video file"),
        (["SOURCES.md"], "OpenCV cannot open it"),
        (["video/ball.mp4", "--param", "hsv_lowr=1,2,3"], ": no param 'hsv_lowr'"),
        (["video/ball.mp4", "--param", "min_fill=2"], "param 'min_fill': got 2.0; expected a number >= 0 and <= 1"),
        (["video/ball.mp4", "--spec", "tracker"], "expected a BallDetector spec"),
    ],
    ids=["missing", "not-a-video", "unknown-param", "bad-param", "not-a-detector"],
)
def test_eval_ball_errors_are_one_clear_line(data_dir: Path, args: list[str], message: str) -> None:
    proc = run_tool("eval_ball.py", str(data_dir / args[0]), *args[1:], "--json")
    assert proc.returncode == 1 and proc.stdout == ""
    assert message.format(data=data_dir) in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


# ---------------------------------------------------------------------------------- accuracy.py


@pytest.mark.process
def test_accuracy_meets_every_target(data_dir: Path) -> None:
    proc = run_tool("accuracy.py", "--json", data_dir=data_dir, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = json.loads(proc.stdout)
    assert all(row["met"] is not False for row in rows)
    by_check = {row["check"]: row for row in rows}
    assert by_check["sim1.mp4 recall (ball in every frame)"]["recall"] >= 0.95
    assert by_check["vtest.avi false detections (no ball)"]["rate"] <= 0.01
    assert sum(row["check"].startswith("synthetic") for row in rows) == 3


# ---------------------------------------------------------------------------------- all tools


def test_every_public_name_of_the_tools_is_documented() -> None:
    assert undocumented(*sorted(TOOLS.glob("*.py"))) == []


# ----------------------------------------------------------------------------------- install.py


def _package(folder: Path, fails: bool = False) -> Path:
    """A small package whose setup.py reports progress as dyknow's does (lines starting ``dyknow:``)."""
    folder.mkdir()
    (folder / "pyproject.toml").write_text('[build-system]\nrequires = ["setuptools"]\nbuild-backend = "setuptools.build_meta"\n'
                                           '[project]\nname = "tiny-progress"\nversion = "1.0"\n')  # fmt: skip
    (folder / "setup.py").write_text(
        "import sys\nfrom setuptools import setup\n"
        "if 'bdist_wheel' in sys.argv or 'editable_wheel' in sys.argv:\n"
        "    print('dyknow: compiling 1 module (a stand-in)', file=sys.stderr, flush=True)\n"
        + ("    raise SystemExit('the compiler broke')\n" if fails else "")
        + "setup(py_modules=[])\n"
    )
    return folder


@pytest.mark.process
@pytest.mark.parametrize("fails", [False, True], ids=["installs", "fails"])
def test_install_shows_the_progress_lines_and_keeps_pips_output(tmp_path: Path, fails: bool) -> None:
    """What make demo runs: pip quiet, but setup.py's dyknow: lines shown with the time, the rest
    in the log, its tail shown and pip's exit status passed on when it fails."""
    package = _package(tmp_path / "pkg", fails)
    log = tmp_path / "install.log"
    target = f"--no-deps --target {tmp_path / 'site'} {package}"
    done = subprocess.run([sys.executable, str(TOOLS / "install.py"), target, "--log", str(log)], capture_output=True, text=True,
                          timeout=300, env=subprocess_env(), cwd=tmp_path)  # fmt: skip
    assert "the first install compiles the hot-path modules with mypyc: about 2 minutes" in done.stdout
    assert re.search(r"^\[\s*\d+ s\] dyknow: compiling 1 module \(a stand-in\)$", done.stdout, re.MULTILINE), done.stdout
    assert "tiny-progress" in log.read_text()
    if fails:
        assert done.returncode != 0 and "the compiler broke" in done.stderr and f"every line is in {log}" in done.stderr
    else:
        assert done.returncode == 0 and "dyknow: installed in" in done.stdout, done.stdout + done.stderr
    skipped = subprocess.run([sys.executable, str(TOOLS / "install.py"), target, "--log", str(log)], capture_output=True, text=True,
                             timeout=300, env={**subprocess_env(), "DYKNOW_PURE_PYTHON": "1"}, cwd=tmp_path)  # fmt: skip
    assert "DYKNOW_PURE_PYTHON is set: the hot-path modules stay interpreted" in skipped.stdout


def test_the_makefile_installs_through_install_py() -> None:
    makefile = (REPO / "Makefile").read_text()
    assert makefile.count("$(BIN)/python tools/install.py") == 3 and "pip install --quiet -e" not in makefile


# -------------------------------------------------------------------------------------- hogs.py

_COUNT_HOGS = """import os, sys
def hog(pid):
    try:
        stat = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return int(stat[1]) == os.getppid() and f"hog-of={os.getppid()}".encode() in open(f"/proc/{pid}/cmdline", "rb").read()
    except OSError:
        return False
print(os.getppid(), sum(hog(p) for p in os.listdir("/proc") if p.isdigit() and int(p) != os.getpid()), flush=True)
"""


def _hogs_of(pid: int) -> int:
    """The hogs still running that the tool of ``pid`` started (orphans included: each names it in its arguments)."""
    alive = 0
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and f"hog-of={pid}".encode() in (entry / "cmdline").read_bytes():
                alive += 1
        except OSError:
            pass
    return alive


@pytest.mark.process
def test_hogs_runs_the_command_beside_busy_processes_and_stops_them() -> None:
    import os

    done = subprocess.run([sys.executable, str(TOOLS / "hogs.py"), "--per-core", "1", "--repeat", "2", "--", sys.executable, "-c", _COUNT_HOGS],
                          capture_output=True, text=True, timeout=60, env=subprocess_env(), cwd=REPO)  # fmt: skip
    assert done.returncode == 0, done.stderr
    counts = [line.split() for line in done.stdout.splitlines() if not line.startswith("hogs:")]
    cores = os.cpu_count() or 1
    assert [int(n) for _, n in counts] == [cores, cores]  # one hog per core beside each run
    assert "hogs: run 2 of 2: exit status 0" in done.stdout and f"({1} per core, {cores} cores)" in done.stdout
    assert _hogs_of(int(counts[0][0])) == 0  # stopped with the tool


@pytest.mark.process
def test_hogs_stops_at_the_first_failed_run_and_passes_its_status_on() -> None:
    done = subprocess.run([sys.executable, str(TOOLS / "hogs.py"), "--per-core", "0", "--repeat", "3", "--", sys.executable, "-c", "raise SystemExit(3)"],
                          capture_output=True, text=True, timeout=60, env=subprocess_env(), cwd=REPO)  # fmt: skip
    assert done.returncode == 3 and "run 1 of 3: exit status 3" in done.stdout and "run 2" not in done.stdout
    nothing = subprocess.run([sys.executable, str(TOOLS / "hogs.py")], capture_output=True, text=True, timeout=60)
    assert nothing.returncode == 2 and "no command given" in nothing.stderr


@pytest.mark.process
def test_hogs_end_with_the_tool_however_it_is_stopped() -> None:
    """A hogs run killed by a signal (a runner stopped, a Ctrl-C that did not reach its cleanup)
    left its hogs busy for every run after it: they now die with the tool."""
    import signal

    tool = subprocess.Popen([sys.executable, str(TOOLS / "hogs.py"), "--per-core", "1", "--", sys.executable, "-c", "import time; time.sleep(60)"],
                            stdout=subprocess.PIPE, text=True, env=subprocess_env(), cwd=REPO, start_new_session=True)  # fmt: skip
    try:
        assert tool.stdout is not None and tool.stdout.readline().startswith("hogs: ")  # (said once its hogs run)
        assert _hogs_of(tool.pid) == (os.cpu_count() or 1)
        tool.send_signal(signal.SIGKILL)  # the tool alone: its command and its hogs go on unless they die with it
        tool.wait(10)
        wait_until(lambda: _hogs_of(tool.pid) == 0, "the hogs to end with the tool")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(tool.pid, signal.SIGKILL)  # (its command, left running)
        if tool.stdout is not None:
            tool.stdout.close()
