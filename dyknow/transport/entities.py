"""What a session declares: publishers, subscribers, queryables, service channels, liveliness tokens.

Entities mirror Zenoh's: each has ``undeclare()`` (safe twice) and is a context manager. Zenoh
errors are wrapped in :class:`~dyknow.errors.TransportError` with the Rust source location
trimmed off. The publishers and subscribers of dyknow messages are on the path of every message
between processes: they hand Zenoh the payload and the header (:mod:`dyknow.message`) as they are.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Final

import zenoh

from dyknow.errors import TransportError
from dyknow.message import ENCODINGS, HEADER_V1, Message, decode, decode_dyknow, encode
from dyknow.transport.key_exprs import is_wild
from dyknow.transport.runtime import error_text, inline_handler, keep_thread_state, pinned
from dyknow.transport.shared_memory import SHM_THRESHOLD, SharedMemory

__all__ = [
    "Index",
    "Entity",
    "HistorySubscriber",
    "LivelinessSubscriber",
    "LivelinessToken",
    "PlainPublisher",
    "PlainQuery",
    "PlainQueryable",
    "Publisher",
    "Queryable",
    "ServiceChannel",
    "ServiceRequest",
    "Subscriber",
]

log = logging.getLogger(__name__)

_ENCODINGS: Final = {text: zenoh.Encoding(text) for text in ENCODINGS.values()}
_HEADER_SIZE: Final = HEADER_V1.size  # the shortest dyknow header (version 1)


class Entity:
    """Something declared on a session: undeclare() is safe twice; a context manager."""

    def __init__(self, handle: Any) -> None:
        self._handle = handle

    def undeclare(self) -> None:
        handle, self._handle = self._handle, None
        if handle is not None:
            with contextlib.suppress(zenoh.ZError):  # the session is already closed: nothing left to undeclare
                handle.undeclare()

    def __enter__(self) -> Entity:
        return self

    def __exit__(self, *exc: object) -> None:
        self.undeclare()


class HistorySubscriber(Entity):
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


class Publisher(Entity):
    """Publishes dyknow messages on one concrete key, to other sessions only.

    ``matched`` tells whether any remote subscriber matches; callers skip encoding when not.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        on_matching: Callable[[bool], None] | None,
        shm: SharedMemory | None = None,
        reliable: bool = False,
    ) -> None:
        self._shm = shm
        # Streams drop rather than stall their producer when the network queue is full (Zenoh's
        # default); a reliable publisher (a replay, say) blocks instead so nothing is lost.
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        try:
            pub = session.declare_publisher(key, allowed_destination=zenoh.Locality.REMOTE, congestion_control=congestion)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a publisher on {key!r}: {error_text(exc)}") from exc
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
        self._listener: Any = pub.declare_matching_listener(inline_handler(matching))
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
            raise TransportError(f"cannot publish on {self.key!r}: {error_text(exc)}") from exc
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
            raise TransportError(f"cannot publish on {self.key!r}: {error_text(exc)}") from exc

    def undeclare(self) -> None:
        """Stop publishing; safe twice."""
        listener, self._listener = getattr(self, "_listener", None), None
        if listener is not None:
            with contextlib.suppress(zenoh.ZError):
                listener.undeclare()
        super().undeclare()


class Subscriber(Entity):
    """Receives dyknow messages (or plain Zenoh samples) published by other sessions.

    By default ``on_message`` runs on a Python thread Zenoh keeps for this subscriber (one per
    subscriber), so it may take its time. ``inline``: it runs on Zenoh's own receiving thread
    instead, which costs no thread at all but holds up every stream arriving over the same link
    while it runs: only for a quick hand-off (the units' input ports queue the message for their
    lane). Exceptions are passed to ``on_error`` instead of being swallowed by Zenoh.

    ``forward``: offered every dyknow message first, as ``forward(payload, header)`` (the
    transport's buffer and the header bytes) before anything is decoded; when it returns True it
    has passed the message on and ``on_message`` is not called (see
    :meth:`~dyknow.proxy.InputPort.forward_wire`).
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
            if inline and not getattr(pinned, "seen", False):
                keep_thread_state()
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
            raise TransportError(f"cannot declare a subscriber on {key!r}: {error_text(exc)}") from exc
        super().__init__(sub)


class PlainPublisher(Entity):
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
            raise TransportError(f"cannot declare a publisher on {key!r}: {error_text(exc)}") from exc
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
            raise TransportError(f"cannot publish on {self.key!r}: {error_text(exc)}") from exc


class PlainQuery:
    """One query of another protocol (ROS 2 over rmw_zenoh) a :class:`PlainQueryable` received:
    its key, payload and attachment. Answer it once with :meth:`reply`, or :meth:`drop` it
    unanswered (the caller waits until its own timeout); either may come from any thread."""

    __slots__ = ("_lock", "_query", "attachment", "key", "payload")

    def __init__(self, query: zenoh.Query, payload: bytes, attachment: bytes | None) -> None:
        self._query: zenoh.Query | None = query
        self._lock = threading.Lock()
        self.key = str(query.key_expr)
        self.payload = payload
        self.attachment = attachment

    def reply(self, data: bytes, attachment: bytes | None, *, encoding: str = "application/cdr") -> None:
        """Send ``data`` with ``attachment`` on the query's key, as the one answer; nothing once answered."""
        with self._lock:
            query, self._query = self._query, None
        if query is None:
            return
        try:
            query.reply(query.key_expr, data, encoding=zenoh.Encoding(encoding), attachment=attachment)
        except zenoh.ZError as exc:
            log.warning("cannot reply to %s: %s", self.key, error_text(exc))
        finally:
            query.drop()

    def drop(self) -> None:
        """End the query without an answer; safe twice."""
        with self._lock:
            query, self._query = self._query, None
        if query is not None:
            query.drop()


class PlainQueryable(Entity):
    """Receives queries of another protocol (ROS 2 services over rmw_zenoh) on a key expression:
    ``on_query(PlainQuery)`` on Zenoh's thread (it must return at once: queue the query). A
    query whose payload is over ``max_bytes`` is dropped unanswered before it is copied:
    ``on_refused(key, why)``. Declared complete, as rmw_zenoh declares a service's queryable."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        on_query: Callable[[PlainQuery], None],
        *,
        max_bytes: int,
        on_refused: Callable[[str, str], None] | None = None,
    ) -> None:
        def arrived(query: zenoh.Query) -> None:
            try:
                size = len(query.payload) if query.payload is not None else 0
                if size > max_bytes:
                    if on_refused is not None:
                        on_refused(str(query.key_expr), f"a request of {size} bytes, over the limit of {max_bytes}")
                    query.drop()
                    return
                payload = query.payload.to_bytes() if query.payload is not None else b""
                attachment = query.attachment.to_bytes() if query.attachment is not None else None
                on_query(PlainQuery(query, payload, attachment))
            except Exception:
                log.exception("a query on %s failed", key)
                query.drop()

        try:
            queryable = session.declare_queryable(key, inline_handler(arrived), complete=True)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a queryable on {key!r}: {error_text(exc)}") from exc
        super().__init__(queryable)
        self.key = key


class Queryable(Entity):
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
            queryable = session.declare_queryable(key, inline_handler(answer) if inline else answer)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a service on {key!r}: {error_text(exc)}") from exc
        super().__init__(queryable)
        self.key = key


class Index(Entity):
    """Answers a query on a key expression with the concrete keys ``held()`` lists that the query's
    key expression covers, one empty reply each (none when it covers none), on Zenoh's thread.

    What a liveliness token says, anyone may declare; an index answers only from a session that
    holds one: a query finds who answers, where a liveliness query finds every token, answered or
    not (issue 51: 2,000 offer tokens of names that ran no manager hid the one real provider).
    """

    def __init__(self, session: zenoh.Session, key: str, held: Callable[[], list[str]]) -> None:
        def answer(query: zenoh.Query) -> None:
            try:
                asked = query.key_expr
                for concrete in held():
                    if asked.intersects(zenoh.KeyExpr(concrete)):
                        query.reply(concrete, b"")
            except (zenoh.ZError, ValueError) as exc:
                log.warning("cannot answer %s on %s: %s", query.key_expr, key, exc)
            finally:
                query.drop()

        try:
            queryable = session.declare_queryable(key, inline_handler(answer))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare an index on {key!r}: {error_text(exc)}") from exc
        super().__init__(queryable)
        self.key = key


def _reply(query: zenoh.Query, ok: bool, reply: bytes) -> None:
    try:
        if ok:
            query.reply(query.key_expr, reply)
        else:
            query.reply_err(reply)
    except zenoh.ZError as exc:
        log.warning("cannot reply to %s: %s", query.key_expr, error_text(exc))
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


class ServiceChannel(Entity):
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
            queryable = session.declare_queryable(key, inline_handler(arrived))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare a service on {key!r}: {error_text(exc)}") from exc
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


class LivelinessToken(Entity):
    """Announces that something is alive on a key until undeclared (or the process dies)."""


class LivelinessSubscriber(Entity):
    """Calls ``on_change(key, alive)`` when liveliness tokens matching a key appear or vanish."""
