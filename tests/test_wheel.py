"""A release a user can install: the wheel, in a fresh venv, outside the checkout, runs the demo.

The wheel is built as ``pip wheel`` builds it for a user; with ``DYKNOW_PURE_PYTHON=1`` (the
hot-path modules as plain Python) to keep the suite short: the compiled build is the one every
other test runs (``make test`` installs it, ``tests/test_build.py`` checks it is current). The
venv gets the wheel's dependencies from the package index, as a user's would.
"""

from __future__ import annotations

import json
import os
import shutil
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


def _source(to: Path) -> Path:
    """The checkout's tracked files, copied to ``to``: what a clean clone holds. The wheel is built
    from them, never in the checkout, whose ``build/`` may hold what an interrupted build left
    (setuptools then fails on a directory that exists) or files of modules since removed."""
    tracked = subprocess.run(["git", "ls-files", "-z"], capture_output=True, check=True, timeout=60, cwd=REPO).stdout.decode()
    for name in filter(None, tracked.split("\0")):
        if (REPO / name).is_file():  # (a file deleted but not yet committed is listed too)
            (to / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, to / name)
    return to


def test_the_wheel_installs_in_a_fresh_venv_and_runs_the_demo_outside_the_checkout(tmp_path: Path) -> None:
    dist, venv, elsewhere = tmp_path / "dist", tmp_path / "venv", tmp_path / "elsewhere"
    elsewhere.mkdir()
    source = _source(tmp_path / "source")
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--wheel-dir", str(dist), str(source)],
        capture_output=True, text=True, timeout=600, env=_clean_env(DYKNOW_PURE_PYTHON="1"), cwd=elsewhere,
    )  # fmt: skip
    assert build.returncode == 0, build.stderr[-3000:]
    (wheel,) = dist.glob("dyknow-*.whl")
    assert wheel.name == f"dyknow-{__version__}-py3-none-any.whl"
    with zipfile.ZipFile(wheel) as built:
        names = built.namelist()
    assert not [name for name in names if name.endswith(".so")]  # pure Python, as asked
    # every module of the package is the checkout's, and no other (a stale build/ adds none here)
    modules = {name for name in names if name.endswith(".py") and name.startswith(("dyknow/", "transformations/"))}
    assert modules == {str(path.relative_to(source)) for path in source.glob("*/**/*.py") if path.parts[len(source.parts)] in ("dyknow", "transformations")}
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
