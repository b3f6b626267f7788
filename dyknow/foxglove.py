"""Live dyknow streams in Foxglove or Lichtblick: ``dyknow foxglove``.

``dyknow foxglove [--connect ENDPOINT] [--host 127.0.0.1] [--port 8765] [KEYEXPR ...]`` subscribes
to the key expressions (default ``dyknow/**``: every stream) as a Zenoh client, like ``dyknow ui``,
and serves what arrives over the Foxglove WebSocket protocol with the ``foxglove-sdk`` package.
Open ``ws://127.0.0.1:8765`` in Foxglove (Open connection, Foxglove WebSocket) or in a Lichtblick
that speaks the SDK's subprotocol ``foxglove.sdk.v1`` (older Lichtblick releases ask only for
``foxglove.websocket.v1``, which the SDK refuses).

Each dyknow key becomes one channel (its topic is the key), created when the key carries its
first message. Payloads are encoded as ``dyknow record`` writes them (:mod:`dyknow.recording.codecs`),
so a live view and a recording look the same:

======================  ===================================  ==================  ==============================
payload                 schema                               message encoding    message
======================  ===================================  ==================  ==============================
image array             ``foxglove.RawImage``                ``protobuf``        mono8, bgr8, bgra8 or mono16
JPEG, PNG, WebP bytes   ``foxglove.CompressedImage``         ``protobuf``        the compressed bytes
other numpy array       ``dyknow.NDArray``                   ``protobuf``        dtype, shape, bytes
JSON object             JSON schema named after the key,     ``json``            the JSON text dyknow sends
                        from its first message
other JSON value        the same                             ``json``            ``{"value": ...}``
``str``                 the same                             ``json``            ``{"text": ...}``
other ``bytes``         not served (one warning per key)
======================  ===================================  ==================  ==============================

A message's log time (the time Foxglove shows) is when its data was captured (``origin_ns``), on
this host's clock: a time another host's clock took is corrected by the offset the client's
manager estimates for that clock (:meth:`Client.follow_clocks`, this host's clock taken as the
manager's); one of a clock whose offset is not known yet is logged as stamped and counted in
:attr:`Bridge.unknown_clock`.
A key whose payload type changes gets a new channel in place of its old one. At most
``max_channels`` keys (default :data:`MAX_CHANNELS`) get a channel; messages on further keys
are skipped, with a warning. Messages are encoded only while a client subscribes to their
channel; each client has a bounded queue (:data:`BACKLOG`) whose oldest messages are dropped
when it falls behind.

The protocol has no access control: whoever reaches the port sees every stream served. The
server binds loopback unless told otherwise, and it is closed to other web pages: the SDK's
server listens on a loopback port of its own, behind a :class:`~dyknow.webguard.OriginGuard` on
the port served, which refuses (403) a WebSocket upgrade whose ``Host`` is not a name it serves
(a DNS-rebound page) or whose ``Origin`` is not allowed: by default none but the Foxglove web app
(:data:`FOXGLOVE_ORIGINS`); ``--allow-origin URL`` adds one (a self-hosted Lichtblick, say).
Desktop apps (Foxglove, Lichtblick) send no ``Origin`` and are served.
"""

from __future__ import annotations

import itertools
import json
import logging
import signal
import threading
from collections.abc import Callable, Iterable
from typing import Any

import foxglove

from dyknow.client import Client, ClockView
from dyknow.errors import RecordingError, TransportError
from dyknow.message import Message
from dyknow.recording.codecs import PAYLOAD_METADATA, PROTOBUF_SCHEMAS, encode, json_schema
from dyknow.transport import Subscriber, check_key_expr
from dyknow.webguard import OriginGuard

__all__ = ["BACKLOG", "DEFAULT_KEYEXPR", "DEFAULT_PORT", "FOXGLOVE_ORIGINS", "MAX_CHANNELS", "Bridge", "run_bridge"]

log = logging.getLogger(__name__)

#: The web pages that may open the bridge besides its own origin: the Foxglove web app.
FOXGLOVE_ORIGINS: tuple[str, ...] = ("https://app.foxglove.dev",)
#: What is served unless told otherwise: every dyknow stream.
DEFAULT_KEYEXPR = "dyknow/**"
#: Foxglove's usual WebSocket port.
DEFAULT_PORT = 8765
#: The most keys that get a channel.
MAX_CHANNELS = 1000
#: Messages queued per client; the oldest are dropped when a client falls behind (frames are
#: large: 128 full-HD frames are 800 MB).
BACKLOG = 128

# A channel's signature: (message encoding, schema name); schema name "" for JSON.
_Signature = tuple[str, str]


class _Stream:
    """The channel of one key and the kind of payload it was created for."""

    __slots__ = ("channel", "signature")

    def __init__(self, channel: foxglove.Channel, signature: _Signature) -> None:
        self.channel = channel
        self.signature = signature


class Bridge:
    """Serves the messages on ``keyexprs`` over the Foxglove WebSocket protocol; a context manager.

    ``client`` is the Zenoh client whose session subscribes; the server listens on ``host`` and
    ``port`` (0: any free port, see :attr:`port`) from construction until :meth:`close`. Raises
    :class:`~dyknow.errors.BindingError` for an invalid key expression and
    :class:`~dyknow.errors.TransportError` when the server cannot listen.
    """

    def __init__(
        self,
        client: Client,
        keyexprs: Iterable[str] = (DEFAULT_KEYEXPR,),
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        max_channels: int = MAX_CHANNELS,
        name: str = "dyknow",
        origins: Iterable[str] = FOXGLOVE_ORIGINS,
    ) -> None:
        # Each once: a key matched by two subscriptions would arrive twice (so would one matched by
        # two overlapping expressions, such as 'a/**' and 'a/b': give the wider one alone).
        self.keyexprs = list(dict.fromkeys(check_key_expr(k, what="key expression to serve") for k in keyexprs)) or [DEFAULT_KEYEXPR]
        self.host = host
        self.max_channels = max_channels
        self._context = foxglove.Context()
        self._streams: dict[str, _Stream] = {}
        self._lock = threading.Lock()
        self._warned: set[str] = set()
        self._refused = 0
        self._refusals = itertools.count(1)
        self._subscribers: list[Subscriber] = []
        self._closed = False
        self._guard: OriginGuard | None = None
        self.unknown_clock = 0  # messages logged at their time as stamped: their clock's offset was not known
        self.clocks: ClockView | None = None
        try:
            # the SDK's server on a loopback port of its own, behind the guard on the port served
            self._server = foxglove.start_server(name=name, host="127.0.0.1", port=0, context=self._context, message_backlog_size=BACKLOG)
        except RuntimeError as exc:  # foxglove's FoxgloveError: "Failed to bind port: ..."
            reason = str(exc).removeprefix("FoxgloveError: ").removeprefix("Failed to bind port: ")
            raise TransportError(
                f"cannot listen on a loopback port ({reason})", where="Foxglove WebSocket server",
                expected="a free loopback port",
            ) from exc  # fmt: skip
        try:
            self._guard = OriginGuard(host, port, self._server.port, origins=list(origins))
        except TransportError as exc:
            self._server.stop()
            raise TransportError(exc.what, where="Foxglove WebSocket server", expected=exc.expected) from exc
        self.port = self._guard.port
        self.clocks = client.follow_clocks()
        self.clocks.fetched.wait(client.timeout_s)  # the offsets before the first message
        try:
            for keyexpr in self.keyexprs:
                self._subscribers.append(client.declare_subscriber(keyexpr, self._on_message))
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Bridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def url(self) -> str:
        """The URL to open in Foxglove: ``ws://HOST:PORT``."""
        shown = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{shown}:{self.port}"

    @property
    def topics(self) -> list[str]:
        """The keys that have a channel, sorted."""
        with self._lock:
            return sorted(self._streams)

    @property
    def refused(self) -> int:
        """Messages skipped because their key would have exceeded ``max_channels``."""
        return self._refused

    def close(self) -> None:
        """Stop receiving, close the channels and stop the server; safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers.clear()
        with self._lock:
            streams = list(self._streams.values())
            self._streams.clear()
        for stream in streams:
            stream.channel.close()
        if self.clocks is not None:
            self.clocks.close()
        if getattr(self, "_guard", None) is not None:
            self._guard.close()  # type: ignore[union-attr]
        if hasattr(self, "_server"):
            self._server.stop()

    # ------------------------------------------------------------------ messages (Zenoh's threads)

    def _on_message(self, msg: Message) -> None:
        stream = self._streams.get(msg.key)
        if stream is not None and not stream.channel.has_sinks():
            return  # nobody watches: skip the encoding (a key's new payload type is noticed once someone does)
        if stream is None and len(self._streams) >= self.max_channels:
            self._refuse(msg.key)
            return
        try:
            kind, encoding, schema_name, data = encode(msg.payload, msg.origin_ns)
        except RecordingError as exc:
            self._warn_once(msg.key, f"messages on {msg.key!r} are not served: {exc}")
            return
        value: Any = msg.payload
        if encoding == "text/plain;charset=utf-8":
            value = {"text": msg.payload}
            encoding, data = "json", json.dumps(value, separators=(",", ":")).encode()
        elif encoding == "json" and not isinstance(msg.payload, dict):
            value = {"value": msg.payload}
            encoding, data = "json", b'{"value":' + data + b"}"
        elif encoding not in ("json", "protobuf"):
            self._warn_once(msg.key, f"messages on {msg.key!r} are not served: Foxglove cannot show {encoding} payloads")
            return
        signature = (encoding, schema_name)
        if stream is None or stream.signature != signature:
            stream = self._stream(msg.key, signature, kind, value)
            if stream is None:
                return
        known = None if self.clocks is None else self.clocks.corrected(msg.origin_clock, msg.origin_ns)
        if known is None:
            self.unknown_clock += 1
        stream.channel.log(data, log_time=max(0, msg.origin_ns if known is None else known[0]))

    def _stream(self, key: str, signature: _Signature, kind: str, value: Any) -> _Stream | None:
        """The channel for ``key`` and ``signature``, created (or replacing the key's old one) if need be."""
        with self._lock:
            if self._closed:
                return None
            stream = self._streams.get(key)
            if stream is not None and stream.signature == signature:
                return stream
            if stream is None and len(self._streams) >= self.max_channels:
                self._refuse(key)
                return None
            if stream is not None:
                log.info("the payload type on %r changed from %s to %s: new channel", key, stream.signature, signature)
                stream.channel.close()
            stream = self._streams[key] = _Stream(_channel(self._context, key, signature, kind, value), signature)
            return stream

    def _refuse(self, key: str) -> None:
        """Skip a message on a key beyond the bound (warning about the first)."""
        n = self._refused = next(self._refusals)  # atomic: no lock needed (it may be held)
        if n == 1:
            log.warning("%d channels already: messages on further keys (first %r) are not served", self.max_channels, key)

    def _warn_once(self, key: str, text: str) -> None:
        with self._lock:
            if key in self._warned or len(self._warned) >= self.max_channels:
                return
            self._warned.add(key)
        log.warning("%s", text)


def _channel(context: foxglove.Context, key: str, signature: _Signature, kind: str, value: Any) -> foxglove.Channel:
    """A new channel on topic ``key``: a protobuf schema dyknow records, or a JSON schema from ``value``.

    Its metadata records the kind of payload published (``ndarray``, ``bytes``, ``json`` or
    ``text``), as a recording's channels do.
    """
    encoding, schema_name = signature
    metadata = {PAYLOAD_METADATA: kind}
    if encoding == "protobuf":
        schema = foxglove.Schema(name=schema_name, encoding="protobuf", data=PROTOBUF_SCHEMAS[schema_name])
        return foxglove.Channel(key, schema=schema, message_encoding="protobuf", context=context, metadata=metadata)
    return foxglove.Channel(key, schema={"title": key, **json_schema(value)}, context=context, metadata=metadata)


def run_bridge(
    client: Client,
    *,
    host: str = "127.0.0.1",
    port: int = DEFAULT_PORT,
    keyexprs: Iterable[str] = (DEFAULT_KEYEXPR,),
    ready: Callable[[str], None] = print,
    origins: Iterable[str] = FOXGLOVE_ORIGINS,
) -> int:
    """Serve ``keyexprs`` until SIGINT or SIGTERM; ``ready(url)`` is told the URL once listening. Returns 0.

    Installs signal handlers, so call it from the main thread.
    """
    stop = threading.Event()
    with Bridge(client, keyexprs, host=host, port=port, origins=origins) as bridge:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
        ready(bridge.url)
        while not stop.wait(0.5):
            pass
    return 0
