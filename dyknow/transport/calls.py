"""A session's service calls: the queriers it keeps, and why a call that got no answer ended.

A call waits for the service to be reachable, asks, and when the request ends without a reply
tells, as far as it can be told, why: the link closed, the service's owner went, or the request
was dropped on its way (an access control).
"""

from __future__ import annotations

import collections
import contextlib
import json
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from dyknow.errors import ServiceError, TransportError
from dyknow.transport.links import Links
from dyknow.transport.runtime import error_text, inline_handler

__all__ = ["MAX_QUERIERS", "ServiceCalls"]

#: Service queriers a session keeps for its next calls (the least recently used go first).
MAX_QUERIERS = 64
# How long a call that ended early with no reply looks for what explains it, asking again
# meanwhile, first after this long (see ServiceCalls._call).
_CUT_GRACE_S = 0.5
_RETRY_FIRST_S = 0.01


def _said(data: bytes, limit: int = 1000) -> str:
    """An error reply that is not a JSON object, as its message: its text, at most ``limit`` characters."""
    text = data[: 4 * limit].decode(errors="replace")
    return text if len(text) <= limit and len(data) <= 4 * limit else f"{text[:limit]}... ({len(data):,} bytes)"


class ServiceCalls:
    """The service calls of one session (:meth:`Session.call <dyknow.transport.Session.call>`): the
    queriers it keeps for them, at most :data:`MAX_QUERIERS` idle ones, the least recently used
    undeclared first."""

    def __init__(self, session: Callable[[], zenoh.Session], links: Links) -> None:
        self._session = session  # the open Zenoh session (ClosedError once it is closed)
        self._links = links
        self._lock = threading.Lock()
        # service key -> [querier, reachable, calls using it now]; the most recently used last
        self._queriers: collections.OrderedDict[str, list[Any]] = collections.OrderedDict()

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
        """Send a request to the service on ``key`` and return its reply (see :meth:`Session.call
        <dyknow.transport.Session.call>`)."""
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
                except (ValueError, RecursionError):  # (not JSON, or nested past the parser's stack: said as it came)
                    err = None
                if not isinstance(err, dict):
                    raise ServiceError(_said(data))
                # (the fields are the service's word: a message or class that is not text is not taken)
                message, kind = err.get("message"), err.get("error")
                raise ServiceError(message if isinstance(message, str) else _said(data), kind=kind if isinstance(kind, str) else None, details=err)
        except zenoh.ZError as exc:
            raise ServiceError(f"request to {what} failed: {error_text(exc)}") from exc
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
                querier = self._session().declare_querier(key, timeout=timeout_s)
                querier.declare_matching_listener(inline_handler(matching))
            except zenoh.ZError as exc:
                raise TransportError(f"cannot declare a querier on {key!r}: {error_text(exc)}") from exc
            if querier.matching_status.matching:  # type: ignore[attr-defined]  # see entities.Publisher
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

    def close(self) -> None:
        """Undeclare every querier (the session closes)."""
        for querier, _, _ in self._queriers.values():
            with contextlib.suppress(zenoh.ZError):
                querier.undeclare()
        self._queriers.clear()
