"""Many clients at once: does a manager serve them in parallel, and stay consistent?

A ``dyknow manager`` process serves; client processes call it through :class:`dyknow.Client`,
each client on a Zenoh session of its own, all starting together. Every client repeats, as fast
as its calls return: ``spawn`` a relay, ``get_config`` it, ``set_config`` (rebind its input),
``get_statistics``, ``get_model``, then ``destroy`` it (every tenth relay is kept instead, and
the client remembers its binding; each client keeps its last three, so the model keeps about
the same size and the phases compare). Each call is timed. A phase runs with one client, then with
``--clients`` (default 32: ``--processes`` processes of several clients each).

Printed per phase: calls, calls per second, p50 and p99 of each operation, unexpected errors;
then a consistency check: the manager's model after the phase against what the clients
believe (every relay they kept runs, bound as they left it; nothing else runs). Targets (issue
14): throughput with 32 clients at least that of one client; ``get_model`` p99 under 50 ms
with 32 clients spawning and destroying.

    python benchmarks/load.py                           # 1 then 32 clients, 30 s each
    python benchmarks/load.py --seconds 60 --json out/load.json
    python benchmarks/load.py --seconds 3 --clients 4 --processes 2   # a quick look
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from dyknow import Client
from dyknow.resources import specs_dir

from harness import cpu_seconds, free_ports, machine, percentile, write_json

OPERATIONS = ("spawn", "get_config", "set_config", "get_statistics", "get_model", "destroy")
GET_MODEL_P99_TARGET_MS = 50.0
KEEP_EVERY = 10
KEEP_AT_MOST = 3


def client_loop(manager: str, endpoint: str, client_id: str, go: threading.Event, end: list[float], out: dict[str, Any]) -> None:
    """One client: the call cycle until ``end[0]`` (monotonic), timing every call into ``out``."""
    times: dict[str, list[float]] = {op: [] for op in OPERATIONS}
    errors: list[str] = []
    kept: dict[str, str] = {}
    with Client(manager, connect=[endpoint], timeout_s=30) as client:
        client.get_model()  # the link is up
        out["ready"].set()
        go.wait()
        n = 0

        def call(op: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            except Exception as exc:  # counted and shown: no call should fail
                errors.append(f"{op}: {type(exc).__name__}: {exc}"[:300])
                return None
            finally:
                times[op].append((time.perf_counter() - start) * 1000)

        while time.monotonic() < end[0]:
            name = f"{client_id}-{n}"
            call("spawn", client.spawn, "relay", name, bindings={"in": f"load/{client_id}/in"})
            call("get_config", client.get_config, name)
            key = f"load/{client_id}/{n}"
            call("set_config", client.set_config, name, {"in": key})
            call("get_statistics", client.get_statistics, name)
            call("get_model", client.get_model)
            if n % KEEP_EVERY == KEEP_EVERY - 1:
                kept[name] = key
                if len(kept) > KEEP_AT_MOST:  # the model stays the same size: phases compare
                    oldest = next(iter(kept))
                    del kept[oldest]
                    call("destroy", client.destroy, oldest)
            else:
                call("destroy", client.destroy, name)
            n += 1
    out.update(times=times, errors=errors, kept=kept)


def worker(args: argparse.Namespace) -> int:
    """A client process: ``--in-process`` clients; prints "ready", waits for "go", runs, prints JSON."""
    go = threading.Event()
    end = [0.0]
    results: list[dict[str, Any]] = [{"ready": threading.Event()} for _ in range(args.in_process)]
    threads = [
        threading.Thread(target=client_loop, args=(args.manager, args.connect, f"{args.prefix}{i}", go, end, results[i]))
        for i in range(args.in_process)
    ]
    for thread in threads:
        thread.start()
    for result in results:
        result["ready"].wait(60)
    print("ready", flush=True)
    if sys.stdin.readline().strip() != "go":
        return 1
    end[0] = time.monotonic() + args.seconds
    go.set()
    for thread in threads:
        thread.join()
    merged: dict[str, Any] = {"times": {op: [] for op in OPERATIONS}, "errors": [], "kept": {}}
    for result in results:
        for op in OPERATIONS:
            merged["times"][op] += result["times"][op]
        merged["errors"] += result["errors"]
        merged["kept"].update(result["kept"])
    print(json.dumps(merged), flush=True)
    return 0


def proc_status(pid: int) -> tuple[int, float]:
    """Threads and resident memory (MB) of process ``pid``."""
    threads, rss = 0, 0.0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Threads:"):
            threads = int(line.split()[1])
        elif line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024
    return threads, rss


def run_phase(manager: str, manager_pid: int, endpoint: str, clients: int, processes: int, seconds: float, phase: int) -> dict[str, Any]:
    """``clients`` clients in ``processes`` processes for ``seconds``; their merged results, and
    the CPU the manager and the clients used meanwhile (in cores)."""
    processes = max(1, min(processes, clients))
    shares = [clients // processes + (1 if i < clients % processes else 0) for i in range(processes)]
    procs = [
        subprocess.Popen(
            [sys.executable, __file__, "--worker", "--connect", endpoint, "--manager", manager, "--in-process", str(share),
             "--prefix", f"p{phase}-{i}-c", "--seconds", str(seconds)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        for i, share in enumerate(shares)
    ]
    try:
        for proc in procs:
            assert proc.stdout is not None and proc.stdout.readline().strip() == "ready", "a client process did not start"
        started = time.monotonic()
        cpu_manager, cpu_clients = cpu_seconds([manager_pid]), cpu_seconds(p.pid for p in procs)
        for proc in procs:
            assert proc.stdin is not None
            proc.stdin.write("go\n")
            proc.stdin.flush()
        time.sleep(seconds)
        cpu_manager, cpu_clients = cpu_seconds([manager_pid]) - cpu_manager, cpu_seconds(p.pid for p in procs) - cpu_clients
        outputs = [json.loads(proc.stdout.readline()) for proc in procs if proc.stdout is not None]
        elapsed = time.monotonic() - started
        for proc in procs:
            proc.wait(30)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
    times: dict[str, list[float]] = {op: [] for op in OPERATIONS}
    errors: list[str] = []
    kept: dict[str, str] = {}
    for output in outputs:
        for op in OPERATIONS:
            times[op] += output["times"][op]
        errors += output["errors"]
        kept.update(output["kept"])
    calls = sum(len(t) for t in times.values())
    return {
        "clients": clients,
        "processes": processes,
        "seconds": round(elapsed, 2),
        "calls": calls,
        "calls_per_s": round(calls / elapsed, 1),
        "manager_cpu_cores": round(cpu_manager / seconds, 2),
        "clients_cpu_cores": round(cpu_clients / seconds, 2),
        "operations": {
            op: {"calls": len(t), "p50_ms": round(percentile(t, 50), 2), "p99_ms": round(percentile(t, 99), 2)} for op, t in times.items() if t
        },
        "errors": len(errors),
        "first_errors": errors[:5],
        "kept": kept,
    }


def consistency(manager: str, endpoint: str, believed: dict[str, str]) -> dict[str, Any]:
    """The manager's model against what the clients believe: missing, unexpected and misbound relays."""
    with Client(manager, connect=[endpoint], timeout_s=30) as client:
        units = {u["name"]: u for u in client.get_model()["units"]}
    missing = sorted(set(believed) - set(units))
    unexpected = sorted(set(units) - set(believed))
    misbound = sorted(n for n, key in believed.items() if n in units and units[n]["bindings"].get("in") != key)
    not_running = sorted(n for n in believed if n in units and units[n]["state"] != "running")
    return {
        "believed": len(believed),
        "running": len(units),
        "missing": missing[:10],
        "unexpected": unexpected[:10],
        "misbound": misbound[:10],
        "not_running": not_running[:10],
        "consistent": not (missing or unexpected or misbound or not_running),
    }


def main(argv: list[str] | None = None) -> int:
    """Run one client, then many, against one manager process; print and check the targets."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=32, help="clients in the second phase (default 32)")
    parser.add_argument("--processes", type=int, default=4, help="processes the clients are spread over (default 4)")
    parser.add_argument("--seconds", type=float, default=30.0, help="length of each phase (default 30)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--connect", help=argparse.SUPPRESS)
    parser.add_argument("--manager", default="loaded", help=argparse.SUPPRESS)
    parser.add_argument("--in-process", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--prefix", default="c", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args)

    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}")
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    manager = subprocess.Popen(
        [sys.executable, "-m", "dyknow.cli", "manager", "--name", args.manager, "--listen", endpoint, "--specs", str(specs_dir() / "generic.xml")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    phases: list[dict[str, Any]] = []
    believed: dict[str, str] = {}
    try:
        assert manager.stdout is not None and manager.stdout.readline(), "the manager did not start"
        for number, clients in enumerate((1, args.clients)):
            phase = run_phase(args.manager, manager.pid, endpoint, clients, args.processes if clients > 1 else 1, args.seconds, number)
            believed.update(phase.pop("kept"))
            phase["consistency"] = consistency(args.manager, endpoint, believed)
            phase["manager_threads"], phase["manager_rss_mb"] = proc_status(manager.pid)
            phases.append(phase)
        manager.terminate()
        exit_code = manager.wait(10)
    finally:
        if manager.poll() is None:
            manager.kill()

    print(f"\n{'clients':>7} {'calls':>7} {'calls/s':>8} {'errors':>6}  {'consistent':>10}  {'threads':>7} {'RSS':>8}  {'CPU (cores) manager':>19} {'clients':>7}")
    for p in phases:
        c = p["consistency"]
        print(
            f"{p['clients']:>7} {p['calls']:>7} {p['calls_per_s']:>8.1f} {p['errors']:>6}  {'yes' if c['consistent'] else 'NO':>10}  "
            f"{p['manager_threads']:>7} {p['manager_rss_mb']:>5.0f} MB  {p['manager_cpu_cores']:>19.2f} {p['clients_cpu_cores']:>7.2f}"
        )
    for p in phases:
        print(f"\n{p['clients']} client(s): per operation{'':<10} {'calls':>7} {'p50':>9} {'p99':>9}")
        for op, row in p["operations"].items():
            print(f"  {op:<32} {row['calls']:>7} {row['p50_ms']:>6.2f} ms {row['p99_ms']:>6.2f} ms")
        for error in p["first_errors"]:
            print(f"  error: {error}")
        c = p["consistency"]
        if not c["consistent"]:
            print(f"  inconsistent: missing {c['missing']}, unexpected {c['unexpected']}, misbound {c['misbound']}, not running {c['not_running']}")
    one, many = phases
    model_p99 = many["operations"]["get_model"]["p99_ms"]
    throughput_met = many["calls_per_s"] >= one["calls_per_s"]
    model_met = model_p99 < GET_MODEL_P99_TARGET_MS
    errors_met = one["errors"] == 0 and many["errors"] == 0
    consistent = all(p["consistency"]["consistent"] for p in phases)
    print(
        f"\ntarget: throughput with {many['clients']} clients >= with 1: {many['calls_per_s']:.1f} vs {one['calls_per_s']:.1f} calls/s: "
        f"{'met' if throughput_met else 'MISSED'}"
    )
    print(
        f"target: get_model p99 with {many['clients']} clients < {GET_MODEL_P99_TARGET_MS:.0f} ms: {model_p99:.2f} ms: "
        f"{'met' if model_met else 'MISSED'}"
    )
    print(f"target: no unexpected error, the model matches what the clients believe: {'met' if errors_met and consistent else 'MISSED'}")
    print(f"manager exit code on SIGTERM: {exit_code} (target 0)")
    if args.json:
        targets = {"throughput": throughput_met, "get_model_p99": model_met, "no_errors": errors_met, "consistent": consistent}
        write_json(args.json, {"machine": info, "results": phases, "targets": targets, "exit_code": exit_code})
    return 0 if exit_code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
