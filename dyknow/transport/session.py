"""The Zenoh session: opened on a configuration, the entry point to declare entities and call services.

A session bounds how long its dead links hold it up (:mod:`~dyknow.transport.links`: the kernel
drops a link whose data goes unacknowledged for a lease), dials a lost link again within a
second, ends a dial under way when it closes, and is closed before the interpreter's threads end
at exit. A call that ends without an answer says why (:mod:`~dyknow.transport.calls`).
"""

from __future__ import annotations

import atexit
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Final

import zenoh

from dyknow.errors import ClosedError, TransportError
from dyknow.message import Message
from dyknow.transport.calls import ServiceCalls
from dyknow.transport.config import lease_and_dials, make_config
from dyknow.transport.entities import (
    Entity,
    HistorySubscriber,
    Index,
    LivelinessSubscriber,
    LivelinessToken,
    PlainPublisher,
    PlainQuery,
    PlainQueryable,
    Publisher,
    Queryable,
    ServiceChannel,
    Subscriber,
)
from dyknow.transport.links import Links, RouterLink, RouterLinks, abort_dials
from dyknow.transport.runtime import error_text, inline_handler, inline_handler_with_end, lay_out_runtimes, panic_error, wait_for_handlers
from dyknow.transport.shared_memory import SharedMemory

__all__ = ["MAX_ALIVE_KEYS", "Session", "open_session"]

log = logging.getLogger(__name__)

#: At most this many liveliness tokens are read in one :meth:`Session.alive` answer (a flood of
#: tokens is hostile input).
MAX_ALIVE_KEYS: Final = 100_000


# Every session still open when the interpreter exits is closed first, newest first. Left to the
# garbage collector at exit, Zenoh closed one from a finalizer once and panicked ("close operation
# timed out", issue 43). It runs before Python waits for its threads (as concurrent.futures does),
# so the threads of Zenoh's callbacks end and a script that forgot to close a session exits.
# (Held strongly: the class is compiled, and mypyc's classes take no weak references. A session
# is taken out as it closes; one never closed stays open until exit, as a Zenoh session would.)
_open_sessions: Final[dict[int, Session]] = {}
_HANDLERS_AT_EXIT_S: Final = 2.0  # how long the exit waits for Zenoh to let go of handlers


def _close_open_sessions() -> None:
    for session in sorted(list(_open_sessions.values()), key=lambda s: s.opened_ns, reverse=True):
        try:
            session.close()
        except Exception:  # at exit: the others are closed whatever this one does
            log.debug("closing a session at exit failed", exc_info=True)
    # and the handlers Zenoh lets go of on its own threads a moment after their sessions closed:
    # let go now, while Python runs, not during its teardown, which a call from Zenoh aborts
    if not wait_for_handlers(_HANDLERS_AT_EXIT_S):
        log.debug("at exit: Zenoh still holds handlers after %g s", _HANDLERS_AT_EXIT_S)


_before_threads_end: Callable[[Callable[[], None]], object] | None = getattr(threading, "_register_atexit", None)
if _before_threads_end is not None:
    _before_threads_end(_close_open_sessions)
else:  # (an interpreter without it: at exit, then)
    atexit.register(_close_open_sessions)


def best_alive_answer(answers: list[tuple[list[str], bool]]) -> list[str]:
    """Of the answers to who is alive, in the order they came, each with whether it was
    complete (Zenoh did not end it at its timeout): the latest complete one, else the fullest."""
    complete = [found for found, whole in answers if whole]
    if complete:
        return complete[-1]
    return max((found for found, _ in answers), key=len, default=[])


class Session:
    """A Zenoh session: the entry point to declare publishers, subscribers and services.

    A context manager; ``close()`` is safe twice and undeclares everything declared on it.
    """

    def __init__(self, config: zenoh.Config | None = None) -> None:
        if config is None:
            config = make_config()
        lease_ms, dials = lease_and_dials(config)
        lay_out_runtimes()
        try:
            self._session: zenoh.Session | None = zenoh.open(config)
        except zenoh.ZError as exc:
            text = error_text(exc)
            expected = None
            if "Address already in use" in text:
                text += "; another process listens there (a manager already running?)"
                expected = "another port (--listen)"
            raise TransportError(f"cannot open a Zenoh session: {text}", expected=expected) from exc
        except BaseException as exc:  # a Zenoh panic is no Exception
            error = panic_error(exc)
            if error is None:
                raise
            raise error from exc
        self._shm = SharedMemory()
        self._links = Links(self._session, lease_ms)
        self._calls = ServiceCalls(self._z, self._links)
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
            self._calls.close()
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
                log.debug("flush: %s did not answer: %s", zid, error_text(exc))
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

    def watch_routers(self, on_change: Callable[[RouterLink], None]) -> RouterLinks:
        """Follow the session's links to other Zenoh routers: ``on_change(link)`` as each comes up
        (those up already too) and goes down, on Zenoh's thread (see :class:`RouterLinks`)."""
        return RouterLinks(self._z(), on_change)

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
    ) -> Entity:
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
                return HistorySubscriber(self._z(), key, callback)
            else:
                sub = self._z().declare_subscriber(key, callback)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {key!r}: {error_text(exc)}") from exc
        return Entity(sub)

    def declare_plain_queryable(
        self,
        key: str,
        on_query: Callable[[PlainQuery], None],
        *,
        max_bytes: int = 64 * 1024 * 1024,
        on_refused: Callable[[str, str], None] | None = None,
    ) -> PlainQueryable:
        """Receive another protocol's queries on ``key`` (see :class:`PlainQueryable`)."""
        return PlainQueryable(self._z(), key, on_query, max_bytes=max_bytes, on_refused=on_refused)

    def query_plain(
        self,
        key: str,
        payload: bytes,
        attachment: bytes | None,
        *,
        timeout_s: float,
        on_reply: Callable[[str, bytes, bytes | None], None],
        on_error: Callable[[str], None],
        done: Callable[[], None],
        max_bytes: int = 64 * 1024 * 1024,
        encoding: str = "application/cdr",
        wanted: Callable[[bytes | None], bool] | None = None,
    ) -> None:
        """Send one query of another protocol (a ROS 2 service request over rmw_zenoh) to the
        complete queryables on ``key`` and return at once. Each reply is given to
        ``on_reply(key, payload, attachment)`` and each error reply to ``on_error(text)``, on a
        Zenoh thread; a reply over ``max_bytes`` is an error, found before it is copied.
        ``done()`` is called once when the query ends (every queryable answered, or
        ``timeout_s`` passed). ``wanted(attachment)``: a reply it says no to is dropped before
        its payload is copied (another caller's, in a flood of replies)."""

        def reply(answer: zenoh.Reply) -> None:
            try:
                ok = answer.ok
                if ok is None:
                    err = answer.err
                    text = err.payload.to_bytes()[:1000].decode("utf-8", "replace") if err is not None else "an empty reply"
                    on_error(text)
                    return
                size = len(ok.payload)
                if size > max_bytes:
                    on_error(f"a reply of {size} bytes, over the limit of {max_bytes}")
                    return
                att = ok.attachment
                attachment = att.to_bytes()[:1024] if att is not None else None
                if wanted is not None and not wanted(attachment):
                    return
                on_reply(str(ok.key_expr), ok.payload.to_bytes(), attachment)
            except Exception:
                log.exception("a reply on %s failed", key)

        def ended() -> None:  # Zenoh drops the handler when the query ends
            try:
                done()
            except Exception:
                log.exception("the end of a query on %s failed", key)

        try:
            self._z().get(
                key,
                inline_handler_with_end(reply, ended),
                payload=payload,
                attachment=attachment,
                encoding=zenoh.Encoding(encoding),
                timeout=timeout_s,
                target=zenoh.QueryTarget.ALL_COMPLETE,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot query {key!r}: {error_text(exc)}") from exc

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
                inline_handler_with_end(on_reply, ended),
                payload=payload,
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.DROP,
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot query {key!r}: {error_text(exc)}") from exc
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
            raise TransportError(f"cannot declare a liveliness token on {key!r}: {error_text(exc)}") from exc

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
            handler = inline_handler(callback) if inline else callback
            sub = self._z().liveliness().declare_subscriber(key, handler, history=True)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot watch liveliness on {key!r}: {error_text(exc)}") from exc
        return LivelinessSubscriber(sub)

    def alive(self, key: str, *, timeout_s: float = 1.0) -> list[str]:
        """The keys of the liveliness tokens matching ``key`` that are up now, sorted.

        A session just opened learns of the others' tokens over a few milliseconds: it asks
        until two answers agree (and are not empty), or ``timeout_s`` passes. Then the latest
        complete answer is given (or, when none was complete, the fullest one): an answer cut
        short by the deadline is never preferred to a complete one before it. (The last answer
        was given: on a loaded machine a complete answer of 1,502 tokens took most of the 2 s,
        the next ask had 0.1 s left, nothing came back in it, and ``dyknow managers`` said "no
        manager reachable".) The first answer is waited for past ``timeout_s`` when Zenoh's thread
        has not handed it over yet (at most ``max(5, 2 * timeout_s)`` s more).
        """
        deadline = time.monotonic() + timeout_s
        last: list[str] | None = None
        asked: list[tuple[list[str], bool]] = []  # (each answer, and whether it was complete)
        while True:
            # (answers come to a callback: a channel of Zenoh's (256 by default) filled up inside
            # get() itself when this session already knew the tokens, and get() never returned:
            # a client that watches the managers' tokens, asking which of 500 managers are up)
            answers: list[list[str]] = []
            cut: list[bool] = []
            answered = threading.Event()

            def done(keys: list[str], count: int, answers: list[list[str]] = answers, answered: threading.Event = answered) -> None:
                answers.append(keys)
                answered.set()

            def cut_short(cut: list[bool] = cut) -> None:
                cut.append(True)

            started = time.monotonic()
            left = max(0.05, deadline - started)
            self.ask_alive(key, timeout_s=left, limit=MAX_ALIVE_KEYS, done=done, timed_out=cut_short)
            if not answered.wait(left + 1.0) and not asked:
                # (no answer yet to the first question: Zenoh ends every question, at its timeout at
                # the latest, but its thread was starved beside CPU hogs while it handed over 1,502
                # tokens; waiting for that answer beats saying that nobody is alive)
                answered.wait(max(5.0, 2 * timeout_s))
            found = sorted(set(answers[0])) if answers else []
            asked.append((found, bool(answers) and not cut))
            now = time.monotonic()
            if found and found == last:
                return found
            # (no time left for another ask as long as this one took: the best answer so far)
            if now >= deadline or (asked[-1][1] and deadline - now < now - started):
                return best_alive_answer(asked)
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
            self._z().liveliness().get(key, inline_handler_with_end(on_reply, ended), timeout=timeout_s)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot ask who is alive on {key!r}: {error_text(exc)}") from exc

    def declare_index(self, key: str, held: Callable[[], list[str]]) -> Index:
        """Answer queries on ``key`` with the concrete keys ``held()`` lists that they cover (see
        :class:`~dyknow.transport.entities.Index`); :meth:`ask_index` asks."""
        return Index(self._z(), key, held)

    def ask_index(self, key: str, *, timeout_s: float, limit: int, done: Callable[[list[str], int], None]) -> None:
        """Ask once which sessions' indexes hold keys on ``key``, and return at once: ``done(keys,
        count)`` is called once, on a Zenoh thread, when every index answered (or ``timeout_s``
        passed): the first ``limit`` distinct keys in the order they came, and how many came."""
        lock = threading.Lock()
        found: dict[str, None] = {}
        count = [0]

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            with lock:
                count[0] += 1
                if len(found) < limit:
                    found[str(reply.ok.key_expr)] = None

        def ended() -> None:  # Zenoh drops the handler when the request ends
            with lock:
                keys, total = list(found), count[0]
            try:
                done(keys, total)
            except Exception:
                log.exception("the answer of the indexes on %s failed", key)

        try:
            self._z().get(
                key,
                inline_handler_with_end(on_reply, ended),
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.DROP,
            )
        except zenoh.ZError as exc:
            raise TransportError(f"cannot ask the indexes on {key!r}: {error_text(exc)}") from exc

    def put(self, key: str, data: bytes | str, *, encoding: str = "application/json") -> None:
        """Publish one plain sample (for events and measurements)."""
        try:
            self._z().put(key, data, encoding=zenoh.Encoding(encoding))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {key!r}: {error_text(exc)}") from exc

    def declare_raw_subscriber(self, key: str, on_sample: Callable[[str, bytes], None], *, inline: bool = False) -> Entity:
        """Receive plain samples from any session, this one included (for events and measurements).
        ``inline``: on Zenoh's thread (no thread of its own; ``on_sample`` must return at once)."""

        def callback(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                try:
                    on_sample(str(sample.key_expr), sample.payload.to_bytes())
                except Exception:
                    log.exception("callback for %s failed", key)

        try:
            return Entity(self._z().declare_subscriber(key, inline_handler(callback) if inline else callback))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {key!r}: {error_text(exc)}") from exc

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
        return self._calls.call(
            key, payload, timeout_s=timeout_s, what=what, sign=sign, gone=gone, reachable_within_s=reachable_within_s, absent=absent
        )

    def queriers(self) -> int:
        """How many service queriers the session keeps (at most :data:`~dyknow.transport.MAX_QUERIERS` idle ones)."""
        return self._calls.queriers()


def open_session(
    *,
    listen: Sequence[str] | None = None,
    connect: Iterable[str] = (),
    config_file: str | os.PathLike[str] | None = None,
) -> Session:
    """Open a session with :func:`make_config`'s defaults."""
    return Session(make_config(listen=listen, connect=list(connect), config_file=config_file))
