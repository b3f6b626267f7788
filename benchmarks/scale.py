"""Many managers: discovery, planning across managers and memory, with 20 managers of 50 units each.

``--managers`` ``dyknow manager`` processes (default 20, named ``m0`` ...) run on loopback, all
connected to the first (``m0``, the hub); gossip lets them find each other. Each has a small
library of its own, generated in a temporary folder: ``src-<i>`` (an idle
``dyknow.testing:Source``, tag ``Idle(m<i>)``) and ``feed-<i>`` (tag ``Feed(m<i>)``); ``m0``
also has ``join``, a relay with one input per producer manager, each needing a tag only one other
manager provides (``Feed(m<k>)`` for the last five managers), and output ``Joined``. After
discovery, ``--units`` units of ``src-<i>`` (default 50) are spawned on every manager through the
client. Measured:

- discovery: from the moment every manager process printed its ready line until a request of
  ``Joined`` on ``m0`` (which needs ``feed-<k>`` from five other managers) can be planned, and
  until ``Client.managers()`` lists every manager (each answering ``get_summary``); also the
  start-up itself (from launching the processes to the last ready line);
- planning end to end: ``client.request("Joined")`` on ``m0`` through the request service, which
  plans over every manager's library and running units and spawns ``join`` on ``m0`` and the five
  feeds on five managers through their spawn services, then ``client.release(key)``;
- planning alone, offline: a :class:`dyknow.planner.Planner` over the same libraries and the same
  running units, ``plan("Joined", running=...)``, cold (a new Planner each time) and warm;
- memory: the resident set (``VmRSS``) of each manager process once its units run and it settled.

    python benchmarks/scale.py                     # 20 managers x 50 units
    python benchmarks/scale.py --managers 10 --units 20 --json out/scale.json
    python benchmarks/scale.py --smoke             # 4 managers x 5 units
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from dyknow import Client
from dyknow.errors import DyKnowError
from dyknow.planner import Planner, RunningUnit
from dyknow.spec import load_specs

from harness import Proc, free_ports, machine, memory_mib, percentile, write_json

PRODUCERS = 5  # managers the joined request spans


def producers(managers: int) -> list[int]:
    """The managers whose feeds ``join`` needs: the last five (fewer when there are fewer other managers)."""
    k = min(PRODUCERS, managers - 1)
    return list(range(managers - k, managers))


def library_xml(i: int, feeds: list[int]) -> str:
    """Manager ``m<i>``'s library: ``src-<i>``, ``feed-<i>`` and, on ``m0``, ``join`` over ``feeds``."""
    specs = [
        f"""  <transformation>
    <label>src-{i}</label>
    <source>dyknow.testing:Source</source>
    <ports><port type="out">out</port></ports>
    <tags><tag port="out">Idle(m{i})</tag></tags>
  </transformation>""",
        f"""  <transformation>
    <label>feed-{i}</label>
    <source>dyknow.testing:Source</source>
    <ports><port type="out">out</port></ports>
    <tags><tag port="out">Feed(m{i})</tag></tags>
  </transformation>""",
    ]
    if i == 0:
        ports = "".join(f'<port type="in">in{k}</port>' for k in feeds)
        tags = "".join(f'<tag port="in{k}">Feed(m{k})</tag>' for k in feeds)
        specs.append(f"""  <transformation>
    <label>join</label>
    <source>transformations.generic:Relay</source>
    <ports>{ports}<port type="out">out</port></ports>
    <tags>{tags}<tag port="out">Joined</tag></tags>
  </transformation>""")
    return '<?xml version="1.0" encoding="UTF-8"?>\n<transformations>\n' + "\n".join(specs) + "\n</transformations>\n"


def memory_summary(pids: list[int]) -> dict[str, Any]:
    """Mean and max of each figure of :func:`memory_mib` over the processes ``pids``, and every VmRSS."""
    rows = [memory_mib(pid) for pid in pids]
    out: dict[str, Any] = {}
    for name in ("rss", "anon", "file", "shmem", "pss"):
        values = [r.get(name, float("nan")) for r in rows]
        out[f"{name}_mean_mib"] = round(sum(values) / len(values), 1)
        out[f"{name}_max_mib"] = round(max(values), 1)
    out["rss_mib"] = [round(r["rss"], 1) for r in rows]
    return out


def stats(samples: list[float], digits: int = 2) -> dict[str, Any]:
    """Count, p50, p99 and max of ``samples`` (ms)."""
    return {
        "count": len(samples),
        "p50_ms": percentile(samples, 50, digits),
        "p99_ms": percentile(samples, 99, digits),
        "max_ms": round(max(samples), digits) if samples else float("nan"),
    }


def discover(client: Client, managers: int, since: float, timeout_s: float) -> dict[str, float]:
    """Seconds from ``since`` until a request of ``Joined`` on ``m0`` can be planned, and until
    ``client.managers()`` lists all ``managers``; both watched at once, on two threads."""
    out: dict[str, float] = {}
    errors: list[BaseException] = []
    deadline = since + timeout_s

    last: list[str] = []  # (why the latest request failed, for the error when none succeeded)

    def plannable() -> None:
        while time.monotonic() < deadline:
            try:
                key = client.request("Joined")
            except DyKnowError as exc:
                last[:] = [str(exc)]
                time.sleep(0.05)
                continue
            out["plannable_s"] = time.monotonic() - since
            client.release(key)
            return

    def listed() -> None:
        while time.monotonic() < deadline:
            if len(client.managers(timeout_s=1.0)) >= managers:
                out["listed_s"] = time.monotonic() - since
                return
            time.sleep(0.05)

    def guard(fn: Any) -> Any:
        def run() -> None:
            try:
                fn()
            except BaseException as exc:  # noqa: BLE001 - reported below
                errors.append(exc)

        return run

    threads = [threading.Thread(target=guard(fn)) for fn in (plannable, listed)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    missing = [k for k in ("plannable_s", "listed_s") if k not in out]
    if missing:
        why = f"; the latest request said: {last[0]}" if last and "plannable_s" in missing else ""
        raise RuntimeError(f"discovery not complete within {timeout_s} s: {missing} never happened{why}")
    return out


def offline_planning(paths: list[Path], units: int, feeds: list[int], repeats: int) -> dict[str, Any]:
    """Time ``Planner.plan("Joined")`` over the same libraries and running units: cold (a new Planner each time) and warm."""
    libraries = {f"m{i}": load_specs([p]) for i, p in enumerate(paths)}
    local = libraries.pop("m0")
    running = [
        RunningUnit(f"src{j}", f"src-{i}", {"out": f"dyknow/m{i}/src{j}/out"}, {"out": (f"Idle(m{i})",)}, True, None if i == 0 else f"m{i}")
        for i in range(len(paths)) for j in range(units)
    ]  # fmt: skip
    load = {f"m{i}": units for i in range(len(paths))}
    cold, warm = [], []
    plan = None
    for _ in range(repeats):
        start = time.perf_counter()
        planner = Planner(local, manager="m0", peers=libraries)
        plan = planner.plan("Joined", running=running, load=load)
        cold.append((time.perf_counter() - start) * 1000)
    planner = Planner(local, manager="m0", peers=libraries)
    planner.plan("Joined", running=running, load=load)
    for _ in range(repeats):
        start = time.perf_counter()
        plan = planner.plan("Joined", running=running, load=load)
        warm.append((time.perf_counter() - start) * 1000)
    assert plan is not None
    where = sorted({u.manager for u in plan.units})
    expected = sorted({"m0", *(f"m{k}" for k in feeds)})
    if where != expected:
        raise RuntimeError(f"the offline plan runs on {where}; expected {expected}")
    return {"cold": stats(cold, 3), "warm": stats(warm, 3), "plan_units": len(plan.units), "plan_managers": where,
            "running_units": len(running), "specs": sum(len(s) for s in libraries.values()) + len(local)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """Start the managers, measure discovery, spawn the units, measure memory and planning, print it all."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--managers", type=int, default=None, help="manager processes (default 20; --smoke 4)")
    parser.add_argument("--units", type=int, default=None, help="idle units per manager (default 50; --smoke 5)")
    parser.add_argument("--requests", type=int, default=None, help="timed request/release pairs (default 20; --smoke 3)")
    parser.add_argument(
        "--settle", type=float, default=None, help="seconds to let things settle before reading memory (default 5; --smoke 1)"
    )
    parser.add_argument("--smoke", action="store_true", help="a quick run: 4 managers x 5 units")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    n = args.managers if args.managers is not None else (4 if args.smoke else 20)
    units = args.units if args.units is not None else (5 if args.smoke else 50)
    repeats = args.requests if args.requests is not None else (3 if args.smoke else 20)
    settle = args.settle if args.settle is not None else (1.0 if args.smoke else 5.0)
    if n < 2:
        parser.error("--managers: expected at least 2")
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the finally blocks: every child killed
    feeds = producers(n)

    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}", flush=True)
    print(f"{n} manager processes on loopback, all connected to m0; {units} idle units each; "
          f"'Joined' on m0 needs feeds of {len(feeds)} other managers ({', '.join(f'm{k}' for k in feeds)})", flush=True)  # fmt: skip
    procs: list[Proc] = []
    results: dict[str, Any] = {"managers": n, "units_per_manager": units, "producer_managers": len(feeds)}
    with tempfile.TemporaryDirectory(prefix="dyknow-scale-") as tmp:
        paths = []
        for i in range(n):
            path = Path(tmp) / f"m{i}.xml"
            path.write_text(library_xml(i, feeds))
            paths.append(path)
        ports = free_ports(n)
        hub = f"tcp/127.0.0.1:{ports[0]}"

        def launch(i: int) -> Proc:
            argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", f"m{i}", "--specs", str(paths[i]),
                    "--listen", f"tcp/127.0.0.1:{ports[i]}", *(["--connect", hub] if i else []), "--json"]  # fmt: skip
            proc = Proc(argv)
            procs.append(proc)
            return proc

        try:
            launch(0).next_json(60, event="ready")
            # the others all at once
            start = time.monotonic()
            for i in range(1, n):
                launch(i)
            launched = time.monotonic()
            for proc in procs[1:]:
                proc.next_json(120, event="ready")
            ready = time.monotonic()
            print(f"\nstart-up: {n - 1} manager processes launched at once (in {launched - start:.2f} s), "
                  f"all printed their ready line {ready - launched:.2f} s after the last launch", flush=True)  # fmt: skip

            with Client("m0", connect=[hub], timeout_s=10) as client:
                try:
                    found = discover(client, n, ready, timeout_s=120)
                except RuntimeError as exc:  # (what m0 logged says why its plans failed)
                    raise RuntimeError(f"{exc}\nm0's log, its end: {procs[0].error_tail()}") from None
                results["discovery"] = {"startup_s": round(ready - launched, 3), **{k: round(v, 3) for k, v in found.items()}}
                up = ready - launched
                print(
                    f"discovery, from the last ready line: a request on m0 spanning {len(feeds)} other managers plannable after "
                    f"{found['plannable_s'] * 1000:.0f} ms; Client.managers() (a fresh client session) lists all {n} after "
                    f"{found['listed_s'] * 1000:.0f} ms",
                    flush=True,
                )
                print(f"discovery, from the last launch (start-up included): plannable after {up + found['plannable_s']:.2f} s, "
                      f"all {n} listed after {up + found['listed_s']:.2f} s", flush=True)  # fmt: skip

                time.sleep(settle)
                baseline = memory_summary([p.proc.pid for p in procs])
                spawn_ms = []
                t0 = time.monotonic()
                for i in range(n):
                    with Client(f"m{i}", session=client.session, timeout_s=10) as on:
                        for j in range(units):
                            s = time.perf_counter()
                            on.spawn(f"src-{i}", f"src{j}")
                            spawn_ms.append((time.perf_counter() - s) * 1000)
                spawn_s = time.monotonic() - t0
                results["spawn"] = {**stats(spawn_ms), "total_s": round(spawn_s, 2)}
                print(f"spawned {n * units} units through the client in {spawn_s:.2f} s: p50 {percentile(spawn_ms, 50, 2)} ms, "
                      f"p99 {percentile(spawn_ms, 99, 2)} ms per spawn call", flush=True)  # fmt: skip
                deadline = time.monotonic() + 60
                while sum(m["units"] for m in client.managers()) < n * units:
                    if time.monotonic() > deadline:
                        raise RuntimeError("the managers' summaries do not list every unit within 60 s")
                    time.sleep(0.2)
                time.sleep(settle)
                memory = memory_summary([p.proc.pid for p in procs])
                results["memory"] = {"before_units": baseline, "with_units": memory, "settle_s": settle}
                print(
                    f"memory per manager process, {units} idle units each, {settle:g} s after the summaries listed every unit:", flush=True
                )
                for label, m in ((f"with {units} units", memory), ("before (after discovery)", baseline)):
                    print(f"  {label:<25} VmRSS mean {m['rss_mean_mib']:.1f} MiB, max {m['rss_max_mib']:.1f} MiB; of which "
                          f"private (RssAnon) mean {m['anon_mean_mib']:.1f}, files (RssFile) {m['file_mean_mib']:.1f}, "
                          f"shared memory (RssShmem) {m['shmem_mean_mib']:.1f}; PSS mean {m['pss_mean_mib']:.1f} MiB", flush=True)  # fmt: skip
                print("  RssShmem: the Zenoh shared-memory segments (/dev/shm/*.zenoh) the process maps, its own and the other "
                      "managers'; they exist once in RAM but count in the VmRSS of every process mapping them (PSS shares them out)", flush=True)  # fmt: skip

                request_ms, release_ms, spanned = [], [], set()
                for _ in range(repeats):
                    time.sleep(0.3)  # let the managers' summaries catch up with the last release
                    s = time.perf_counter()
                    key = client.request("Joined")
                    request_ms.append((time.perf_counter() - s) * 1000)
                    (req,) = client.get_model()["requests"]
                    spanned.add(tuple(sorted(u.rsplit("@", 1)[1] for u in req["units"] if "@" in u)))
                    s = time.perf_counter()
                    client.release(key)
                    release_ms.append((time.perf_counter() - s) * 1000)
                results["request_service"] = {**stats(request_ms), "release": stats(release_ms), "remote_managers": sorted(spanned)}
            expected = tuple(f"m{k}" for k in feeds)
            if spanned != {expected}:
                print(f"warning: the requests' remote units ran on {sorted(spanned)}; expected {expected} every time", flush=True)
        finally:
            for proc in reversed(procs):
                proc.close()

        offline = offline_planning(paths, units, feeds, max(repeats, 20) * 5)
    results["planner_offline"] = offline

    e2e = results["request_service"]
    print(f"\nplanning a request whose producers span {len(feeds)} managers ({n} managers, {n * units} running units):")
    print(f"  end to end, client.request('Joined') on m0 (plan, spawn join on m0 and a feed on each of {len(feeds)} managers through "
          f"their spawn services, wire): p50 {e2e['p50_ms']:.1f} ms, p99 {e2e['p99_ms']:.1f} ms over {e2e['count']} requests")  # fmt: skip
    print(
        f"  client.release(key) (destroy the {len(feeds) + 1} units): p50 {e2e['release']['p50_ms']:.1f} ms, p99 {e2e['release']['p99_ms']:.1f} ms"
    )
    print(f"  planner alone, offline ({offline['specs']} specs, {offline['running_units']} running units): "
          f"cold (new Planner + plan) p50 {offline['cold']['p50_ms']:.2f} ms, p99 {offline['cold']['p99_ms']:.2f} ms; "
          f"warm p50 {offline['warm']['p50_ms']:.2f} ms, p99 {offline['warm']['p99_ms']:.2f} ms over {offline['warm']['count']} plans")  # fmt: skip
    if args.json:
        write_json(args.json, {"machine": info, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
