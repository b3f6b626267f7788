"""A soak: a chain of relays at 1 kHz for minutes, every lost message accounted for, the manager's memory watched.

A ``dyknow manager`` process (the CLI, the shipped ``generic.xml`` specs) runs, spawned through
the client services, a ``periodic-source`` publishing 16-byte messages at ``--rate-hz`` and a
chain of ``--relays`` relays (``soak/0`` -> ``relay-01`` -> ``soak/1`` -> ... -> ``soak/<n>``).
This process subscribes to the last relay's key over Zenoh (the only hop that leaves the
manager) and keeps, per message, its end-to-end age (arrival minus the origin time the source
stamped, carried unchanged through every relay) and the last relay's sequence number.

The source is told to publish ``minutes x 60 x rate`` messages and stops by itself; the chain
then drains and everything is counted:

- sent: the source's output port, ``messages`` in ``get_statistics``;
- received: distinct messages at the sink (a sequence number of the last relay seen twice is a
  duplicate, counted apart);
- explained losses: what dyknow counts, per unit and port: every relay input's ``dropped`` (a
  full queue) and ``rejected``;
- unexplained: the rest. It is then located hop by hop from the same counters: messages still
  queued at an input, handled by a relay but not republished, or published by the last relay and
  never seen by the sink (its sequence numbers skipped: the Zenoh hop, where a publisher drops
  under congestion without counting).

A relay renumbers what it publishes (``seq`` is per output port) and the source's payload is
zeros, so the sink cannot name which of the source's messages went missing, only how many and on
which hop.

Meanwhile the manager's resident set (``VmRSS`` in ``/proc/<pid>/status``) is sampled every
``--sample-s`` seconds; its least-squares slope after the first minute (with ``--minutes`` under
2, over the second half) is printed beside the target, < 0.5 MB/min, with the manager's CPU.

    python benchmarks/soak.py --minutes 5 --json benchmarks/results/soak.json
    python benchmarks/soak.py --minutes 0.1 --relays 3 --rate-hz 200   # a smoke run
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from array import array
from pathlib import Path
from typing import Any

import numpy as np

from dyknow import Client, Message
from dyknow.resources import specs_dir

from harness import Proc, cpu_seconds, free_ports, machine, percentile, write_json

MANAGER = "soak"
PAYLOAD_BYTES = 16
TARGET_SLOPE_MB_PER_MIN = 0.5
TARGET_UNEXPLAINED = 0
WARM_UP_S = 60.0  # the RSS slope leaves out the first minute (start-up, first allocations)
QUIET_S = 1.0  # the chain counts as drained when the sink got nothing new for this long
DRAIN_TIMEOUT_S = 15.0
POLL_S = 1.0  # how often the source's counter is asked for while it runs
WORST = 10  # the oldest arrivals are listed with when they were sent
MB = 1e6


def hop_key(i: int) -> str:
    """The key between hop ``i`` and hop ``i + 1`` (0: the source's output)."""
    return f"soak/{i}"


def relay_name(i: int) -> str:
    """The name of the ``i``-th relay (1-based)."""
    return f"relay-{i:02d}"


class Sink:
    """What arrives on the last relay's key: counts, the last relay's sequence numbers, ages.

    ``on_message`` runs on the subscriber's Zenoh thread; the other methods on any thread.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.received = 0  # every message, duplicates included
        self.duplicates = 0  # a sequence number not above the previous one
        self.first_seq = 0
        self.last_seq = 0
        self.gaps = 0  # sequence numbers skipped between two messages received
        self.origin_disorder = 0  # an origin time not after the previous message's
        self.first_origin_ns = 0
        self.last_origin_ns = 0
        self.ages_ms = array("d")
        self.origins_ns = array("q")

    def on_message(self, msg: Message) -> None:
        """Count ``msg``, its age and any gap or repeat in the last relay's sequence numbers."""
        now = time.time_ns()
        with self._lock:
            self.received += 1
            self.ages_ms.append((now - msg.origin_ns) / 1e6)
            self.origins_ns.append(msg.origin_ns)
            if self.first_seq == 0:
                self.first_seq = self.last_seq = msg.seq
                self.first_origin_ns = self.last_origin_ns = msg.origin_ns
                return
            if msg.seq <= self.last_seq:
                self.duplicates += 1
            else:
                self.gaps += msg.seq - self.last_seq - 1
                self.last_seq = msg.seq
            if msg.origin_ns <= self.last_origin_ns:
                self.origin_disorder += 1
            else:
                self.last_origin_ns = msg.origin_ns

    @property
    def distinct(self) -> int:
        """Messages received, duplicates left out."""
        with self._lock:
            return self.received - self.duplicates

    def ages(self) -> tuple[np.ndarray, np.ndarray]:
        """Every end-to-end age so far in milliseconds, and each message's origin time in nanoseconds."""
        with self._lock:
            return np.frombuffer(self.ages_ms, dtype=np.float64).copy(), np.frombuffer(self.origins_ns, dtype=np.int64).copy()


def load_average() -> float:
    """The machine's 1-minute load average (other work competing with the run shows here)."""
    return float(Path("/proc/loadavg").read_text().split()[0])


def _status_field(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


class RssSampler:
    """Samples a process's ``VmRSS`` every ``interval_s`` on a thread of its own, from ``start()`` to ``stop()``."""

    def __init__(self, pid: int, interval_s: float) -> None:
        self.pid = pid
        self.interval_s = interval_s
        self.samples: list[tuple[float, float]] = []  # (seconds since start, MiB)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss-sampler", daemon=True)
        self._t0 = 0.0

    def start(self) -> None:
        """Take the first sample now and go on every ``interval_s``."""
        self._t0 = time.monotonic()
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                kib = _status_field(self.pid, "VmRSS")
            except OSError:
                return  # the process is gone
            self.samples.append((time.monotonic() - self._t0, kib / 1024))
            if self._stop.wait(self.interval_s):
                return

    def stop(self) -> None:
        """Stop sampling (takes one last sample first)."""
        self._stop.set()
        self._thread.join(5)
        try:
            self.samples.append((time.monotonic() - self._t0, _status_field(self.pid, "VmRSS") / 1024))
        except OSError:
            pass

    def latest_mib(self) -> float:
        """The last sample, in MiB (NaN before the first)."""
        return self.samples[-1][1] if self.samples else float("nan")


def rss_slope(samples: list[tuple[float, float]], duration_s: float) -> dict[str, Any]:
    """Least-squares slope of RSS samples (MB per minute) over the run after the first minute.

    With a run under two minutes, the second half is used instead (``window`` says which).
    """
    if duration_s >= 2 * WARM_UP_S:
        start_s, window = WARM_UP_S, "after the first minute"
    else:
        start_s, window = duration_s / 2, "over the second half (the run is under 2 minutes)"
    kept = [(t, mib) for t, mib in samples if t >= start_s]
    slope = float("nan")
    if len(kept) >= 2:
        t_min = np.array([t for t, _ in kept]) / 60
        mb = np.array([mib for _, mib in kept]) * (1 << 20) / MB
        slope = float(np.polyfit(t_min, mb, 1)[0])
    return {
        "slope_mb_per_min": round(slope, 4),
        "window": window,
        "window_start_s": round(start_s, 1),
        "samples_in_window": len(kept),
        "target_mb_per_min": TARGET_SLOPE_MB_PER_MIN,
        "met": bool(len(kept) >= 2 and slope < TARGET_SLOPE_MB_PER_MIN),
    }


def account(sent: int, sink: Sink, stats: dict[str, dict[str, Any]], relays: int) -> dict[str, Any]:
    """Sent, received, lost; the losses dyknow counted (per unit and port) and where the others were lost.

    ``stats``: ``get_statistics`` of ``source`` and of every relay, by unit name, after the drain.
    """
    received = sink.distinct
    lost = sent - received
    counted: list[dict[str, Any]] = []
    located: list[dict[str, Any]] = []
    upstream_name, upstream_out = "source", sent
    for i in range(1, relays + 1):
        name = relay_name(i)
        ports = stats[name]["ports"]
        inp, out = ports["in"], ports["out"]
        for cause, count in (("dropped: its input queue was full", inp["dropped"]), ("rejected by the unit", inp["rejected"])):
            if count:
                counted.append({"unit": name, "port": "in", "cause": cause, "count": count})
        queued = upstream_out - inp["messages"] - inp["dropped"]
        if queued:
            located.append({"where": f"{name}.in", "count": queued,
                            "cause": f"published by {upstream_name} but neither handled nor dropped by {name} (still queued)"})  # fmt: skip
        not_forwarded = inp["messages"] - inp["rejected"] - out["messages"]
        if not_forwarded:
            located.append({"where": f"{name}", "count": not_forwarded, "cause": "handled but not republished"})
        upstream_name, upstream_out = name, out["messages"]
    last_hop = upstream_out - received
    if last_hop:
        before, after = max(0, sink.first_seq - 1), max(0, upstream_out - sink.last_seq)
        located.append({
            "where": f"{upstream_name}.out -> sink (Zenoh)",
            "count": last_hop,
            "cause": f"published by {upstream_name}, never seen by the sink: {before} before the first received, "
                     f"{sink.gaps} skipped in between, {after} after the last (a Zenoh publisher dropping under "
                     "congestion does not count it)",
        })  # fmt: skip
    explained = sum(c["count"] for c in counted)
    return {
        "sent": sent,
        "received": received,
        "lost": lost,
        "explained": explained,
        "unexplained": lost - explained,
        "explained_by": counted,
        "unexplained_located": located,
        "duplicates": sink.duplicates,
        "origin_out_of_order": sink.origin_disorder,
        "balanced": explained + sum(x["count"] for x in located) == lost,
    }


def wait_drained(sink: Sink, quiet_s: float, timeout_s: float) -> float:
    """Wait until the sink got nothing new for ``quiet_s`` (at most ``timeout_s``); the seconds waited."""
    start = time.monotonic()
    last, since = sink.received, start
    while time.monotonic() - start < timeout_s:
        time.sleep(0.05)
        now_count = sink.received
        if now_count != last:
            last, since = now_count, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            break
    return time.monotonic() - start


def run(minutes: float, relays: int, rate_hz: float, sample_s: float) -> dict[str, Any]:
    """Start the manager, the chain and the sink; run ``minutes``; drain; count. The results as plain data."""
    count = max(1, round(minutes * 60 * rate_hz))
    expected_s = count / rate_hz
    endpoint = f"tcp/127.0.0.1:{free_ports(1)[0]}"
    argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", MANAGER, "--listen", endpoint,
            "--specs", str(specs_dir() / "generic.xml"), "--json"]  # fmt: skip
    manager = Proc(argv)
    try:
        manager.next_json(30, event="ready")
        pid = manager.proc.pid
        rss_at_ready_mib = _status_field(pid, "VmRSS") / 1024
        sink = Sink()
        with Client(MANAGER, connect=[endpoint], timeout_s=10) as client:
            with client.declare_subscriber(hop_key(relays), sink.on_message):
                for i in range(relays, 0, -1):  # downstream first: nothing is published before its reader is bound
                    client.spawn("relay", relay_name(i), bindings={"in": hop_key(i - 1), "out": hop_key(i)})
                sampler = RssSampler(pid, sample_s)
                cpu0, cpu0_at = cpu_seconds([pid]), time.monotonic()
                sampler.start()
                started, load_at_start = time.monotonic(), load_average()
                client.spawn("periodic-source", "source", params={"rate_hz": rate_hz, "count": count, "payload_size": PAYLOAD_BYTES},
                             bindings={"out": hop_key(0)})  # fmt: skip
                print(
                    f"running: {count:,} messages at {rate_hz:g} Hz through {relays} relays (about {expected_s / 60:.2f} min)", flush=True
                )
                deadline = started + 1.5 * expected_s + 30
                next_report = started + 60
                sent = 0
                while sent < count:
                    time.sleep(POLL_S)
                    received = sink.received  # before sent, so that received <= sent
                    sent = client.get_statistics("source")["ports"]["out"]["messages"]
                    now = time.monotonic()
                    if now >= next_report:
                        next_report += 60
                        print(f"  {(now - started) / 60:5.1f} min: sent {sent:,}, received {received:,}, "
                              f"manager RSS {sampler.latest_mib():.1f} MiB", flush=True)  # fmt: skip
                    if now > deadline:
                        raise RuntimeError(f"the source published {sent:,} of {count:,} messages in {now - started:.0f} s")
                stopped = time.monotonic()
                cpu1, cpu1_at = cpu_seconds([pid]), stopped
                load_at_stop = load_average()
                drain_s = wait_drained(sink, QUIET_S, DRAIN_TIMEOUT_S)
                sampler.stop()
                names = ["source", *(relay_name(i) for i in range(1, relays + 1))]
                stats = {name: client.get_statistics(name) for name in names}
            threads = _status_field(pid, "Threads")
            client.destroy("source")
            for i in range(1, relays + 1):
                client.destroy(relay_name(i))
        manager.proc.terminate()
        exit_code = manager.proc.wait(10)
    finally:
        manager.close()

    sent = stats["source"]["ports"]["out"]["messages"]
    loss = account(sent, sink, stats, relays)
    ages, origins_ns = sink.ages()
    # in flight when the source published its last message: sent before it, arrived after it
    after_end_ms = (origins_ns - sink.last_origin_ns) / 1e6 + ages
    late = after_end_ms[after_end_ms > 0]
    worst = np.argsort(ages)[::-1][:WORST]
    span_s = (sink.last_origin_ns - sink.first_origin_ns) / 1e9
    duration_s = stopped - started
    rss = [s[1] for s in sampler.samples]
    return {
        **loss,
        "in_flight_at_stop": int(late.size),
        "in_flight_arrived_within_ms": round(float(late.max()), 3) if late.size else 0.0,
        "drain_s": round(drain_s, 2),
        "age_ms": {
            "count": int(ages.size),
            "p50": percentile(ages, 50),
            "p99": percentile(ages, 99),
            "p99_9": percentile(ages, 99.9),
            "max": round(float(ages.max()), 3) if ages.size else float("nan"),
            "over_ms": {str(ms): int((ages > ms).sum()) for ms in (1, 10, 100)},
            "worst": [
                {"age_ms": round(float(ages[i]), 3), "at_s": round((int(origins_ns[i]) - sink.first_origin_ns) / 1e9, 3)} for i in worst
            ],
        },
        "rate_hz": round((sent - 1) / span_s, 1) if span_s > 0 else float("nan"),
        "source_span_s": round(span_s, 2),
        "ticks_skipped": round(span_s * rate_hz) + 1 - sent if span_s > 0 else 0,
        "duration_s": round(duration_s, 1),
        "load_average_1min": [load_at_start, load_at_stop],
        "expected_s": round(expected_s, 1),
        "units_not_running": {n: s["state"] for n, s in stats.items() if s["state"] != "running"},
        "relay_callback_avg_us": round(float(np.mean([stats[relay_name(i)]["callback_avg_us"] for i in range(1, relays + 1)])), 2),
        "manager": {
            "cpu_percent": round(100 * (cpu1 - cpu0) / (cpu1_at - cpu0_at), 1),
            "rss_at_ready_mib": round(rss_at_ready_mib, 1),
            "rss_first_mib": round(rss[0], 1) if rss else float("nan"),
            "rss_last_mib": round(rss[-1], 1) if rss else float("nan"),
            "rss_max_mib": round(max(rss), 1) if rss else float("nan"),
            "rss_samples": [[round(t, 1), round(m, 2)] for t, m in sampler.samples],
            "rss": rss_slope(sampler.samples, duration_s),
            "threads": threads,
            "exit_code": exit_code,
        },
    }


def report(r: dict[str, Any], relays: int, rate_hz: float) -> None:
    """Print the figures of one run, targets beside them."""
    print(f"\nmessages: sent {r['sent']:,}, received {r['received']:,}, lost {r['lost']:,} "
          f"(explained by dyknow's counters {r['explained']:,}, unexplained {r['unexplained']:,}; target {TARGET_UNEXPLAINED} "
          f"unexplained: {'met' if r['unexplained'] <= TARGET_UNEXPLAINED else 'NOT met'})")  # fmt: skip
    for c in r["explained_by"]:
        print(f"  explained: {c['unit']}.{c['port']} {c['cause']}: {c['count']:,}")
    for x in r["unexplained_located"]:
        print(f"  unexplained, located at {x['where']}: {x['count']:,}: {x['cause']}")
    print(f"  accounts balance hop by hop: {'yes' if r['balanced'] else 'NO'}; duplicates at the sink {r['duplicates']}, "
          f"origin times out of order {r['origin_out_of_order']}")  # fmt: skip
    print(f"  at stop: in flight when the source published its last message: {r['in_flight_at_stop']:,} (all arrived within "
          f"{r['in_flight_arrived_within_ms']:.3f} ms of it); counted after the sink was quiet for {QUIET_S:g} s ({r['drain_s']:.1f} s)")  # fmt: skip
    if r["units_not_running"]:
        print(f"  units not running at the end: {r['units_not_running']}")
    a = r["age_ms"]
    print(f"end-to-end age through {relays} relays and one Zenoh hop ({a['count']:,} messages): "
          f"p50 {a['p50']:.3f} ms, p99 {a['p99']:.3f} ms, p99.9 {a['p99_9']:.3f} ms, max {a['max']:.3f} ms")  # fmt: skip
    over = ", ".join(f"{n:,} over {ms} ms" for ms, n in a["over_ms"].items())
    worst = ", ".join(f"{w['age_ms']:.1f} ms at {w['at_s']:.1f} s" for w in a["worst"][:5])
    print(f"  {over}; the oldest: {worst} (seconds after the first message)")
    print(f"rate achieved: {r['rate_hz']:,.1f} msg/s of {rate_hz:g} asked: {r['sent']:,} messages over {r['source_span_s']:.1f} s of "
          f"origin times ({r['expected_s']:.1f} s at the asked rate); the source's timer skipped {r['ticks_skipped']:,} ticks it was "
          f"late for (it skips rather than bursts)")  # fmt: skip
    print(f"relays: callback average {r['relay_callback_avg_us']:.1f} us")
    m = r["manager"]
    s = m["rss"]
    print(f"machine load average (1 min) at the source's start and stop: {r['load_average_1min'][0]:.2f}, {r['load_average_1min'][1]:.2f}")
    print(f"manager: CPU {m['cpu_percent']:.1f} % of one core while the source ran, {m['threads']} threads; VmRSS {m['rss_at_ready_mib']:.1f} MiB when ready, "
          f"{m['rss_first_mib']:.1f} MiB at the source's start, {m['rss_last_mib']:.1f} MiB at the end (max {m['rss_max_mib']:.1f})")  # fmt: skip
    print(f"manager RSS slope {s['window']} ({s['samples_in_window']} samples from {s['window_start_s']:g} s): "
          f"{s['slope_mb_per_min']:+.4f} MB/min; target < {s['target_mb_per_min']:g} MB/min: {'met' if s['met'] else 'NOT met'}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """Run the soak, print its figures beside their targets, write the JSON if asked."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=5.0, help="how long the source publishes (default 5)")
    parser.add_argument("--relays", type=int, default=20, help="relays in the chain (default 20)")
    parser.add_argument("--rate-hz", type=float, default=1000.0, help="the source's rate (default 1000)")
    parser.add_argument("--sample-s", type=float, default=None, help="seconds between RSS samples (default 2; shorter for short runs)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    if args.minutes <= 0 or args.relays < 1 or args.rate_hz <= 0:
        parser.error(f"got --minutes {args.minutes:g} --relays {args.relays} --rate-hz {args.rate_hz:g}; expected all positive")
    if not Path("/proc/self/status").is_file():
        parser.error("this benchmark reads /proc (Linux only)")
    sample_s = args.sample_s or min(2.0, args.minutes * 60 / 20)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the finally blocks: the manager is stopped

    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}", flush=True)
    print(f"soak: periodic-source at {args.rate_hz:g} Hz ({PAYLOAD_BYTES} B) -> {args.relays} relays in one dyknow manager process "
          f"-> Zenoh -> sink in this process; {args.minutes:g} min; VmRSS sampled every {sample_s:g} s", flush=True)  # fmt: skip
    results = run(args.minutes, args.relays, args.rate_hz, sample_s)
    report(results, args.relays, args.rate_hz)
    if args.json:
        config = {
            "minutes": args.minutes,
            "relays": args.relays,
            "rate_hz": args.rate_hz,
            "payload_bytes": PAYLOAD_BYTES,
            "sample_s": sample_s,
        }
        targets = {"unexplained": TARGET_UNEXPLAINED, "rss_slope_mb_per_min": f"< {TARGET_SLOPE_MB_PER_MIN:g} after the first minute"}
        write_json(args.json, {"machine": info, "config": config, "targets": targets, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
