"""Shared fixtures: managers on loopback, CLI runners, the real test data folder."""

from __future__ import annotations

import ast
import itertools
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from dyknow import Manager

REPO = Path(__file__).resolve().parent.parent
GENERIC_SPECS = REPO / "specs" / "generic.xml"
UNIT_SPECS = REPO / "tests" / "units.xml"

_names = itertools.count(1)


def undocumented(*files: Path) -> list[str]:
    """``file:line name`` of each public function, class and method in ``files`` without a docstring.

    Functions nested in functions are left out (they are not public).
    """
    missing = []

    def walk(file: Path, node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                if not child.name.startswith("_") and ast.get_docstring(child) is None:
                    missing.append(f"{file.name}:{child.lineno} {prefix}{child.name}")
                if isinstance(child, ast.ClassDef):
                    walk(file, child, f"{prefix}{child.name}.")

    for file in files:
        walk(file, ast.parse(file.read_text(), str(file)), "")
    return missing


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def subprocess_env() -> dict[str, str]:
    """Environment for child processes: the repo importable (tests.units), quiet logs."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.fixture
def make_manager() -> Iterator[Callable[..., Manager]]:
    """Create managers (generic and test-unit specs loaded); all are closed after the test."""
    created: list[Manager] = []

    def factory(name: str | None = None, **kwargs: object) -> Manager:
        kwargs.setdefault("specs", [GENERIC_SPECS, UNIT_SPECS])
        manager = Manager(name or f"m{next(_names)}", **kwargs)  # type: ignore[arg-type]
        created.append(manager)
        return manager

    yield factory
    for manager in reversed(created):
        manager.close()


@pytest.fixture
def manager(make_manager: Callable[..., Manager]) -> Manager:
    return make_manager()


def run_cli(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    """Run ``dyknow ARGS`` in a child process and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "dyknow.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=subprocess_env(),
        cwd=REPO,
    )


class ManagerProcess:
    """A ``dyknow manager`` child process, ready once it printed its ready line."""

    def __init__(self, name: str, port: int, *extra: str) -> None:
        self.name = name
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dyknow.cli", "manager", "--name", name, "--listen", self.endpoint,
             "--specs", str(GENERIC_SPECS), str(UNIT_SPECS), "--json", *extra],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=subprocess_env(),
            cwd=REPO,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line)

    def wait_ready(self, timeout: float = 20.0) -> dict[str, object]:
        try:
            ready = json.loads(self.lines.get(timeout=timeout))
            assert ready["event"] == "ready" and ready["endpoints"] == [self.endpoint], ready
            return ready
        except queue.Empty:
            self.proc.kill()
            raise AssertionError(f"manager process did not become ready; stderr: {self.proc.stderr.read() if self.proc.stderr else ''}") from None

    def client_args(self) -> list[str]:
        return ["--connect", self.endpoint, "--manager", self.name]

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.proc.wait(timeout)


@pytest.fixture
def manager_process() -> Iterator[Callable[..., ManagerProcess]]:
    """Start ``dyknow manager`` processes on free loopback ports; all are stopped after the test."""
    started: list[ManagerProcess] = []

    def start(*extra: str, name: str | None = None) -> ManagerProcess:
        proc = ManagerProcess(name or f"proc{next(_names)}", free_port(), *extra)
        started.append(proc)
        proc.wait_ready()
        return proc

    yield start
    for proc in started:
        if proc.proc.poll() is None:
            proc.proc.kill()
            proc.proc.wait(10)
        for stream in (proc.proc.stdout, proc.proc.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real, externally authored test data (``$DYKNOW_DATA``, default ``../shared/data``).

    Missing data fails under CI (``CI=true``); elsewhere the tests that need it are skipped.
    """
    path = Path(os.environ.get("DYKNOW_DATA", REPO.parent / "shared" / "data"))
    if not (path / "SOURCES.md").is_file():
        message = f"test data not found at {path}; set DYKNOW_DATA to the shared/data folder"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(message)
        pytest.skip(message)
    return path
