"""A session's links: dead ones bounded by a lease, dials under way ended, closed ones counted,
and those to other routers named as they come and go.

Zenoh closes a dead link only after the kernel lets go of what the link still holds (see "dead
links" below), and its close waits for a dial under way: :func:`bound_unacknowledged` and
:func:`abort_dials` bound both, and :class:`Links` follows a session's links as they open and
close, so that a call that ended without a reply can tell a link closed under it.
:class:`RouterLinks` reports each link to another Zenoh router going and coming back, with the
router's name (``dyknow router`` logs them: the link between two sites).
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import os
import queue
import socket
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import zenoh

from dyknow.transport.runtime import inline_handler

__all__ = ["Links", "RouterLink", "RouterLinks", "abort_dials", "bound_unacknowledged"]

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- dead links

# Zenoh sets SO_LINGER to 10 s on every TCP (and TLS) socket, a compile-time constant
# (eclipse-zenoh/zenoh#2350), and closes a link on one of its network threads. After a silent cut
# a socket still holds data its peer never acknowledged (keep-alives, a camera's frames), so
# closing it blocks that thread for up to 10 s, and Zenoh closes a session's links one after the
# other: a manager cut off from two others kept the third's transport for 25 s after the lease
# expired, past the link's return, and refused that manager's new link meanwhile (issue 43). So
# every TCP link of a session gets TCP_USER_TIMEOUT = its lease: the kernel itself drops a
# connection whose data went unacknowledged for a whole lease (Zenoh's own definition of a dead
# link), purging what it held, and Zenoh's close then returns at once. A healthy link is not
# touched: its data is acknowledged within a round trip. Zenoh gives no option for it, so it is
# set on the socket of each new link (Zenoh's link events name its two addresses), in this
# process (Linux).
_USER_TIMEOUT: Final = getattr(socket, "TCP_USER_TIMEOUT", None)
# The two ends of each socket of this process seen so far, by its /proc/self/fd link
# ("socket:[inode]"): None for a socket that is not a connected TCP one.
_ends_by_inode: dict[str, Any] = {}
_ends_lock = threading.Lock()
_bounding: queue.SimpleQueue[tuple[str, str, int]] | None = None  # links for the bounding thread
_bounding_lock = threading.Lock()  # (not _ends_lock: Zenoh's thread must not wait for a scan)
_bounding_pid = 0


def _socket_address(locator: str) -> tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, int] | None:
    """The (address, port) of a ``tcp/`` or ``tls/`` locator with a numeric address, else None."""
    proto, _, rest = locator.partition("/")
    if proto not in ("tcp", "tls"):
        return None
    host, _, port = rest.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    try:
        return _plain_ip(host.strip("[]")), int(port)
    except ValueError:
        return None


def _plain_ip(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    address = ipaddress.ip_address(text.split("%", 1)[0])
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


def bound_unacknowledged(local: str, remote: str, timeout_ms: int) -> bool:
    """Give the TCP socket of this process between the locators ``local`` and ``remote`` (a
    Zenoh link's ``src`` and ``dst``) a ``TCP_USER_TIMEOUT`` of ``timeout_ms``; whether one was
    found and set (never on other systems than Linux, nor for other protocols).

    It looks through this process's file descriptors; the two ends of each socket seen are
    remembered by its inode (a connected socket keeps its ends), so a process with many links
    (a router) reads one link per descriptor, not a socket's addresses each time."""
    ends = _socket_address(local), _socket_address(remote)
    if _USER_TIMEOUT is None or ends[0] is None or ends[1] is None:
        return False
    try:
        names = os.listdir("/proc/self/fd")
    except OSError:
        return False
    with _ends_lock:
        seen = _ends_by_inode
        live: set[str] = set()
        found = False
        for name in names:
            try:
                target = os.readlink(f"/proc/self/fd/{name}")
            except OSError:
                continue
            if not target.startswith("socket:"):
                continue
            live.add(target)
            if target in seen and seen[target] != ends:
                continue  # not a TCP socket, or another link's
            try:
                sock = socket.socket(fileno=os.dup(int(name)))  # a duplicate: closing it leaves Zenoh's open
            except (OSError, ValueError):
                continue
            with sock:
                mine = _socket_ends(sock)
                if mine != "unconnected":  # (one still connecting is looked at again)
                    seen[target] = mine
                found = mine == ends and _set_user_timeout(sock, timeout_ms)
            if found:
                break
        if len(seen) > 2 * len(live) + 64:  # forget the sockets closed since
            for gone in [t for t in seen if t not in live]:
                del seen[gone]
        return found


def _bound_soon(local: str, remote: str, timeout_ms: int) -> None:
    """:func:`bound_unacknowledged` on the process's bounding thread (started on first use), not
    on Zenoh's thread that reports the link: looking through the descriptors there held up the
    links being accepted, and a router (``dyknow router``) refused every session after about 300."""
    global _bounding, _bounding_pid
    with _bounding_lock:
        if _bounding is None or _bounding_pid != os.getpid():  # (a forked child has no such thread)
            _bounding, _bounding_pid = queue.SimpleQueue(), os.getpid()
            threading.Thread(target=_bound_links, args=(_bounding,), name="dyknow-links", daemon=True).start()
        todo = _bounding
    todo.put((local, remote, timeout_ms))


def _bound_links(todo: queue.SimpleQueue[tuple[str, str, int]]) -> None:
    while True:
        local, remote, timeout_ms = todo.get()
        try:
            if not bound_unacknowledged(local, remote, timeout_ms):
                log.debug("link %s => %s: no TCP socket found to bound", local, remote)
        except Exception:  # a link left unbounded is no failure
            log.exception("bounding link %s => %s", local, remote)


def _socket_ends(sock: socket.socket) -> Any:
    """(local, remote) of a connected TCP socket, each (address, port); None for a socket that
    is not a TCP one, "unconnected" for one that has no peer (yet)."""
    try:
        if sock.type != socket.SOCK_STREAM or sock.family not in (socket.AF_INET, socket.AF_INET6):
            return None
        here = sock.getsockname()
    except (OSError, ValueError):
        return None
    try:
        there = sock.getpeername()
    except OSError:
        return "unconnected"
    return (_plain_ip(here[0]), here[1]), (_plain_ip(there[0]), there[1])


def _set_user_timeout(sock: socket.socket, timeout_ms: int) -> bool:
    """Set ``TCP_USER_TIMEOUT`` on ``sock``; whether it could be."""
    try:
        sock.setsockopt(socket.IPPROTO_TCP, _USER_TIMEOUT, max(1, int(timeout_ms)))  # type: ignore[arg-type]
        return True
    except (OSError, ValueError):
        return False


def _proc_address(text: str) -> tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, int]:
    """An address of ``/proc/net/tcp`` or ``tcp6`` (hex, each 32-bit word in the host's order)."""
    host, port = text.split(":")
    raw = bytes.fromhex(host)
    if sys.byteorder == "little":
        raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    return _plain_ip(str(ipaddress.ip_address(raw))), int(port, 16)


def abort_dials(endpoints: Sequence[str]) -> int:
    """End this process's TCP connections still being made to ``endpoints`` (``tcp/``, ``tls/``):
    each socket still in SYN_SENT is shut down, so the connect under way fails at once. Zenoh's
    close waits for a dial under way (up to its open timeout), and a session dialling a silent
    host must close without waiting for it (issue 43). Returns how many were ended (Linux only)."""
    targets = {a for a in map(_socket_address, endpoints) if a is not None}
    inodes: set[str] = set()
    for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6") if targets else ():
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            try:
                if len(fields) > 9 and fields[3] == "02" and _proc_address(fields[2]) in targets:  # 02: SYN_SENT
                    inodes.add(f"socket:[{fields[9]}]")
            except ValueError:
                continue
    ended = 0
    for name in os.listdir("/proc/self/fd") if inodes else ():
        try:
            if os.readlink(f"/proc/self/fd/{name}") not in inodes:
                continue
            with socket.socket(fileno=os.dup(int(name))) as sock:
                sock.shutdown(socket.SHUT_RDWR)
                ended += 1
        except (OSError, ValueError):
            continue
    return ended


class Links:
    """A session's links as they open and close (Zenoh's link events, on Zenoh's thread):
    each new TCP link gets :func:`bound_unacknowledged` (see above), and the links that closed
    are counted, so a call that ended without a reply can tell a link closed under it."""

    def __init__(self, session: zenoh.Session, timeout_ms: int) -> None:
        self._timeout_ms = timeout_ms
        self._changed = threading.Condition()
        self.closed = 0  # links closed so far
        self.last_closed = ""  # the other end of the last one
        self._listener: Any = None
        try:
            # inline: a callback of its own would be a thread Python waits for at exit (a script
            # that forgot to close its session would hang); a link event is rare and this is quick
            self._listener = session.info.declare_link_events_listener(inline_handler(self._event), history=True)
        except (zenoh.ZError, AttributeError) as exc:
            log.info("no watch of the session's links (%s)", exc)

    def _event(self, event: Any) -> None:
        try:
            link = event.link
            if event.kind != zenoh.SampleKind.PUT:
                with self._changed:
                    self.closed += 1
                    self.last_closed = str(link.dst)
                    self._changed.notify_all()
            elif _USER_TIMEOUT is not None:
                _bound_soon(str(link.src), str(link.dst), self._timeout_ms)
        except Exception:  # Zenoh would swallow it; a link left unbounded is no failure
            log.exception("link event %s", event)

    def wait_closed(self, since: int, timeout_s: float) -> bool:
        """Whether a link closed after ``since`` (a value of :attr:`closed`), waiting up to ``timeout_s``."""
        with self._changed:
            return self._changed.wait_for(lambda: self.closed != since, timeout_s)

    def close(self) -> None:
        listener, self._listener = self._listener, None
        if listener is not None:
            with contextlib.suppress(zenoh.ZError):
                listener.undeclare()



# --------------------------------------------------------------------------- links to routers


@dataclass(frozen=True, slots=True)
class RouterLink:
    """A session's link to another Zenoh router as it came up or went down (:class:`RouterLinks`)."""

    zid: str  # the router's Zenoh id (a new one each time a router without a configured id starts)
    address: str  # the link's other end ("tls/192.168.9.1:7447"; a dialling router's own port); "" if unknown
    name: str | None  # the common name of the router's TLS certificate; None without TLS
    up: bool
    down_ns: int | None = None  # (a link up) how long it had been down, when this session saw it go

    @property
    def peer(self) -> str:
        """How an operator knows the router: its certificate's name, else its Zenoh id."""
        return self.name or self.zid


#: At most this many routers are remembered as down (for how long a link was down when it comes
#: back): routers without a configured id get a new one each time they start.
MAX_REMEMBERED_DOWN: Final = 1_000


class RouterLinks:
    """A session's links to other Zenoh routers as they come up and go down: ``on_change(link)``
    for each (:class:`RouterLink`), on Zenoh's thread, so it must return at once (put it on a
    queue). The links already up when it is declared are reported too.

    Only routers: a ``dyknow router``'s managers behind it and its clients (thousands of them)
    link as Zenoh clients and are left out (logged at debug level); a manager that links as a
    Zenoh router (one that ``--connect`` s, or that started before its router) counts as one.
    A context manager; ``close()`` is safe twice."""

    def __init__(self, session: zenoh.Session, on_change: Callable[[RouterLink], None]) -> None:
        self._session = session
        self._on_change = on_change
        self._changed = threading.Condition()
        self._linked: dict[str, RouterLink] = {}  # by zid
        self._down_since: dict[str, int] = {}  # by peer: time.monotonic_ns() when its link went
        self._listener: Any = None
        try:
            self._listener = session.info.declare_transport_events_listener(inline_handler(self._event), history=True)
        except (zenoh.ZError, AttributeError) as exc:
            log.warning("no watch of the links to other routers (%s)", exc)

    def _event(self, event: Any) -> None:
        try:
            transport = event.transport
            up = event.kind == zenoh.SampleKind.PUT
            if transport.whatami != zenoh.WhatAmI.ROUTER:  # (kept quick: a router may hold thousands)
                log.debug("%s %s link %s", transport.whatami, transport.zid, "up" if up else "down")
                return
            now, zid = time.monotonic_ns(), str(transport.zid)
            # (the link's ends, while it is up: Zenoh's transport events do not carry them)
            address, name = self._ends(transport.zid) if up else ("", None)
            with self._changed:
                if up:
                    since = self._down_since.pop(name or zid, None)
                    link = RouterLink(zid, address, name, True, None if since is None else now - since)
                    self._linked[zid] = link
                else:
                    was = self._linked.pop(zid, None)
                    link = RouterLink(zid, was.address if was else "", was.name if was else None, False)
                    self._down_since.pop(link.peer, None)
                    self._down_since[link.peer] = now
                    while len(self._down_since) > MAX_REMEMBERED_DOWN:
                        del self._down_since[next(iter(self._down_since))]
                self._on_change(link)  # (under the lock: in the order they happened)
                self._changed.notify_all()
        except Exception:  # Zenoh would swallow it
            log.exception("transport event %s", event)

    def _ends(self, zid: Any) -> tuple[str, str | None]:
        """The other end of the session's link to ``zid`` and its certificate's name."""
        for link in self._session.info.links():
            if link.zid == zid:
                return str(link.dst), link.auth_identifier or None
        return "", None

    def linked(self) -> list[RouterLink]:
        """The routers linked now, by name."""
        with self._changed:
            return sorted(self._linked.values(), key=lambda link: link.peer)

    def wait_linked(self, count: int, timeout_s: float) -> list[RouterLink]:
        """:meth:`linked`, once ``count`` routers are (or ``timeout_s`` passed)."""
        with self._changed:
            self._changed.wait_for(lambda: len(self._linked) >= count, timeout_s)
        return self.linked()

    def close(self) -> None:
        listener, self._listener = self._listener, None
        if listener is not None:
            with contextlib.suppress(zenoh.ZError):
                listener.undeclare()

    def __enter__(self) -> RouterLinks:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
