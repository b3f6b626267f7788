"""What the benchmarks share: the machine's description, JSON output, ports, CPU time, memory, pacing.

Benchmarks import the installed ``dyknow`` package (``pip install -e .``) and this module, which
Python finds because it sits beside the benchmark script being run; nothing edits ``sys.path``
and nothing imports the test suite.
"""

from __future__ import annotations

import json
import os
import platform
import queue
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "Proc",
    "cpu_seconds",
    "free_ports",
    "machine",
    "memory_mib",
    "percentile",
    "schedstat_ns",
    "sleep_until",
    "thread_cpu_ns",
    "write_json",
]


def machine() -> dict[str, Any]:
    """The machine a benchmark runs on: CPU model, cores, Python, Zenoh and dyknow versions, OS."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "zenoh": version("eclipse-zenoh"),
        "dyknow": _version("dyknow"),
        "os": f"{platform.system()} {platform.release()}",
        "pinned": False,
    }


def _version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write a benchmark's results as JSON (creating the folder) and say where."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2))
    print(f"wrote {path}")


def free_ports(n: int) -> list[int]:
    """``n`` distinct TCP ports on 127.0.0.1 that nothing listens on right now."""
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def worker_env(zenoh_runtime: str | None = None) -> dict[str, str]:
    """The environment for a worker process: this one's without ``ZENOH_RUNTIME`` (a dyknow
    session in this process sets it, and a raw Zenoh worker must get Zenoh's own runtime threads;
    a dyknow worker sets its own), or with ``zenoh_runtime`` when given."""
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if zenoh_runtime is not None:
        env["ZENOH_RUNTIME"] = zenoh_runtime
    return env


def cpu_seconds(pids: Iterable[int]) -> float:
    """User plus system CPU time of the given processes so far (Linux ``/proc``; 0 for the others)."""
    total = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])  # utime, stime
        except (OSError, IndexError, ValueError):
            pass
    return total / os.sysconf("SC_CLK_TCK")


def schedstat_ns(pid: int) -> tuple[int, int]:
    """How long every thread of ``pid`` so far ran on a CPU, and waited for one (runnable, on a run
    queue), in nanoseconds (``/proc/PID/task/*/schedstat``; threads that ended are not counted)."""
    ran = waited = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "schedstat").read_text().split()
            ran, waited = ran + int(fields[0]), waited + int(fields[1])
        except (OSError, ValueError, IndexError):
            pass  # a thread that ended meanwhile
    return ran, waited


def thread_cpu_ns(pid: int) -> int:
    """CPU time of every thread of ``pid`` so far, in nanoseconds (``/proc/PID/task/*/schedstat``).

    Finer than the 10 ms ticks of ``/proc/PID/stat`` (:func:`cpu_seconds`), which an idle process
    hardly reaches.
    """
    return schedstat_ns(pid)[0]


def memory_mib(pid: int) -> dict[str, float]:
    """Memory of process ``pid`` in MiB: ``VmRSS`` and its parts (``rss``; ``anon``: ``RssAnon``,
    ``file``: ``RssFile``, ``shmem``: ``RssShmem``) from ``/proc/<pid>/status``, and ``pss`` (shared
    pages divided among the processes mapping them; NaN when unreadable) from ``smaps_rollup``."""
    out: dict[str, float] = {}
    fields = {"VmRSS": "rss", "RssAnon": "anon", "RssFile": "file", "RssShmem": "shmem"}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in fields:
            out[fields[name]] = int(value.split()[0]) / 1024
    out["pss"] = float("nan")
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                out["pss"] = int(line.split()[1]) / 1024
    except OSError:
        pass
    return out


def sleep_until(deadline: float) -> None:
    """Sleep until ``time.perf_counter()`` reaches ``deadline`` (at once if it has)."""
    delay = deadline - time.perf_counter()
    if delay > 0:
        time.sleep(delay)


def percentile(values: Iterable[float], q: float, digits: int = 3) -> float:
    """The ``q``-th percentile of ``values`` (numpy's linear interpolation), rounded; NaN when empty."""
    array = np.asarray(list(values), dtype=np.float64)
    return round(float(np.percentile(array, q)), digits) if array.size else float("nan")


class Proc:
    """A child process whose stdout lines are read as they come and whose stderr goes to a file."""

    def __init__(self, argv: Sequence[str], popen: Callable[..., subprocess.Popen[str]] = subprocess.Popen, **kwargs: Any) -> None:
        self.stderr = tempfile.TemporaryFile(mode="w+")
        self.proc = popen(list(argv), stdout=subprocess.PIPE, stderr=self.stderr, stdin=subprocess.DEVNULL, text=True, **kwargs)
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line)

    def next_json(self, timeout_s: float, **match: Any) -> dict[str, Any]:
        """The next JSON line with the given fields (others skipped); RuntimeError with stderr's tail when none comes."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(
                    f"no line {match} from {self.proc.args[-12:] if isinstance(self.proc.args, list) else self.proc.args!r} within {timeout_s} s; stderr: {self.error_tail()}"
                ) from None
            if line.startswith("{"):
                data = json.loads(line)
                if all(data.get(k) == v for k, v in match.items()):
                    return dict(data)

    def error_tail(self) -> str:
        """The last 2,000 characters the process wrote on stderr."""
        self.stderr.seek(0)
        return self.stderr.read()[-2000:]

    def error_text(self) -> str:
        """Everything the process wrote on stderr so far."""
        self.stderr.seek(0)
        text = self.stderr.read()
        self.stderr.seek(0, 2)
        return text

    def kill(self) -> None:
        """Kill the process (SIGKILL) if it still runs and reap it."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        """Kill the process if it still runs, reap it and close its pipes and files."""
        self.kill()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self.stderr.close()
