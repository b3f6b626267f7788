"""Failover across manager processes: how long the requested stream goes without the preferred camera.

The paper's scenario split over three ``dyknow manager`` processes (``SCENARIO_HOSTS``): the
``station`` runs the processing and serves the request ``BallTrack(field)``, the ``robot`` runs
the preferred camera (``robot-camera``, id 1), the ``field`` the fallback (``ceiling-camera``,
id 3). A subscriber on the requested key (``dyknow/station/requests/BallTrack(field)``) notes
which camera each message came from (the tracker's output names it).

- ``sigkill-loopback``: all three on loopback; the robot's manager process is killed with
  SIGKILL. Measured: from just before ``os.kill`` to the first message on the requested key
  from the ceiling camera. Then the robot's manager is started again (same name) and the
  preferred camera comes back after the station's dwell time before the next kill.
  Target: p99 <= 200 ms.
- ``link-cut-1s-lease``: each manager in its own network namespace on one bridge
  (:class:`dyknow.testing.hosts.Hosts`, root and ``nft`` needed), every manager with a 1 s Zenoh
  lease; the robot is cut off, in turn by taking its link down and by dropping every packet of it
  while the link stays up (silent), and its manager keeps running. Measured: from just before the
  cut to the first ceiling-camera message on the key, seen by a subscriber inside the station's
  namespace. Target: p99 <= 1.5 s. Skipped, with the reason, where namespaces cannot be made.
- ``rejoin-*`` and ``preferred-*`` (each topology and kind of cut): the link stays cut 1.5 s
  more (every side has given the others up), then comes back. Measured: from just before its
  return until the station lists the robot among its peers and the robot the station (their
  models), and until the robot's camera is on the key again less the probation the station gave
  it (the dwell doubled for each loss in the last minute: the adaptation's cause says how long).
  Target for both: p99 <= lease + 1 s. ``false-losses-*``: a manager other than the robot
  declared lost, or a unit of another declared broken, by the station or the field (target 0).
- ``link-cut-router``: the same, with the three managers connected to a ``dyknow router`` on a
  fourth host (the rendezvous point of docs/tutorials/two-hosts.md) instead of to the station.
- ``link-cut-behind``: the same, with the three managers behind that router (``--router``, as a
  fleet deploys them: each holds one link, to the router, and listens on nothing); the robot's
  cut is of its one link, and on its return the robot dials the router again by itself.
- ``silent-host-report`` / ``-close``: a client of a host that drops every packet: from its
  construction to ``get_model``'s error with ``--timeout 2`` (target: the timeout + 0.5 s), and
  its ``close()`` (its session was dialling the host; target 100 ms: no wait for the dial); the
  wall time of ``dyknow model --timeout 2`` beside it, with Python's start and imports alone.

Every phase prints the machine's load average.

    python benchmarks/failover.py                       # 30 kills, 20 cuts of each kind per topology, 10 silent clients
    python benchmarks/failover.py --kills 5 --cuts 2 --json out/failover.json
    python benchmarks/failover.py --smoke               # 3 kills, 1 cut of each kind, 1 silent client
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dyknow import Client, Message
from dyknow.errors import DyKnowError
from dyknow.resources import specs_dir
from dyknow.testing import CAMERA_IDS, SCENARIO_HOSTS
from dyknow.transport import Session, make_config

from harness import Proc, free_ports, machine, percentile, write_json

ONTOLOGY = specs_dir() / "dyknow.ttl"
TAG = "BallTrack(field)"
BOTTOM, CEILING = CAMERA_IDS["bottom"], CAMERA_IDS["ceiling"]
TARGETS_MS = {"sigkill-loopback": 200.0, "link-cut-1s-lease": 1500.0, "link-cut-router": 1500.0, "link-cut-behind": 1500.0}
NETNS_PORT = 7447
LEASE_MS = 1000  # every manager's lease in the link-cut scenario
DWELL_S = 0.5
STEADY = 20  # messages in a row from one camera before it counts as flowing (0.1 s at 200 Hz)


def camera_of(payload: Any) -> int:
    """The camera id a message on the requested key carries: the tracker's ``camera`` field, or pixel [0, 1] of a raw frame."""
    if isinstance(payload, dict):
        return int(payload["camera"])
    return int(np.asarray(payload)[0, 1])


class CameraWatch:
    """Which camera feeds the requested key: every change, with the ``time.time_ns()`` it was seen at."""

    def __init__(self, on_change: Callable[[int, int], None] | None = None) -> None:
        self.changes: list[tuple[int, int]] = []  # (t_ns, camera)
        self.current: int | None = None
        self.run = 0  # messages in a row from the current camera
        self._cond = threading.Condition()
        self._on_change = on_change

    def on_message(self, msg: Message) -> None:
        """The subscriber's callback: note the camera, and the time when it changes."""
        t_ns = time.time_ns()
        camera = camera_of(msg.payload)
        with self._cond:
            if camera != self.current:
                self.current, self.run = camera, 0
                self.changes.append((t_ns, camera))
                if self._on_change is not None:
                    self._on_change(t_ns, camera)
            self.run += 1
            self._cond.notify_all()

    def wait_flowing(self, camera: int, timeout_s: float) -> None:
        """Wait until ``camera`` has fed the key for ``STEADY`` messages in a row; TimeoutError after ``timeout_s``."""
        with self._cond:
            if not self._cond.wait_for(lambda: self.current == camera and self.run >= STEADY, timeout_s):
                raise TimeoutError(f"camera {camera} not flowing on the key within {timeout_s} s (now: camera {self.current})")

    def wait_switch(self, camera: int, after_ns: int, timeout_s: float) -> int:
        """The time of the first message from ``camera`` seen after ``after_ns``; TimeoutError after ``timeout_s``."""

        def found() -> int | None:
            return next((t for t, c in self.changes if c == camera and t >= after_ns), None)

        with self._cond:
            if not self._cond.wait_for(lambda: found() is not None, timeout_s):
                raise TimeoutError(f"no message from camera {camera} within {timeout_s} s (now: camera {self.current})")
            return found() or 0


def manager_argv(name: str, listen: str | None, connect: str | None, *extra: str) -> list[str]:
    """``dyknow manager`` for one of the scenario's managers (its library from ``SCENARIO_HOSTS``);
    without ``listen``, behind the router ``connect`` (``--router``)."""
    links = ["--listen", listen, *(["--connect", connect] if connect else [])] if listen is not None else ["--router", str(connect)]
    return [
        sys.executable, "-m", "dyknow.cli", "manager", "--name", name, "--specs", str(SCENARIO_HOSTS[name]),
        "--ontology", str(ONTOLOGY), *links, "--host", f"{name}-host", "--json", *extra,
    ]  # fmt: skip


def load() -> str:
    """The machine's load average over 1, 5 and 15 minutes, as printed beside the figures."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def summary(samples: Sequence[float], target_ms: float) -> dict[str, Any]:
    """p50, p99 and max of ``samples`` (ms) and whether p99 meets ``target_ms``."""
    p99 = percentile(samples, 99, 1)
    return {
        "runs": len(samples),
        "p50_ms": percentile(samples, 50, 1),
        "p99_ms": p99,
        "max_ms": round(max(samples), 1) if samples else float("nan"),
        "target_ms": target_ms,
        "met": bool(samples) and p99 <= target_ms,
        "samples_ms": [round(s, 1) for s in samples],
    }


def print_row(row: dict[str, Any]) -> None:
    """One scenario's figures with its target, on one line."""
    target = f"target p99 <= {row['target_ms'] / 1000:g} s" if row["target_ms"] >= 1000 else f"target p99 <= {row['target_ms']:g} ms"
    print(
        f"{row['scenario']:<24} {row['runs']:>5} {row['p50_ms']:>9.1f} ms {row['p99_ms']:>9.1f} ms {row['max_ms']:>9.1f} ms"
        f"   {target}: {'met' if row['met'] else 'NOT met'}",
        flush=True,
    )


def request_until_planned(client: Client, timeout_s: float = 30.0) -> str:
    """Request ``TAG`` until the station can plan it (the other managers may not be known yet); its key."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return client.request(TAG)
        except DyKnowError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


# ---------------------------------------------------------------------------- (a) SIGKILL on loopback


def run_sigkill(kills: int) -> tuple[list[float], list[float]]:
    """Per kill of the robot's manager: ms from the kill to the first ceiling-camera message; and ms from
    the restart of the robot's manager to its camera flowing again on the key."""
    station_port, robot_port, field_port = free_ports(3)
    hub = f"tcp/127.0.0.1:{station_port}"
    procs: list[Proc] = []

    def start(name: str, port: int, *extra: str) -> Proc:
        proc = Proc(manager_argv(name, f"tcp/127.0.0.1:{port}", None if name == "station" else hub, *extra))
        procs.append(proc)
        proc.next_json(30, event="ready")
        return proc

    failover, returns = [], []
    try:
        start("station", station_port, "--dwell", str(DWELL_S))
        robot = start("robot", robot_port)
        start("field", field_port)
        with Client("station", connect=[hub], timeout_s=10) as client:
            deadline = time.monotonic() + 30
            while len(client.managers()) < 3:
                if time.monotonic() > deadline:
                    raise RuntimeError("the three managers did not find each other within 30 s")
                time.sleep(0.1)
            watch = CameraWatch()
            with Session(make_config(connect=[hub])) as session:
                key = request_until_planned(client)
                sub = session.declare_subscriber(key, watch.on_message)
                try:
                    watch.wait_flowing(BOTTOM, 30)
                    for i in range(kills):
                        time.sleep(0.2)
                        killed_ns = time.time_ns()
                        os.kill(robot.proc.pid, signal.SIGKILL)
                        seen_ns = watch.wait_switch(CEILING, killed_ns, 30)
                        failover.append((seen_ns - killed_ns) / 1e6)
                        robot.close()
                        procs.remove(robot)
                        print(f"  kill {i + 1}/{kills}: ceiling camera on the key {failover[-1]:.1f} ms after the SIGKILL", flush=True)
                        started = time.monotonic()
                        robot = start("robot", free_ports(1)[0])
                        watch.wait_flowing(BOTTOM, 60)
                        returns.append((time.monotonic() - started) * 1000)
                finally:
                    sub.undeclare()
            client.release(key)
    finally:
        for proc in reversed(procs):
            proc.close()
    return failover, returns


# ---------------------------------------------------------------------------- (b) link cut, 1 s lease


def netem_probe() -> str:
    """Whether this kernel has ``tc netem``: tried on the loopback of a throwaway namespace."""
    ns = f"dk-netem-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", ns], capture_output=True, text=True)
    if made.returncode != 0:
        return f"unknown (cannot make a namespace: {made.stderr.strip()})"
    try:
        tried = subprocess.run(
            ["tc", "-n", ns, "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms"], capture_output=True, text=True
        )
        return "available" if tried.returncode == 0 else f"unavailable on this kernel ({tried.stderr.strip() or 'tc failed'})"
    except OSError as exc:
        return f"unavailable ({exc})"
    finally:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def observe(endpoint: str, lease_ms: int | None) -> int:
    """The measuring process inside the station's namespace: request ``TAG`` and print, as JSON
    lines with the ``time.time_ns()`` they were seen at: each camera change on the key
    (``camera``); each change of whether the station lists the robot among its peers and the
    robot the station (``view``, from their models); each new adaptation of the station
    (``adapted``, with its cause).

    ``lease_ms``: the lease of its own Zenoh session (None: Zenoh's default, 10 s).
    """
    lock = threading.Lock()

    def say(data: dict[str, Any]) -> None:
        with lock:
            print(json.dumps({"t_ns": time.time_ns(), **data}), flush=True)

    def peers(looker: Client, manager: str) -> list[str]:
        try:  # a page past every unit and spec: the model's other fields only
            return list(looker.call_manager(manager, "get_model", {"page": {"units": 1 << 30, "specs": 1 << 30}}).get("peers", []))
        except DyKnowError:
            return []

    with Client("station", connect=[endpoint], timeout_s=10, lease_ms=lease_ms) as client, \
         Client("station", connect=[endpoint], timeout_s=1, lease_ms=lease_ms) as looker:  # fmt: skip
        key = request_until_planned(client, 60)
        say({"event": "key", "key": key})
        watch = CameraWatch(lambda t_ns, camera: say({"event": "camera", "camera": camera, "t_ns": t_ns}))
        with client.declare_subscriber(key, watch.on_message):
            view: tuple[bool, bool] | None = None
            told = 0
            for turn in itertools.count():
                station = "robot" in peers(looker, "station")
                now = (station, station and "station" in peers(looker, "robot"))
                if now != view:
                    view = now
                    say({"event": "view", "station_lists_robot": now[0], "robot_lists_station": now[1]})
                if turn % 4 == 0:
                    try:
                        events = client.get_adaptations()
                    except DyKnowError:
                        events = []
                    for event in events[told:]:
                        say({"event": "adapted", "cause": event.get("cause", ""), "kind": event.get("kind", "")})
                    told = max(told, len(events))
                time.sleep(0.05)
    return 0


class Events:
    """The observer's lines as they come, kept in order, to wait on."""

    def __init__(self, proc: Proc) -> None:
        self.seen: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        self._proc = proc
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        while True:
            line = self._proc.lines.get()
            if line.startswith("{"):
                with self._cond:
                    self.seen.append(json.loads(line))
                    self._cond.notify_all()

    def wait(self, test: Callable[[dict[str, Any]], bool], after_ns: int, timeout_s: float, what: str) -> dict[str, Any]:
        """The first line seen at or after ``after_ns`` that passes ``test``; RuntimeError after ``timeout_s``."""

        def found() -> dict[str, Any] | None:
            return next((e for e in self.seen if e["t_ns"] >= after_ns and test(e)), None)

        with self._cond:
            if not self._cond.wait_for(lambda: found() is not None, timeout_s):
                tail = [{k: v for k, v in e.items() if k != "t_ns"} for e in self.seen[-12:]]
                raise RuntimeError(f"no {what} within {timeout_s} s; the observer's last lines: {tail}; its stderr: {self._proc.error_tail()}")
            event = found()
            assert event is not None
            return event

    def since(self, after_ns: int, event: str) -> list[dict[str, Any]]:
        """The lines of ``event`` seen at or after ``after_ns``."""
        with self._cond:
            return [e for e in self.seen if e["t_ns"] >= after_ns and e.get("event") == event]

    def last_camera(self) -> int | None:
        """The camera of the latest message seen on the key (None before the first)."""
        with self._cond:
            return next((e["camera"] for e in reversed(self.seen) if e.get("event") == "camera"), None)


def stderr_text(proc: Proc) -> str:
    """Everything ``proc`` wrote on stderr so far."""
    proc.stderr.flush()
    proc.stderr.seek(0)
    return proc.stderr.read()


PROBATION = re.compile(r"manager 'robot' is trusted again: back for its probation of ([0-9.]+) s")
#: Causes that name a manager other than the robot as lost or a unit of theirs as broken: false alarms
#: (only the robot is ever cut).
FALSE_ALARM = re.compile(r"manager '(?!robot')[^']+' was lost|unit '[^']*@(?!robot')[^']+' (is unhealthy|vanished|stalled)")


def run_partitions(
    heals: int, observer_lease_ms: int | None, router: bool = False, hold_s: float = 1.5, logs: Path | None = None, behind: bool = False
) -> dict[str, Any]:
    """Cut the robot off ``heals`` times each way, alternating: its link taken down, then brought
    back up ("down"); every packet of its link dropped, then let through again ("silent"). Per cut:
    ms from the cut to the first ceiling-camera message (failover); the link stays cut ``hold_s``
    more (every side past its lease). Per heal: ms from the link's return until the station lists
    the robot among its peers and the robot the station (rejoined), and until the robot's camera
    is on the key again, less the probation the station gave the robot (the adaptation's cause
    says it). False alarms: the station or the field declaring a manager other than the robot
    lost, and the station's adaptations naming another manager lost or a unit of another broken.

    ``router``: the managers connect to a ``dyknow router`` on a host of its own (the
    two-host tutorial's rendezvous point) instead of the robot and the field connecting to the station;
    ``behind``: every manager behind that router (``--router``), the measuring client connected to it.
    ``logs``: a folder to write each process's stderr to (``DYKNOW_LOG=INFO`` says more)."""
    from dyknow.testing.hosts import Hosts

    procs: dict[str, Proc] = {}
    observer: Proc | None = None
    out: dict[str, Any] = {"failover_ms": {"down": [], "silent": []}, "rejoined_ms": {"down": [], "silent": []},
                           "preferred_ms": {"down": [], "silent": []}, "probation_s": {"down": [], "silent": []},
                           "false_alarms": [], "cuts": 0}  # fmt: skip
    router = router or behind
    with Hosts(["station", "robot", "field", *(["hub"] if router else [])]) as hosts:
        station = f"tcp/{hosts.address('station')}:{NETNS_PORT}"
        hub = f"tcp/{hosts.address('hub')}:{NETNS_PORT}" if router else None

        def start(name: str, *extra: str) -> None:
            connect = hub if router else (None if name == "station" else station)
            listen = None if behind else f"tcp/{hosts.address(name)}:{NETNS_PORT}"
            argv = manager_argv(name, listen, connect, "--lease-ms", str(LEASE_MS), *extra)
            procs[name] = Proc(argv, popen=lambda a, **kw: hosts.popen(name, a, **kw))
            procs[name].next_json(30, event="ready")

        try:
            if hub is not None:
                argv = [sys.executable, "-m", "dyknow.cli", "router", "--listen", hub, "--lease-ms", str(LEASE_MS), "--json"]
                procs["hub"] = Proc(argv, popen=lambda a, **kw: hosts.popen("hub", a, **kw))
                procs["hub"].next_json(30, event="ready")
            start("station", "--dwell", str(DWELL_S))
            start("robot")
            start("field")
            lease = ["--observer-lease-ms", str(observer_lease_ms or 0)]
            via = str(hub) if behind else station  # (a manager behind the router listens on nothing)
            observer = Proc([sys.executable, __file__, "--observe", via, *lease], popen=lambda a, **kw: hosts.popen("station", a, **kw))
            events = Events(observer)
            events.wait(lambda e: e.get("event") == "key", 0, 60, "key")
            events.wait(lambda e: e.get("event") == "camera" and e["camera"] == BOTTOM, 0, 60, "robot camera")
            began_ns = time.time_ns()
            for i in range(2 * heals):
                kind = ("down", "silent")[i % 2]
                if events.last_camera() != BOTTOM:
                    events.wait(lambda e: e.get("event") == "camera" and e["camera"] == BOTTOM, 0, 60, "robot camera")
                time.sleep(1.0)  # let the robot's camera flow for a while
                cut_ns = time.time_ns()
                hosts.cut("robot", silent=kind == "silent")
                seen = events.wait(lambda e: e.get("event") == "camera" and e["camera"] == CEILING, cut_ns, 30, "ceiling camera")
                out["failover_ms"][kind].append((seen["t_ns"] - cut_ns) / 1e6)
                time.sleep(hold_s)
                back_ns = time.time_ns()
                hosts.restore("robot")
                listed = events.wait(lambda e: e.get("event") == "view" and e["station_lists_robot"], back_ns, 120, "the robot listed")
                joined = events.wait(lambda e: e.get("event") == "view" and e["robot_lists_station"], back_ns, 120, "rejoin")
                camera = events.wait(lambda e: e.get("event") == "camera" and e["camera"] == BOTTOM, back_ns, 120, "robot camera back")
                # the adaptation that brought it back (the observer reads them a few times a second)
                trusted = events.wait(lambda e: e.get("event") == "adapted" and PROBATION.search(e["cause"]) is not None, back_ns, 30,
                                      "the robot trusted again")  # fmt: skip
                match = PROBATION.search(trusted["cause"])
                probation = float(match.group(1)) if match else 0.0
                out["rejoined_ms"][kind].append((joined["t_ns"] - back_ns) / 1e6)
                out["preferred_ms"][kind].append((camera["t_ns"] - back_ns) / 1e6 - probation * 1000)
                out["probation_s"][kind].append(probation)
                out["cuts"] += 1
                print(f"  {kind:>6} {i // 2 + 1}/{heals}: failover {out['failover_ms'][kind][-1]:.0f} ms; after the link's return the "
                      f"station listed the robot in {(listed['t_ns'] - back_ns) / 1e6:.0f} ms, both each other in "
                      f"{out['rejoined_ms'][kind][-1]:.0f} ms, robot's camera back {(camera['t_ns'] - back_ns) / 1e6:.0f} ms "
                      f"(probation {probation:g} s)", flush=True)  # fmt: skip
            said = {name: stderr_text(procs[name]) for name in ("station", "field")}  # (WARNING lines: a manager lost)
            for name, text in said.items():
                out["false_alarms"] += [f"{name}: {line.strip()[:200]}" for line in text.splitlines() if FALSE_ALARM.search(line)]
            out["false_alarms"] += [f"station adapted: {e['cause'][:200]}" for e in events.since(began_ns, "adapted") if FALSE_ALARM.search(e["cause"])]
        finally:
            if observer is not None:
                observer.close()
            for name, proc in reversed(procs.items()):
                if logs is not None:
                    logs.mkdir(parents=True, exist_ok=True)
                    (logs / f"{'behind' if behind else 'router' if router else 'peers'}-{name}.log").write_text(stderr_text(proc))
                proc.close()
        out["links"] = hosts.shaping
    return out


# ---------------------------------------------------------------------------- (d) a silent host

SILENT_TIMEOUT_S = 2.0
SILENT_CLIENT = """
import json, sys, time
t0 = time.monotonic()
from dyknow import Client, ServiceError
imported = time.monotonic()
client = Client("robot", connect=[sys.argv[1]], timeout_s=float(sys.argv[2]), lease_ms=1000)
try:
    client.get_model()
    reason = "answered"
except ServiceError as exc:
    reason = str(exc.details.get("reason"))
said = time.monotonic()
client.close()
closed = time.monotonic()
print(json.dumps({"import_s": imported - t0, "report_s": said - imported, "close_s": closed - said, "reason": reason}), flush=True)
"""


def run_silent_host(runs: int) -> dict[str, list[float]]:
    """A client of a host that drops every packet (its manager's address on a host cut off
    silently): per run, the seconds from the client's construction to ``get_model``'s error
    (``report``; target --timeout + 0.5 s), the seconds its ``close()`` took (target: no wait for
    the dial under way), and the whole command's wall time, ``dyknow model --timeout 2`` (Python's
    start and imports included, measured alone too)."""
    from dyknow.testing.hosts import Hosts

    out: dict[str, list[float]] = {"report_s": [], "close_s": [], "import_s": [], "command_s": [], "python_import_s": []}
    with Hosts(["robot", "laptop"]) as hosts:
        hosts.cut("robot", silent=True)
        endpoint = f"tcp/{hosts.address('robot')}:{NETNS_PORT}"
        for _ in range(runs):
            done = subprocess.run(hosts.command("laptop", [sys.executable, "-c", SILENT_CLIENT, endpoint, str(SILENT_TIMEOUT_S)]),
                                  capture_output=True, text=True, timeout=120)  # fmt: skip
            row = json.loads(done.stdout)
            assert row["reason"] == "silent", (row, done.stderr[-1000:])
            for name in ("report_s", "close_s", "import_s"):
                out[name].append(row[name])
            argv = [sys.executable, "-m", "dyknow.cli", "model", "--manager", "robot", "--connect", endpoint, "--timeout", f"{SILENT_TIMEOUT_S:g}"]
            started = time.monotonic()
            done = subprocess.run(hosts.command("laptop", argv), capture_output=True, text=True, timeout=120)
            out["command_s"].append(time.monotonic() - started)
            assert done.returncode == 1 and "did not answer" in done.stderr, done.stderr[-1000:]
            started = time.monotonic()
            subprocess.run(hosts.command("laptop", [sys.executable, "-c", "import dyknow.cli"]), check=True, timeout=120)
            out["python_import_s"].append(time.monotonic() - started)
    return out


# ---------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    """Run both scenarios (or skip the link cut, saying why) and print p50/p99/max beside their targets."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=None, help="SIGKILLs of the robot's manager on loopback (default 30; --smoke 3)")
    parser.add_argument("--cuts", type=int, default=None,
                        help="cuts of the robot's link in namespaces, of each kind (down, silent) and topology (default 20; --smoke 1)")  # fmt: skip
    parser.add_argument("--smoke", action="store_true", help="a quick run: 3 kills, 1 cut of each kind")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument(
        "--observer-lease-ms",
        type=int,
        default=LEASE_MS,
        help=f"link cut: the lease of the measuring client's own Zenoh session (default {LEASE_MS}, the managers'; 0: Zenoh's default, 10 s)",
    )
    parser.add_argument("--topology", choices=["peers", "router", "behind", "both", "all"], default="all",
                        help="link cut: the managers as peers (robot and field connect to the station), connected to a router, behind "
                             "a router (--router), peers and router (both), or the three (all, default)")  # fmt: skip
    parser.add_argument("--silent", type=int, default=None, help="clients of a silent host, in namespaces (default 10; --smoke 1)")
    parser.add_argument("--logs", type=Path, help="link cuts: write each manager's stderr to this folder (with DYKNOW_LOG=INFO: what it saw)")
    parser.add_argument("--observe", metavar="ENDPOINT", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.observe:
        return observe(args.observe, args.observer_lease_ms or None)
    kills = args.kills if args.kills is not None else (3 if args.smoke else 30)
    cuts = args.cuts if args.cuts is not None else (1 if args.smoke else 20)
    args.silent = args.silent if args.silent is not None else (1 if args.smoke else 10)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the finally blocks: children killed, namespaces deleted

    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}; load average {load()}", flush=True)
    print(f"scenario: {TAG} requested on the station; robot-camera (id {BOTTOM}) on the robot, ceiling-camera (id {CEILING}) "
          f"on the field, cameras at 200 Hz, station --dwell {DWELL_S}", flush=True)  # fmt: skip
    results: list[dict[str, Any]] = []
    skipped: dict[str, str] = {}
    notes: list[str] = []

    if kills > 0:
        print(f"\n(a) sigkill-loopback: {kills} SIGKILLs of the robot's manager, three processes on loopback; load average {load()}", flush=True)
        samples, returns = run_sigkill(kills)
        results.append({"scenario": "sigkill-loopback", **summary(samples, TARGETS_MS["sigkill-loopback"]),
                         "measured": "from just before os.kill(robot, SIGKILL) to the first ceiling-camera message on the requested key",
                         "return_p50_ms": percentile(returns, 50, 1), "return_max_ms": round(max(returns), 1) if returns else None})  # fmt: skip
        notes.append(f"sigkill-loopback: after a restart of the robot's manager its camera was back on the key in "
                     f"p50 {percentile(returns, 50, 0):.0f} ms, max {max(returns):.0f} ms (from launching it to 20 messages in a row from its camera: start-up, discovery, and its "
                     f"probation: the dwell {DWELL_S} s doubled for each loss in the last minute, at most 30 s; a kill every few seconds)")  # fmt: skip

    from dyknow.testing.hosts import faults_unavailable, unavailable

    why = unavailable() or faults_unavailable()
    if why is not None:
        skipped["link-cut-1s-lease"] = why
        print(f"\n(b) link-cut-1s-lease: skipped: {why}", flush=True)
    elif cuts > 0:
        netem = netem_probe()
        observer_lease = f"{args.observer_lease_ms} ms" if args.observer_lease_ms else "Zenoh's default (10 s)"
        topologies = {"peers": ["link-cut-1s-lease"], "router": ["link-cut-router"], "behind": ["link-cut-behind"],
                      "both": ["link-cut-1s-lease", "link-cut-router"]}.get(args.topology, ["link-cut-1s-lease", "link-cut-router", "link-cut-behind"])  # fmt: skip
        for scenario in topologies:
            router, behind = scenario == "link-cut-router", scenario == "link-cut-behind"
            short = "behind" if behind else "router" if router else "peers"
            layout = {
                "router": "the three managers connect to a dyknow router on a fourth host",
                "behind": "the three managers behind a dyknow router on a fourth host (--router: one link each)",
                "peers": "the robot and the field connect to the station",
            }[short]
            print(
                f"\n({'c' if router else 'c2' if behind else 'b'}) {scenario}: the robot cut off {2 * cuts} times, its link taken down and brought back up "
                f"({cuts}) and every packet of it dropped then let through ({cuts}), in turn; network namespaces on a bridge ({layout}), "
                f"every manager --lease-ms {LEASE_MS}, the measuring client's session lease {observer_lease}; load average {load()}",
                flush=True,
            )
            run = run_partitions(cuts, args.observer_lease_ms or None, router=router, logs=args.logs, behind=behind)
            samples = run["failover_ms"]["down"] + run["failover_ms"]["silent"]
            results.append({"scenario": scenario, **summary(samples, TARGETS_MS[scenario]),
                            "measured": "from just before the robot's link goes down (or silent) to the first ceiling-camera message on the "
                                        "requested key (subscriber in the station's namespace)",
                            "topology": layout, "links": f"Hosts.shaping = {run['links']!r}; netem {netem}",
                            "observer_lease_ms": args.observer_lease_ms or None, "load_average": load()})  # fmt: skip
            for kind in ("down", "silent"):
                results.append({"scenario": f"rejoin-{short}-{kind}", **summary(run["rejoined_ms"][kind], LEASE_MS + 1000.0),
                                "measured": "from just before the link's return to the station listing the robot among its peers and the "
                                            "robot the station (their models, polled every 50 ms)", "topology": layout})  # fmt: skip
                results.append({"scenario": f"preferred-{short}-{kind}", **summary(run["preferred_ms"][kind], LEASE_MS + 1000.0),
                                "measured": "from just before the link's return to the robot's camera on the key again, less the probation "
                                            "the station gave the robot (its adaptation's cause)", "topology": layout,
                                "probation_s": run["probation_s"][kind]})  # fmt: skip
            false = run["false_alarms"]
            results.append({"scenario": f"false-losses-{short}", "cuts": run["cuts"], "false_losses": len(false), "target": 0,
                            "met": not false, "said": false[:20]})  # fmt: skip
            notes.append(f"{scenario}: {len(false)} false losses in {run['cuts']} cuts (target 0: no manager but the robot declared lost, "
                         "no unit of another declared broken)" + (": " + "; ".join(false[:5]) if false else ""))  # fmt: skip
            slow = [x for x in samples if x > 2 * LEASE_MS]
            notes.append(f"{scenario}: {len(slow)} of {len(samples)} cuts took more than twice the lease ({2 * LEASE_MS} ms) to fail over"
                         + (f": {', '.join(f'{x:.0f}' for x in slow)} ms" if slow else ""))  # fmt: skip
            notes.append(f"{scenario}: the probations the station gave the robot back (the dwell {DWELL_S} s doubled for each loss in the "
                         f"last minute, at most 30 s): {', '.join(f'{x:g}' for x in run['probation_s']['down'] + run['probation_s']['silent'])} s")  # fmt: skip
            notes.append(f"link cuts: links Hosts.shaping = {run['links']!r} (no delay or loss asked; netem {netem})")

    if why is None and args.silent > 0:
        print(f"\n(d) silent-host: {args.silent} clients of a host that drops every packet, --timeout {SILENT_TIMEOUT_S:g}; "
              f"load average {load()}", flush=True)  # fmt: skip
        silent = run_silent_host(args.silent)
        target_ms = (SILENT_TIMEOUT_S + 0.5) * 1000
        results.append({"scenario": "silent-host-report", **summary([x * 1000 for x in silent["report_s"]], target_ms),
                        "measured": "from the Client's construction to get_model's error (reason 'silent'), --timeout 2"})  # fmt: skip
        results.append({"scenario": "silent-host-close", **summary([x * 1000 for x in silent["close_s"]], 100.0),
                        "measured": "Client.close() after that error (its session still dialling the silent host)"})  # fmt: skip
        notes.append(f"silent-host: the command `dyknow model --timeout {SILENT_TIMEOUT_S:g}` took p50 {percentile(silent['command_s'], 50, 2)} s, "
                     f"max {max(silent['command_s']):.2f} s from start to exit, of which Python's start and `import dyknow.cli` alone take "
                     f"p50 {percentile(silent['python_import_s'], 50, 2)} s on this machine")  # fmt: skip

    print(f"\n{'scenario':<24} {'runs':>5} {'p50':>12} {'p99':>12} {'max':>12}   (load average {load()})")
    for row in results:
        if "false_losses" in row:
            print(f"{row['scenario']:<24} {row['cuts']:>5} cuts: {row['false_losses']} false losses   target 0: {'met' if row['met'] else 'NOT met'}")
        else:
            print_row(row)
    for scenario, reason in skipped.items():
        print(f"{scenario:<24} skipped: {reason}")
    for note in notes:
        print(note)
    if args.json:
        data: dict[str, Any] = {"machine": info, "results": results}
        if skipped:
            data["skipped"] = skipped
        write_json(args.json, data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
