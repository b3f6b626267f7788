"""Recording and replay: ``record``, ``replay``, ``mcap cat``, ``mcap info``."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from collections.abc import Iterable

from dyknow.cli.common import Commands, UsageError, default_endpoint, parse_pairs, print_json, read_limits, report_result, shown, tls_files


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
    return list(args.connect) or ([default_endpoint(tls_files(args))] if args.zenoh_config is None else [])


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    return stop


def cmd_record(args: argparse.Namespace) -> int:
    """record key expressions to an MCAP file until Ctrl-C/SIGTERM (or --duration, --max-messages)"""
    from dyknow.recording import Recorder

    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration: got {args.duration}; expected a positive number of seconds")
    if args.max_messages is not None and args.max_messages < 1:
        raise UsageError(f"--max-messages: got {args.max_messages}; expected a positive number")
    if args.chunk_size < 1:
        raise UsageError(f"--chunk-size: got {args.chunk_size}; expected a positive number of bytes")
    recorder = Recorder(
        args.keyexprs,
        args.output,
        connect=_zenoh_connect(args),
        zenoh_config=args.zenoh_config,
        tls=tls_files(args),
        compression=args.compression,
        chunk_size=args.chunk_size,
        max_messages=args.max_messages,
    )
    with recorder:
        stop = _stop_on_signals()  # from here on, SIGINT/SIGTERM end the recording with a complete file
        report_result(
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
    report_result(
        args,
        {"event": "done", "file": args.output, "messages": recorder.count, "topics": recorder.topics, "bytes": recorder.bytes_written},
        f"recorded {recorder.count} messages on {keys} key{'s' if keys != 1 else ''} to {args.output} ({recorder.bytes_written} bytes)",
    )
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    """replay an MCAP file into Zenoh in log-time order, at the original pace, once its consumers are
    there (--wait); exit 1 when no message reached a subscriber

    examples:
      dyknow replay run.mcap
      dyknow replay run.mcap --rate max --topics camera/front --remap camera/front=replayed/front"""
    from dyknow.recording import Player

    remap = parse_pairs(args.remap, "--remap")
    with Player(
        args.file,
        rate=args.rate,
        loop=args.loop,
        start_s=args.start,
        end_s=args.end,
        topics=args.topics,
        remap=remap,
        recover=args.recover,
        limits=read_limits(args),
    ) as player:
        stop = _stop_on_signals()
        topics = ", ".join(f"{topic} -> {key}" if key != topic else topic for topic, key in player.keys.items())
        report_result(args, {"event": "ready", "file": args.file, "keys": player.keys}, f"replaying {args.file} ({topics}); Ctrl-C to stop")
        count = player.publish(
            connect=_zenoh_connect(args), zenoh_config=args.zenoh_config, tls=tls_files(args), stop=stop, wait_s=args.wait
        )
        unmatched = {key: n for key, n in player.unmatched.items() if n}
    delivered = count - sum(unmatched.values())
    report_result(args, {"event": "done", "file": args.file, "messages": count, "unmatched": unmatched},
                  f"replayed {count} messages from {args.file}")  # fmt: skip
    if count and not delivered:
        print(f"dyknow: error: no subscriber matched any key while the {count} messages were put (waited up to --wait {args.wait:g} s "
              f"for one first): nothing was delivered; start the consumer first (a manager's unit bound to the key, dyknow echo), "
              "check --connect reaches it, or give a longer --wait", file=sys.stderr)  # fmt: skip
        return 1
    for key, n in unmatched.items():
        print(f"dyknow: warning: {n} of the messages on {key!r} were put while no subscriber matched it: delivered to no one",
              file=sys.stderr)  # fmt: skip
    return 0


def cmd_mcap_cat(args: argparse.Namespace) -> int:
    """print the messages in log-time order (--json: one JSON object per message and line: topic, sequence,
    log_time, publish_time, schema, message_encoding, data_b64)"""
    from dyknow.recording import Player

    with Player(args.file, topics=args.topics, recover=args.recover, decode=False, limits=read_limits(args)) as player:
        try:
            for record in player.messages():
                if args.json:
                    print_json(record.to_dict())
                    continue
                channel = record.channel
                if channel.message_encoding in ("json",) or channel.message_encoding.startswith("text/"):
                    preview = record.data[:80].decode(errors="replace") + ("..." if len(record.data) > 80 else "")
                else:
                    preview = f"<{len(record.data)} bytes>"
                kind = channel.schema_name or channel.message_encoding
                # (topics and payloads were recorded off the network: shown escaped)
                print(shown(f"{record.log_time_ns} {record.topic} #{record.sequence} [{kind}] {preview}"))
        except BrokenPipeError:  # the reader went away (| head): stop quietly
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


def cmd_mcap_info(args: argparse.Namespace) -> int:
    """summarise channels, counts and time range"""
    from datetime import UTC, datetime

    from dyknow.recording import Recording

    with Recording(args.file, recover=args.recover, limits=read_limits(args)) as recording:
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

    report_result(args, info.to_dict(), text)
    return 0


def add_commands(cmds: Commands) -> None:
    """Add this family's commands to the parser."""
    zenoh_options = cmds.zenoh_options

    def record_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("keyexprs", nargs="+", metavar="KEYEXPR", help="key expressions to record, e.g. 'robot/**'")
        p.add_argument("-o", "--output", required=True, metavar="FILE.mcap", help="the MCAP file to write")
        p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
        p.add_argument("--max-messages", type=int, metavar="N", help="stop after N messages")
        p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd", help="chunk compression (default zstd)")
        p.add_argument("--chunk-size", type=int, default=1024 * 1024, metavar="BYTES", help="uncompressed chunk size (default 1 MiB)")
        zenoh_options(p, connect_help=cmds.connect_help())

    cmds.command("record", cmd_record, record_options)

    def replay_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("file", metavar="FILE.mcap", help="an MCAP file (dyknow record's, or any writer's)")
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
            "--wait", type=float, default=5.0, metavar="S",
            help="first wait up to S seconds for a subscriber on every key (default 5; it starts as soon as every key has one); "
            "exit 1 when no message reached a subscriber"
        )
        cmds.mcap_limit_options(p)
        zenoh_options(p, connect_help=cmds.connect_help())

    cmds.command("replay", cmd_replay, replay_options)

    mcap = cmds.group("mcap", help="inspect MCAP files (cat, info)", description="inspect MCAP files, whoever wrote them")

    def cat_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("file", metavar="FILE.mcap", help="an MCAP file")
        p.add_argument(
            "--topics", nargs="+", action="extend", default=[], metavar="T", help="only these topics (names, keys or key expressions)"
        )
        p.add_argument("--recover", action="store_true", help="print what is valid in a truncated or corrupt file, with a warning")
        cmds.mcap_limit_options(p)

    mcap.command("cat", cmd_mcap_cat, cat_options)

    def info_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("file", metavar="FILE.mcap", help="an MCAP file")
        p.add_argument("--recover", action="store_true", help="summarise what is valid in a truncated or corrupt file")
        cmds.mcap_limit_options(p)

    mcap.command("info", cmd_mcap_info, info_options)
