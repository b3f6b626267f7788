"""Zenoh, behind a small surface. The only module of dyknow that imports ``zenoh``.

The default session is a Zenoh *peer* that talks over loopback only: multicast scouting is off,
it listens on ``tcp/127.0.0.1`` (a given port, or any free one) and connects to the endpoints it is
given. Gossip scouting stays on so that peers which connect to a manager also find each other and
exchange data directly. A manager's session is a Zenoh *router* (``mode="router"``): routers route
for each other over any path, so two managers that cannot link directly still reach each other
through a third one or a ``dyknow router``, where peers see only the peers they link to. A Zenoh
configuration file (json5) replaces these defaults to join a real deployment.

A session bounds how long its dead links hold it up (see "dead links" below: the kernel drops a
link whose data goes unacknowledged for a lease), dials a lost link again within a second, ends
a dial under way when it closes, and is closed before the interpreter's threads end at exit. A
call that ends without an answer says why, as far as it can be told: the link closed, the
service's owner went, or the request was dropped on its way (an access control).

Entities mirror Zenoh's: ``declare_*`` returns an object with ``undeclare()`` (safe twice) that is
also a context manager. Zenoh errors are wrapped in :class:`~dyknow.errors.TransportError` with the
Rust source location trimmed off.
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import ctypes
import ipaddress
import json
import logging
import os
import queue
import re
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import zenoh

from dyknow.access import AccessControl, TlsFiles
from dyknow.errors import BindingError, ClosedError, ServiceError, TransportError, did_you_mean
from dyknow.keys import MAX_KEY_BYTES
from dyknow.message import ENCODINGS, HEADER_V1, Message, decode, decode_dyknow, encode

__all__ = [
    "DEFAULT_ENDPOINT",
    "MAX_QUERIERS",
    "SCHEMES",
    "ZENOH_RUNTIME",
    "LivelinessSubscriber",
    "LivelinessToken",
    "PlainPublisher",
    "Publisher",
    "Queryable",
    "ServiceChannel",
    "ServiceRequest",
    "Session",
    "Subscriber",
    "check_key_expr",
    "check_schemes",
    "is_wild",
    "key_exprs_intersect",
    "make_config",
    "shared_memory_problem",
]

log = logging.getLogger(__name__)

#: Where ``dyknow manager`` listens and where clients connect when told nothing else.
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: Service queriers a session keeps for its next calls (the least recently used go first).
MAX_QUERIERS = 64
# How long a call that ended early with no reply looks for what explains it, asking again
# meanwhile, first after this long (see Session._call).
_CUT_GRACE_S = 0.5
_RETRY_FIRST_S = 0.01

_WILD = re.compile(r"\*|\$\*")
_ENCODINGS: Final = {text: zenoh.Encoding(text) for text in ENCODINGS.values()}

# Payloads at least this large go out through Zenoh shared memory (each session reserves a pool
# lazily). It was chosen when an earlier benchmark measured it 4x faster than a plain put; the
# fairer one now (benchmarks/payload.py, every copy inside the figure) finds raw Zenoh's plain put
# faster for a 6 MiB frame with nothing else in flight (1.0 vs 1.5 ms), since the receiver copies a
# shared-memory sample out too. When to use it is an open question (README, Payload sizes).
SHM_THRESHOLD: Final = 64 * 1024
#: How many sessions a router (``dyknow router``, a manager) accepts at once by default (as
#: rmw_zenoh's router configuration does; Zenoh's own default is 1,000).
ROUTER_MAX_SESSIONS: Final = 10_000
#: At most this many liveliness tokens are read in one :meth:`Session.alive` answer (a flood of
#: tokens is hostile input).
MAX_ALIVE_KEYS: Final = 100_000
_HEADER_SIZE: Final = HEADER_V1.size  # the shortest dyknow header (version 1)
SHM_POOL_BYTES = 96 * 1024 * 1024


def shared_memory_problem(pool_bytes: int = SHM_POOL_BYTES) -> str | None:
    """Why this process could not use Zenoh shared memory for large payloads (a pool of
    ``pool_bytes`` made and a buffer taken from it, as a publisher does), or None when it can.
    Where it cannot, such payloads are copied the ordinary way (dyknow doctor says so)."""
    try:
        provider = zenoh.shm.ShmProvider.default_backend(pool_bytes)
        provider.alloc(SHM_THRESHOLD, zenoh.shm.GarbageCollect())
    except (zenoh.ZError, AttributeError) as exc:
        return _clean(exc)
    return None


class _SharedMemory:
    """A session's shared-memory pool for large payloads, created on first use.

    Allocation never blocks: when the pool is full (receivers still hold buffers) the payload
    goes out the ordinary way. Where Zenoh has no shared memory, it is never used.
    """

    def __init__(self) -> None:
        self._provider: Any = None
        self._lock = threading.Lock()
        self._broken = False

    def wrap(self, data: bytes) -> Any:
        """``data`` copied into a shared-memory buffer, or ``data`` itself when that is not possible."""
        provider = self._provider
        if provider is None:
            if self._broken:
                return data
            with self._lock:
                if self._provider is None and not self._broken:
                    try:
                        self._provider = zenoh.shm.ShmProvider.default_backend(SHM_POOL_BYTES)
                    except (zenoh.ZError, AttributeError) as exc:
                        self._broken = True
                        log.info("no Zenoh shared memory here (%s); large payloads are copied", _clean(exc))
                        return data
                provider = self._provider
        try:
            buffer = provider.alloc(len(data), zenoh.shm.GarbageCollect())
        except zenoh.ZError:
            return data  # pool full right now
        buffer[:] = data
        return buffer


# --------------------------------------------------------------------------- Zenoh's runtimes

#: How dyknow has Zenoh lay out its network threads, unless the process sets ``ZENOH_RUNTIME``
#: itself (Zenoh's syntax; ``ZENOH_RUNTIME='()'`` gives Zenoh's own defaults). By default Zenoh
#: reads sockets on its ``net`` and ``acc`` runtimes' threads and hands every message over to
#: the ``rx`` runtime, another thread, and tokio then often wakes rx's second worker as well.
#: Handing ``net`` and ``acc`` over to ``rx`` makes the thread that is woken by the socket the one
#: that handles the message (``benchmarks/chain.py``: raw Zenoh with this layout,
#: ``zenoh-process-tuned``, against Zenoh's own, ``zenoh-process``). The ``tx`` runtime stays apart on purpose: a put with congestion
#: control BLOCK from a receive callback waits for the tx task, which must not need the waiting
#: thread (Zenoh's source warns that receiving on TX deadlocks). ``rx`` keeps its two workers, so
#: one slow callback does not stop every link.
ZENOH_RUNTIME: Final = "(net: (handover: rx), acc: (handover: rx))"


def _lay_out_runtimes() -> None:
    """Set ``ZENOH_RUNTIME`` to :data:`ZENOH_RUNTIME` unless the process chose its own. Zenoh reads
    it once, when it first starts a runtime: from then on it no longer has any effect."""
    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)


def _panic_error(exc: BaseException) -> TransportError | None:
    """A clear error for a Zenoh panic while opening a session (it escapes ``except Exception``),
    else None. The usual cause is a ``ZENOH_RUNTIME`` Zenoh cannot parse; once Zenoh panicked
    so, every later open in the process panics too ("Once panicked")."""
    if type(exc).__name__ != "PanicException":
        return None
    text = str(exc)[:300]
    chosen = os.environ.get("ZENOH_RUNTIME")
    if chosen is None or chosen == ZENOH_RUNTIME:
        return TransportError(f"Zenoh failed while opening a session: {text}")
    return TransportError(
        f"Zenoh cannot start with ZENOH_RUNTIME={chosen!r}: {text}",
        where="environment variable ZENOH_RUNTIME",
        expected=f"Zenoh's runtime syntax, e.g. {ZENOH_RUNTIME!r} (dyknow's default) or '()' (Zenoh's own); "
        "or unset it, and start the process again",
    )


# --------------------------------------------------------------------------- Zenoh's threads

# Zenoh runs an inline callback on its own (Rust) threads and takes the GIL through
# PyGILState_Ensure. On a thread Python does not know, that builds a thread state and frees it
# again when the callback returns: per message, an mmap and a munmap of the 16 kB frame stack, a
# gettid, and cold caches (measured with strace: one of each per message on a relay). Taking the
# GIL once more and never giving it back keeps the thread state for the life of Zenoh's thread,
# so later callbacks reuse it.
# Every callback checks that its thread was seen, in a thread-local attribute: exact, since it
# lives in the thread's own state. (An earlier check by the thread's ident in a set cost half as
# much on a cold cache, 4 vs 8 µs on a relay at 50 Hz, but was not exact: once a pinned thread
# ends, a new thread can get its ident and pass as pinned, and then builds and frees a thread
# state per message again; the test suite twice caught a Zenoh thread losing its state, most
# likely that way.) Only threads Python did not start are
# pinned: a callback can also run on a Python thread (a call or a declaration from this very
# session), which has a state of its own.
_pinned: Final = threading.local()  # seen: set once the thread was looked at (and pinned if foreign)
_gil_ensure: Final[Callable[[], int] | None] = getattr(getattr(ctypes, "pythonapi", None), "PyGILState_Ensure", None)


def _keep_thread_state() -> None:
    """Keep this thread's Python state past the current callback (see above) if Python did not
    start the thread (it then shows as a "dummy" thread to ``threading``); once per thread."""
    if type(threading.current_thread()).__name__ == "_DummyThread" and _gil_ensure is not None:
        _gil_ensure()
    _pinned.seen = True


def _inline(callback: Callable[[Any], None]) -> Any:
    """A Zenoh handler that runs ``callback`` on the thread delivering the sample, keeping that
    thread's Python state between calls."""

    def run(arg: Any) -> None:
        if not getattr(_pinned, "seen", False):
            _keep_thread_state()
        callback(arg)

    return zenoh.handlers.Callback(run, indirect=False)


def _inline_with_end(callback: Callable[[Any], None], end: Callable[[], None]) -> Any:
    """:func:`_inline`, and ``end()`` once Zenoh lets go of the handler (a request ended)."""

    def run(arg: Any) -> None:
        if not getattr(_pinned, "seen", False):
            _keep_thread_state()
        callback(arg)

    return zenoh.handlers.Callback(run, end, indirect=False)


def _clean(exc: BaseException) -> str:
    """Zenoh's message without the Rust source locations it appends."""
    text = str(exc)
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    return text.strip().rstrip(".")


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


class _Links:
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
            self._listener = session.info.declare_link_events_listener(_inline(self._event), history=True)
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


# --------------------------------------------------------------------------- key expressions


def check_key_expr(key: str, *, what: str = "key expression", concrete: bool = False) -> str:
    """Return ``key`` if Zenoh accepts it, else raise :class:`BindingError` naming ``what``.

    With ``concrete=True`` wildcards are refused too (a publisher needs one concrete key).
    """
    if not isinstance(key, str) or not key:
        raise BindingError(f"got {key!r}", where=what, expected="a non-empty Zenoh key expression like 'robot/camera/image'")
    if len(key.encode()) > MAX_KEY_BYTES:
        raise BindingError(
            f"a key expression of {len(key.encode())} bytes is too long", where=what, expected=f"at most {MAX_KEY_BYTES} bytes"
        )
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise BindingError(
            f"{key!r} is not a valid Zenoh key expression ({_clean(exc)})",
            where=what,
            expected="chunks separated by '/', like 'robot/camera/image'",
        ) from exc
    if concrete and is_wild(key):
        raise BindingError(f"{key!r} has wildcards", where=what, expected="a concrete key to publish on, like 'robot/camera/image'")
    return key


def is_wild(key: str) -> bool:
    """Whether ``key`` holds a wildcard (``*``, ``**`` or ``$*``)."""
    return _WILD.search(key) is not None


def key_exprs_intersect(a: str, b: str) -> bool:
    """Whether some key matches both key expressions."""
    if not is_wild(a) and not is_wild(b):
        return a == b
    return zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))


# --------------------------------------------------------------------------- configuration


#: The link protocols of the Zenoh that dyknow installs (eclipse-zenoh's wheel leaves out
#: unixpipe, serial and vsock).
SCHEMES: Final = ("tcp", "tls", "udp", "quic", "ws", "unixsock-stream")


def check_schemes(endpoints: Iterable[str], option: str) -> None:
    """Refuse an endpoint whose protocol Zenoh does not speak (``tpc/...``), naming the ones it
    does (Zenoh itself says only "Unicast not supported for tpc protocol")."""
    for endpoint in endpoints:
        scheme, slash, _ = endpoint.partition("/")
        if slash and scheme not in SCHEMES:  # (no protocol at all: Zenoh's own error, at make_config)
            raise TransportError(
                f"{endpoint}: no Zenoh link protocol {scheme!r}{did_you_mean(scheme, SCHEMES)}",
                where=option,
                expected=f"PROTOCOL/ADDRESS:PORT with PROTOCOL one of {', '.join(SCHEMES)} (such as tcp/127.0.0.1:7447)",
            )


def make_config(
    *,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] = (),
    config_file: str | os.PathLike[str] | None = None,
    tls: TlsFiles | None = None,
    access: AccessControl | None = None,
    lease_ms: int | None = None,
    mode: str = "peer",
    max_message_bytes: int | None = None,
    open_timeout_ms: int | None = None,
    max_sessions: int | None = None,
    shared_memory: bool = True,
) -> zenoh.Config:
    """Build a Zenoh configuration.

    Without ``config_file``: a loopback-only peer (multicast scouting off, gossip on) listening on
    ``listen`` (default: any free port on 127.0.0.1) and connecting to ``connect``. With
    ``config_file``: that json5 file, with ``listen``/``connect`` applied on top when given.
    ``tls``: TLS with mutual authentication on ``tls/HOST:PORT`` endpoints (this process's
    certificate for both listening and connecting, the CA to verify the peer's). ``access``: the
    roles to enforce, as Zenoh access control. ``lease_ms``: how long a silent link lives before
    Zenoh closes it (default 10,000 ms): what a peer cut off from the network takes to be noticed;
    shorter detects sooner, at the cost of keep-alive traffic and of false alarms on a slow link.
    ``mode``: "peer" (default), "router" (a manager, and ``dyknow router``: Zenoh routes
    between routers over any path, so two managers that cannot link directly still reach each
    other through a third or a router, where peers would not) or "client" (a leaf that only
    connects: :class:`~dyknow.client.Client` sessions; give it ``listen=[]``).
    ``max_message_bytes``: the largest message this session takes in (Zenoh's
    ``transport/link/rx/max_message_size``, 1 GiB by default). Zenoh drops a larger one while it
    reassembles it, fragment by fragment, so an oversized message costs at most this much memory.
    ``open_timeout_ms``: how long one attempt to open a link may take (Zenoh's
    ``transport/unicast/open_timeout``; by default the lease, from 2 to 10 s). A lost link is
    dialled again after 0.25 s, then up to every 1 s (half the lease when shorter).
    ``max_sessions``: how many sessions (managers, clients, routers) may link to this one at
    once (Zenoh's ``transport/unicast/max_sessions``); by default 10,000 for a router (Zenoh's
    own 1,000 refused the 1,001st manager of a fleet behind a ``dyknow router``), Zenoh's
    1,000 otherwise. ``shared_memory=False``: no Zenoh shared memory on this session's links, unless
    ``config_file`` says otherwise (``dyknow router``: it carries between hosts, and Zenoh 1.10 made a segment in /dev/shm for
    every session that negotiated it, refusing every session after the 351st).
    """
    for option, endpoints in (("--listen", listen or ()), ("--connect", connect)):
        check_schemes(endpoints, option)
    try:
        if config_file is not None:
            path = Path(config_file)
            if not path.is_file():
                raise TransportError("no such Zenoh configuration file", where=str(path), expected="a json5 file")
            try:
                config = zenoh.Config.from_file(str(path))
            except zenoh.ZError as exc:
                raise TransportError(f"not a valid Zenoh configuration: {_clean(exc)}", where=str(path)) from exc
        else:
            config = zenoh.Config()
            config.insert_json5("mode", json.dumps(mode))
            config.insert_json5("scouting/multicast/enabled", "false")
            config.insert_json5("scouting/gossip/enabled", "true")
            # One link per pair: when both dial each other (two peers that learn of each other
            # at once), the pair holds two TCP links, and after a silent cut closing them blocked
            # both of Zenoh's receive threads for up to 10 s (its fixed SO_LINGER, see "dead
            # links" above), so nothing was read from the healthy links meanwhile. Only the
            # greater id dials. Routers (managers are) also dial the routers they hear of, for a
            # direct path; the path through the others stays when it cannot be made.
            config.insert_json5(
                "scouting/gossip/autoconnect_strategy",
                '{ peer: { to_router: "always", to_peer: "greater-zid" }, router: { to_router: "greater-zid", to_peer: "greater-zid" } }',
            )
            if mode == "router":
                config.insert_json5("scouting/gossip/autoconnect", '{ router: ["router"], peer: ["router", "peer"] }')
            # Dial again soon after a link is lost (Zenoh: after 1 s, then up to every 4 s), each
            # attempt bounded (Zenoh: 10 s): an attempt started while the link was down waits for
            # TCP's next SYN, 1, 3 then 7 s on, so a link back was used up to 4 s late (issue 43).
            # With attempts of at most 2 s (or the lease, up to 10 s), a SYN leaves every 1.25 s.
            lease = lease_ms if lease_ms is not None else 10_000
            retry = {"period_init_ms": 250, "period_max_ms": max(250, min(1000, lease // 2)), "period_increase_factor": 2}
            config.insert_json5("connect/retry", json.dumps(retry))
            if open_timeout_ms is None:
                open_timeout_ms = max(2000, min(10_000, lease))
            # Shared memory only where dyknow asks for it (unit payloads of SHM_THRESHOLD and up, in
            # a pool made on first use): Zenoh's own transport optimization put every message over
            # 3 KiB (the managers' summaries among them) in a 16 MiB pool of each session, and
            # every process mapped every other's, so an idle manager's memory grew with the number
            # of managers (benchmarks/memory.py).
            config.insert_json5("transport/shared_memory/transport_optimization/enabled", "false")
            config.insert_json5("scouting/delay", "0")
            # The admin space tells a manager which port it got when asked for port 0.
            config.insert_json5("adminspace/enabled", "true")
            if listen is None:
                listen = ["tls/127.0.0.1:0" if tls is not None else "tcp/127.0.0.1:0"]
        if listen is not None:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect or config_file is None:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if mode == "client" and config_file is None:
            # like a peer, a client opens before what it connects to is up, and keeps trying
            config.insert_json5("connect/exit_on_failure", "false")
        if tls is not None:
            prefix = "transport/link/tls"
            config.insert_json5(f"{prefix}/root_ca_certificate", json.dumps(tls.ca))
            for side in ("listen", "connect"):
                config.insert_json5(f"{prefix}/{side}_certificate", json.dumps(tls.cert))
                config.insert_json5(f"{prefix}/{side}_private_key", json.dumps(tls.key))
            config.insert_json5(f"{prefix}/enable_mtls", "true")
        if access is not None:
            config.insert_json5("access_control", json.dumps(access.zenoh()))
        if lease_ms is not None:
            if lease_ms < 100:
                raise TransportError(f"got {lease_ms} ms", where="lease", expected="at least 100 ms")
            config.insert_json5("transport/link/tx/lease", str(int(lease_ms)))
        if open_timeout_ms is not None:
            config.insert_json5("transport/unicast/open_timeout", str(max(100, int(open_timeout_ms))))
        if not shared_memory and config_file is None:
            config.insert_json5("transport/shared_memory/enabled", "false")
        if max_sessions is None and mode == "router" and config_file is None:
            max_sessions = ROUTER_MAX_SESSIONS
        if max_sessions is not None:
            if max_sessions < 1:
                raise TransportError(f"got {max_sessions}", where="max_sessions", expected="a whole number of at least 1")
            config.insert_json5("transport/unicast/max_sessions", str(int(max_sessions)))
        if max_message_bytes is not None:
            if max_message_bytes < 65536:
                raise TransportError(f"got {max_message_bytes} bytes", where="max_message_bytes", expected="at least 65,536")
            config.insert_json5("transport/link/rx/max_message_size", str(int(max_message_bytes)))
    except zenoh.ZError as exc:
        raise TransportError(f"invalid Zenoh endpoint: {_clean(exc)}", where=f"listen={listen!r} connect={list(connect)!r}") from exc
    return config


# --------------------------------------------------------------------------- entities


class _Entity:
    """Something declared on a session: undeclare() is safe twice; a context manager."""

    def __init__(self, handle: Any) -> None:
        self._handle = handle

    def undeclare(self) -> None:
        handle, self._handle = self._handle, None
        if handle is not None:
            with contextlib.suppress(zenoh.ZError):  # the session is already closed: nothing left to undeclare
                handle.undeclare()

    def __enter__(self) -> _Entity:
        return self

    def __exit__(self, *exc: object) -> None:
        self.undeclare()


class _HistorySubscriber(_Entity):
    """Zenoh's advanced subscriber with history (rmw_zenoh's transient-local durability), declared
    again while it has received nothing: a router (a manager) that has just linked may not have
    its neighbour's cache routed yet when the subscriber asks for history and sees the late
    publisher's token, and the latched sample was then never asked for again (a transient-local
    ``/map`` missed by a subscriber that joined late; Zenoh 1.10). Once a sample came, the
    subscriber stays as it is (asking again would deliver the cache twice)."""

    def __init__(self, session: zenoh.Session, key: str, callback: Callable[[zenoh.Sample], None]) -> None:
        import zenoh.ext as zext  # (an extension: unstable API)

        self._zext: Any = zext
        self._session = session
        self._key = key
        self._callback = callback
        self._lock = threading.Lock()
        self._received = False
        self._timer: threading.Timer | None = None
        super().__init__(self._declare())
        self._schedule(0)

    def _declare(self) -> Any:
        zext = self._zext
        return zext.declare_advanced_subscriber(
            self._session, self._key, self._on_sample, history=zext.HistoryConfig(detect_late_publishers=True)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._received = True
        self._callback(sample)

    def _schedule(self, attempt: int) -> None:
        delays = (0.5, 1.0, 2.0, 4.0, 8.0)  # s, while nothing was received (a 15.5 s window)
        if attempt >= len(delays):
            return
        timer = threading.Timer(delays[attempt], self._again, (attempt,))
        timer.daemon = True
        self._timer = timer
        timer.start()

    def _again(self, attempt: int) -> None:
        with self._lock:
            if self._received or self._handle is None:
                return
            try:
                fresh = self._declare()
            except zenoh.ZError:
                return  # the session closed meanwhile
            old, self._handle = self._handle, fresh
        with contextlib.suppress(zenoh.ZError):
            old.undeclare()
        self._schedule(attempt + 1)

    def undeclare(self) -> None:
        """Stop receiving; safe twice."""
        with self._lock:
            timer, self._timer = self._timer, None
            if timer is not None:
                timer.cancel()
            super().undeclare()


class Publisher(_Entity):
    """Publishes dyknow messages on one concrete key, to other sessions only.

    ``matched`` tells whether any remote subscriber matches; callers skip encoding when not.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        on_matching: Callable[[bool], None] | None,
        shm: _SharedMemory | None = None,
        reliable: bool = False,
    ) -> None:
        self._shm = shm
        # Streams drop rather than stall their producer when the network queue is full (Zenoh's
        # default); a reliable publisher (a replay, say) blocks instead so nothing is lost.
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        try:
            pub = session.declare_publisher(key, allowed_destination=zenoh.Locality.REMOTE, congestion_control=congestion)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a publisher on {key!r}: {_clean(exc)}") from exc
        super().__init__(pub)
        self.key = key
        self.matched = False
        self._on_matching = on_matching
        # The status read below and the listener's news can cross: Zenoh may report a match on its
        # thread while this one still reads the (older) status. The read then must not overwrite
        # the news, or the publisher stays unmatched until the next change.
        heard = False
        lock = threading.Lock()

        def matching(status: zenoh.MatchingStatus) -> None:
            nonlocal heard
            with lock:
                self.matched = status.matching
                heard = True
            if self._on_matching is not None:
                self._on_matching(status.matching)

        # on Zenoh's thread: it only sets a flag (a thread per publisher would cost a thread per unit)
        self._listener: Any = pub.declare_matching_listener(_inline(matching))
        # the 1.10 stub says bool, but the property returns a MatchingStatus (always truthy)
        current = pub.matching_status.matching  # type: ignore[attr-defined]
        with lock:
            if not heard:
                self.matched = current

    def put(self, msg: Message) -> int:
        """Encode and send ``msg``; returns the number of payload bytes sent."""
        handle = self._handle
        if handle is None:
            return 0
        data, attachment, encoding = encode(msg)
        size = len(data)
        if size >= SHM_THRESHOLD and self._shm is not None and type(data) is bytes:
            data = self._shm.wrap(data)
        try:
            handle.put(data, attachment=attachment, encoding=_ENCODINGS[encoding])
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {self.key!r}: {_clean(exc)}") from exc
        return size

    def put_wire(self, data: Any, attachment: bytes, encoding: str) -> None:
        """Send a payload as it was received (the transport's own buffer, not copied) under a
        header made by :func:`~dyknow.message.reheader`."""
        handle = self._handle
        if handle is None:
            return
        try:
            handle.put(data, attachment=attachment, encoding=_ENCODINGS[encoding])
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {self.key!r}: {_clean(exc)}") from exc

    def undeclare(self) -> None:
        """Stop publishing; safe twice."""
        listener, self._listener = getattr(self, "_listener", None), None
        if listener is not None:
            with contextlib.suppress(zenoh.ZError):
                listener.undeclare()
        super().undeclare()


class Subscriber(_Entity):
    """Receives dyknow messages (or plain Zenoh samples) published by other sessions.

    By default ``on_message`` runs on a Python thread Zenoh keeps for this subscriber (one per
    subscriber), so it may take its time. ``inline``: it runs on Zenoh's own receiving thread
    instead, which costs no thread at all but holds up every stream arriving over the same link
    while it runs: only for a quick hand-off (the units' input ports queue the message for their
    lane). Exceptions are passed to ``on_error`` instead of being swallowed by Zenoh.

    ``forward``: offered every dyknow message first, as ``forward(payload, header)`` (the
    transport's buffer and the header bytes) before anything is decoded; when it returns True it
    has passed the message on and ``on_message`` is not called (see
    :meth:`~dyknow.proxy.Proxy.forward_wire`).
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        on_message: Callable[[Message], None],
        on_error: Callable[[BaseException], None],
        inline: bool = False,
        wanted: Callable[[str], object] | None = None,
        forward: Callable[[Any, bytes], bool] | None = None,
    ) -> None:
        self.key = key
        self._count = 0
        fixed_key = None if is_wild(key) else key
        put_kind = zenoh.SampleKind.PUT

        def callback(sample: zenoh.Sample) -> None:
            # Cheapest checks first: this runs once per message from another process.
            if inline and not getattr(_pinned, "seen", False):
                _keep_thread_state()
            try:
                if wanted is not None and not wanted(str(sample.key_expr)):
                    return  # nobody reads this key: not worth decoding
                attachment = sample.attachment
                header = attachment.to_bytes() if attachment is not None else None
                if header is not None and header[:2] == b"DK" and len(header) >= _HEADER_SIZE:  # is_dyknow(), inlined
                    payload = sample.payload  # one call into Zenoh's object, for either path
                    if forward is not None and forward(payload, header):
                        return
                    msg = decode_dyknow(payload, header, fixed_key or str(sample.key_expr))
                elif sample.kind == put_kind:
                    self._count += 1
                    msg = decode(
                        sample.payload,
                        header,
                        str(sample.key_expr),
                        encoding=str(sample.encoding),
                        arrival_ns=time.time_ns(),
                        seq=self._count,
                    )
                else:
                    return
                on_message(msg)
            except Exception as exc:  # Zenoh would only log it; the owner records it
                on_error(exc)

        try:
            handler = zenoh.handlers.Callback(callback, indirect=False) if inline else callback
            sub = session.declare_subscriber(key, handler, allowed_origin=zenoh.Locality.REMOTE)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a subscriber on {key!r}: {_clean(exc)}") from exc
        super().__init__(sub)


class PlainPublisher(_Entity):
    """Publishes payloads of another protocol (ROS 2 over rmw_zenoh) as they are: bytes with an
    attachment of that protocol, to every session (this one included).

    ``cache``: keep the last ``cache`` samples for late subscribers that ask for history (Zenoh's
    advanced publisher, as rmw_zenoh declares it for transient-local durability); 0 is a plain
    publisher. ``block``: block when the network queue is full instead of dropping.
    """

    def __init__(self, session: zenoh.Session, key: str, *, block: bool, cache: int, encoding: str) -> None:
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._encoding = zenoh.Encoding(encoding)
        try:
            if cache > 0:
                import zenoh.ext as zext  # the advanced publisher is an extension (unstable API)

                pub: Any = zext.declare_advanced_publisher(
                    session,
                    key,
                    congestion_control=congestion,
                    cache=zext.CacheConfig(cache),
                    # sequence numbers, not timestamps (those need timestamping on in the session config)
                    sample_miss_detection=zext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=None),
                    publisher_detection=True,
                )
            else:
                pub = session.declare_publisher(key, congestion_control=congestion)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a publisher on {key!r}: {_clean(exc)}") from exc
        super().__init__(pub)
        self.key = key

    def put(self, data: bytes, attachment: bytes | None = None) -> None:
        """Send ``data`` with ``attachment``; nothing once undeclared."""
        handle = self._handle
        if handle is None:
            return
        try:
            handle.put(data, attachment=attachment, encoding=self._encoding)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {self.key!r}: {_clean(exc)}") from exc


class Queryable(_Entity):
    """Answers requests on a key expression with ``handler(key, payload) -> (ok, reply_bytes)``.

    The handler runs on a Python thread of its own (one per queryable), one request at a time.
    For calls served by several threads, see :class:`ServiceChannel`.
    """

    def __init__(self, session: zenoh.Session, key: str, handler: Callable[[str, bytes], tuple[bool, bytes]], inline: bool = False) -> None:
        def answer(query: zenoh.Query) -> None:
            qkey = str(query.key_expr)
            try:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                ok, reply = handler(qkey, payload)
            except Exception as exc:  # a bug in a handler must still answer the caller
                log.exception("service handler for %s failed", qkey)
                ok, reply = False, json.dumps({"error": type(exc).__name__, "message": str(exc)}).encode()
            _reply(query, ok, reply)

        try:
            queryable = session.declare_queryable(key, _inline(answer) if inline else answer)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a service on {key!r}: {_clean(exc)}") from exc
        super().__init__(queryable)
        self.key = key


def _reply(query: zenoh.Query, ok: bool, reply: bytes) -> None:
    try:
        if ok:
            query.reply(query.key_expr, reply)
        else:
            query.reply_err(reply)
    except zenoh.ZError as exc:
        log.warning("cannot reply to %s: %s", query.key_expr, _clean(exc))
    finally:
        query.drop()  # the final answer: the caller stops waiting


class ServiceRequest:
    """One call a :class:`ServiceChannel` received: its key, payload and attachment. Answer it once."""

    __slots__ = ("_query", "attachment", "key", "payload")

    def __init__(self, query: zenoh.Query) -> None:
        self._query = query
        self.key = str(query.key_expr)
        self.payload = query.payload.to_bytes() if query.payload is not None else b""
        self.attachment = query.attachment.to_bytes() if query.attachment is not None else None  # the caller's signature, if any

    def reply(self, ok: bool, data: bytes) -> None:
        """Send the answer (``ok``) or the error reply; the caller stops waiting."""
        _reply(self._query, ok, data)


class ServiceChannel(_Entity):
    """Receives the calls on a key expression into a queue of ``capacity`` that several threads
    take from with :meth:`receive` (so no single thread stands between the calls and their
    handlers). When the queue is full, Zenoh holds further calls back on the link they came by.

    Calls are queued by an inline callback (on Zenoh's thread, or on the caller's for a call from
    this session) rather than through Zenoh's own channel, whose blocking receive wakes every
    reader ten times a second to check for signals: an idle manager's readers sleep until a call
    comes.
    """

    def __init__(
        self, session: zenoh.Session, key: str, capacity: int, at_once: Mapping[str, Callable[[bytes, int], tuple[bool, bytes]]] | None = None
    ) -> None:
        self.key = key
        self._closed = False
        self._calls: queue.Queue[ServiceRequest | None] = queue.Queue(capacity)
        quick = dict(at_once or {})

        def arrived(query: zenoh.Query) -> None:  # on Zenoh's thread, or the caller's in this session
            if quick:
                handler = quick.get(str(query.key_expr))
                if handler is not None:  # answered right here: handler(payload, arrival ns)
                    now = time.time_ns()
                    payload = query.payload.to_bytes() if query.payload is not None else b""
                    _reply(query, *handler(payload, now))
                    return
            request = ServiceRequest(query)
            while not self._closed:
                try:
                    self._calls.put(request, timeout=0.1)  # full: hold the link back, as Zenoh's channel does
                    return
                except queue.Full:
                    continue

        try:
            queryable = session.declare_queryable(key, _inline(arrived))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a service on {key!r}: {_clean(exc)}") from exc
        super().__init__(queryable)

    def receive(self) -> ServiceRequest | None:
        """The next call, waiting for it; None once the channel is undeclared."""
        request = self._calls.get() if not self._closed else None
        if request is None or self._closed:
            with contextlib.suppress(queue.Full):
                self._calls.put_nowait(None)  # wake the next reader too
            return None
        return request

    def undeclare(self) -> None:
        """Stop receiving; the readers' :meth:`receive` returns None. Safe twice."""
        self._closed = True
        super().undeclare()
        with contextlib.suppress(queue.Full):
            self._calls.put_nowait(None)


class LivelinessToken(_Entity):
    """Announces that something is alive on a key until undeclared (or the process dies)."""


class LivelinessSubscriber(_Entity):
    """Calls ``on_change(key, alive)`` when liveliness tokens matching a key appear or vanish."""


# --------------------------------------------------------------------------- session


# Every session still open when the interpreter exits is closed first, newest first. Left to the
# garbage collector at exit, Zenoh closed one from a finalizer once and panicked ("close operation
# timed out", issue 43). It runs before Python waits for its threads (as concurrent.futures does),
# so the threads of Zenoh's callbacks end and a script that forgot to close a session exits.
# (Held strongly: the class is compiled, and mypyc's classes take no weak references. A session
# is taken out as it closes; one never closed stays open until exit, as a Zenoh session would.)
_open_sessions: Final[dict[int, Session]] = {}


def _close_open_sessions() -> None:
    for session in sorted(list(_open_sessions.values()), key=lambda s: s.opened_ns, reverse=True):
        try:
            session.close()
        except Exception:  # at exit: the others are closed whatever this one does
            log.debug("closing a session at exit failed", exc_info=True)


_before_threads_end: Callable[[Callable[[], None]], object] | None = getattr(threading, "_register_atexit", None)
if _before_threads_end is not None:
    _before_threads_end(_close_open_sessions)
else:  # (an interpreter without it: at exit, then)
    atexit.register(_close_open_sessions)


def _lease_and_dials(config: zenoh.Config) -> tuple[int, list[str]]:
    """The lease (ms) of a configuration, and the endpoints it dials (a list, or one per mode)."""
    try:
        lease = json.loads(config.get_json("transport/link/tx/lease"))
        lease_ms = int(lease) if isinstance(lease, int) and not isinstance(lease, bool) and lease > 0 else 10_000
    except (zenoh.ZError, ValueError):
        lease_ms = 10_000
    try:
        found = json.loads(config.get_json("connect/endpoints"))
    except (zenoh.ZError, ValueError):
        found = []
    listed = found if isinstance(found, list) else [e for v in found.values() if isinstance(v, list) for e in v] if isinstance(found, dict) else []
    return lease_ms, [str(e) for e in listed]


class Session:
    """A Zenoh session: the entry point to declare publishers, subscribers and services.

    A context manager; ``close()`` is safe twice and undeclares everything declared on it.
    """

    def __init__(self, config: zenoh.Config | None = None) -> None:
        if config is None:
            config = make_config()
        lease_ms, dials = _lease_and_dials(config)
        _lay_out_runtimes()
        try:
            self._session: zenoh.Session | None = zenoh.open(config)
        except zenoh.ZError as exc:
            text = _clean(exc)
            expected = None
            if "Address already in use" in text:
                text += "; another process listens there (a manager already running?)"
                expected = "another port (--listen)"
            raise TransportError(f"cannot open a Zenoh session: {text}", expected=expected) from exc
        except BaseException as exc:  # a Zenoh panic is no Exception
            error = _panic_error(exc)
            if error is None:
                raise
            raise error from exc
        self._lock = threading.Lock()
        # service key -> [querier, reachable, calls using it now]; the most recently used last
        self._queriers: collections.OrderedDict[str, list[Any]] = collections.OrderedDict()
        self._shm = _SharedMemory()
        self._links = _Links(self._session, lease_ms)
        self._dials = dials
        self.opened_ns = time.monotonic_ns()
        _open_sessions[id(self)] = self

    # -- lifecycle

    @property
    def closed(self) -> bool:
        """Whether the session is closed."""
        return self._session is None

    def _z(self) -> zenoh.Session:
        session = self._session
        if session is None:
            raise ClosedError("the Zenoh session is closed", expected="a new session")
        return session

    def close(self) -> None:
        """Close the session; safe to call twice."""
        session, self._session = self._session, None
        if session is not None:
            _open_sessions.pop(id(self), None)
            self._links.close()
            if self._dials:  # (Zenoh's close would wait for a dial under way)
                abort_dials(self._dials)
            for querier, _, _ in self._queriers.values():
                with contextlib.suppress(zenoh.ZError):
                    querier.undeclare()
            self._queriers.clear()
            session.close()

    def flush(self, timeout_s: float = 5.0) -> int:
        """Wait until what this session sent so far has reached the Zenoh nodes it is linked to
        directly; returns how many confirmed.

        Zenoh's ``put`` returns once a message is queued, and closing a session right after
        can lose what is still queued (a replay that ends and exits, say). This asks each
        neighbour's admin space a question over the same link and priority as the data: its
        answer comes after everything sent before. Neighbours without an admin space (a plain
        Zenoh peer that did not enable it) do not answer, and give no such guarantee; dyknow's
        managers and Zenoh routers do.
        """
        session = self._z()
        info = session.info
        neighbours = [str(z) for z in (*info.peers_zid(), *info.routers_zid())]
        confirmed = 0
        for zid in neighbours:
            try:
                replies = session.get(f"@/{zid}/*", timeout=timeout_s)
                confirmed += any(r.ok is not None for r in replies)
            except zenoh.ZError as exc:
                log.debug("flush: %s did not answer: %s", zid, _clean(exc))
        return confirmed

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- information

    @property
    def zid(self) -> str:
        """The session's Zenoh id."""
        return str(self._z().zid())

    def endpoints(self) -> list[str]:
        """The locators this session listens on (actual ports, also when asked for port 0)."""
        session = self._z()
        zid = session.zid()
        for mode in ("peer", "router", "client"):
            # the key names our own zid, so only this session answers
            for reply in session.get(f"@/{zid}/{mode}", timeout=2):
                if reply.ok is not None:
                    try:
                        return list(json.loads(reply.ok.payload.to_bytes()).get("locators", []))
                    except (ValueError, AttributeError):
                        return []
        return []

    def linked(self) -> bool:
        """Whether the session has a link to another Zenoh node (a peer or a router) now."""
        info = self._z().info
        return bool(info.peers_zid()) or bool(info.routers_zid())

    # -- declarations

    def declare_publisher(self, key: str, on_matching: Callable[[bool], None] | None = None, *, reliable: bool = False) -> Publisher:
        """A publisher on ``key``; ``reliable`` blocks when the network queue is full instead of dropping."""
        return Publisher(self._z(), key, on_matching, self._shm, reliable)

    def declare_subscriber(
        self,
        key: str,
        on_message: Callable[[Message], None],
        on_error: Callable[[BaseException], None] | None = None,
        *,
        inline: bool = False,
        wanted: Callable[[str], object] | None = None,
        forward: Callable[[Any, bytes], bool] | None = None,
    ) -> Subscriber:
        """Receive dyknow messages (or plain samples) published on ``key`` by other sessions.

        ``inline``: call ``on_message`` on Zenoh's receiving thread (no thread of its own; it must
        return at once, see :class:`Subscriber`). ``wanted(key)``: samples on keys it says no to
        are dropped before they are decoded. ``forward``: offered each dyknow message before it
        is decoded (see :class:`Subscriber`)."""
        on_error = on_error or (lambda exc: log.warning("on %s: %s", key, exc))
        return Subscriber(self._z(), key, on_message, on_error, inline, wanted, forward)

    def declare_plain_publisher(
        self, key: str, *, block: bool = False, cache: int = 0, encoding: str = "application/cdr"
    ) -> PlainPublisher:
        """A publisher of another protocol's payloads on ``key`` (see :class:`PlainPublisher`)."""
        return PlainPublisher(self._z(), key, block=block, cache=cache, encoding=encoding)

    def declare_sample_subscriber(
        self,
        key: str,
        on_sample: Callable[[str, bytes, bytes | None], None],
        *,
        history: bool = False,
        max_bytes: int = 64 * 1024 * 1024,
        on_refused: Callable[[str, str], None] | None = None,
    ) -> _Entity:
        """Receive another protocol's samples on ``key`` from every session, this one included:
        ``on_sample(key, payload, attachment)`` on a thread Zenoh keeps for this subscriber.

        A payload over ``max_bytes`` is refused before it is copied: ``on_refused(key, why)``.
        ``history``: also ask publishers with a cache for what they kept (Zenoh's advanced
        subscriber, as rmw_zenoh declares it for transient-local durability)."""

        def callback(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            key_expr = str(sample.key_expr)
            try:
                size = len(sample.payload)
                if size > max_bytes:
                    if on_refused is not None:
                        on_refused(key_expr, f"a payload of {size} bytes, over the limit of {max_bytes}")
                    return
                attachment = sample.attachment
                on_sample(key_expr, sample.payload.to_bytes(), attachment.to_bytes() if attachment is not None else None)
            except Exception:
                log.exception("callback for %s failed", key)

        try:
            if history:
                return _HistorySubscriber(self._z(), key, callback)
            else:
                sub = self._z().declare_subscriber(key, callback)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {key!r}: {_clean(exc)}") from exc
        return _Entity(sub)

    def declare_queryable(self, key: str, handler: Callable[[str, bytes], tuple[bool, bytes]], *, inline: bool = False) -> Queryable:
        """Serve requests on ``key`` with ``handler(key, payload) -> (ok, reply)``; ``inline``: on
        Zenoh's receiving thread (the handler must return at once), not a thread of its own."""
        return Queryable(self._z(), key, handler, inline)

    def exchange(self, key: str, payload: bytes, *, timeout_s: float, done: Callable[[tuple[bytes, int, int, int] | None], None]) -> None:
        """Send one timed request to the queryable on ``key`` and return at once; ``done(result)``
        is called once, on a Zenoh thread, when the request ends (every reply in, or
        ``timeout_s`` passed): ``(first reply, t_sent_ns, t_received_ns, replies)``, or None when
        no reply came. The times are this process's wall clock, taken once Zenoh took the request
        and on Zenoh's thread as the first reply arrived: no thread hand-off inside either. For
        clock exchanges (:mod:`dyknow.clocks`). Replies are not consolidated, so ``replies``
        counts them all (a peer that floods is seen); only the first is kept. (A reply may
        arrive before ``t_sent_ns`` is taken: the caller then uses its own earlier time.)"""
        lock = threading.Lock()
        state: list[Any] = [None, 0, 0, False, False]  # first (payload, arrival), replies, sent, get returned, ended

        def on_reply(reply: zenoh.Reply) -> None:
            arrived = time.time_ns()
            with lock:
                state[1] += 1
                if state[0] is None and reply.ok is not None:
                    state[0] = (reply.ok.payload.to_bytes(), arrived)

        def finish() -> None:
            first, replies, sent = state[0], state[1], state[2]
            done(None if first is None else (first[0], sent, first[1], replies))

        def ended() -> None:  # Zenoh drops the handler when the request ends
            with lock:
                state[4] = True
                returned = state[3]
            if returned:
                finish()

        try:
            # DROP, not Zenoh's BLOCK for queries: the reply takes the query's congestion control,
            # and the peer answers on the thread that reads its link (the arrival time is the
            # exchange's point). Over a saturated link a BLOCK reply waited there for room in the
            # queue, for seconds: nothing else was read from that link meanwhile (the keep-alives
            # neither), the link was closed and made again, and a camera's frames across it stopped
            # for 4 s at a time. An exchange that cannot be sent now is worth nothing later anyway.
            self._z().get(
                key,
                _inline_with_end(on_reply, ended),
                payload=payload,
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.DROP,
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot query {key!r}: {_clean(exc)}") from exc
        # taken once Zenoh has the query: before it, the Python call's own cost counted on the
        # request's leg alone and tilted every offset by tens of µs (measured in namespaces)
        sent = time.time_ns()
        with lock:
            state[2] = sent
            state[3] = True
            over = state[4]
        if over:
            finish()

    def declare_service_channel(
        self, key: str, capacity: int = 1024, *, at_once: Mapping[str, Callable[[bytes, int], tuple[bool, bytes]]] | None = None
    ) -> ServiceChannel:
        """Receive the calls on ``key`` for several threads to answer (see :class:`ServiceChannel`).

        ``at_once``: calls on these concrete keys are answered on the thread that receives them,
        by ``handler(payload, arrival_ns) -> (ok, reply)``, which must return at once (a clock
        exchange: :mod:`dyknow.clocks`)."""
        return ServiceChannel(self._z(), key, capacity, at_once)

    def declare_liveliness_token(self, key: str) -> LivelinessToken:
        """Announce on ``key`` that something lives, until undeclared or the process ends."""
        try:
            return LivelinessToken(self._z().liveliness().declare_token(key))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a liveliness token on {key!r}: {_clean(exc)}") from exc

    def declare_liveliness_subscriber(
        self, key: str, on_change: Callable[[str, bool], None], *, inline: bool = False
    ) -> LivelinessSubscriber:
        """Call ``on_change(key, alive)`` as tokens on ``key`` appear and vanish (existing ones first).

        ``inline``: on Zenoh's thread (no thread of its own; ``on_change`` must return at once).
        While this watch's first tokens are on their way, a liveliness query of this session on
        keys it covers is answered from what the session heard so far, not by the network (a
        Zenoh client: nothing, in 19 of 30 fresh sessions asked just after declaring it)."""

        def callback(sample: zenoh.Sample) -> None:
            try:
                on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
            except Exception:
                log.exception("liveliness callback for %s failed", key)

        try:
            handler = _inline(callback) if inline else callback
            sub = self._z().liveliness().declare_subscriber(key, handler, history=True)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot watch liveliness on {key!r}: {_clean(exc)}") from exc
        return LivelinessSubscriber(sub)

    def alive(self, key: str, *, timeout_s: float = 1.0) -> list[str]:
        """The keys of the liveliness tokens matching ``key`` that are up now, sorted.

        A session just opened learns of the others' tokens over a few milliseconds: it asks
        until two answers agree (and are not empty), or ``timeout_s`` passes.
        """
        deadline = time.monotonic() + timeout_s
        last: list[str] | None = None
        while True:
            # (answers come to a callback: a channel of Zenoh's (256 by default) filled up inside
            # get() itself when this session already knew the tokens, and get() never returned:
            # a client that watches the managers' tokens, asking which of 500 managers are up)
            answers: list[list[str]] = []
            answered = threading.Event()

            def done(keys: list[str], count: int, answers: list[list[str]] = answers, answered: threading.Event = answered) -> None:
                answers.append(keys)
                answered.set()

            left = max(0.05, deadline - time.monotonic())
            self.ask_alive(key, timeout_s=left, limit=MAX_ALIVE_KEYS, done=done)
            answered.wait(left + 1.0)
            found = sorted(set(answers[0])) if answers else []
            if (found and found == last) or time.monotonic() >= deadline:
                return found
            last = found
            threading.Event().wait(0.05)  # (time.sleep fails under a faked clock: libfaketime's clock_nanosleep)

    def ask_alive(
        self,
        key: str,
        *,
        timeout_s: float,
        limit: int,
        done: Callable[[list[str], int], None],
        timed_out: Callable[[], None] | None = None,
    ) -> None:
        """Ask once which liveliness tokens on ``key`` are up, and return at once: ``done(keys,
        count)`` is called once, on a Zenoh thread, when the answer is complete (or ``timeout_s``
        passed): the first ``limit`` keys in the order they came, and how many came in all.
        ``timed_out()`` is called first when it is not complete: Zenoh ended the question at
        ``timeout_s`` (its only error reply to it), so tokens may be missing from the answer."""
        lock = threading.Lock()
        found: list[str] = []
        count = [0]
        late = [False]

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                late[0] = True
                return
            with lock:
                count[0] += 1
                if len(found) < limit:
                    found.append(str(reply.ok.key_expr))

        def ended() -> None:  # Zenoh drops the handler when the request ends
            with lock:
                keys, total = list(found), count[0]
            try:
                if late[0] and timed_out is not None:
                    timed_out()
                done(keys, total)
            except Exception:
                log.exception("the answer to who is alive on %s failed", key)

        try:
            self._z().liveliness().get(key, _inline_with_end(on_reply, ended), timeout=timeout_s)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot ask who is alive on {key!r}: {_clean(exc)}") from exc

    def put(self, key: str, data: bytes | str, *, encoding: str = "application/json") -> None:
        """Publish one plain sample (for events and measurements)."""
        try:
            self._z().put(key, data, encoding=zenoh.Encoding(encoding))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {key!r}: {_clean(exc)}") from exc

    def declare_raw_subscriber(self, key: str, on_sample: Callable[[str, bytes], None]) -> _Entity:
        """Receive plain samples from any session, this one included (for events and measurements)."""

        def callback(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                try:
                    on_sample(str(sample.key_expr), sample.payload.to_bytes())
                except Exception:
                    log.exception("callback for %s failed", key)

        try:
            return _Entity(self._z().declare_subscriber(key, callback))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {key!r}: {_clean(exc)}") from exc

    # -- services

    def call(
        self,
        key: str,
        payload: bytes,
        *,
        timeout_s: float,
        what: str,
        sign: Callable[[str, bytes], bytes] | None = None,
        gone: Callable[[], str | None] | None = None,
        reachable_within_s: float | None = None,
        absent: Callable[[], str | None] | None = None,
    ) -> bytes:
        """Send a request to the service on ``key`` and return its reply.

        Waits up to ``timeout_s`` seconds (``reachable_within_s`` when given) for the service to be
        reachable, then up to ``timeout_s`` for its answer.
        Raises :class:`ServiceError` when nobody answers (``what`` names the service for the
        message) or with the service's own error when it refuses the request. ``sign(key,
        payload)`` gives the call's attachment (its caller's signature: see
        :mod:`dyknow.identity`), made once the service is reachable, so its time is fresh.
        ``gone()``: why the service's owner is known to be gone, or None; while it says so the
        call ends at once with that reason instead of waiting for the service to come back.
        ``absent()``: why the service's owner seems not to be there (the network said its token is
        not up), or None; when it says so, the request is sent once anyway (the router routes it
        to a service this session has not heard of yet, or ends it at once without a reply), and
        only if nothing answered does the call end with that reason (``details["reason"]``
        ``"absent"``). A request that reached no service did nothing, so it is safe to send later.
        """
        window_s = timeout_s if reachable_within_s is None else reachable_within_s
        deadline = time.monotonic() + window_s
        entry = self._querier(key, timeout_s)
        try:
            return self._call(entry[0], entry[1], key, payload, deadline, window_s, timeout_s, what, sign, gone, absent)
        finally:
            with self._lock:
                entry[2] -= 1

    def _call(
        self,
        querier: Any,
        reachable: threading.Event,
        key: str,
        payload: bytes,
        deadline: float,
        window_s: float,
        timeout_s: float,
        what: str,
        sign: Callable[[str, bytes], bytes] | None,
        gone: Callable[[], str | None] | None,
        absent: Callable[[], str | None] | None,
    ) -> bytes:
        while not reachable.is_set():
            why = gone() if gone is not None else None
            if why is not None:
                raise ServiceError(f"no answer from {what}: {why}", details={"reason": "gone"})
            why = absent() if absent is not None and not reachable.is_set() else None
            if why is not None and not reachable.is_set():
                reply = self._ask(querier, key, payload, what, sign)  # (once: a service not heard of yet answers it)
                if reply is not None:
                    return reply
                if not reachable.is_set():
                    raise ServiceError(f"no answer from {what}: {why}", details={"reason": "absent"})
            left = deadline - time.monotonic()
            if left <= 0:
                raise ServiceError(f"no answer from {what}: nothing serves {key!r} within {window_s:.3g} s", details={"reason": "unreachable"})
            reachable.wait(min(left, 0.05) if gone is not None else left)
        since = self._links.closed
        until: float | None = None  # when an early end, unexplained, is taken as a drop
        pause = _RETRY_FIRST_S
        while True:
            sent = time.monotonic()
            reply = self._ask(querier, key, payload, what, sign)
            if reply is not None:
                return reply
            now = time.monotonic()
            if now >= sent + 0.9 * timeout_s:
                raise ServiceError(f"no answer from {what} on {key!r} within {timeout_s:g} s")
            # It ended early, without a reply. Zenoh ends a request so when the link it went over
            # closes (a host cut off past its lease, a process gone), when an access control on
            # the way drops it, and when no route reaches the service yet although the service
            # is known (just after a router appears, while the routers compute their paths); it
            # says nothing of which (issue 43: a link lost mid-call read as the manager's --acl
            # refusing the caller). A link of this session that closed, or the service's owner
            # gone (``gone()``: its liveliness token), shows within moments: looked for, while the
            # request is asked again (it reached no service: asking again is safe) for up to
            # _CUT_GRACE_S; only when nothing explains it is it taken as dropped on its way.
            until = until if until is not None else min(sent + timeout_s, now + _CUT_GRACE_S)
            if self._links.closed != since:
                raise ServiceError(
                    f"no answer from {what}: the link to {self._links.last_closed} closed during the call "
                    "(a host cut off past its lease, or the process at the other end stopped)",
                    expected="the link back (Zenoh dials again by itself), then the call again",
                    details={"reason": "link-closed"},
                )
            why = gone() if gone is not None else None
            if why is not None:
                raise ServiceError(f"no answer from {what}: {why}, during the call", details={"reason": "gone"})
            if now >= until:
                raise ServiceError(
                    f"no answer from {what}: the request to {key!r} was dropped without a reply",
                    expected="a role allowed to call it (the manager's --acl refuses silently), and a manager that stays up until it answers",
                    details={"reason": "dropped"},
                )
            self._links.wait_closed(since, min(pause, until - now))
            pause = min(2 * pause, 0.1)

    def _ask(
        self, querier: Any, key: str, payload: bytes, what: str, sign: Callable[[str, bytes], bytes] | None
    ) -> bytes | None:
        """One request: the reply, None when it ended without one; :class:`ServiceError` with
        the service's own error when it refused."""
        try:
            attachment = sign(key, payload) if sign is not None else None
            replies = querier.get(payload=payload, attachment=attachment)
            for reply in replies:
                if reply.ok is not None:
                    return bytes(reply.ok.payload.to_bytes())
                data = reply.err.payload.to_bytes()
                try:
                    err = json.loads(data)
                except ValueError:
                    raise ServiceError(data.decode(errors="replace")) from None
                if not isinstance(err, dict):
                    raise ServiceError(data.decode(errors="replace"))
                raise ServiceError(str(err.get("message", data)), kind=err.get("error"), details=err)
        except zenoh.ZError as exc:
            raise ServiceError(f"request to {what} failed: {_clean(exc)}") from exc
        return None

    def _querier(self, key: str, timeout_s: float) -> list[Any]:
        """The querier of ``key`` (declared on first use, kept for the next calls), marked in use.

        At most :data:`MAX_QUERIERS` are kept: a client calling the services of ever new units
        undeclares the least recently used ones rather than holding them all."""
        with self._lock:
            found = self._queriers.get(key)
            if found is not None:
                self._queriers.move_to_end(key)
                found[2] += 1
                return found
            reachable = threading.Event()

            def matching(status: zenoh.MatchingStatus) -> None:  # on Zenoh's thread: only sets the event
                if status.matching:
                    reachable.set()
                else:
                    reachable.clear()

            try:
                querier = self._z().declare_querier(key, timeout=timeout_s)
                querier.declare_matching_listener(_inline(matching))
            except zenoh.ZError as exc:
                raise TransportError(f"cannot declare a querier on {key!r}: {_clean(exc)}") from exc
            if querier.matching_status.matching:  # type: ignore[attr-defined]  # see Publisher
                reachable.set()
            entry = [querier, reachable, 1]
            self._queriers[key] = entry
            idle = [k for k, e in self._queriers.items() if e[2] == 0]
            for old in idle[: max(0, len(self._queriers) - MAX_QUERIERS)]:
                with contextlib.suppress(zenoh.ZError):
                    self._queriers.pop(old)[0].undeclare()
            return entry

    def queriers(self) -> int:
        """How many service queriers the session keeps (at most :data:`MAX_QUERIERS` idle ones)."""
        with self._lock:
            return len(self._queriers)


def open_session(
    *,
    listen: Sequence[str] | None = None,
    connect: Iterable[str] = (),
    config_file: str | os.PathLike[str] | None = None,
) -> Session:
    """Open a session with :func:`make_config`'s defaults."""
    return Session(make_config(listen=listen, connect=list(connect), config_file=config_file))
