"""What one Zenoh session's cost of a new key does as the session holds more keys (issue 41, item 4).

A dyknow manager declares, for each unit, a publisher per output port (with a matching listener
and a liveliness token) and a subscriber per input bound outside its namespace. This measures
those declarations with raw Zenoh, with no dyknow in the way: one session (peer, no listener,
scouting off) declares ``--keys`` entities of one kind, each on a key of its own
(``bench/k<i>/out``), and prints the seconds per 1,000 declarations block by block. Then, with the
session holding them, one ``put`` on a key nobody declared, and the same kind declared again on one
key shared by all (``bench/same``), against a fresh session.

Zenoh 1.10 on a 2-core machine (issue 41; ``--keys 6000``, load average 6): per 1,000 on keys of
their own, from the first block to the sixth, publishers 0.07 -> 1.16 s, publishers with a matching
listener 0.07 -> 1.54 s, subscribers 0.15 -> 2.48 s, liveliness tokens 0.05 -> 1.62 s; a put on a
fresh key 2 us in an empty session, 2.4 ms beside 6,000 publishers; declarations on one shared key
do not grow. The kind ``put`` declares nothing: one ``put`` on each fresh key, what an output
port without a publisher of its own would cost. ``--shard N`` spreads the keys N to a node of
the key tree: Zenoh looks for the declarations a new key matches by trying every sibling of each
node on its path (``Resource::get_matches`` in zenoh/src/net/routing/dispatcher/resource.rs), so
keys with fewer siblings cost less. So a manager's spawn cost is flat only if what it declares per unit is not a key of
its own: the target printed is the one issue 41 sets for spawn (the last block within 1.5x of the
first), to show what Zenoh itself allows.

    python benchmarks/zenoh_keys.py                     # 10,000 of each kind
    python benchmarks/zenoh_keys.py --keys 2000 --json out/zenoh_keys.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from harness import machine, write_json

FLAT_RATIO = 1.5  # issue 41's spawn target: the last block within 1.5x of the first
KINDS = ("publisher", "publisher+listener", "subscriber", "token", "put")


def _session() -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    return zenoh.open(conf)


def _declarer(session: zenoh.Session, kind: str, keep: list[Any]) -> Callable[[str], None]:
    remote = zenoh.Locality.REMOTE

    def declare(key: str) -> None:
        if kind == "put":  # nothing declared: one put on the key (what an output without a publisher would cost)
            session.put(key, b"12345678", allowed_destination=remote)
        elif kind == "subscriber":
            keep.append(session.declare_subscriber(key, zenoh.handlers.Callback(lambda s: None, indirect=False), allowed_origin=remote))
        elif kind == "token":
            keep.append(session.liveliness().declare_token(key))
        else:
            pub = session.declare_publisher(key, allowed_destination=remote)
            keep.append(pub)
            if kind == "publisher+listener":
                keep.append(pub.declare_matching_listener(zenoh.handlers.Callback(lambda s: None, indirect=False)))

    return declare


def _key(i: int, shard: int) -> str:
    """The ``i``-th key: ``bench/k<i>/out``, or with ``shard`` ``bench/<i // shard>/k<i>/out`` (at most
    ``shard`` siblings under one node of the key tree)."""
    return f"bench/{i // shard}/k{i}/out" if shard else f"bench/k{i}/out"


def measure(kind: str, count: int, block: int, shard: int = 0) -> dict[str, Any]:
    """Declare ``count`` entities of ``kind`` on keys of their own in one session: seconds per
    1,000 for each ``block``; a put on a fresh key then; ``block`` more on one shared key."""
    keep: list[Any] = []
    session = _session()
    try:
        declare = _declarer(session, kind, keep)
        per_block: list[float] = []
        start = time.perf_counter()
        for i in range(count):
            declare(_key(i, shard))
            if (i + 1) % block == 0:
                now = time.perf_counter()
                per_block.append((now - start) * 1000 / block)
                start = now
        puts = 200
        t0 = time.perf_counter()
        for i in range(puts):
            session.put(f"bench/fresh{i}/out", b"12345678", allowed_destination=zenoh.Locality.REMOTE)
        put_us = (time.perf_counter() - t0) / puts * 1e6
        t0 = time.perf_counter()
        for _ in range(block):
            declare("bench/same")
        same = (time.perf_counter() - t0) * 1000 / block
    finally:
        for entity in reversed(keep):
            entity.undeclare()
        session.close()
    empty = _session()
    try:
        t0 = time.perf_counter()
        for i in range(200):
            empty.put(f"bench/fresh{i}/out", b"12345678", allowed_destination=zenoh.Locality.REMOTE)
        put_empty_us = (time.perf_counter() - t0) / 200 * 1e6
    finally:
        empty.close()
    first, last = per_block[0], per_block[-1]
    return {
        "kind": kind,
        "shard": shard,
        "count": count,
        "block": block,
        "s_per_1000": [round(x, 3) for x in per_block],
        "ratio": round(last / first, 2) if first else None,
        "flat": bool(first) and last <= FLAT_RATIO * first,
        "same_key_s_per_1000": round(same, 3),
        "put_fresh_key_us": round(put_us, 1),
        "put_fresh_key_empty_session_us": round(put_empty_us, 1),
    }


def main(argv: list[str] | None = None) -> int:
    """Run the measurement (see the module documentation)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--keys", type=int, default=10_000, help="entities of each kind, each on a key of its own (default 10,000)")
    parser.add_argument("--kinds", default=",".join(KINDS), help=f"which kinds, comma-separated (default: {','.join(KINDS)})")
    parser.add_argument("--shard", type=int, default=0, metavar="N",
                        help="spread the keys N to a node of the key tree, bench/<i // N>/k<i>/out (default: all under bench/)")  # fmt: skip
    parser.add_argument("--json", type=Path, help="write the results as JSON")
    args = parser.parse_args(argv)
    kinds = [k for k in args.kinds.split(",") if k]
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        parser.error(f"--kinds: got {', '.join(unknown)}; expected some of {', '.join(KINDS)}")
    block = 1000 if args.keys >= 2000 else max(1, args.keys // 10)
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info.get('zenoh')}; load average {os.getloadavg()[0]:.2f}")
    results = []
    for kind in kinds:
        row = measure(kind, args.keys, block, args.shard)
        results.append(row)
        layout = f", {args.shard} to a node" if args.shard else ""
        print(f"{kind:>18}: s per 1,000 on keys of their own{layout}, block by block of {block}: {', '.join(f'{x:.3f}' for x in row['s_per_1000'])}")
        print(f"{'':>18}  last/first {row['ratio']} (target <= {FLAT_RATIO:g}: {'met' if row['flat'] else 'NOT met'}); "
              f"on one shared key {row['same_key_s_per_1000']:.3f} s per 1,000; a put on a fresh key {row['put_fresh_key_us']:.0f} us "
              f"(in an empty session {row['put_fresh_key_empty_session_us']:.0f} us)")  # fmt: skip
    print(f"load average {os.getloadavg()[0]:.2f}")
    if args.json:
        write_json(args.json, {"machine": info, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
