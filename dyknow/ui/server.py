"""The web tool's server: the managers' model pushed to the page, the page's actions sent to them.

It is a Zenoh client of the managers like any other (a :class:`~dyknow.client.Client`): it reads
every reachable manager's model through ``get_model`` and forwards each action of the page to the
manager's own services, so the managers' access control applies to it as to the command line.

HTTP (aiohttp):

- ``GET /`` the page; ``GET /static/...`` its script, style and the vendored cytoscape.js;
- ``GET /api/model`` ``{"version", "managers": [model, ...], "stats": {"manager/unit": {port: {"rate", "hop_p50_us", "lost", "dropped",
  "unknown_clock"}}}}`` (statistics asked every ``stats_s``; ``unknown_clock``: messages of a clock whose offset was not known),
  and ``"verdicts": {key: [[t, verdict, gap cause], ...]}``, the latest verdicts of every monitor and requirement the models list;
  and ``"lost": [{"manager", "since_ns", "why"}, ...]``, the managers the tool itself saw leave (it watches every manager's
  token, as a manager, which watches only those it follows, does not: :meth:`~dyknow.client.Client.seen_lost`);
- ``GET /api/events`` server-sent events: the model again each time it changes (checked every
  ``poll_s``);
- ``GET /api/stream?key=KEY`` a WebSocket of the messages on ``KEY``: for each, a JSON header
  (``seq``, ``latency_ms``, ``kind`` "image", "json" or "other", ``dropped``) and, for an image,
  the frame as JPEG; only the latest message is kept while the page is busy;
- ``POST /api/call`` ``{"manager", "service", "request", "unit"?}``: one service call; the reply
  as JSON, or ``{"error", "message"}`` with status 400 (the manager refused) or 502 (no answer).

Bound to loopback it needs no token; bound beyond, every request must carry the access token
(``?token=`` once, then a cookie, or the ``X-Dyknow-Token`` header).

Closed to other web pages (as Jupyter and the Docker and Kubernetes dashboards close theirs): a
page the operator opens in the same browser must not drive the tool. So, whatever the binding:

- ``Host`` must be a name the tool serves (:func:`~dyknow.webguard.served_hosts`: on loopback ``localhost``,
  ``127.0.0.1``, ``[::1]`` and the address it is bound to; beyond, any, since the token guards it):
  a page on a DNS-rebound name (``evil.example`` resolving to 127.0.0.1) is refused before it
  reads anything;
- every request that changes something (``POST /api/call``) and every WebSocket upgrade
  (``/api/stream``, which no CORS rule covers) that carries an ``Origin`` must come from the
  tool's own origin; so must any whose ``Sec-Fetch-Site`` says ``cross-site`` or ``same-site``;
  a request with neither header (the command line, curl) is not a web page's;
- ``POST /api/call`` takes ``application/json`` only, which a web page cannot send to another
  origin without a CORS preflight the tool never answers (an HTML form's ``text/plain`` or
  ``application/x-www-form-urlencoded`` post is refused).

Each refusal is a 403 (415 for the content type) whose JSON says what was refused and why.

Connections cost a socket each, so they are bounded too (:func:`serve`): a connection that has not
sent a whole request head within :data:`~dyknow.webguard.HEAD_TIMEOUT_S` (5 s, as the Foxglove
guard waits), or stays that long idle between requests, is closed; a call's body must arrive
within :data:`BODY_TIMEOUT_S`; and at most :data:`MAX_CONNECTIONS` are open at once (open pages'
event streams and views included): one more is answered 503 and closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from aiohttp import web

from dyknow.client import Client
from dyknow.errors import DyKnowError, ServiceError
from dyknow.message import Message, describe_payload
from dyknow.security import is_loopback
from dyknow.service import MANAGER_SERVICES, UNIT_SERVICES
from dyknow.transport import check_key_expr
from dyknow.webguard import HEAD_TIMEOUT_S, foreign, host_name, served_hosts

__all__ = [
    "BODY_TIMEOUT_S",
    "MAX_CALL_BYTES",
    "MAX_CONNECTIONS",
    "MAX_OBJECT_ROWS",
    "MAX_STREAMS",
    "MAX_VERDICT_KEYS",
    "ModelWatch",
    "check_bind",
    "make_app",
    "recorded_timeline",
    "serve",
]

log = logging.getLogger(__name__)

STATIC = Path(__file__).with_name("static")
MAX_CALL_BYTES = 1 << 20  # an imported spec is the largest thing the page sends
_MAX_JSON_CHARS = 64 << 10  # larger JSON payloads are described, not shown
MAX_STREAMS = 16  # streams watched at once (each is a Zenoh subscriber and JPEG encoding)
_MAX_STATS_UNITS = 1000  # units whose statistics are asked each round
MAX_VERDICT_KEYS = 32  # verdict streams followed at once (monitors' and requirements')
MAX_CONNECTIONS = 256  # open at once, whatever they are doing
BODY_TIMEOUT_S = 10.0  # for a call's body to arrive once its head has
_VERDICTS_KEPT = 300  # the latest verdicts of each, for the page's timeline
_CHANGES_KEPT = 50  # the latest changes of each, with the values that decided them
MAX_OBJECT_ROWS = 64  # rows of one foreach monitor's objects (further objects are not shown)
MAX_OBJECT_CHARS = 80  # of an object's id in its row's name
MAX_WHY_ATOMS = 8  # atoms shown of a change's why
MAX_WHY_CHARS = 300  # of each


class ModelWatch:
    """Keeps the model of every reachable manager, asking them every ``poll_s``; a context manager.

    ``listen(callback)`` has ``callback()`` called (on the watch's thread) after each change.
    """

    def __init__(self, client: Client, *, poll_s: float = 0.25, stats_s: float = 1.0, recorded: dict[str, Any] | None = None) -> None:
        self.client = client
        self.poll_s = poll_s
        self.stats_s = stats_s
        self._stats_at = 0.0
        self._counts: dict[tuple[str, str, str], tuple[int, float]] = {}  # (manager, unit, port) -> (messages, at)
        self._stats: dict[str, dict[str, dict[str, float | None]]] = {}
        self._clocks: dict[Any, Any] = {}  # manager -> its model's clocks, as of the last statistics
        self.version = 0
        self.data: dict[str, Any] = {"version": 0, "managers": []}
        self._names: list[str] = []
        self._names_at = 0.0
        self._lock = threading.Lock()
        self._listeners: list[Callable[[], None]] = []
        self._verdicts: dict[str, deque[list[Any]]] = {}  # row (key, or key [object]) -> [t, verdict, gap cause or None]
        self._changes: dict[str, deque[list[Any]]] = {}  # row -> [t, verdict, why or None], where the verdict changed
        self._verdict_subs: dict[str, Any] = {}
        self._recorded = recorded if recorded is not None else {}
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="dyknow-ui-watch", daemon=True)
        self._thread.start()

    def __enter__(self) -> ModelWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop asking; safe twice."""
        self._closed = True
        self._thread.join(2.0)
        for sub in self._verdict_subs.values():
            sub.undeclare()
        self._verdict_subs.clear()

    def _follow_verdicts(self, models: list[dict[str, Any]]) -> None:
        """Subscribe to the verdicts of every monitor and requirement the models list (and drop
        those gone), at most :data:`MAX_VERDICT_KEYS`. A ``foreach`` monitor's verdicts make a
        row per object (``KEY [OBJECT]``, at most :data:`MAX_OBJECT_ROWS` per key)."""
        wanted: list[str] = []
        for model in models:
            for monitor in model.get("monitors", []):
                wanted += [str(m["key"]) for m in monitor.get("monitors", [])]
            for request in model.get("requests", []):
                wanted += [f"{request['key']}/requirements/{n}" for n in range(1, len(request.get("requirements", [])) + 1)]
                wanted += [str(r["key"]) for r in request.get("spec_requirements", []) if isinstance(r, dict) and "key" in r]
        wanted = list(dict.fromkeys(wanted))[:MAX_VERDICT_KEYS]
        for key in [k for k in self._verdict_subs if k not in wanted]:
            self._verdict_subs.pop(key).undeclare()
            with self._lock:
                for row in [r for r in self._verdicts if r == key or r.startswith(f"{key} [")]:
                    self._verdicts.pop(row, None)
                    self._changes.pop(row, None)
        for key in wanted:
            if key not in self._verdict_subs:
                with self._lock:
                    self._verdicts[key] = deque(maxlen=_VERDICTS_KEPT)
                    self._changes[key] = deque(maxlen=_CHANGES_KEPT)

                def take(msg: Message, key: str = key) -> None:
                    p = msg.payload
                    if not isinstance(p, dict) or not (isinstance(p.get("verdict"), bool) or p.get("verdict") is None and "t" in p):
                        return
                    verdict = p.get("verdict")
                    gap = p.get("gap")
                    obj = p.get("object")
                    row = key if obj is None else f"{key} [{str(obj)[:MAX_OBJECT_CHARS]}]"
                    why = p.get("why")
                    with self._lock:
                        kept = self._verdicts.get(row)
                        if kept is None:
                            if obj is None or sum(r.startswith(f"{key} [") for r in self._verdicts) >= MAX_OBJECT_ROWS:
                                return  # (a key given up meanwhile, or more objects than the page shows)
                            kept = self._verdicts[row] = deque(maxlen=_VERDICTS_KEPT)
                            self._changes[row] = deque(maxlen=_CHANGES_KEPT)
                        changes = self._changes[row]
                        if not changes or changes[-1][1] is not verdict:
                            said = [str(w)[:MAX_WHY_CHARS] for w in why[:MAX_WHY_ATOMS]] if isinstance(why, list) else None
                            changes.append([p.get("t"), verdict, said])
                        kept.append([p.get("t"), verdict, gap.get("cause") if isinstance(gap, dict) else None])

                try:
                    self._verdict_subs[key] = self.client.declare_subscriber(key, take)
                except DyKnowError as exc:
                    log.debug("cannot follow the verdicts on %r: %s", key, exc)

    def refresh(self) -> None:
        """Ask the managers now (after an action, so the page sees its effect at once)."""
        models = []
        now = time.monotonic()
        if now - self._names_at > 1.0 or not self._names:
            self._names = self.client.manager_names(timeout_s=0.5)
            self._names_at = now
        for name in self._names:
            try:
                models.append(self.client.get_model(name))
            except DyKnowError as exc:
                log.debug("no model from %r: %s", name, exc)
        if now - self._stats_at >= self.stats_s:
            self._stats_at = now
            self._stats = self._statistics(models)
            self._clocks = {m.get("manager"): m.get("clocks") for m in models}
        else:  # clock offsets move a little at every look: they are refreshed with the statistics, so as not to redraw at each
            for m in models:
                if m.get("manager") in self._clocks:
                    m["clocks"] = self._clocks[m.get("manager")]
        self._follow_verdicts(models)
        with self._lock:
            objects = {row.split(" [", 1)[0] for row in self._verdicts if " [" in row}
            verdicts = {key: [list(v) for v in kept] for key, kept in self._verdicts.items() if kept or key not in objects}
            changes = {key: [list(c) for c in kept] for key, kept in self._changes.items() if key in verdicts}
            lost = self.client.seen_lost()
            if (models, self._stats, verdicts, changes, lost) == (
                self.data["managers"], self.data.get("stats"), self.data.get("verdicts"), self.data.get("changes"), self.data.get("lost")
            ):  # fmt: skip
                return
            self.version += 1
            self.data = {"version": self.version, "managers": models, "stats": self._stats, "verdicts": verdicts, "changes": changes,
                         "lost": lost, "recorded": self._recorded}  # fmt: skip
            listeners = list(self._listeners)
        for listener in listeners:
            listener()

    def _statistics(self, models: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, float | None]]]:
        """Per unit ("manager/unit") and port: messages per second since the last look, and the
        median per-hop latency of input ports (at most ``_MAX_STATS_UNITS`` units a round)."""
        out: dict[str, dict[str, dict[str, float | None]]] = {}
        seen: set[tuple[str, str, str]] = set()
        asked = 0
        for model in models:
            for unit in model.get("units", []):
                if asked >= _MAX_STATS_UNITS:
                    break
                asked += 1
                try:
                    stats = self.client.call_unit(model["manager"], unit["name"], "get_statistics", {})
                except DyKnowError:
                    continue
                now = time.monotonic()
                ports: dict[str, dict[str, float | None]] = {}
                for port, entry in stats.get("ports", {}).items():
                    ident = (model["manager"], unit["name"], port)
                    seen.add(ident)
                    count = int(entry.get("messages", 0))
                    before = self._counts.get(ident)
                    self._counts[ident] = (count, now)
                    rate = round((count - before[0]) / (now - before[1]), 1) if before and now > before[1] and count >= before[0] else None
                    hop = (entry.get("hop") or {}).get("p50_us")
                    unknown = (entry.get("clock") or {}).get("unknown", 0)
                    ports[port] = {"rate": rate, "hop_p50_us": hop, "lost": entry.get("lost", 0), "dropped": entry.get("dropped", 0), "unknown_clock": unknown}
                out[f"{model['manager']}/{unit['name']}"] = ports
        for gone in set(self._counts) - seen:
            del self._counts[gone]
        return out

    def listen(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Call ``callback()`` after each change; returns a function that stops it."""
        with self._lock:
            self._listeners.append(callback)

        def stop() -> None:
            with self._lock:
                if callback in self._listeners:
                    self._listeners.remove(callback)

        return stop

    def _run(self) -> None:
        while not self._closed:
            try:
                self.refresh()
            except Exception:
                log.exception("the model could not be refreshed")
            time.sleep(self.poll_s)


def recorded_timeline(results: Sequence[Any], *, cells: int = _VERDICTS_KEPT, changes: int = 200) -> dict[str, Any]:
    """The verdict timeline of requirements checked over a recording
    (:func:`dyknow.reasoning.check_recording`'s results), for the page: a row per requirement and
    instance (``NAME [INSTANCE]``), each ``{"formula", "verdicts": [[t, verdict, null], ...],
    "changes": [[t, verdict, why], ...], "error"}`` (``t`` in seconds of the recording's clock).
    A row's verdicts are at most ``cells``: each cell stands for an equal run of states and shows
    the worst of them (false, then unknown, then true), so no false state is hidden; its first
    ``changes`` changes are listed."""
    rows: dict[str, Any] = {}
    for result in results:
        name = result.requirement.name
        if result.error is not None:
            rows[name] = {"formula": result.requirement.formula, "verdicts": [], "changes": [], "error": str(result.error)}
            continue
        for instance, series in result.verdicts.items():
            step = max(1, -(-len(series) // cells))
            strip = []
            for i in range(0, len(series), step):
                run = [v for _, v in series[i : i + step]]
                worst = False if False in run else None if None in run else True
                strip.append([series[i][0] / 1e9, worst, None])
            said = [[t / 1e9, v, atoms or None] for t, v, atoms in result.changes.get(instance, [])[:changes]]
            rows[f"{name} [{instance}]" if instance else name] = {"formula": result.requirement.formula, "verdicts": strip, "changes": said, "error": None}
    return rows


def make_app(client: Client, watch: ModelWatch, *, token: str | None = None, bind: str = "127.0.0.1") -> web.Application:
    """The aiohttp application of the tool (``token``: required on every request when given;
    ``bind``: the address it is served on, which decides the ``Host`` names it answers)."""
    hosts = served_hosts(bind)

    @web.middleware
    async def guard(request: web.Request, handler: Any) -> web.StreamResponse:
        if hosts is not None and host_name(request.host) not in hosts:
            why = f"the Host {request.host[:200]!r} is not a name this tool serves (a page on another name resolving here?)"
            return _refused("AccessError", f"{why}; expected one of {', '.join(sorted(hosts))}", 403)
        changes = request.method not in ("GET", "HEAD", "OPTIONS") or request.headers.get("Upgrade", "").lower() == "websocket"
        if changes:
            own = f"{request.scheme}://{request.host}".lower()
            page = foreign(request.headers.get("Origin"), request.headers.get("Sec-Fetch-Site"), {own})
            if page is not None:
                return _refused("AccessError", f"refused a request from another web page ({page}); expected the tool's own page ({own})", 403)
        if token is not None:
            given = request.query.get("token") or request.headers.get("X-Dyknow-Token") or request.cookies.get("dyknow_token") or ""
            if not hmac.compare_digest(given.encode(), token.encode()):
                return web.json_response({"error": "AccessError", "message": "this tool needs its access token: open the URL it printed"}, status=403)
        response = await handler(request)
        if token is not None and request.query.get("token"):
            response.set_cookie("dyknow_token", token, httponly=True, samesite="Strict")
        response.headers["Cache-Control"] = "no-store"
        response.headers["X-Content-Type-Options"] = "nosniff"
        return response

    async def index(request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    async def model(request: web.Request) -> web.StreamResponse:
        return web.json_response(watch.data)

    async def events(request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store"})
        await response.prepare(request)
        loop = asyncio.get_running_loop()
        changed = asyncio.Event()  # no thread waits per open page: the watch wakes the loop

        def wake() -> None:  # on the watch's thread
            with contextlib.suppress(RuntimeError):  # the loop has closed: the server is stopping
                loop.call_soon_threadsafe(changed.set)

        stop = watch.listen(wake)
        version = -1
        try:
            while True:
                data = watch.data
                if data["version"] != version:
                    version = data["version"]
                    await response.write(b"data: " + json.dumps(data).encode() + b"\n\n")
                try:
                    await asyncio.wait_for(changed.wait(), 15.0)
                except TimeoutError:
                    await response.write(b": keep-alive\n\n")
                changed.clear()
        finally:
            stop()

    async def call(request: web.Request) -> web.StreamResponse:
        if request.content_type != "application/json":
            return _refused("RequestError", f"a call of Content-Type {request.content_type!r}; expected application/json", 415)
        if request.content_length is not None and request.content_length > MAX_CALL_BYTES:
            return _refused("RequestError", f"a request of {request.content_length} bytes; expected at most {MAX_CALL_BYTES}", 413)
        try:
            data = await asyncio.wait_for(request.content.read(MAX_CALL_BYTES + 1), BODY_TIMEOUT_S)
        except TimeoutError:
            return _refused("RequestError", f"the call's body did not arrive within {BODY_TIMEOUT_S:g} s", 408)
        try:
            body = json.loads(data)
            manager, service = str(body["manager"]), str(body["service"])
            unit = body.get("unit")
            payload = body.get("request", {})
            if not isinstance(payload, dict):
                raise ValueError("'request' must be an object")
        except (ValueError, KeyError, TypeError, RecursionError) as exc:
            return _refused("RequestError", f"not a call: {str(exc)[:200]}; expected {{\"manager\", \"service\", \"request\", \"unit\"?}}", 400)
        allowed = UNIT_SERVICES if unit is not None else MANAGER_SERVICES
        if service not in allowed:
            return _refused("RequestError", f"no service {service!r}; expected one of {', '.join(allowed)}", 400)
        try:
            if unit is not None:
                reply = await asyncio.to_thread(client.call_unit, manager, str(unit), service, payload)
            else:
                reply = await asyncio.to_thread(client.call_manager, manager, service, payload)
        except ServiceError as exc:
            return _refused(type(exc).__name__, str(exc), 502)
        except DyKnowError as exc:
            return _refused(type(exc).__name__, str(exc), 400)
        await asyncio.to_thread(watch.refresh)
        return web.json_response({"reply": reply})

    streams: set[web.WebSocketResponse] = set()

    async def stream(request: web.Request) -> web.StreamResponse:
        key = request.query.get("key", "")
        try:
            check_key_expr(key, what="stream")
        except DyKnowError as exc:
            return _refused(type(exc).__name__, str(exc), 400)
        if len(streams) >= MAX_STREAMS:
            return _refused("RequestError", f"{len(streams)} streams are watched already; expected at most {MAX_STREAMS}: close a View", 429)
        socket = web.WebSocketResponse(heartbeat=20)
        streams.add(socket)
        try:
            await socket.prepare(request)
            latest = _Latest(asyncio.get_running_loop())
            with client.declare_subscriber(key, latest.put):
                sender = asyncio.ensure_future(_send_frames(socket, latest))
                async for _ in socket:  # the page says nothing; this ends when it goes
                    pass
                sender.cancel()
        finally:
            streams.discard(socket)
        return socket

    app = web.Application(middlewares=[guard], client_max_size=MAX_CALL_BYTES + 1024)
    app.router.add_get("/api/stream", stream)
    app.router.add_get("/", index)
    app.router.add_get("/api/model", model)
    app.router.add_get("/api/events", events)
    app.router.add_post("/api/call", call)
    app.router.add_static("/static/", STATIC)
    return app


async def serve(app: web.Application, host: str, port: int) -> tuple[web.AppRunner, asyncio.Server]:
    """Serve ``app`` on ``host``:``port`` (0: any free port) with the connection bounds of the
    module documentation; returns the runner and the listening server (its ``sockets`` say the
    port). To stop: close the server, then ``await runner.cleanup()``."""
    runner = web.AppRunner(app, handle_signals=False, shutdown_timeout=1.0, keepalive_timeout=HEAD_TIMEOUT_S)
    await runner.setup()
    handlers = runner.server
    assert handlers is not None  # (set up just now)
    try:
        server = await asyncio.get_running_loop().create_server(_Bounded(handlers, MAX_CONNECTIONS), host, port)
    except BaseException:
        await runner.cleanup()
        raise
    return runner, server


class _Bounded:
    """The protocol factory of :func:`serve`: aiohttp's handler for each connection while fewer
    than ``limit`` are open, a :class:`_Busy` one beyond. (aiohttp closes a connection that has not
    sent a request head within its ``keepalive_timeout``, which it starts as the connection opens.)"""

    def __init__(self, handlers: web.Server, limit: int) -> None:
        self._handlers = handlers
        self._limit = limit
        self._accepting = 0  # made here, not yet counted by aiohttp (it counts them in connection_made)

    def __call__(self) -> asyncio.BaseProtocol:
        if len(self._handlers.connections) + self._accepting >= self._limit:
            return _Busy()
        self._accepting += 1
        # runs just before the connection's connection_made, which the transport schedules next
        asyncio.get_running_loop().call_soon(self._accepted)
        return self._handlers()

    def _accepted(self) -> None:
        self._accepting -= 1


class _Busy(asyncio.Protocol):
    """A connection over :data:`MAX_CONNECTIONS`: answered 503 and closed."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        body = f"the tool has {MAX_CONNECTIONS} connections open, its most; close some pages or views\n".encode()
        transport.write(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                        + f"Content-Length: {len(body)}\r\n\r\n".encode() + body)  # fmt: skip
        transport.close()


class _Latest:
    """The latest message of a stream, handed from Zenoh's thread to the event loop (older ones are
    dropped: a slow page sees fewer frames, never a growing queue)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._message: Message | None = None
        self._ready = asyncio.Event()
        self.dropped = 0

    def put(self, msg: Message) -> None:
        if self._message is not None:
            self.dropped += 1
        self._message = msg
        self._loop.call_soon_threadsafe(self._ready.set)

    async def get(self) -> Message:
        while True:
            await self._ready.wait()
            self._ready.clear()
            msg, self._message = self._message, None
            if msg is not None:
                return msg


async def _send_frames(socket: web.WebSocketResponse, latest: _Latest) -> None:
    """Send each message as a JSON header (time, latency, kind) and, for images, a JPEG."""
    while not socket.closed:
        msg = await latest.get()
        header, image = await asyncio.to_thread(_frame, msg)
        header["dropped"] = latest.dropped
        await socket.send_str(json.dumps(header))
        if image is not None:
            await socket.send_bytes(image)


def _frame(msg: Message) -> tuple[dict[str, Any], bytes | None]:
    """What the page shows of one message: an image as JPEG, JSON as is (bounded), else a description."""
    header: dict[str, Any] = {"key": msg.key, "seq": msg.seq, "latency_ms": round((time.time_ns() - msg.origin_ns) / 1e6, 3)}
    payload = msg.payload
    if isinstance(payload, np.ndarray) and payload.dtype == np.uint8 and (payload.ndim == 2 or (payload.ndim == 3 and payload.shape[2] in (1, 3, 4))):
        ok, jpeg = cv2.imencode(".jpg", payload, [cv2.IMWRITE_JPEG_QUALITY, 80])
        if ok:
            header.update(kind="image", width=int(payload.shape[1]), height=int(payload.shape[0]))
            return header, jpeg.tobytes()
    if isinstance(payload, (dict, list, int, float, str)) and not isinstance(payload, bool):
        text = json.dumps(payload, default=str)
        if len(text) <= _MAX_JSON_CHARS:
            header.update(kind="json", payload=payload if isinstance(payload, dict) else {"value": payload})
            return header, None
    header.update(kind="other", description=describe_payload(payload))
    return header, None


def _refused(kind: str, message: str, status: int) -> web.Response:
    return web.json_response({"error": kind, "message": message}, status=status)


def check_bind(host: str, token: str | None) -> str | None:
    """The token to require: None on loopback without one; a new one beyond loopback when none is given."""
    if is_loopback(host):
        return token
    return token or secrets.token_urlsafe(18)
