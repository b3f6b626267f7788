"""What each message of the federation costs, and so what a fleet of 10, 100 and 1,000 managers pays (issue 40).

The federation's messages (docs/concepts/federation.md, "What a fleet pays"):

- **tokens**: a manager's liveliness token, its clock token and one offer token per tag it offers;
  in Zenoh's peer and router modes every declaration reaches every node, whatever it subscribes
  to; behind a router, a Zenoh client receives only those matching its own subscriptions;
- **offers query**: one liveliness query per tag a plan needs, the first time;
- **summary**: ``get_summary`` of a candidate (once, then its publications while followed);
- **clock exchange**: three a second with each manager one exchanges data or calls with.

Measured here, on loopback:

- the CPU a node spends per token it receives (``time.process_time`` of this process, all its
  threads, while a child process declares ``--tokens`` offer tokens that this process does not
  subscribe to, then as many it subscribes to: the first is what every node pays for every
  token in peer or router mode, the second what a subscriber pays on top);
- an offers query among ``--tokens`` tokens of which 3 match: its time, median of 30;
- ``get_summary`` of a manager with the robot's library of the paper's scenario: its time
  (median of 30) and size;
- a clock exchange: its size and the CPU of both ends (one process: an upper bound of either).

Then it prints, from these figures, what one manager and the whole fleet pay at 10, 100 and
1,000 managers (the model is in the docs). The load average is printed beside the figures.

    flock /tmp/dyknow-heavy.lock python benchmarks/fleet_messages.py [--tokens 2000]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from dyknow import Client, Manager, clocks, keys
from dyknow.resources import specs_dir, testing_dir
from dyknow.transport import Session, make_config

from harness import free_ports

_CHILD = """
import sys, threading
from dyknow import keys
from dyknow.transport import Session, make_config
endpoint, tag, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
with Session(make_config(connect=[endpoint], listen=[])) as s:
    held = [s.declare_liveliness_token(keys.offer_token(tag, (f"a{i}",), f"m{i:05d}")) for i in range(count)]
    held.append(s.declare_liveliness_token(keys.offer_token("Done", (), "child")))
    print("declared", flush=True)
    sys.stdin.readline()
"""


def token_cpu(session: Session, endpoint: str, tag: str, count: int, subscribe: bool, base: float) -> float:
    """CPU (us) this process spends per offer token a child declares (``subscribe``: matching a subscription of ours)."""
    done = threading.Event()
    seen = [0]

    def on_token(key: str, alive: bool) -> None:
        if alive:
            seen[0] += 1

    def on_done(key: str, alive: bool) -> None:
        if alive:
            done.set()

    watches = [session.declare_liveliness_subscriber(keys.offers_pattern("Done", ()), on_done, inline=True)]
    if subscribe:
        watches.append(session.declare_liveliness_subscriber(f"@dyknow/offers/{tag}/**", on_token, inline=True))
    time.sleep(0.3)
    started, wall = time.process_time(), time.perf_counter()
    child = subprocess.Popen([sys.executable, "-c", _CHILD, endpoint, tag, str(count)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)  # fmt: skip
    assert child.stdout is not None and child.stdin is not None
    child.stdout.readline()
    if not done.wait(60):
        raise SystemExit("the child's tokens did not arrive within 60 s")
    spent = time.process_time() - started - base * (time.perf_counter() - wall)
    if subscribe and seen[0] < count:
        deadline = time.monotonic() + 10
        while seen[0] < count and time.monotonic() < deadline:
            time.sleep(0.01)
    child.stdin.write("\n")
    child.stdin.flush()
    child.wait(10)
    for w in watches:
        w.undeclare()
    return spent * 1e6 / count


def idle_cpu(seconds: float) -> float:
    """This process's CPU at rest (all its threads), in CPU seconds per second, over ``seconds``."""
    started = time.process_time()
    time.sleep(seconds)
    return (time.process_time() - started) / seconds


def main() -> int:
    """Measure each message's cost, print it and what fleets of 10, 100 and 1,000 pay from it."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tokens", type=int, default=2000, help="offer tokens the child declares (default 2000)")
    parser.add_argument("--json", type=Path, help="write the figures here too")
    args = parser.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    figures: dict[str, float] = {}
    ontology = [specs_dir() / "dyknow.ttl"]
    with (
        Manager("robot", specs=[testing_dir() / "scenario-robot.xml"], ontology=ontology, listen=[endpoint]) as robot,
        Session(make_config(connect=[endpoint], listen=[], mode="router")) as session,
    ):
        time.sleep(1.0)
        base = idle_cpu(2.0)  # this process at rest (the manager's threads included), CPU s per s
        figures["idle_cpu_per_s"] = base
        # (the child's start takes about a second of wall time during which this process idles: taken off)
        foreign = token_cpu(session, endpoint, "Foreign", args.tokens, subscribe=False, base=base)
        matching = token_cpu(session, endpoint, "Wanted", args.tokens, subscribe=True, base=base)
        figures["token_us_not_subscribed"] = foreign
        figures["token_us_subscribed"] = matching
        # an offers query among many tokens, 3 of which match
        held = [session.declare_liveliness_token(keys.offer_token("Filler", (f"a{i}",), f"f{i:05d}")) for i in range(args.tokens)]
        held += [session.declare_liveliness_token(keys.offer_token("Few", (), f"p{i}")) for i in range(3)]
        with Client("robot", connect=[endpoint]) as client:
            client.session.alive(keys.offers_pattern("Few", ()), timeout_s=2.0)
            times = []
            for _ in range(30):
                done = threading.Event()
                got: list[int] = []
                started = time.perf_counter()
                client.session.ask_alive(keys.offers_pattern("Few", ()), timeout_s=1.0, limit=64,
                                         done=lambda found, count, got=got, done=done: (got.append(count), done.set()))  # fmt: skip
                done.wait(2.0)
                times.append((time.perf_counter() - started) * 1e3)
                assert got == [3], got
            figures["offers_query_ms"] = statistics.median(times)
            times = []
            size = 0
            for _ in range(30):
                started = time.perf_counter()
                summary = client.call_manager("robot", "get_summary", {})
                times.append((time.perf_counter() - started) * 1e3)
                size = len(json.dumps(summary))
            figures["summary_ms"] = statistics.median(times)
            figures["summary_bytes"] = size
            brief = client.call_manager("robot", "get_summary", {"brief": True})
            figures["brief_summary_bytes"] = len(json.dumps(brief))
        for h in held:
            h.undeclare()
        # clock exchanges: both ends in this process
        n = 300
        finished = threading.Semaphore(0)
        started = time.process_time()
        wall = time.perf_counter()
        for _ in range(n):
            session.exchange(keys.clock_key("robot"), clocks.request(time.time_ns()), timeout_s=1.0, done=lambda got: finished.release())
            finished.acquire(timeout=2.0)
        elapsed = time.perf_counter() - wall
        figures["clock_exchange_us_cpu"] = ((time.process_time() - started) - base * elapsed) * 1e6 / n
        figures["clock_exchange_bytes"] = len(clocks.request(0)) + len(clocks.answer(clocks.request(0), 0)[1])
        del robot
    load = round(os.getloadavg()[0], 2)
    # a fleet, from these figures (see docs/concepts/federation.md, "What a fleet pays")
    tags = 10  # tags a manager offers (an offer token each)
    per_join = tags + 2  # + its manager token and its clock token
    in_use = 3  # managers one exchanges data or calls with
    print(f"measured on loopback, load average {load}")
    print(f"  a token received, not subscribed to: {foreign:7.1f} us CPU (every node, in peer or router mode)")
    print(f"  a token received, subscribed to:     {matching:7.1f} us CPU")
    print(f"  an offers query (3 of {args.tokens} tokens match): {figures['offers_query_ms']:.2f} ms")
    print(f"  get_summary (the robot's library):   {figures['summary_ms']:.2f} ms, {size} bytes; brief: {figures['brief_summary_bytes']} bytes")
    print(f"  a clock exchange: {figures['clock_exchange_bytes']} bytes of payload, {figures['clock_exchange_us_cpu']:.0f} us CPU (both ends)")
    print()
    print(f"a fleet (each manager offers {tags} tags, exchanges data with {in_use}, and one manager in 1,000 joins or leaves a minute):")
    print(f"{'managers':>10} {'join: CPU per node (ms)':>26} {'join: fleet (ms)':>18} {'idle clocks per manager (% core)':>34} {'first plan (ms)':>16}")
    for fleet in (10, 100, 1000):
        join_node_ms = per_join * foreign / 1e3  # what one join costs every node (peer or router mode)
        join_fleet_ms = join_node_ms * fleet
        clocks_pct = in_use * 3 * figures["clock_exchange_us_cpu"] / 1e4
        plan_ms = 3 * figures["offers_query_ms"] + figures["summary_ms"]  # 3 tags asked at once... counted one after the other; candidates fetched 8 at once
        print(f"{fleet:>10} {join_node_ms:>26.2f} {join_fleet_ms:>18.1f} {clocks_pct:>34.3f} {plan_ms:>16.1f}")
    if args.json is not None:
        args.json.write_text(json.dumps({**figures, "load": load}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
