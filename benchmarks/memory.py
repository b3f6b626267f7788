"""What an idle manager costs in memory as the system grows: 1, 10 and 20 managers on one machine.

For each size, that many ``dyknow manager`` processes (the shipped specs and ontology, no units)
start on loopback, every one connected to the first; gossip lets them find each other. Once each
lists all the others (``Client.managers()`` on the first finds them all answering) and a settling
window has passed, every manager's memory is read from ``/proc``:

- ``Pss``: its resident pages, shared ones divided among the processes that map them (what it
  really costs the machine), from ``smaps_rollup``;
- ``VmRSS`` and its part ``RssShmem`` (shared memory it maps, counted in full in every process).

Target: an idle manager's PSS at most 64 MiB whatever the number of managers it knows (the issue
"Safe and quick on a real network", item 4). Before this benchmark, each manager mapped every
other manager's Zenoh shared-memory pool (Zenoh's transport put every message over 3 KiB, the
managers' summaries among them, in its own 16 MiB pool): 20 managers cost 104.5 MiB PSS each.

    python benchmarks/memory.py                   # 1, 10 and 20 managers
    python benchmarks/memory.py --sizes 1,4 --settle 2 --json out/memory.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from dyknow import Client
from dyknow.resources import specs_dir

from harness import Proc, free_ports, machine, memory_mib, write_json

TARGET_PSS_MIB = 64.0


def run(size: int, settle_s: float) -> dict[str, Any]:
    """``size`` managers on loopback until they all know each other; their memory."""
    ports = free_ports(size)
    hub = f"tcp/127.0.0.1:{ports[0]}"
    specs = specs_dir()
    procs: list[Proc] = []
    try:
        for i, port in enumerate(ports):
            argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", f"m{i}", "--specs", str(specs),
                    "--ontology", str(specs / "dyknow.ttl"), "--listen", f"tcp/127.0.0.1:{port}", "--json",
                    *(["--connect", hub] if i else [])]  # fmt: skip
            procs.append(Proc(argv))
        for proc in procs:
            proc.next_json(60, event="ready")
        started = time.monotonic()
        with Client("m0", connect=[hub], timeout_s=10) as client:
            while len(client.managers()) < size:
                if time.monotonic() - started > 120:
                    raise RuntimeError(f"the {size} managers did not find each other within 120 s")
                time.sleep(0.5)
        joined_s = time.monotonic() - started
        time.sleep(settle_s)
        rows = [memory_mib(p.proc.pid) for p in procs]
    finally:
        for proc in reversed(procs):
            proc.close()
    pss = [r["pss"] for r in rows]
    return {
        "managers": size,
        "joined_s": round(joined_s, 1),
        "pss_max_mib": round(max(pss), 1),
        "pss_mean_mib": round(sum(pss) / len(pss), 1),
        "rss_max_mib": round(max(r["rss"] for r in rows), 1),
        "shmem_max_mib": round(max(r["shmem"] for r in rows), 1),
        "target_pss_mib": TARGET_PSS_MIB,
        "met": max(pss) <= TARGET_PSS_MIB,
    }


def main(argv: list[str] | None = None) -> int:
    """Measure each size and print its figures beside the target."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1,10,20", help="numbers of managers, comma-separated (default 1,10,20)")
    parser.add_argument("--settle", type=float, default=5.0, help="seconds to wait once they know each other (default 5)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}", flush=True)
    print(f"idle managers (shipped specs, no units) on loopback, all connected to m0; measured {args.settle:g} s after they "
          "all know each other\n", flush=True)  # fmt: skip
    print(f"{'managers':>8} {'PSS max':>10} {'PSS mean':>10} {'RSS max':>10} {'shmem max':>10}", flush=True)
    rows = []
    for size in sizes:
        row = run(size, args.settle)
        rows.append(row)
        verdict = f"target PSS <= {TARGET_PSS_MIB:g} MiB: {'met' if row['met'] else 'NOT met'}"
        print(f"{size:>8} {row['pss_max_mib']:>7.1f} MiB {row['pss_mean_mib']:>6.1f} MiB {row['rss_max_mib']:>6.1f} MiB "
              f"{row['shmem_max_mib']:>6.1f} MiB   {verdict}", flush=True)  # fmt: skip
    if args.json:
        write_json(args.json, {"machine": info, "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
