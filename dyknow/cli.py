"""The ``dyknow`` command line.

Thin by design: every subcommand is a small function over the public API. ``--json`` gives
machine-readable output wherever a command prints data. Errors are one line on stderr and a
non-zero exit, never a traceback (set ``DYKNOW_DEBUG=1`` to see one).

Commands::

    dyknow manager --name NAME [--specs PATH ...] [--listen ENDPOINT] [--zenoh-config FILE]
    dyknow demo [--duration S]
    dyknow validate PATH ... [--ontology FILE ...]  (offline)
    dyknow expand PATH ... [--json]                (offline)
    dyknow plan --specs PATH ... [--ontology FILE ...] --request TAG [--unavailable LABEL ...]
                [--measure NAME=VALUE ...] --json  (offline)
    dyknow spawn LABEL NAME [--protect] [--param K=V ...] [--bind PORT=KEY ...]
    dyknow destroy NAME
    dyknow model
    dyknow config get NAME | dyknow config set NAME PORT=KEY ...
    dyknow stats NAME
    dyknow add-spec FILE | dyknow remove-spec LABEL
    dyknow echo KEYEXPR [--count N] | dyknow echo ros2:/TOPIC | ros2dds:/TOPIC?type=T [--ros2-domain N]
    dyknow ros2 list [--dds] [--ros2-domain N]
    dyknow foxglove [KEYEXPR ...] [--host ADDR] [--port N]
    dyknow request TAG [--standby warm] | dyknow release KEY | dyknow measure NAME=VALUE ... | dyknow adaptations
    dyknow record KEYEXPR ... -o FILE.mcap [--duration S] [--max-messages N] [--compression zstd|lz4|none]
    dyknow replay FILE.mcap [--rate X] [--loop] [--start S] [--end S] [--topics T ...] [--remap FROM=TO ...]
    dyknow mcap cat FILE [--topics T ...] [--json] | dyknow mcap info FILE [--json]   (offline)

Client commands reach a manager with ``--connect ENDPOINT`` (default tcp/127.0.0.1:7447) and
``--manager NAME`` (default ``dyknow``).
"""

from __future__ import annotations

import argparse
import base64
import gc
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dyknow.client import Client
from dyknow.errors import DyKnowError, SpecError
from dyknow.message import Message, describe_payload
from dyknow.model import STANDBY_MODES
from dyknow.spec import DEFAULT_MAX_EXPANSIONS, load_specs
from dyknow.transport import DEFAULT_ENDPOINT

__all__ = ["main"]

DEFAULT_MANAGER = "dyknow"


class _Usage(Exception):
    """A command line that parses but makes no sense (exit code 2)."""


def _out(data: Any) -> None:
    sys.stdout.write(json.dumps(data, indent=None, separators=(",", ":")) + "\n")
    sys.stdout.flush()


def _report(args: argparse.Namespace, data: Any, text: str | Iterable[str] | Callable[[], Iterable[str]]) -> None:
    """How every command ends: ``data`` as one JSON line with ``--json``, else ``text`` for people."""
    if args.json:
        _out(data)
        return
    lines = text() if callable(text) else [text] if isinstance(text, str) else text
    for line in lines:
        print(line, flush=True)


def _pairs(items: Sequence[str], what: str) -> dict[str, str]:
    result: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise _Usage(f"{what}: got {item!r}; expected NAME=VALUE")
        result[name] = value
    return result


# ---------------------------------------------------------------------- offline commands


def _ontology(paths: Sequence[str]) -> Any:
    from dyknow.ontology import Ontology

    return Ontology.load(paths) if paths else None


def _load(args: argparse.Namespace) -> list[Any]:
    ontology = _ontology(getattr(args, "ontology", []))
    return load_specs(args.paths, individuals=ontology.individuals if ontology is not None else None, max_expansions=args.max_expansions)


def _value(text: str) -> float | str:
    try:
        return float(text)
    except ValueError:
        return text


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a positive whole number")
    return value


def _names(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected names separated by commas, such as manager,operator")
    return names


def cmd_certs(args: argparse.Namespace) -> int:
    """write a development CA and certificates signed by it, for TLS with mutual authentication"""
    from dyknow.certs import write_dev_certs

    written = write_dev_certs(args.dir, args.names, hosts=args.hosts)
    _report(args, {"written": [str(p) for p in written]}, [f"wrote {p}" for p in written])
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    """check spec files; exit 1 with one PATH:LINE: message per error"""
    try:
        specs = _load(args)
    except SpecError as exc:
        for issue in exc.issues:
            print(str(issue), file=sys.stderr)
        if args.json:
            _out({"valid": False, "errors": [str(i) for i in exc.issues], "issues": [i.to_dict() for i in exc.issues]})
        return 1
    files = len({s.path for s in specs})
    _report(
        args,
        {"valid": True, "transformations": len(specs), "files": files},
        f"ok: {len(specs)} transformations in {files} file{'s' if files != 1 else ''}",
    )
    return 0


def cmd_expand(args: argparse.Namespace) -> int:
    """print every transformation after template expansion"""
    specs = _load(args)

    def text() -> Iterable[str]:
        for s in specs:
            yield f"{s.label}  ({s.source})  {s.location}"
            for p in s.ports:
                tags = ", ".join(s.tags_for(p.name))
                yield f"    {p.direction:>3} {p.name}" + (f"  [{tags}]" if tags else "")
            for name, value in s.param_values().items():
                yield f"    param {name} = {value!r}"

    data = [
        {
            "label": s.label,
            "source": s.source,
            "params": s.param_values(),
            "ports": [{"name": p.name, "direction": p.direction} for p in s.ports],
            "tags": [{"port": t.port, "tag": t.tag} for t in s.tags],
        }
        for s in specs
    ]
    _report(args, data, text)
    return 0


def cmd_plan(args: argparse.Namespace) -> int:
    """plan a configuration for a tag, offline; exit 1 with the explanation when none exists"""
    from dyknow.errors import PlanningError
    from dyknow.planner import plan

    ontology = _ontology(args.ontology)
    specs = load_specs(args.specs, individuals=ontology.individuals if ontology is not None else None, max_expansions=args.max_expansions)
    measurements = {k: _value(v) for k, v in _pairs(args.measure, "--measure").items()}
    individuals = ontology.individuals if ontology is not None else None
    peers: dict[str, list[Any]] = {}
    for name, path in ((n, p) for item in args.peer for n, p in _pairs([item], "--peer").items()):
        peers.setdefault(name, []).extend(load_specs([path], individuals=individuals, max_expansions=args.max_expansions))
    try:
        result = plan(args.request, specs, ontology, (), set(args.unavailable), measurements, manager=args.manager, peers=peers)
    except PlanningError as exc:
        if args.json:
            _out({"request": args.request, "error": str(exc), "rejection": exc.rejection.to_dict() if exc.rejection else None})
        print(str(exc), file=sys.stderr)
        return 1

    def text() -> Iterable[str]:
        yield f"{result.request}: {len(result.units)} units, output {result.output_unit}.{result.output_port} on {result.output_key}"
        for unit in result.units:
            yield f"  {'new ' if unit.new else 'reuse'} {unit.name} ({unit.label})" + (f" on {unit.manager}" if unit.remote else "")
        for c in result.connections:
            yield f"  {c.source} -> {c.target}  ({c.key})"

    _report(args, result.to_dict(), text)
    return 0


# ---------------------------------------------------------------------- the manager


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
    sys.setswitchinterval(MANAGER_SWITCH_INTERVAL_S)
    from dyknow.manager import Manager
    from dyknow.security import Limits

    tls = _tls(args)
    listen = args.listen or ([_default_endpoint(tls)] if args.zenoh_config is None else None)
    limits = Limits(
        max_request_bytes=args.max_request_bytes,
        max_expansions=args.max_expansions,
        max_units=args.max_units,
        max_message_bytes=args.max_message_bytes,
        max_expansion_bytes=args.max_expansion_bytes,
    )
    with Manager(
        args.name,
        specs=args.specs,
        ontology=args.ontology,
        listen=listen,
        connect=args.connect,
        zenoh_config=args.zenoh_config,
        allow_sources=args.allow_source,
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
        **({"dwell_s": args.dwell} if args.dwell is not None else {}),
    ) as manager:
        exposed = manager.exposed()
        if exposed:
            print(
                f"dyknow: warning: listening beyond this host without TLS ({', '.join(exposed)}): anyone who reaches it may "
                "call its services; use --tls-ca/--tls-cert/--tls-key and --acl (see the README's Security section)",
                file=sys.stderr,
                flush=True,
            )
        # What start-up built lives as long as the manager: keep it out of the garbage
        # collector's way, so collections stay short while the robot runs.
        gc.collect()
        gc.freeze()
        endpoints = manager.endpoints
        stop = _stop_event()
        _report(
            args,
            {"event": "ready", "manager": args.name, "host": manager.host, "endpoints": endpoints, "specs": len(manager.library)},
            f"dyknow manager {args.name!r} ready on {', '.join(endpoints) or '(no listener)'} with {len(manager.library)} specs; Ctrl-C to stop",
        )
        _wait_for(stop)
        _exit_by_deadline(f"manager {args.name!r}")
    if not args.json:
        print(f"dyknow manager {args.name!r} stopped", flush=True)
    return 0


# ---------------------------------------------------------------------- client commands


def _tls(args: argparse.Namespace) -> Any:
    from dyknow.access import TlsFiles

    return TlsFiles.from_options(args.tls_ca, args.tls_cert, args.tls_key)


def _default_endpoint(tls: Any) -> str:
    return DEFAULT_ENDPOINT.replace("tcp/", "tls/", 1) if tls is not None else DEFAULT_ENDPOINT


def _client(args: argparse.Namespace) -> Client:
    tls = _tls(args)
    connect = args.connect or ([_default_endpoint(tls)] if args.zenoh_config is None else [])
    return Client(args.manager, connect=connect, zenoh_config=args.zenoh_config, timeout_s=args.timeout, tls=tls)


def cmd_spawn(args: argparse.Namespace) -> int:
    """spawn a unit on a manager"""
    params, bindings = _pairs(args.param, "--param"), _pairs(args.bind, "--bind")  # usage first, then connect
    with _client(args) as client:
        info = client.spawn(args.label, args.name, protected=args.protect, params=params, bindings=bindings)

    def text() -> Iterable[str]:
        yield f"spawned {info['name']} ({info['label']}): {info['state']}" + (" [protected]" if info["protected"] else "")
        if info.get("error"):
            yield f"  error: {info['error']}"

    _report(args, info, text)
    return 1 if info["state"] == "failed" else 0


def cmd_destroy(args: argparse.Namespace) -> int:
    """destroy a unit"""
    with _client(args) as client:
        client.destroy(args.name, force=args.force)
    _report(args, {"destroyed": args.name}, f"destroyed {args.name}")
    return 0


def cmd_model(args: argparse.Namespace) -> int:
    """show the manager's units and specs (--all: of every manager reachable)"""
    with _client(args) as client:
        data = client.get_federated_model() if args.all else client.get_model()
    models = data["managers"] if args.all else [data]

    def text() -> Iterable[str]:
        if args.all and not models:
            yield "no manager reachable"
        for model in models:
            yield f"manager {model['manager']}: {len(model['units'])} units, {len(model['specs'])} specs"
            for unit in model["units"]:
                yield f"  {unit['name']} ({unit['label']}) {unit['state']}" + (" [protected]" if unit["protected"] else "")
                for port, key in unit["bindings"].items():
                    yield f"      {port} -> {key}"
                if unit.get("error"):
                    yield f"      error: {unit['error']}"
            for request in model.get("requests", []):
                yield f"  request {request['tag']} on {request['key']}: {request['state']}"
            if model["specs"]:
                yield "specs: " + ", ".join(s["label"] for s in model["specs"])

    _report(args, data, text)
    return 0


def cmd_managers(args: argparse.Namespace) -> int:
    """list every manager reachable: host, library size, units, requests, and its clock's offset as --manager estimates it"""
    with _client(args) as client:
        managers = client.managers(timeout_s=min(args.timeout, 2.0))
        try:  # (a --manager that is not there would hold the list up for --timeout)
            clocks = client.clocks() if any(m["manager"] == args.manager for m in managers) else {}
        except DyKnowError as exc:  # the other columns stand without it
            logging.getLogger(__name__).debug("no clock offsets from %r: %s", args.manager, exc)
            clocks = {}
    for m in managers:  # the offset of each manager's clock from --manager's (None: not known to it yet)
        found = clocks.get(m["manager"])
        m["clock"] = None if found is None else {"offset_us": found.offset_ns / 1000, "uncertainty_us": found.uncertainty_ns / 1000}

    def text() -> Iterable[str]:
        if not managers:
            yield "no manager reachable"
        for m in managers:
            clock = "clock unknown" if m["clock"] is None else f"clock {m['clock']['offset_us']:+.1f} us +/- {m['clock']['uncertainty_us']:.1f}"
            yield f"{m['manager']:<20} host {m['host']:<20} {m['specs']:>5} specs {m['units']:>5} units {m['requests']:>4} requests  {clock}"

    _report(args, managers, text)
    return 0


def cmd_ui(args: argparse.Namespace) -> int:
    """serve the interactive tool in the browser: the live graph of every manager and its control panel"""
    from dyknow.ui import run_ui

    if not 0 <= args.port <= 65535:
        raise _Usage(f"--port: got {args.port}; expected 0 to 65535")

    def ready(url: str) -> None:
        _report(args, {"event": "ready", "url": url}, f"dyknow ui: open {url} (Ctrl-C to stop)")
        sys.stdout.flush()

    with _client(args) as client:
        return run_ui(client, host=args.host, port=args.port, token=args.token, ready=ready)


def cmd_foxglove(args: argparse.Namespace) -> int:
    """serve streams live to Foxglove or Lichtblick over the Foxglove WebSocket protocol (images, JSON)"""
    from dyknow.foxglove import FOXGLOVE_ORIGINS, run_bridge
    from dyknow.security import is_loopback

    if not 0 <= args.port <= 65535:
        raise _Usage(f"--port: got {args.port}; expected 0 to 65535")
    if not is_loopback(args.host):
        print(f"dyknow: warning: serving on {args.host}, beyond this host: the Foxglove WebSocket protocol has no access control, "
              "so anyone who reaches the port sees every stream served", file=sys.stderr, flush=True)  # fmt: skip

    def ready(url: str) -> None:
        _report(args, {"event": "ready", "url": url}, f"dyknow foxglove: open {url} in Foxglove or Lichtblick (Ctrl-C to stop)")
        sys.stdout.flush()

    with _client(args) as client:
        origins = [*FOXGLOVE_ORIGINS, *args.allow_origin]
        return run_bridge(client, host=args.host, port=args.port, keyexprs=args.keyexprs, ready=ready, origins=origins)


def cmd_router(args: argparse.Namespace) -> int:
    """run a Zenoh router: a rendezvous point managers and clients connect to (it runs no units)"""
    from dyknow.transport import Session, make_config

    tls = _tls(args)
    access = None
    if args.acl is not None:
        from dyknow.access import AccessControl
        from dyknow.errors import AccessError

        if tls is None:
            raise AccessError("roles (--acl) are given by certificate, and the router has none", where="dyknow router",
                              expected="--tls-ca, --tls-cert and --tls-key with --acl")  # fmt: skip
        access = AccessControl.load(args.acl)
    listen = args.listen or [_default_endpoint(tls)]
    config = make_config(
        listen=listen, connect=args.connect, config_file=args.zenoh_config, tls=tls, access=access, mode="router", lease_ms=args.lease_ms
    )
    with Session(config) as session:
        endpoints = session.endpoints()
        stop = _stop_event()
        _report(
            args,
            {"event": "ready", "router": session.zid, "endpoints": endpoints},
            f"dyknow router ready on {', '.join(endpoints)}; Ctrl-C to stop",
        )
        _wait_for(stop)
        _exit_by_deadline("router")
    if not args.json:
        print("dyknow router stopped", flush=True)
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    """get or set a unit's port bindings"""
    if args.action == "get" and args.bindings:  # usage first, then connect
        raise _Usage("config get takes no PORT=KEY pairs; did you mean 'config set'?")
    if args.action != "get" and not args.bindings:
        raise _Usage("config set needs at least one PORT=KEY pair")
    changes = _pairs(args.bindings, "config set") if args.action != "get" else {}
    with _client(args) as client:
        config = client.get_config(args.name) if args.action == "get" else client.set_config(args.name, changes)
    _report(args, config, [f"{port} -> {key}" for port, key in config.items()])
    return 0


def cmd_stats(args: argparse.Namespace) -> int:
    """show a unit's statistics"""
    with _client(args) as client:
        stats = client.get_statistics(args.name)

    def text() -> Iterable[str]:
        yield (
            f"{stats['name']} ({stats['label']}) {stats['state']}: up {stats['uptime_s']:.1f} s, "
            f"{stats['reconfigurations']} reconfigurations, {stats['executor']}"
        )
        for port, p in stats["ports"].items():
            line = f"  {p['direction']:>3} {port} ({p['key']}): {p['messages']} msgs, {p['bytes']} B, {p['dropped']} dropped"
            if p["direction"] == "in" and p["latency"]["count"]:
                lat, hop = p["latency"], p["hop"]
                line += f"; latency p50 {lat['p50_us']:.1f} µs p99 {lat['p99_us']:.1f} µs; hop p50 {hop['p50_us']:.1f} µs p99 {hop['p99_us']:.1f} µs"
            yield line
        if stats.get("error"):
            yield f"  error: {stats['error']}"

    _report(args, stats, text)
    return 0


def cmd_add_spec(args: argparse.Namespace) -> int:
    """add the transformations of a spec file (or - for standard input) to the manager"""
    source = sys.stdin.read() if args.file == "-" else args.file
    if args.file == "-" and not source.lstrip().startswith("<"):
        raise _Usage("add-spec -: standard input holds no XML; expected a spec such as <transformation>...")
    with _client(args) as client:
        labels = client.add_transformation(source)
    _report(args, {"labels": labels}, "added " + ", ".join(labels))
    return 0


def cmd_remove_spec(args: argparse.Namespace) -> int:
    """remove a transformation from the manager's library"""
    with _client(args) as client:
        removed = client.remove_transformation(args.label)
    text = f"removed {args.label}" if removed else f"no spec labelled {args.label!r}; nothing removed"
    _report(args, {"label": args.label, "removed": removed}, text)
    return 0


def cmd_request(args: argparse.Namespace) -> int:
    """ask a manager for a stream by tag; prints its key"""
    with _client(args) as client:
        key = client.request(args.tag, standby=args.standby, require=args.require)
    _report(args, {"request": args.tag, "key": key, "standby": args.standby or "none", "require": args.require}, key)
    return 0


def cmd_release(args: argparse.Namespace) -> int:
    """give back a requested stream"""
    with _client(args) as client:
        client.release(args.key)
    _report(args, {"released": args.key}, f"released {args.key}")
    return 0


def cmd_measure(args: argparse.Namespace) -> int:
    """record measurements on a manager, e.g. battery=0.2"""
    values = {k: _value(v) for k, v in _pairs(args.values, "measure").items()}
    if not values:
        raise _Usage("measure needs at least one NAME=VALUE, e.g. battery=0.2")
    with _client(args) as client:
        for name, value in values.items():
            client.measure(name, value)
    _report(args, {"measured": values}, ())
    return 0


def cmd_adaptations(args: argparse.Namespace) -> int:
    """list a manager's adaptations"""
    with _client(args) as client:
        events = client.get_adaptations()

    def text() -> Iterable[str]:
        for e in events:
            times = f"adapted in {e['adaptation_ms']} ms" if e["adaptation_ms"] is not None else ""
            if e["recovery_ms"] is not None:
                times += f", recovered in {e['recovery_ms']} ms"
            via = " (onto the warm standby)" if e.get("standby") else ""
            yield f"#{e['id']} {e['kind']} {e['request']}: {e['cause']}; {', '.join(e['old'])} -> {', '.join(e['new']) or '(none)'}{via} {times}"

    _report(args, events, text)
    return 0


def _payload_json(payload: Any) -> Any:
    if isinstance(payload, np.ndarray):
        return {"ndarray": {"dtype": str(payload.dtype), "shape": list(payload.shape)}}
    if isinstance(payload, (bytes, bytearray)):
        return {"bytes": len(payload), "base64": base64.b64encode(payload[:4096]).decode()}
    return payload


def cmd_echo(args: argparse.Namespace) -> int:
    """print the messages published on a key expression, with their age (corrected by --manager's clock offsets; this host's clock taken as its)"""
    from dyknow.clocks import Estimate
    from dyknow.message import CLOCK_ID

    if args.count is not None and args.count <= 0:
        raise _Usage(f"--count: got {args.count}; expected a positive number")
    if args.keyexpr.startswith(("ros2:", "ros2dds:")):
        return _echo_ros2(args)
    done = threading.Event()
    lock = threading.Lock()
    seen = 0
    clocks: dict[int, Estimate] = {CLOCK_ID: Estimate(CLOCK_ID, 0, 0, 0.0, 0, 0)}  # clock id -> offset from --manager's; swapped whole

    def show(msg: Message) -> None:
        nonlocal seen
        with lock:
            if done.is_set():
                return
            now = time.time_ns()
            estimate = clocks.get(msg.origin_clock)  # (a message of a clock --manager does not know: its age is not shown)
            known = None if estimate is None else estimate.carried(now)
            age_us = None if known is None else round((now - msg.origin_ns + known[0]) / 1000, 1)
            data = {
                "key": msg.key,
                "seq": msg.seq,
                "origin_ns": msg.origin_ns,
                "send_ns": msg.send_ns,
                "origin_clock": f"{msg.origin_clock:08x}",
                "latency_us": age_us,
                "uncertainty_us": None if known is None else round(known[1] / 1000, 1),
                "payload": _payload_json(msg.payload),
            }
            age = "clock unknown" if known is None or age_us is None else f"{age_us / 1000:.3f} ms" + (f" +/- {known[1] / 1e6:.3f}" if known[1] else "")
            _report(args, data, f"{msg.key} #{msg.seq} age {age}: {describe_payload(msg.payload)}")
            seen += 1
            if args.count is not None and seen >= args.count:
                done.set()

    fetched = threading.Event()

    def follow(client: Client) -> None:  # the offsets, kept current (a clock drifts; a peer appears)
        nonlocal clocks
        while True:
            try:  # (a --manager that is not there would hold the first message up for --timeout)
                if args.manager in client.manager_names(timeout_s=min(args.timeout, 1.0)):
                    clocks = {CLOCK_ID: Estimate(CLOCK_ID, 0, 0, 0.0, 0, 0), **{e.clock: e for e in client.clocks().values()}}
            except DyKnowError as exc:
                logging.getLogger(__name__).debug("no clock offsets from %r: %s", args.manager, exc)
            fetched.set()
            if done.wait(5.0):
                return

    with _client(args) as client:
        threading.Thread(target=follow, args=(client,), name="dyknow-echo-clocks", daemon=True).start()
        fetched.wait(args.timeout)  # the offsets before the first message
        with client.declare_subscriber(args.keyexpr, show):
            signal.signal(signal.SIGINT, lambda *_: done.set())
            signal.signal(signal.SIGTERM, lambda *_: done.set())
            done.wait(args.timeout_total) if args.timeout_total else done.wait()
        done.set()
    if args.count is not None and seen < args.count:
        print(f"dyknow: error: received {seen} of {args.count} messages on {args.keyexpr!r}", file=sys.stderr)
        return 1
    return 0


def _ros2_domain_number(text: str) -> int:
    if not text.isdigit() or int(text) > 232:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a ROS_DOMAIN_ID from 0 to 232")
    return int(text)


def _ros2_domain(args: argparse.Namespace) -> int:
    if args.ros2_domain is not None:
        return int(args.ros2_domain)
    text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    if not text.isdigit() or int(text) > 232:
        raise _Usage(f"ROS_DOMAIN_ID={text!r}; expected a number from 0 to 232 (or --ros2-domain)")
    return int(text)


def _echo_ros2(args: argparse.Namespace) -> int:
    """``dyknow echo ros2:/TOPIC``: a ROS 2 topic decoded, with its latency (from the header stamp
    when the type has one, else from the publisher's source timestamp)."""
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
                "payload": _payload_json(payload),
            }
            text = f"{binding.topic} [{received.ros_type}] #{data['seq']} age {data['latency_us'] / 1000:.3f} ms: {describe_payload(payload)}"
            _report(args, data, text)
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

        with DdsNode(domain=_ros2_domain(args)) as participant:
            participant.create_subscription(binding.topic, binding.ros_type, show, binding.qos)
            wait()
    else:
        with _client(args) as client, Ros2Node(client.session, f"dyknow_echo_{os.getpid()}", domain=_ros2_domain(args)) as node:
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

        with DdsNode(domain=_ros2_domain(args)) as participant:
            topics = participant.topics(wait_s=args.timeout)
        _report(args, {"topics": topics}, ["topics (DDS):", *(f"  {t} [{', '.join(types)}]" for t, types in topics.items())])
        return 0
    with _client(args) as client:
        view = snapshot(client.session, _ros2_domain(args), timeout_s=args.timeout)

    def lines() -> Iterable[str]:
        yield "nodes:"
        yield from (f"  {node}" for node in view.nodes())
        yield "topics:"
        for topic, types in view.topics().items():
            publishers = len(view.publishers(topic))
            yield f"  {topic} [{', '.join(types)}] ({publishers} publisher{'s' if publishers != 1 else ''})"

    _report(args, view.to_dict(), lines)
    return 0


def cmd_monitor(args: argparse.Namespace) -> int:
    """monitor a temporal formula: its verdicts as they are decided (or over a recording, with --mcap)"""
    if args.mcap is not None:
        return _monitor_recording(args)
    if args.bind:
        raise _Usage("--bind: only with --mcap (live, the manager finds each term's stream by its meaning)")
    if args.duration is not None and args.duration <= 0:
        raise _Usage(f"--duration: got {args.duration}; expected a positive number of seconds")
    done = threading.Event()
    lock = threading.Lock()

    def show(msg: Message) -> None:
        verdict = msg.payload if isinstance(msg.payload, dict) else {}
        with lock:
            if done.is_set():
                return
            gap = verdict.get("gap")
            said = "true " if verdict.get("verdict") is True else "false"
            text = f"{msg.key}  t={verdict.get('t', 0):.3f} s  {said}" + (
                f"  (after a gap: {gap.get('term')} re-planned: {gap.get('cause')})" if isinstance(gap, dict) else ""
            )
            _report(args, {"key": msg.key, **verdict}, text)

    with _client(args) as client:
        key = client.monitor(args.formula, reorder_ms=args.reorder_ms)
        if not args.json:
            print(f"monitoring {args.formula} on {key} (Ctrl-C to stop)", flush=True)
        try:
            with client.declare_subscriber(key, show):
                signal.signal(signal.SIGINT, lambda *_: done.set())
                signal.signal(signal.SIGTERM, lambda *_: done.set())
                done.wait(args.duration) if args.duration else done.wait()
                done.set()
        finally:
            client.release(key)
    return 0


def _monitor_recording(args: argparse.Namespace) -> int:
    from dyknow.reasoning.offline import evaluate_recording

    bindings = _pairs(args.bind, "--bind")
    results = evaluate_recording(args.formula, args.mcap, bindings)
    if args.json:
        for t_ns, verdict in results:
            _out({"t": t_ns / 1e9, "t_ns": t_ns, "verdict": verdict})
        return 0
    counts = {True: 0, False: 0, None: 0}
    for t_ns, verdict in results:
        counts[verdict] += 1
        print(f"t={t_ns / 1e9:.3f} s  {'unknown' if verdict is None else 'true' if verdict else 'false'}")
    print(f"{len(results)} states: {counts[True]} true, {counts[False]} false, {counts[None]} unknown", flush=True)
    return 0


# --- recording (MCAP)


def _rate(text: str) -> float:
    from math import inf, isnan

    if text.strip().lower() in ("max", "inf"):
        return inf
    try:
        rate = float(text)
    except ValueError:
        rate = 0.0
    if isnan(rate) or rate <= 0:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a positive number (2 is twice as fast, 0.5 half) or max")
    return rate


def _zenoh_connect(args: argparse.Namespace) -> list[str]:
    return list(args.connect) or ([_default_endpoint(_tls(args))] if args.zenoh_config is None else [])


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    return stop


def cmd_record(args: argparse.Namespace) -> int:
    """record key expressions to an MCAP file until Ctrl-C/SIGTERM (or --duration, --max-messages)"""
    from dyknow.recording import Recorder

    if args.duration is not None and not args.duration > 0:
        raise _Usage(f"--duration: got {args.duration}; expected a positive number of seconds")
    if args.max_messages is not None and args.max_messages < 1:
        raise _Usage(f"--max-messages: got {args.max_messages}; expected a positive number")
    if args.chunk_size < 1:
        raise _Usage(f"--chunk-size: got {args.chunk_size}; expected a positive number of bytes")
    recorder = Recorder(
        args.keyexprs,
        args.output,
        connect=_zenoh_connect(args),
        zenoh_config=args.zenoh_config,
        tls=_tls(args),
        compression=args.compression,
        chunk_size=args.chunk_size,
        max_messages=args.max_messages,
    )
    with recorder:
        stop = _stop_on_signals()  # from here on, SIGINT/SIGTERM end the recording with a complete file
        _report(
            args,
            {"event": "ready", "file": args.output, "key_exprs": args.keyexprs},
            f"recording {', '.join(args.keyexprs)} to {args.output}; Ctrl-C to stop",
        )
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while not recorder.wait(0):
            left = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
            if left <= 0 or stop.wait(left):
                break
    keys = len(recorder.topics)
    _report(
        args,
        {"event": "done", "file": args.output, "messages": recorder.count, "topics": recorder.topics, "bytes": recorder.bytes_written},
        f"recorded {recorder.count} messages on {keys} key{'s' if keys != 1 else ''} to {args.output} ({recorder.bytes_written} bytes)",
    )
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    """replay an MCAP file into Zenoh in log-time order, at the original pace"""
    from dyknow.recording import Player

    remap = _pairs(args.remap, "--remap")
    with Player(
        args.file, rate=args.rate, loop=args.loop, start_s=args.start, end_s=args.end, topics=args.topics, remap=remap, recover=args.recover
    ) as player:
        stop = _stop_on_signals()
        topics = ", ".join(f"{topic} -> {key}" if key != topic else topic for topic, key in player.keys.items())
        _report(args, {"event": "ready", "file": args.file, "keys": player.keys}, f"replaying {args.file} ({topics}); Ctrl-C to stop")
        count = player.publish(connect=_zenoh_connect(args), zenoh_config=args.zenoh_config, tls=_tls(args), stop=stop, wait_s=args.wait)
    _report(args, {"event": "done", "file": args.file, "messages": count}, f"replayed {count} messages from {args.file}")
    return 0


def cmd_mcap_cat(args: argparse.Namespace) -> int:
    """print the messages in log-time order"""
    from dyknow.recording import Player

    with Player(args.file, topics=args.topics, recover=args.recover, decode=False) as player:
        try:
            for record in player.messages():
                if args.json:
                    _out(record.to_dict())
                    continue
                channel = record.channel
                if channel.message_encoding in ("json",) or channel.message_encoding.startswith("text/"):
                    preview = record.data[:80].decode(errors="replace") + ("..." if len(record.data) > 80 else "")
                else:
                    preview = f"<{len(record.data)} bytes>"
                kind = channel.schema_name or channel.message_encoding
                print(f"{record.log_time_ns} {record.topic} #{record.sequence} [{kind}] {preview}")
        except BrokenPipeError:  # the reader went away (| head): stop quietly
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


def cmd_mcap_info(args: argparse.Namespace) -> int:
    """summarise channels, counts and time range"""
    from datetime import UTC, datetime

    from dyknow.recording import Recording

    with Recording(args.file, recover=args.recover) as recording:
        info = recording.info

    def when(ns: int) -> str:
        return datetime.fromtimestamp(ns / 1e9, tz=UTC).isoformat(timespec="milliseconds")

    def text() -> Iterable[str]:
        yield f"file:      {info.path} ({info.size} bytes)" + (f"; DAMAGED: {info.problem}" if info.problem else "")
        yield f"library:   {info.library or '-'}   profile: {info.profile or '-'}"
        yield f"messages:  {info.message_count}"
        if info.start_ns is not None and info.end_ns is not None:
            yield f"time:      {when(info.start_ns)} to {when(info.end_ns)} ({info.duration_s:.3f} s; log_time {info.start_ns} to {info.end_ns})"
        yield f"chunks:    {info.chunk_count} ({', '.join(info.compressions) or 'none'})   indexed: {'yes' if info.indexed else 'no'}"
        if info.attachment_count or info.metadata_count:
            yield f"other:     {info.attachment_count} attachments, {info.metadata_count} metadata records"
        yield f"channels:  {len(info.channels)}"
        for c in info.channels:
            schema = f"{c.schema_name} ({c.schema_encoding})" if c.schema_name else "no schema"
            yield f"  {c.id:>4} {c.topic}  {c.message_count} msgs  {schema}  [{c.message_encoding}]"

    _report(args, info.to_dict(), text)
    return 0


# ---------------------------------------------------------------------- demo


def cmd_demo(args: argparse.Namespace) -> int:
    """run the ball-tracking demo (the battery runs low midway; the stream adapts)"""
    from dyknow.demo import run_demo

    for video in (args.robot_video, args.ceiling_video):
        if video is not None and not os.path.isfile(video):
            raise _Usage(f"{video}: no such video file; expected a video readable by OpenCV")
    if args.duration is not None and args.duration <= 0:
        raise _Usage(f"--duration: got {args.duration}; expected a positive number of seconds")
    return run_demo(
        chain=args.chain,
        duration_s=args.duration,
        robot_video=args.robot_video,
        ceiling_video=args.ceiling_video,
        out_dir=args.out,
        hops=args.hops,
        rate_hz=args.rate,
        as_json=args.json,
        distributed=args.distributed,
        ui_port=args.ui_port if args.ui else None,
        ros2=args.ros2,
    )


# ---------------------------------------------------------------------- parser


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dyknow", description="Reconfigurable stream reasoning on Eclipse Zenoh.")
    parser.add_argument("--version", action="version", version=f"dyknow {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, fn: Callable[[argparse.Namespace], int], client: bool = False) -> argparse.ArgumentParser:
        help = (fn.__doc__ or "").strip()  # each command's docstring is its help
        p = sub.add_parser(name, help=help, description=help)
        p.set_defaults(fn=fn)
        p.add_argument("--json", action="store_true", help="machine-readable output")
        if client:
            zenoh_options(p, connect_help=f"Zenoh endpoint of the manager (default {DEFAULT_ENDPOINT})")
            p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help=f"the manager's name (default {DEFAULT_MANAGER})")
            p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="seconds to wait for the manager (default 5)")
        return p

    def zenoh_options(p: argparse.ArgumentParser, connect_help: str) -> None:
        """The options every command that opens a Zenoh session shares."""
        p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help=connect_help)
        p.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh json5 configuration file instead of the loopback defaults")
        p.add_argument(
            "--tls-ca",
            metavar="FILE",
            help="TLS: the CA certificate that signs every peer's certificate (PEM); with --tls-cert and --tls-key",
        )
        p.add_argument(
            "--tls-cert", metavar="FILE", help="TLS: this process's certificate (PEM); its common name is its identity for --acl"
        )
        p.add_argument("--tls-key", metavar="FILE", help="TLS: this process's private key (PEM)")

    def ros2_domain_option(p: argparse.ArgumentParser) -> None:
        p.add_argument("--ros2-domain", type=_ros2_domain_number, metavar="N",
                       help="the ROS 2 domain for ros2: bindings and topics (default ROS_DOMAIN_ID, else 0)")  # fmt: skip

    def lease_option(p: argparse.ArgumentParser) -> None:
        p.add_argument("--lease-ms", type=_positive_int, metavar="MS",
                       help="how long a silent link lives (default Zenoh's 10000): a host cut off is noticed after about this; "
                            "shorter is sooner, with more keep-alive traffic and false alarms on a slow link")  # fmt: skip

    def limit_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--max-expansions", type=_positive_int, default=DEFAULT_MAX_EXPANSIONS, metavar="N",
                       help=f"refuse a template that expands to more specs (default {DEFAULT_MAX_EXPANSIONS})")  # fmt: skip

    p = command("manager", cmd_manager)
    p.add_argument("--name", default=DEFAULT_MANAGER, help=f"the manager's name (default {DEFAULT_MANAGER})")
    p.add_argument("--specs", action="extend", nargs="+", default=[], metavar="PATH", help="spec files or directories of .xml specs")
    p.add_argument("--ontology", action="extend", nargs="+", default=[], metavar="FILE", help="ontology files (Turtle or RDF/XML)")
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to listen on (default {DEFAULT_ENDPOINT}; tls/... with TLS)",
    )
    zenoh_options(p, connect_help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--allow-source", action="append", default=[], metavar="PATTERN",
                   help="also load units of these modules (mypkg, mypkg.units*, mypkg.units:Class); repeatable")  # fmt: skip
    p.add_argument("--data-root", action="append", default=[], metavar="DIR",
                   help="folders whose files remote callers may name in file params (reads also: the spec folders); repeatable")  # fmt: skip
    p.add_argument(
        "--acl",
        metavar="FILE",
        help="roles by certificate common name (JSON5: { roles: { viewer: [...], operator: [...], admin: [...], manager: [...], "
        "router: [...] } }); every call must then be signed by its caller (dyknow clients with --tls-* do)",
    )
    p.add_argument(
        "--max-request-bytes", type=_positive_int, default=1 << 20, metavar="N", help="refuse larger service requests (default 1 MiB)"
    )
    p.add_argument(
        "--max-units", type=_positive_int, default=1000, metavar="N", help="refuse spawns beyond this many units (default 1000)"
    )
    p.add_argument("--max-message-bytes", type=_positive_int, default=64 << 20, metavar="N",
                   help="drop larger messages (data or calls) while they arrive, before they take memory (default 64 MiB)")  # fmt: skip
    p.add_argument("--max-expansion-bytes", type=_positive_int, default=16 << 20, metavar="N",
                   help="refuse a spec added remotely whose expansions would hold more text (default 16 MiB)")  # fmt: skip
    limit_options(p)
    p.add_argument("--host", metavar="NAME", help="the machine it runs on, for measurements addressed by host (default: the host name)")
    p.add_argument("--dwell", type=float, metavar="S",
                   help="how long a request keeps a configuration before switching to a better one (default 2)")  # fmt: skip
    p.add_argument("--alone", action="store_true", help="do not plan with the other managers on the network, nor announce this one")
    lease_option(p)
    ros2_domain_option(p)
    p.add_argument("--ros2-node", metavar="NAME", help="the manager's ROS 2 node name (default: its name; declared at start when given)")
    p.add_argument("--ros2-namespace", default="/", metavar="NS", help="the ROS 2 node's namespace (default /)")
    p.add_argument("--ros2-dds-config", metavar="FILE",
                   help="Cyclone DDS XML for ros2dds: bindings (default: discovery on loopback only)")  # fmt: skip

    p = command("ui", cmd_ui, client=True)
    p.add_argument("--host", default="127.0.0.1", help="the address to serve on (default 127.0.0.1; elsewhere a token is required)")
    p.add_argument("--port", type=int, default=8321, help="the port to serve on (default 8321; 0: any free port)")
    p.add_argument("--token", help="the access token the page must carry (default: none on loopback, a new one elsewhere)")

    p = command("foxglove", cmd_foxglove, client=True)
    p.add_argument("keyexprs", nargs="*", metavar="KEYEXPR", help="key expressions to serve (default dyknow/**: every stream)")
    p.add_argument("--host", default="127.0.0.1", help="the address to serve on (default 127.0.0.1; the protocol has no access control)")
    p.add_argument("--port", type=int, default=8765, help="the port to serve on (default 8765; 0: any free port)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="URL",
                   help="a web page origin that may connect besides the Foxglove web app (https://app.foxglove.dev), "
                        "e.g. a self-hosted Lichtblick; repeatable (desktop apps send no origin and are always served)")  # fmt: skip

    p = command("router", cmd_router)
    p.add_argument(
        "--listen", action="append", default=[], metavar="ENDPOINT", help=f"Zenoh endpoint to listen on (default {DEFAULT_ENDPOINT})"
    )
    zenoh_options(p, connect_help="another router to connect to (repeatable)")
    p.add_argument("--acl", metavar="FILE", help="enforce these roles at the router's links (the managers' ACL file; see dyknow manager --acl)")
    lease_option(p)

    p = command("certs", cmd_certs)
    p.add_argument("dir", metavar="DIR", help="where to write ca.pem, ca.key and NAME.pem, NAME.key (an existing CA there is reused)")
    p.add_argument("--names", required=True, type=_names, metavar="A,B,C", help="the certificates' common names")
    p.add_argument("--hosts", type=_names, default=["localhost", "127.0.0.1"], metavar="H,H",
                   help="host names and addresses the certificates are valid for (default localhost,127.0.0.1)")  # fmt: skip

    p = command("demo", cmd_demo)
    p.add_argument("--duration", type=float, default=None, metavar="S", help="how long to run (default 30 s; 6 s with --chain)")
    p.add_argument("--robot-video", metavar="PATH", help="a video for the robot camera instead of the synthetic scene")
    p.add_argument("--ceiling-video", metavar="PATH", help="a video for the ceiling camera instead of the synthetic scene")
    p.add_argument("--out", default="dyknow-demo-report", metavar="DIR", help="where to write the report (default ./dyknow-demo-report)")
    p.add_argument("--chain", action="store_true", help="the latency demo instead: a chain of relays, per-hop latency")
    p.add_argument("--ui", action="store_true", help="serve the interactive tool beside the demo (dyknow ui) and print its URL")
    p.add_argument("--ui-port", type=int, default=8321, metavar="PORT", help="the tool's port with --ui (default 8321; 0: any free port)")
    p.add_argument("--distributed", action="store_true",
                   help="the scenario across three manager processes (robot, field, station): battery drop, then a manager killed")  # fmt: skip
    p.add_argument("--ros2", action="store_true",
                   help="the robot camera as a ROS 2 node (rmw_zenoh) and the tracked ball published back to ROS 2")  # fmt: skip
    p.add_argument("--hops", type=int, default=5, help="relays in the chain (--chain; default 5)")
    p.add_argument("--rate", type=float, default=20.0, metavar="HZ", help="source rate (--chain; default 20 Hz)")

    # --- recording (MCAP)
    p = command("record", cmd_record)
    p.add_argument("keyexprs", nargs="+", metavar="KEYEXPR", help="key expressions to record, e.g. 'robot/**'")
    p.add_argument("-o", "--output", required=True, metavar="FILE.mcap", help="the MCAP file to write")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--max-messages", type=int, metavar="N", help="stop after N messages")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd", help="chunk compression (default zstd)")
    p.add_argument("--chunk-size", type=int, default=1024 * 1024, metavar="BYTES", help="uncompressed chunk size (default 1 MiB)")
    zenoh_options(p, connect_help=f"Zenoh endpoint to connect to (default {DEFAULT_ENDPOINT})")

    p = command("replay", cmd_replay)
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument(
        "--rate", type=_rate, default=1.0, metavar="X", help="pace: 2 is twice as fast, 0.5 half, max as fast as possible (default 1)"
    )
    p.add_argument("--loop", action="store_true", help="start over at the end, until interrupted")
    p.add_argument("--start", type=float, metavar="S", help="begin S seconds after the first message")
    p.add_argument("--end", type=float, metavar="S", help="stop S seconds after the first message")
    p.add_argument(
        "--topics", nargs="+", action="extend", default=[], metavar="T", help="replay only these topics (names, keys or key expressions)"
    )
    p.add_argument(
        "--remap", action="append", default=[], metavar="FROM=TO", help="replay topic FROM (or a prefix FROM/**) on key TO (repeatable)"
    )
    p.add_argument("--recover", action="store_true", help="replay what is valid in a truncated or corrupt file, with a warning")
    p.add_argument(
        "--wait", type=float, default=1.0, metavar="S", help="first wait up to S seconds for a subscriber on every key (default 1)"
    )
    zenoh_options(p, connect_help=f"Zenoh endpoint to connect to (default {DEFAULT_ENDPOINT})")

    p = sub.add_parser("mcap", help="inspect MCAP files (cat, info)", description="inspect MCAP files, whoever wrote them")
    mcap = p.add_subparsers(dest="mcap_command", required=True, metavar="COMMAND")
    p = mcap.add_parser("cat", help=cmd_mcap_cat.__doc__, description=cmd_mcap_cat.__doc__)
    p.set_defaults(fn=cmd_mcap_cat)
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument(
        "--topics", nargs="+", action="extend", default=[], metavar="T", help="only these topics (names, keys or key expressions)"
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="one JSON object per message and line: topic, sequence, log_time, publish_time, schema, message_encoding, data_b64",
    )
    p.add_argument("--recover", action="store_true", help="print what is valid in a truncated or corrupt file, with a warning")
    p = mcap.add_parser("info", help=cmd_mcap_info.__doc__, description=cmd_mcap_info.__doc__)
    p.set_defaults(fn=cmd_mcap_info)
    p.add_argument("file", metavar="FILE.mcap")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--recover", action="store_true", help="summarise what is valid in a truncated or corrupt file")

    p = command("validate", cmd_validate)
    limit_options(p)
    p.add_argument("paths", nargs="+", metavar="PATH", help="spec file or directory of .xml specs")
    p.add_argument("--ontology", action="extend", nargs="+", default=[], metavar="FILE", help="ontologies for <arg class=...>")

    p = command("expand", cmd_expand)
    limit_options(p)
    p.add_argument("paths", nargs="+", metavar="PATH", help="spec file or directory of .xml specs")
    p.add_argument("--ontology", action="extend", nargs="+", default=[], metavar="FILE", help="ontologies for <arg class=...>")

    p = command("plan", cmd_plan)
    limit_options(p)
    p.add_argument("--specs", action="extend", nargs="+", required=True, metavar="PATH", help="spec files or directories")
    p.add_argument("--ontology", action="extend", nargs="+", default=[], metavar="FILE", help="ontology files")
    p.add_argument("--request", required=True, metavar="TAG", help="the tag to provide, e.g. 'BallPosition(field)'")
    p.add_argument("--unavailable", action="extend", nargs="+", default=[], metavar="LABEL", help="transformations not to use")
    p.add_argument("--measure", action="extend", nargs="+", default=[], metavar="NAME=VALUE", help="latest measurements")
    p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help="manager name used in the planned keys")
    p.add_argument("--peer", action="append", default=[], metavar="NAME=PATH",
                   help="another manager's library (spec file or directory), to plan across managers; repeatable")  # fmt: skip

    p = command("spawn", cmd_spawn, client=True)
    p.add_argument("label")
    p.add_argument("name")
    p.add_argument("--protect", action="store_true", help="refuse destroy requests for this unit, unless forced (by an admin)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="override a param (repeatable)")
    p.add_argument("--bind", action="append", default=[], metavar="PORT=KEY", help="bind a port to a key (repeatable)")

    p = command("destroy", cmd_destroy, client=True)
    p.add_argument("name")
    p.add_argument("--force", action="store_true", help="destroy a protected unit too (an admin's call, when the manager has roles)")

    p = command("model", cmd_model, client=True)
    p.add_argument("--all", action="store_true", help='the model of every manager reachable: {"managers": [...]}')
    command("managers", cmd_managers, client=True)

    p = command("config", cmd_config, client=True)
    p.add_argument("action", choices=["get", "set"])
    p.add_argument("name")
    p.add_argument("bindings", nargs="*", metavar="PORT=KEY")

    p = command("stats", cmd_stats, client=True)
    p.add_argument("name")

    p = command("add-spec", cmd_add_spec, client=True)
    p.add_argument("file")

    p = command("remove-spec", cmd_remove_spec, client=True)
    p.add_argument("label")

    p = command("request", cmd_request, client=True)
    p.add_argument("tag")
    p.add_argument("--standby", choices=STANDBY_MODES, metavar="MODE",
                   help="'warm': keep the next-best configuration running, so a fault only moves the stream onto it; "
                        "'none' (default): re-plan and spawn when the configuration breaks")  # fmt: skip
    p.add_argument("--require", action="append", default=[], metavar="FORMULA",
                   help="a temporal formula the stream must satisfy: a false verdict moves it to the next-best configuration "
                        "(repeatable; see dyknow monitor)")  # fmt: skip

    p = command("release", cmd_release, client=True)
    p.add_argument("key")

    p = command("measure", cmd_measure, client=True)
    p.add_argument("values", nargs="+", metavar="NAME=VALUE")

    command("adaptations", cmd_adaptations, client=True)

    p = command("monitor", cmd_monitor, client=True)
    p.add_argument("formula", help="e.g. 'BallTrack(field).predicted implies eventually[0, 1.5s] not BallTrack(field).predicted'")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C); the monitor is released")
    p.add_argument("--reorder-ms", type=float, default=0.0, metavar="MS", help="how late a sample may arrive and still count (default 0)")
    p.add_argument("--mcap", metavar="FILE", help="evaluate over this recording instead, offline, with the same semantics")
    p.add_argument("--bind", action="append", default=[], metavar="TERM=TOPIC", help="with --mcap: the topic that carries a term (repeatable)")

    p = command("echo", cmd_echo, client=True)
    p.add_argument("keyexpr", help="a key expression, or ros2:/TOPIC[?type=T] (rmw_zenoh) or ros2dds:/TOPIC?type=T (DDS), decoded")
    p.add_argument("--count", type=int, metavar="N", help="exit after N messages")
    p.add_argument("--timeout-total", type=float, metavar="S", help="give up after S seconds")
    ros2_domain_option(p)

    p = sub.add_parser("ros2", help="the ROS 2 graph on Zenoh (list)", description="the ROS 2 graph, as rmw_zenoh's tokens show it")
    ros2 = p.add_subparsers(dest="ros2_command", required=True, metavar="COMMAND")
    help = (cmd_ros2_list.__doc__ or "").strip()
    p = ros2.add_parser("list", help=help, description=help)
    p.set_defaults(fn=cmd_ros2_list)
    p.add_argument("--json", action="store_true", help="machine-readable output")
    zenoh_options(p, connect_help=f"Zenoh endpoint to connect to (default {DEFAULT_ENDPOINT})")
    p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help=argparse.SUPPRESS)
    p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="seconds to gather the graph (default 1)")
    p.add_argument("--dds", action="store_true", help="the topics on DDS (Cyclone DDS, loopback discovery) instead of rmw_zenoh")
    ros2_domain_option(p)
    return parser


def _version() -> str:
    from dyknow import __version__

    return __version__


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=os.environ.get("DYKNOW_LOG", "WARNING").upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.fn(args))
    except _Usage as exc:
        parser.error(str(exc))
    except SpecError as exc:
        for issue in exc.issues:
            print(str(issue), file=sys.stderr)
        return 1
    except DyKnowError as exc:
        print(f"dyknow: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        if os.environ.get("DYKNOW_DEBUG"):
            raise
        print(
            f"dyknow: internal error: {type(exc).__name__}: {exc} (set DYKNOW_DEBUG=1 for a traceback, and please report it)",
            file=sys.stderr,
        )
        return 70
    return 2


if __name__ == "__main__":
    sys.exit(main())
