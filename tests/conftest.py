"""Shared fixtures: managers on loopback, CLI runners, the real test data folder."""

from __future__ import annotations

import ast
import fcntl
import itertools
import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

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


def worker() -> tuple[int, int]:
    """This pytest process's place among the workers of a parallel run (pytest-xdist's ``-n``):
    ``(index, count)``; ``(0, 1)`` when the suite runs in one process."""
    index = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw"))
    return index, max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), index + 1)


def _share(first: int, last: int) -> range:
    """This worker's share of ``first..last``: the workers of a parallel run never pick the same."""
    index, count = worker()
    size = (last - first + 1) // count
    return range(first + index * size, first + (index + 1) * size)


#: Ports the tests listen on: above the kernel's ephemeral range (32768-60999 on Linux: what
#: ``bind(0)`` and every outgoing connection take) and above every DDS domain's ports that
#: :func:`dds_domain` hands out, so nothing else on the machine takes one between the check and
#: the listen; each worker of a parallel run takes its own share, in turn.
_PORTS = _share(61000, 65535)
_next_port = itertools.count()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now, of this worker's own share (see
    ``_PORTS``): a parallel worker never hands out the same, and a port comes back only after
    the rest of the share went round."""
    for _ in range(len(_PORTS)):
        port = _PORTS[next(_next_port) % len(_PORTS)]
        with socket.socket() as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue  # in use, or still held by a closing connection
            return port
    raise RuntimeError(f"no free port among {_PORTS}")


#: DDS domains of the tests: 1-213, whose ports (7400 + 250 * domain and up, the RTPS mapping)
#: stay below the tests' own (``_PORTS``); each worker of a parallel run has its own share, as
#: DDS discovery on loopback would join two tests on one domain.
_DOMAINS = _share(1, 213)
_next_domain = itertools.count()


def dds_domain() -> int:
    """A DDS domain (ROS 2's ``ROS_DOMAIN_ID``) no other worker of this run uses and no participant
    on this machine has joined right now (its first discovery port is free)."""
    for _ in range(len(_DOMAINS)):
        domain = _DOMAINS[next(_next_domain) % len(_DOMAINS)]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            try:
                sock.bind(("0.0.0.0", 7400 + 250 * domain + 10))  # participant 0's unicast discovery port
            except OSError:
                continue
            return domain
    raise RuntimeError(f"no free DDS domain among {_DOMAINS}")


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


def run_cli(*args: str, timeout: float = 30.0, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``dyknow ARGS`` in a child process (``stdin`` as its input) and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "dyknow.cli", *args],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=subprocess_env(),
        cwd=REPO,
    )


def run_group(argv: list[str], *, timeout: float, **kwargs: Any) -> subprocess.CompletedProcess[str]:
    """Run ``argv`` to its end, as ``subprocess.run(argv, capture_output=True, text=True)``, in a
    process group of its own; whatever of the group is left when it ends, fails or the test is cut
    short (its timeout) is killed, so no worker process of a benchmark outlives the test."""
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, **kwargs)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the leader's group: the children it left, or all of it
        except ProcessLookupError:
            pass
        if proc.returncode is None:
            proc.communicate()
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


def end_process(proc: subprocess.Popen[Any], grace_s: float = 0.0) -> None:
    """End ``proc`` (SIGTERM and up to ``grace_s`` seconds to finish when given, then SIGKILL),
    wait for it and close its pipes."""
    if proc.poll() is None and grace_s > 0:
        proc.terminate()
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            pass
    if proc.poll() is None:
        proc.kill()
    proc.wait(10)
    for stream in (proc.stdin, proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


def under_ci() -> bool:
    """Whether the suite runs in CI (``CI=true``), where nothing may be skipped."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def need_hosts(faults: bool = False) -> None:
    """Network namespaces (and, with ``faults``, nftables for link faults, installed with apt-get
    when missing, as Chromium is) are required: the test fails under CI without them and is
    skipped elsewhere, saying what is missing."""
    from dyknow.testing.hosts import faults_unavailable, unavailable

    if faults and faults_unavailable() is not None:
        apt_install("nftables")
    why = unavailable() or (faults_unavailable() if faults else None)
    if why is None:
        return
    if under_ci():
        pytest.fail(f"network namespaces{' and nft' if faults else ''} are required under CI: {why}")
    pytest.skip(why)


def wait_until(condition: Callable[[], bool], what: str, timeout_s: float = 20.0) -> None:
    """Wait for state another thread or process changes and that has no event to wait on."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"{what} within {timeout_s} s"
        time.sleep(0.005)


class CliProcess:
    """A ``dyknow`` child process whose stdout lines are read as they come (JSON lines with ``--json``)."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dyknow.cli", *args],
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

    def line(self, timeout_s: float = 20.0) -> dict[str, Any]:
        """The next line of output, as JSON; kills the process and fails when none comes."""
        try:
            return dict(json.loads(self.lines.get(timeout=timeout_s)))
        except queue.Empty:
            self.proc.kill()
            stderr = self.proc.stderr.read() if self.proc.stderr else ""
            raise AssertionError(f"no line from {self.proc.args} within {timeout_s} s; stderr: {stderr}") from None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        """Send ``sig`` (unless it ended already) and return the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.proc.wait(timeout_s)

    def close(self) -> None:
        """Kill the process if it still runs, and close its pipes."""
        end_process(self.proc)


@pytest.fixture
def cli_process() -> Iterator[Callable[..., CliProcess]]:
    """Start ``dyknow ARGS`` child processes; all are killed after the test."""
    started: list[CliProcess] = []

    def start(*args: str) -> CliProcess:
        proc = CliProcess(*args)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        proc.close()


class ManagerProcess(CliProcess):
    """A ``dyknow manager`` child process, ready once it printed its ready line."""

    def __init__(self, name: str, port: int, *extra: str) -> None:
        self.name = name
        self.endpoint = f"tcp/127.0.0.1:{port}"
        super().__init__(
            "manager", "--name", name, "--listen", self.endpoint, "--specs", str(GENERIC_SPECS), str(UNIT_SPECS), "--json", *extra
        )

    def wait_ready(self, timeout_s: float = 60.0) -> dict[str, Any]:
        """The ready line (fails when the manager does not become ready). The bound is for a
        stuck process, not a speed limit: a manager's start (Python, its imports, Zenoh, the specs)
        took over 20 s once on a machine loaded with two CPU hogs per core, apt and a compiler."""
        ready = self.line(timeout_s)
        assert ready["event"] == "ready" and ready["endpoints"] == [self.endpoint], ready
        return ready

    def client_args(self) -> list[str]:
        """The options that point a client command at this manager."""
        return ["--connect", self.endpoint, "--manager", self.name]


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
        proc.close()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real, externally authored test data (``$DYKNOW_DATA``, default ``../shared/data``).

    Missing data fails under CI (``CI=true``); elsewhere the tests that need it are skipped.
    """
    path = Path(os.environ.get("DYKNOW_DATA", REPO.parent / "shared" / "data"))
    if not (path / "SOURCES.md").is_file():
        message = f"test data not found at {path}; set DYKNOW_DATA to the shared/data folder"
        if under_ci():
            pytest.fail(message)
        pytest.skip(message)
    return path


def apt_install(*packages: str) -> None:
    """Install Debian ``packages`` with apt-get, when running as root on a machine that has it
    (the suite's system tools: Chromium, Graphviz, libfaketime, nftables). Workers of a parallel
    run take turns (a lock file), and apt-get waits for dpkg's own lock rather than failing."""
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return
    with open("/tmp/dyknow-tests-apt.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        subprocess.run(["apt-get", "install", "-y", "-q", "-o", "DPkg::Lock::Timeout=900", *packages], capture_output=True, timeout=1800,
                       env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})  # fmt: skip


def _browser_paths() -> tuple[str, str] | None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    return (browser, driver) if browser and driver else None


@pytest.fixture(scope="session")
def browser_paths() -> tuple[str, str]:
    """Debian's Chromium and chromedriver, installed with apt-get when missing and run as root.

    Every test that drives a browser (the tool's tests, the UI benchmark's smoke run) asks for
    this fixture, so whichever runs first on a fresh machine installs them. Missing browsers
    fail under CI (``CI=true``); elsewhere the tests that need them are skipped with the reason.
    """
    found = _browser_paths()
    if found is None:
        apt_install("chromium", "chromium-driver")
        found = _browser_paths()
    if found is None:
        why = "Chromium and chromedriver are not installed (apt-get install chromium chromium-driver)"
        if under_ci():
            pytest.fail(why)
        pytest.skip(why)
    return found


@pytest.fixture(scope="session")
def graphviz() -> str:
    """Debian's Graphviz (``dot``), which the site's build draws its figures with, installed with
    apt-get when missing and run as root (as the browser is). Missing, it fails under CI
    (``CI=true``); elsewhere the tests that need it are skipped with the reason."""
    found = shutil.which("dot")
    if found is None:
        apt_install("graphviz")
        found = shutil.which("dot")
    if found is None:
        why = "Graphviz is not installed (apt-get install graphviz): the site's figures are drawn with its dot"
        if under_ci():
            pytest.fail(why)
        pytest.skip(why)
    return found


FAKETIME = Path("/usr/lib/x86_64-linux-gnu/faketime/libfaketime.so.1")


@pytest.fixture(scope="session")
def faketime() -> Path:
    """Debian's libfaketime (a process's wall clock faked: ``LD_PRELOAD`` it with ``FAKETIME``),
    installed with apt-get when missing and run as root. Missing, it fails under CI (``CI=true``);
    elsewhere the tests that need it are skipped with the reason."""
    if not FAKETIME.is_file():
        apt_install("faketime")
    if not FAKETIME.is_file():
        why = f"libfaketime is not installed ({FAKETIME}; apt-get install faketime)"
        if under_ci():
            pytest.fail(why)
        pytest.skip(why)
    return FAKETIME


def faked_clock(faketime: Path, setting: str) -> dict[str, str]:
    """The environment that runs a process with its wall clock faked by ``setting`` (libfaketime's
    ``FAKETIME``: ``+0.25``, ``+0 x1.0001``), its monotonic clock left alone (Zenoh's leases, timers)."""
    return {"FAKETIME": setting, "FAKETIME_DONT_FAKE_MONOTONIC": "1", "LD_PRELOAD": str(faketime)}


# ------------------------------------------------------------------------------------------- tiers
#
# Every test belongs to one tier, so a contributor can run the quick part alone (CONTRIBUTING.md):
#
#   unit        in this process only: Zenoh sessions on loopback, files, OpenCV (no mark: the default)
#   process     starts other processes: managers, CLI commands, benchmarks' smoke runs, ROS 2 peers
#   namespaces  makes network namespaces (several hosts on one machine; root)
#   browser     drives a real Chromium
#
# A test's tier is checked as it runs: one that starts a program of a tier above its mark fails,
# naming the program and the mark it needs. Programs that only install what the suite needs
# (apt-get) belong to no tier.

TIERS = ("unit", "process", "namespaces", "browser")
_UNTIERED = {"apt-get", "dpkg", "ldconfig", "ldconfig.real", "uname"}
_started: list[tuple[str, str]] = []  # (tier, command) of each program started by the running test


def _tier_of(argv: Any) -> str | None:
    """The tier a program belongs to, from its command line (None: no tier)."""
    words = [os.path.basename(str(word)) for word in ([argv] if isinstance(argv, (str, bytes, os.PathLike)) else list(argv))[:8]]
    if not words or words[0] in _UNTIERED:
        return None
    if words[0] in ("ip", "nft", "tc", "unshare", "nsenter"):
        return "namespaces"
    if any("chromium" in word or "chromedriver" in word or "chrome" == word for word in words):
        return "browser"
    return "process"


def _audit(event: str, args: tuple[Any, ...]) -> None:
    if event == "subprocess.Popen":
        tier = _tier_of(args[1] if args[1] is not None else args[0])
        if tier is not None:
            _started.append((tier, " ".join(str(a) for a in ([args[1]] if isinstance(args[1], (str, bytes)) else list(args[1] or [args[0]])))[:200]))
    elif event in ("os.system", "os.posix_spawn", "os.spawn", "os.exec", "os.fork", "os.forkpty"):
        _started.append(("process", f"{event} {args[0] if args else ''}"[:200]))


sys.addaudithook(_audit)


def _tier(item: pytest.Item) -> str:
    marked = [tier for tier in TIERS[1:] if item.get_closest_marker(tier) is not None]
    return marked[-1] if marked else "unit"


def pytest_configure(config: pytest.Config) -> None:
    for tier, what in (("unit", "in this process only (given to every test without another tier's mark)"),
                       ("process", "starts other processes (managers, CLI commands, smoke runs of benchmarks, ROS 2 peers)"),
                       ("namespaces", "makes network namespaces to stand in for several hosts (root)"),
                       ("browser", "drives a real Chromium")):  # fmt: skip
        config.addinivalue_line("markers", f"{tier}: the {tier} tier: {what}")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if _tier(item) == "unit":
            item.add_marker(pytest.mark.unit)


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> Any:
    _started.clear()  # before any fixture of this test: what its setup and its call start is its own
    return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    report = yield
    if call.when == "call" and report.passed:
        rank = TIERS.index(_tier(item))
        above = [(tier, command) for tier, command in _started if TIERS.index(tier) > rank]
        if above:
            tier, command = above[0]
            report.outcome = "failed"
            report.longrepr = (f"{item.nodeid} is in the {_tier(item)} tier but started `{command}`, a program of the {tier} tier: "
                               f"mark it @pytest.mark.{tier} (or its module: pytestmark = pytest.mark.{tier}); see CONTRIBUTING.md, 'Tiers'")  # fmt: skip
    return report
