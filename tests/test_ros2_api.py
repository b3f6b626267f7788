"""dyknow.ros2's public surface: one sorted ``__all__``, every name importable and documented,
and ``import dyknow.ros2`` imports neither rosbags nor Cyclone DDS (they load when used)."""

from __future__ import annotations

import subprocess
import sys

import pytest

import dyknow.ros2
from tests.conftest import REPO, subprocess_env, undocumented


def test_all_is_sorted_and_importable() -> None:
    names = dyknow.ros2.__all__
    # isort's order: CONSTANTS, then Classes, then functions
    assert names == sorted(names, key=lambda n: (0 if n.isupper() else 1 if n[0].isupper() else 2, n))
    assert all(hasattr(dyknow.ros2, name) for name in names)


def test_every_public_name_is_documented() -> None:
    assert undocumented(*sorted((REPO / "dyknow" / "ros2").glob("*.py")), REPO / "dyknow" / "demo" / "ros2.py") == []


@pytest.mark.process
def test_importing_it_loads_no_optional_library() -> None:
    code = "import sys, dyknow.ros2, dyknow.manager; print(sorted(m for m in ('rosbags', 'cyclonedds', 'xxhash') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=subprocess_env(), cwd=REPO, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
