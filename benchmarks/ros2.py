"""ROS 2 interop cost: a 640x480 rgb8 ``sensor_msgs/Image`` at 30 Hz from a ROS-side publisher,
through a relay, back to a ROS-side subscriber; latency p50/p99 and CPU per message.

Variants (each relay in a process of its own; the ROS side, publisher and subscriber, in another,
so latency is one clock: arrival minus the image's ``header.stamp``, set when it is sent):

- ``dyknow-zenoh``: a dyknow manager whose ``relay`` unit is bound ``in=ros2:/bench/in``,
  ``out=ros2:/bench/out`` (rmw_zenoh); the ROS side is a :class:`dyknow.ros2.Ros2Node` (the same
  wire as rmw_zenoh_cpp, which has no wheel to run here);
- ``dyknow-dds``: the same relay bound ``ros2dds:`` (Cyclone DDS); the ROS side is rclpy on
  rmw_fastrtps_cpp (the ROS 2 wheels);
- ``rclpy-dds``: an rclpy relay node (subscription -> publish) between the same rclpy ROS side:
  what ROS 2 itself costs over the same middleware as ``dyknow-dds``;
- ``dyknow-native``: dyknow's own path for comparison: the same relay bound to dyknow keys, fed
  and read by a dyknow manager (BGR arrays, dyknow's header; latency from its origin time).

The dyknow relays convert as a unit sees it (Image -> BGR array -> Image: two copies and a
channel swap); the rclpy relay republishes the message object. CPU per message is the relay
process's CPU time over the messages it relayed, and the ROS side's over the messages it sent.
Targets printed: dyknow's relay within 2x rclpy's CPU per message and within 5 ms of its p50.
The rclpy processes load dyknow's Fast DDS profile (``dyknow.ros2.dds.FASTDDS_PROFILE``: type
propagation off, 4 MB UDP socket buffers), as its docs tell ROS 2 users to (``--fastdds-profile``
another); the kernel caps those buffers at ``net.core.rmem_max``, printed first. Each variant
also reports the UDP datagrams the kernel dropped for a full socket receive buffer meanwhile
(``RcvbufErrors`` in ``/proc/net/snmp``).

    python benchmarks/ros2.py --json out/ros2.json
    python benchmarks/ros2.py --smoke --json /tmp/ros2.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from harness import Proc, cpu_seconds, free_ports, machine, percentile, write_json

WIDTH, HEIGHT = 640, 480
IMAGE = "sensor_msgs/msg/Image"
SCRIPT = str(Path(__file__).resolve())
VARIANTS = ("dyknow-native", "dyknow-zenoh", "dyknow-dds", "rclpy-dds")
STRAGGLERS_S = 30.0  # how long the ROS side waits, after sending, for the frames still on their way


def _rclpy_env(domain: int, profile: Path | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
    # Cyclone (dyknow-dds) refuses Fast DDS 3's type objects for byte sequences: type propagation off
    from dyknow.ros2.dds import FASTDDS_PROFILE

    env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(profile or FASTDDS_PROFILE)
    return env


def udp_receive_buffer_errors() -> int:
    """The kernel's count of UDP datagrams dropped for a full socket receive buffer (this network
    namespace, every process: the benchmark runs alone)."""
    lines = [line.split() for line in Path("/proc/net/snmp").read_text().splitlines() if line.startswith("Udp:")]
    return int(lines[1][lines[0].index("RcvbufErrors")])


def _import_rclpy() -> Any:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import rclpy
        from sensor_msgs.msg import Image
    return rclpy, Image


def ros_side(middleware: str, endpoint: str, domain: int, rate_hz: float, duration_s: float) -> None:
    """Publish frames on /bench/in, take them back on /bench/out; print one JSON line of results."""
    frame = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    latencies: list[float] = []
    lock = threading.Lock()
    sent = 0

    def stamp_ns(msg: Any) -> int:
        return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)

    def arrived(msg: Any) -> None:
        with lock:
            latencies.append((time.time_ns() - stamp_ns(msg)) / 1e6)

    print(json.dumps({"ready": True}), flush=True)
    if middleware == "native":
        from dyknow import Manager
        from dyknow.resources import specs_dir

        with Manager("side", specs=[specs_dir() / "generic.xml"], connect=[endpoint]) as side:
            from dyknow.spec import Port, TransformationSpec

            side.add_transformation(TransformationSpec("source", "dyknow.testing:Source", ports=(Port("out", "out"),)))
            side.add_transformation(TransformationSpec("sink", "dyknow.testing:Sink", ports=(Port("in", "in", queue=64),)))
            side.spawn("source", "source", bindings={"out": "bench/in"})
            side.spawn("sink", "sink", bindings={"in": "bench/out"})
            source, sink = side.unit("source"), side.unit("sink")
            bgr = np.ascontiguousarray(frame)
            # the relay's clock, for its times: estimated on demand once its data reaches this
            # manager (issue 40), so frames flow until it is (they are not counted)
            deadline = time.monotonic() + 30
            while "bench" not in side.get_model().clocks and time.monotonic() < deadline:
                source.emit(bgr.copy())  # type: ignore[attr-defined]
                time.sleep(0.1)
            time.sleep(0.5)
            warmup = len(sink.messages)  # type: ignore[attr-defined]
            start = time.monotonic()
            cpu0 = time.process_time()
            while time.monotonic() - start < duration_s:
                source.emit(bgr.copy())  # type: ignore[attr-defined]  # a new frame each time, as a camera's
                sent += 1
                time.sleep(max(0.0, sent / rate_hz - (time.monotonic() - start)))
            time.sleep(0.5)
            cpu = time.process_time() - cpu0
            _until(lambda: len(sink.messages) - warmup >= sent)  # type: ignore[attr-defined]  # (frames still on their way: not in the CPU figure)
            # the sink's input port measures arrival minus origin itself (the last 1,000 or so)
            latency = side.get_statistics("sink").ports[0].latency
            received = len(sink.messages) - warmup  # type: ignore[attr-defined]
        print(
            json.dumps({"sent": sent, "received": received, "p50_ms": latency.p50_us / 1000, "p99_ms": latency.p99_us / 1000, "cpu_s": cpu})
        )
        return
    if middleware == "zenoh":
        from dyknow.ros2 import Ros2Node
        from dyknow.ros2.convert import to_message
        from dyknow.transport import open_session

        with (
            open_session(listen=["tcp/127.0.0.1:0"], connect=[endpoint]) as session,
            Ros2Node(session, "bench_ros_side", domain=domain) as node,
        ):
            pub = node.create_publisher("/bench/in", IMAGE)
            node.create_subscription("/bench/out", IMAGE, lambda r: arrived(r.message))
            time.sleep(1.0)  # discovery
            start = time.monotonic()
            cpu0 = time.process_time()
            while (t := time.monotonic() - start) < duration_s:
                now = time.time_ns()
                pub.publish(to_message(frame, IMAGE, node.types, origin_ns=now))
                sent += 1
                time.sleep(max(0.0, sent / rate_hz - (time.monotonic() - start)))
            time.sleep(0.5)
            cpu = time.process_time() - cpu0
            _until(lambda: len(latencies) >= sent)
    else:
        rclpy, Image = _import_rclpy()
        rclpy.init()
        node = rclpy.create_node("bench_ros_side")
        pub = node.create_publisher(Image, "/bench/in", 10)
        sub = node.create_subscription(Image, "/bench/out", arrived, 10)
        data = frame[:, :, ::-1].tobytes()
        end = time.monotonic() + 30.0
        while time.monotonic() < end and not (pub.get_subscription_count() and sub.get_publisher_count()):  # discovery
            rclpy.spin_once(node, timeout_sec=0.05)
        start = time.monotonic()
        cpu0 = time.process_time()
        while (t := time.monotonic() - start) < duration_s + 0.5:
            if t < duration_s and sent < (t * rate_hz):
                msg = Image(height=HEIGHT, width=WIDTH, encoding="rgb8", step=WIDTH * 3, data=data)
                now = time.time_ns()
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 1_000_000_000)
                pub.publish(msg)
                sent += 1
            rclpy.spin_once(node, timeout_sec=0.002)
        cpu = time.process_time() - cpu0
        _until(lambda: len(latencies) >= sent, lambda: rclpy.spin_once(node, timeout_sec=0.05))
        node.destroy_node()
        rclpy.shutdown()
    with lock:
        got = list(latencies)
    print(json.dumps({"sent": sent, "received": len(got), "latencies_ms": got, "cpu_s": cpu}), flush=True)


def _until(done: Callable[[], bool], wait: Callable[[], object] = lambda: time.sleep(0.05), timeout_s: float = STRAGGLERS_S) -> None:
    """Wait (``wait`` at a time) until ``done()`` or ``timeout_s``: the frames still on their way
    when sending ends, which a loaded machine delays by seconds. Outside the CPU figures; a frame
    that never comes is counted as not received."""
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        wait()


def _until_sigterm() -> threading.Event:
    import signal

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    return stop


def relay_dyknow(middleware: str, listen: str, domain: int) -> None:
    """A manager with one relay unit between /bench/in and /bench/out (dyknow keys bench/in and
    bench/out for ``native``); runs until SIGTERM."""
    from dyknow import Manager
    from dyknow.resources import specs_dir

    scheme = "ros2" if middleware == "zenoh" else "ros2dds"
    with Manager("bench", specs=[specs_dir() / "generic.xml"], listen=[listen], ros2_domain=domain) as manager:
        if middleware == "native":
            manager.spawn("relay", "relay", bindings={"in": "bench/in", "out": "bench/out"})
        else:
            manager.spawn("relay", "relay", bindings={"in": f"{scheme}:/bench/in?type={IMAGE}", "out": f"{scheme}:/bench/out?type={IMAGE}"})
        stop = _until_sigterm()
        print(json.dumps({"ready": True}), flush=True)
        stop.wait()
        relayed = next(p.messages for p in manager.get_statistics("relay").ports if p.direction == "out")
        print(json.dumps({"relayed": relayed}), flush=True)


def relay_rclpy() -> None:
    """An rclpy node republishing /bench/in on /bench/out; runs until SIGTERM."""
    rclpy, Image = _import_rclpy()
    rclpy.init()
    node = rclpy.create_node("bench_relay")
    pub = node.create_publisher(Image, "/bench/out", 10)
    relayed = 0

    def forward(msg: Any) -> None:
        nonlocal relayed
        pub.publish(msg)
        relayed += 1

    node.create_subscription(Image, "/bench/in", forward, 10)
    closed = _until_sigterm()
    print(json.dumps({"ready": True}), flush=True)
    while not closed.is_set():
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps({"relayed": relayed}), flush=True)
    node.destroy_node()
    rclpy.shutdown()


def run_variant(variant: str, rate_hz: float, duration_s: float, domain: int, profile: Path | None = None) -> dict[str, Any]:
    """One variant: start the relay, run the ROS side, stop the relay; the figures."""
    import signal

    port = free_ports(1)[0]
    endpoint = f"tcp/127.0.0.1:{port}"
    middleware = {"dyknow-zenoh": "zenoh", "dyknow-native": "native"}.get(variant, "dds")
    env = _rclpy_env(domain, profile)
    relay_args = ["relay-rclpy"] if variant == "rclpy-dds" else ["relay-dyknow", middleware, endpoint]
    relay = Proc([sys.executable, SCRIPT, *relay_args, str(domain)], env=env)
    try:
        relay.next_json(60, ready=True)
        cpu_before = cpu_seconds([relay.proc.pid])
        drops_before = udp_receive_buffer_errors()
        side = Proc([sys.executable, SCRIPT, "ros-side", middleware, endpoint, str(domain), str(rate_hz), str(duration_s)], env=env)
        try:
            side.next_json(60, ready=True)
            result = side.next_json(duration_s + 60)
        finally:
            side.close()
        relay_cpu = cpu_seconds([relay.proc.pid]) - cpu_before
        drops = udp_receive_buffer_errors() - drops_before
        relay.proc.send_signal(signal.SIGTERM)
        relayed = int(relay.next_json(30)["relayed"])
    finally:
        relay.close()
    lat = result.get("latencies_ms", [])
    p50 = result.get("p50_ms", percentile(lat, 50) if lat else None)
    p99 = result.get("p99_ms", percentile(lat, 99) if lat else None)
    return {
        "variant": variant,
        "rate_hz": rate_hz,
        "sent": result["sent"],
        "received": result["received"],
        "relayed": relayed,
        "latency_p50_ms": None if p50 is None else round(p50, 3),
        "latency_p99_ms": None if p99 is None else round(p99, 3),
        "relay_cpu_ms_per_msg": round(relay_cpu * 1000 / max(1, relayed), 3),
        "ros_side_cpu_ms_per_msg": round(result["cpu_s"] * 1000 / max(1, result["sent"]), 3),
        "udp_rcvbuf_drops": drops,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the variants and print the table and the targets."""
    args = sys.argv[1:] if argv is None else argv
    if args and args[0] == "ros-side":
        ros_side(args[1], args[2], int(args[3]), float(args[4]), float(args[5]))
        return 0
    if args and args[0] == "relay-dyknow":
        relay_dyknow(args[1], args[2], int(args[3]))
        return 0
    if args and args[0] == "relay-rclpy":
        relay_rclpy()  # (its domain comes in ROS_DOMAIN_ID)
        return 0
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0, help="seconds of frames per variant (default 10)")
    parser.add_argument("--rate", type=float, default=30.0, help="frames per second (default 30)")
    parser.add_argument("--smoke", action="store_true", help="a quick run that checks the benchmark works (1 s at 10 Hz)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--variant", action="append", choices=VARIANTS, help="run only this variant (repeatable; default all)")
    parser.add_argument("--domains", metavar="A,B,...", help="the DDS domain of each variant in turn (default: 150 + pid %% 40 and the next ones)")
    parser.add_argument("--fastdds-profile", type=Path, metavar="FILE",
                        help="the Fast DDS profile the rclpy processes load (default: dyknow's, dyknow.ros2.dds.FASTDDS_PROFILE)")  # fmt: skip
    opts = parser.parse_args(args)
    duration, rate = (1.0, 10.0) if opts.smoke else (opts.duration, opts.rate)
    # the DDS variants' UDP buffers (dyknow's Fast DDS profile asks 4 MB) are capped by the kernel here
    rmem_max = Path("/proc/sys/net/core/rmem_max").read_text().strip()
    print(f"net.core.rmem_max={rmem_max} (the Fast DDS profile's 4 MB UDP buffers need >= 4194304)")
    first = 150 + os.getpid() % 40
    domains = [int(d) for d in opts.domains.split(",")] if opts.domains else [first + i for i in range(len(VARIANTS))]
    if len(domains) < len(VARIANTS) or not all(0 <= d <= 232 for d in domains):
        parser.error(f"--domains {opts.domains}: expected {len(VARIANTS)} DDS domain ids of 0-232, one per variant")
    if opts.fastdds_profile is not None:
        if not opts.fastdds_profile.is_file():  # (Fast DDS would go on without it, saying nothing)
            parser.error(f"--fastdds-profile: no file at {opts.fastdds_profile}")
        print(f"Fast DDS profile: {opts.fastdds_profile}")
    rows = [
        run_variant(v, rate, duration, domains[i], opts.fastdds_profile) for i, v in enumerate(VARIANTS) if not opts.variant or v in opts.variant
    ]
    print(f"{'variant':<14} {'sent':>5} {'back':>5} {'p50 ms':>8} {'p99 ms':>8} {'relay CPU ms/msg':>17} {'ROS side CPU ms/msg':>20} {'UDP rcvbuf drops':>17}")
    for r in rows:
        print(
            f"{r['variant']:<14} {r['sent']:>5} {r['received']:>5} {r['latency_p50_ms'] or float('nan'):>8.2f} {r['latency_p99_ms'] or float('nan'):>8.2f} "
            f"{r['relay_cpu_ms_per_msg']:>17.2f} {r['ros_side_cpu_ms_per_msg']:>20.2f} {r['udp_rcvbuf_drops']:>17}"
        )
    by = {r["variant"]: r for r in rows}
    dds, ros = by.get("dyknow-dds"), by.get("rclpy-dds")
    if dds and ros and dds["latency_p50_ms"] is not None and ros["latency_p50_ms"] is not None:
        cpu_ok = dds["relay_cpu_ms_per_msg"] <= 2 * ros["relay_cpu_ms_per_msg"]
        lat_ok = dds["latency_p50_ms"] <= ros["latency_p50_ms"] + 5
        print(f"target: dyknow's DDS relay CPU/msg within 2x rclpy's: {'met' if cpu_ok else 'NOT met'} "
              f"({dds['relay_cpu_ms_per_msg']:.2f} vs {ros['relay_cpu_ms_per_msg']:.2f} ms)")  # fmt: skip
        print(f"target: dyknow's DDS relay p50 within 5 ms of rclpy's: {'met' if lat_ok else 'NOT met'} "
              f"({dds['latency_p50_ms']:.2f} vs {ros['latency_p50_ms']:.2f} ms)")  # fmt: skip
    if opts.json:
        write_json(opts.json, {"machine": machine(), "width": WIDTH, "height": HEIGHT, "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
