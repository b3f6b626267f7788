"""A manager on a starved CPU: threads, spawn cost and the latency of an important stream beside busy processes.

One manager in this process (the switch interval of ``dyknow manager``) runs ``--units`` units
(default 1,000; ``--full``: 10,000): groups of a source at 1 Hz, a relay (a Python callback) and a
formula monitor over the relay's output, spawned one after the other through the Python API.
Beside them run two streams of 200 Hz, each into a sink that records the age of every message on
arrival (its hop from the source, counted from the time the source's tick was due, so a lane that
runs it late counts): the *high-priority* one is a request (``Heartbeat(robot)``,
transformations of ``<priority>`` 1, so the anchor and the sink have it too), the *low-priority*
one a source and a sink of priority 200; the masses have the default, 100.

Then, for 0, 1 and 2 CPU hogs per core (busy ``python -c "while True: pass"`` processes), it
records the two streams for ``--seconds`` (after a second to settle; longer, up to 30 s, until the
high-priority stream gave 20 messages), sampling the process's
threads (``/proc``) and the manager's lanes every 0.1 s. Printed, each beside its target:

- spawn: seconds per 1,000 units, for each block of 1,000 (or of a tenth of the units), the
  first and the last (target: the last costs at most 1.5 times the first: flat);
- threads: the most lanes seen against the bound (``max_lanes``: never above it) and the most
  threads of the process (Zenoh's and the services' included);
- the p99 hop of the high- and of the low-priority stream with each number of hogs (target: the
  high-priority p99 with two hogs per core within 3x of its p99 with none), the overload state
  and how many units were shed;
- the load average (1 min) at the start and end of each phase.

``--nice`` (default ``0,-10,-20``): the phases are run at each of these scheduling nicenesses of the
manager's process (:func:`dyknow.priority.set_nice`, what ``dyknow manager --nice`` does), one
after the other in the same manager; the hogs always run at the default, 0, as other work on the
robot's computer would. A niceness the system refuses (under 0 without ``CAP_SYS_NICE``) is said
and left out.

    python benchmarks/overload.py                    # 1,000 units, 5 s per phase
    python benchmarks/overload.py --full             # 10,000 units, 10 s per phase
    python benchmarks/overload.py --units 150 --seconds 1 --json out/overload.json   # a smoke run
    python benchmarks/overload.py --full --units 4000 --spawn-only --keys namespace   # spawn cost only, smaller
    python benchmarks/overload.py --nice 0           # the manager at the hogs' priority only
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from dyknow import Manager, Message, Unit
from dyknow.keys import default_key
from dyknow.priority import PriorityError, set_nice
from dyknow.reasoning import monitor_spec
from dyknow.security import Limits
from dyknow.spec import Param, Port, Tag, TransformationSpec

from harness import machine, percentile, write_json

RATE_HZ = 200.0  # the two streams measured (1,000 ages a phase of 5 s: a p99 not decided by two or three messages)
SPAWN_FLAT_RATIO = 1.5  # the last block of spawns may cost at most this many times the first (issue 41: flat)
HIGH_P99_RATIO = 3.0  # the high-priority p99 with two hogs per core, against none
FORMULA = "historically[0, 2s] Level(x{k}) > 0.1"


class Beat(Unit):
    """Publishes a value every ``1/rate_hz`` s (a timer on its lane), stamped with the time the
    tick was due: a lane that runs it late shows in the age at the sink."""

    def setup(self) -> None:
        """Start the timer."""
        self.count = 0
        self._timer = self.create_timer(1.0 / float(self.params.get("rate_hz", 1.0)), self._tick)

    def _tick(self) -> None:
        self.count += 1
        late_ns = time.monotonic_ns() - self._timer.next_ns  # (next_ns: this tick's due time while it runs)
        self.publish("out", float(self.count % 10) / 10, origin_ns=time.time_ns() - max(0, late_ns))


class Pass(Unit):
    """Republishes what comes in (a Python callback per message)."""

    def on_message(self, port: str, msg: Message) -> None:
        """Publish the payload on."""
        self.publish("out", msg.payload)


class Ages(Unit):
    """Records, while ``recording``, how old each message is on arrival (ns)."""

    def setup(self) -> None:
        """Not recording yet."""
        self.recording = False
        self.ages_ns: list[int] = []

    def on_message(self, port: str, msg: Message) -> None:
        """Record the message's age."""
        if self.recording:
            self.ages_ns.append(time.time_ns() - msg.origin_ns)


def _specs() -> list[TransformationSpec]:
    rate = Param("rate_hz", "float", RATE_HZ)
    return [
        TransformationSpec(label="mass-source", source="overload:Beat", params=(Param("rate_hz", "float", 1.0),), ports=(Port("out", "out"),)),
        TransformationSpec(label="mass-relay", source="overload:Pass", ports=(Port("in", "in"), Port("out", "out"))),
        monitor_spec(FORMULA.format(k=0), label="mass-monitor"),
        TransformationSpec(
            label="heartbeat", source="overload:Beat", params=(rate,), ports=(Port("out", "out"),), tags=(Tag("out", "Heartbeat(robot)"),), priority=1
        ),
        TransformationSpec(label="high-sink", source="overload:Ages", ports=(Port("in", "in", queue=64),), priority=1),
        TransformationSpec(label="low-source", source="overload:Beat", params=(rate,), ports=(Port("out", "out"),), priority=200),
        TransformationSpec(label="low-sink", source="overload:Ages", ports=(Port("in", "in", queue=64),), priority=200),
    ]


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def _spawn_masses(manager: Manager, units: int, block: int, keys: str = "outside") -> list[float]:
    """Spawn ``units`` units in groups of three; seconds per 1,000 units for each block of ``block``.

    ``keys``: ``outside`` binds every port to a key of its own under ``bench/`` (each input then
    costs a Zenoh subscriber of its own); ``namespace`` leaves the outputs at their default keys,
    ``dyknow/<manager>/<unit>/<port>``, which the manager's one subscriber on its namespace serves."""
    per_block: list[float] = []
    spawned, start = 0, time.perf_counter()
    k = 0
    while spawned < units:
        if keys == "namespace":
            source_out, relay_out = default_key(manager.name, f"s{k}", "out"), default_key(manager.name, f"r{k}", "out")
            verdicts = default_key(manager.name, f"m{k}", "verdicts")
        else:
            source_out, relay_out, verdicts = f"bench/source/{k}", f"bench/relay/{k}", f"bench/verdicts/{k}"
        group = [
            ("mass-source", f"s{k}", {"out": source_out}, {}),
            ("mass-relay", f"r{k}", {"in": source_out, "out": relay_out}, {}),
            ("mass-monitor", f"m{k}", {"t0": relay_out, "verdicts": verdicts}, {"formula": FORMULA.format(k=k)}),
        ]
        for label, name, bindings, params in group[: units - spawned]:
            manager.spawn(label, name, bindings=bindings, params=params)
            spawned += 1
            if spawned % block == 0:
                now = time.perf_counter()
                per_block.append((now - start) * 1000 / block)
                start = now
        k += 1
    return per_block


#: A busy process at the default priority (it leaves the niceness it inherited from the benchmark).
HOG = "import os\nos.setpriority(os.PRIO_PROCESS, 0, 0)\nwhile True: pass"


def _hogs(count: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(count)]


#: The fewest high-priority messages a phase records (it runs past --seconds for them, up to MAX_EXTRA_S).
MIN_HIGH, MAX_EXTRA_S = 20, 30.0


def _phase(manager: Manager, high: Any, low: Any, hogs: int, seconds: float, nice: int) -> dict[str, Any]:
    procs = _hogs(hogs)
    try:
        load_before = os.getloadavg()[0]
        time.sleep(1.0)  # the hogs start; the manager settles
        high.ages_ns, low.ages_ns = [], []
        high.recording = low.recording = True
        lanes_max, threads_max, states, shed_max = 0, 0, set(), 0
        start = time.monotonic()
        end, limit = start + seconds, start + seconds + MAX_EXTRA_S
        # for --seconds, and on until the high-priority stream has given MIN_HIGH messages (a short
        # smoke phase on a machine loaded beyond its own hogs may otherwise record none)
        while time.monotonic() < end or (len(high.ages_ns) < MIN_HIGH and time.monotonic() < limit):
            load = manager.load()
            lanes_max = max(lanes_max, load["threads"])
            threads_max = max(threads_max, _threads())
            states.add(load["overload"]["state"])
            shed_max = max(shed_max, load["overload"]["units_shed"])
            time.sleep(0.1)
        high.recording = low.recording = False
        return {
            "nice": nice,
            "hogs": hogs,
            "recorded_s": round(time.monotonic() - start, 2),
            "lanes_max": lanes_max,
            "threads_max": threads_max,
            "high_p50_ms": percentile([a / 1e6 for a in high.ages_ns], 50),
            "high_p99_ms": percentile([a / 1e6 for a in high.ages_ns], 99),
            "high_count": len(high.ages_ns),
            "low_p50_ms": percentile([a / 1e6 for a in low.ages_ns], 50),
            "low_p99_ms": percentile([a / 1e6 for a in low.ages_ns], 99),
            "low_count": len(low.ages_ns),
            "overloaded": "overloaded" in states,
            "units_shed_max": shed_max,
            "load_before": round(load_before, 2),
            "load_after": round(os.getloadavg()[0], 2),
        }
    finally:
        for proc in procs:
            proc.kill()
        for proc in procs:
            proc.wait()


def _high_target(phases: list[dict[str, Any]]) -> dict[str, Any]:
    """The high-priority p99 with the most hogs against none, at one niceness."""
    none, most = phases[0]["high_p99_ms"], phases[-1]["high_p99_ms"]
    return {"nice": phases[0]["nice"], "none_ms": none, "two_per_core_ms": most, "ratio": round(most / none, 2) if none else None,
            "target_ratio": HIGH_P99_RATIO, "met": bool(none) and most <= HIGH_P99_RATIO * none}  # fmt: skip


def run(
    units: int, seconds: float, max_lanes: int | None, keys: str = "outside", spawn_only: bool = False, nices: tuple[int, ...] = (0,)
) -> dict[str, Any]:
    """Spawn the units, then measure each phase of hogs at each niceness; the results and the targets."""
    sys.setswitchinterval(0.001)  # as dyknow manager does
    cores = os.cpu_count() or 1
    options: dict[str, Any] = {"max_lanes": max_lanes} if max_lanes is not None else {}
    with Manager("overload-bench", specs=_specs(), listen=[], serve=False, limits=Limits(max_units=units + 20), **options) as manager:
        bound = manager.load()["max_lanes"]
        block = 1000 if units >= 2000 else max(1, units // 10)
        spawn0 = time.perf_counter()
        per_block = _spawn_masses(manager, units, block, keys)
        spawn_s = time.perf_counter() - spawn0
        key = manager.request("Heartbeat(robot)")
        manager.spawn("high-sink", "high", bindings={"in": key})
        manager.spawn("low-sink", "low", bindings={"in": "bench/low"})
        manager.spawn("low-source", "low-src", bindings={"out": "bench/low"})
        # the sinks are Ages of the module "overload" (this script runs as __main__)
        high: Any = manager.unit("high")
        low: Any = manager.unit("low")
        phases: list[dict[str, Any]] = []
        refused: dict[int, str] = {}
        for nice in (nices[:1] if spawn_only else nices):
            try:
                set_nice(nice)
            except PriorityError as error:
                refused[nice] = str(error)
                print(f"nice {nice}: not measured: {error}", flush=True)
                continue
            phases += [_phase(manager, high, low, hogs, seconds, nice) for hogs in ((0,) if spawn_only else (0, cores, 2 * cores))]
    first, last = (per_block[0], per_block[-1]) if per_block else (float("nan"), float("nan"))
    measured = sorted({p["nice"] for p in phases}, reverse=True)
    return {
        "units": units,
        "keys": keys,
        "cores": cores,
        "max_lanes": bound,
        "spawn_s": round(spawn_s, 2),
        "spawn_block": block,
        "spawn_s_per_1000": [round(x, 2) for x in per_block],
        "phases": phases,
        "refused_nice": refused,
        "targets": {
            "lanes_within_bound": {"max": max(p["lanes_max"] for p in phases), "bound": bound, "met": all(p["lanes_max"] <= bound for p in phases)},
            "spawn_flat": {"first_s_per_1000": round(first, 2), "last_s_per_1000": round(last, 2), "ratio": round(last / first, 2) if first else None,
                           "target_ratio": SPAWN_FLAT_RATIO, "met": bool(first) and last <= SPAWN_FLAT_RATIO * first},  # fmt: skip
            "high_p99": None if spawn_only else [_high_target([p for p in phases if p["nice"] == nice]) for nice in measured],
        },
    }


def report(result: dict[str, Any]) -> None:
    """Print the figures beside their targets."""
    t = result["targets"]
    print(f"{result['units']} units (sources at 1 Hz, relays, formula monitors; keys {result['keys']}) in one manager, {result['cores']} cores; "
          f"load average {os.getloadavg()[0]:.2f}")  # fmt: skip
    spawn = t["spawn_flat"]
    print(f"spawn: {result['spawn_s']:.1f} s in all; per 1,000 units, block by block of {result['spawn_block']}: "
          f"{', '.join(f'{x:.1f}' for x in result['spawn_s_per_1000'])} s")  # fmt: skip
    print(f"  first {spawn['first_s_per_1000']:.1f} s, last {spawn['last_s_per_1000']:.1f} s per 1,000 (ratio {spawn['ratio']}; "
          f"target <= {SPAWN_FLAT_RATIO:g}: {'met' if spawn['met'] else 'NOT met'})")  # fmt: skip
    print(f"{'nice':>5} {'hogs':>5} {'lanes max':>9} {'bound':>5} {'threads max':>11} {'high p50':>9} {'high p99':>9} {'low p50':>8} {'low p99':>8} "
          f"{'overloaded':>10} {'shed':>5} {'load before/after':>17}")  # fmt: skip
    for p in result["phases"]:
        print(f"{p['nice']:>5} {p['hogs']:>5} {p['lanes_max']:>9} {result['max_lanes']:>5} {p['threads_max']:>11} {p['high_p50_ms']:>7.2f}ms {p['high_p99_ms']:>7.2f}ms "
              f"{p['low_p50_ms']:>6.2f}ms {p['low_p99_ms']:>6.2f}ms {str(p['overloaded']):>10} {p['units_shed_max']:>5} "
              f"{p['load_before']:>8.2f}/{p['load_after']:<8.2f}")  # fmt: skip
    lanes = t["lanes_within_bound"]
    print(f"lanes: at most {lanes['max']} (target: never above the bound of {lanes['bound']}: {'met' if lanes['met'] else 'NOT met'})")
    if t["high_p99"] is None:
        print("high-priority p99 with hogs: not measured (--spawn-only)")
        return
    for high in t["high_p99"]:
        at = "the hogs' priority" if high["nice"] == 0 else f"--nice {high['nice']}"
        print(f"high-priority p99 at nice {high['nice']} ({at}): {high['none_ms']:.2f} ms with no hogs, {high['two_per_core_ms']:.2f} ms "
              f"with two per core (ratio {high['ratio']}; target <= {HIGH_P99_RATIO:g}x: {'met' if high['met'] else 'NOT met'})")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (see the module documentation)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--units", type=int, default=1000, help="units in the manager (default 1,000)")
    parser.add_argument("--seconds", type=float, default=5.0, help="seconds recorded per phase of hogs (default 5)")
    parser.add_argument("--full", action="store_true", help="10,000 units and 10 s per phase (unless --units or --seconds say otherwise)")
    parser.add_argument("--max-lanes", type=int, help="the manager's bound on lanes (default: the manager's own)")
    parser.add_argument("--keys", choices=("outside", "namespace"), default="outside",
                        help="where the masses' ports are bound: keys of their own under bench/ (default; an input costs a Zenoh "
                             "subscriber each) or their default keys in the manager's namespace (one subscriber serves them all)")  # fmt: skip
    parser.add_argument("--spawn-only", action="store_true", help="measure the spawns and one phase without hogs only")
    parser.add_argument("--nice", default="0,-10,-20", metavar="N[,N...]",
                        help="the manager's nicenesses to measure at, in this order (default 0,-10,-20; the hogs run at 0)")  # fmt: skip
    parser.add_argument("--json", type=Path, help="write the results as JSON")
    args = parser.parse_args(argv)
    try:
        nices = tuple(int(n) for n in args.nice.split(","))
    except ValueError:
        parser.error(f"--nice: got {args.nice!r}; expected whole numbers from -20 to 19, comma-separated")
    units = 10_000 if args.full and args.units == 1000 else args.units
    seconds = 10.0 if args.full and args.seconds == 5.0 else args.seconds
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}")
    result = run(units, seconds, args.max_lanes, args.keys, args.spawn_only, nices)
    report(result)
    if args.json:
        write_json(args.json, {"machine": info, "results": result})
    return 0


if __name__ == "__main__":
    threading.current_thread().name = "bench-main"
    sys.exit(main())
