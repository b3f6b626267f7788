"""Who holds each request and monitor: a client's end with the client, a grace period after it is gone.

A request counts its references (:meth:`dyknow.manager.Manager.request` twice, two references),
each with its :class:`~dyknow.model.Owner`. A reference a client takes through the ``request``
service names the client (``holder``: a random id per :class:`~dyknow.client.Client`), and the
client declares a liveliness token on ``<request key>/holders/<holder>`` while it holds it; a
monitor it asks for, likewise on ``<monitor key>/holders/<holder>`` (a quantified monitor's key
without its ``/*``). When that token goes (the client closed, crashed, or its host was cut off
past its lease), the manager waits ``grace_s`` and, unless the token came back, releases every
reference the client held there (and its monitor). A reference taken with ``keep`` (``dyknow
request`` does: it exits at once) or through the Python API names no holder and lasts until
released. A holder that never declares its token is released ``max(grace_s, TOKEN_WAIT_S)``
after its request, as one that went (the client declares it once the reply with the key is
back: a grace of 0 must not release it before).

The holder id comes from the network: the service checks it (:data:`HOLDER`: hexadecimal,
bounded), each request keeps the holders of at most :data:`MAX_HOLDERS` callers (a caller: a
certificate's common name on a manager with roles, however many clients it runs; a client id
without), and only the tokens of holders the manager knows are tracked (anyone may declare
tokens; they cost nothing unless they are of a holder that asked for something here). How many
references one caller may take on one request is the manager's
:attr:`~dyknow.security.Limits.max_references_per_caller`, so no caller fills a shared request for
the others. A token keeps a reference alive; it never releases one, and no client can give back
another's reference (:meth:`dyknow.model.Owner.holds`).

**A holder token is its caller's.** On a manager with roles a signed caller's holder ids start
with its *scope*, :func:`~dyknow.keys.holder_scope` of its certificate's common name (16
hexadecimal digits: the first 8 bytes of its SHA-256), and the service refuses any other
(:func:`check_holder`). The session's access control (:meth:`dyknow.access.AccessControl.zenoh`, the same file on every
manager and router) lets each certificate declare holder tokens of its own scope only, at the
first link the token crosses. So a client cannot keep another client's request alive by
declaring its token once that client is gone. Without roles a token proves nothing: anyone who
reaches the manager may declare any client's token (and force any release).
"""

from __future__ import annotations

import heapq
import logging
import re
import threading
import time
from collections.abc import Callable

from dyknow.errors import AccessError, ServiceError
from dyknow.keys import holder_scope, holder_token, holders_pattern
from dyknow.transport import LivelinessSubscriber, Session

__all__ = [
    "DEFAULT_GRACE_S",
    "HOLDER",
    "MAX_HOLDERS",
    "TOKEN_WAIT_S",
    "Holders",
    "check_holder",
    "holder_scope",
    "holder_token",
    "holders_pattern",
]

log = logging.getLogger(__name__)

#: How long a manager keeps the requests of a client that is gone (s): longer than a lease, so a
#: client whose link flapped keeps what it asked for.
DEFAULT_GRACE_S = 10.0
#: How long a holder has to declare its token after its request (s): the reply's way back and the
#: token's way in, on a slow link.
TOKEN_WAIT_S = 5.0
#: The callers whose holders one request keeps track of (each caller a certificate's common name
#: on a manager with roles, a client id without), each with at most
#: :attr:`~dyknow.security.Limits.max_references_per_caller` references.
MAX_HOLDERS = 1000
#: What a holder id looks like: the hexadecimal id a Client makes for itself (16 random digits,
#: after its certificate's 16-digit scope when it has one).
HOLDER = re.compile(r"[0-9a-f]{8,32}")


def check_holder(holder: str, common_name: str, where: str) -> None:
    """Refuse (:class:`AccessError`) a holder id that is not of the scope of ``common_name``: a
    signed caller holds only through client ids of its own (see the module documentation)."""
    scope = holder_scope(common_name)
    if not holder.startswith(scope):
        raise AccessError(
            f"{common_name!r} may not hold through the client id {holder!r}: on a manager with roles a certificate's "
            f"client ids start with its scope, {scope} for {common_name!r}",
            where=where,
            expected="a dyknow client that makes its id from its certificate (this version's Client does), or the request kept (keep=True)",
        )


class Holders:
    """The holders of a manager's requests and monitors, and the releases of those that are gone.

    ``release(key, holder)`` gives back every reference ``holder`` holds on ``key`` (the manager's
    own release); it runs on this object's thread, once per holder gone. A context manager;
    :meth:`close` stops the watch and the thread.
    """

    def __init__(self, session: Session, manager: str, release: Callable[[str, str], object], grace_s: float = DEFAULT_GRACE_S) -> None:
        self.grace_s = grace_s
        self._release = release
        self._lock = threading.Condition()
        self._held: dict[str, dict[str, int]] = {}  # key -> holder -> references
        self._caller_of: dict[str, dict[str, str]] = {}  # key -> holder -> its caller (a common name, or the holder itself)
        self._callers: dict[str, dict[str, int]] = {}  # key -> caller -> its holders there
        self._tokens: dict[str, tuple[str, str]] = {}  # token -> (key, holder), of the holders known
        self._alive: set[tuple[str, str]] = set()  # (key, holder) whose token is up
        self._due: list[tuple[float, str, str]] = []  # (monotonic time, key, holder): look again then
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"dyknow-{manager}-holders", daemon=True)
        self._thread.start()
        self._watch: LivelinessSubscriber | None = session.declare_liveliness_subscriber(holders_pattern(manager), self._changed)

    def __enter__(self) -> Holders:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop watching and releasing; safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._lock.notify_all()
        if self._watch is not None:
            self._watch.undeclare()
            self._watch = None
        self._thread.join(timeout=2.0)

    def took(self, key: str, holder: str, caller: str | None = None) -> None:
        """``holder`` took a reference to the request (or asked for the monitor) on ``key``, for
        ``caller`` (its certificate's common name on a manager with roles; None without, where
        each client counts as a caller of its own). :class:`ServiceError` when ``key`` has the
        holders of :data:`MAX_HOLDERS` other callers already."""
        who = caller if caller is not None else holder
        with self._lock:
            held = self._held.get(key, {})
            callers = self._callers.get(key, {})
            if holder not in held and who not in callers and len(callers) >= MAX_HOLDERS:
                raise ServiceError(
                    f"request {key!r} has the clients of {MAX_HOLDERS} callers already",
                    where="field 'holder'",
                    expected="a request once one of them is released, or the request kept (keep=True)",
                )
            held = self._held.setdefault(key, held)
            if holder not in held:
                self._caller_of.setdefault(key, {})[holder] = who
                callers = self._callers.setdefault(key, callers)
                callers[who] = callers.get(who, 0) + 1
            held[holder] = held.get(holder, 0) + 1
            self._tokens[holder_token(key, holder)] = (key, holder)
            if (key, holder) not in self._alive:  # its token may be on its way: look again once it had time to come
                self._look_later(key, holder, max(self.grace_s, TOKEN_WAIT_S))

    def gave_back(self, key: str, holder: str) -> None:
        """``holder`` released one reference it held (the manager released it)."""
        with self._lock:
            held = self._held.get(key, {})
            if held.get(holder, 0) > 1:
                held[holder] -= 1
            else:
                self._drop(key, holder)

    def holders(self, key: str) -> dict[str, int]:
        """The clients holding the request on ``key``: holder -> references."""
        with self._lock:
            return dict(self._held.get(key, {}))

    def alive(self, key: str, holder: str) -> bool:
        """Whether the manager sees ``holder``'s token for ``key`` (it holds it, and is there)."""
        with self._lock:
            return (key, holder) in self._alive

    def forget(self, key: str) -> None:
        """The request or monitor on ``key`` is gone."""
        with self._lock:
            for holder in list(self._held.get(key, {})):
                self._drop(key, holder)

    def _drop(self, key: str, holder: str) -> None:
        held = self._held.get(key, {})
        if held.pop(holder, None) is not None:
            who = self._caller_of[key].pop(holder)
            callers = self._callers[key]
            if callers[who] > 1:
                callers[who] -= 1
            else:
                del callers[who]
        if not held:
            self._held.pop(key, None)
            self._caller_of.pop(key, None)
            self._callers.pop(key, None)
        self._tokens.pop(holder_token(key, holder), None)
        self._alive.discard((key, holder))

    # -- liveliness (Zenoh's thread) and the releases (this object's thread)

    def _changed(self, token: str, alive: bool) -> None:
        with self._lock:
            known = self._tokens.get(token)
            if known is None:
                return  # a holder of nothing here (anyone may declare tokens)
            if alive:
                self._alive.add(known)
            else:
                self._alive.discard(known)
                self._look_later(*known)

    def _look_later(self, key: str, holder: str, after_s: float | None = None) -> None:
        heapq.heappush(self._due, (time.monotonic() + (self.grace_s if after_s is None else after_s), key, holder))
        self._lock.notify_all()

    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._closed and (not self._due or self._due[0][0] > time.monotonic()):
                    self._lock.wait(None if not self._due else max(0.0, self._due[0][0] - time.monotonic()))
                if self._closed:
                    return
                _, key, holder = heapq.heappop(self._due)
                if (key, holder) in self._alive or holder not in self._held.get(key, {}):
                    continue
                references = self._held[key][holder]
                self._drop(key, holder)
            log.info("client %s holding %s is gone: %d reference(s) released after %.1f s", holder, key, references, self.grace_s)
            try:
                self._release(key, holder)
            except Exception as exc:  # (released meanwhile by someone else: nothing left to give back)
                log.debug("releasing %s for the gone client %s: %s", key, holder, exc)
