"""Commands that talk to a running manager: spawn, destroy, model, managers, config, stats, add-spec,
remove-spec, request, release, measure, adaptations, monitor, echo.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from dyknow.cli.common import (
    DEFAULT_MANAGER,
    Commands,
    UsageError,
    open_client,
    parse_pairs,
    parse_value,
    payload_json,
    positive_int,
    print_json,
    read_limits,
    report_result,
    shipped,
    shown,
)
from dyknow.cli.ros2 import echo_ros2

if TYPE_CHECKING:
    from dyknow.client import ClockView
    from dyknow.message import Message

#: Keys and objects whose last verdict ``dyknow monitor --changes-only`` remembers (ids come and go).
_MAX_CHANGES_KEPT = 100_000

def traceback_tail(text: object, frames: int = 3) -> list[str]:
    """The last ``frames`` frames of a unit's traceback (where in its code it failed), as lines;
    none when there is no traceback."""
    if not isinstance(text, str) or not text.strip():
        return []
    lines = text.rstrip().splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith("  File ")]
    if not starts:
        return lines[-1:]
    shown = lines[starts[-frames] if len(starts) >= frames else starts[0] :]
    return [f"traceback (last {min(frames, len(starts))} of {len(starts)} frames):", *shown]


def cmd_spawn(args: argparse.Namespace) -> int:
    """spawn a unit on a manager, from a transformation of its library

    examples:
      dyknow spawn periodic-source src --param rate_hz=20
      dyknow spawn relay r1 --bind in=dyknow/robot/src/out --manager robot
      dyknow spawn doubler double --param factor=3 --bind in=sensors/x --protect"""
    params, bindings = parse_pairs(args.param, "--param"), parse_pairs(args.bind, "--bind")  # usage first, then connect
    with open_client(args) as client:
        info = client.spawn(args.label, args.name, protected=args.protect, params=params, bindings=bindings)

    def text() -> Iterable[str]:
        yield f"spawned {info['name']} ({info['label']}): {info['state']}" + (" [protected]" if info["protected"] else "")
        if info.get("error"):
            yield f"  error: {info['error']}"
            yield from (f"  {line}" for line in traceback_tail(info.get("traceback")))

    report_result(args, info, text)
    return 1 if info["state"] == "failed" else 0


def cmd_destroy(args: argparse.Namespace) -> int:
    """destroy a unit"""
    with open_client(args) as client:
        client.destroy(args.name, force=args.force)
    report_result(args, {"destroyed": args.name}, f"destroyed {args.name}")
    return 0


def cmd_model(args: argparse.Namespace) -> int:
    """show the manager's units and specs (--all: of every manager reachable)"""
    with open_client(args) as client:
        data = (
            client.get_federated_model(match=args.match or "*", limit=args.limit, after=args.after) if args.all else client.get_model()
        )
        why = client.unreachable() if args.all and not data["managers"] else None
    if why is not None:
        raise why
    models = data["managers"] if args.all else [data]

    def text() -> Iterable[str]:
        if args.all and not models and not data.get("refused"):
            yield "no manager reachable"
        for model in models:
            yield f"manager {model['manager']}: {len(model['units'])} units, {len(model['specs'])} specs"
            # a monitor's unit is named by its formula too (issue 54: 'monitor-2' alone said nothing)
            formulas = {m["unit"]: m["formula"] for info in model.get("monitors", []) for m in info.get("monitors", [])}
            for unit in model["units"]:
                judged = f"  monitors {formulas[unit['name']]}" if unit["name"] in formulas else ""
                yield f"  {unit['name']} ({unit['label']}) {unit['state']}" + (" [protected]" if unit["protected"] else "") + judged
                for port, key in unit["bindings"].items():
                    yield f"      {port} -> {key}"
                if unit.get("error"):
                    yield f"      error: {unit['error']}"
                    yield from (f"      {line}" for line in traceback_tail(unit.get("traceback")))
            if not model["units"]:
                yield "  no units"
            for request in model.get("requests", []):
                yield f"  request {request['tag']} on {request['key']}: {request['state']}"
            for mode in model.get("modes", []):
                when = time.strftime("%H:%M:%S", time.localtime(mode["since_ns"] / 1e9))
                yield f"  system {mode['system']} in mode {mode['mode']} since {when} (unit {mode['unit']}): {mode['why']}"
            for lost in model.get("lost", []):
                when = time.strftime("%H:%M:%S", time.localtime(lost["since_ns"] / 1e9))
                yield f"  lost manager {lost['manager']} since {when}: {lost['why']}"
            if model["specs"]:
                yield "specs: " + ", ".join(s["label"] for s in model["specs"])

    report_result(args, data, text)
    if args.all and data.get("next") is not None:
        print(f"dyknow: more managers after {data['next']}: continue with --after {data['next']}", file=sys.stderr)
    refused = _say_refused(data.get("refused", {}) if args.all else {})
    if args.all and not models and not refused:
        print("dyknow: error: no manager reachable; expected a running manager at --connect", file=sys.stderr)
        return 1
    return 1 if refused else 0


def _say_refused(refused: dict[str, str]) -> dict[str, str]:
    """Say on stderr why each manager left out was (its reply was no manager's: :mod:`dyknow.replies`)."""
    for why in refused.values():
        print(f"dyknow: error: {shown(why)}; left out", file=sys.stderr)
    return refused


def cmd_managers(args: argparse.Namespace) -> int:
    """list every manager reachable (host, library size, units, requests, its clock's offset as --manager estimates it),
    then those --manager knew and lost (since when, why); exit 1 when none is reachable, or one answered as no manager does"""
    from dyknow.errors import DyKnowError
    from dyknow.reach import DEFINITE

    with open_client(args) as client:
        why = client.unreachable()  # (a refusal at once, rather than after listening for 2 s)
        if why is not None and why.details.get("reason") in DEFINITE:
            raise why
        page = client.managers_page(timeout_s=min(args.timeout, 2.0), match=args.match or "*", limit=args.limit, after=args.after)
        if page["total"] == 0 and args.timeout > 2.0:  # (a loaded host, or a router with thousands of tokens, answers late: once more, as long as --timeout)
            page = client.managers_page(timeout_s=args.timeout, match=args.match or "*", limit=args.limit, after=args.after)
        managers = page["managers"]
        if not managers and page["total"] == 0:
            why = client.unreachable()
            if why is not None:
                raise why
        names = [m["manager"] for m in managers]
        # (a --manager that is not there would hold the list up for --timeout: ask another one)
        # (on another page, maybe: asked apart, briefly, for it is usually absent when not listed)
        up = args.manager in names or (len(names) < page["total"] and args.manager in client.manager_names(0.3, match=args.manager))
        asked = args.manager if up else names[0] if names else None
        clocks: dict[str, Any] = {}
        lost: list[dict[str, Any]] = []
        if asked is not None:
            try:
                model = client.get_model(asked)
                clocks = client.clocks(asked, model=model) if asked == args.manager else {}
                lost = [m for m in client.lost_managers(asked, model=model) if m["manager"] not in names]
            except DyKnowError as exc:  # the other columns stand without it
                logging.getLogger(__name__).debug("no clock offsets or lost managers from %r: %s", asked, exc)
    for m in managers:  # the offset of each manager's clock from --manager's (None: not known to it yet)
        found = clocks.get(m["manager"])
        m["state"] = "silent" if m.pop("silent", False) else "up"  # (a token up, and nothing answers for that name)
        m["clock"] = None if found is None else {"offset_us": found.offset_ns / 1000, "uncertainty_us": found.uncertainty_ns / 1000}
    now = time.time_ns()
    for m in lost:
        m.update(state="lost", reported_by=asked)

    def text() -> Iterable[str]:
        if not managers and not page.get("refused"):
            yield "no manager reachable"
        for m in managers:
            if m["state"] == "silent":
                yield f"{m['manager']:<20} SILENT: its token is up, nothing answers for it (no manager there, or not one yet)"
                continue
            clock = (
                "clock unknown" if m["clock"] is None else f"clock {m['clock']['offset_us']:+.1f} us +/- {m['clock']['uncertainty_us']:.1f}"
            )
            yield f"{m['manager']:<20} host {m['host']:<20} {m['specs']:>5} specs {m['units']:>5} units {m['requests']:>4} requests  {clock}"
        for m in lost:
            when = time.strftime("%H:%M:%S", time.localtime(m["since_ns"] / 1e9))
            yield f"{m['manager']:<20} LOST since {when} ({(now - m['since_ns']) / 1e9:.1f} s ago, as {asked} saw it): {m['why']}"

    report_result(args, [*managers, *lost], text)
    refused = _say_refused(page.get("refused", {}))
    if page["next"] is not None:
        print(
            f"dyknow: {len(managers)} of {page['total']} managers listed; continue with --after {page['next']}",
            file=sys.stderr,
        )
    if not managers and page["total"] == 0:
        where = ", ".join(args.connect) or "--connect"
        print(f"dyknow: error: no manager reachable through {where}; expected a running manager there (dyknow manager)", file=sys.stderr)
        return 1
    return 1 if refused else 0


def cmd_config(args: argparse.Namespace) -> int:
    """get or set a unit's port bindings (set: rebinds the ports given, atomically, while it runs)

    examples:
      dyknow config get r1
      dyknow config set r1 out=robot/elsewhere
      dyknow config set fusion in1=dyknow/robot/left/out in2=dyknow/robot/right/out"""
    if args.action == "get" and args.bindings:  # usage first, then connect
        raise UsageError("config get takes no PORT=KEY pairs; did you mean 'config set'?")
    if args.action != "get" and not args.bindings:
        raise UsageError("config set needs at least one PORT=KEY pair")
    changes = parse_pairs(args.bindings, "config set") if args.action != "get" else {}
    with open_client(args) as client:
        config = client.get_config(args.name) if args.action == "get" else client.set_config(args.name, changes)
    report_result(args, config, [f"{port} -> {key}" for port, key in config.items()])
    return 0


def cmd_stats(args: argparse.Namespace) -> int:
    """show a unit's statistics: per port messages, bytes, drops, lost, and for inputs latency (age since
    the data's origin) and hop (time since the previous unit sent it) percentiles; its error and traceback.
    Without a name: the manager's lanes, how busy each is, and its overload state

    examples:
      dyknow stats r1
      dyknow stats tracker --manager station --json
      dyknow stats"""
    if args.name is None:
        return _manager_stats(args)
    with open_client(args) as client:
        stats = client.get_statistics(args.name)

    def text() -> Iterable[str]:
        yield (
            f"{stats['name']} ({stats['label']}) {stats['state']}: up {stats['uptime_s']:.1f} s, "
            f"{stats['reconfigurations']} reconfigurations, {stats['executor']}"
        )
        for port, p in stats["ports"].items():
            unsized = f" (+{p['unsized']} msgs of unknown size: passed by reference, never encoded)" if p.get("unsized") else ""
            line = f"  {p['direction']:>3} {port} ({p['key']}): {p['messages']} msgs, {p['bytes']} B{unsized}, {p['dropped']} dropped"
            if p.get("shed"):
                line += f", {p['shed']} shed"
            if p["direction"] == "in" and p["latency"]["count"]:
                lat, hop = p["latency"], p["hop"]
                line += f"; latency p50 {lat['p50_us']:.1f} µs p99 {lat['p99_us']:.1f} µs; hop p50 {hop['p50_us']:.1f} µs p99 {hop['p99_us']:.1f} µs"
            yield line
        if stats.get("error"):
            yield f"  error: {stats['error']}"
            yield from (f"  {line}" for line in traceback_tail(stats.get("traceback"), frames=5))

    report_result(args, stats, text)
    return 0


def _manager_stats(args: argparse.Namespace) -> int:
    with open_client(args) as client:
        load = client.get_load()

    def text() -> Iterable[str]:
        overload = load["overload"]
        state = f"{overload['state']} (lag {overload['lag_ms']:.1f} ms, budget {overload['lag_budget_ms']:g} ms)"
        if overload["shed"]:
            shed = ", ".join(f"priority {t['priority']} " + ("paused" if t["rate"] == 0 else f"at {t['rate']:g} of its rate") for t in overload["shed"])
            state += f"; shedding {shed} ({overload['units_shed']} units)"
        nice = f"; nice {load['nice']}" if load.get("nice") else ""  # (a manager from before --nice says nothing)
        yield f"{args.manager}: {state}; {load['threads']} of at most {load['max_lanes']} lanes{nice}"
        for lane in load["lanes"]:
            stuck = f", stuck {lane['stuck_ms'] / 1000:.1f} s in a callback" if lane["stuck_ms"] >= 1000 else ""
            lag = f", lag {lane['lag_ms']:.1f} ms" if lane["kind"] == "shared" else ""
            names = f": {', '.join(lane['names'])}" if lane["names"] else ""
            more = "..." if len(lane["names"]) < lane["units"] and lane["names"] else ""
            yield f"  {lane['name']} ({lane['kind']}): {lane['units']} units, busy {lane['busy']:.0%}{lag}, {lane['queued']} queued{stuck}{names}{more}"

    report_result(args, load, text)
    return 0


def cmd_add_spec(args: argparse.Namespace) -> int:
    """add the transformations of a spec file (or - for standard input) to the manager"""
    source = sys.stdin.read() if args.file == "-" else args.file
    if args.file == "-" and not source.lstrip().startswith("<"):
        raise UsageError("add-spec -: standard input holds no XML; expected a spec such as <transformation>...")
    with open_client(args) as client:
        labels = client.add_transformation(source)
    report_result(args, {"labels": labels}, "added " + ", ".join(labels))
    return 0


def cmd_remove_spec(args: argparse.Namespace) -> int:
    """remove a transformation from the manager's library"""
    with open_client(args) as client:
        removed = client.remove_transformation(args.label)
    text = f"removed {args.label}" if removed else f"no spec labelled {args.label!r}; nothing removed"
    report_result(args, {"label": args.label, "removed": removed}, text)
    return 0 if removed else 1


def cmd_request(args: argparse.Namespace) -> int:
    """ask a manager for a stream by its meaning (a tag); prints the key it flows on, kept until released

    examples:
      dyknow request 'BallTrack(field)'
      dyknow request 'BallTrack(field)' --standby warm --require 'not historically[0, 500ms] BallTrack(field).predicted'"""
    with open_client(args) as client:
        key = client.request(args.tag, standby=args.standby, require=args.require, keep=True)
    report_result(args, {"request": args.tag, "key": key, "standby": args.standby or "none", "require": args.require, "kept": True}, key)
    if not args.json:  # (stdout is the key alone, for scripts)
        print(f"dyknow: the request is kept until released: dyknow release '{shown(key)}' --manager {args.manager}", file=sys.stderr)
    return 0


def cmd_release(args: argparse.Namespace) -> int:
    """give back a requested stream: by the key dyknow request printed, or by its tag

    examples:
      dyknow release dyknow/robot/requests/BallTrack(field)
      dyknow release 'Mode(motion)' --manager auv"""
    with open_client(args) as client:
        if "/" not in args.key:  # a tag (keys have slashes, tags none): the key of the one request for it
            requests = client.get_model().get("requests", [])
            keys = sorted(r["key"] for r in requests if r.get("tag") == args.key)
            if len(keys) > 1:
                raise UsageError(f"{len(keys)} requests for {args.key!r}: {', '.join(keys)}; give the key of the one to release")
            if keys:
                args.key = keys[0]
        remaining = client.release(args.key, force=args.force)
    if remaining:
        text = f"released one reference to {args.key}; {remaining} more remain, so it runs on until they are released too"
    else:
        text = f"released {args.key}: it is gone (the units only it used were destroyed)"
    report_result(args, {"released": args.key, "references": remaining}, text)
    return 0


def cmd_measure(args: argparse.Namespace) -> int:
    """record measurements on a manager, e.g. battery=0.2"""
    values = {k: parse_value(v) for k, v in parse_pairs(args.values, "measure").items()}
    if not values:
        raise UsageError("measure needs at least one NAME=VALUE, e.g. battery=0.2")
    with open_client(args) as client:
        for name, value in values.items():
            client.measure(name, value)
    report_result(args, {"measured": values}, ())
    return 0


def cmd_adaptations(args: argparse.Namespace) -> int:
    """list a manager's adaptations"""
    with open_client(args) as client:
        events = client.get_adaptations()

    def text() -> Iterable[str]:
        if not events:
            yield f"no adaptations on manager {args.manager!r} yet"
        for e in events:
            times = f"adapted in {e['adaptation_ms']} ms" if e["adaptation_ms"] is not None else ""
            if e["recovery_ms"] is not None:
                times += f", recovered in {e['recovery_ms']} ms"
            via = " (onto the warm standby)" if e.get("standby") else ""
            yield f"#{e['id']} {e['kind']} {e['request']}: {e['cause']}; {', '.join(e['old'])} -> {', '.join(e['new']) or '(none)'}{via} {times}"

    report_result(args, events, text)
    return 0


def _printable(payload: Any) -> str:
    """A payload as a user can paste it: JSON for JSON-like values and text, a description of
    arrays and bytes."""
    import numpy as np

    from dyknow.message import describe_payload

    if isinstance(payload, (np.ndarray, bytes, bytearray, memoryview)):
        return describe_payload(payload)
    try:
        return json.dumps(payload, ensure_ascii=False)
    except (TypeError, ValueError):
        return describe_payload(payload)


def cmd_echo(args: argparse.Namespace) -> int:
    """print the messages published on a key expression, with their age (corrected by --manager's clock offsets; this host's clock taken as its)"""
    from dyknow.errors import did_you_mean
    from dyknow.reach import DEFINITE

    if args.count is not None and args.count <= 0:
        raise UsageError(f"--count: got {args.count}; expected a positive number")
    if args.keyexpr.startswith(("ros2:", "ros2dds:")):
        return echo_ros2(args)
    done = threading.Event()
    lock = threading.Lock()
    seen = 0
    clocks: ClockView | None = None

    def show(msg: Message) -> None:
        nonlocal seen
        with lock:
            if done.is_set() or clocks is None:
                return
            now = time.time_ns()
            known = clocks.corrected(msg.origin_clock, msg.origin_ns, now)  # (a clock --manager does not know: no age shown)
            age_us = None if known is None else round((now - known[0]) / 1000, 1)
            data = {
                "key": msg.key,
                "seq": msg.seq,
                "origin_ns": msg.origin_ns,
                "send_ns": msg.send_ns,
                "origin_clock": f"{msg.origin_clock:08x}",
                "latency_us": age_us,
                "uncertainty_us": None if known is None else round(known[1] / 1000, 1),
                "payload": payload_json(msg.payload),
            }
            age = (
                "clock unknown"
                if known is None or age_us is None
                else f"{age_us / 1000:.3f} ms" + (f" +/- {known[1] / 1e6:.3f}" if known[1] else "")
            )
            report_result(args, data, f"{msg.key} #{msg.seq} age {age}: {_printable(msg.payload)}")
            seen += 1
            if args.count is not None and seen >= args.count:
                done.set()

    with open_client(args) as client:
        why = client.unreachable()  # nothing would ever come: say why at once (a silent host may come back: wait)
        if why is not None and why.details.get("reason") in DEFINITE:
            raise why
        view = client.follow_clocks()
        view.fetched.wait(args.timeout)  # the offsets before the first message
        clocks = view
        if view.found is False and args.manager != DEFAULT_MANAGER:  # --manager given, and not there: say so
            there = ", ".join(view.reachable) or "none"
            print(
                f"dyknow: warning: no manager {args.manager!r} is reachable (reachable: {there}"
                f"{did_you_mean(args.manager, view.reachable)}): the ages of messages from other hosts' clocks cannot be corrected",
                file=sys.stderr,
            )
        with client.declare_subscriber(args.keyexpr, show):
            signal.signal(signal.SIGINT, lambda *_: done.set())
            signal.signal(signal.SIGTERM, lambda *_: done.set())
            done.wait(args.timeout_total) if args.timeout_total else done.wait()
        done.set()
        view.close()
    if args.count is not None and seen < args.count:
        print(f"dyknow: error: received {seen} of {args.count} messages on {args.keyexpr!r}", file=sys.stderr)
        return 1
    return 0


def cmd_monitor(args: argparse.Namespace) -> int:
    """monitor a temporal formula: its verdicts as they are decided (or over a recording, with --mcap)

    examples:
      dyknow monitor 'historically[0, 1s] BallTrack(field).tracked > 0' --duration 10
      dyknow monitor 'BallTrack(field).predicted implies eventually[0, 1.5s] not BallTrack(field).predicted'
      dyknow monitor 'Odom(r1).twist.twist.linear.x < 1.5' --bind 'Odom(r1)=ros2:/r1/odom' --manager robot
      dyknow monitor 'Battery(r1) > 0.2' --bind 'Battery(r1)=robots/r1/battery'
      dyknow monitor 'always x > 0' --mcap run.mcap --bind x=sensors/x
      dyknow monitor 'always x > 0' --mcap run.mcap --bind x=sensors/x --changes-only --robustness
      dyknow monitor 'Battery(r1) > 0.2' --bind 'Battery(r1)=robots/r1/battery' --changes-only --robustness"""
    if args.robustness and args.mcap is not None and not args.changes_only:
        raise UsageError("--robustness goes with --changes-only over a recording (--mcap FILE): each change, with each subformula's robustness")
    if args.mcap is not None:
        return _monitor_recording(args)
    bindings = parse_pairs(args.bind, "--bind")
    if bindings:  # usage first, then connect: the same check the manager makes (it checks Zenoh keys further)
        from dyknow.reasoning.bindings import check_bindings
        from dyknow.reasoning.syntax import parse

        check_bindings(parse(args.formula), bindings)
    if args.duration is not None and args.duration <= 0:
        raise UsageError(f"--duration: got {args.duration}; expected a positive number of seconds")
    done = threading.Event()
    lock = threading.Lock()
    started_ns = time.time_ns()

    def when(t: object) -> str:
        """A verdict's time as the user reads it: seconds since the command started, or ISO."""
        if not isinstance(t, int | float) or isinstance(t, bool):
            return "?"
        if args.iso:
            return datetime.datetime.fromtimestamp(float(t), tz=datetime.UTC).isoformat(timespec="milliseconds")
        return f"{(float(t) * 1e9 - started_ns) / 1e9:+.3f} s"

    last: dict[tuple[str, str], object] = {}  # (key, object) -> its last verdict, with --changes-only

    def show(msg: Message) -> None:
        verdict = msg.payload if isinstance(msg.payload, dict) else {}
        with lock:
            if done.is_set():
                return
            if "warning" in verdict:  # what the monitor found wrong with its data (a field no sample holds)
                report_result(args, {"key": msg.key, **verdict}, f"{msg.key}  warning: {verdict.get('warning')}")
                return
            if args.changes_only:
                seen = (msg.key, str(verdict.get("object", "")))
                if seen in last and last[seen] is verdict.get("verdict"):
                    return
                if seen not in last and len(last) >= _MAX_CHANGES_KEPT:
                    last.clear()  # (objects come and go: the memory of their verdicts is bounded)
                last[seen] = verdict.get("verdict")
            gap = verdict.get("gap")
            said = "true " if verdict.get("verdict") is True else "false"
            who = f"  object {verdict['object']}" if "object" in verdict else ""
            rob = f"  robustness {verdict['robustness']}" if "robustness" in verdict else ""
            text = f"{msg.key}  {when(verdict.get('t'))}{who}  {said}{rob}" + (
                f"  (a gap: {gap.get('term')} re-planned: {gap.get('cause')})" if isinstance(gap, dict) else ""
            )
            why, margins = verdict.get("why"), verdict.get("robustness_of")
            shown_why = [f"  {atom}" for atom in why if isinstance(atom, str)] if isinstance(why, list) else []
            shown_why += [f"  robustness of {m}" for m in margins if isinstance(m, str)] if isinstance(margins, list) else []
            report_result(args, {"key": msg.key, **verdict}, [text, *shown_why[:16]])

    with open_client(args) as client:
        key = client.monitor(args.formula, reorder_ms=args.reorder_ms, bindings=bindings, robustness=args.robustness)
        if not args.json:
            bound = "".join(f", {term} from {source}" for term, source in bindings.items())
            print(shown(f"monitoring {args.formula} on {key}{bound} (Ctrl-C to stop)"), flush=True)
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
    from dyknow.reasoning.explain import object_explainer, object_robustness_explainer
    from dyknow.reasoning.offline import changes, evaluate_recording, recording_samples
    from dyknow.reasoning.semantics import evaluate_objects_ns
    from dyknow.reasoning.syntax import Quantifier, parse, walk

    bindings = parse_pairs(args.bind, "--bind")
    parsed = parse(args.formula)
    root = parsed.root
    if args.robustness and any(isinstance(node, Quantifier) and node.kind != "foreach" for node in walk(root)):
        raise UsageError("--robustness: a formula without forall or exists (each subformula's robustness is said of one series, or of each object's)")
    quantified = any(isinstance(node, Quantifier) and node.kind in ("forall", "exists") for node in walk(root))
    if quantified or (not isinstance(root, Quantifier) and any("{" in topic for topic in bindings.values())):
        return _quantified_recording(args, bindings, quantified=quantified)  # (a template binding: read as a requirement is)
    if isinstance(root, Quantifier) and root.kind == "foreach":  # verdicts per object and life
        parsed, samples = recording_samples(args.formula, args.mcap, bindings, read_limits(args))
        idle_ns = round(args.idle_ms * 1e6)
        objects = evaluate_objects_ns(parsed, samples, idle_ns=idle_ns)
        explain = robust = None
        if args.changes_only:  # each object's changes, with its body's atoms over its own samples
            objects = {key: [changes(sorted(v for life in lives for v in life))] for key, lives in objects.items()}
            explain = object_explainer(parsed, samples)
            robust = object_robustness_explainer(parsed, samples, idle_ns=idle_ns) if args.robustness else None
        rows = sorted((t_ns, key, verdict) for key, lives in objects.items() for life in lives for t_ns, verdict in life)
        if args.json:
            for t_ns, key, verdict in rows:
                said = {"why": explain(key, t_ns)} if explain else {}
                if robust is not None:
                    said["robustness"] = robust(key, t_ns)
                print_json({"t": t_ns / 1e9, "t_ns": t_ns, "object": key, "verdict": verdict, **said})
            return 0
        counted = {True: 0, False: 0, None: 0}
        for t_ns, key, verdict in rows:
            counted[verdict] += 1
            print(f"t={t_ns / 1e9:.3f} s  {shown(key)}  {'unknown' if verdict is None else 'true' if verdict else 'false'}")
            for atom in explain(key, t_ns) if explain is not None else ():
                print(shown(f"  {atom}"))
            for margin in robust(key, t_ns) if robust is not None else ():
                print(shown(f"  robustness of {margin}"))
        false = sorted({key for _, key, verdict in rows if verdict is False})
        named = f"; false for {', '.join(shown(k) for k in false[:10])}{', ...' if len(false) > 10 else ''}" if false else ""
        what = "changes" if args.changes_only else "states"
        print(f"{len(rows)} {what} of {len(objects)} objects: {counted[True]} true, {counted[False]} false, {counted[None]} unknown{named}", flush=True)
        return 0
    if args.changes_only:
        return _changes_of_recording(args, bindings)
    results = evaluate_recording(args.formula, args.mcap, bindings, read_limits(args))
    if args.json:
        for t_ns, verdict in results:
            print_json({"t": t_ns / 1e9, "t_ns": t_ns, "verdict": verdict})
        return 0
    counts = {True: 0, False: 0, None: 0}
    for t_ns, verdict in results:
        counts[verdict] += 1
        print(f"t={t_ns / 1e9:.3f} s  {'unknown' if verdict is None else 'true' if verdict else 'false'}")
    print(f"{len(results)} states: {counts[True]} true, {counts[False]} false, {counts[None]} unknown", flush=True)
    return 0


def _quantified_recording(args: argparse.Namespace, bindings: dict[str, str], *, quantified: bool = True) -> int:
    """``--mcap`` with ``forall``/``exists``: expanded over ``--ontology`` as a manager expands it,
    each term bound by ``--bind`` (a template such as ``State(r)=floor/{r}/state`` binds them all),
    a verdict series per individual (per tuple) as :func:`dyknow.reasoning.check_recording` gives it;
    a formula without them, bound by a template (a parameterized term's members, say), one series."""
    from dyknow.errors import DyKnowError
    from dyknow.ontology import Ontology
    from dyknow.reasoning.offline import changes
    from dyknow.reasoning.requirements import Requirement, check_recording
    from dyknow.tags import parse_term

    if quantified and not args.ontology:
        raise UsageError("a formula with forall or exists over a recording needs --ontology FILE (the individuals it ranges over)")
    try:
        given = {str(parse_term(term)): topic for term, topic in bindings.items()}
    except DyKnowError as exc:
        raise UsageError(f"--bind: {exc}") from None
    (result,) = check_recording([Requirement("formula", args.formula, given, where="--bind")], args.mcap,
                                individuals=Ontology.load(args.ontology).individuals if args.ontology else None, limits=read_limits(args))  # fmt: skip
    if result.error is not None:
        raise result.error
    series = {key: changes(rows) if args.changes_only else rows for key, rows in result.verdicts.items()}
    rows = sorted((t_ns, key, verdict) for key, values in series.items() for t_ns, verdict in values)
    if args.json:
        for t_ns, key, verdict in rows:
            print_json({"t": t_ns / 1e9, "t_ns": t_ns, **({"individual": key} if key else {}), "verdict": verdict})
        return 0
    for t_ns, key, verdict in rows:
        print(shown(f"t={t_ns / 1e9:.3f} s  {key}  {'unknown' if verdict is None else 'true' if verdict else 'false'}"))
    counted = [sum(1 for _, _, v in rows if v is which) for which in (True, False, None)]
    print(f"{len(rows)} {'changes' if args.changes_only else 'states'} of {len(series)} instances: {counted[0]} true, "
          f"{counted[1]} false, {counted[2]} unknown", flush=True)  # fmt: skip
    return 0


def _changes_of_recording(args: argparse.Namespace, bindings: dict[str, str]) -> int:
    """``--mcap --changes-only``: each change of the verdict, with the values of the formula's comparisons at it."""
    from dyknow.reasoning.explain import robustness_explainer
    from dyknow.reasoning.offline import changes, explainer, recording_samples
    from dyknow.reasoning.semantics import evaluate_ns

    parsed, samples = recording_samples(args.formula, args.mcap, bindings, read_limits(args))
    rows = changes([(t, v) for t, v in evaluate_ns(parsed, samples)])
    explain = explainer(parsed, samples)
    robust = robustness_explainer(parsed, samples) if args.robustness else None
    for t_ns, verdict in rows:
        why = explain(t_ns)
        margins = robust(t_ns) if robust is not None else []
        if args.json:
            print_json({"t": t_ns / 1e9, "t_ns": t_ns, "verdict": verdict, "why": why, **({"robustness": margins} if robust is not None else {})})
            continue
        print(shown(f"t={t_ns / 1e9:.3f} s  {'unknown' if verdict is None else 'true' if verdict else 'false'}"))
        for atom in why:
            print(shown(f"  {atom}"))
        for margin in margins:
            print(shown(f"  robustness of {margin}"))
    if not args.json:
        print(f"{len(rows)} changes", flush=True)
    return 0


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""

    def spawn_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("label", help="the transformation's label in the manager's library (dyknow model lists them), e.g. relay")
        p.add_argument("name", help="the new unit's name, unique on the manager, e.g. r1 (its outputs default to dyknow/MANAGER/NAME/PORT)")
        p.add_argument("--protect", action="store_true", help="refuse destroy requests for this unit, unless forced (by an admin)")
        p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="override a param (repeatable)")
        p.add_argument("--bind", action="append", default=[], metavar="PORT=KEY", help="bind a port to a key (repeatable)")

    cmds.command("spawn", cmd_spawn, spawn_options, client=True)

    def destroy_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("name", help="the unit's name")
        p.add_argument("--force", action="store_true", help="destroy a protected unit too (an admin's call, when the manager has roles)")

    cmds.command("destroy", cmd_destroy, destroy_options, client=True)

    def page_options(p: argparse.ArgumentParser, limit: int | None) -> None:
        p.add_argument(
            "--match", action="append", metavar="GLOB", help="only the managers whose names match (repeatable; 'robot-*', 'station?')"
        )
        p.add_argument(
            "--limit", type=positive_int, default=limit, metavar="N",
            help=f"at most N managers (a page; default {limit or 'all'}): the last line on stderr says how to go on",
        )  # fmt: skip
        p.add_argument("--after", metavar="NAME", help="the managers whose names sort after NAME (the next page)")

    def model_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--all", action="store_true", help='the model of every manager reachable: {"managers": [...], "next": ...}')
        page_options(p, None)

    cmds.command("model", cmd_model, model_options, client=True)

    cmds.command("managers", cmd_managers, lambda p: page_options(p, 100), client=True)

    def config_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("action", choices=["get", "set"], help="get: print the bindings; set: rebind the ports given")
        p.add_argument("name", help="the unit's name")
        p.add_argument("bindings", nargs="*", metavar="PORT=KEY", help="with set: a port and the key (or key expression, for an input) to bind it to")

    cmds.command("config", cmd_config, config_options, client=True)

    def stats_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("name", nargs="?",
                       help="the unit's name (dyknow model lists them; default: the manager itself: its lanes, how busy each is, "
                            "its overload state)")  # fmt: skip

    cmds.command("stats", cmd_stats, stats_options, client=True)

    def add_spec_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("file", type=shipped, help="a spec file (@shipped/NAME.xml: one of dyknow's own), or - for standard input")

    cmds.command("add-spec", cmd_add_spec, add_spec_options, client=True)

    def remove_spec_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("label", help="the transformation's label")

    cmds.command("remove-spec", cmd_remove_spec, remove_spec_options, client=True)

    def request_options(p: argparse.ArgumentParser) -> None:
        from dyknow.model import STANDBY_MODES

        p.add_argument("tag", help="what the stream means, a semantic tag such as 'BallTrack(field)' (quote it for the shell)")
        p.add_argument("--standby", choices=STANDBY_MODES, metavar="MODE",
                       help="'warm': keep the next-best configuration running, so a fault only moves the stream onto it; "
                            "'none' (default): re-plan and spawn when the configuration breaks")  # fmt: skip
        p.add_argument("--require", action="append", default=[], metavar="FORMULA",
                       help="a temporal formula the stream must satisfy: a false verdict moves it to the next-best configuration "
                            "(repeatable; see dyknow monitor)")  # fmt: skip

    cmds.command("request", cmd_request, request_options, client=True)

    def release_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("key", metavar="KEY_OR_TAG", help="the key dyknow request printed, or the tag it was asked for (when one request has it)")
        p.add_argument("--force", action="store_true",
                       help="give back every reference, whoever requested it (an admin's call on a manager with roles); "
                            "without it, only what this caller requested")  # fmt: skip

    cmds.command("release", cmd_release, release_options, client=True)

    def measure_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("values", nargs="+", metavar="NAME=VALUE", help="a measurement and its value, e.g. battery=0.2 (a number, else text)")

    cmds.command("measure", cmd_measure, measure_options, client=True)

    cmds.command("adaptations", cmd_adaptations, client=True)

    def monitor_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("formula", help="e.g. 'BallTrack(field).predicted implies eventually[0, 1.5s] not BallTrack(field).predicted'")
        p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C); the monitor is released")
        p.add_argument("--reorder-ms", type=float, default=0.0, metavar="MS",
                       help="the least reorder delay: how late a sample may arrive and still count; it grows with the disorder seen, up to 1 s (default 0)")
        p.add_argument("--iso", action="store_true",
                       help="print each verdict's time as ISO 8601 wall time (default: seconds since the command started)")  # fmt: skip
        p.add_argument("--changes-only", action="store_true",
                       help="print a verdict only when it differs from the last one (per object); with --mcap, each change "
                       "with the values of the formula's comparisons at it")  # fmt: skip
        p.add_argument("--mcap", metavar="FILE", help="evaluate over this recording instead, offline, with the same semantics")
        p.add_argument("--robustness", action="store_true",
                       help="at each change of the verdict, also the robustness of each subformula (how far it is from flipping); "
                            "over a recording with --changes-only")  # fmt: skip
        p.add_argument("--ontology", action="extend", nargs="+", default=[], type=shipped, metavar="FILE",
                       help="with --mcap, a formula with forall or exists: the ontologies whose individuals it ranges over")  # fmt: skip
        p.add_argument("--idle-ms", type=float, default=10_000.0, metavar="MS",  # (dyknow.reasoning.objects.DEFAULT_IDLE_NS: not imported to parse)
                       help="with --mcap, a foreach formula: an object's life ends after this long without a sample (default 10,000)")
        p.add_argument(
            "--bind", action="append", default=[], metavar="TERM=SOURCE",
            help="read a term from what exists, not planned: ros2:/TOPIC (rmw_zenoh), ros2dds:/TOPIC?type=T (DDS) or a Zenoh key; "
            "with --mcap: the topic that carries it (repeatable)",
        )  # fmt: skip
        cmds.mcap_limit_options(p, prefix="with --mcap: ")

    cmds.command("monitor", cmd_monitor, monitor_options, client=True)

    def echo_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("keyexpr", help="a key expression, or ros2:/TOPIC[?type=T] (rmw_zenoh) or ros2dds:/TOPIC?type=T (DDS), decoded")
        p.add_argument("--count", type=int, metavar="N", help="exit after N messages")
        p.add_argument("--timeout-total", type=float, metavar="S", help="give up after S seconds")
        cmds.ros2_domain_option(p)

    cmds.command("echo", cmd_echo, echo_options, client=True)
