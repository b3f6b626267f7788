"""What an idle manager costs: CPU time, wake-ups, threads and memory while nothing happens.

Four processes are measured the same way, one after the other, over the same window:

- ``zenoh-peer``: a bare Zenoh peer in Python (the same loopback configuration dyknow uses), the
  floor any Zenoh application pays;
- ``zenoh-peer+client``: the same peer after one Zenoh client session connected to it and left,
  as the client that spawns the units does in ``manager+units`` (Zenoh 1.10's network thread
  then wakes about 20 times a second for good);
- ``manager``: ``dyknow manager`` with the shipped specs and ontology, no units;
- ``manager+units``: the same manager with ``--units`` idle units (relays whose input nobody
  publishes), spawned through the services before the window starts.

For each: CPU time used in the window (all threads, from ``/proc/PID/task/*/schedstat``) as a
percentage of one core, context switches per second summed over its threads (each is a wake-up
of a thread), the thread count and the resident memory at the end.

    python benchmarks/idle.py                      # 20 s windows
    python benchmarks/idle.py --window 5 --json out/idle.json
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import zenoh

from dyknow import Client
from dyknow.resources import specs_dir
from dyknow.transport import make_config

from harness import free_ports, machine, thread_cpu_ns, worker_env, write_json


def _switches(pid: int) -> int:
    """Voluntary plus involuntary context switches of every thread of ``pid`` so far."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            for line in (task / "status").read_text().splitlines():
                if line.startswith(("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches")):
                    total += int(line.split()[1])
        except OSError:
            pass  # a thread that ended meanwhile
    return total


def _status(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def measure(proc: subprocess.Popen[str], window_s: float) -> dict[str, Any]:
    """CPU, wake-ups, threads and memory of ``proc`` over ``window_s`` seconds of idling."""
    cpu0, sw0, t0 = thread_cpu_ns(proc.pid), _switches(proc.pid), time.monotonic()
    time.sleep(window_s)  # the measurement window: the process is left alone
    cpu1, sw1, t1 = thread_cpu_ns(proc.pid), _switches(proc.pid), time.monotonic()
    elapsed = t1 - t0
    cpu_s = (cpu1 - cpu0) / 1e9
    return {
        "window_s": round(elapsed, 2),
        "cpu_percent": round(100 * cpu_s / elapsed, 4),
        "cpu_ms_per_s": round(1000 * cpu_s / elapsed, 3),
        "wakeups_per_s": round((sw1 - sw0) / elapsed, 1),
        "threads": _status(proc.pid, "Threads"),
        "rss_mib": round(_status(proc.pid, "VmRSS") / 1024, 1),
    }


def _wait_line(proc: subprocess.Popen[str], what: str) -> None:
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line:
        raise RuntimeError(f"{what} did not start: {proc.stderr.read() if proc.stderr else ''}")


def run(variant: str, window_s: float, settle_s: float, units: int) -> dict[str, Any]:
    """Start the process of ``variant``, let it settle, then measure a window."""
    port = free_ports(1)[0]
    endpoint = f"tcp/127.0.0.1:{port}"
    if variant.startswith("zenoh-peer"):
        script = textwrap.dedent(
            f"""
            import threading, zenoh
            from dyknow.transport import make_config
            with zenoh.open(make_config(listen=[{endpoint!r}])) as session:
                print("ready", flush=True)
                threading.Event().wait()
            """
        )
        args = [sys.executable, "-c", script]
    else:
        specs = specs_dir()
        args = [sys.executable, "-m", "dyknow.cli", "manager", "--name", "idle", "--listen", endpoint,
                "--specs", str(specs), "--ontology", str(specs / "dyknow.ttl")]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=worker_env())
    try:
        _wait_line(proc, variant)
        if variant == "manager+units":
            with Client("idle", connect=[endpoint]) as client:
                for i in range(units):
                    client.spawn("relay", f"idle{i}", bindings={"in": f"nobody/publishes/{i}"})
        elif variant == "zenoh-peer+client":  # the same kind of session as Client's, come and gone
            with zenoh.open(make_config(connect=[endpoint], mode="client", listen=[])):
                time.sleep(0.5)
        time.sleep(settle_s)  # start-up work (imports, first collections) is over
        result = measure(proc, window_s)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
    return {"variant": variant, "units": units if variant == "manager+units" else 0, **result}


def main(argv: list[str] | None = None) -> int:
    """Measure the four variants and print them side by side."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--window", type=float, default=20.0, metavar="S", help="seconds measured per variant (default 20)")
    parser.add_argument("--settle", type=float, default=3.0, metavar="S", help="seconds to wait before measuring (default 3)")
    parser.add_argument("--units", type=int, default=50, help="idle units in the manager+units variant (default 50)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    if not Path("/proc/self/task").is_dir():
        parser.error("this benchmark reads /proc (Linux only)")
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}")
    print(f"idle for {args.window:g} s after {args.settle:g} s to settle")
    print(f"{'variant':<18} {'units':>5} {'CPU % of a core':>16} {'wake-ups/s':>11} {'threads':>8} {'RSS MiB':>8}")
    results = []
    for variant in ("zenoh-peer", "zenoh-peer+client", "manager", "manager+units"):
        row = run(variant, args.window, args.settle, args.units)
        results.append(row)
        print(f"{variant:<18} {row['units']:>5} {row['cpu_percent']:>15.4f}% {row['wakeups_per_s']:>11.1f} {row['threads']:>8} {row['rss_mib']:>8.1f}", flush=True)
    if args.json:
        write_json(args.json, {"machine": info, "window_s": args.window, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
