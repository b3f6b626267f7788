"""ROS 2 from the command line: ``dyknow echo ros2:/TOPIC`` (a topic decoded, with its latency)
and ``dyknow ros2 list`` (the ROS 2 graph on Zenoh, or on DDS with ``--dds``)."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from collections.abc import Iterable
from typing import Any

from dyknow.cli.common import DEFAULT_MANAGER, Commands, open_client, payload_json, report_result, ros2_domain


def echo_ros2(args: argparse.Namespace) -> int:
    """``dyknow echo ros2:/TOPIC``: a ROS 2 topic decoded, with its latency (from the header stamp
    when the type has one, else from the publisher's source timestamp)."""
    from dyknow.errors import DyKnowError
    from dyknow.message import describe_payload
    from dyknow.ros2 import Received, Ros2Node, parse_binding
    from dyknow.ros2.convert import from_message, stamp_ns

    binding = parse_binding(args.keyexpr, where="echo")
    done = threading.Event()
    lock = threading.Lock()
    seen = 0

    def show(received: Received) -> None:
        nonlocal seen
        with lock:
            if done.is_set():
                return
            try:
                payload: Any = from_message(received.message, received.ros_type)
            except DyKnowError as exc:
                payload = {"refused": str(exc)}
            stamp = stamp_ns(received.message)
            origin = stamp or received.attachment.source_timestamp_ns
            data = {
                "topic": binding.topic,
                "type": received.ros_type,
                "seq": received.attachment.sequence_number,
                "source_timestamp_ns": received.attachment.source_timestamp_ns,
                "stamp_ns": stamp,
                "latency_us": round((received.arrival_ns - origin) / 1000, 1),
                "measured_from": "header.stamp" if stamp else "source_timestamp",
                "payload": payload_json(payload),
            }
            text = f"{binding.topic} [{received.ros_type}] #{data['seq']} age {data['latency_us'] / 1000:.3f} ms: {describe_payload(payload)}"
            report_result(args, data, text)
            seen += 1
            if args.count is not None and seen >= args.count:
                done.set()

    def wait() -> None:
        signal.signal(signal.SIGINT, lambda *_: done.set())
        signal.signal(signal.SIGTERM, lambda *_: done.set())
        done.wait(args.timeout_total) if args.timeout_total else done.wait()
        done.set()

    if binding.dds:  # DDS needs no manager: a participant of its own (discovery on loopback)
        from dyknow.ros2.dds import DdsNode

        with DdsNode(domain=ros2_domain(args)) as participant:
            participant.create_subscription(binding.topic, binding.ros_type, show, binding.qos)
            wait()
    else:
        with open_client(args) as client, Ros2Node(client.session, f"dyknow_echo_{os.getpid()}", domain=ros2_domain(args)) as node:
            node.create_subscription(binding.topic, binding.ros_type, show, binding.qos, humble=binding.humble)
            wait()
    if args.count is not None and seen < args.count:
        print(f"dyknow: error: received {seen} of {args.count} messages on {binding.topic!r}", file=sys.stderr)
        return 1
    return 0


def cmd_ros2_list(args: argparse.Namespace) -> int:
    """list the ROS 2 graph seen on Zenoh (rmw_zenoh's liveliness tokens): nodes, topics and their types"""
    from dyknow.ros2 import snapshot

    if args.dds:  # DDS: what discovery brings within --timeout (types only: DDS has no node tokens)
        from dyknow.ros2.dds import DdsNode

        with DdsNode(domain=ros2_domain(args)) as participant:
            topics = participant.topics(wait_s=args.timeout)
        report_result(args, {"topics": topics}, ["topics (DDS):", *(f"  {t} [{', '.join(types)}]" for t, types in topics.items())])
        return 0
    with open_client(args) as client:
        view = snapshot(client.session, ros2_domain(args), timeout_s=args.timeout)

    def lines() -> Iterable[str]:
        yield "nodes:"
        yield from (f"  {node}" for node in view.nodes())
        yield "topics:"
        for topic, types in view.topics().items():
            publishers = len(view.publishers(topic))
            yield f"  {topic} [{', '.join(types)}] ({publishers} publisher{'s' if publishers != 1 else ''})"

    report_result(args, view.to_dict(), lines)
    return 0


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""
    ros2 = cmds.group("ros2", help="the ROS 2 graph on Zenoh (list)", description="the ROS 2 graph, as rmw_zenoh's tokens show it")

    def list_options(p: argparse.ArgumentParser) -> None:
        cmds.zenoh_options(p, connect_help=cmds.connect_help())
        p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help=argparse.SUPPRESS)
        p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="seconds to gather the graph (default 1)")
        p.add_argument("--dds", action="store_true", help="the topics on DDS (Cyclone DDS, loopback discovery) instead of rmw_zenoh")
        cmds.ros2_domain_option(p)
        cmds.lease_option(p)

    ros2.command("list", cmd_ros2_list, list_options)
