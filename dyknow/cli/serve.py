"""Commands that serve until stopped: ``manager``, ``router``, ``ui`` (the browser tool), ``foxglove``."""

from __future__ import annotations

import argparse
import gc
import logging
import os
import queue
import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dyknow.cli.common import (
    DEFAULT_MANAGER,
    Commands,
    UsageError,
    default_endpoint,
    open_client,
    positive_int,
    read_limits,
    report_result,
    seconds,
    shipped,
    tls_files,
)

if TYPE_CHECKING:
    from dyknow.access import AccessControl
    from dyknow.transport import RouterLink


def _lanes(text: str) -> int:
    """--max-lanes: a whole number of at least 2 (the shared lane and one for slow units)."""
    value = positive_int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"got {value}; expected at least 2 (the shared lane and one for slow units)")
    return value


def _lag(text: str) -> float:
    """--overload-lag: seconds, more than 0."""
    value = seconds(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected seconds, more than 0, such as 0.05")
    return value


def _nice(text: str) -> int:
    """--nice: a whole number from -20 to 19."""
    from dyknow.priority import MAX_NICE, MIN_NICE

    expected = f"got {text!r}; expected a whole number from {MIN_NICE} (the most precedence) to {MAX_NICE}"
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(expected) from None
    if not MIN_NICE <= value <= MAX_NICE:
        raise argparse.ArgumentTypeError(expected)
    return value


def _apply_nice(args: argparse.Namespace) -> None:
    """Before anything starts a thread: the niceness --nice asks for, or a clear refusal."""
    if args.nice is None:
        return
    from dyknow.priority import PriorityError, set_nice

    try:
        set_nice(args.nice)
    except PriorityError as error:
        raise UsageError(f"--nice: {error}") from None


def _stop_event() -> threading.Event:
    """An event SIGINT and SIGTERM set: install it before saying "ready", so that a signal sent
    as soon as the ready line is read stops the process cleanly instead of killing it."""
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def _wait_for(stop: threading.Event) -> None:
    while not stop.wait(0.5):
        pass


#: How long a manager may take to stop once asked (SIGINT or SIGTERM); past it, it exits at once.


#: How long a manager may take to stop once asked (SIGINT or SIGTERM); past it, it exits at once.
STOP_DEADLINE_S = 5.0


def _exit_by_deadline(what: str) -> None:
    """From now on, exit within :data:`STOP_DEADLINE_S` whatever the process is doing.

    The manager closes its units, services and session in a bounded time; this is the backstop
    for what no timeout reaches (a unit's C code holding the interpreter lock, say). It runs on
    faulthandler's own C thread, which needs no interpreter lock: it prints every thread's
    stack to stderr (what was stuck) and exits with status 1. A second signal exits at once.
    """
    import faulthandler

    faulthandler.dump_traceback_later(STOP_DEADLINE_S, exit=True)

    def again(signum: int, frame: object) -> None:
        print(f"dyknow: {what} stopped at once (a second signal)", file=sys.stderr, flush=True)
        os._exit(1)

    signal.signal(signal.SIGINT, again)
    signal.signal(signal.SIGTERM, again)


# How long a thread of a manager process keeps the interpreter lock while others wait for it
# (Python's default: 5 ms). A manager is a server: a service call or a message from another
# process waiting 5 ms for each turn adds up (with 32 clients calling at once, get_model's p99
# went from about 60 ms to under 50 with 1 ms; benchmarks/load.py).


MANAGER_SWITCH_INTERVAL_S = 0.001


def cmd_manager(args: argparse.Namespace) -> int:
    """run a manager until interrupted"""
    import faulthandler

    faulthandler.enable()  # (a crash in native code, Zenoh's or a DDS's, prints every thread's Python stack, not nothing)
    if hasattr(signal, "SIGUSR1"):  # kill -USR1 PID: every thread's stack on stderr, from C, even when the manager is stuck
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    sys.setswitchinterval(MANAGER_SWITCH_INTERVAL_S)
    _apply_nice(args)
    from dyknow.errors import DyKnowError
    from dyknow.manager import Manager
    from dyknow.manager.feeds import parse_feed
    from dyknow.security import Limits

    tls = tls_files(args)
    if args.router and (args.listen or args.connect):
        raise UsageError("--router: a manager behind a router dials only its router; give --router alone, or --listen/--connect without it")
    listen = args.listen or ([default_endpoint(tls)] if args.zenoh_config is None and not args.router else None)
    limits = Limits(
        max_request_bytes=args.max_request_bytes,
        max_expansions=args.max_expansions,
        max_units=args.max_units,
        max_message_bytes=args.max_message_bytes,
        max_expansion_bytes=args.max_expansion_bytes,
        max_ros2_message_bytes=args.max_ros2_message_bytes,
        max_formula_nodes=args.max_formula_nodes,
        max_window_ns=round(args.max_window * 1e9),
        max_monitor_cells=args.max_monitor_cells,
        max_monitor_nodes=args.max_monitor_nodes,
        max_library_bytes=args.max_library_bytes,
        max_metric_series=args.max_metric_series,
    )
    feeds = []
    for entry in args.measure_from:  # checked before anything starts
        name, equals, source = entry.partition("=")
        if not equals:
            raise UsageError(f"--measure-from {entry[:200]!r}: expected NAME=SOURCE[#FIELD], such as visibility=ros2dds:/water_visibility?type=std_msgs/msg/Float64#data")
        try:
            parse_feed(name, source)
        except DyKnowError as exc:
            raise UsageError(f"--measure-from {entry[:200]!r}: {exc}") from None
        feeds.append((name, source))
    with Manager(
        args.name,
        specs=args.specs,
        ontology=args.ontology,
        listen=listen,
        connect=args.connect,
        router=args.router,
        zenoh_config=args.zenoh_config,
        allow_sources=args.allow_source,
        code_paths=args.path,
        data_roots=args.data_root,
        limits=limits,
        tls=tls,
        acl=args.acl,
        host=args.host,
        lease_ms=args.lease_ms,
        federate=not args.alone,
        ros2_domain=args.ros2_domain,
        ros2_node=args.ros2_node,
        ros2_namespace=args.ros2_namespace,
        dds_config=Path(args.ros2_dds_config).read_text() if args.ros2_dds_config else None,
        diagnostics=args.diagnostics,
        client_grace_s=args.client_grace,
        max_lanes=args.max_lanes,
        overload_lag_s=args.overload_lag,
        **({"dwell_s": args.dwell} if args.dwell is not None else {}),
    ) as manager:
        for name, source in feeds:
            manager.measure_from(name, source)
        exposed = manager.exposed()
        if exposed:
            print(
                f"dyknow: warning: {'behind a router' if args.router else 'listening'} beyond this host without TLS "
                f"({', '.join(exposed)}): anyone who reaches {'the router' if args.router else 'it'} may call its services; "
                "use --tls-ca/--tls-cert/--tls-key and --acl (see docs/howto/security.md)",
                file=sys.stderr,
                flush=True,
            )
        exporter = None
        if args.metrics_port is not None:
            from dyknow.metrics import MetricsExporter
            from dyknow.security import is_loopback

            exporter = MetricsExporter(manager.metrics, args.metrics_port, host=args.metrics_host)
            if not is_loopback(args.metrics_host):
                print(f"dyknow: warning: serving metrics on {exporter.url}, beyond this host: they name every unit and key, "
                      "and the endpoint has no access control", file=sys.stderr, flush=True)  # fmt: skip
        # What start-up built lives as long as the manager: keep it out of the garbage
        # collector's way, so collections stay short while the robot runs.
        gc.collect()
        gc.freeze()
        endpoints = manager.endpoints
        stop = _stop_event()
        metrics = f"; metrics on {exporter.url}" if exporter is not None else ""
        where = f"on {', '.join(endpoints)}" if endpoints else f"behind {', '.join(args.router)}" if args.router else "on (no listener)"
        report_result(
            args,
            {"event": "ready", "manager": args.name, "host": manager.host, "endpoints": endpoints, "specs": len(manager.library),
             **({"router": args.router} if args.router else {}), **({"metrics": exporter.url} if exporter is not None else {})},
            f"dyknow manager {args.name!r} ready {where} with {len(manager.library)} specs{metrics}; Ctrl-C to stop",
        )  # fmt: skip
        _wait_for(stop)
        _exit_by_deadline(f"manager {args.name!r}")
        if exporter is not None:
            exporter.close()
    if not args.json:
        print(f"dyknow manager {args.name!r} stopped", flush=True)
    return 0


def cmd_ui(args: argparse.Namespace) -> int:
    """serve the interactive tool in the browser: the live graph of every manager and its control panel"""
    from dyknow.ui import run_ui

    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port: got {args.port}; expected 0 to 65535")

    recorded = None
    if args.requirements is not None or args.mcap is not None:
        recorded = _recorded_timeline(args)

    def ready(url: str) -> None:
        report_result(args, {"event": "ready", "url": url}, f"dyknow ui: open {url} (Ctrl-C to stop)")
        sys.stdout.flush()

    with open_client(args) as client:
        return run_ui(client, host=args.host, port=args.port, token=args.token, ready=ready, recorded=recorded)


def _recorded_timeline(args: argparse.Namespace) -> dict[str, Any]:
    """``--requirements F --mcap M``: the requirements checked over the recording, as the page's rows."""
    from dyknow.ontology import Ontology
    from dyknow.reasoning.requirements import check_recording, load_requirements
    from dyknow.ui.server import recorded_timeline

    if args.requirements is None or args.mcap is None:
        raise UsageError("--requirements and --mcap go together: the requirements file, and the recording to check it over")
    ontology = Ontology.load(args.ontology) if args.ontology else None
    results = check_recording(load_requirements(args.requirements), args.mcap, individuals=ontology.individuals if ontology is not None else None,
                              limits=read_limits(args))  # fmt: skip
    return recorded_timeline(results)


def cmd_foxglove(args: argparse.Namespace) -> int:
    """serve streams live to Foxglove or Lichtblick over the Foxglove WebSocket protocol (images, JSON)"""
    from dyknow.foxglove import FOXGLOVE_ORIGINS, run_bridge
    from dyknow.security import is_loopback

    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port: got {args.port}; expected 0 to 65535")
    if not is_loopback(args.host):
        print(f"dyknow: warning: serving on {args.host}, beyond this host: the Foxglove WebSocket protocol has no access control, "
              "so anyone who reaches the port sees every stream served", file=sys.stderr, flush=True)  # fmt: skip

    def ready(url: str) -> None:
        report_result(args, {"event": "ready", "url": url}, f"dyknow foxglove: open {url} in Foxglove or Lichtblick (Ctrl-C to stop)")
        sys.stdout.flush()

    with open_client(args) as client:
        origins = [*FOXGLOVE_ORIGINS, *args.allow_origin]
        return run_bridge(client, host=args.host, port=args.port, keyexprs=args.keyexprs, ready=ready, origins=origins)


#: How long ``dyknow router`` waits for its ``--connect`` routers before its ready line, which names
#: those linked by then (a router whose peer is not up yet says so, and logs the link when it comes).
ROUTER_LINK_WAIT_S = 2.0

#: The router's own lines: each link to another router going (a warning) and coming back. Shown
#: unless DYKNOW_LOG says otherwise (Python's default level would hide the links coming back).
router_log = logging.getLogger("dyknow.router")


def _router_named(link: RouterLink) -> str:
    return f"router {link.peer} ({link.address or 'address unknown'}, zid {link.zid})"


def _link_json(link: RouterLink) -> dict[str, object]:
    return {"peer": link.peer, "zid": link.zid, "address": link.address}


def _routine(link: RouterLink, access: AccessControl | None) -> bool:
    """Whether a Zenoh router's link is routine, as a client's is: with --acl, a peer whose
    certificate has another role than router (a manager that linked as a Zenoh router)."""
    return access is not None and link.name is not None and access.role_of(link.name) not in (None, "router")


def _report_router_link(args: argparse.Namespace, link: RouterLink, access: AccessControl | None) -> None:
    """A link to another router up or down: a log line (stderr) and, with --json, an event on
    stdout; a routine one (:func:`_routine`) at debug level only."""
    if _routine(link, access):
        router_log.debug("link to %s %s", _router_named(link), "up" if link.up else "down")
        return
    if link.up:
        again = "" if link.down_ns is None else f" again after {link.down_ns / 1e9:.1f} s down"
        router_log.info("link to %s up%s", _router_named(link), again)
    else:
        dialled = link.address in args.connect
        router_log.warning("link to %s down: nothing passes between the routers until it is back%s", _router_named(link),
                           "; dialling it again" if dialled else "")  # fmt: skip
    if args.json:
        from dyknow.cli.common import print_json

        down = {"down_s": round(link.down_ns / 1e9, 3)} if link.up and link.down_ns is not None else {}
        print_json({"event": "link-up" if link.up else "link-down", **_link_json(link), **down})


def cmd_router(args: argparse.Namespace) -> int:
    """run a Zenoh router: a rendezvous point managers and clients connect to (it runs no units)"""
    _apply_nice(args)
    from dyknow.transport import Session, make_config

    tls = tls_files(args)
    access = None
    if args.acl is not None:
        from dyknow.access import AccessControl
        from dyknow.errors import AccessError

        if tls is None:
            raise AccessError("roles (--acl) are given by certificate, and the router has none", where="dyknow router",
                              expected="--tls-ca, --tls-cert and --tls-key with --acl")  # fmt: skip
        access = AccessControl.load(args.acl)
    listen = args.listen or [default_endpoint(tls)]
    if args.zenoh_config is None:  # (Zenoh would say only "Missing TLS private key")
        from dyknow.reach import check_endpoints

        check_endpoints(listen, tls, option="--listen", who="the router")
        check_endpoints(args.connect, tls, option="--connect", who="the router")
    config = make_config(
        listen=listen, connect=args.connect, config_file=args.zenoh_config, tls=tls, access=access, mode="router", lease_ms=args.lease_ms,
        max_sessions=args.max_sessions, shared_memory=False,
    )
    if "DYKNOW_LOG" not in os.environ:
        router_log.setLevel(logging.INFO)
    changes: queue.SimpleQueue[RouterLink] = queue.SimpleQueue()
    with Session(config) as session, session.watch_routers(changes.put) as routers:
        endpoints = session.endpoints()
        routers.wait_linked(len(args.connect), ROUTER_LINK_WAIT_S)
        while not changes.empty():  # what the ready line says (taken after: a change since is said twice, never lost)
            changes.get()
        linked = [link for link in routers.linked() if not _routine(link, access)]
        stop = _stop_event()
        where = f"on {', '.join(endpoints)}"
        named = "linked to " + ", ".join(map(_router_named, linked)) if linked else "not linked yet"
        if args.connect:
            where += f"; dialling {', '.join(args.connect)}: {named}"
        elif linked:
            where += f"; {named}"
        report_result(
            args,
            {"event": "ready", "router": session.zid, "endpoints": endpoints, "connect": args.connect,
             "routers": [_link_json(link) for link in linked]},
            f"dyknow router ready {where}; Ctrl-C to stop",
        )  # fmt: skip
        while not stop.is_set():
            try:
                link = changes.get(timeout=0.5)
            except queue.Empty:
                continue
            _report_router_link(args, link, access)
        _exit_by_deadline("router")
    if not args.json:
        print("dyknow router stopped", flush=True)
    return 0


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""
    zenoh_options = cmds.zenoh_options
    lease_option = cmds.lease_option

    def nice_option(p: argparse.ArgumentParser, who: str) -> None:
        p.add_argument("--nice", type=_nice, metavar="N",
                       help=f"the {who}'s scheduling niceness, -20 to 19 (default: inherited, usually 0): on a CPU shared with other heavy "
                            "work, a negative value (-20 the most precedence, -10 less) keeps its messages on time; needs CAP_SYS_NICE (root) or RLIMIT_NICE; "
                            "see docs/concepts/execution.md")  # fmt: skip

    limit_options = cmds.limit_options

    def manager_options(p: argparse.ArgumentParser) -> None:
        from dyknow.executor import DEFAULT_MAX_LANES
        from dyknow.holders import DEFAULT_GRACE_S
        from dyknow.overload import DEFAULT_LAG_BUDGET_S
        from dyknow.transport import DEFAULT_ENDPOINT

        p.add_argument("--name", default=DEFAULT_MANAGER, help=f"the manager's name (default {DEFAULT_MANAGER})")
        p.add_argument("--specs", action="extend", nargs="+", default=[], type=shipped, metavar="PATH",
                       help="spec files or directories of .xml specs (@shipped: dyknow's own; dyknow paths)")  # fmt: skip
        p.add_argument("--ontology", action="extend", nargs="+", default=[], type=shipped, metavar="FILE",
                       help="ontology files (Turtle or RDF/XML; @shipped/dyknow.ttl: the example ontology)")  # fmt: skip
        p.add_argument(
            "--listen",
            action="append",
            default=[],
            metavar="ENDPOINT",
            help=f"Zenoh endpoint to listen on (default {DEFAULT_ENDPOINT}; tls/... with TLS)",
        )
        zenoh_options(p, connect_help="Zenoh endpoint to connect to (repeatable)")
        p.add_argument(
            "--router",
            action="append",
            default=[],
            metavar="ENDPOINT",
            help="sit behind this Zenoh router (dyknow router), as in a fleet: dial it alone, hold that one link, listen on nothing; "
            "repeat for standbys, dialled in turn when the link is lost (not with --listen or --connect)",
        )
        p.add_argument("--allow-source", action="append", default=[], metavar="PATTERN",
                       help="also load units of these modules (mypkg, mypkg.units*, mypkg.units:Class); repeatable")  # fmt: skip
        p.add_argument("--path", action="append", default=[], metavar="DIR",
                       help="a folder to find units' modules in, besides the spec files' own folders (repeatable)")  # fmt: skip
        p.add_argument("--data-root", action="append", default=[], metavar="DIR",
                       help="folders whose files remote callers may name in file params (reads also: the spec folders); repeatable")  # fmt: skip
        p.add_argument(
            "--acl",
            metavar="FILE",
            help="roles by certificate common name (JSON5: { roles: { viewer: [...], operator: [...], admin: [...], manager: [...], "
            "router: [...], ROLE: [...] }, define: { ROLE: { like: viewer, calls: [SERVICE, ...], publish: [...], subscribe: [...] } } }); "
            "every call must then be signed by its caller (dyknow clients with --tls-* do)",
        )
        p.add_argument(
            "--max-request-bytes", type=positive_int, default=1 << 20, metavar="N", help="refuse larger service requests (default 1 MiB)"
        )
        p.add_argument("--max-units", type=positive_int, default=1000, metavar="N", help="refuse spawns beyond this many units (default 1000)")
        p.add_argument("--max-message-bytes", type=positive_int, default=64 << 20, metavar="N",
                       help="drop larger messages (data or calls) while they arrive, before they take memory (default 64 MiB)")  # fmt: skip
        p.add_argument("--max-expansion-bytes", type=positive_int, default=16 << 20, metavar="N",
                       help="refuse a spec added remotely whose expansions would hold more text (default 16 MiB)")  # fmt: skip
        p.add_argument("--max-formula-nodes", type=positive_int, default=500, metavar="N",
                       help="refuse a temporal formula with more atoms, constants and operators (default 500)")  # fmt: skip
        p.add_argument("--max-window", type=seconds, default=86400.0, metavar="S",
                       help="refuse a formula whose interval bounds, or how far ahead it looks, pass this (default 86400: a day)")  # fmt: skip
        p.add_argument("--max-monitor-cells", type=positive_int, default=2_000_000, metavar="N",
                       help="what the formula monitors keep together, in cells of 12-73 bytes (250 at most); past their share they "
                            "give old states up (default 2,000,000)")  # fmt: skip
        p.add_argument("--max-monitor-nodes", type=positive_int, default=20_000, metavar="N",
                       help="refuse a monitor or requirement past this many formula nodes in all (default 20,000)")  # fmt: skip
        p.add_argument("--max-library-bytes", type=positive_int, default=8 << 20, metavar="N",
                       help="refuse specs that would make the library larger, as its summary carries it (default 8 MiB; peers take 16)")  # fmt: skip
        limit_options(p)
        p.add_argument("--max-lanes", type=_lanes, default=DEFAULT_MAX_LANES, metavar="N",
                       help=f"the most threads units run on, whatever the load (default {DEFAULT_MAX_LANES}; at least 2): past it, slow "
                            "units share threads (units that ask for a thread of their own aside)")  # fmt: skip
        p.add_argument("--overload-lag", type=_lag, default=DEFAULT_LAG_BUDGET_S, metavar="S",
                       help=f"how long a message may wait for its unit's turn before the manager counts as overloaded and sheds its "
                            f"least important units (default {DEFAULT_LAG_BUDGET_S:g})")  # fmt: skip
        nice_option(p, "manager")
        p.add_argument("--host", metavar="NAME", help="the machine it runs on, for measurements addressed by host (default: the host name)")
        p.add_argument("--client-grace", type=seconds, default=DEFAULT_GRACE_S, metavar="S",
                       help=f"how long a client's requests outlive it once it is gone: closed, crashed or cut off (default {DEFAULT_GRACE_S:g})")  # fmt: skip
        p.add_argument("--dwell", type=seconds, metavar="S",
                       help="how long a request keeps a configuration before switching to a better one (default 2)")  # fmt: skip
        p.add_argument("--metrics-port", type=int, metavar="PORT",
                       help="serve the manager's figures to Prometheus on http://--metrics-host:PORT/metrics (0: any free port; "
                            "default: not served)")  # fmt: skip
        p.add_argument("--metrics-host", default="127.0.0.1", metavar="ADDR",
                       help="the address --metrics-port serves on (default 127.0.0.1; the figures name every unit and key)")  # fmt: skip
        p.add_argument("--max-metric-series", type=positive_int, default=100_000, metavar="N",
                       help="the most series a scrape of --metrics-port serves (default 100,000; a unit takes 2, 3 per output "
                            "and 37 per input): the latest spawned units past it are left out, logged and counted")  # fmt: skip
        p.add_argument("--alone", action="store_true", help="do not plan with the other managers on the network, nor announce this one")
        lease_option(p)
        cmds.ros2_domain_option(p)
        p.add_argument("--ros2-node", metavar="NAME", help="the manager's ROS 2 node name (default: its name; declared at start when given)")
        p.add_argument("--ros2-namespace", default="/", metavar="NS", help="the ROS 2 node's namespace (default /)")
        p.add_argument("--diagnostics", choices=("ros2", "ros2dds"), default=None,
                       help="publish the health of its requirements, monitors, requests and managed nodes on ROS 2's /diagnostics "
                            "(diagnostic_msgs/DiagnosticArray, once a second and on changes): ros2 on its ROS 2 node (rmw_zenoh), "
                            "ros2dds on its DDS participant (default: not published)")  # fmt: skip
        p.add_argument("--ros2-dds-config", metavar="FILE",
                       help="Cyclone DDS XML for ros2dds: bindings (default: discovery on loopback only)")  # fmt: skip
        p.add_argument("--measure-from", action="append", default=[], metavar="NAME=SOURCE[#FIELD]",
                       help="take measure NAME (which constraints read) from a stream: a ros2:/ros2dds: topic or a Zenoh key, "
                            "and a field path into its samples, such as visibility=ros2dds:/water_visibility?type=std_msgs/msg/Float64#data "
                            "(repeatable)")  # fmt: skip
        p.add_argument("--max-ros2-message-bytes", type=positive_int, default=16 << 20, metavar="N",
                       help="drop a larger ROS 2 message on a ros2:/ros2dds: input before decoding it, unless its binding says "
                            "max_bytes= (default 16 MiB; untyped inputs: at most 1 MiB)")  # fmt: skip

    cmds.command("manager", cmd_manager, manager_options)

    def ui_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--host", default="127.0.0.1", help="the address to serve on (default 127.0.0.1; elsewhere a token is required)")
        p.add_argument("--port", type=int, default=8321, help="the port to serve on (default 8321; 0: any free port)")
        p.add_argument("--token", help="the access token the page must carry (default: none on loopback, a new one elsewhere)")
        p.add_argument("--requirements", metavar="REQUIREMENTS.toml",
                       help="with --mcap: also show the verdict timeline of these requirements over that recording (as dyknow check judges it)")  # fmt: skip
        p.add_argument("--mcap", metavar="FILE", help="the recording --requirements are checked over")
        p.add_argument("--ontology", action="extend", nargs="+", default=[], type=shipped, metavar="FILE",
                       help="ontologies whose individuals a requirement's forall ranges over")  # fmt: skip
        cmds.mcap_limit_options(p)

    cmds.command("ui", cmd_ui, ui_options, client=True)

    def foxglove_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("keyexprs", nargs="*", metavar="KEYEXPR", help="key expressions to serve (default dyknow/**: every stream)")
        p.add_argument("--host", default="127.0.0.1", help="the address to serve on (default 127.0.0.1; the protocol has no access control)")
        p.add_argument("--port", type=int, default=8765, help="the port to serve on (default 8765; 0: any free port)")
        p.add_argument("--allow-origin", action="append", default=[], metavar="URL",
                       help="a web page origin that may connect besides the Foxglove web app (https://app.foxglove.dev), "
                            "e.g. a self-hosted Lichtblick; repeatable (desktop apps send no origin and are always served)")  # fmt: skip

    cmds.command("foxglove", cmd_foxglove, foxglove_options, client=True)

    def router_options(p: argparse.ArgumentParser) -> None:
        from dyknow.transport import DEFAULT_ENDPOINT, ROUTER_MAX_SESSIONS

        p.add_argument(
            "--listen", action="append", default=[], metavar="ENDPOINT", help=f"Zenoh endpoint to listen on (default {DEFAULT_ENDPOINT})"
        )
        zenoh_options(p, connect_help="another router to connect to (repeatable)")
        p.add_argument(
            "--acl", metavar="FILE", help="enforce these roles at the router's links (the managers' ACL file; see dyknow manager --acl)"
        )
        p.add_argument(
            "--max-sessions", type=positive_int, metavar="N",
            help=f"how many managers and clients may link to the router at once (default {ROUTER_MAX_SESSIONS:,}, or what --zenoh-config says; "
            "Zenoh's own is 1,000)",
        )  # fmt: skip
        nice_option(p, "router")
        lease_option(p)

    cmds.command("router", cmd_router, router_options)
