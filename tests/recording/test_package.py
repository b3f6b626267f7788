"""Tests for the dyknow.recording package as a whole: its public surface and what importing it pulls in."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import subprocess
import sys

import pytest

import dyknow.recording
from tests.conftest import REPO, subprocess_env

# Every public name dyknow.recording and dyknow.replay exported before they became this package, and since.
EXPECTED = [
    "CLOCKS_TOPIC", "CLOCK_METADATA",  # (added with the clock records, issue 31)
    "COMPRESSED_IMAGE", "COMPRESSIONS", "NDARRAY", "PAYLOAD_METADATA", "PROTOBUF_SCHEMAS", "RAW_IMAGE",
    "ChannelInfo", "Player",
    "ReadLimits",  # (added with the bounds on decompression, issue 38)
    "RecordedMessage", "Recorder", "Recording", "RecordingError", "RecordingInfo",
    "image_array", "image_encoding", "key_for_topic",
]  # fmt: skip
MODULES = sorted(m.name for m in pkgutil.iter_modules(dyknow.recording.__path__))


def test_all_is_sorted_and_locked() -> None:
    def kind(name: str) -> int:  # constants, then classes, then functions (isort's order)
        return 0 if name.isupper() else 1 if name[0].isupper() else 2

    assert dyknow.recording.__all__ == sorted(dyknow.recording.__all__, key=lambda n: (kind(n), n))
    assert dyknow.recording.__all__ == EXPECTED
    for name in EXPECTED:
        assert getattr(dyknow.recording, name) is not None


def test_the_old_replay_module_is_gone() -> None:
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("dyknow.replay")


@pytest.mark.parametrize("module", MODULES)
def test_every_module_and_public_name_has_a_docstring(module: str) -> None:
    mod = importlib.import_module(f"dyknow.recording.{module}")
    assert inspect.getdoc(mod), module
    for name, obj in vars(mod).items():
        if name.startswith("_") or getattr(obj, "__module__", None) != mod.__name__:
            continue
        if inspect.isfunction(obj) or inspect.isclass(obj):
            assert inspect.getdoc(obj), f"{module}.{name}"
        if inspect.isclass(obj):
            for member, value in vars(obj).items():
                if not member.startswith("_") and (inspect.isfunction(value) or isinstance(value, property)):
                    assert inspect.getdoc(value), f"{module}.{name}.{member}"


@pytest.mark.process
def test_import_does_not_pull_opencv() -> None:
    code = "import sys, dyknow.recording, transformations.recording; print('cv2' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=subprocess_env(), cwd=REPO)
    assert out.stdout.strip() == "False"
