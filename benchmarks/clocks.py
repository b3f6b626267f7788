"""Clocks that disagree across hosts: how well the station estimates the robot's clock, and at what cost.

Two hosts in network namespaces on one bridge (:class:`dyknow.testing.hosts.Hosts`, root needed,
each process with its own ``/dev/shm``): the ``station`` serves ``BallTrack(field)``, the
``robot`` runs its camera (200 Hz), its manager under libfaketime (``FAKETIME_DONT_FAKE_MONOTONIC=1``:
only the wall clock is faked). Each case runs on hosts of its own:

- ``equal``: the robot's clock is the machine's (for reference; ``equal-again`` repeats it, to
  show how much two runs with equal clocks differ anyway);
- ``ahead``, ``behind``: the robot's clock 250 ms ahead, behind (libfaketime ``+0.25``, ``-0.25``);
- ``drift``: the robot's clock runs 100 ppm fast (``+0 x1.0001``);
- ``ahead-loss-5``: 250 ms ahead, and 5 % of the robot's packets dropped both ways, from its start.

The injected offset is known exactly at every moment: the robot's manager first prints its wall
clock between two readings of the monotonic clock (the machine's, which libfaketime leaves alone
here). An observer in the station's namespace reads the station's model five times a second (its
estimate of the robot's clock) and the statistics of the stage fed across hosts,
``subsampler(bottom)``, once a second. Reported per case, each figure measured in that run:

- the estimate's error against the injected offset 2 s after the robot's manager was ready, and
  the largest from then on; at steady state (the second half of the run) the median and the
  largest error and the stated uncertainty. Target: within 100 µs from 2 s on (on the clean
  link), within 500 µs under 5 % loss;
- the exchanges per second each peer costs (counted from the estimate's samples) and the
  cross-host hop p50 of ``subsampler(bottom)`` as the station reports it (corrected), against the
  hop the same messages took on equal clocks: the corrected one less the estimate's error, known
  at every moment from the injected offset (the median over the statistics' last 5 s). Target:
  within 10 %. Against the ``equal`` run's hop too, for what it is worth: two runs differ by more
  than that with equal clocks (where the scheduler put each process's threads; ``equal-again``
  shows how much).

And the CPU one exchange costs each side, measured on loopback: back-to-back exchanges of this
process with a ``dyknow manager`` process (this side: ``Session.exchange`` and the estimator, as
a tracker runs them; the other: its answer on Zenoh's thread), CPU time over the count.

    python benchmarks/clocks.py                          # 20 s per case
    python benchmarks/clocks.py --seconds 10 --json out/clocks.json
    python benchmarks/clocks.py --smoke                  # 6 s, equal and ahead only, 200 exchanges
    python benchmarks/clocks.py --pin                    # the robot on CPU 1, the station on CPU 0
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from dyknow import Client, keys
from dyknow.clocks import Estimator, request
from dyknow.errors import DyKnowError
from dyknow.testing import SCENARIO_HOSTS
from dyknow.transport import Session, make_config

from failover import NETNS_PORT, ONTOLOGY, TAG
from harness import Proc, cpu_seconds, free_ports, machine, write_json

FAKETIME = Path("/usr/lib/x86_64-linux-gnu/faketime/libfaketime.so.1")
OFFSET_TARGET_US = 100.0
LOSS_TARGET_US = 500.0
HOP_TARGET = 0.10
AT_S = 2.0


@dataclass(frozen=True)
class Case:
    """One run: the robot's ``FAKETIME`` (None: its clock is the machine's), its rate, and the loss on its link."""

    name: str
    faketime: str | None
    rate: float = 1.0
    loss: float = 0.0


CASES = {
    c.name: c
    for c in (
        Case("equal", None),
        Case("ahead", "+0.25"),
        Case("behind", "-0.25"),
        Case("drift", "+0 x1.0001", 1.0001),
        Case("ahead-loss-5", "+0.25", loss=5.0),
        Case("equal-again", None),
    )
}


# ---------------------------------------------------------------------------- inside the namespaces


def run_manager(argv: list[str]) -> NoReturn:
    """``dyknow ARGS`` in this process, after a line with its wall clock between two readings of the monotonic clock."""
    from dyknow.cli import run as run_dyknow

    before, realtime, after = time.monotonic_ns(), time.time_ns(), time.monotonic_ns()
    print(json.dumps({"event": "clock", "realtime_ns": realtime, "monotonic_ns": (before + after) // 2, "read_ns": after - before}), flush=True)
    run_dyknow(argv)


def observe(endpoint: str) -> int:
    """The observer (inside the station's namespace): request ``TAG``, then print the station's
    estimate of the robot's clock five times a second and the cross-host stage's figures once a second."""
    with Client("station", connect=[endpoint], timeout_s=10) as client:
        key = None
        last_stats = 0.0
        while True:
            before = time.time_ns()
            clocks = client.get_model()["clocks"]
            after = time.time_ns()
            line: dict[str, Any] = {"event": "poll", "before_ns": before, "after_ns": after, "robot": clocks.get("robot")}
            if key is None:
                try:
                    key = client.request(TAG)
                    print(json.dumps({"event": "key", "key": key}), flush=True)
                except DyKnowError:
                    pass
            elif time.monotonic() - last_stats >= 1.0:
                last_stats = time.monotonic()
                for unit in client.get_model()["units"]:
                    if unit["label"] == "subsampler(bottom)":
                        port = client.get_statistics(unit["name"])["ports"]["in"]
                        line["hop"] = {"p50_us": port["hop"]["p50_us"], "messages": port["messages"], **port["clock"]}
            print(json.dumps(line), flush=True)
            time.sleep(0.2)


# ---------------------------------------------------------------------------- one case


def injected(clock_line: dict[str, Any], rate: float, at_ns: int) -> int:
    """The robot's clock minus the machine's at ``at_ns`` (the machine's wall clock), from its clock line."""
    before, realtime, after = time.monotonic_ns(), time.time_ns(), time.monotonic_ns()
    machine_offset = realtime - (before + after) // 2
    offset_then = clock_line["realtime_ns"] - clock_line["monotonic_ns"] - machine_offset
    return offset_then + round((rate - 1) * (at_ns - (clock_line["monotonic_ns"] + machine_offset)))


def run(case: Case, seconds: float, pin: bool) -> dict[str, Any]:
    """One case on hosts of its own; its figures. ``pin``: the robot on CPU 1, the station and its
    observer on CPU 0 (where a message crosses between CPUs is then the same in every run)."""
    from dyknow.testing.hosts import Hosts

    def on(cpu: int, argv: list[str]) -> list[str]:
        return ["taskset", "-c", str(cpu), *argv] if pin else argv

    procs: dict[str, Proc] = {}
    polls: list[dict[str, Any]] = []
    with Hosts(["station", "robot"]) as hosts:
        station = f"tcp/{hosts.address('station')}:{NETNS_PORT}"
        try:
            for name in ("station", "robot"):
                env = dict(os.environ)
                if name == "robot" and case.faketime is not None:
                    env.update(FAKETIME=case.faketime, FAKETIME_DONT_FAKE_MONOTONIC="1", LD_PRELOAD=str(FAKETIME))
                if name == "robot":
                    if case.loss:
                        hosts.loss("robot", case.loss)
                    observer = Proc(on(0, [sys.executable, __file__, "--observe", station]), popen=lambda a, **kw: hosts.popen("station", a, **kw))
                    procs["observer"] = observer
                argv = [
                    sys.executable, __file__, "--run-manager", "manager", "--name", name, "--specs", str(SCENARIO_HOSTS[name]),
                    "--ontology", str(ONTOLOGY), "--listen", f"tcp/{hosts.address(name)}:{NETNS_PORT}",
                    *(["--connect", station] if name != "station" else []), "--host", f"{name}-host", "--lease-ms", "1000", "--json",
                ]  # fmt: skip
                procs[name] = Proc(on(int(name == "robot"), argv), popen=lambda a, n=name, e=env, **kw: hosts.popen(n, a, env=e, **kw))
                clock_line = procs[name].next_json(30, event="clock")
                procs[name].next_json(30, event="ready")
            ready_ns = time.time_ns()
            procs["observer"].next_json(60, event="key")
            end = ready_ns + int(seconds * 1e9)
            while time.time_ns() < end:
                polls.append(procs["observer"].next_json(30, event="poll"))
        finally:
            for proc in reversed(list(procs.values())):
                proc.close()
    return figures(case, seconds, clock_line, ready_ns, polls)


def figures(case: Case, seconds: float, clock_line: dict[str, Any], ready_ns: int, polls: list[dict[str, Any]]) -> dict[str, Any]:
    """The case's figures from the observer's polls."""
    rows = []
    for poll in polls:
        estimate = poll["robot"]
        if estimate is None:
            continue
        at = (poll["before_ns"] + poll["after_ns"]) // 2
        error = estimate["offset_us"] - injected(clock_line, case.rate, at) / 1000
        rows.append({"t_s": (at - ready_ns) / 1e9, "error_us": error, "uncertainty_us": estimate["uncertainty_us"], "samples": estimate["samples"]})
    from_2s = [r for r in rows if r["t_s"] >= AT_S]
    steady = [r for r in rows if r["t_s"] >= seconds / 2]
    hops = [p["hop"] for p in polls if "hop" in p]
    # the hop the same messages took, read on equal clocks: the corrected one less the estimate's
    # error over the statistics' window (the last 1,024 messages, 5 s at 200 Hz)
    window = [r["error_us"] for r in rows if r["t_s"] >= seconds - 5.0]
    hop_equal = hops[-1]["p50_us"] - statistics.median(window) if hops and window else None
    exchanges = None
    if len(steady) >= 2 and steady[-1]["t_s"] > steady[0]["t_s"]:
        exchanges = (steady[-1]["samples"] - steady[0]["samples"]) / (steady[-1]["t_s"] - steady[0]["t_s"])
    return {
        "case": case.name,
        "faketime": case.faketime,
        "loss_percent": case.loss,
        "seconds": seconds,
        "injected_offset_us": round(injected(clock_line, case.rate, ready_ns + int(seconds * 1e9)) / 1000, 1),
        "first_estimate_s": round(rows[0]["t_s"], 2) if rows else None,
        "error_at_2s_us": round(from_2s[0]["error_us"], 1) if from_2s else None,
        "error_max_from_2s_us": round(max(abs(r["error_us"]) for r in from_2s), 1) if from_2s else None,
        "error_steady_median_us": round(statistics.median(abs(r["error_us"]) for r in steady), 1) if steady else None,
        "error_steady_max_us": round(max(abs(r["error_us"]) for r in steady), 1) if steady else None,
        "uncertainty_steady_median_us": round(statistics.median(r["uncertainty_us"] for r in steady), 1) if steady else None,
        "within_uncertainty": all(abs(r["error_us"]) <= r["uncertainty_us"] + clock_line["read_ns"] / 2000 + 1 for r in rows),
        "exchanges_per_s": round(exchanges, 2) if exchanges is not None else None,
        "hop_p50_us": hops[-1]["p50_us"] if hops else None,
        "hop_p50_equal_clocks_us": round(hop_equal, 1) if hop_equal is not None else None,
        "hop_uncertainty_us": hops[-1]["uncertainty_us"] if hops else None,
        "hop_unknown": hops[-1]["unknown"] if hops else None,
        "polls": len(polls),
    }


# ---------------------------------------------------------------------------- the cost of an exchange


def cost(exchanges: int) -> dict[str, Any]:
    """CPU per exchange on each side: back-to-back exchanges with a manager process on loopback."""
    (port,) = free_ports(1)
    endpoint = f"tcp/127.0.0.1:{port}"
    peer = Proc([sys.executable, "-m", "dyknow.cli", "manager", "--name", "peer", "--listen", endpoint, "--json"])
    try:
        peer.next_json(30, event="ready")
        with Session(make_config(connect=[endpoint])) as session:
            estimator = Estimator()
            done = threading.Event()
            got: list[Any] = []

            def finished(result: Any) -> None:
                got.append(result)
                done.set()

            def one() -> bool:
                """One exchange as a tracker runs it; whether its answer was taken."""
                done.clear()
                got.clear()
                t1 = time.time_ns()
                session.exchange(keys.clock_key("peer"), request(t1), timeout_s=1.0, done=finished)
                done.wait(2.0)
                if not got or got[0] is None:
                    return False
                reply, sent, arrived, _ = got[0]
                return estimator.add(t1, reply, arrived, sent_ns=sent)

            deadline = time.monotonic() + 30
            while not one():  # until the link is up and the peer's services declared
                if time.monotonic() > deadline:
                    raise RuntimeError(f"no clock exchange with the peer within 30 s; refused: {dict(estimator.refused)}")
                threading.Event().wait(0.01)
            for _ in range(50):  # the code warm
                one()
            before_here, before_peer, started = time.process_time(), cpu_seconds([peer.proc.pid]), time.perf_counter()
            failed = sum(not one() for _ in range(exchanges))
            here, there = time.process_time() - before_here, cpu_seconds([peer.proc.pid]) - before_peer
            wall = time.perf_counter() - started
            found = estimator.estimate()
    finally:
        peer.close()
    return {
        "exchanges": exchanges,
        "estimating_side_us": round(here / exchanges * 1e6, 1),
        "answering_side_us": round(there / exchanges * 1e6, 1),
        "round_trip_us": round(wall / exchanges * 1e6, 1),
        "failed": failed,  # of the measured exchanges, those with no answer taken
        "offset_us": round(found.offset_ns / 1000, 1) if found else None,  # one machine: 0 within the uncertainty
        "uncertainty_us": round(found.uncertainty_ns / 1000, 1) if found else None,
    }


# ---------------------------------------------------------------------------- the report


def verdict(row: dict[str, Any], equal_hop: float | None) -> str:
    """The row's targets and whether each was met (and the hop against the equal run's, for what it is worth)."""
    target = LOSS_TARGET_US if row["loss_percent"] else OFFSET_TARGET_US
    worst = row["error_max_from_2s_us"]
    parts = [f"offset error from {AT_S:g} s on {worst} us (target <= {target:g}): {'met' if worst is not None and worst <= target else 'NOT met'}"]
    hop, hop_equal = row["hop_p50_us"], row["hop_p50_equal_clocks_us"]
    if hop is not None and hop_equal:
        ratio = hop / hop_equal - 1
        parts.append(
            f"hop p50 {hop:.1f} us against {hop_equal:.1f} us on equal clocks, {ratio:+.1%} (target within {HOP_TARGET:.0%}): "
            f"{'met' if abs(ratio) <= HOP_TARGET else 'NOT met'}"
        )
    if hop is not None and equal_hop:
        parts.append(f"against the equal run's {hop / equal_hop - 1:+.0%}")
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    """Run every case and print its figures beside its targets."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--run-manager"]:  # (inside a namespace: the rest is dyknow's command line)
        run_manager(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=None, help="how long each case runs once the robot is ready (default 20)")
    parser.add_argument("--smoke", action="store_true", help="a quick run: 6 s, equal and ahead, 200 exchanges for the cost")
    parser.add_argument("--cases", help=f"comma-separated, of {', '.join(CASES)} (default all)")
    parser.add_argument("--exchanges", type=int, default=None, help="back-to-back exchanges for the cost (default 3000)")
    parser.add_argument("--pin", action="store_true", help="the robot on CPU 1, the station and its observer on CPU 0 (default: left to the scheduler)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--observe", metavar="ENDPOINT", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.observe:
        return observe(args.observe)
    from dyknow.testing.hosts import unavailable

    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}", flush=True)
    exchanges = args.exchanges or (200 if args.smoke else 3000)
    spent = cost(exchanges)
    print(f"cost of one exchange ({exchanges} back to back on loopback): {spent['estimating_side_us']} us CPU estimating, "
          f"{spent['answering_side_us']} us answering, round trip {spent['round_trip_us']} us", flush=True)  # fmt: skip
    why = unavailable() or (None if FAKETIME.is_file() else f"libfaketime is not installed ({FAKETIME}; apt-get install faketime)")
    if why is not None:
        print(f"skipped: {why}")
        if args.json:
            write_json(args.json, {"machine": info, "cost": spent, "results": [], "skipped": why})
        return 0
    seconds = args.seconds or (6.0 if args.smoke else 20.0)
    pin = args.pin and (os.cpu_count() or 1) >= 2 and shutil.which("taskset") is not None
    info["pinned"] = "robot on CPU 1, station and observer on CPU 0" if pin else False
    names = ["equal", "ahead"] if args.smoke else list(CASES)
    if args.cases:
        names = [s.strip() for s in args.cases.split(",") if s.strip()]
        unknown = set(names) - set(CASES)
        if unknown:
            parser.error(f"--cases: unknown {', '.join(sorted(unknown))}")
    print(f"scenario: {TAG} on the station, robot-camera 200 Hz on the robot (its manager under libfaketime); "
          f"{seconds:g} s per case from the robot's manager ready; clean links unless said; pinned: {info['pinned']}\n", flush=True)  # fmt: skip
    rows = []
    equal_hop = None
    for name in names:
        row = run(CASES[name], seconds, pin)
        rows.append(row)
        if name == "equal":
            equal_hop = row["hop_p50_us"]
        print(f"{name:<13} injected {row['injected_offset_us']:>10.1f} us  first estimate {row['first_estimate_s']} s  "
              f"error at {AT_S:g} s {row['error_at_2s_us']} us, steady median {row['error_steady_median_us']} max {row['error_steady_max_us']} us "
              f"(uncertainty {row['uncertainty_steady_median_us']} us, every estimate within it: {row['within_uncertainty']})  "
              f"{row['exchanges_per_s']} exchanges/s  hop p50 {row['hop_p50_us']} us (+/- {row['hop_uncertainty_us']}, unknown {row['hop_unknown']})"
              f"\n{'':<13} {verdict(row, equal_hop if name != 'equal' else None)}", flush=True)  # fmt: skip
    rates = [r["exchanges_per_s"] for r in rows if r["exchanges_per_s"] is not None]
    if rates:
        rate = statistics.median(rates)
        spent["per_peer_percent_of_a_core"] = round(rate * (spent["estimating_side_us"] + spent["answering_side_us"]) / 1e4, 4)
        print(f"\ncost per peer: {rate:g} exchanges a second (measured above) x {spent['estimating_side_us']} us estimating + "
              f"{spent['answering_side_us']} us answering = {spent['per_peer_percent_of_a_core']} % of a core", flush=True)  # fmt: skip
    if args.json:
        targets = {"offset_error_us": OFFSET_TARGET_US, "offset_error_under_loss_us": LOSS_TARGET_US, "hop_p50_vs_equal": HOP_TARGET, "at_s": AT_S}
        write_json(args.json, {"machine": info, "targets": targets, "cost": spent, "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
