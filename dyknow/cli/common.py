"""What every command shares: usage errors, output (text or ``--json``), ``NAME=VALUE`` pairs, and the
client that reaches a manager (``--connect``, TLS, ``--wait``).

The command starts fast: this module and each family's imports only what parsing needs, and a
command's options are declared only when that command is the one run (:class:`Commands`), so
``dyknow --help`` imports none of the middleware and ``dyknow model`` none of the planner's.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import inspect
import json
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dyknow.client import Client
    from dyknow.recording.framing import ReadLimits

DEFAULT_MANAGER = "dyknow"

#: A command's options: a function that adds them to its parser (run only when the command is).
Options = Callable[[argparse.ArgumentParser], None]


class UsageError(Exception):
    """A command line that parses but makes no sense (exit code 2)."""


def shown(text: object) -> str:
    """``text`` as a terminal may show it: every character that is not printable (control
    characters and escapes, line breaks, bidirectional overrides such as U+202E, other formatting
    characters) written as its Python escape (``\\x1b``, ``\\n``, ``\\u202e``).

    What a command prints comes from the network (a manager's reply, a key, a peer's error): printed
    raw, an escape would retitle the window, clear the screen or write a line that seems the
    command's own (``docs/howto/security.md``). Every line people read goes through here.

    >>> shown("ok\\x1b]0;pwned\\x07 \\u202etxt.exe")
    'ok\\\\x1b]0;pwned\\\\x07 \\\\u202etxt.exe'
    """
    text = str(text)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def print_json(data: Any) -> None:
    """``data`` as one line of JSON (ASCII: every other character escaped, so JSON shows no terminal escape either)."""
    sys.stdout.write(json.dumps(data, indent=None, separators=(",", ":")) + "\n")
    sys.stdout.flush()


def report_result(args: argparse.Namespace, data: Any, text: str | Iterable[str] | Callable[[], Iterable[str]]) -> None:
    """How every command ends: ``data`` as one JSON line with ``--json``, else ``text`` for people,
    each line :func:`shown` (one line each: a line break inside one is shown escaped)."""
    if args.json:
        print_json(data)
        return
    lines = text() if callable(text) else [text] if isinstance(text, str) else text
    for line in lines:
        print(shown(line), flush=True)


def parse_pairs(items: Sequence[str], what: str) -> dict[str, str]:
    result: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise UsageError(f"{what}: got {item!r}; expected NAME=VALUE")
        result[name] = value
    return result


def parse_value(text: str) -> float | str:
    try:
        return float(text)
    except ValueError:
        return text


def positive_int(text: str) -> int:
    """An argparse type: a whole number of at least 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a positive whole number")
    return value


def seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 <= value < 1e9:  # (nan fails too)
        raise argparse.ArgumentTypeError(f"got {text!r}; expected seconds, a number of 0 or more such as 10 or 0.5")
    return value


def shipped(text: str) -> str:
    """A path option's value, where ``@shipped``, ``@testing`` and ``@pipeline`` name the shipped folders
    (:func:`dyknow.resources.shipped_path`), so a documented command line works from any folder."""
    from pathlib import Path

    from dyknow.resources import shipped_path, specs_dir

    try:
        path = shipped_path(text)
    except (ValueError, FileNotFoundError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    parts = Path(text).parts
    if parts and parts[0] == "specs" and not Path(text).exists():  # the checkout's path, from another folder
        shipped = Path("@shipped", *parts[1:]).as_posix()
        with contextlib.suppress(FileNotFoundError):
            if (specs_dir().joinpath(*parts[1:])).exists():
                raise argparse.ArgumentTypeError(f"{text}: no such file in {Path.cwd()}; dyknow's shipped copy is {shipped} (dyknow paths)")
    return path


def name_list(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected names separated by commas, such as manager,operator")
    return names


def tls_files(args: argparse.Namespace) -> Any:
    from dyknow.access import TlsFiles

    return TlsFiles.from_options(args.tls_ca, args.tls_cert, args.tls_key)


def default_endpoint(tls: Any) -> str:
    from dyknow.transport import DEFAULT_ENDPOINT

    return DEFAULT_ENDPOINT.replace("tcp/", "tls/", 1) if tls is not None else DEFAULT_ENDPOINT


def open_client(args: argparse.Namespace) -> Client:
    from dyknow.client import Client

    tls = tls_files(args)
    connect = args.connect or ([default_endpoint(tls)] if args.zenoh_config is None else [])
    client = Client(args.manager, connect=connect, zenoh_config=args.zenoh_config, timeout_s=args.timeout, tls=tls, lease_ms=args.lease_ms)
    wait = getattr(args, "wait", 0.0)
    if wait < 0:
        client.close()
        raise UsageError(f"--wait: got {wait}; expected a number of seconds, 0 or more")
    deadline = time.monotonic() + wait
    try:  # --wait: until the manager is there (or the time is up: the call then says what is wrong)
        while wait and time.monotonic() < deadline and args.manager not in client.manager_names(timeout_s=0.3):
            time.sleep(0.1)
    except BaseException:
        client.close()
        raise
    return client


class HelpFormatter(argparse.HelpFormatter):
    """argparse's, but a command's examples (its epilog) are shown as written, line by line."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("examples:"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


def command_help(fn: Callable[..., Any]) -> tuple[str, str | None]:
    """A command's help (the first paragraph of its function's docstring) and its examples (a
    paragraph that starts with ``examples:``, shown as written)."""
    doc = inspect.cleandoc(fn.__doc__ or "")
    paragraphs = doc.split("\n\n")
    examples = next((p for p in paragraphs if p.startswith("examples:")), None)
    return " ".join(paragraphs[0].split()), examples


class Commands:
    """What each family's ``add_commands`` declares its commands with: the options every command
    of a kind shares are declared here, once.

    Every command is listed (``dyknow --help``, a typo's "invalid choice"), but its options are
    added only when it is the command being run (``selected``, the first word of the command line
    that is not an option; ``None``: every command, as the site's reference and the tests build
    it). Declaring options imports what their defaults and choices come from, and a command
    should not pay for its neighbours'.
    """

    def __init__(self, sub: Any, selected: str | None = None) -> None:
        self.sub = sub
        self.selected = selected

    def wanted(self, name: str) -> bool:
        """Whether the options of command ``name`` are needed for this command line."""
        return self.selected is None or self.selected == name

    def command(self, name: str, fn: Callable[[argparse.Namespace], int], options: Options | None = None, client: bool = False) -> None:
        """A subcommand whose help is ``fn``'s docstring and whose own options ``options`` adds;
        ``client``: it reaches a manager (the client options: --connect, TLS, --manager,
        --timeout, --wait, --lease-ms)."""
        help, examples = command_help(fn)
        p: argparse.ArgumentParser = self.sub.add_parser(name, help=help, description=help, epilog=examples, formatter_class=HelpFormatter)
        p.set_defaults(fn=fn)
        if not self.wanted(name):
            return
        p.add_argument("--json", action="store_true", help="machine-readable output")
        if client:
            self.client_options(p)
        if options is not None:
            options(p)

    def group(self, name: str, help: str, description: str) -> Commands:
        """A command of subcommands (``dyknow mcap cat``): the Commands to declare them with."""
        p = self.sub.add_parser(name, help=help, description=description)
        sub = p.add_subparsers(dest=f"{name}_command", required=True, metavar="COMMAND")
        return Commands(sub, selected=None) if self.wanted(name) else _Listed(sub)

    def client_options(self, p: argparse.ArgumentParser) -> None:
        """The options of every command that reaches a manager."""
        from dyknow.transport import DEFAULT_ENDPOINT

        self.zenoh_options(p, connect_help=f"Zenoh endpoint of the manager (default {DEFAULT_ENDPOINT})")
        p.add_argument("--manager", default=DEFAULT_MANAGER, metavar="NAME", help=f"the manager's name (default {DEFAULT_MANAGER})")
        p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="seconds to wait for the manager (default 5)")
        p.add_argument("--wait", type=float, default=0.0, metavar="S",
                       help="first wait up to S seconds for the manager to come up (one started just before); "
                       "without it a manager that is not there is reported at once")  # fmt: skip
        self.lease_option(p)

    @staticmethod
    def connect_help(what: str = "Zenoh endpoint to connect to") -> str:
        """``--connect``'s help, with the default endpoint."""
        from dyknow.transport import DEFAULT_ENDPOINT

        return f"{what} (default {DEFAULT_ENDPOINT})"

    @staticmethod
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

    @staticmethod
    def ros2_domain_option(p: argparse.ArgumentParser) -> None:
        """--ros2-domain, for every command that reaches ROS 2 topics."""
        p.add_argument("--ros2-domain", type=ros2_domain_number, metavar="N",
                       help="the ROS 2 domain for ros2: bindings and topics (default ROS_DOMAIN_ID, else 0)")  # fmt: skip

    @staticmethod
    def lease_option(p: argparse.ArgumentParser) -> None:
        """--lease-ms, for every command whose session must notice a host cut off."""
        p.add_argument("--lease-ms", type=positive_int, metavar="MS",
                       help="how long a silent link lives (default Zenoh's 10000): a host cut off is noticed after about this; "
                            "shorter is sooner, with more keep-alive traffic and false alarms on a slow link")  # fmt: skip

    @staticmethod
    def limit_options(p: argparse.ArgumentParser) -> None:
        """--max-expansions, for every command that expands templates."""
        from dyknow.spec.model import DEFAULT_MAX_EXPANSIONS

        p.add_argument("--max-expansions", type=positive_int, default=DEFAULT_MAX_EXPANSIONS, metavar="N",
                       help=f"refuse a template that expands to more specs (default {DEFAULT_MAX_EXPANSIONS})")  # fmt: skip

    @staticmethod
    def mcap_limit_options(p: argparse.ArgumentParser, prefix: str = "") -> None:
        """--max-chunk-bytes and --max-memory-bytes, for every command that reads MCAP files
        (``read_limits(args)`` gives them as ReadLimits); ``prefix`` starts their help."""
        from dyknow.recording.framing import ReadLimits

        chunk, memory = ReadLimits().max_chunk_bytes, ReadLimits().max_memory_bytes
        p.add_argument("--max-chunk-bytes", type=positive_int, default=chunk, metavar="N",
                       help=f"{prefix}refuse a chunk declaring more bytes uncompressed, before reading it (default {chunk}: {chunk >> 20} MiB)")  # fmt: skip
        p.add_argument("--max-memory-bytes", type=positive_int, default=memory, metavar="N",
                       help=f"{prefix}refuse to hold more decompressed bytes at once: the chunk being read and the messages of "
                       f"chunks whose time ranges overlap (default {memory}: {memory >> 30} GiB)")  # fmt: skip



class _Listed(Commands):
    """The subcommands of a group that is not the command being run: listed, no options."""

    def wanted(self, name: str) -> bool:
        return False


def read_limits(args: argparse.Namespace) -> ReadLimits:
    """The ReadLimits of a command's --max-chunk-bytes and --max-memory-bytes."""
    from dyknow.recording.framing import ReadLimits

    return ReadLimits(max_chunk_bytes=args.max_chunk_bytes, max_memory_bytes=args.max_memory_bytes)


def payload_json(payload: Any) -> Any:
    """A payload as JSON can hold it: arrays described (also inside a JSON-like value: a ROS 2
    message's large arrays), bytes in base64 (the first 4 KiB)."""
    import numpy as np

    if isinstance(payload, np.ndarray):
        return {"ndarray": {"dtype": str(payload.dtype), "shape": list(payload.shape)}}
    if isinstance(payload, (bytes, bytearray)):
        return {"bytes": len(payload), "base64": base64.b64encode(payload[:4096]).decode()}
    if isinstance(payload, dict):
        return {key: payload_json(value) for key, value in payload.items()}
    if isinstance(payload, (list, tuple)):
        return [payload_json(value) for value in payload]
    return payload


def ros2_domain_number(text: str) -> int:
    """--ros2-domain's value: a ROS_DOMAIN_ID."""
    if not text.isdigit() or int(text) > 232:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a ROS_DOMAIN_ID from 0 to 232")
    return int(text)


def ros2_domain(args: argparse.Namespace) -> int:
    """The ROS 2 domain: --ros2-domain, else ROS_DOMAIN_ID, else 0."""
    if args.ros2_domain is not None:
        return int(args.ros2_domain)
    text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    if not text.isdigit() or int(text) > 232:
        raise UsageError(f"ROS_DOMAIN_ID={text!r}; expected a number from 0 to 232 (or --ros2-domain)")
    return int(text)
