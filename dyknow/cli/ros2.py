"""ROS 2 from the command line: ``dyknow echo ros2:/TOPIC`` (a topic decoded, with its latency),
``dyknow ros2 list`` (the ROS 2 graph on Zenoh, or on DDS with ``--dds``) and ``dyknow ros2 call``
(a service called, as ``ros2 service call`` does)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from dyknow.cli.common import DEFAULT_MANAGER, Commands, UsageError, open_client, payload_json, report_result, ros2_domain, tls_files

if TYPE_CHECKING:
    from dyknow.access import TlsFiles
    from dyknow.errors import ServiceError


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
    """list the ROS 2 graph seen on Zenoh (rmw_zenoh's liveliness tokens): nodes, topics, services and their types"""
    from dyknow.ros2 import snapshot

    if args.dds:  # DDS: what discovery brings within --timeout (types only: DDS has no node tokens)
        from dyknow.ros2.dds import DdsNode

        with DdsNode(domain=ros2_domain(args)) as participant:
            topics, services = participant.discover(wait_s=args.timeout)

        def dds_lines() -> Iterable[str]:
            yield "topics (DDS):"
            yield from (f"  {t} [{', '.join(types)}]" for t, types in topics.items())
            yield "services (DDS):"
            yield from (_service_line(name, entry) for name, entry in services.items())

        report_result(args, {"topics": topics, "services": services}, dds_lines)
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
        yield "services:"
        yield from (_service_line(name, entry) for name, entry in view.services().items())

    report_result(args, view.to_dict(), lines)
    return 0


def _service_line(name: str, entry: dict[str, Any]) -> str:
    servers, clients = int(entry["servers"]), int(entry["clients"])
    return f"  {name} [{', '.join(entry['types'])}] ({servers} server{'s' if servers != 1 else ''}, {clients} client{'s' if clients != 1 else ''})"


def parse_request(text: str) -> dict[str, Any]:
    """A request's fields as ``ros2 service call`` takes them: YAML (``{transition: {id: 3}}``)
    or JSON; an empty text is an empty request. Raises :class:`UsageError` saying what is wrong."""
    import json5

    if not text.strip():
        return {}
    try:
        value = json5.loads(text)
    except ValueError as first:
        try:
            import yaml  # type: ignore[import-untyped]  # (when installed: block YAML, bare strings; it ships no stubs)
        except ImportError:
            raise UsageError(f"the request {text[:80]!r} does not parse: {first}; expected JSON or YAML such as '{{transition: {{id: 3}}}}'") from None
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise UsageError(f"the request {text[:80]!r} does not parse: {exc}; expected JSON or YAML such as '{{transition: {{id: 3}}}}'") from None
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise UsageError(f"the request is a {type(value).__name__}; expected a mapping of the request's fields, like '{{transition: {{id: 3}}}}'")
    return value


def _small_arrays_listed(value: Any, most: int = 1024) -> Any:
    """``value`` with its arrays of at most ``most`` elements as lists (as ``ros2 service call``
    prints ``byte_array_value=[]``); larger ones stay arrays, described by :func:`payload_json`."""
    import numpy as np

    if isinstance(value, np.ndarray):
        return value.tolist() if value.size <= most else value
    if isinstance(value, dict):
        return {key: _small_arrays_listed(item, most) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_small_arrays_listed(item, most) for item in value]
    return value


def cmd_ros2_call(args: argparse.Namespace) -> int:
    """call a ROS 2 service once and print its response, as `ros2 service call` does (rmw_zenoh, or DDS with --dds)

    examples:
      dyknow ros2 call /camera_top/change_state lifecycle_msgs/srv/ChangeState '{transition: {id: 3}}'
      dyknow ros2 call /camera_top/get_state lifecycle_msgs/srv/GetState --json
      dyknow ros2 call /camera_top/get_state lifecycle_msgs/srv/GetState --dds --ros2-domain 7"""
    from dyknow.ros2 import Ros2Node
    from dyknow.ros2.convert import from_message

    request = parse_request(args.request)
    started = time.monotonic()
    if args.dds:  # DDS needs no manager: a participant of its own (discovery on loopback)
        from dyknow.ros2.dds import DdsNode

        with DdsNode(domain=ros2_domain(args)) as participant:
            from dyknow.ros2.services import READ_ONLY_SERVICES, RESEND_S

            client = participant.create_client(args.service, args.srv_type)
            resend = RESEND_S if args.srv_type in READ_ONLY_SERVICES else None  # (an answer lost to discovery: asked again)
            response = client.call(request, timeout_s=args.timeout, resend_s=resend)
            response_type = client.response_type
    else:
        from dyknow.errors import ServiceError

        with open_client(args) as session_client, Ros2Node(session_client.session, f"dyknow_call_{os.getpid()}", domain=ros2_domain(args)) as node:
            zclient = node.create_client(args.service, args.srv_type)
            try:
                response = zclient.call(request, timeout_s=args.timeout)
            except ServiceError as exc:
                tls = tls_files(args)
                if tls is None:
                    raise
                raise _with_roles(exc, args.service, tls) from exc
            response_type = zclient.response_type
    took_ms = (time.monotonic() - started) * 1000
    fields = payload_json(_small_arrays_listed(from_message(response, response_type)))
    data = {"service": args.service, "type": args.srv_type, "request": request, "response": fields, "took_ms": round(took_ms, 1)}

    def lines() -> Iterable[str]:
        yield f"requester: making request: {args.srv_type} {json.dumps(request)}"
        yield f"response ({took_ms:.0f} ms):"
        yield from json.dumps(fields, indent=2).splitlines()

    report_result(args, data, lines)
    return 0


def _with_roles(exc: ServiceError, service: str, tls: TlsFiles) -> ServiceError:
    """A call's :class:`~dyknow.errors.ServiceError` over TLS, saying what roles have to do with it:
    a request that ended at once without an answer was dropped by an ACL on the way (Zenoh
    drops it silently) or by the server, and the right the service needs is named
    (:func:`dyknow.access.ros2_right`); no server at all is what a certificate with no role sees."""
    from dyknow.access import MANAGE, ros2_right
    from dyknow.errors import ServiceError
    from dyknow.identity import Signer

    reason = exc.details.get("reason")
    if reason not in ("dropped", "no-server"):
        return exc
    name = Signer(tls).common_name
    right = ros2_right(service)
    if reason == "no-server":
        return ServiceError(
            exc.what, details=exc.details, where=exc.where,
            expected=f"{exc.expected}; over a link with roles (--acl), a certificate with no role there (common name {name!r}) sees no ROS 2 server at all",
        )  # fmt: skip
    if right == MANAGE:
        needs = (
            f"a certificate whose role has the right {MANAGE} in the --acl of the manager or router it connects to (operator, admin, "
            f'or a role of the file\'s own with calls: ["{MANAGE}"]): {service} changes a node'
        )
    elif right is not None:
        needs = (
            "a certificate whose role may read nodes in the --acl of the manager or router it connects to (viewer, operator, admin, or a "
            f"role of the file's own like one of them or with {MANAGE}); with one, the server dropped it: its log says why"
        )
    else:
        needs = (
            "a service a link with roles carries: of other nodes' services, dyknow's ACL lets through only their lifecycle, parameter and "
            "mode services (a router's certificate carries everything); call it on the robot's side"
        )
    return ServiceError(
        f"the request ended at once without an answer: refused by the --acl of a manager or router on the way (this client's "
        f"certificate, common name {name!r}, --tls-cert {tls.cert}, may not call it there), or dropped by the server",
        details=exc.details, where=exc.where, expected=needs,
    )  # fmt: skip


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""
    ros2 = cmds.group(
        "ros2", help="the ROS 2 graph on Zenoh or DDS (list, call)", description="the ROS 2 graph (as rmw_zenoh's tokens show it) and its services"
    )

    def list_options(p: argparse.ArgumentParser) -> None:
        cmds.zenoh_options(p, connect_help=cmds.connect_help())
        p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help=argparse.SUPPRESS)
        p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="seconds to gather the graph (default 1)")
        p.add_argument("--dds", action="store_true", help="the topics on DDS (Cyclone DDS, loopback discovery) instead of rmw_zenoh")
        cmds.ros2_domain_option(p)
        cmds.lease_option(p)

    ros2.command("list", cmd_ros2_list, list_options)

    def call_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("service", metavar="SERVICE", help="the service's fully qualified name, like /camera_top/change_state")
        p.add_argument("srv_type", metavar="TYPE", help="its type, like lifecycle_msgs/srv/ChangeState")
        p.add_argument("request", metavar="REQUEST", nargs="?", default="{}", help="the request's fields in YAML or JSON (default: {})")
        cmds.zenoh_options(p, connect_help=cmds.connect_help())
        p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help=argparse.SUPPRESS)
        p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="seconds to wait for a server and its answer (default 5)")
        p.add_argument("--dds", action="store_true", help="call over DDS (Cyclone DDS, loopback discovery) instead of rmw_zenoh")
        cmds.ros2_domain_option(p)
        cmds.lease_option(p)

    ros2.command("call", cmd_ros2_call, call_options)
