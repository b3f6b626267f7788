"""The peers of the chain benchmark: Cyclone DDS, dora-rs and pyzmq, one process per hop.

``chain.py`` measures dyknow against raw Zenoh; this module runs the same chain on the middleware
users compare against, with exactly the same workload and protocol as ``chain.py``'s
``zenoh-process`` variant, so the figures sit side by side:

- a source, ``hops - 1`` relays and a sink, one OS process each, linked in a line; hop ``i``
  carries the messages from process ``i`` to process ``i + 1``;
- every message is 16 bytes with its origin time (``time.time_ns()``) beside it, as the Zenoh
  variant carries it in an attachment; every relay reads the clock and republishes at once;
- the source probes the chain (a ``probe`` payload every 0.1 s) until the sink acks a probe,
  then touches the up file and starts: back-to-back (one message in flight: the sink acks each
  message straight back to the source, which then sends the next; without an ack for
  ``STALL_S`` the source sends the next one anyway) or paced (a fixed rate);
- the sink records arrival minus origin for every message and ends at the last one, or after
  ``IDLE_S`` without messages (lost messages never arrive);
- CPU time is that of every process involved (for dora, its daemon too), from the moment the
  up file is seen to the end, divided by the messages sent; the caller drops the warm-up.

The variants, each used the fastest normal way for small messages:

- ``dds-process``: Eclipse Cyclone DDS (``cyclonedds``, the Python binding of the C library;
  DDS is the ROS 2 default middleware family): one topic per hop (``bench_h0``, ...), a small
  IDL struct (``int64 origin; octet payload[16];``), reliable, keep-last 100 (back-to-back has
  one message in flight, paced a few: nothing is dropped). Relays and the sink take samples in
  a Listener's ``on_data_available`` callback: against a WaitSet loop it tied back-to-back and
  was faster paced (measured on this machine, see ``_dds_worker``). Cyclone is confined to
  loopback without multicast (``CYCLONEDDS_URI``: interface ``lo``, unicast discovery with the
  one peer ``127.0.0.1``), in a domain of its own per run, so concurrent runs do not cross-talk.
- ``dora-process``: dora-rs 1.1 with Python nodes, ``dora run`` on a generated dataflow (one
  local daemon in the ``dora run`` process, no coordinator); the sink's ``ack`` output feeds
  the source's ``ack`` input, a cycle dora accepts. The payload is a 16-byte ``pyarrow``
  ``UInt8Array`` built once; the origin rides in the metadata (dora's per-message parameters)
  and relays send the input's array on with ``{"origin": ...}``: faster here than the origin in
  the payload or the whole metadata passed on (5 hops back-to-back, 3 interleaved runs each).
  Inputs are queued 100 deep. ``dora run`` binds its Zenoh to loopback with multicast scouting
  off (``DORA_ZENOH_MULTICAST=off`` makes sure); ``RUST_BACKTRACE`` is unset for it, as in
  production, so a timed-out wait does not capture a backtrace.
- ``zmq-process``: pyzmq PUSH/PULL over ``ipc://`` sockets in a temporary folder, the Python
  IPC floor: each receiver binds a PULL, its sender connects a PUSH; the origin is the first
  8 bytes of the frame; the sink acks over another PUSH/PULL pair.

    python benchmarks/peers.py --variants zmq-process,dds-process --hops 5   (one run each)

They need ``pip install -e '.[bench]'``; ``missing(variant)`` says what is absent.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import random
import shlex
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import IO, Any

from harness import cpu_seconds, sleep_until

__all__ = ["PEER_VARIANTS", "main", "missing", "run_peer"]

PEER_VARIANTS = ("dds-process", "dora-process", "zmq-process")

# the same workload and protocol as chain.py's process variants (kept in step by hand: chain.py
# imports dyknow, which the peers' worker processes have no need to load)
PAYLOAD = bytes(16)
PROBE = b"probe"
PROBE_S = 0.1
STALL_S = 0.5
IDLE_S = 3.0
# Unlike chain.py's source, ours waits (this long at most) after touching the up file until the
# parent has read the CPU times and touched ``<up>.go``: the CPU window then starts exactly at the
# up file, and even a run shorter than the parent's polling period has a CPU figure.
GO_WAIT_S = 5.0
# keep-last depth (DDS) and input queue (dora): far above what is ever in flight in these modes
DEPTH = 100
INSTALL = "pip install -e '.[bench]'"
_PACKAGES = {
    "dds-process": (("cyclonedds", "cyclonedds"),),
    "dora-process": (("dora", "dora-rs"), ("dora_cli", "dora-rs-cli"), ("pyarrow", "pyarrow")),
    "zmq-process": (("zmq", "pyzmq"),),
}


def missing(variant: str) -> str | None:
    """None when ``variant`` can run here, else a sentence saying what to install."""
    if variant not in PEER_VARIANTS:
        raise ValueError(f"unknown peer {variant!r}; expected one of {', '.join(PEER_VARIANTS)}")
    absent = [dist for module, dist in _PACKAGES[variant] if importlib.util.find_spec(module) is None]
    if absent:
        return f"{variant} needs {', '.join(absent)}: {INSTALL}"
    if variant == "dora-process":
        try:
            found = version("dora-rs")
        except PackageNotFoundError:
            found = "unknown"
        if not found.startswith("1.1."):
            return f"dora-process is measured with dora-rs 1.1, found {found}: {INSTALL}"
        if _dora_cli() is None:
            return f"dora-process needs the dora command (dora-rs-cli) beside {sys.executable} or on PATH: {INSTALL}"
    return None


def run_peer(
    variant: str, hops: int, total: int, rate_hz: float | None, domain: int | None = None, idle_s: float = IDLE_S
) -> tuple[list[int], float]:
    """Run one chain; returns (every last-hop latency in ns of the `total` messages that arrived,
    in order, warm-up NOT dropped; CPU seconds per message of every process involved, NaN when the
    run ended before the up file was seen). ``domain``: the DDS domain of ``dds-process`` (default:
    one whose discovery port is free now); ``idle_s``: the sink ends this long after the latest
    message (a test on a loaded machine waits longer: a process may stall seconds there)."""
    why = missing(variant)
    if why:
        raise RuntimeError(why)
    if hops < 1 or total < 1:
        raise ValueError(f"got hops={hops}, total={total}; expected at least one hop and one message")
    rate = float(rate_hz or 0.0)
    with tempfile.TemporaryDirectory(prefix="dyknow-peers-") as tmp:
        folder = Path(tmp)
        result, up = folder / "latencies.json", folder / "up"
        common = [
            "--hops", str(hops), "--messages", str(total), "--rate", repr(rate), "--result", str(result),
            "--up-file", str(up), "--dir", str(folder), "--idle", repr(float(idle_s)),
        ]  # fmt: skip
        procs: list[_Child] = []
        try:
            if variant == "dora-process":
                procs.append(_start_dora(folder, hops, common))
            else:
                env = dict(os.environ)
                if variant == "dds-process":
                    env["CYCLONEDDS_URI"] = _cyclone_config(hops)
                    common += ["--domain", str(_free_domain() if domain is None else domain)]
                for i in range(hops, -1, -1):  # receivers first, the source last
                    role = "source" if i == 0 else ("sink" if i == hops else "relay")
                    argv = [sys.executable, __file__, "--worker", variant, "--role", role, "--index", str(i), *common]
                    procs.append(_Child(argv, env, folder / f"stderr-{i}.txt", new_session=False))
            latencies, cpu = _wait(variant, hops, total, rate, procs, result, up)
        finally:
            for child in reversed(procs):
                child.stop()
    return latencies, cpu / total


# ---------------------------------------------------------------------------- the parent side


class _Child:
    """A worker process (or ``dora run`` and its nodes) whose output goes to a file."""

    def __init__(self, argv: list[str], env: dict[str, str], log: Path, new_session: bool, cwd: Path | None = None) -> None:
        self.argv = argv
        self.log_path = log
        self.log: IO[bytes] = log.open("wb")
        self.new_session = new_session
        self.proc = subprocess.Popen(
            argv, stdin=subprocess.DEVNULL, stdout=self.log, stderr=subprocess.STDOUT, env=env, cwd=cwd, start_new_session=new_session
        )

    def pids(self) -> list[int]:
        """The process and, for a session of its own (``dora run``), every process in that session."""
        return sorted({self.proc.pid, *_session(self.proc.pid)}) if self.new_session else [self.proc.pid]

    def tail(self) -> str:
        """The last 1,500 characters the process wrote."""
        self.log.flush()
        return self.log_path.read_text(errors="replace")[-1500:]

    def stop(self) -> None:
        """End the process (``dora run``: Ctrl-C first, so it stops its nodes), then what is left of its session."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT if self.new_session else signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        if self.new_session:  # nodes that outlived their daemon (a paced source does not read its STOP)
            for pid in _session(self.proc.pid):
                try:
                    os.kill(pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
        self.log.close()


def _session(sid: int) -> list[int]:
    """The processes of session ``sid`` (dora's nodes each lead a process group of their own)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[3]) == sid:
                members.append(int(stat.parent.name))
        except (OSError, IndexError, ValueError):
            continue
    return members


def _deadline_s(total: int, rate: float) -> float:
    """As long as chain.py's process variants may take."""
    return 120 + total * (1.0 / rate if rate else 0.05)  # (more than a sink's idle end a test asks for)


def _wait(variant: str, hops: int, total: int, rate: float, procs: list[_Child], result: Path, up: Path) -> tuple[list[int], float]:
    deadline = time.monotonic() + _deadline_s(total, rate)
    pids: list[int] = []
    cpu0 = None
    while not result.exists():
        if cpu0 is None and up.exists():
            pids = [pid for child in procs for pid in child.pids()]
            cpu0 = cpu_seconds(pids)
            Path(f"{up}.go").touch()
        failed = [child for child in procs if child.proc.poll() is not None]
        if failed:
            child = failed[0]
            raise RuntimeError(
                f"{variant} chain of {hops}: {shlex.join(child.argv)} exited with {child.proc.returncode} "
                f"before the sink wrote its result; its output ends: {child.tail()}"
            )
        if time.monotonic() > deadline:
            tails = "; ".join(f"[{i}] {child.tail()[-300:]}" for i, child in enumerate(procs))
            raise RuntimeError(
                f"{variant} chain of {hops} did not finish {total} messages within {_deadline_s(total, rate):.0f} s "
                f"(up file seen: {cpu0 is not None}); the outputs end: {tails}"
            )
        time.sleep(0.05 if cpu0 is not None else 0.005)
    # no CPU figure only if the source gave up waiting for the go (GO_WAIT_S) and the run ended unseen
    cpu = cpu_seconds(pids) - cpu0 if cpu0 is not None else float("nan")
    return list(json.loads(result.read_text())), cpu


def _write_result(path: str, latencies: list[int]) -> None:
    tmp = path + ".tmp"
    Path(tmp).write_text(json.dumps(latencies))
    os.replace(tmp, path)


# ---------------------------------------------------------------------------- the protocol


def _source(send: Callable[[bytes], None], wait_ack: Callable[[float], bytes | None], args: argparse.Namespace) -> None:
    """Probe until the sink acks, touch the up file, then send ``args.messages``: paced at
    ``args.rate``, or back-to-back (the next one on each ack, or after ``STALL_S`` without one)."""
    up = False
    while not up:  # probe until the whole line answers
        send(PROBE)
        until = time.monotonic() + PROBE_S
        while not up and (left_s := until - time.monotonic()) > 0:
            up = wait_ack(left_s) == PROBE
    Path(args.up_file).touch()
    go, until = Path(args.up_file + ".go"), time.monotonic() + GO_WAIT_S
    while not go.exists() and time.monotonic() < until:  # the parent reads the CPU times first
        time.sleep(0.001)
    left = args.messages
    if args.rate:
        period = 1.0 / args.rate
        next_at = time.perf_counter()
        while left > 0:
            next_at += period
            sleep_until(next_at)
            left -= 1
            send(PAYLOAD)
        return
    left -= 1
    send(PAYLOAD)
    last_ack = time.monotonic()
    while left > 0:
        ack = wait_ack(max(0.0, last_ack + STALL_S - time.monotonic()))
        if ack == PROBE:  # a late ack of one of the probes
            last_ack = time.monotonic()
            continue
        last_ack = time.monotonic()  # an ack, or STALL_S without one: the previous message was lost
        left -= 1
        send(PAYLOAD)


class _Sink:
    """The sink's bookkeeping: ``arrived`` records a message and says what to ack."""

    def __init__(self, args: argparse.Namespace, ack: Callable[[bytes], None]) -> None:
        self.expected = args.messages
        self.back_to_back = not args.rate
        self.idle_s = float(getattr(args, "idle", IDLE_S))
        self.ack = ack
        self.latencies: list[int] = []
        self.last_ns = 0
        self.done = threading.Event()

    def arrived(self, now_ns: int, origin_ns: int, payload: bytes) -> None:
        """A probe is acked; a message's latency is recorded, ending the run at the last one or acked back-to-back."""
        if payload == PROBE:
            self.ack(PROBE)
            return
        self.last_ns = now_ns
        self.latencies.append(now_ns - origin_ns)
        if len(self.latencies) >= self.expected:
            self.done.set()
        elif self.back_to_back:
            self.ack(b"")

    def idle(self) -> bool:
        """True (and done) when no message came for ``IDLE_S`` after the first."""
        if self.last_ns and time.time_ns() - self.last_ns > self.idle_s * 1e9:
            self.done.set()
        return self.done.is_set()


# ---------------------------------------------------------------------------- pyzmq


def _zmq_worker(args: argparse.Namespace) -> int:
    import zmq

    def address(name: str) -> str:
        return f"ipc://{args.dir}/{name}"

    i, hops = args.index, args.hops
    context = zmq.Context()
    try:
        if args.role == "source":
            push = context.socket(zmq.PUSH)
            push.connect(address("h0"))
            acks = context.socket(zmq.PULL)
            acks.bind(address("ack"))

            def send(payload: bytes) -> None:
                push.send(time.time_ns().to_bytes(8, "little") + payload)

            def wait_ack(timeout_s: float) -> bytes | None:
                if acks.poll(int(timeout_s * 1000) + 1):
                    return bytes(acks.recv())
                return None

            _source(send, wait_ack, args)
        elif args.role == "relay":
            pull = context.socket(zmq.PULL)
            pull.bind(address(f"h{i - 1}"))
            push = context.socket(zmq.PUSH)
            push.connect(address(f"h{i}"))
            while True:
                frame = pull.recv()
                time.time_ns()  # each receiver reads the clock, as in every other variant
                push.send(frame)
        else:
            pull = context.socket(zmq.PULL)
            pull.bind(address(f"h{hops - 1}"))
            pull.setsockopt(zmq.RCVTIMEO, 250)
            ack = context.socket(zmq.PUSH)
            ack.connect(address("ack"))
            sink = _Sink(args, ack.send)
            while not sink.done.is_set():
                try:
                    frame = pull.recv()
                except zmq.Again:
                    sink.idle()
                    continue
                sink.arrived(time.time_ns(), int.from_bytes(frame[:8], "little"), frame[8:])
            _write_result(args.result, sink.latencies)
        threading.Event().wait()  # until the parent has read the CPU times and ends us
    finally:
        context.destroy(linger=0)
    return 0


# ---------------------------------------------------------------------------- Cyclone DDS


def _cyclone_config(hops: int) -> str:
    """Loopback only, no multicast: discovery by unicast to 127.0.0.1, one participant per process."""
    return (
        "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface name='lo'/></Interfaces>"
        "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
        f"<MaxAutoParticipantIndex>{hops + 8}</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
        "</Discovery></Domain></CycloneDDS>"
    )


def _free_domain() -> int:
    """A DDS domain id whose first participant's discovery port is free on this machine, so a
    concurrent run (in another domain) cannot be seen."""
    for domain in random.sample(range(1, 230), 229):
        port = 7400 + 250 * domain + 10  # Cyclone's unicast discovery port of participant index 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
        return domain
    raise RuntimeError("no free DDS domain: every domain's discovery port 7410 + 250 * id is taken")


def _dds_hop_type() -> Any:
    """The IDL struct ``Hop { int64 origin; octet payload[16]; }``, built here with real (not
    string) annotations: this module's are strings, which Cyclone resolves in its globals. A
    fixed array goes to and from ``bytes`` in one copy (a ``sequence<octet>`` is a list of ints
    in Python, and a ``bytes`` field has no XTypes type object)."""
    import types
    from dataclasses import dataclass

    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import array, int64, uint8

    def body(namespace: dict[str, Any]) -> None:
        payload: Any = array[uint8, len(PAYLOAD)]  # type: ignore[misc]
        namespace.update(__annotations__={"origin": int64, "payload": payload}, __module__=__name__)

    return dataclass(types.new_class("Hop", (IdlStruct,), {"typename": "dyknow_bench::Hop"}, body))


def _dds_worker(args: argparse.Namespace) -> int:
    """One DDS process. Relays and the sink take samples in a Listener's ``on_data_available``
    callback (on Cyclone's receive thread). Measured here against a WaitSet loop in the main
    thread, 5 hops: back-to-back a tie (77 against 80 us/hop, medians of 8 interleaved runs of
    2,000 messages), paced at 50 Hz the listener ahead (257 against 290 us/hop, 3 runs each)."""
    from cyclonedds.core import InstanceState, Listener, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    Hop = _dds_hop_type()
    i, hops = args.index, args.hops
    qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(DEPTH), Policy.Durability.Volatile)
    participant = DomainParticipant(args.domain)
    probe = PROBE.ljust(len(PAYLOAD), b"\0")  # the payload field is 16 bytes: the probe is padded

    def topic(name: str) -> Any:
        return Topic(participant, name, Hop, qos=qos)

    def hop(origin: int, payload: bytes) -> Any:
        return Hop(origin=origin, payload=payload.ljust(len(PAYLOAD), b"\0"))

    def listen(name: str, on_sample: Callable[[Any], None]) -> Any:
        def on_data_available(reader: Any) -> None:
            for sample in reader.take(N=DEPTH):
                if type(sample) is Hop:  # not a dispose or unregister notice
                    on_sample(sample)

        return DataReader(participant, topic(name), qos=qos, listener=Listener(on_data_available=on_data_available))

    if args.role == "source":
        out = DataWriter(participant, topic("bench_h0"), qos=qos)
        acks = DataReader(participant, topic("bench_ack"), qos=qos)
        waitset = WaitSet(participant)
        waitset.attach(ReadCondition(acks, SampleState.NotRead | ViewState.Any | InstanceState.Any))
        pending: list[bytes] = []

        def send(payload: bytes) -> None:
            out.write(hop(time.time_ns(), payload))

        def wait_ack(timeout_s: float) -> bytes | None:
            if not pending:
                waitset.wait(duration(seconds=timeout_s))
                pending.extend(s.payload.rstrip(b"\0") for s in acks.take(N=DEPTH) if type(s) is Hop)
            return pending.pop(0) if pending else None

        _source(send, wait_ack, args)
    elif args.role == "relay":
        out = DataWriter(participant, topic(f"bench_h{i}"), qos=qos)

        def relay(sample: Any) -> None:
            time.time_ns()  # each receiver reads the clock, as in every other variant
            out.write(sample)

        _reader = listen(f"bench_h{i - 1}", relay)
    else:
        ack = DataWriter(participant, topic("bench_ack"), qos=qos)
        sink = _Sink(args, lambda payload: ack.write(hop(0, payload)))

        def last(sample: Any) -> None:
            sink.arrived(time.time_ns(), sample.origin, PROBE if sample.payload == probe else sample.payload)

        _reader = listen(f"bench_h{hops - 1}", last)
        while not sink.done.wait(0.25):
            sink.idle()
        _write_result(args.result, sink.latencies)
    threading.Event().wait()  # until the parent has read the CPU times and ends us
    return 0


# ---------------------------------------------------------------------------- dora-rs


def _dora_cli() -> str | None:
    beside = Path(sys.executable).parent / "dora"
    return str(beside) if beside.exists() else shutil.which("dora")


def _start_dora(folder: Path, hops: int, common: list[str]) -> _Child:
    """Write the dataflow (source, relays, sink, the sink's ack back to the source) and ``dora run`` it."""

    def node(role: str, i: int, inputs: dict[str, str], outputs: list[str]) -> dict[str, Any]:
        args = [__file__, "--worker", "dora-process", "--role", role, "--index", str(i), *common]
        return {
            "id": role if role != "relay" else f"r{i}",
            "path": sys.executable,
            "args": shlex.join(args),
            "inputs": {name: {"source": source, "queue_size": DEPTH} for name, source in inputs.items()},
            "outputs": outputs,
        }

    def sender(i: int) -> str:
        return "source/out" if i == 0 else f"r{i}/out"

    nodes = [node("source", 0, {"ack": "sink/ack"}, ["out"])]
    nodes += [node("relay", i, {"in": sender(i - 1)}, ["out"]) for i in range(1, hops)]
    nodes.append(node("sink", hops, {"in": sender(hops - 1)}, ["ack"]))
    dataflow = folder / "dataflow.yml"
    dataflow.write_text(json.dumps({"nodes": nodes}, indent=1))  # JSON is YAML
    env = dict(os.environ, DORA_ZENOH_MULTICAST="off")
    # no backtrace capture on every timed-out wait (RUST_BACKTRACE=1 is a debugging setting)
    env.pop("RUST_BACKTRACE", None)
    env.pop("RUST_LIB_BACKTRACE", None)
    cli = _dora_cli()
    assert cli is not None  # missing() said so
    return _Child([cli, "run", "--log-level", "warn", str(dataflow)], env, folder / "dora-run.txt", new_session=True, cwd=folder)


def _dora_worker(args: argparse.Namespace) -> int:
    import pyarrow as pa  # type: ignore[import-untyped]
    from dora import Node

    node = Node()

    def stopped(event: dict[str, Any] | None) -> bool:
        return event is None or event["type"] == "STOP"

    def until_stopped() -> None:  # keep the node alive until dora stops the dataflow
        while not stopped(node.next()):
            pass

    if args.role == "source":
        arrays = {PAYLOAD: pa.array(PAYLOAD, type=pa.uint8()), PROBE: pa.array(PROBE, type=pa.uint8())}

        def send(payload: bytes) -> None:
            node.send_output("out", arrays[payload], {"origin": time.time_ns()})

        def wait_ack(timeout_s: float) -> bytes | None:
            event = node.next(timeout=max(timeout_s, 0.001))
            if stopped(event):
                raise SystemExit(0)
            assert event is not None
            if event["type"] != "INPUT":
                return None  # a timeout comes as an ERROR event
            return PROBE if len(event["value"]) == len(PROBE) else b""

        _source(send, wait_ack, args)
        until_stopped()
    elif args.role == "relay":
        while True:
            event = node.next()
            if stopped(event):
                break
            assert event is not None
            if event["type"] == "INPUT":
                time.time_ns()  # each receiver reads the clock, as in every other variant
                node.send_output("out", event["value"], {"origin": event["metadata"]["origin"]})
    else:
        empty = pa.array(b"", type=pa.uint8())
        probe = pa.array(PROBE, type=pa.uint8())
        sink = _Sink(args, lambda payload: node.send_output("ack", probe if payload == PROBE else empty))
        while not sink.done.is_set():
            event = node.next(timeout=0.25)
            now = time.time_ns()
            if stopped(event):
                break
            assert event is not None
            if event["type"] != "INPUT":  # a timeout
                sink.idle()
                continue
            value = event["value"]
            sink.arrived(now, event["metadata"]["origin"], PROBE if len(value) == len(PROBE) else PAYLOAD)
        _write_result(args.result, sink.latencies)
        until_stopped()
    return 0


# ---------------------------------------------------------------------------- command line

_WORKERS: dict[str, Callable[[argparse.Namespace], int]] = {
    "dds-process": _dds_worker,
    "dora-process": _dora_worker,
    "zmq-process": _zmq_worker,
}


def main(argv: list[str] | None = None) -> int:
    """A worker process of a chain (``--worker``), or one run of each peer asked for, printed."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", default=",".join(PEER_VARIANTS), help="comma-separated peers to run once each")
    parser.add_argument("--hops", type=int, default=5, help="chain length")
    parser.add_argument("--messages", type=int, default=2000, help="messages to send (nothing dropped as warm-up)")
    parser.add_argument("--rate", type=float, default=0.0, help="paced rate in Hz (0: back-to-back)")
    # worker processes
    parser.add_argument("--worker", choices=PEER_VARIANTS, help=argparse.SUPPRESS)
    parser.add_argument("--role", choices=("source", "relay", "sink"), help=argparse.SUPPRESS)
    parser.add_argument("--index", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    parser.add_argument("--up-file", help=argparse.SUPPRESS)
    parser.add_argument("--dir", help=argparse.SUPPRESS)
    parser.add_argument("--idle", type=float, default=IDLE_S, help=argparse.SUPPRESS)
    parser.add_argument("--domain", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return _WORKERS[args.worker](args)
    for variant in [v for v in args.variants.split(",") if v]:
        if variant not in PEER_VARIANTS:
            parser.error(f"unknown variant {variant!r}; expected some of {', '.join(PEER_VARIANTS)}")
        why = missing(variant)
        if why:
            print(f"{variant}: {why}")
            continue
        latencies, cpu = run_peer(variant, args.hops, args.messages, args.rate or None)
        median_us = statistics.median(latencies) / 1000 if latencies else float("nan")
        print(
            f"{variant:<13} {args.hops} hops: {len(latencies)} of {args.messages} arrived, last-hop median {median_us:.1f} us "
            f"({median_us / args.hops:.2f} us/hop), CPU {cpu * 1e6:.0f} us/message"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
