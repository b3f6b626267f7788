"""A fleet: what one manager pays for the federation as the fleet grows (issue 40).

For each size N (``--sizes``, default 1, 5, 10, 20, 40; ``--max`` goes on, 1.5 times larger each
time, until a fleet no longer holds) and each topology, N ``dyknow manager`` processes run on
loopback with multicast scouting off (the loopback defaults), named ``m0`` ...:

- ``peers``: as the docs recommend today, ``m0`` listens and every other manager connects to it;
  gossip introduces the rest;
- ``router``: a ``dyknow router`` listens and every manager sits behind it (``--router``): it
  dials the router only and listens on nothing, as a fleet deploys them (docs/howto/router.md).

Each manager has a small library of its own in a temporary folder, and runs two units of it,
spawned through its services: ``src`` (an idle ``dyknow.testing:Source``, tag ``Idle(m<i>)``) and
``relay`` (``transformations.generic:Relay`` bound to ``src``'s output). The newest three (``m<N-3>``
to ``m<N-1>``; fewer when there are fewer other managers) also offer the shared tag ``Shared``
(``transformations.generic:PeriodicSource`` at 200 Hz), so a request of it has few providers;
``m0`` never offers it and makes the requests. Measured, one phase after the other:

- **idle** (no client connected; ``--settle`` seconds, then a ``--window``): per manager the CPU
  time of all its threads (``/proc/PID/task/*/schedstat``) as % of a core; the **traffic it
  received**: the payload bytes its TCP sockets received in the window (``ss -tinp``:
  ``bytes_received`` of each established socket of the process, summed; every message between
  these processes crosses a TCP socket on loopback, and nothing else, such as file reads, counts);
  its **TCP links** (established sockets of the process at the window's end); its memory (PSS,
  ``/proc/PID/smaps_rollup``); the router's own figures; the machine's CPU use in the window
  (``/proc/stat``): at 95 % or more the machine was saturated, and a manager's CPU is then a lower
  bound (it may have wanted more);
- **listing**: ``Client.get_federated_model()`` and ``dyknow managers --connect HUB --manager m0
  --json`` (a process of its own, its start-up included), each with the number of managers it
  listed. There is no paging in the product today: the whole listing is measured;
- **first plan**: ``client.request("Shared")`` end to end on managers that never requested it
  before (``m0`` and the next ones not offering it, up to ``--first``), then ``client.release``;
- **repeated plan**: the same on ``m0``, ``--repeats`` times;
- **newcomer**: one more manager (``new<k>``) offering ``Shared`` and its own ``Fresh(new<k>)``,
  started into the idle fleet; from its ready line (and from its launch) until a request of
  ``Fresh(new<k>)`` on ``m0`` (polled every 20 ms; the newcomer its only producer) returns
  planned. It is stopped before the next one. The time from its ready line can be negative: its
  tokens are up before it prints the line, and on a busy machine the line is read later still;
- **failover on kill**: ``m0`` requests ``Shared``; a subscriber on the request's key; the manager
  whose unit feeds it is killed (SIGKILL) and the time runs from just before the kill to the
  first message on the key from another process (each message says whose clock stamped it). The
  killed manager is started again (same name and library, its units spawned again) before the
  next kill, so the fleet keeps its size.

Every figure is printed per N with its fitted growth exponent (least squares of log figure on
log N), the 1-minute load average of its phase, and the issue's targets with MET / NOT MET. A
figure that could not be measured (a timeout, a failure) prints as such, with the reason.

    flock /tmp/dyknow-heavy.lock python benchmarks/fleet.py          # writes benchmarks/results/fleet.{txt,json}
    python benchmarks/fleet.py --sizes 5,10 --topologies router --json out/fleet.json --txt out/fleet.txt
    python benchmarks/fleet.py --max                                 # and on until a fleet no longer holds
    python benchmarks/fleet.py --smoke --json out/fleet.json         # sizes 1, 2 and 3, short windows
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from collections.abc import Set as AbstractSet
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dyknow import Client, Message
from dyknow.errors import DyKnowError
from dyknow.keys import default_key

from harness import Proc, free_ports, machine, memory_mib, percentile, schedstat_ns, worker_env, write_json

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = "Shared"
PROVIDERS = 3  # managers offering SHARED
RATE_HZ = 200.0  # SHARED's messages per second: the failover's resolution is 5 ms
STEADY = 20  # messages in a row from one process before the stream counts as flowing
# the idle window saturated the machine when its CPU was this busy and the fleet (managers and
# router) itself used at least FLEET_SHARE of it: the fleet may then have wanted more than it got,
# and its CPU figures are lower bounds (another program keeping the machine busy alone does not
# make them so: an idle manager's work waits for a CPU, it is not cut short)
SATURATED_PCT = 95.0
FLEET_SHARE = 0.5
POLL_S = 0.02
CALL_TIMEOUT_S = 60.0  # the measuring client's service timeout: a slow answer is measured, not cut short
START_TIMEOUT_S = 240.0
DISCOVERY_TIMEOUT_S = 120.0
SWITCH_TIMEOUT_S = 30.0
TOPOLOGIES = ("peers", "router")

# the issue's targets, at AT managers against REF managers
AT, REF = 40, 5
CPU_TARGET_PCT = 0.5
GROWTH_TARGET = 1.5
FIRST_PLAN_TARGET_MS = 50.0
NEWCOMER_TARGET_MS = 1000.0
FAILOVER_TARGET_MS = 200.0


# ---------------------------------------------------------------------------- figures


@dataclass
class Figure:
    """One measured figure: its value (None: not measured, ``note`` says why), the 1-minute load
    average of its phase, and whether the value is only a lower bound (``note`` says why)."""

    value: float | None
    load: float
    note: str = ""
    bound: bool = False

    def cell(self, digits: int) -> str:
        """The figure as a table cell: the value, ``>=`` before a lower bound, or why it is missing."""
        if self.value is None:
            return self.note.split(":")[0][:14] or "-"
        text = f"{self.value:,.{digits}f}"
        return f">={text}" if self.bound else text


def load_average() -> float:
    """The machine's 1-minute load average."""
    return round(os.getloadavg()[0], 2)


def machine_cpu() -> tuple[int, int]:
    """The machine's busy and total CPU time so far, in clock ticks (``/proc/stat``)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle, iowait
    return sum(fields) - idle, sum(fields)


_PID = re.compile(r"pid=(\d+),")
_RECEIVED = re.compile(r"bytes_received:(\d+)")


def tcp_sockets(pids: Sequence[int]) -> dict[int, dict[str, int]]:
    """Each process's established TCP sockets, ``"local peer"`` -> payload bytes received so far
    (``ss -tinpH state established``: the kernel's ``tcp_info``)."""
    out = subprocess.run(["ss", "-tinpH", "state", "established"], capture_output=True, text=True, check=True, timeout=30).stdout
    sockets: dict[int, dict[str, int]] = {pid: {} for pid in pids}
    owners: list[tuple[int, str]] = []
    for line in out.splitlines():
        if not line.strip():
            continue
        if line[0].isspace():  # the socket's details, under its line
            found = _RECEIVED.search(line)
            for pid, key in owners:
                sockets[pid][key] = int(found.group(1)) if found else 0
            continue
        fields = line.split()  # Recv-Q Send-Q Local Peer Process
        key = f"{fields[2]} {fields[3]}" if len(fields) > 3 else line
        owners = [(pid, key) for pid in {int(p) for p in _PID.findall(line)} if pid in sockets]
        for pid, k in owners:
            sockets[pid].setdefault(k, 0)
    return sockets


def stats(samples: Sequence[float]) -> dict[str, Any]:
    """Count, p50, p99 and max of ``samples`` (ms), and the samples."""
    return {"count": len(samples), "p50_ms": percentile(samples, 50, 1), "p99_ms": percentile(samples, 99, 1),
            "max_ms": round(max(samples), 1) if samples else None, "samples_ms": [round(s, 1) for s in samples]}  # fmt: skip


def growth(sizes: Sequence[int], figures: Sequence[Figure]) -> float | None:
    """The exponent b of figure ~ a N^b, least squares on logs over the fleets of two managers or
    more (a lone manager has no one to federate with: its traffic is nil) measured exactly (no
    lower bounds) with a positive value; None with fewer than two."""
    points = [(n, f.value) for n, f in zip(sizes, figures, strict=True) if n >= 2 and f.value is not None and f.value > 0 and not f.bound]
    if len({n for n, _ in points}) < 2:
        return None
    slope = np.polyfit(np.log([n for n, _ in points]), np.log([v for _, v in points]), 1)[0]
    return round(float(slope), 2)


# ---------------------------------------------------------------------------- the fleet


def library_xml(name: str, *, shared: bool, fresh: bool = False) -> str:
    """Manager ``name``'s library: ``src-<name>`` and ``relay-<name>``; with ``shared``, ``shared-<name>``
    (tag ``Shared``); with ``fresh``, ``fresh-<name>`` (tag ``Fresh(<name>)``, offered by it alone)."""

    def periodic(label: str, tag: str) -> str:
        return f"""  <transformation>
    <label>{label}</label>
    <source>transformations.generic:PeriodicSource</source>
    <params><param name="rate_hz" type="float">{RATE_HZ:g}</param></params>
    <ports><port type="out">out</port></ports>
    <tags><tag port="out">{tag}</tag></tags>
  </transformation>"""

    specs = [
        f"""  <transformation>
    <label>src-{name}</label>
    <source>dyknow.testing:Source</source>
    <ports><port type="out">out</port></ports>
    <tags><tag port="out">Idle({name})</tag></tags>
  </transformation>""",
        f"""  <transformation>
    <label>relay-{name}</label>
    <source>transformations.generic:Relay</source>
    <ports><port type="in">in</port><port type="out">out</port></ports>
    <tags><tag port="in">Idle({name})</tag><tag port="out">Relayed({name})</tag></tags>
  </transformation>""",
    ]
    if shared:
        specs.append(periodic(f"shared-{name}", SHARED))
    if fresh:
        specs.append(periodic(f"fresh-{name}", f"Fresh({name})"))
    return '<?xml version="1.0" encoding="UTF-8"?>\n<transformations>\n' + "\n".join(specs) + "\n</transformations>\n"


class Fleet:
    """N ``dyknow manager`` processes (and a ``dyknow router`` in the router topology) on loopback.

    A context manager: leaving it stops every process (SIGTERM, then SIGKILL after 15 s)."""

    def __init__(self, topology: str, n: int, folder: Path) -> None:
        self.topology, self.n, self.folder = topology, n, folder
        self.names = [f"m{i}" for i in range(n)]
        self.providers = self.names[max(1, n - PROVIDERS) :]
        self.procs: dict[str, Proc] = {}
        self.router: Proc | None = None
        self.hub = ""

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def argv(self, name: str, *, shared: bool, fresh: bool = False) -> list[str]:
        """``dyknow manager`` for ``name``, its library written into the folder."""
        path = self.folder / f"{name}.xml"
        path.write_text(library_xml(name, shared=shared, fresh=fresh))
        if self.topology == "router":  # behind the router: it alone is dialled, nothing listens
            links = ["--router", self.hub]
        else:
            links = ["--listen", f"tcp/127.0.0.1:{free_ports(1)[0]}", *([] if name == "m0" else ["--connect", self.hub])]
        return [sys.executable, "-m", "dyknow.cli", "manager", "--name", name, "--specs", str(path), *links, "--json"]

    def launch(self, name: str, *, fresh: bool = False) -> Proc:
        """Start manager ``name`` (not waiting for its ready line)."""
        proc = Proc(self.argv(name, shared=name in self.providers or fresh, fresh=fresh), env=worker_env())
        self.procs[name] = proc
        return proc

    def start(self) -> float:
        """Start the router or ``m0``, then every other manager at once; seconds from the first launch to the last ready line."""
        started = time.monotonic()
        if self.topology == "router":
            port = free_ports(1)[0]
            self.hub = f"tcp/127.0.0.1:{port}"
            self.router = Proc([sys.executable, "-m", "dyknow.cli", "router", "--listen", self.hub, "--json"], env=worker_env())
            self.router.next_json(START_TIMEOUT_S, event="ready")
        else:
            self.hub = self.launch("m0").next_json(START_TIMEOUT_S, event="ready")["endpoints"][0]
        rest = [self.launch(name) for name in self.names if name not in self.procs]
        deadline = time.monotonic() + START_TIMEOUT_S
        for proc in rest:
            proc.next_json(max(0.0, deadline - time.monotonic()), event="ready")
        return time.monotonic() - started

    def pids(self) -> dict[str, int]:
        """Each manager's process id."""
        return {name: self.procs[name].proc.pid for name in self.names}

    def stop(self, name: str) -> None:
        """Stop manager ``name`` cleanly (SIGTERM; SIGKILL after 15 s) and forget it."""
        proc = self.procs.pop(name)
        proc.proc.terminate()
        try:
            proc.proc.wait(15)
        except subprocess.TimeoutExpired:
            pass
        proc.close()

    def close(self) -> None:
        """Stop every process: SIGTERM to all, then SIGKILL to those still running after 15 s."""
        procs = [*self.procs.values(), *([self.router] if self.router else [])]
        for proc in procs:
            if proc.proc.poll() is None:
                proc.proc.terminate()
        deadline = time.monotonic() + 15
        for proc in procs:
            try:
                proc.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
            proc.close()
        self.procs.clear()
        self.router = None


def client(fleet: Fleet, manager: str = "m0") -> Client:
    """A client of ``manager`` connected where every manager connects (``m0`` or the router)."""
    return Client(manager, connect=[fleet.hub], timeout_s=CALL_TIMEOUT_S)


def wait_listed(on: Client, names: AbstractSet[str], gone: AbstractSet[str] = frozenset(), timeout_s: float = DISCOVERY_TIMEOUT_S) -> float:
    """Seconds until every manager of ``names`` is reachable (its liveliness token) and none of ``gone``; TimeoutError after ``timeout_s``."""
    started = time.monotonic()
    while True:
        seen = set(on.manager_names(timeout_s=2.0))
        if names <= seen and not gone & seen:
            return time.monotonic() - started
        if time.monotonic() - started > timeout_s:
            raise TimeoutError(f"after {timeout_s:g} s: not reachable {sorted(names - seen)[:5]}, still there {sorted(gone & seen)[:5]}")
        time.sleep(0.2)


def spawn_units(on: Client, name: str) -> None:
    """Start manager ``name``'s ``src`` and ``relay`` (bound to ``src``'s output) through its services."""
    with Client(name, session=on.session, timeout_s=CALL_TIMEOUT_S) as there:
        there.spawn(f"src-{name}", "src")
        there.spawn(f"relay-{name}", "relay", bindings={"in": default_key(name, "src", "out")})


@contextmanager
def phase(results: dict[str, Any], name: str, out: Callable[[str], None]) -> Iterator[None]:
    """Run a phase; an exception in it becomes ``results[name]["error"]`` (its figures then print as not measured)."""
    try:
        yield
    except (DyKnowError, TimeoutError, RuntimeError, OSError, subprocess.SubprocessError) as exc:
        reason = f"{type(exc).__name__}: {str(exc).splitlines()[0][:300] if str(exc) else ''}"
        results.setdefault(name, {})["error"] = reason
        out(f"  {name}: not measured: {reason}")


# ---------------------------------------------------------------------------- the phases


def measure_idle(fleet: Fleet, window_s: float) -> dict[str, Any]:
    """Each manager's (and the router's) CPU, traffic received, links and PSS over ``window_s`` of idling."""
    named = fleet.pids()
    if fleet.router is not None:
        named["router"] = fleet.router.proc.pid
    pids = list(named.values())
    busy0, total0 = machine_cpu()
    sockets0 = tcp_sockets(pids)
    cpu0, t0 = {pid: schedstat_ns(pid) for pid in pids}, time.monotonic()
    time.sleep(window_s)  # the window: nothing is asked of the fleet
    cpu1, t1 = {pid: schedstat_ns(pid) for pid in pids}, time.monotonic()
    sockets1 = tcp_sockets(pids)
    busy1, total1 = machine_cpu()
    elapsed = t1 - t0
    rows: dict[str, dict[str, float]] = {}
    closed = 0
    for name, pid in named.items():
        before, after = sockets0[pid], sockets1[pid]
        closed += len(set(before) - set(after))
        received = sum(b - before.get(k, 0) for k, b in after.items())
        rows[name] = {
            "cpu_pct": 100 * (cpu1[pid][0] - cpu0[pid][0]) / 1e9 / elapsed,
            "wait_pct": 100 * (cpu1[pid][1] - cpu0[pid][1]) / 1e9 / elapsed,
            "received_bps": received / elapsed,
            "links": len(after),
            "pss_mib": memory_mib(pid)["pss"],
        }
    machine_pct = 100 * (busy1 - busy0) / max(1, total1 - total0)
    fleet_pct = sum(r["cpu_pct"] for r in rows.values())
    capacity_pct = 100 * (os.cpu_count() or 1)
    saturated = machine_pct >= SATURATED_PCT and fleet_pct >= FLEET_SHARE * capacity_pct
    return {"window_s": round(elapsed, 2), "machine_cpu_pct": round(machine_pct, 1), "saturated": saturated,
            "sockets_closed_in_window": closed, "load": load_average(), "per_process": rows}  # fmt: skip


def idle_figures(idle: dict[str, Any], names: Sequence[str]) -> dict[str, Figure]:
    """The idle phase's figures: means over the managers ``names`` (and their max), their sum, the router's."""
    rows = [idle["per_process"][name] for name in names]
    load, saturated = idle["load"], idle["saturated"]
    why = f"lower bound: the fleet saturated the machine ({idle['machine_cpu_pct']:.0f} % of its CPU busy, at least {FLEET_SHARE:.0%} of it the fleet's)"

    def mean(field: str) -> float:
        return float(np.mean([r[field] for r in rows]))

    def top(field: str) -> float:
        return float(max(r[field] for r in rows))

    out = {
        "cpu_per_manager": Figure(round(mean("cpu_pct"), 3), load, why if saturated else "", saturated),
        "cpu_per_manager_max": Figure(round(top("cpu_pct"), 3), load, why if saturated else "", saturated),
        "cpu_fleet": Figure(round(sum(r["cpu_pct"] for r in rows), 2), load, why if saturated else "", saturated),
        "wait_per_manager": Figure(round(mean("wait_pct"), 3), load),
        "machine_cpu": Figure(idle["machine_cpu_pct"], load),
        "traffic_per_manager": Figure(round(mean("received_bps"), 1), load),
        "traffic_per_manager_max": Figure(round(top("received_bps"), 1), load),
        "links_per_manager": Figure(round(mean("links"), 2), load),
        "links_per_manager_max": Figure(top("links"), load),
        "pss_per_manager": Figure(round(mean("pss_mib"), 1), load),
    }
    router = idle["per_process"].get("router")
    for key, field, digits in (("router_cpu", "cpu_pct", 3), ("router_traffic", "received_bps", 1), ("router_links", "links", 0)):
        out[key] = Figure(round(router[field], digits), load, why if saturated and key == "router_cpu" else "",
                          saturated and key == "router_cpu") if router else Figure(None, load, "n/a: no router")  # fmt: skip
    return out


def measure_listing(fleet: Fleet, on: Client, repeats: int, runs: int) -> dict[str, Any]:
    """``Client.get_federated_model()`` ``repeats`` times and ``dyknow managers`` ``runs`` times: ms and how many managers each listed."""
    model_ms, model_listed = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        federated = on.get_federated_model()
        model_ms.append((time.perf_counter() - started) * 1000)
        model_listed.append(len(federated["managers"]))
    model_load = load_average()
    cmd_ms, cmd_listed, exits = [], [], []
    argv = [sys.executable, "-m", "dyknow.cli", "managers", "--connect", fleet.hub, "--manager", "m0", "--json"]
    for _ in range(runs):
        started = time.perf_counter()
        done = subprocess.run(argv, capture_output=True, text=True, timeout=600, env=worker_env())
        cmd_ms.append((time.perf_counter() - started) * 1000)
        exits.append(done.returncode)
        try:
            listed = json.loads(done.stdout)
        except json.JSONDecodeError:
            listed = None
        managers = listed.get("managers", []) if isinstance(listed, dict) else listed if isinstance(listed, list) else []
        cmd_listed.append(sum(1 for m in managers if isinstance(m, dict) and m.get("state", "reachable") != "lost"))
    return {"federated_model": {**stats(model_ms), "listed": model_listed, "load": model_load},
            "managers_cmd": {**stats(cmd_ms), "listed": cmd_listed, "exit_codes": exits, "load": load_average()}}  # fmt: skip


def measure_plans(fleet: Fleet, on: Client, first: int, repeats: int) -> dict[str, Any]:
    """First plans of ``Shared`` on managers that never requested it, then ``repeats`` on ``m0``: ms per request and release."""
    requesters = [m for m in fleet.names if m not in fleet.providers][:first]
    first_ms, first_release, where = [], [], []
    for name in requesters:
        with Client(name, session=on.session, timeout_s=CALL_TIMEOUT_S) as there:
            started = time.perf_counter()
            key = there.request(SHARED)
            first_ms.append((time.perf_counter() - started) * 1000)
            where.append(provider_of(there, key))
            started = time.perf_counter()
            there.release(key)
            first_release.append((time.perf_counter() - started) * 1000)
    first_load = load_average()
    again_ms, again_release = [], []
    for _ in range(repeats):
        time.sleep(0.3)  # the managers' summaries catch up with the last release
        started = time.perf_counter()
        key = on.request(SHARED)
        again_ms.append((time.perf_counter() - started) * 1000)
        started = time.perf_counter()
        on.release(key)
        again_release.append((time.perf_counter() - started) * 1000)
    return {"first": {**stats(first_ms), "requesters": requesters, "providers_used": where, "release": stats(first_release), "load": first_load},
            "repeated": {**stats(again_ms), "release": stats(again_release), "load": load_average()}}  # fmt: skip


def provider_of(on: Client, key: str) -> str:
    """The manager whose unit feeds request ``key`` of ``on``'s manager (its model's ``unit@manager``)."""
    for request in on.get_model()["requests"]:
        if request["key"] == key:
            remote = [u.rsplit("@", 1)[1] for u in request["units"] if "@" in u]
            return remote[0] if remote else on.manager
    raise RuntimeError(f"request {key} is not in the model of {on.manager}")


def measure_newcomers(fleet: Fleet, on: Client, count: int) -> dict[str, Any]:
    """Per newcomer: ms from its ready line (and from its launch) until a request of its own tag on ``m0`` is planned."""
    from_ready, from_launch = [], []
    for k in range(count):
        name = f"new{k}"
        ready: list[float] = []
        launched = time.monotonic()
        proc = fleet.launch(name, fresh=True)

        def wait_ready(p: Proc = proc, box: list[float] = ready) -> None:
            try:
                p.next_json(START_TIMEOUT_S, event="ready")
                box.append(time.monotonic())
            except RuntimeError:
                pass

        waiter = threading.Thread(target=wait_ready, daemon=True)
        waiter.start()
        try:
            deadline = launched + START_TIMEOUT_S
            while True:
                try:
                    key = on.request(f"Fresh({name})")
                    planned = time.monotonic()
                    break
                except DyKnowError:
                    if time.monotonic() > deadline:
                        raise TimeoutError(f"{name}: a request of Fresh({name}) on m0 not planned within {START_TIMEOUT_S:g} s of its launch") from None
                    time.sleep(POLL_S)
            on.release(key)
            waiter.join(5)
            if not ready:
                raise RuntimeError(f"{name} planned but its ready line never read: {proc.error_tail()[-300:]}")
            from_ready.append((planned - ready[0]) * 1000)
            from_launch.append((planned - launched) * 1000)
        finally:
            fleet.stop(name)
        wait_listed(on, set(), gone={name})
    return {"from_ready": stats(from_ready), "from_launch": stats(from_launch), "load": load_average()}


class Watch:
    """Which process feeds a key: per message the process's clock id (``origin_clock``) and when it arrived."""

    def __init__(self) -> None:
        self.current: int | None = None
        self.run = 0
        self.changes: list[tuple[int, int]] = []  # (time.time_ns(), origin clock)
        self._cond = threading.Condition()

    def on_message(self, msg: Message) -> None:
        """The subscriber's callback."""
        now = time.time_ns()
        with self._cond:
            if msg.origin_clock != self.current:
                self.current, self.run = msg.origin_clock, 0
                self.changes.append((now, msg.origin_clock))
            self.run += 1
            self._cond.notify_all()

    def steady(self, timeout_s: float) -> int:
        """Wait until one process fed ``STEADY`` messages in a row; its clock id. TimeoutError after ``timeout_s``."""
        with self._cond:
            if not self._cond.wait_for(lambda: self.current is not None and self.run >= STEADY, timeout_s):
                raise TimeoutError(f"no steady stream on the key within {timeout_s:g} s")
            assert self.current is not None
            return self.current

    def other(self, clock: int, after_ns: int, timeout_s: float) -> int:
        """The arrival time of the first message from another process than ``clock`` at or after ``after_ns``."""

        def found() -> int | None:
            return next((t for t, c in self.changes if c != clock and t >= after_ns), None)

        with self._cond:
            if not self._cond.wait_for(lambda: found() is not None, timeout_s):
                raise TimeoutError(f"the stream not back on the key from another provider within {timeout_s:g} s of the kill")
            return found() or 0


def measure_failover(fleet: Fleet, on: Client, kills: int, out: Callable[[str], None]) -> dict[str, Any]:
    """``kills`` times: SIGKILL of the provider of ``m0``'s request of ``Shared``; ms until the next message on its key from another."""
    samples: list[float] = []
    restarts: list[float] = []
    killed: list[str] = []
    result: dict[str, Any] = {}
    watch = Watch()
    key = on.request(SHARED)
    try:
        with on.declare_subscriber(key, watch.on_message):
            for i in range(kills):
                victim = provider_of(on, key)
                clock = watch.steady(SWITCH_TIMEOUT_S)
                if provider_of(on, key) != victim:  # it moved meanwhile: measure the next kill from a settled stream
                    victim = provider_of(on, key)
                    clock = watch.steady(SWITCH_TIMEOUT_S)
                if victim not in fleet.providers:
                    raise RuntimeError(f"the request runs on {victim}, not on a provider of {SHARED} ({fleet.providers})")
                time.sleep(0.2)
                killed_ns = time.time_ns()
                os.kill(fleet.procs[victim].proc.pid, signal.SIGKILL)
                try:
                    seen_ns = watch.other(clock, killed_ns, SWITCH_TIMEOUT_S)
                except TimeoutError as exc:
                    result["error"] = f"kill {i + 1} of {victim}: {exc}"
                    break
                samples.append((seen_ns - killed_ns) / 1e6)
                killed.append(victim)
                out(f"    kill {i + 1}/{kills} of {victim}: the stream back on the key after {samples[-1]:.1f} ms")
                fleet.procs.pop(victim).close()
                started = time.monotonic()
                fleet.launch(victim).next_json(START_TIMEOUT_S, event="ready")
                wait_listed(on, {victim})
                spawn_units(on, victim)
                restarts.append(time.monotonic() - started)
                time.sleep(1.0)  # the restarted manager's summary reaches the others
    finally:
        on.release(key)
    return {**stats(samples), **result, "killed": killed, "restart_s_p50": percentile(restarts, 50, 2), "load": load_average()}


# ---------------------------------------------------------------------------- one fleet


def run_fleet(topology: str, n: int, args: argparse.Namespace, out: Callable[[str], None]) -> dict[str, Any]:
    """Start a fleet of ``n`` managers in ``topology``, run every phase, stop it; its results."""
    results: dict[str, Any] = {"topology": topology, "managers": n, "load_at_start": load_average()}
    try:
        _run_phases(topology, n, args, out, results)
    finally:
        results["load_at_end"] = load_average()
    return results


def _run_phases(topology: str, n: int, args: argparse.Namespace, out: Callable[[str], None], results: dict[str, Any]) -> None:
    with tempfile.TemporaryDirectory(prefix="dyknow-fleet-") as tmp, Fleet(topology, n, Path(tmp)) as fleet:
        results["providers"] = fleet.providers
        out(f"\n{topology}, {n} managers (providers of {SHARED}: {', '.join(fleet.providers) or 'none'}); load average {load_average():.2f}")
        with phase(results, "start", out):
            results["start"] = {"startup_s": round(fleet.start(), 2)}
            with client(fleet) as on:
                results["start"]["discovered_s"] = round(wait_listed(on, set(fleet.names)), 2)
                for name in fleet.names:
                    spawn_units(on, name)
            out(f"  started in {results['start']['startup_s']} s, all {n} reachable {results['start']['discovered_s']} s later; units spawned")
        if "error" in results.get("start", {}):
            return
        time.sleep(args.settle)
        with phase(results, "idle", out):
            results["idle"] = measure_idle(fleet, args.window)
            idle = results["idle"]
            rows = [idle["per_process"][m] for m in fleet.names]
            out(f"  idle {idle['window_s']} s: CPU per manager mean {np.mean([r['cpu_pct'] for r in rows]):.3f} % of a core, "
                f"traffic received {np.mean([r['received_bps'] for r in rows]):.0f} B/s, links {np.mean([r['links'] for r in rows]):.1f}, "
                f"PSS {np.mean([r['pss_mib'] for r in rows]):.1f} MiB; machine CPU {idle['machine_cpu_pct']} %; load average {idle['load']}")  # fmt: skip
        with client(fleet) as on:
            with phase(results, "listing", out):
                results["listing"] = measure_listing(fleet, on, args.listings, args.cmd_runs)
                lst = results["listing"]
                out(f"  get_federated_model p50 {lst['federated_model']['p50_ms']} ms (listed {lst['federated_model']['listed']}); "
                    f"dyknow managers p50 {lst['managers_cmd']['p50_ms']} ms (listed {lst['managers_cmd']['listed']}, exit {lst['managers_cmd']['exit_codes']})")  # fmt: skip
            if fleet.providers:
                with phase(results, "plans", out):
                    results["plans"] = measure_plans(fleet, on, args.first, args.repeats)
                    p = results["plans"]
                    out(f"  first plan p50 {p['first']['p50_ms']} ms over {p['first']['count']} ({p['first']['providers_used']}); "
                        f"repeated p50 {p['repeated']['p50_ms']} ms over {p['repeated']['count']}")  # fmt: skip
            with phase(results, "newcomer", out):
                results["newcomer"] = measure_newcomers(fleet, on, args.newcomers)
                nc = results["newcomer"]
                out(f"  newcomer plannable p50 {nc['from_ready']['p50_ms']} ms after its ready line ({nc['from_launch']['p50_ms']} ms after its launch)")
            if len(fleet.providers) >= 2:
                with phase(results, "failover", out):
                    results["failover"] = measure_failover(fleet, on, args.kills, out)
                    fo = results["failover"]
                    out(f"  failover on kill p50 {fo['p50_ms']} ms, p99 {fo['p99_ms']} ms over {fo['count']} kills")


def held(result: dict[str, Any]) -> bool:
    """Whether a fleet held: it started, every manager was reachable, the first plans and the listing worked."""
    listing = result.get("listing", {})
    return ("error" not in result.get("start", {"error": "not run"}) and "error" not in result.get("plans", {})
            and "error" not in listing and all(k == result["managers"] for k in listing.get("federated_model", {}).get("listed", [0])))  # fmt: skip


# ---------------------------------------------------------------------------- the report


def figures(result: dict[str, Any]) -> dict[str, Figure]:
    """Every figure of one fleet's results, by row key (missing ones say why)."""
    n = result["managers"]
    out: dict[str, Figure] = {}

    def absent(section: str, needs: str | None = None) -> Figure:
        error = result.get("start", {}).get("error") or result.get(section, {}).get("error")
        load = result.get(section, {}).get("load", result["load_at_end"])
        if error:
            return Figure(None, load, ("timeout: " if "Timeout" in error or "within" in error else "failed: ") + error)
        return Figure(None, load, f"n/a: {needs}" if needs else "n/a")

    idle = result.get("idle")
    if idle and "per_process" in idle:
        out.update(idle_figures(idle, [f"m{i}" for i in range(n)]))
    for key in ("cpu_per_manager", "cpu_per_manager_max", "cpu_fleet", "wait_per_manager", "machine_cpu", "traffic_per_manager", "traffic_per_manager_max",
                "links_per_manager", "links_per_manager_max", "pss_per_manager", "router_cpu", "router_traffic", "router_links"):  # fmt: skip
        out.setdefault(key, absent("idle"))

    listing = result.get("listing", {})
    for key, part in (("federated_model", "federated_model"), ("managers_cmd", "managers_cmd")):
        if part in listing:
            row = listing[part]
            out[f"{key}_ms"] = Figure(row["p50_ms"], row["load"])
            out[f"{key}_listed"] = Figure(float(min(row["listed"])), row["load"], f"of {n}")
        else:
            out[f"{key}_ms"] = out[f"{key}_listed"] = absent("listing")

    plans = result.get("plans", {})
    for key, part in (("first_plan_ms", "first"), ("repeated_plan_ms", "repeated")):
        out[key] = Figure(plans[part]["p50_ms"], plans[part]["load"]) if part in plans else absent("plans", "needs a provider other than m0")

    newcomer = result.get("newcomer", {})
    if "from_ready" in newcomer:
        out["newcomer_ms"] = Figure(newcomer["from_ready"]["p50_ms"], newcomer["load"])
        out["newcomer_max_ms"] = Figure(newcomer["from_ready"]["max_ms"], newcomer["load"])
        out["newcomer_launch_ms"] = Figure(newcomer["from_launch"]["p50_ms"], newcomer["load"])
    else:
        out["newcomer_ms"] = out["newcomer_max_ms"] = out["newcomer_launch_ms"] = absent("newcomer")

    failover = result.get("failover", {})
    if failover.get("count") and "error" not in failover:
        out["failover_p50_ms"] = Figure(failover["p50_ms"], failover["load"])
        out["failover_p99_ms"] = Figure(failover["p99_ms"], failover["load"], f"over {failover['count']} kills")
    else:  # a kill whose stream never came back leaves its p99 unknown: no figure from the other kills
        out["failover_p50_ms"] = out["failover_p99_ms"] = absent("failover", "needs two providers other than m0")
    return out


# (row key, label, digits, phase)
ROWS = [
    ("cpu_per_manager", "idle CPU per manager (% of a core, mean)", 3, "idle"),
    ("cpu_per_manager_max", "  the busiest manager", 3, "idle"),
    ("cpu_fleet", "idle CPU of all the managers (% of a core)", 2, "idle"),
    ("wait_per_manager", "waiting for a CPU per manager (% of the time, mean)", 3, "idle"),
    ("machine_cpu", "machine CPU busy in the window (% of all cores)", 0, "idle"),
    ("traffic_per_manager", "idle traffic received per manager (B/s, mean)", 0, "idle"),
    ("traffic_per_manager_max", "  the manager receiving most", 0, "idle"),
    ("links_per_manager", "TCP links per manager (mean)", 2, "idle"),
    ("links_per_manager_max", "  the manager with most", 0, "idle"),
    ("pss_per_manager", "memory per manager (PSS MiB, mean)", 1, "idle"),
    ("router_cpu", "router: idle CPU (% of a core)", 3, "idle"),
    ("router_traffic", "router: idle traffic received (B/s)", 0, "idle"),
    ("router_links", "router: TCP links", 0, "idle"),
    ("federated_model_ms", "Client.get_federated_model() p50 (ms)", 1, "listing"),
    ("federated_model_listed", "  managers in it (fewest)", 0, "listing"),
    ("managers_cmd_ms", "dyknow managers p50 (ms, its start-up included)", 0, "listing"),
    ("managers_cmd_listed", "  managers it listed (fewest)", 0, "listing"),
    ("first_plan_ms", "first plan of Shared p50 (ms, request end to end)", 1, "plans"),
    ("repeated_plan_ms", "repeated plan of Shared p50 (ms)", 1, "plans"),
    ("newcomer_ms", "newcomer plannable p50 (ms after its ready line)", 0, "newcomer"),
    ("newcomer_max_ms", "  the slowest newcomer", 0, "newcomer"),
    ("newcomer_launch_ms", "  p50 from its launch (its start-up included)", 0, "newcomer"),
    ("failover_p50_ms", "failover on kill p50 (ms)", 1, "failover"),
    ("failover_p99_ms", "failover on kill p99 (ms)", 1, "failover"),
]
NO_GROWTH = {"wait_per_manager", "machine_cpu", "federated_model_listed", "managers_cmd_listed"}  # no growth exponent: not a cost
PHASE_LOAD = {"idle": "idle window", "listing": "listing", "plans": "plans", "newcomer": "newcomers", "failover": "kills"}


def verdicts(topology: str, by_n: dict[int, dict[str, Figure]]) -> list[dict[str, Any]]:
    """The issue's targets for one topology, each at ``AT`` managers (and ``REF``), or at the
    largest (and smallest) size measured when those were not: ``met`` is None when its figure is missing."""
    sizes = sorted(by_n)
    at = AT if AT in by_n else sizes[-1]
    ref = REF if REF in by_n else sizes[0]
    checks: list[dict[str, Any]] = []

    def check(row: str, target: str, test: Callable[[float], bool], versus: str | None = None) -> None:
        fig = by_n[at][row]
        base = by_n[ref][versus] if versus else None
        value, ok = fig.value, None
        if value is not None and (base is None or base.value is not None):
            ok = test(value)
            # a lower bound settles only a NOT MET of its own (its true value is larger still); a
            # reference that is one makes a ratio unsure either way
            if (fig.bound and ok) or (base is not None and base.bound):
                ok = None
        checks.append({"topology": topology, "row": row, "target": target, "at": at, "ref": ref if versus else None,
                       "value": value, "reference": base.value if base else None, "bound": fig.bound,
                       "note": fig.note, "load": fig.load, "met": ok})  # fmt: skip

    def within(row: str) -> Callable[[float], bool]:
        base = by_n[ref][row].value
        return lambda v: base is not None and v <= GROWTH_TARGET * base

    cpu_ok = within("cpu_per_manager")
    check("cpu_per_manager", f"at {at} <= {GROWTH_TARGET:g}x its value at {ref} and < {CPU_TARGET_PCT:g} % of a core",
          lambda v: cpu_ok(v) and v < CPU_TARGET_PCT, "cpu_per_manager")  # fmt: skip
    check("traffic_per_manager", f"at {at} <= {GROWTH_TARGET:g}x its value at {ref}", within("traffic_per_manager"), "traffic_per_manager")
    if topology == "router":
        check("links_per_manager_max", f"at {at}: 1 (the router; idle, no data exchanged) for every manager", lambda v: v <= 1)
    check("first_plan_ms", f"p50 < {FIRST_PLAN_TARGET_MS:g} ms at {at}", lambda v: v < FIRST_PLAN_TARGET_MS)
    check("newcomer_max_ms", f"every newcomer within {NEWCOMER_TARGET_MS / 1000:g} s of its ready line at {at}", lambda v: v <= NEWCOMER_TARGET_MS)
    check("failover_p99_ms", f"p99 < {FAILOVER_TARGET_MS:g} ms at {at}", lambda v: v < FAILOVER_TARGET_MS)
    return checks


def verdict_text(check: dict[str, Any]) -> str:
    """MET, NOT MET, or UNSETTLED (lower bounds) or NOT MEASURED with the reason."""
    if check["met"] is None and check["value"] is not None:
        return "UNSETTLED (a lower bound: the fleet saturated the machine)"
    if check["met"] is None:
        return f"NOT MEASURED ({check['note'] or 'its figure is missing'})"
    return "MET" if check["met"] else "NOT MET"


def report(runs: list[dict[str, Any]], info: dict[str, Any], args: argparse.Namespace, argv: Sequence[str]) -> tuple[list[str], list[dict[str, Any]]]:
    """The report's lines (a table per topology, then the targets) and the target checks."""
    lines = [
        f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}, dyknow {info['dyknow']}",
        f"command: python benchmarks/fleet.py {' '.join(argv)}".rstrip(),
        f"each size: settle {args.settle:g} s, idle window {args.window:g} s; {args.listings} federated models, {args.cmd_runs} dyknow managers; "
        f"first plans on up to {args.first} managers, {args.repeats} repeated; {args.newcomers} newcomers; {args.kills} kills",
        f"cells: the figure; >=x a lower bound (the fleet saturated the machine: {SATURATED_PCT:g} % of its CPU busy, {FLEET_SHARE:.0%} of it or more "
        "the fleet's, which may have wanted more than it got); "
        "a word (timeout, failed, n/a) where nothing was measured, the reason below the table",
        "growth: b of figure ~ N^b, least squares on logs over the sizes of 2 or more measured exactly (not the lower bounds)",
    ]
    checks: list[dict[str, Any]] = []
    for topology in dict.fromkeys(r["topology"] for r in runs):
        mine = sorted((r for r in runs if r["topology"] == topology), key=lambda r: r["managers"])
        sizes = [r["managers"] for r in mine]
        by_n = {r["managers"]: figures(r) for r in mine}
        mine_checks = verdicts(topology, by_n)
        checks += mine_checks
        targets = {c["row"]: c for c in mine_checks}
        width = 12
        lines.append("")
        lines.append(f"{topology}: " + ("m0 listens, every other manager connects to it (gossip does the rest)" if topology == "peers"
                                         else "a dyknow router listens, every manager sits behind it (--router)"))  # fmt: skip
        lines.append(f"{'figure':<52}" + "".join(f"{'N=' + str(n):>{width}}" for n in sizes) + f"{'growth':>9}   target: verdict")
        current_phase = None
        reasons: dict[str, str] = {}
        for key, label, digits, section in ROWS:
            if topology == "peers" and key.startswith("router_"):
                continue
            if section != current_phase:
                current_phase = section
                loads = [by_n[n][key].load for n in sizes]
                lines.append(f"{'  (load average, 1 min: ' + PHASE_LOAD[section] + ')':<52}" + "".join(f"{x:>{width}.2f}" for x in loads))
            row = [by_n[n][key] for n in sizes]
            exponent = None if key in NO_GROWTH else growth(sizes, row)
            cells = "".join(f"{f.cell(digits):>{width}}" for f in row)
            target = targets.get(key)
            tail = f"   {target['target']}: {verdict_text(target)}" if target else ""
            lines.append(f"{label:<52}{cells}{'N^' + format(exponent, '.2f') if exponent is not None else '-':>9}{tail}")
            for n, f in zip(sizes, row, strict=True):
                if f.value is None and not f.note.startswith("n/a"):
                    reasons.setdefault(f"N={n} {section}", f.note)
        for where, why in reasons.items():
            lines.append(f"  not measured, {where}: {why}")
    lines.append("")
    lines.append(f"targets (issue 40), at {AT} managers against {REF} (else at the largest and the smallest size measured):")
    for c in checks:
        value = "missing" if c["value"] is None else (">=" if c["bound"] else "") + f"{c['value']:g}"
        versus = f" (at {c['ref']}: {c['reference']:g})" if c["ref"] is not None and c["reference"] is not None else ""
        lines.append(f"  {c['topology']:<7} {c['row']:<22} {value}{versus}; target {c['target']}: {verdict_text(c)}  (load average {c['load']:.2f})")
    return lines, checks


def parse_sizes(text: str) -> list[int]:
    """``"1,5,10"`` -> [1, 5, 10]; each at least 1."""
    try:
        sizes = sorted({int(x) for x in text.split(",") if x.strip()})
    except ValueError:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected whole numbers separated by commas, such as 1,5,10") from None
    if not sizes or sizes[0] < 1:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected sizes of at least 1 manager")
    return sizes


def main(argv: list[str] | None = None) -> int:
    """Measure each size in each topology, print the tables with growth and targets, write the results."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=parse_sizes, help="fleet sizes (default 1,5,10,20,40; --smoke 1,2,3)")
    parser.add_argument("--topologies", default="peers,router", help="peers, router or both (default peers,router)")
    parser.add_argument("--max", action="store_true", help="after the sizes, 1.5 times larger each time until a fleet no longer holds")
    parser.add_argument("--max-limit", type=int, default=400, help="--max stops here whatever happens (default 400)")
    parser.add_argument("--settle", type=float, help="seconds between the units' start and the idle window (default 15; --smoke 1)")
    parser.add_argument("--window", type=float, help="seconds of the idle window (default 30; --smoke 2)")
    parser.add_argument("--listings", type=int, help="get_federated_model calls (default 5; --smoke 2)")
    parser.add_argument("--cmd-runs", type=int, help="dyknow managers runs (default 3; --smoke 1)")
    parser.add_argument("--first", type=int, help="managers making a first plan (default 5; --smoke 2)")
    parser.add_argument("--repeats", type=int, help="repeated plans on m0 (default 10; --smoke 3)")
    parser.add_argument("--newcomers", type=int, help="newcomers, one at a time (default 3; --smoke 1)")
    parser.add_argument("--kills", type=int, help="SIGKILLs of the provider (default 20; --smoke 2)")
    parser.add_argument("--smoke", action="store_true", help="a quick run: sizes 1, 2 and 3, short windows, few repeats")
    parser.add_argument("--json", type=Path, help="write the results here (default benchmarks/results/fleet.json; --smoke: none)")
    parser.add_argument("--txt", type=Path, help="write the report here (default benchmarks/results/fleet.txt; --smoke: none)")
    args = parser.parse_args(argv)
    smoke = args.smoke
    defaults = {"sizes": ([1, 2, 3], [1, 5, 10, 20, 40]), "settle": (1.0, 15.0), "window": (2.0, 30.0), "listings": (2, 5),
                "cmd_runs": (1, 3), "first": (2, 5), "repeats": (3, 10), "newcomers": (1, 3), "kills": (2, 20)}  # fmt: skip
    for name, (quick, full) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if smoke else full)
    if not smoke:
        args.json = args.json or RESULTS / "fleet.json"
        args.txt = args.txt or RESULTS / "fleet.txt"
    topologies = [t.strip() for t in args.topologies.split(",") if t.strip()]
    if not topologies or set(topologies) - set(TOPOLOGIES):
        parser.error(f"--topologies: got {args.topologies!r}; expected peers, router or peers,router")
    for name in ("listings", "cmd_runs", "first", "repeats", "newcomers", "kills"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')}: got {getattr(args, name)}; expected at least 1")
    if not Path("/proc/self/task").is_dir():
        parser.error("this benchmark reads /proc (Linux only)")
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the finally blocks: every child stopped

    info = machine()

    def out(line: str) -> None:
        print(line, flush=True)

    out(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}; load average {load_average():.2f}")
    runs: list[dict[str, Any]] = []
    began = time.monotonic()
    for topology in topologies:
        for n in args.sizes:
            runs.append(run_fleet(topology, n, args, out))
        n = args.sizes[-1]
        while args.max and held(runs[-1]):
            n = math.ceil(n * 1.5)
            available = _available_mib()
            if n > args.max_limit or available < n * 100:
                out(f"\n{topology}: --max stops before {n} managers ({'past --max-limit' if n > args.max_limit else f'{available:.0f} MiB of memory available'})")
                break
            runs.append(run_fleet(topology, n, args, out))
        if args.max:
            largest = max((r["managers"] for r in runs if r["topology"] == topology and held(r)), default=0)
            out(f"{topology}: the largest fleet that held: {largest} managers")

    lines, checks = report(runs, info, args, argv)
    out(f"\nall fleets measured in {time.monotonic() - began:.0f} s")
    for line in lines:
        out(line)
    serial = [{**r, "figures": {k: asdict(f) for k, f in figures(r).items()}} for r in runs]
    if args.json:
        write_json(args.json, {"machine": info, "config": {k: v for k, v in vars(args).items() if k not in ("json", "txt")} | {
            "json": str(args.json), "txt": str(args.txt) if args.txt else None}, "results": serial, "targets": checks})  # fmt: skip
    if args.txt:
        args.txt.parent.mkdir(parents=True, exist_ok=True)
        args.txt.write_text("\n".join(lines) + "\n")
        out(f"wrote {args.txt}")
    return 0


def _available_mib() -> float:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) / 1024
    return float("inf")


if __name__ == "__main__":
    sys.exit(main())
