"""A manager's scheduling priority (``--nice``, :mod:`dyknow.priority`): real processes, their
threads read from /proc."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow.priority import set_nice
from tests.conftest import REPO, ManagerProcess, free_port, run_cli, subprocess_env


def _thread_nices(pid: int) -> list[int]:
    """The niceness of every thread of process ``pid`` (field 19 of each /proc/PID/task/TID/stat)."""
    nices = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except FileNotFoundError:  # the thread ended meanwhile
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # (the command name may hold spaces and parentheses)
        nices.append(int(fields[16]))
    return nices


@pytest.mark.process
def test_a_manager_given_nice_runs_every_thread_at_it_and_stats_say_so(manager_process: Callable[..., ManagerProcess]) -> None:
    """All of the manager's threads (Zenoh's included, started after the option took effect) have
    the niceness asked for, and ``dyknow stats --manager`` shows it in text and JSON."""
    proc = manager_process("--nice", "4")
    nices = _thread_nices(proc.proc.pid)
    assert len(nices) > 5 and set(nices) == {4}, nices
    load = json.loads(run_cli("stats", "--json", *proc.client_args()).stdout)
    assert load["nice"] == 4
    text = run_cli("stats", *proc.client_args()).stdout
    assert text.splitlines()[0].endswith("lanes; nice 4"), text


@pytest.mark.process
def test_a_manager_without_nice_says_nothing_of_it(manager_process: Callable[..., ManagerProcess]) -> None:
    """The default priority is not news: the stats line has no ``nice`` (the JSON says 0)."""
    proc = manager_process()
    assert set(_thread_nices(proc.proc.pid)) == {os.getpriority(os.PRIO_PROCESS, 0)}
    assert "nice" not in run_cli("stats", *proc.client_args()).stdout.splitlines()[0]


@pytest.mark.process
def test_a_refused_nice_stops_the_manager_before_it_starts_and_says_how_to_allow_it() -> None:
    """Without CAP_SYS_NICE (dropped with setpriv when the test runs as root), raising the priority
    is refused: exit 2, nothing started, and the message names the option and the ways to allow it."""
    command = [sys.executable, "-m", "dyknow.cli", "manager", "--name", "refused", "--listen", f"tcp/127.0.0.1:{free_port()}", "--nice", "-5"]
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        assert setpriv is not None, "setpriv (util-linux) is needed to run without CAP_SYS_NICE as root"
        command = [setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", *command]
    done = subprocess.run(command, capture_output=True, text=True, timeout=60, env=subprocess_env(), cwd=REPO)
    assert done.returncode == 2, (done.stdout, done.stderr)
    assert "ready" not in done.stdout
    assert "--nice: nice -5: the operating system refused" in done.stderr and "CAP_SYS_NICE" in done.stderr, done.stderr
    assert "limits.conf" in done.stderr and "leave --nice out" in done.stderr


@pytest.mark.process
@pytest.mark.parametrize("value", ["25", "-21", "high", "1.5"])
def test_a_nice_out_of_range_is_a_usage_error_naming_the_range(value: str) -> None:
    """argparse refuses it before anything starts, naming what was given and the range."""
    done = run_cli("manager", "--name", "bad", "--nice", value)
    assert done.returncode == 2
    assert f"argument --nice: got '{value}'; expected a whole number from -20" in done.stderr, done.stderr


@pytest.mark.parametrize("value", [20, -21, True, 1.0])
def test_set_nice_refuses_a_value_that_is_not_a_niceness(value: object) -> None:
    """The Python API checks the value before it touches any thread."""
    before = os.getpriority(os.PRIO_PROCESS, 0)
    with pytest.raises(ValueError, match="nice: got .*; expected a whole number from -20"):
        set_nice(value)  # type: ignore[arg-type]
    assert os.getpriority(os.PRIO_PROCESS, 0) == before
