"""The ``dyknow`` command line.

Thin by design: every subcommand is a small function over the public API, in the module of its
family: :mod:`~dyknow.cli.serve` (manager, router, ui, foxglove), :mod:`~dyknow.cli.client`
(the commands that talk to a manager), :mod:`~dyknow.cli.offline` (certs, validate, expand,
plan, paths), :mod:`~dyknow.cli.mcap` (record, replay, mcap), :mod:`~dyknow.cli.operate` (hz, top,
doctor), :mod:`~dyknow.cli.ros2` (echo of ROS 2 topics, ros2 list) and :mod:`~dyknow.cli.demo`; the options
they share are declared once, in :mod:`~dyknow.cli.common`. ``--json`` gives
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
    dyknow hz KEYEXPR [--window N] | dyknow top [--interval S] [--once] | dyknow doctor [--listen ENDPOINT]
    dyknow paths                                   (offline)

Client commands reach a manager with ``--connect ENDPOINT`` (default tcp/127.0.0.1:7447) and
``--manager NAME`` (default ``dyknow``).
"""

from __future__ import annotations

import argparse
import atexit
import logging
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from dyknow.cli import client, demo, mcap, offline, operate, ros2, serve
from dyknow.cli.common import DEFAULT_MANAGER, Commands, UsageError, shown

__all__ = ["DEFAULT_MANAGER", "main", "run"]


def _parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser; ``selected``: only that command's options are declared (the
    others are listed), so that a command imports what it needs and no more."""
    parser = argparse.ArgumentParser(prog="dyknow", description="Reconfigurable stream reasoning on Eclipse Zenoh.")
    parser.add_argument("--version", action="version", version=f"dyknow {_version()}")
    commands = Commands(parser.add_subparsers(dest="command", required=True, metavar="COMMAND"), selected)
    for family in (serve, offline, demo, mcap, client, operate, ros2):
        family.add_commands(commands)
    return parser


def _version() -> str:
    from dyknow import __version__

    return __version__


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = _parser(selected=next((word for word in argv if not word.startswith("-")), ""))
    args = parser.parse_args(argv)
    logging.basicConfig(level=os.environ.get("DYKNOW_LOG", "WARNING").upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for handler in logging.getLogger().handlers:
        handler.addFilter(_shown_record)
    from dyknow.errors import DyKnowError, SpecError

    try:
        return int(args.fn(args))
    except UsageError as exc:
        parser.error(shown(exc))
    except SpecError as exc:  # (a manager's refusal carries its issues: another process's text, shown escaped)
        for issue in exc.issues:
            print(shown(issue), file=sys.stderr)
        return 1
    except DyKnowError as exc:
        print(f"dyknow: error: {shown(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        if os.environ.get("DYKNOW_DEBUG"):
            raise
        print(
            f"dyknow: internal error: {type(exc).__name__}: {shown(exc)} (set DYKNOW_DEBUG=1 for a traceback, and please report it)",
            file=sys.stderr,
        )
        return 70
    return 2


def _shown_record(record: logging.LogRecord) -> bool:
    """A log line's message :func:`~dyknow.cli.common.shown` (it may quote a peer's words); its traceback, if any, as it is."""
    try:
        record.msg, record.args = shown(record.getMessage()), None
    except Exception:  # (a message that does not format: logging says so itself)
        pass
    return True


def run(argv: Sequence[str] | None = None) -> NoReturn:
    """The ``dyknow`` program: :func:`main` (over ``argv``, by default the command line's), then
    an exit without the interpreter's teardown.

    Zenoh's threads outlive a closed session; one that calls into Python (to end a query, say)
    while the interpreter is being torn down is ended by it mid-call, and the process aborts
    ("FATAL: exception not rethrown", exit -6) when it had finished its work. So the program
    exits as Python does up to its teardown (the sessions still open closed, the threads joined,
    the exit handlers run), and then, by the exit handler registered first (which runs last),
    with the command's code, logs and output flushed, before the teardown begins.
    """
    code = [1]
    atexit.register(_leave, code)
    try:
        code[0] = main(argv)
    except SystemExit as exc:  # argparse's errors and --help/--version, or a command's own exit
        code[0] = _exit_code(exc.code)
    sys.exit(code[0])


def _leave(code: list[int]) -> None:
    """The last exit handler of :func:`run`: flush what is said, and end the process with ``code``."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing left to say
            pass
    os._exit(code[0])


def _exit_code(code: object) -> int:
    """The status ``SystemExit(code)`` ends a program with (a message is printed, status 1)."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1
