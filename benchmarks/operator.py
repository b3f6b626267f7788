"""What an operator's tools cost: ``dyknow top`` beside a manager of 50 units, and the start-up
of the ``dyknow`` command.

``top``: a manager runs ``--units`` units (half periodic sources at 20 Hz, half relays reading
them), then ``dyknow top --interval 1`` runs for ``--window`` seconds. Measured over the same
window (``/proc/PID/task/*/schedstat``, every thread): the CPU of the ``top`` process, as a
percentage of one core (target: under 1 %), and what the manager spends more while ``top``
watches it (its ``get_metrics`` answers: the manager's CPU over a window with ``top`` minus one
without, so its own work at 20 Hz is the baseline).

``start-up``: ``dyknow --help``, a ``dyknow model`` that fails at once (nothing listens at
``--connect``) and one that asks for a manager that is not there (``--manager robt`` of a
manager ``robot`` that runs: said at once, naming ``robot``), each run ``--runs`` times: the wall
time of the whole command (median and min), and the import time of ``python -X importtime``
(every top-level import: what Python spends importing). Target: under 0.3 s. Where the
environment sets ``PYTHONDONTWRITEBYTECODE`` (a source checkout without ``__pycache__`` folders
then compiles its modules again at each start; one that has them, from an earlier run, reads
them all the same), the commands are measured once more with byte-code caches, as an installed
package has them (a first run writes them).

    python benchmarks/operator.py                     # 20 s windows, 50 units, 10 runs
    python benchmarks/operator.py --window 5 --units 10 --runs 3 --json out/operator.json
    python benchmarks/operator.py --startup-only      # the start-up figures alone

The load average is printed beside the figures: on a loaded machine every figure is larger.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from dyknow import Client
from dyknow.resources import specs_dir

from harness import free_ports, machine, thread_cpu_ns, worker_env, write_json

TOP_TARGET_PCT = 1.0
START_TARGET_S = 0.3


def _cpu_pct(pid: int, window_s: float) -> float:
    before, t0 = thread_cpu_ns(pid), time.monotonic()
    time.sleep(window_s)
    return 100 * (thread_cpu_ns(pid) - before) / 1e9 / (time.monotonic() - t0)


def _stop(proc: subprocess.Popen[str]) -> None:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


def top(units: int, window_s: float, settle_s: float) -> dict[str, Any]:
    """The CPU of ``dyknow top`` beside a manager of ``units`` units, and what it adds to the manager's."""
    port = free_ports(1)[0]
    endpoint = f"tcp/127.0.0.1:{port}"
    manager = subprocess.Popen([sys.executable, "-m", "dyknow.cli", "manager", "--name", "watched", "--listen", endpoint,
                                "--specs", str(specs_dir() / "generic.xml")],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=worker_env())  # fmt: skip
    try:
        assert manager.stdout is not None
        if not manager.stdout.readline():
            raise RuntimeError(f"the manager did not start: {manager.stderr.read() if manager.stderr else ''}")
        with Client("watched", connect=[endpoint], timeout_s=10) as client:
            for i in range(units // 2):
                client.spawn("periodic-source", f"src{i}", params={"rate_hz": 20}, bindings={"out": f"bench/{i}"})
                client.spawn("relay", f"relay{i}", bindings={"in": f"bench/{i}"})
            if units % 2:
                client.spawn("periodic-source", "src-odd", params={"rate_hz": 20})
        time.sleep(settle_s)
        alone = _cpu_pct(manager.pid, window_s)
        watcher = subprocess.Popen([sys.executable, "-m", "dyknow.cli", "top", "--interval", "1", "--connect", endpoint, "--manager", "watched"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=worker_env())  # fmt: skip
        try:
            time.sleep(settle_s)  # its start-up (imports, the first snapshots) is over
            before_top, before_manager, t0 = thread_cpu_ns(watcher.pid), thread_cpu_ns(manager.pid), time.monotonic()
            time.sleep(window_s)
            elapsed = time.monotonic() - t0
            top_pct = 100 * (thread_cpu_ns(watcher.pid) - before_top) / 1e9 / elapsed
            watched = 100 * (thread_cpu_ns(manager.pid) - before_manager) / 1e9 / elapsed
            alive = watcher.poll() is None
        finally:
            _stop(watcher)
        if not alive:
            raise RuntimeError("dyknow top ended during the window")
    finally:
        _stop(manager)
    return {"units": units, "window_s": window_s, "top_cpu_pct": round(top_pct, 3), "manager_cpu_pct_alone": round(alone, 3),
            "manager_cpu_pct_watched": round(watched, 3), "manager_added_pct": round(watched - alone, 3)}  # fmt: skip


def _runs(argv: list[str], runs: int, env: dict[str, str]) -> dict[str, Any]:
    """Wall and import times of ``dyknow ARGV``, ``runs`` times each."""
    walls, imports = [], []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "dyknow.cli", *argv], capture_output=True, env=env, timeout=60)
        walls.append(time.perf_counter() - t0)
        done = subprocess.run([sys.executable, "-X", "importtime", "-m", "dyknow.cli", *argv], capture_output=True, text=True,
                              env=env, timeout=60)  # fmt: skip
        total = sum(int(m.group(1)) for m in re.finditer(r"^import time:\s+\d+ \|\s+(\d+) \| [^ ]", done.stderr, re.MULTILINE))
        imports.append(total / 1e6)
    return {
        "runs": runs,
        "wall_median_s": round(statistics.median(walls), 3),
        "wall_min_s": round(min(walls), 3),
        "imports_median_s": round(statistics.median(imports), 3),
    }


def startup(runs: int) -> dict[str, Any]:
    """Wall and import times of ``dyknow --help``, of a ``dyknow model`` that fails at once (nothing
    listens), and of one asking for a manager that is not there (another is); again with byte-code
    caches when the environment keeps Python from writing them."""
    refused, listening = free_ports(2)
    endpoint = f"tcp/127.0.0.1:{listening}"
    manager = subprocess.Popen([sys.executable, "-m", "dyknow.cli", "manager", "--name", "robot", "--listen", endpoint],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=worker_env())  # fmt: skip
    try:
        assert manager.stdout is not None
        if not manager.stdout.readline():
            raise RuntimeError(f"the manager did not start: {manager.stderr.read() if manager.stderr else ''}")
        commands = {
            "dyknow --help": ["--help"],
            "dyknow model (no manager)": ["model", "--connect", f"tcp/127.0.0.1:{refused}"],
            "dyknow model (misspelled)": ["model", "--manager", "robt", "--connect", endpoint],
        }
        misspelled = subprocess.run([sys.executable, "-m", "dyknow.cli", *commands["dyknow model (misspelled)"]], capture_output=True,
                                    text=True, env=worker_env(), timeout=60)  # fmt: skip
        if "no manager 'robt' among those reachable (robot)" not in misspelled.stderr:
            raise RuntimeError(f"the misspelled manager was not said as expected: {misspelled.stderr.strip()}")
        found: dict[str, Any] = {name: _runs(argv, runs, worker_env()) for name, argv in commands.items()}
        if os.environ.get("PYTHONDONTWRITEBYTECODE"):
            cached = {k: v for k, v in worker_env().items() if k != "PYTHONDONTWRITEBYTECODE"}
            for name, argv in commands.items():
                subprocess.run([sys.executable, "-m", "dyknow.cli", *argv], capture_output=True, env=cached, timeout=60)  # (writes them)
                found[f"{name}, .pyc"] = _runs(argv, runs, cached)
    finally:
        _stop(manager)
    bare = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "pass"], env=worker_env(), timeout=60)
        bare.append(time.perf_counter() - t0)
    found["python -c pass"] = {"runs": runs, "wall_median_s": round(statistics.median(bare), 3), "wall_min_s": round(min(bare), 3)}
    return found


def main(argv: list[str] | None = None) -> int:
    """Measure, and print each figure beside its target."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--window", type=float, default=20.0, metavar="S", help="seconds measured with and without top (default 20)")
    parser.add_argument("--settle", type=float, default=3.0, metavar="S", help="seconds to wait before each window (default 3)")
    parser.add_argument("--units", type=int, default=50, help="units in the watched manager (default 50)")
    parser.add_argument("--runs", type=int, default=10, help="runs of each start-up command (default 10)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--startup-only", action="store_true", help="measure the start-up of the command only (no top)")
    args = parser.parse_args(argv)
    if not Path("/proc/self/task").is_dir():
        parser.error("this benchmark reads /proc (Linux only)")
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    start = startup(args.runs)
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        print("PYTHONDONTWRITEBYTECODE is set: modules without a __pycache__ are compiled at each start; "
              "', .pyc': with byte-code caches written, as installed")
    print(f"{'command':<34} {'median s':>9} {'min s':>7} {'imports s':>10}   target")
    for name, row in start.items():
        imports = f"{row['imports_median_s']:>10.3f}" if "imports_median_s" in row else f"{'':>10}"
        target = f"< {START_TARGET_S} s" if name.startswith("dyknow") else "(Python itself)"
        print(f"{name:<34} {row['wall_median_s']:>9.3f} {row['wall_min_s']:>7.3f} {imports}   {target}", flush=True)
    if args.startup_only:
        print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        if args.json:
            write_json(args.json, {"machine": info, "startup": start, "loadavg": os.getloadavg()})
        return 0
    watched = top(args.units, args.window, args.settle)
    print(f"dyknow top beside {watched['units']} units, {watched['window_s']:g} s: {watched['top_cpu_pct']:.2f} % of a core "
          f"(target < {TOP_TARGET_PCT:g} %); the manager {watched['manager_cpu_pct_alone']:.2f} % alone, "
          f"{watched['manager_cpu_pct_watched']:.2f} % watched ({watched['manager_added_pct']:+.2f})")  # fmt: skip
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json:
        write_json(args.json, {"machine": info, "startup": start, "top": watched, "loadavg": os.getloadavg()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
