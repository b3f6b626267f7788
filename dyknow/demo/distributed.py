"""The paper's scenario across hosts: three manager processes on loopback (``dyknow demo --distributed``).

- ``robot`` runs the robot's camera (it needs the robot's battery at 25 % or more);
- ``field`` runs the ceiling camera;
- ``station`` runs the processing, and a user asks it for ``BallTrack(field)``.

The demo watches the requested key and goes through four phases: the robot's camera feeds the
track; the robot's battery drops (a measurement addressed to the robot's host) and the track
moves to the ceiling camera on another manager; the battery is recharged, but the station keeps
the ceiling camera during its dwell time (no flapping); the field manager is killed (SIGKILL)
and the track moves back to the robot's camera at once. The key never changes. It exits 0 when
every phase happened, and prints each adaptation with its cause and times.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dyknow.client import Client
from dyknow.message import Message
from dyknow.testing.scenario import CAMERA_IDS, SCENARIO_HOSTS
from dyknow.transport import Session, make_config

__all__ = ["run_distributed_demo"]

_CAMERAS = {v: k for k, v in CAMERA_IDS.items()}
_TAG = "BallTrack(field)"


def _ontology() -> str:
    """The ontology shipped beside the specs (a source checkout, or the installed share folder)."""
    for folder in (Path(__file__).resolve().parents[2] / "specs", Path(sys.prefix) / "share" / "dyknow" / "specs"):
        if (folder / "dyknow.ttl").is_file():
            return str(folder / "dyknow.ttl")
    raise FileNotFoundError("dyknow.ttl not found beside the specs; reinstall dyknow (pip install -e .)")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class _Manager:
    """A ``dyknow manager`` child process on loopback."""

    def __init__(self, name: str, ontology: str, *extra: str) -> None:
        self.name = name
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", name, "--specs", str(SCENARIO_HOSTS[name]), "--ontology", ontology,
                "--listen", self.endpoint, "--host", f"{name}-host", "--json", *extra]  # fmt: skip
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith("{") or json.loads(line).get("event") != "ready":
            self.close()
            raise RuntimeError(f"manager {name!r} did not start (exit code {self.proc.poll()})")

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


class _Watch:
    """Which camera feeds the requested key, as a consumer sees it."""

    def __init__(self) -> None:
        self.camera: str | None = None
        self.messages = 0
        self._changed = threading.Condition()

    def __call__(self, msg: Message) -> None:
        camera = _CAMERAS.get(int(msg.payload["camera"]), "?")
        with self._changed:
            self.messages += 1
            if camera != self.camera:
                self.camera = camera
                self._changed.notify_all()

    def wait_for(self, camera: str, timeout_s: float) -> float | None:
        """Seconds until ``camera`` feeds the key (None: not within ``timeout_s``)."""
        start = time.monotonic()
        with self._changed:
            if self._changed.wait_for(lambda: self.camera == camera, timeout_s):
                return time.monotonic() - start
        return None


def run_distributed_demo(*, dwell_s: float = 8.0, as_json: bool = False) -> int:
    """Run the demo (a few seconds); returns 0 when every phase happened, 1 otherwise."""
    say: Callable[[str], None] = (lambda text: None) if as_json else (lambda text: print(text, flush=True))
    ontology = _ontology()
    managers: list[_Manager] = []
    phases: list[dict[str, Any]] = []
    try:
        station = _Manager("station", ontology, "--dwell", str(dwell_s))
        managers.append(station)
        hub = ("--connect", station.endpoint)
        managers += [_Manager("robot", ontology, *hub), _Manager("field", ontology, *hub)]
        say("three managers on loopback: station (processing), robot (robot camera), field (ceiling camera)")
        with Client("station", connect=[station.endpoint], timeout_s=10.0) as client, Session(make_config(connect=[station.endpoint])) as data:
            deadline = time.monotonic() + 20
            while len(client.managers()) < 3 and time.monotonic() < deadline:
                time.sleep(0.1)
            key = _request(client, deadline)
            watch = _Watch()
            with data.declare_subscriber(key, watch):
                say(f"requested {_TAG} from the station: key {key}")

                def phase(name: str, camera: str, timeout_s: float, action: Callable[[], None] | None = None) -> None:
                    started = time.monotonic()
                    if action is not None:
                        action()
                    waited = watch.wait_for(camera, timeout_s)
                    ok = waited is not None
                    phases.append({"phase": name, "camera": watch.camera, "expected": camera, "ok": ok, "seconds": round(time.monotonic() - started, 3)})
                    say(f"  {'ok  ' if ok else 'FAIL'} {name}: the track comes from the {watch.camera} camera (expected {camera})")

                phase("the robot's camera feeds the track", "bottom", 15)
                phase("the robot's battery drops to 10 %", "ceiling", 10, lambda: _battery(data, 0.1))
                _battery(data, 0.9)
                time.sleep(min(2.0, dwell_s / 2))
                phases.append({"phase": "recharged within the dwell time: no flapping", "camera": watch.camera, "expected": "ceiling", "ok": watch.camera == "ceiling"})
                say(f"  {'ok  ' if watch.camera == 'ceiling' else 'FAIL'} recharged within the dwell time: still the {watch.camera} camera (no flapping)")
                field = managers[2]
                phase("the field manager is killed (SIGKILL)", "bottom", 10, lambda: os.kill(field.proc.pid, signal.SIGKILL))
                # The station records an adaptation just before or just after the new
                # configuration's first message, which the watch may see first: wait for both
                # adaptations (the battery, the field's loss), each with its recovery.
                events = client.get_adaptations()
                until = time.monotonic() + 5
                while (len(events) < 2 or any(e["kind"] == "adapted" for e in events)) and time.monotonic() < until:
                    time.sleep(0.05)
                    events = client.get_adaptations()
            say("adaptations on the station (the key never changed):")
            for e in events:
                say(f"  #{e['id']} {e['kind']}: {e['cause']}; adapted in {e['adaptation_ms']} ms, first message after {e['recovery_ms']} ms")
            say(f"{watch.messages} messages on {key}")
        ok = all(p["ok"] for p in phases)
        if as_json:
            print(json.dumps({"key": key, "phases": phases, "adaptations": events, "messages": watch.messages, "ok": ok}))
        return 0 if ok else 1
    finally:
        for manager in reversed(managers):
            manager.close()


def _request(client: Client, deadline: float) -> str:
    while True:  # the station may not know the cameras' managers yet
        try:
            return client.request(_TAG)
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _battery(session: Session, value: float) -> None:
    """The robot's battery, as a sensor on the robot's host publishes it."""
    session.put("dyknow/measurements/battery", json.dumps({"value": value, "host": "robot-host"}))
