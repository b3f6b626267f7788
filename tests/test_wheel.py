"""A release a user can install: the wheel, in a fresh venv, outside the checkout, runs the demo.

The wheel is built as ``pip wheel`` builds it for a user; with ``DYKNOW_PURE_PYTHON=1`` (the
hot-path modules as plain Python) to keep the suite short: the compiled build is the one every
other test runs (``make test`` installs it, ``tests/test_build.py`` checks it is current). The
venv gets the wheel's dependencies from the package index, as a user's would.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from dyknow import __version__
from tests.conftest import REPO

pytestmark = pytest.mark.process  # every test here: see CONTRIBUTING.md, 'Tiers'


def _clean_env(**extra: str) -> dict[str, str]:
    """This environment without anything that points into the checkout."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DYKNOW_SPECS", "VIRTUAL_ENV")}
    return {**env, **extra}


def test_the_wheel_installs_in_a_fresh_venv_and_runs_the_demo_outside_the_checkout(tmp_path: Path) -> None:
    dist, venv, elsewhere = tmp_path / "dist", tmp_path / "venv", tmp_path / "elsewhere"
    elsewhere.mkdir()
    compiled = {path: path.stat().st_mtime_ns for path in (REPO / "dyknow").rglob("*.so")}  # the checkout's own install's
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--wheel-dir", str(dist), str(REPO)],
        capture_output=True, text=True, timeout=600, env=_clean_env(DYKNOW_PURE_PYTHON="1"), cwd=elsewhere,
    )  # fmt: skip
    assert build.returncode == 0, build.stderr[-3000:]
    (wheel,) = dist.glob("dyknow-*.whl")
    assert wheel.name == f"dyknow-{__version__}-py3-none-any.whl"
    with zipfile.ZipFile(wheel) as built:
        assert not [name for name in built.namelist() if name.endswith(".so")]  # pure: no compiled copy of the checkout's
    # building a pure wheel leaves the checkout's compiled modules alone (an editable install's)
    assert {path: path.stat().st_mtime_ns for path in (REPO / "dyknow").rglob("*.so")} == compiled
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120, env=_clean_env())
    python, dyknow = venv / "bin" / "python", venv / "bin" / "dyknow"
    install = subprocess.run(
        [str(python), "-m", "pip", "install", "--quiet", str(wheel)],
        capture_output=True,
        text=True,
        timeout=900,
        env=_clean_env(),
        cwd=elsewhere,
    )
    assert install.returncode == 0, install.stderr[-3000:]

    def run(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        return subprocess.run(list(argv), capture_output=True, text=True, timeout=timeout, env=_clean_env(), cwd=elsewhere)

    where = run(str(python), "-c", "import dyknow, dyknow.resources as r; print(dyknow.__file__); print(r.specs_dir())")
    module, specs = where.stdout.split()
    assert Path(module).is_relative_to(venv) and Path(specs) == venv / "share" / "dyknow" / "specs", where.stdout
    assert run(str(dyknow), "--version").stdout.strip() == f"dyknow {__version__}"
    assert run(str(python), "-m", "dyknow", "--version").stdout.strip() == f"dyknow {__version__}"
    license_files = run(str(python), "-c", "import importlib.metadata as m; print(m.metadata('dyknow')['License-Expression'])")
    assert license_files.stdout.strip() == "Apache-2.0"
    demo = run(str(dyknow), "demo", "--duration", "6", "--json", timeout=180)
    assert demo.returncode == 0, demo.stderr[-3000:]
    summary = json.loads(demo.stdout.splitlines()[-1])
    assert summary["track_messages"] > 0 and summary["key"] == "dyknow/demo/requests/BallTrack(field)"
    assert (elsewhere / "dyknow-demo-report" / "report.json").is_file()
