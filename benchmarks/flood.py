"""A flood of hostile requests: is a well-formed request from another client still answered?

A ``dyknow manager`` process serves; this process calls ``get_model`` (a well-formed request)
again and again and times each call, first with nothing else going on, then while another
process sends bad requests as fast as it can from several threads: requests over the size limit
(2 MiB), JSON nested 100,000 deep, bytes that are not JSON, unknown fields and unit names of
70 kB. Every bad request must be refused (counted), and the well-formed calls' p99 is printed
beside its value without the flood.

    python benchmarks/flood.py                     # 1,000 bad requests, 300 timed calls per phase
    python benchmarks/flood.py --bad 200 --calls 50 --json out/flood.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

from dyknow.errors import ServiceError
from dyknow.resources import specs_dir
from dyknow.transport import Session, make_config

from harness import free_ports, machine, percentile, write_json

BAD: list[tuple[str, bytes]] = [
    ("get_model", b"{" + b" " * (2 << 20) + b"}"),
    ("get_model", b"[" * 100_000 + b"]" * 100_000),
    ("get_model", b"\xff\xfe not json at all"),
    ("destroy", b'{"name": "x", "force": true}'),
    ("spawn", json.dumps({"label": "relay", "name": "n" * 70_000}).encode()),
]


def timed_calls(session: Session, manager: str, count: int) -> list[float]:
    """Milliseconds each of ``count`` sequential get_model calls took."""
    out = []
    for _ in range(count):
        start = time.perf_counter()
        session.call(f"@dyknow/{manager}/get_model", b"{}", timeout_s=10, what="get_model")
        out.append((time.perf_counter() - start) * 1000)
    return out


def flood_worker(args: argparse.Namespace) -> int:
    """The flooding process: ``--bad`` bad requests from ``--threads`` threads, then a JSON summary."""
    with Session(make_config(connect=[args.connect])) as session:
        session.call(f"@dyknow/{args.manager}/get_model", b"{}", timeout_s=10, what="warm-up")
        counts = {"refused": 0, "answered": 0, "unanswered": 0}
        lock = threading.Lock()
        per_thread = args.bad // args.threads
        print("ready", flush=True)

        def send(offset: int) -> None:
            for i in range(per_thread):
                service, payload = BAD[(offset + i) % len(BAD)]
                try:
                    session.call(f"@dyknow/{args.manager}/{service}", payload, timeout_s=10, what=service)
                    outcome = "answered"
                except ServiceError as exc:
                    outcome = "refused" if exc.kind else "unanswered"
                with lock:
                    counts[outcome] += 1

        start = time.perf_counter()
        threads = [threading.Thread(target=send, args=(t,)) for t in range(args.threads)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        print(json.dumps({**counts, "seconds": round(time.perf_counter() - start, 3)}), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Time well-formed calls without and during a flood of bad ones, side by side."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bad", type=int, default=1000, help="bad requests in the flood (default 1000)")
    parser.add_argument("--threads", type=int, default=4, help="flooding threads (default 4)")
    parser.add_argument("--calls", type=int, default=300, help="timed well-formed calls per phase (default 300)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--connect", help=argparse.SUPPRESS)
    parser.add_argument("--manager", default="flooded", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return flood_worker(args)

    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}")
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    manager = subprocess.Popen(
        [sys.executable, "-m", "dyknow.cli", "manager", "--name", args.manager, "--listen", endpoint, "--specs", str(specs_dir() / "generic.xml")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    flood = None
    try:
        assert manager.stdout is not None and manager.stdout.readline(), "the manager did not start"
        with Session(make_config(connect=[endpoint])) as session:
            timed_calls(session, args.manager, 20)  # warm-up
            quiet = timed_calls(session, args.manager, args.calls)
            flood = subprocess.Popen(
                [sys.executable, __file__, "--worker", "--connect", endpoint, "--manager", args.manager, "--bad", str(args.bad), "--threads", str(args.threads)],
                stdout=subprocess.PIPE, text=True,
            )  # fmt: skip
            assert flood.stdout is not None and flood.stdout.readline().strip() == "ready"
            flooded: list[float] = []
            while flood.poll() is None and len(flooded) < 100 * args.calls:
                flooded += timed_calls(session, args.manager, 1)
            summary = json.loads(flood.stdout.readline())
        manager.terminate()
        exit_code = manager.wait(10)
    finally:
        for proc in (flood, manager):
            if proc is not None and proc.poll() is None:
                proc.kill()
    rows = [
        {"phase": "no flood", "calls": len(quiet), "p50_ms": percentile(quiet, 50), "p99_ms": percentile(quiet, 99)},
        {"phase": f"during {args.bad} bad requests", "calls": len(flooded), "p50_ms": percentile(flooded, 50), "p99_ms": percentile(flooded, 99)},
    ]
    print(f"\n{'get_model from a well-formed client':<40} {'calls':>6} {'p50':>9} {'p99':>9}")
    for row in rows:
        print(f"{row['phase']:<40} {row['calls']:>6} {row['p50_ms']:>6.2f} ms {row['p99_ms']:>6.2f} ms")
    print(
        f"\nflood: {summary['refused']} of {args.bad // args.threads * args.threads} bad requests refused with an error reply, "
        f"{summary['answered']} answered, {summary['unanswered']} unanswered, in {summary['seconds']:.1f} s; "
        f"manager exit code on SIGTERM: {exit_code} (target 0)"
    )
    print(f"target: the well-formed client is still answered: {'met' if flooded and summary['answered'] == 0 else 'MISSED'}")
    if args.json:
        write_json(args.json, {"machine": info, "results": rows, "flood": summary, "exit_code": exit_code})
    return 0 if exit_code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
