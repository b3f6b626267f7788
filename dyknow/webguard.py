"""Local web tools closed to other web pages: which ``Host`` and ``Origin`` a request may carry.

A tool served on loopback (``dyknow ui``, ``dyknow foxglove``) is reachable by every web page the
operator opens in the same browser: a page can post a cross-site form to it, read it from a
DNS-rebound name (``evil.example`` resolving to 127.0.0.1), or open a WebSocket to it, which no
CORS rule covers. Well-kept local tools (Jupyter, the Docker and Kubernetes dashboards) close
these the same way, and so does dyknow:

- the ``Host`` a request names must be one the tool serves (:func:`served_hosts`): on loopback,
  ``localhost``, ``127.0.0.1``, ``[::1]`` and the address it is bound to; beyond loopback any,
  since an access token or the network guards it then;
- a request from a web page carries ``Origin`` (and modern browsers ``Sec-Fetch-Site``): one that
  changes something, or opens a WebSocket, must come from an allowed origin (:func:`foreign`):
  the tool's own, or one the operator allows (the Foxglove web app, for the bridge). A request
  with neither header comes from a program, not a page (the command line, curl, a desktop app).

:class:`OriginGuard` applies the same checks in front of a WebSocket server that cannot check
them itself (the Foxglove SDK's): it reads each connection's HTTP request head, refuses a
foreign one with a 403 that says why, and otherwise passes the connection's bytes through both
ways, untouched.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from collections.abc import Collection

from dyknow.errors import TransportError
from dyknow.security import is_loopback

__all__ = ["HEAD_TIMEOUT_S", "MAX_HEAD_BYTES", "OriginGuard", "foreign", "host_name", "served_hosts"]

log = logging.getLogger(__name__)

#: The largest HTTP request head :class:`OriginGuard` reads before refusing the connection.
MAX_HEAD_BYTES = 16 * 1024
#: How long a connection may take to send its HTTP request head (and, for ``dyknow ui``, to be
#: idle between requests) before it is closed: half-open connections cost a socket each.
HEAD_TIMEOUT_S = 5.0


def served_hosts(bind: str) -> frozenset[str] | None:
    """The host names (without port) a request's ``Host`` may name for a tool bound to ``bind``;
    None when any (bound beyond loopback, where an access token or the network guards it)."""
    if not is_loopback(bind):
        return None
    return frozenset({"localhost", "127.0.0.1", "[::1]", f"[{bind}]" if ":" in bind else bind})


def host_name(host_header: str) -> str:
    """``Host`` without its port (``[::1]:8321`` -> ``[::1]``), in lower case."""
    value = host_header.strip().lower()
    if value.startswith("["):
        return value.split("]", 1)[0] + "]"
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


def foreign(origin: str | None, fetch_site: str | None, allowed: Collection[str]) -> str | None:
    """Why a request with these ``Origin`` and ``Sec-Fetch-Site`` headers comes from a web page
    the tool does not trust, or None. ``allowed``: the origins that may (lower case, no slash at
    the end: ``http://127.0.0.1:8321``)."""
    if origin is not None:
        if origin.strip().lower().rstrip("/") not in allowed:
            return f"Origin {origin[:200]!r} is not allowed"
        return None
    if fetch_site in ("cross-site", "same-site"):
        return f"Sec-Fetch-Site: {fetch_site}, without an Origin"
    return None


class OriginGuard:
    """A TCP front for a WebSocket server on this machine: checks each connection's ``Host`` and
    ``Origin`` (see the module documentation), then passes its bytes through to ``target_port``.

    Listens on ``host``:``port`` (0: any free port, see :attr:`port`) from construction until
    :meth:`close`; its own thread runs the connections. ``origins``: the origins allowed besides
    the guard's own URL (``http://HOST:PORT``). Raises :class:`~dyknow.errors.TransportError`
    when it cannot listen.
    """

    def __init__(self, host: str, port: int, target_port: int, *, origins: Collection[str] = ()) -> None:
        self.host = host
        self._target = target_port
        self._hosts = served_hosts(host)
        self._origins = {o.strip().lower().rstrip("/") for o in origins}
        self.refused = 0
        self._tasks: set[asyncio.Task[None]] = set()
        self._loop = asyncio.new_event_loop()
        try:
            self._server = self._loop.run_until_complete(asyncio.start_server(self._serve, host, port, limit=MAX_HEAD_BYTES))
        except OSError as exc:
            self._loop.close()
            reason = os.strerror(exc.errno) if exc.errno else str(exc)
            raise TransportError(
                f"cannot listen on {host}:{port} ({reason})",
                expected="a free port (--port, 0 for any) on an address of this host (--host)",
            ) from exc
        self.port = int(self._server.sockets[0].getsockname()[1])
        shown = f"[{host}]" if ":" in host else host
        self._origins |= {f"http://{shown}:{self.port}", f"https://{shown}:{self.port}"}
        self._thread = threading.Thread(target=self._loop.run_forever, name="dyknow-origin-guard", daemon=True)
        self._thread.start()

    def __enter__(self) -> OriginGuard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop listening and drop every connection; safe twice."""
        if self._loop.is_closed():
            return

        async def stop() -> None:
            self._server.close()
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)

        with contextlib.suppress(RuntimeError, TimeoutError):
            asyncio.run_coroutine_threadsafe(stop(), self._loop).result(5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)
        if not self._thread.is_alive():
            self._loop.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, ConnectionError):
                return
            why = self._why_refused(head)
            if why is not None:
                self.refused += 1
                log.warning("refused a connection from another web page: %s", why)
                body = f"refused: {why}; expected the tool's own page, or a program (no Origin)\n".encode()
                writer.write(b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                             + f"Content-Length: {len(body)}\r\n\r\n".encode() + body)  # fmt: skip
                with contextlib.suppress(ConnectionError):
                    await writer.drain()
                return
            try:
                up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self._target)
            except OSError as exc:
                log.warning("the server behind the guard cannot be reached: %s", exc)
                return
            try:
                up_writer.write(head)
                await asyncio.gather(_pipe(reader, up_writer), _pipe(up_reader, writer))
            finally:
                up_writer.close()
        finally:
            writer.close()
            self._tasks.discard(task)

    def _why_refused(self, head: bytes) -> str | None:
        headers: dict[str, str] = {}
        for line in head.decode("latin-1").split("\r\n")[1:]:
            name, sep, value = line.partition(":")
            if sep:
                headers.setdefault(name.strip().lower(), value.strip())
        host = headers.get("host", "")
        if self._hosts is not None and host_name(host) not in self._hosts:
            return f"the Host {host[:200]!r} is not a name this server serves (expected one of {', '.join(sorted(self._hosts))})"
        return foreign(headers.get("origin"), headers.get("sec-fetch-site"), self._origins)


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Copy ``reader`` to ``writer`` until it ends, then end ``writer``."""
    try:
        while data := await reader.read(65536):
            writer.write(data)
            await writer.drain()
    except (ConnectionError, asyncio.CancelledError):
        pass
    finally:
        with contextlib.suppress(OSError, RuntimeError):
            writer.write_eof()
