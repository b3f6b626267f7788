"""Runtime operations while messages flow: rebinding a port, spawning and destroying a unit.

A source publishes at ``--rate`` Hz to a witness sink that is never touched. Meanwhile the
benchmark rebinds another unit's input back and forth between two keys (``set_config``), and
spawns and destroys a relay on the same stream, many times. It reports the median and p99 time of
each operation, in-process (Python API) and through the Zenoh service (a client in a second
session), and the messages the witness lost (must be zero).

    python benchmarks/runtime_ops.py --json out/runtime_ops.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dyknow import Client, Manager, Message, TransformationSpec, Unit
from dyknow.resources import specs_dir
from dyknow.spec import Port

from harness import machine, write_json

TARGET_REBIND_P99_MS = 1.0


class Witness(Unit):
    """Counts what arrives and the gaps in the sequence numbers."""

    def setup(self) -> None:
        """Start the counters at zero."""
        self.received = 0
        self.last_seq = 0
        self.gaps = 0
        self.duplicates = 0

    def on_message(self, port: str, msg: Message) -> None:
        """Count the message, and the sequence numbers skipped or repeated since the previous one."""
        self.received += 1
        if self.last_seq and msg.seq != self.last_seq + 1:
            if msg.seq <= self.last_seq:
                self.duplicates += 1
            else:
                self.gaps += msg.seq - self.last_seq - 1
        self.last_seq = max(self.last_seq, msg.seq)


def specs() -> list[TransformationSpec]:
    """The witness's spec."""
    module = __name__ if __name__ != "__main__" else "__main__"
    return [TransformationSpec("witness", f"{module}:Witness", ports=(Port("in", "in"),))]


def stats(samples_s: list[float]) -> dict[str, float]:
    """Median and p99 in milliseconds of durations given in seconds, and their count."""
    ms = np.asarray(samples_s) * 1000
    return {"median_ms": round(float(np.median(ms)), 3), "p99_ms": round(float(np.percentile(ms, 99)), 3), "count": len(ms)}


def main(argv: list[str] | None = None) -> int:
    """Time rebinds (in-process and via the service), spawns and destroys while a stream flows; print them and the witness's losses."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--rate", type=float, default=1000.0, help="source rate in Hz while operations run")
    parser.add_argument("--smoke", action="store_true", help="a few iterations (CI)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    n = 10 if args.smoke else args.iterations
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}")
    generic = specs_dir() / "generic.xml"
    results: dict[str, Any] = {}
    with Manager("ops", specs=[generic, *specs()], listen=["tcp/127.0.0.1:0"]) as manager:
        manager.spawn("periodic-source", "a", params={"rate_hz": args.rate}, bindings={"out": "ops/a"})
        manager.spawn("periodic-source", "b", params={"rate_hz": args.rate}, bindings={"out": "ops/b"})
        manager.spawn("witness", "witness", bindings={"in": "ops/a"})
        manager.spawn("relay", "moving", bindings={"in": "ops/a", "out": "ops/moved"})
        witness = manager.unit("witness")
        assert isinstance(witness, Witness)
        time.sleep(0.2)  # the stream is flowing before the first operation

        def timed(fn: Any) -> float:
            t0 = time.perf_counter()
            fn()
            return time.perf_counter() - t0

        keys = ["ops/b", "ops/a"]
        rebind = [timed(lambda i=i: manager.set_config("moving", {"in": keys[i % 2]})) for i in range(n)]
        spawn, destroy = [], []
        for i in range(n):
            spawn.append(timed(lambda i=i: manager.spawn("relay", f"tmp{i}", bindings={"in": "ops/a"})))
            destroy.append(timed(lambda i=i: manager.destroy(f"tmp{i}")))
        with Client("ops", connect=manager.endpoints) as client:
            client.get_model()  # the link is up before timing
            remote = [timed(lambda i=i: client.set_config("moving", {"in": keys[i % 2]})) for i in range(n)]
        time.sleep(0.1)
        source_sent = manager.get_statistics("a").ports[0].messages
        results = {
            "rebind_inproc": stats(rebind),
            "rebind_service": stats(remote),
            "spawn": stats(spawn),
            "destroy": stats(destroy),
            "witness": {
                "received": witness.received,
                "lost": witness.gaps,
                "duplicated": witness.duplicates,
                "source_sent": source_sent,
                "dropped": manager.get_statistics("witness").ports[0].dropped,
            },
            "rate_hz": args.rate,
            "reconfigurations": manager.get_statistics("moving").reconfigurations,
        }
    for name in ("rebind_inproc", "rebind_service", "spawn", "destroy"):
        r = results[name]
        note = ""
        if name == "rebind_inproc":
            note = f"  target p99 < {TARGET_REBIND_P99_MS:g} ms: {'met' if r['p99_ms'] < TARGET_REBIND_P99_MS else 'MISSED'}"
        print(f"{name:<15} median {r['median_ms']:7.3f} ms   p99 {r['p99_ms']:7.3f} ms   ({r['count']} times){note}")
    w = results["witness"]
    lost_ok = w["lost"] == 0 and w["duplicated"] == 0 and w["dropped"] == 0
    print(
        f"unaffected witness port: {w['received']} received, {w['lost']} lost, {w['duplicated']} duplicated, "
        f"{w['dropped']} dropped while {2 * n} rebinds and {n} spawn/destroy ran at {args.rate:g} Hz "
        f"(target: zero lost): {'met' if lost_ok else 'MISSED'}"
    )
    if args.json:
        write_json(args.json, {"machine": info, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
