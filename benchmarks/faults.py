"""Faults beyond a clean cut: packet loss, a slow link and a flapping link, on the paper's scenario.

The paper's scenario on three hosts (network namespaces on one bridge, :class:`dyknow.testing.hosts.Hosts`,
each process with its own ``/dev/shm``): the ``station`` serves the request ``BallTrack(field)``,
the ``robot`` runs the preferred camera (200 Hz, 4x4 frames), the ``field`` the fallback; every
manager ``--lease-ms 1000``, the station ``--dwell 1``. An observer in the station's namespace
counts what arrives on the requested key, window by window. Each scenario runs on hosts of its
own, the fault on the robot's link only:

- ``clean``: no fault, for reference;
- ``loss-5``: 5 % of the robot's packets dropped both ways (nftables). Target: no failover (the
  camera never switches);
- ``loss-30``: 30 % dropped. What happens is reported (rate, age, switches, their causes); target:
  no manager's memory grows by 64 MiB or more;
- ``slow-1mbit``: the robot's camera sends 32 KiB frames at 30 Hz (7.9 Mbit/s) over a 1 Mbit/s
  link (tc tbf both ways). Reported: the robot's frames per second, the age, switches; target:
  memory as above;
- ``flapping``: the link goes down and up every 2 s for 32 s. Target: at most 7 camera switches
  (the request moves off the robot at each loss, and back after the dwell time from a first loss,
  but after losses close together only once their penalty has decayed: flap damping,
  ``dyknow.adaptation.LINKS``; without it the same run switched 16 times, ``tests/test_hosts.py``).

    python benchmarks/faults.py                    # 20 s per fault
    python benchmarks/faults.py --seconds 10 --json out/faults.json
    python benchmarks/faults.py --smoke            # 4 s per fault, no flapping
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from dyknow import Client, Message
from dyknow.testing import CAMERA_IDS, SCENARIO_HOSTS

from failover import LEASE_MS, NETNS_PORT, ONTOLOGY, TAG, request_until_planned
from harness import Proc, machine, write_json

BOTTOM = CAMERA_IDS["bottom"]
DWELL_S = 1.0
FLAP_SWITCHES_MAX = 7
MEMORY_GROWTH_MAX_MIB = 64.0


def observe(endpoint: str, window_s: float) -> int:
    """The observer (inside the station's namespace): request ``TAG`` and print a stats line every ``window_s``."""
    lock = threading.Lock()
    arrived: list[tuple[int, int, int]] = []  # (arrival ns, age ns, camera)
    last: list[int] = []
    switches = [0]

    def on_message(msg: Message) -> None:
        now = time.time_ns()
        camera = int(msg.payload["camera"])
        with lock:
            arrived.append((now, now - msg.origin_ns, camera))  # one machine's clock: ages are true
            if last and last[0] != camera:
                switches[0] += 1
            last[:] = [camera]

    with Client("station", connect=[endpoint], timeout_s=10, lease_ms=LEASE_MS) as client:
        key = request_until_planned(client, 60)
        print(json.dumps({"event": "key", "key": key}), flush=True)
        with client.declare_subscriber(key, on_message):
            start = time.time_ns()
            while True:
                time.sleep(window_s)
                now = time.time_ns()
                with lock:
                    window, arrived[:] = list(arrived), []
                    switched, switches[0] = switches[0], 0
                    camera = last[0] if last else None
                ages = sorted(a for _, a, _ in window)
                times = [start, *(t for t, _, _ in window), now]
                print(json.dumps({
                    "event": "stats",
                    "seconds": (now - start) / 1e9,
                    "messages": len(window),
                    "by_camera": {str(c): sum(1 for _, _, x in window if x == c) for c in sorted({x for _, _, x in window})},
                    "age_p99_ms": ages[min(len(ages) - 1, int(0.99 * len(ages)))] / 1e6 if ages else None,
                    "gap_max_ms": max(b - a for a, b in zip(times, times[1:], strict=False)) / 1e6,
                    "switches": switched,
                    "camera": camera,
                }), flush=True)  # fmt: skip
                start = now


def rss_mib(proc: Proc) -> float:
    """A child's resident memory now (its PID is the same from the machine's side)."""
    for line in Path(f"/proc/{proc.proc.pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run(scenario: str, seconds: float, tmp: Path) -> dict[str, Any]:
    """One scenario on hosts of its own; its figures."""
    from dyknow.testing.hosts import Hosts

    robot_specs = SCENARIO_HOSTS["robot"]
    if scenario == "slow-1mbit":
        robot_specs = tmp / "robot-64.xml"
        robot_specs.write_text(
            SCENARIO_HOSTS["robot"].read_text().replace('<param name="rate_hz" type="float">200</param>',
                                                        '<param name="rate_hz" type="float">30</param><param name="size" type="int">64</param>')
        )  # fmt: skip
    procs: dict[str, Proc] = {}
    with Hosts(["station", "robot", "field"]) as hosts:
        station = f"tcp/{hosts.address('station')}:{NETNS_PORT}"
        try:
            for name in ("station", "robot", "field"):
                argv = [
                    sys.executable, "-m", "dyknow.cli", "manager", "--name", name,
                    "--specs", str(robot_specs if name == "robot" else SCENARIO_HOSTS[name]), "--ontology", str(ONTOLOGY),
                    "--listen", f"tcp/{hosts.address(name)}:{NETNS_PORT}", *(["--connect", station] if name != "station" else []),
                    "--host", f"{name}-host", "--lease-ms", str(LEASE_MS), "--json", *(["--dwell", str(DWELL_S)] if name == "station" else []),
                ]  # fmt: skip
                # (the station logs its adaptations and peers at INFO: what it planned, and why, when the robot's camera never comes)
                env = {**os.environ, "DYKNOW_LOG": "INFO"} if name == "station" else None
                procs[name] = Proc(argv, popen=lambda a, n=name, **kw: hosts.popen(n, a, **kw), env=env)
                procs[name].next_json(30, event="ready")
            window = 2.0
            observer = Proc([sys.executable, __file__, "--observe", station, str(window)], popen=lambda a, **kw: hosts.popen("station", a, **kw))
            procs["observer"] = observer
            observer.next_json(60, event="key")
            deadline = time.monotonic() + 60
            while (stats := observer.next_json(30, event="stats"))["camera"] != BOTTOM:  # the robot's camera feeds the key
                if time.monotonic() > deadline:
                    said = "".join(f"\n{n}'s log, its end: {procs[n].error_tail()}" for n in ("station", "robot"))
                    said += "\nthe station's adaptation and peer lines:\n" + "\n".join(
                        line for line in procs["station"].error_text().splitlines() if " dyknow.adaptation: " in line or " dyknow.manager" in line
                    )[-6000:]
                    raise RuntimeError(f"the robot's camera never fed the key within 60 s; the last window: {stats}{said}")
            observer.next_json(30, event="stats")  # a full window on the preferred camera
            before = {n: rss_mib(procs[n]) for n in ("station", "robot")}
            if scenario.startswith("loss-"):
                hosts.loss("robot", float(scenario.split("-")[1]))
            elif scenario == "slow-1mbit":
                hosts.bandwidth("robot", "1mbit")
            if scenario == "flapping":
                threading.Thread(target=_flap, args=(hosts, seconds), daemon=True).start()
            windows = [observer.next_json(30, event="stats") for _ in range(max(1, round(seconds / window)))]
            grew = {n: round(rss_mib(procs[n]) - before[n], 1) for n in before}
        finally:
            for proc in reversed(list(procs.values())):
                proc.close()
    seconds_total = sum(w["seconds"] for w in windows)
    messages = sum(w["messages"] for w in windows)
    robot = sum(w["by_camera"].get(str(BOTTOM), 0) for w in windows)
    ages = [w["age_p99_ms"] for w in windows if w["age_p99_ms"] is not None]
    return {
        "scenario": scenario,
        "seconds": round(seconds_total, 1),
        "rate": round(messages / seconds_total, 1),
        "robot_rate": round(robot / seconds_total, 1),
        "age_p99_ms_worst_window": round(max(ages), 1) if ages else None,
        "gap_max_ms": round(max(w["gap_max_ms"] for w in windows), 1),
        "switches": sum(w["switches"] for w in windows),
        "memory_growth_mib": grew,
        "windows": windows,
    }


def _flap(hosts: Any, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end - 4:
        hosts.cut("robot")
        time.sleep(2)
        hosts.restore("robot")
        time.sleep(2)


def verdict(row: dict[str, Any]) -> str:
    """The row's target and whether it was met."""
    grew = max(row["memory_growth_mib"].values())
    memory = f"memory growth {grew:.1f} MiB (target < {MEMORY_GROWTH_MAX_MIB:g}): {'met' if grew < MEMORY_GROWTH_MAX_MIB else 'NOT met'}"
    if row["scenario"] == "loss-5":
        return f"switches {row['switches']} (target 0: no false failover): {'met' if row['switches'] == 0 else 'NOT met'}; {memory}"
    if row["scenario"] == "flapping":
        met = row["switches"] <= FLAP_SWITCHES_MAX
        return f"switches {row['switches']} (target <= {FLAP_SWITCHES_MAX}): {'met' if met else 'NOT met'}; {memory}"
    return memory


def main(argv: list[str] | None = None) -> int:
    """Run every scenario and print its figures beside its target."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=None, help="how long each fault lasts (default 20; flapping 32)")
    parser.add_argument("--smoke", action="store_true", help="a quick run: 4 s per fault, no flapping")
    parser.add_argument("--scenarios", help="comma-separated, of clean, loss-5, loss-30, slow-1mbit, flapping (default all; --smoke: no flapping)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--observe", nargs=2, metavar=("ENDPOINT", "WINDOW_S"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.observe:
        return observe(args.observe[0], float(args.observe[1]))
    from dyknow.testing.hosts import faults_unavailable, unavailable

    why = unavailable() or faults_unavailable()
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}", flush=True)
    if why is not None:
        print(f"skipped: {why}")
        return 0
    seconds = args.seconds or (4.0 if args.smoke else 20.0)
    scenarios = ["clean", "loss-5", "loss-30", "slow-1mbit"] + ([] if args.smoke else ["flapping"])
    if args.scenarios:
        scenarios = [s.strip() for s in args.scenarios.split(",") if s.strip()]
        unknown = set(scenarios) - {"clean", "loss-5", "loss-30", "slow-1mbit", "flapping"}
        if unknown:
            parser.error(f"--scenarios: unknown {', '.join(sorted(unknown))}")
    print(f"scenario: {TAG} on the station, robot-camera 200 Hz on the robot, ceiling-camera on the field; "
          f"lease {LEASE_MS} ms, dwell {DWELL_S} s; each fault on the robot's link for {seconds:g} s (flapping: 32 s)\n", flush=True)  # fmt: skip
    rows = []
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        for scenario in scenarios:
            row = run(scenario, 32.0 if scenario == "flapping" else seconds, Path(tmp))
            rows.append(row)
            print(f"{scenario:<11} {row['rate']:>7.1f} msg/s (robot {row['robot_rate']:>6.1f})  age p99 {row['age_p99_ms_worst_window']:>8} ms  "
                  f"gap max {row['gap_max_ms']:>7.1f} ms  switches {row['switches']:>2}   {verdict(row)}", flush=True)  # fmt: skip
    if args.json:
        write_json(args.json, {"machine": info, "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
