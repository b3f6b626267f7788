"""An operator's tools: ``hz`` (a stream's rate, jitter and sizes), ``top`` (every manager and
unit, live) and ``doctor`` (what is wrong with a set-up, and the fix)."""

from __future__ import annotations

import argparse
import shutil
import signal
import sys
import threading
import time
from collections.abc import Iterable
from typing import Any

from dyknow.cli.common import Commands, UsageError, open_client, positive_int, print_json, report_result, seconds, shown, tls_files


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    return stop


def _why_silent(client: Any, keyexpr: str) -> tuple[str, str] | None:
    """Why nothing comes on ``keyexpr``, as the managers know it (``(why, fix)``), when it is a
    manager's key (``dyknow/<manager>/...``): that manager LOST, or a degraded request of its on
    that key; None when nothing known explains it."""
    from dyknow import keys, presence
    from dyknow.errors import DyKnowError

    chunks = keyexpr.split("/")
    if len(chunks) < 2 or chunks[0] != keys.DATA_ROOT or any(c in chunks[1] for c in "*$"):
        return None
    manager = chunks[1]
    try:
        names = client.manager_names(timeout_s=0.5)
        if manager not in names:
            loss = client.recall_lost(names).get(manager)
            return None if loss is None else (f"it is a key of manager {manager!r}, and {loss.said()}", loss.fix())
        known = presence.health(client, [manager]).get(manager)
    except DyKnowError:
        return None
    for request in known.degraded if known is not None else ():
        if keys.includes(keyexpr, request["key"]) or keys.includes(request["key"], keyexpr):
            return (
                f"it is the key of request {request['tag']} of manager {manager!r}, which is degraded: {request.get('reason') or 'no reason given'}",
                f"the request back on a full configuration, which it returns to by itself once one exists "
                f"(dyknow plan '{request['tag']}' --manager {manager} says what is missing now)",
            )
    return None


def cmd_hz(args: argparse.Namespace) -> int:
    """print the rate, interval jitter, message sizes and bandwidth of the streams on a key expression
    (as ros2 topic hz and bw do), every --every seconds over the last --window messages

    examples:
      dyknow hz 'dyknow/robot/src/out'
      dyknow hz 'dyknow/robot/**' --window 50 --duration 10 --json"""
    from dyknow.meter import StreamMeter
    from dyknow.transport import check_key_expr

    check_key_expr(args.keyexpr, what="hz")
    meter = StreamMeter(window=args.window)
    why: list[tuple[str, str] | None] = []  # why nothing comes, once asked (at the first silent report)
    with open_client(args) as client:
        subscriber = client.session.declare_sample_subscriber(
            args.keyexpr, lambda key, payload, attachment: meter.add(key, len(payload) + len(attachment or b""))
        )
        try:
            stop = _stop_on_signals()
            deadline = None if args.duration is None else time.monotonic() + args.duration
            while not stop.wait(args.every if deadline is None else max(0.0, min(args.every, deadline - time.monotonic()))):
                figures = meter.figures()
                if args.json:
                    for f in figures:
                        print_json(f.to_dict())
                else:
                    if not figures:
                        if not why and not meter.counts():
                            why.append(_why_silent(client, args.keyexpr))
                        said = f": {why[0][0]}" if why and why[0] is not None and not meter.counts() else ""
                        print(shown(f"no messages on {args.keyexpr!r} yet" + ("" if not meter.counts() else " (one so far)") + said), flush=True)
                    for f in figures:  # (keys are the publishers' choice: shown escaped)
                        print(shown(f), flush=True)
                if deadline is not None and time.monotonic() >= deadline:
                    break
            if not meter.counts() and not why:
                why.append(_why_silent(client, args.keyexpr))
        finally:
            subscriber.undeclare()
    if not meter.counts():
        if why and why[0] is not None:
            print(shown(f"dyknow: error: no message on {args.keyexpr!r}: {why[0][0]}; expected {why[0][1]}"), file=sys.stderr)
        else:
            print(f"dyknow: error: no message on {args.keyexpr!r} (is anything publishing there? dyknow model shows the keys)", file=sys.stderr)
        return 1
    return 0


def _rates(previous: dict[str, Any] | None, snap: dict[str, Any]) -> dict[str, Any]:
    """Rates between two snapshots of one manager: per unit msgs/s in and out, CPU share."""
    dt = (snap["time_ns"] - previous["time_ns"]) / 1e9 if previous else 0.0
    before = {u["name"]: u for u in previous["units"]} if previous else {}
    rows = []
    for unit in snap["units"]:
        old = before.get(unit["name"])
        ins = sum(p["messages"] for p in unit["ports"].values() if p["direction"] == "in")
        outs = sum(p["messages"] for p in unit["ports"].values() if p["direction"] == "out")
        old_in = sum(p["messages"] for p in old["ports"].values() if p["direction"] == "in") if old else ins
        old_out = sum(p["messages"] for p in old["ports"].values() if p["direction"] == "out") if old else outs
        in_hz = (ins - old_in) / dt if dt > 0 else 0.0
        out_hz = (outs - old_out) / dt if dt > 0 else 0.0
        callbacks = in_hz if any(p["direction"] == "in" for p in unit["ports"].values()) else out_hz
        hops = [p["hop"] for p in unit["ports"].values() if p["direction"] == "in" and p.get("hop", {}).get("count")]
        rows.append(
            {
                "name": unit["name"],
                "label": unit["label"],
                "state": unit["state"],
                "cpu_pct": round(unit["callback_avg_us"] * callbacks / 1e4, 2),  # callback time x rate
                "in_hz": round(in_hz, 1),
                "out_hz": round(out_hz, 1),
                "queued": sum(p.get("queued", 0) for p in unit["ports"].values()),
                "dropped": sum(p["dropped"] for p in unit["ports"].values()),
                "lost": sum(p.get("lost", 0) for p in unit["ports"].values()),
                "hop_p50_us": max((h["p50_us"] for h in hops), default=None),
                "hop_p99_us": max((h["p99_us"] for h in hops), default=None),
                "error": unit.get("error"),
            }
        )
    cpu = (snap["cpu_s"] - previous["cpu_s"]) / dt * 100 if previous and dt > 0 else None
    return {"manager": snap["manager"], "cpu_pct": None if cpu is None else round(cpu, 1), "threads": snap["threads"],
            "adaptations": sum(snap["adaptations"].values()), "units": rows, "requests": snap.get("requests", [])}  # fmt: skip


def _table(views: list[dict[str, Any]], errors: dict[str, str], interval: float, width: int, lost: Iterable[Any] = ()) -> list[str]:
    lines = [f"dyknow top - {time.strftime('%H:%M:%S')}, every {interval:g} s; cpu: process for a manager, callback time x rate for a unit; Ctrl-C to quit"]
    header = f"{'UNIT':<24} {'LABEL':<22} {'STATE':<8} {'CPU%':>6} {'IN/s':>8} {'OUT/s':>8} {'QUEUE':>5} {'DROP':>6} {'LOST':>6} {'HOP p50':>9} {'p99 us':>9}"
    for view in views:
        cpu = "-" if view["cpu_pct"] is None else f"{view['cpu_pct']:.1f}"
        lines += ["", f"manager {view['manager']}: cpu {cpu} %, {view['threads']} threads, {len(view['units'])} units, "
                  f"{view['adaptations']} adaptations", header[:width]]  # fmt: skip
        for u in view["units"]:
            p50 = "-" if u["hop_p50_us"] is None else f"{u['hop_p50_us']:.0f}"
            p99 = "-" if u["hop_p99_us"] is None else f"{u['hop_p99_us']:.0f}"
            row = (f"{u['name'][:24]:<24} {u['label'][:22]:<22} {u['state'][:8]:<8} {u['cpu_pct']:>6.2f} {u['in_hz']:>8.1f} {u['out_hz']:>8.1f} "
                   f"{u['queued']:>5} {u['dropped']:>6} {u['lost']:>6} {p50:>9} {p99:>9}")  # fmt: skip
            lines.append(row[:width])
            if u["error"]:
                lines.append(f"  error: {u['error']}"[:width])
        for r in view["requests"]:  # (a degraded one whole, with why: it is what the operator looks for)
            if r["state"] == "degraded":
                lines.append(f"request {r['tag']} on {r['key']}: DEGRADED: {r.get('reason') or 'no reason given'}")
            else:
                lines.append(f"request {r['tag']} on {r['key']}: {r['state']}"[:width])
    for loss in lost:
        lines += ["", loss.said()]  # "manager 'robot' is LOST since ..."
    for name, why in errors.items():
        lines += ["", f"manager {name}: {why}"]  # (whole: why a manager is left out, however wide the terminal)
    return lines


def cmd_top(args: argparse.Namespace) -> int:
    """a live view of every manager reachable and its units: CPU, messages in and out a second,
    queue depth, drops, lost, hop p50/p99; refreshed every --interval seconds (one get_metrics
    call per manager)

    examples:
      dyknow top
      dyknow top --manager robot --interval 2
      dyknow top --once --json      # one snapshot with rates, for scripts"""
    from dyknow.errors import DyKnowError
    from dyknow.presence import THIS_CLIENT, merge

    stop = _stop_on_signals()
    previous: dict[str, dict[str, Any]] = {}
    interactive = sys.stdout.isatty() and not args.json and not args.once
    with open_client(args) as client:
        why = client.unreachable()
        if why is not None:
            raise why
        first = True
        while True:
            names = [args.manager] if args.only else sorted(client.manager_names(timeout_s=0.5))
            views, errors = [], {}
            for name in names:
                try:
                    snap = client.call_manager(name, "get_metrics", {})
                except DyKnowError as exc:
                    errors[name] = str(exc)
                    continue
                views.append(_rates(previous.get(name), snap))
                previous[name] = snap
            if args.once and first:
                first = False  # rates need two snapshots: take the second after --interval
                if not stop.wait(args.interval):
                    continue
            # the managers lost and not back, as this client saw them go and as those up remember
            reports = [(THIS_CLIENT, client.seen_lost()), *((v["manager"], previous[v["manager"]].get("lost", [])) for v in views)]
            lost = list(merge(reports, up=[v["manager"] for v in views]).values())
            if args.json:
                print_json({"time_ns": time.time_ns(), "managers": views, "errors": errors, "lost": [x.to_dict() for x in lost]})
            else:
                width = shutil.get_terminal_size((160, 40)).columns
                # (names, labels, states and errors are the managers' word: shown escaped)
                table = _table(views, {n: e for n, e in errors.items() if n not in {x.manager for x in lost}}, args.interval, width, lost)
                lines = [shown(line) for line in table] if names or lost else ["no manager reachable"]
                if interactive:
                    sys.stdout.write("\x1b[H\x1b[2J" + "\n".join(lines) + "\n")
                    sys.stdout.flush()
                else:
                    print("\n".join(lines), flush=True)
            if args.once or stop.wait(args.interval):
                break
    return 0 if not errors else 1


def cmd_doctor(args: argparse.Namespace) -> int:
    """diagnose this set-up and name the fix for each problem: the Zenoh configuration, /dev/shm,
    the port a manager would listen on, each --connect endpoint, the managers reachable, their
    ACLs, and the offsets between their clocks; exit 1 when a check fails

    examples:
      dyknow doctor
      dyknow doctor --connect tcp/10.0.0.2:7447 --manager station
      dyknow doctor --listen tcp/127.0.0.1:7448 --zenoh-config robot.json5 --json"""
    from dyknow.doctor import diagnose
    from dyknow.transport import DEFAULT_ENDPOINT

    tls = tls_files(args)
    connect = list(args.connect) or ([DEFAULT_ENDPOINT.replace("tcp/", "tls/", 1) if tls else DEFAULT_ENDPOINT] if args.zenoh_config is None else [])
    listen = list(args.listen)  # (without it, the first --connect when it is this host's address)
    if args.max_clock_offset_ms <= 0:
        raise UsageError(f"--max-clock-offset-ms: got {args.max_clock_offset_ms}; expected a positive number")
    found = diagnose(connect=connect, listen=listen, manager=args.manager, zenoh_config=args.zenoh_config, tls=tls,
                     max_offset_ms=args.max_clock_offset_ms)  # fmt: skip
    failed = [d for d in found if d.status == "fail"]

    def text() -> Iterable[str]:
        yield from (line for d in found for line in d.lines())
        warned = sum(d.status == "warn" for d in found)
        yield f"{len(failed)} failed, {warned} warnings, {len(found) - len(failed) - warned} ok"

    report_result(args, [d.to_dict() for d in found], text)
    return 1 if failed else 0


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""

    def hz_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("keyexpr", metavar="KEYEXPR", help="a key or key expression, e.g. 'dyknow/robot/**' (each key gets its own line)")
        p.add_argument("--window", type=positive_int, default=100, metavar="N", help="messages the figures are computed over (default 100)")
        p.add_argument("--every", type=seconds, default=1.0, metavar="S", help="print every S seconds (default 1)")
        p.add_argument("--duration", type=seconds, metavar="S", help="stop after S seconds (default: until Ctrl-C)")

    cmds.command("hz", cmd_hz, hz_options, client=True)

    def top_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--interval", type=seconds, default=1.0, metavar="S", help="refresh every S seconds (default 1)")
        p.add_argument("--once", action="store_true", help="print one view (two snapshots --interval apart, for the rates) and exit")
        p.add_argument("--only", action="store_true", help="only --manager, not every manager reachable")

    cmds.command("top", cmd_top, top_options, client=True)

    def doctor_options(p: argparse.ArgumentParser) -> None:
        from dyknow.doctor import DEFAULT_MAX_OFFSET_MS

        p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="where a manager would listen, to check the port is free (default: the first --connect, "
                            "when it is an address of this host)")  # fmt: skip
        p.add_argument("--max-clock-offset-ms", type=float, default=DEFAULT_MAX_OFFSET_MS, metavar="MS",
                       help=f"fail when two managers' clocks are further apart (default {DEFAULT_MAX_OFFSET_MS:g})")  # fmt: skip

    cmds.command("doctor", cmd_doctor, doctor_options, client=True)

