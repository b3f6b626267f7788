"""What the benchmarks share: the machine's description, JSON output, ports, CPU time, pacing.

Benchmarks import the installed ``dyknow`` package (``pip install -e .``) and this module, which
Python finds because it sits beside the benchmark script being run; nothing edits ``sys.path``
and nothing imports the test suite.
"""

from __future__ import annotations

import json
import os
import platform
import socket
import time
from collections.abc import Iterable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["cpu_seconds", "free_ports", "machine", "percentile", "sleep_until", "write_json"]


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


def sleep_until(deadline: float) -> None:
    """Sleep until ``time.perf_counter()`` reaches ``deadline`` (at once if it has)."""
    delay = deadline - time.perf_counter()
    if delay > 0:
        time.sleep(delay)


def percentile(values: Iterable[float], q: float, digits: int = 3) -> float:
    """The ``q``-th percentile of ``values`` (numpy's linear interpolation), rounded; NaN when empty."""
    array = np.asarray(list(values), dtype=np.float64)
    return round(float(np.percentile(array, q)), digits) if array.size else float("nan")
