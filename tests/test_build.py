"""The install compiles the hot-path modules (setup.py), and the compiled copies are current."""

from __future__ import annotations

import importlib
import os
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
COMPILED = re.findall(r'^    "(dyknow/[\w/]+\.py)",$', (REPO / "setup.py").read_text(), re.MULTILINE)


def test_setup_names_the_hot_path_modules() -> None:
    assert "dyknow/proxy/job.py" in COMPILED and all((REPO / path).is_file() for path in COMPILED)


@pytest.mark.parametrize("path", COMPILED)
def test_hot_path_module_is_compiled_and_current(path: str) -> None:
    """Unless the install asked for pure Python, each module is mypyc's build of today's source:
    an editable install compiles in place, and a stale copy would shadow an edited source."""
    module = importlib.import_module(path[:-3].replace("/", "."))
    if os.environ.get("DYKNOW_PURE_PYTHON"):
        assert module.__file__ is not None and module.__file__.endswith(".py")
        return
    built = Path(str(module.__file__))
    assert built.suffix == ".so", f"{path} runs interpreted: install again (make test does) to compile it"
    assert built.stat().st_mtime >= (REPO / path).stat().st_mtime, f"{built.name} is older than {path}: install again"
