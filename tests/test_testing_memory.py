"""peak_run: the peak memory of a command alone, not of the process that started it."""

from __future__ import annotations

import sys

import pytest

from dyknow.testing.memory import peak_run

GROW = "b = bytearray(200 << 20); b[::4096] = b'x' * len(b[::4096])"  # touches 200 MiB


@pytest.mark.process
def test_a_large_parent_does_not_count_towards_its_commands_peak() -> None:
    ballast = bytearray(400 << 20)
    ballast[::4096] = b"x" * len(ballast[::4096])  # this process now holds 400 MiB more
    code, small = peak_run([sys.executable, "-c", "pass"], timeout_s=60)
    assert code == 0 and small < 100, small
    code, grown = peak_run([sys.executable, "-c", GROW], timeout_s=60)
    assert code == 0 and 200 <= grown < 300, grown
    del ballast


@pytest.mark.process
def test_the_exit_code_and_a_timeout_come_back() -> None:
    assert peak_run([sys.executable, "-c", "raise SystemExit(3)"], timeout_s=60)[0] == 3
    assert peak_run([sys.executable, "-c", "import time; time.sleep(60)"], timeout_s=0.5)[0] == -9
    assert peak_run(["/nonexistent/command"], timeout_s=60)[0] == 127


def test_an_empty_command_is_refused() -> None:
    with pytest.raises(ValueError, match="argv is empty"):
        peak_run([], timeout_s=1)
