"""The README says only what is true: its offline commands and its unit example run as written."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, run_cli, subprocess_env

README = (REPO / "README.md").read_text()


def _blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README, re.DOTALL)


def _offline_commands() -> list[tuple[str, str]]:
    """``dyknow validate|expand|plan`` lines of the README's sh blocks, with their comment."""
    commands = []
    for block in _blocks("sh"):
        for line in block.replace("\\\n", " ").splitlines():
            command, _, comment = line.partition("  #")
            words = shlex.split(command)
            if words[:1] == ["dyknow"] and words[1:2] and words[1] in ("validate", "expand", "plan"):
                commands.append((" ".join(words[1:]), comment.strip()))
    return commands


def test_the_readme_has_offline_commands() -> None:
    assert {c.split()[0] for c, _ in _offline_commands()} == {"validate", "expand", "plan"}


@pytest.mark.parametrize(("command", "comment"), _offline_commands())
def test_offline_commands_run_as_written(command: str, comment: str) -> None:
    result = run_cli(*shlex.split(command), timeout=120)
    expected = 1 if "exit 1" in comment and "validate" not in command else 0
    assert result.returncode == expected, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    if command.startswith("plan") and expected == 0 and "--peer" in command:
        assert '"label":"robot-camera","new":true,"manager":"robot"' in result.stdout  # the camera runs on the robot
    elif command.startswith("plan") and expected == 0:
        assert "ceiling-camera" in result.stdout  # the low battery rules out the robot camera
    if expected == 1:
        assert "robot-camera (port out): constraint violated: battery = 0.1, needs >= 0.25" in result.stderr


def test_the_unit_and_its_test_run_as_written(tmp_path: Path) -> None:
    """Writing a unit (mypkg/doubler.py, specs/doubler.xml) and Testing a unit (its test), verbatim."""
    unit = next(b for b in _blocks("python") if b.startswith("# mypkg/doubler.py"))
    spec = next(b for b in _blocks("xml") if b.startswith("<!-- specs/doubler.xml -->"))
    test = next(b for b in _blocks("python") if "def test_doubler" in b)
    (tmp_path / "mypkg").mkdir()
    (tmp_path / "mypkg" / "__init__.py").write_text("")
    (tmp_path / "mypkg" / "doubler.py").write_text(unit)
    (tmp_path / "specs").mkdir()
    (tmp_path / "specs" / "doubler.xml").write_text(spec)
    (tmp_path / "test_doubler.py").write_text(test)
    env = subprocess_env()
    env["PYTHONPATH"] = f"{tmp_path}:{env['PYTHONPATH']}"
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_doubler.py"],
        capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "1 passed" in result.stdout


def test_the_spec_format_example_reads_as_the_readme_says() -> None:
    """Transformation specifications: the example expands to one spec per camera, its requirement included."""
    from dyknow.spec import parse_specs

    block = next(b for b in _blocks("xml") if b.startswith('<transformation type="unit">\n  <label>undistort(${Cam})'))
    specs = parse_specs(block, "README.md")
    assert [s.label for s in specs] == ["undistort(cam1)", "undistort(cam2)", "undistort(cam3)"]
    assert specs[1].requirements == ("not historically[0, 1s] UndistortedImage(cam2).blank",)
    assert specs[1].priority == 1 and specs[1].port("undist").deadline_ms == 500
