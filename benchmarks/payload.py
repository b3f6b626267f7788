"""Payload sizes: latency and throughput of 64 B to 6 MiB messages, in-process and across processes.

For each size (64 B, 64 KiB, 1 MiB, and a 1080p BGR frame of 6,220,800 B, "6 MiB"):

- ``dyknow-inproc``: a source and a sink unit in one manager (1 hop), plus a 5-hop chain of
  relays for the zero-copy check: the per-hop cost must not grow with the size;
- ``dyknow-process``: source and sink in two manager processes (1 hop);
- ``zenoh-process``: raw Zenoh between two processes, ``put(frame.tobytes())`` and
  ``payload.to_bytes()`` on receipt (the plain path);
- ``zenoh-shm-process``: the same through a Zenoh shared-memory pool, as dyknow sends payloads of
  64 KiB and more (the fairest raw form for large payloads; only run for those sizes).

Latency: one message in flight (the sink acks each), arrival minus origin at the sink. Every
variant stamps the origin before it serialises the frame and the arrival once the receiver holds
it as an array, so the copies each side makes are inside the figure.
Throughput: four messages in flight; messages per second and MB/s at the sink.

    python benchmarks/payload.py --json out/payload.json --plot out/payload.png
    python benchmarks/payload.py --smoke --json /tmp/payload.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from dyknow import Manager, Message, TransformationSpec, Unit
from dyknow.spec import Param, Port
from dyknow.transport import SHM_POOL_BYTES, SHM_THRESHOLD

from harness import free_ports, machine, worker_env, write_json

SIZES = {"64 B": (64,), "64 KiB": (65536,), "1 MiB": (1 << 20,), "6 MiB": (1080, 1920, 3)}
PROBE = b"probe"
TARGETS = {"inproc_6mib_5hop_us_per_hop": 20.0, "process_6mib_frames_per_s": 800.0}


# A frame can be dropped on the way (Zenoh publishers drop rather than block when their queue is
# full): the source then sends the next one after STALL_S without an ack, and the sink finishes
# after IDLE_S without frames. Losses are reported.
STALL_S = 0.5
IDLE_S = 2.0


class PayloadSource(Unit):
    """Keeps ``window`` messages of ``shape`` bytes in flight; each ack from the sink sends the next."""

    def setup(self) -> None:
        """Read the params, make the random frame to send and start probing the sink every 0.1 s."""
        self.left = int(self.params["messages"])
        self.window = int(self.params["window"])
        shape = tuple(int(x) for x in str(self.params["shape"]).split("x"))
        self.frame = np.random.default_rng(1).integers(0, 255, shape, dtype=np.uint8)
        self.started = False
        self.last_ack = time.monotonic()
        self.prober = self.create_timer(0.1, lambda: self.publish("out", PROBE))
        self.publish("out", PROBE)

    def send(self) -> None:
        """Send the frame, stamped now, unless every message was sent."""
        if self.left > 0:
            self.left -= 1
            self.publish("out", self.frame, origin_ns=time.time_ns())

    def unstall(self) -> None:
        """Send the next frame when no ack came for ``STALL_S`` (one was lost on the way)."""
        if time.monotonic() - self.last_ack > STALL_S:
            self.last_ack = time.monotonic()
            self.send()

    def on_message(self, port: str, msg: Message) -> None:
        """An ack: the first probe ack sends ``window`` frames, every later ack the next one."""
        self.last_ack = time.monotonic()
        if msg.payload == PROBE:
            if not self.started:
                self.started = True
                self.prober.cancel()
                self.create_timer(STALL_S / 2, self.unstall)
                for _ in range(self.window):
                    self.send()
        else:
            self.send()


class PayloadSink(Unit):
    """Records arrival minus origin and arrival times; acks every message."""

    def setup(self) -> None:
        """Read the params and start the idle check (the run ends after ``IDLE_S`` without frames)."""
        self.latencies: list[int] = []
        self.arrivals: list[int] = []
        self.expected = int(self.params["messages"])
        self.done = threading.Event()
        self.create_timer(0.25, self.check_idle)

    def check_idle(self) -> None:
        """End the run when no frame came for ``IDLE_S`` (lost frames never arrive)."""
        if self.arrivals and time.time_ns() - self.arrivals[-1] > IDLE_S * 1e9:
            self.done.set()

    def on_message(self, port: str, msg: Message) -> None:
        """Ack a probe; record a frame's latency and arrival time, and ack it."""
        now = time.time_ns()
        if isinstance(msg.payload, bytes) and msg.payload == PROBE:
            self.publish("ack", PROBE)
            return
        self.latencies.append(now - msg.origin_ns)
        self.arrivals.append(now)
        if len(self.latencies) >= self.expected:
            self.done.set()
        self.publish("ack", b"")


def specs(shape: tuple[int, ...], messages: int, window: int) -> list[TransformationSpec]:
    """The specs of the source, a relay and the sink, for ``messages`` of ``shape`` with ``window`` in flight."""
    module = __name__ if __name__ != "__main__" else "__main__"
    params = (
        Param("messages", "int", messages),
        Param("window", "int", window),
        Param("shape", "string", "x".join(str(x) for x in shape)),
    )
    return [
        TransformationSpec("payload-source", f"{module}:PayloadSource", params, (Port("ack", "in"), Port("out", "out"))),
        TransformationSpec("relay", "transformations.generic:Relay", (), (Port("in", "in"), Port("out", "out"))),
        TransformationSpec("payload-sink", f"{module}:PayloadSink", params, (Port("in", "in"), Port("ack", "out"))),
    ]


def run_inproc(shape: tuple[int, ...], messages: int, window: int, hops: int) -> tuple[list[int], list[int]]:
    """Source, ``hops`` - 1 relays and sink in one manager; the latencies and arrival times (ns) at the sink."""
    with Manager("payload", specs=specs(shape, messages, window), listen=[], serve=False) as manager:
        manager.spawn("payload-sink", "sink", bindings={"in": f"p/h{hops - 1}", "ack": "p/ack"})
        for i in range(hops - 1, 0, -1):
            manager.spawn("relay", f"r{i}", bindings={"in": f"p/h{i - 1}", "out": f"p/h{i}"})
        manager.spawn("payload-source", "source", bindings={"ack": "p/ack", "out": "p/h0"})
        sink = manager.unit("sink")
        assert isinstance(sink, PayloadSink)
        if not sink.done.wait(120):
            raise RuntimeError(f"in-process {shape}: {len(sink.latencies)} of {messages} arrived")
        return sink.latencies[:messages], sink.arrivals[:messages]


def run_process(variant: str, shape: tuple[int, ...], messages: int, window: int) -> tuple[list[int], list[int]]:
    """Source and sink of ``variant`` in two processes; the latencies and arrival times (ns) at the sink."""
    ports = free_ports(2)
    eps = [f"tcp/127.0.0.1:{p}" for p in ports]
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.json"
        common = [
            "--variant", variant, "--shape", "x".join(map(str, shape)), "--messages", str(messages),
            "--window", str(window), "--result", str(result),
        ]  # fmt: skip
        procs = [
            subprocess.Popen([sys.executable, __file__, "--worker", "sink", "--listen", eps[1], "--connect", eps[0], *common], env=worker_env()),
            subprocess.Popen([sys.executable, __file__, "--worker", "source", "--listen", eps[0], *common], env=worker_env()),
        ]
        try:
            deadline = time.monotonic() + 180
            while not result.exists():
                if time.monotonic() > deadline or any(p.poll() not in (None, 0) for p in procs):
                    raise RuntimeError(f"{variant} {shape}: the worker processes did not finish")
                time.sleep(0.05)
            data = json.loads(result.read_text())
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                p.wait(10)
    return data["latencies"], data["arrivals"]


def worker(args: argparse.Namespace) -> int:
    """One process of a two-process run (``--worker source`` or ``sink``); the sink writes the result file."""
    shape = tuple(int(x) for x in args.shape.split("x"))
    if args.variant == "dyknow-process":
        with Manager(f"w-{args.worker}", specs=specs(shape, args.messages, args.window), listen=[args.listen],
                     connect=args.connect, serve=False) as manager:  # fmt: skip
            if args.worker == "sink":
                manager.spawn("payload-sink", "sink", bindings={"in": "p/h0", "ack": "p/ack"})
                sink = manager.unit("sink")
                assert isinstance(sink, PayloadSink)
                sink.done.wait()
                _write(args.result, sink.latencies, sink.arrivals)
            else:
                manager.spawn("payload-source", "source", bindings={"ack": "p/ack", "out": "p/h0"})
            threading.Event().wait()
    import zenoh

    from dyknow.transport import make_config

    with zenoh.open(make_config(listen=[args.listen], connect=args.connect)) as session:
        if args.worker == "sink":
            latencies: list[int] = []
            arrivals: list[int] = []
            done = threading.Event()
            ack = session.declare_publisher("p/ack")

            def idle() -> None:
                while not done.wait(0.25):
                    if arrivals and time.time_ns() - arrivals[-1] > IDLE_S * 1e9:
                        done.set()

            threading.Thread(target=idle, daemon=True).start()

            def on_frame(sample: Any) -> None:
                data = sample.payload.to_bytes()
                if data == PROBE:
                    ack.put(PROBE)
                    return
                np.frombuffer(data, dtype=np.uint8).reshape(shape)
                now = time.time_ns()  # the frame is in hand as an array, as a dyknow unit gets it
                latencies.append(now - int.from_bytes(sample.attachment.to_bytes(), "little"))
                arrivals.append(now)
                if len(latencies) >= args.messages:
                    done.set()
                ack.put(b"")

            _sub = session.declare_subscriber("p/h0", on_frame)
            done.wait()
            _write(args.result, latencies, arrivals)
        else:
            out = session.declare_publisher("p/h0")
            frame = np.random.default_rng(1).integers(0, 255, shape, dtype=np.uint8)
            shm = args.variant == "zenoh-shm-process" and frame.nbytes >= SHM_THRESHOLD
            provider = zenoh.shm.ShmProvider.default_backend(SHM_POOL_BYTES) if shm else None

            def payload() -> Any:
                data = frame.tobytes()
                if provider is None:
                    return data
                try:
                    buffer = provider.alloc(len(data), zenoh.shm.GarbageCollect())
                except zenoh.ZError:
                    return data  # the pool is full right now (receivers still hold buffers)
                buffer[:] = data
                return buffer

            left = [args.messages]
            up = threading.Event()
            lock = threading.Lock()
            last_ack = [time.monotonic()]

            def send() -> None:
                with lock:
                    if left[0] <= 0:
                        return
                    left[0] -= 1
                origin = time.time_ns()  # stamped before the frame is serialised, as dyknow's source does
                out.put(payload(), attachment=origin.to_bytes(8, "little"))

            def unstall() -> None:
                up.wait()
                while left[0] > 0:
                    time.sleep(STALL_S / 2)
                    if time.monotonic() - last_ack[0] > STALL_S:
                        last_ack[0] = time.monotonic()
                        send()

            threading.Thread(target=unstall, daemon=True).start()

            def on_ack(sample: Any) -> None:
                last_ack[0] = time.monotonic()
                if sample.payload.to_bytes() == PROBE:
                    if not up.is_set():
                        up.set()
                        for _ in range(args.window):
                            send()
                else:
                    send()

            _ack = session.declare_subscriber("p/ack", on_ack)
            while not up.wait(0.1):
                out.put(PROBE)
        threading.Event().wait()
    return 0


def _write(path: str, latencies: list[int], arrivals: list[int]) -> None:
    Path(path + ".tmp").write_text(json.dumps({"latencies": latencies, "arrivals": arrivals}))
    Path(path + ".tmp").replace(path)


def summarize(latencies: list[int], arrivals: list[int], nbytes: int, hops: int, warmup: int) -> dict[str, float]:
    """Latency percentiles, per-hop latency and throughput (messages/s, MB/s) after the warm-up messages."""
    lat = np.asarray(latencies[warmup:], dtype=np.float64) / 1000
    arr = arrivals[warmup:]
    span = (arr[-1] - arr[0]) / 1e9 if len(arr) > 1 else float("nan")
    rate = (len(arr) - 1) / span if span and span > 0 else float("nan")
    return {
        "latency_median_us": round(float(np.median(lat)), 2),
        "latency_p99_us": round(float(np.percentile(lat, 99)), 2),
        "per_hop_median_us": round(float(np.median(lat)) / hops, 2),
        "messages_per_s": round(rate, 1),
        "mb_per_s": round(rate * nbytes / 1e6, 1),
    }


def main(argv: list[str] | None = None) -> int:
    """Measure every size and variant, print a table and the target checks (and write JSON and a plot if asked)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--smoke", action="store_true", help="a few messages per size (CI)")
    parser.add_argument("--messages", type=int, default=None, help="messages per run (default 300)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--worker", choices=("source", "sink"), help=argparse.SUPPRESS)
    parser.add_argument("--variant", help=argparse.SUPPRESS)
    parser.add_argument("--shape", help=argparse.SUPPRESS)
    parser.add_argument("--window", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--listen", help=argparse.SUPPRESS)
    parser.add_argument("--connect", action="append", default=[], help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args)

    messages = args.messages or (12 if args.smoke else 300)
    warmup = 2 if args.smoke else 20
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}")
    print(f"{'variant':<16} {'size':>7} {'hops':>4} {'lat p50':>10} {'lat p99':>10} {'per hop':>10} {'msg/s':>9} {'MB/s':>9}")
    results = []
    for label, shape in SIZES.items():
        nbytes = int(np.prod(shape))
        runs = [("dyknow-inproc", 1), ("dyknow-inproc", 5), ("dyknow-process", 1), ("zenoh-process", 1)]
        if nbytes >= SHM_THRESHOLD:
            runs.append(("zenoh-shm-process", 1))
        for variant, hops in runs:
            total = messages + warmup
            if variant == "dyknow-inproc":
                lat, _ = run_inproc(shape, total, 1, hops)
                _, arrivals = run_inproc(shape, total, 4, hops)
            else:
                lat, _ = run_process(variant, shape, total, 1)
                _, arrivals = run_process(variant, shape, total, 4)
            row = {"variant": variant, "size": label, "bytes": nbytes, "hops": hops, "messages": messages,
                   "lost": max(0, total - len(lat)) + max(0, total - len(arrivals))}  # fmt: skip
            row.update(summarize(lat, arrivals, nbytes, hops, warmup))
            results.append(row)
            print(
                f"{variant:<16} {label:>7} {hops:>4} {row['latency_median_us']:>8.1f}us {row['latency_p99_us']:>8.1f}us "
                f"{row['per_hop_median_us']:>8.2f}us {row['messages_per_s']:>9.0f} {row['mb_per_s']:>9.0f}",
                flush=True,
            )
    checks = _checks(results)
    for line in checks:
        print(line)
    if args.json:
        write_json(args.json, {"machine": info, "results": results, "targets": TARGETS})
    if args.plot:
        plot(results, info, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _checks(results: list[dict[str, Any]]) -> list[str]:
    def get(variant: str, size: str, hops: int) -> dict[str, Any]:
        return next(r for r in results if (r["variant"], r["size"], r["hops"]) == (variant, size, hops))

    small, big = get("dyknow-inproc", "64 B", 5), get("dyknow-inproc", "6 MiB", 5)
    proc = get("dyknow-process", "6 MiB", 1)
    raw, raw_shm = get("zenoh-process", "6 MiB", 1), get("zenoh-shm-process", "6 MiB", 1)
    t1, t2 = TARGETS["inproc_6mib_5hop_us_per_hop"], TARGETS["process_6mib_frames_per_s"]
    return [
        f"6 MiB through 5 in-process hops: {big['per_hop_median_us']:.2f} us per hop (64 B: {small['per_hop_median_us']:.2f} us; "
        f"target at most {t1:g} us, zero copy): {'met' if big['per_hop_median_us'] <= t1 else 'MISSED'}",
        f"6 MiB across processes, one hop: {proc['messages_per_s']:.0f} frames/s ({proc['mb_per_s']:.0f} MB/s; raw Zenoh "
        f"{raw['messages_per_s']:.0f}/s plain, {raw_shm['messages_per_s']:.0f}/s through shared memory; target at least {t2:g}/s): {'met' if proc['messages_per_s'] >= t2 else 'MISSED'}",
    ]


def plot(results: list[dict[str, Any]], info: dict[str, Any], path: Path) -> None:
    """Plot per-hop latency and throughput against the payload size to a PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    for variant, hops in [("dyknow-inproc", 1), ("dyknow-inproc", 5), ("dyknow-process", 1), ("zenoh-process", 1), ("zenoh-shm-process", 1)]:
        rows = [r for r in results if r["variant"] == variant and r["hops"] == hops]
        label = f"{variant} ({hops} hop{'s' if hops > 1 else ''})"
        ax1.plot([r["bytes"] for r in rows], [r["per_hop_median_us"] for r in rows], marker="o", label=label)
        ax2.plot([r["bytes"] for r in rows], [r["messages_per_s"] for r in rows], marker="o", label=label)
    for ax, ylabel in ((ax1, "median latency per hop (us)"), (ax2, "messages per second (4 in flight)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("payload bytes")
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle("Payload size: in-process delivery is by reference; across processes Zenoh shared memory")
    fig.text(0.5, 0.005, f"{info['cpu']}, {info['cores']} cores, Python {info['python']}, Zenoh {info['zenoh']}", ha="center", fontsize=8)
    fig.tight_layout(rect=(0, 0.03, 1, 0.95))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
