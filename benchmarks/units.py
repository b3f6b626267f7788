"""Many units in one manager, and many spawns and destroys: threads, memory, time, latency.

Two measurements, in this order, each with a manager of its own in this process (it serves
and federates, as a ``dyknow manager`` does):

- **churn**: spawn/destroy cycles of a relay on a key of its own that is rebound once
  (``set_config``) before it goes, with a source running throughout: ``--warmup`` cycles
  (default 2,000: the allocator's arenas grow by a few MB over the first thousand, then stay),
  then ``--blocks`` blocks (default 5) of ``--cycles`` cycles (default 1,000). Printed: the
  resident set (``VmRSS``, after a garbage collection) after each block, the growth per block
  (the average over all blocks) against the target (< 1 MB per 1,000 cycles), and the manager's
  own counts of per-unit structures (:meth:`Manager.resources`) before and after;
- **many**: ``--units`` relay units (default 10,000) in chains of 60 (a message passed on by
  :data:`dyknow.message.MAX_FORWARDS` = 63 relays is dropped as a relay cycle, issue 38), spawned
  one after the other through the Python API, every chain fed by one periodic source, the last
  relay of the first chain feeding a sink. Printed:
  the time to spawn them all against the target (<= 10 s), the process's threads (from
  ``/proc``) against the target (<= 64), the resident set before and after (and per unit), the
  end-to-end age of the messages through the first chain at the sink (p50/p99) and per hop,
  then the time to destroy them all.

    python benchmarks/units.py                            # 1,000 cycles, 10,000 units
    python benchmarks/units.py --units 2000 --cycles 200 --json out/units.json
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from dyknow import Manager
from dyknow.resources import specs_dir
from dyknow.spec import Port, TransformationSpec

from harness import machine, write_json

SINK = TransformationSpec(label="sink", source="dyknow.testing:Sink", ports=(Port("in", "in"),))
MAX_THREADS = 64
SPAWN_ALL_S = 10.0
CHURN_GROWTH_MB = 1.0
CHAIN = 60  # relays per chain: under dyknow.message.MAX_FORWARDS, the relay-cycle guard


def rss_mb() -> float:
    """This process's resident set, in MB, after a full garbage collection."""
    gc.collect()
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def os_threads() -> int:
    """The threads of this process, as the OS counts them (Zenoh's own included)."""
    return len(os.listdir("/proc/self/task"))


def churn(warmup: int, cycles: int, blocks: int) -> dict[str, Any]:
    """Spawn, rebind and destroy a relay ``warmup`` times, then ``blocks`` x ``cycles`` times,
    reading the RSS after every block; the growth per block is the average over them all."""
    with Manager("churn", specs=[specs_dir() / "generic.xml"]) as manager:
        manager.spawn("periodic-source", "src", params={"rate_hz": 200})

        def cycle(i: int) -> None:
            manager.spawn("relay", f"r{i}", bindings={"in": f"churn/{i}"})
            manager.set_config(f"r{i}", {"in": "dyknow/churn/src/out"})
            manager.destroy(f"r{i}")

        warm_before = rss_mb()
        for i in range(warmup):
            cycle(i)
        time.sleep(0.3)  # the adaptation loop and the directory settle
        rss = [rss_mb()]
        counts_before = manager.resources()
        started = time.perf_counter()
        i = warmup
        for _ in range(blocks):
            for _ in range(cycles):
                cycle(i)
                i += 1
            time.sleep(0.3)
            rss.append(rss_mb())
        elapsed = time.perf_counter() - started - 0.3 * blocks
        counts_after = manager.resources()
    return {
        "cycles": cycles,
        "blocks": blocks,
        "warmup": warmup,
        "seconds_per_block": round(elapsed / blocks, 3),
        "rss_before_warmup_mb": round(warm_before, 2),
        "rss_mb": [round(r, 2) for r in rss],
        "growth_mb": round((rss[-1] - rss[0]) / blocks, 3),
        "resources_before": counts_before,
        "resources_after": counts_after,
    }


def many(units: int, rate_hz: float, listen_s: float) -> dict[str, Any]:
    """``units`` relays in chains of :data:`CHAIN` in one manager: spawn time, threads, memory, latency."""
    threads_before, rss_before = os_threads(), rss_mb()
    with Manager("many", specs=[specs_dir() / "generic.xml"]) as manager:
        started = time.perf_counter()
        for i in range(units):
            upstream = f"dyknow/many/r{i - 1}/out" if i % CHAIN else "dyknow/many/src/out"
            manager.spawn("relay", f"r{i}", bindings={"in": upstream})
        spawn_s = time.perf_counter() - started
        hops = min(units, CHAIN) + 1
        manager.spawn(SINK, "sink", bindings={"in": f"dyknow/many/r{hops - 2}/out"})
        manager.spawn("periodic-source", "src", params={"rate_hz": rate_hz})
        time.sleep(listen_s)
        threads, rss = os_threads(), rss_mb()
        stats = manager.get_statistics("sink").ports[0]
        py_threads = threading.active_count()
        started = time.perf_counter()
        for i in range(units):
            manager.destroy(f"r{i}")
        destroy_s = time.perf_counter() - started
        resources = manager.resources()
    latency = stats.latency
    return {
        "units": units,
        "spawn_s": round(spawn_s, 3),
        "spawn_per_s": round(units / spawn_s, 1),
        "os_threads_before": threads_before,
        "os_threads": threads,
        "python_threads": py_threads,
        "rss_before_mb": round(rss_before, 1),
        "rss_mb": round(rss, 1),
        "rss_per_unit_kb": round((rss - rss_before) * 1024 / units, 1),
        "messages_at_sink": stats.messages,
        "dropped_at_sink": stats.dropped,
        "end_to_end_p50_ms": round(latency.p50_us / 1000, 3),
        "end_to_end_p99_ms": round(latency.p99_us / 1000, 3),
        "hops": hops,
        "per_hop_p50_us": round(latency.p50_us / hops, 3),
        "per_hop_p99_us": round(latency.p99_us / hops, 3),
        "destroy_s": round(destroy_s, 3),
        "resources_after_destroy": resources,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the churn and the many-units measurements; print the figures beside their targets."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--units", type=int, default=10_000, help="relays, in chains of 60 (default 10,000)")
    parser.add_argument("--cycles", type=int, default=1000, help="spawn/destroy cycles measured (default 1,000)")
    parser.add_argument("--blocks", type=int, default=5, help="blocks of --cycles cycles measured (default 5)")
    parser.add_argument("--warmup", type=int, default=2000, help="cycles before measuring (default 2,000: the allocator settles)")
    parser.add_argument("--rate-hz", type=float, default=5.0, help="the source's rate through the chain (default 5: at 20 Hz, 10,000 hops of about 5 us keep one core busy)")
    parser.add_argument("--listen-s", type=float, default=3.0, help="how long messages flow through the chain (default 3)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)

    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}")
    c = churn(args.warmup, args.cycles, args.blocks)
    churn_met = c["growth_mb"] < CHURN_GROWTH_MB
    print(f"\nchurn: {c['blocks']} blocks of {c['cycles']} spawn/set_config/destroy cycles, after {c['warmup']} (RSS {c['rss_before_warmup_mb']:.1f} MB before those)")
    print(f"  {c['seconds_per_block']:.2f} s per block; RSS after each block: {', '.join(f'{r:.1f}' for r in c['rss_mb'])} MB")
    print(f"  per-unit structures before {c['resources_before']}")
    print(f"                      after  {c['resources_after']}")
    print(
        f"target: RSS growth per {c['cycles']} cycles < {CHURN_GROWTH_MB:g} MB: {c['growth_mb']:+.3f} MB "
        f"(average over {c['blocks']} blocks): {'met' if churn_met else 'MISSED'}"
    )

    m = many(args.units, args.rate_hz, args.listen_s)
    spawn_met = m["spawn_s"] <= SPAWN_ALL_S
    threads_met = m["os_threads"] <= MAX_THREADS
    print(f"\nmany: {m['units']:,} relays in chains of {CHAIN} from one source, in one manager")
    print(f"  spawned in {m['spawn_s']:.2f} s ({m['spawn_per_s']:,.0f} per second); destroyed in {m['destroy_s']:.2f} s")
    print(f"  threads: {m['os_threads']} (OS; {m['python_threads']} Python), {m['os_threads_before']} before the manager")
    print(f"  RSS {m['rss_before_mb']:.0f} MB -> {m['rss_mb']:.0f} MB ({m['rss_per_unit_kb']:.1f} kB per unit)")
    print(
        f"  through the first chain's {m['hops']} hops at {args.rate_hz:g} Hz: {m['messages_at_sink']} messages at the sink ({m['dropped_at_sink']} dropped), "
        f"age p50 {m['end_to_end_p50_ms']:.2f} ms, p99 {m['end_to_end_p99_ms']:.2f} ms; "
        f"per hop p50 {m['per_hop_p50_us']:.2f} us, p99 {m['per_hop_p99_us']:.2f} us"
    )
    print(f"target: spawn all within {SPAWN_ALL_S:g} s: {m['spawn_s']:.2f} s: {'met' if spawn_met else 'MISSED'}")
    print(f"target: <= {MAX_THREADS} threads: {m['os_threads']}: {'met' if threads_met else 'MISSED'}")
    if args.json:
        targets = {"churn_growth": churn_met, "spawn_all": spawn_met, "threads": threads_met}
        write_json(args.json, {"machine": info, "churn": c, "many": m, "targets": targets})
    return 0


if __name__ == "__main__":
    sys.exit(main())
