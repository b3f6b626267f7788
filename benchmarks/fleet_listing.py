"""A fleet-wide listing of 1,000 managers, in pages (issue 40, item 2).

A ``dyknow router`` listens on loopback; ``--processes`` host processes each run ``--per-process``
managers behind it (``Manager(name, router=[hub])``: each a Zenoh client with its own session,
its own services and liveliness token, dialling the router only). Packing many managers into one
process is what lets 1,000 of them run on a 2-core machine (a ``dyknow manager`` process each
would need about 45 GiB); what a listing exchanges with each is the same as with a process each.
Then, from a client of the router:

- **names**: ``Client.manager_names()`` (one liveliness query, a name each), ``--repeats`` times;
- **a page**: ``Client.managers_page(limit=--page)`` (the names, then the brief summary of each
  manager of the page, 8 at once), the first page ``--repeats`` times;
- **the whole fleet, page by page**: every page followed by ``next`` until the last; checked:
  every manager listed exactly once;
- **``dyknow managers --limit N --json``**: a process of its own (its start-up included), the
  first page, ``--cmd-runs`` times; checked: it lists ``N`` and says where the next page starts;
- **a page of models**: ``Client.get_federated_model(limit=20)``.

Printed with the load average and the memory of each host process (PSS per manager). The
target (the issue's): the listing works at 1,000 managers, in pages; no time is set for it.

    flock /tmp/dyknow-heavy.lock python benchmarks/fleet_listing.py     # writes benchmarks/results/fleet-listing.{txt,json}
    python benchmarks/fleet_listing.py --processes 2 --per-process 10 --page 7 --json out.json --txt out.txt   # a smoke run
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from harness import Proc, free_ports, machine, memory_mib, percentile, worker_env, write_json

RESULTS = Path(__file__).resolve().parent / "results"
START_TIMEOUT_S = 600.0


class Refused(logging.Handler):
    """Counts the managers that found no router answering (refused by it) and fell back."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.count = 0
        self.names: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        """Count a manager's warning that no router of it answers."""
        message = record.getMessage()
        if "answers yet" in message:
            self.count += 1
            self.names.append(message.split("'")[1] if message.count("'") >= 2 else "?")


def host(hub: str, prefix: str, count: int) -> None:
    """Run ``count`` managers named ``<prefix><i>`` behind ``hub`` until SIGTERM; a JSON line once all are up."""
    from dyknow import Manager

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    refused = Refused()
    logging.getLogger("dyknow.manager").addHandler(refused)
    started = time.monotonic()
    managers = []
    try:
        for i in range(count):
            managers.append(Manager(f"{prefix}{i:04d}", router=[hub], specs=[]).__enter__())
        threads = len(os.listdir("/proc/self/task"))
        print(json.dumps({"event": "ready", "managers": count, "seconds": round(time.monotonic() - started, 2), "threads": threads, "refused": refused.count,
                          "refused_names": refused.names[:50]}), flush=True)
        stop.wait()
    finally:
        for manager in managers:
            manager.close()


def load_average() -> float:
    """The 1-minute load average."""
    return os.getloadavg()[0]


def stats(ms: list[float]) -> dict[str, Any]:
    """p50 and max of ``ms``, and how many."""
    return {"p50_ms": percentile(ms, 50, 1), "max_ms": round(max(ms), 1), "n": len(ms)} if ms else {"n": 0}


def measure(hub: str, expected: list[str], page: int, repeats: int, cmd_runs: int) -> dict[str, Any]:
    """The listing figures of the fleet behind ``hub`` (the managers ``expected``)."""
    from dyknow import Client

    total = len(expected)
    out: dict[str, Any] = {}
    with Client("m", connect=[hub], timeout_s=30) as client:
        started = time.monotonic()
        said_at = started
        while (named := len(client.manager_names(2.0))) < total:
            if time.monotonic() - said_at >= 10:  # (progress, to stderr: the report stays on stdout)
                print(f"{time.monotonic() - started:.0f} s: {named} of {total} named (load {load_average():.1f})", file=sys.stderr, flush=True)
                said_at = time.monotonic()
            if time.monotonic() - started > START_TIMEOUT_S:
                missing = sorted(set(expected) - set(client.manager_names(2.0)))
                raise RuntimeError(f"only {total - len(missing)} of {total} managers listed after {START_TIMEOUT_S} s; missing: {missing[:40]}")
            time.sleep(0.5)
        out["all_named_after_s"] = round(time.monotonic() - started, 2)
        names_ms = []
        for _ in range(repeats):
            t = time.perf_counter()
            names = client.manager_names(2.0)
            names_ms.append((time.perf_counter() - t) * 1000)
            assert len(names) == total, f"{len(names)} names of {total}"
        out["names"] = {**stats(names_ms), "load": load_average()}
        first_ms = []
        for _ in range(repeats):
            t = time.perf_counter()
            first = client.managers_page(2.0, limit=page)
            first_ms.append((time.perf_counter() - t) * 1000)
        out["first_page"] = {**stats(first_ms), "listed": len(first["managers"]), "total": first["total"], "load": load_average()}
        seen: list[str] = []
        pages_ms = []
        after = None
        t0 = time.perf_counter()
        while True:
            t = time.perf_counter()
            got = client.managers_page(2.0, limit=page, after=after)
            pages_ms.append((time.perf_counter() - t) * 1000)
            seen += [m["manager"] for m in got["managers"]]
            after = got["next"]
            if after is None:
                break
        whole_s = time.perf_counter() - t0
        out["all_pages"] = {
            "pages": len(pages_ms), "seconds": round(whole_s, 2), **stats(pages_ms), "listed": len(seen),
            "each_once": sorted(seen) == sorted(set(seen)) and len(seen) == total, "load": load_average(),
        }  # fmt: skip
        t = time.perf_counter()
        models = client.get_federated_model(2.0, limit=min(page, 20))
        out["model_page"] = {"ms": round((time.perf_counter() - t) * 1000, 1), "listed": len(models["managers"]), "load": load_average()}
    argv = [sys.executable, "-m", "dyknow.cli", "managers", "--connect", hub, "--limit", str(page), "--json", "--timeout", "30"]
    cmd_ms, listed, said = [], [], []
    for _ in range(cmd_runs):
        t = time.perf_counter()
        done = subprocess.run(argv, capture_output=True, text=True, timeout=600, env=worker_env())
        cmd_ms.append((time.perf_counter() - t) * 1000)
        if done.returncode != 0:
            raise RuntimeError(f"dyknow managers exited {done.returncode}: {done.stderr[-2000:]}")
        listed.append(sum(1 for m in json.loads(done.stdout) if m.get("state") == "up"))
        said.append(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "")
    out["managers_cmd"] = {**stats(cmd_ms), "listed": listed, "said": said[-1] if said else "", "load": load_average()}
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Start the router and the hosts, measure, stop them; the results."""
    total = args.processes * args.per_process
    hub = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    result: dict[str, Any] = {"machine": machine(), "managers": total, "processes": args.processes, "per_process": args.per_process,
                              "page": args.page, "load_at_start": load_average()}  # fmt: skip
    router = Proc([sys.executable, "-m", "dyknow.cli", "router", "--listen", hub, "--json"], env=worker_env())
    hosts: list[Proc] = []
    try:
        router.next_json(60, event="ready")
        started = time.monotonic()
        for k in range(args.processes):
            hosts.append(Proc([sys.executable, __file__, "--host", hub, f"p{k:02d}m", str(args.per_process)], env=worker_env()))
        ready = [h.next_json(START_TIMEOUT_S, event="ready") for h in hosts]
        result["start"] = {"seconds": round(time.monotonic() - started, 2), "threads_per_process": max(r["threads"] for r in ready),
                           "refused": sum(r["refused"] for r in ready), "load": load_average(),
                           "refused_names": [n for r in ready for n in r.get("refused_names", [])][:50]}  # fmt: skip
        print(f"all {total} started: {result['start']}", file=sys.stderr, flush=True)
        expected = [f"p{k:02d}m{i:04d}" for k in range(args.processes) for i in range(args.per_process)]
        result.update(measure(hub, expected, args.page, args.repeats, args.cmd_runs))
        pss = [memory_mib(h.proc.pid)["pss"] for h in hosts]
        result["memory"] = {"pss_mib_per_process": round(max(pss), 1), "pss_mib_per_manager": round(sum(pss) / total, 2),
                            "router_pss_mib": round(memory_mib(router.proc.pid)["pss"], 1)}  # fmt: skip
    finally:
        for proc in [*hosts, router]:
            if proc.proc.poll() is None:
                proc.proc.terminate()
        for proc in [*hosts, router]:
            try:
                proc.proc.wait(60)
            except subprocess.TimeoutExpired:
                pass
            proc.close()
    result["load_at_end"] = load_average()
    return result


def report(r: dict[str, Any]) -> str:
    """The results as text."""
    m = r["machine"]
    whole = r["all_pages"]
    lines = [
        f"# python benchmarks/fleet_listing.py --processes {r['processes']} --per-process {r['per_process']} --page {r['page']}",
        f"machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}, Zenoh {m['zenoh']}",
        f"{r['managers']} managers behind one router, {r['per_process']} in each of {r['processes']} processes: "
        f"started in {r['start']['seconds']} s (load {r['start']['load']:.1f}; {r['start']['refused']} refused by the router at first), "
        f"all named by the client {r['all_named_after_s']} s later",
        f"memory: PSS {r['memory']['pss_mib_per_manager']} MiB per manager, {r['memory']['pss_mib_per_process']} MiB per host process, "
        f"router {r['memory']['router_pss_mib']} MiB; at most {r['start']['threads_per_process']} threads in a host process",
        f"names (one liveliness query): p50 {r['names']['p50_ms']} ms, max {r['names']['max_ms']} ms (load {r['names']['load']:.1f})",
        f"first page of {r['page']} (names + {r['page']} brief summaries): p50 {r['first_page']['p50_ms']} ms, max {r['first_page']['max_ms']} ms, "
        f"listed {r['first_page']['listed']} of {r['first_page']['total']} (load {r['first_page']['load']:.1f})",
        f"the whole fleet, page by page: {whole['pages']} pages in {whole['seconds']} s (a page p50 {whole['p50_ms']} ms), "
        f"{whole['listed']} listed, each exactly once: {whole['each_once']} (load {whole['load']:.1f})",
        f"a page of {r['model_page']['listed']} models (get_federated_model): {r['model_page']['ms']} ms",
        f"dyknow managers --limit {r['page']} --json (a process, its start-up included): p50 {r['managers_cmd']['p50_ms']} ms, "
        f"listed {r['managers_cmd']['listed']}; it said: {r['managers_cmd']['said']!r} (load {r['managers_cmd']['load']:.1f})",
        f"target: a fleet-wide listing of {r['managers']} managers works, in pages: "
        + ("met" if whole["each_once"] and all(n == min(r["page"], r["managers"]) for n in r["managers_cmd"]["listed"]) else "NOT met"),
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    """Run the benchmark (or, with --host, be one of its host processes)."""
    if len(sys.argv) == 5 and sys.argv[1] == "--host":
        host(sys.argv[2], sys.argv[3], int(sys.argv[4]))
        return 0
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--processes", type=int, default=10, help="host processes (default 10)")
    parser.add_argument("--per-process", type=int, default=100, help="managers in each (default 100)")
    parser.add_argument("--page", type=int, default=100, help="managers per page (default 100)")
    parser.add_argument("--repeats", type=int, default=5, help="timed names and first-page calls (default 5)")
    parser.add_argument("--cmd-runs", type=int, default=3, help="dyknow managers runs (default 3)")
    parser.add_argument("--json", type=Path, default=RESULTS / "fleet-listing.json", help="write the results here")
    parser.add_argument("--txt", type=Path, default=RESULTS / "fleet-listing.txt", help="write the report here")
    args = parser.parse_args()
    result = run(args)
    text = report(result)
    print(text, end="")
    write_json(args.json, result)
    args.txt.parent.mkdir(parents=True, exist_ok=True)
    args.txt.write_text(text)
    print(f"wrote {args.txt}")
    return 0 if "NOT met" not in text else 1


if __name__ == "__main__":
    sys.exit(main())
