"""A consumer on one host of a namespace test: requests a stream and reports which camera feeds it.

Run as ``python -m tests.netns_observer ENDPOINT MANAGER TAG [CA CERT KEY]`` inside a host's
namespace (the test process cannot reach addresses inside the namespaces); with TLS files it
calls with that certificate. It prints JSON lines: the request's
``key``, then a ``camera`` line each time the camera id in the frames changes; on a line
``adaptations`` or ``managers`` on its standard input it prints that list, and on ``stats`` what
arrived since the last ``stats`` (messages, rate, the largest gap, the age p99 on this host's
clock as stamped, the age p50 corrected by the station's clock offsets (``Client.follow_clocks``,
looked up every second as a user who wants current ages would) with the largest uncertainty of
those used and the count of messages of a clock it did not know, the camera switches and the messages from each camera); on ``lost``, the messages lost on the way into each
unit of the manager (by label); on ``ports``, every input port of the manager's units with its
hop and age (latency) p50 and its clock figures (see :class:`dyknow.stats.PortStatistics`); on
``model NAME``, the model of manager NAME (as its ``get_model`` gives it).
"""

from __future__ import annotations

import json
import sys
import threading
import time

from dyknow import Client, Message
from dyknow.access import TlsFiles
from dyknow.client import ClockView


def main() -> int:
    """Request, watch, answer questions until standard input closes."""
    endpoint, manager, tag = sys.argv[1:4]
    tls = TlsFiles(*sys.argv[4:7]) if len(sys.argv) >= 7 else None  # CA, certificate, key
    lock = threading.Lock()
    last: list[int] = []

    def say(data: dict[str, object]) -> None:
        with lock:
            print(json.dumps(data), flush=True)

    window: dict[str, list[int]] = {"arrived": [], "ages": [], "corrected": [], "corrections": [], "cameras": []}  # since the last stats
    view: list[ClockView] = []  # the station's estimates of the clocks, once following them
    unknown = [0]
    uncertainty = [0]
    switches = [0]
    started = [time.time_ns()]

    def on_message(msg: Message) -> None:
        now = time.time_ns()
        camera = int(msg.payload["camera"])  # the tracker says which camera the frames came from
        known = view[0].corrected(msg.origin_clock, msg.origin_ns, now) if view else None  # carried on by its drift
        with lock:
            window["arrived"].append(now)
            window["ages"].append(now - msg.origin_ns)  # one machine's clock: ages are true (unless a clock is faked)
            window["cameras"].append(camera)
            if known is None:
                unknown[0] += 1
            else:
                window["corrected"].append(now - known[0])
                window["corrections"].append(msg.origin_ns - known[0])  # the clock's offset, as estimated
                uncertainty[0] = max(uncertainty[0], known[1])
        if last != [camera]:
            if last:
                switches[0] += 1
            last[:] = [camera]
            say({"event": "camera", "camera": camera, "t_ns": now})

    def stats() -> dict[str, object]:
        now = time.time_ns()
        with lock:
            arrived, ages, cameras, corrected = window["arrived"], sorted(window["ages"]), window["cameras"], sorted(window["corrected"])
            corrections = sorted(window["corrections"])
            window["arrived"], window["ages"], window["cameras"], window["corrected"], window["corrections"] = [], [], [], [], []
            since, started[0] = started[0], now
            switched, switches[0] = switches[0], 0
            not_known, unknown[0] = unknown[0], 0
            worst, uncertainty[0] = uncertainty[0], 0
        times = [since, *arrived, now]
        return {
            "event": "stats",
            "seconds": (now - since) / 1e9,
            "messages": len(arrived),
            "rate": len(arrived) / max(1e-9, (now - since) / 1e9),
            "gap_max_ms": max(b - a for a, b in zip(times, times[1:], strict=False)) / 1e6,
            "age_p99_ms": ages[min(len(ages) - 1, int(0.99 * len(ages)))] / 1e6 if ages else None,
            "age_p50_us_corrected": corrected[len(corrected) // 2] / 1e3 if corrected else None,
            "age_uncertainty_us": worst / 1e3,
            "correction_p50_us": corrections[len(corrections) // 2] / 1e3 if corrections else None,
            "middle_ns": (since + now) // 2,
            "age_unknown_clock": not_known,
            "switches": switched,
            "by_camera": {str(c): cameras.count(c) for c in sorted(set(cameras))},
            "camera": last[0] if last else None,
        }

    with Client(manager, connect=[endpoint], timeout_s=10.0, lease_ms=1000, tls=tls) as client:  # the managers' lease: see the cut as soon
        deadline = time.monotonic() + 30
        while True:
            try:
                key = client.request(tag)
                break
            except Exception as exc:  # the other managers may not be known yet
                if time.monotonic() > deadline:
                    raise
                say({"event": "waiting", "why": str(exc)[:200]})
                time.sleep(0.2)
        say({"event": "key", "key": key})

        with client.follow_clocks(every_s=1.0) as clocks, client.declare_subscriber(key, on_message):
            clocks.fetched.wait(client.timeout_s)
            view.append(clocks)
            stats()  # the window starts now
            for line in sys.stdin:
                if line.strip() == "stats":
                    say(stats())
                elif line.strip() == "lost":  # messages lost on the way into the manager's units, by unit
                    lost = {}
                    for unit in client.get_model()["units"]:
                        ports = client.get_statistics(unit["name"])["ports"].values()
                        lost[unit["label"]] = sum(int(p.get("lost", 0)) for p in ports if p["direction"] == "in")
                    say({"event": "lost", "items": sorted(lost.items())})
                elif line.strip() == "ports":  # each input port's hop and age, corrected where the clock is another's
                    ports = []
                    for unit in client.get_model()["units"]:
                        for port, entry in client.get_statistics(unit["name"])["ports"].items():
                            if entry["direction"] == "in":
                                ports.append({
                                    "unit": unit["label"], "port": port, "messages": entry["messages"],
                                    "hop_p50_us": entry["hop"]["p50_us"], "latency_p50_us": entry["latency"]["p50_us"], **entry["clock"],
                                })  # fmt: skip
                    say({"event": "ports", "items": ports})
                elif line.strip().startswith("model "):
                    name = line.split()[1]
                    say({"event": f"model {name}", "items": [client.get_model(name)]})
                elif line.strip() == "adaptations":
                    say({"event": "adaptations", "items": client.get_adaptations()})
                elif line.strip() == "managers":
                    say({"event": "managers", "items": client.managers()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
