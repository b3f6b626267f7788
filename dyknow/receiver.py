"""The receiver: the Zenoh subscribers of one manager, shared by its units' input ports.

Units do not declare Zenoh subscribers of their own. Every input port is attached here, and
the receiver keeps as few subscribers as the ports' keys allow:

- one subscriber on the manager's own namespace, ``dyknow/<manager>/**``, serves every input
  bound to a concrete key there (the default keys of this manager's units: a chain of local
  units); an arriving message is routed by its key through a dictionary;
- one subscriber per other key expression, shared by all the inputs bound to it.

Why: Zenoh's cost of declaring grows with what the session has declared already (about 13 s
to declare the entities of 10,000 relays one by one on this machine), and a subscriber with a
plain Python callback costs a thread. Here the subscribers call back on Zenoh's own receiving
thread, which hands the message to each reader's port (:meth:`InputPort.deliver_remote
<dyknow.proxy.InputPort.deliver_remote>`): a unit proven quick and free runs right there, any
other gets it queued for its lane (see :mod:`dyknow.executor`). A key read by one port of a
unit that only forwards (``Unit.forward_to``) is passed on before it is even decoded.
Every subscriber only receives from other sessions: local producers reach their readers
through the :class:`~dyknow.bus.LocalBus`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

from dyknow import keys
from dyknow.transport import is_wild

if TYPE_CHECKING:
    from dyknow.message import Message
    from dyknow.transport import Session, Subscriber

__all__ = ["Receiver", "Reader"]

log = logging.getLogger(__name__)


class Reader(Protocol):
    """An input port as the receiver sees it."""

    key: str

    def deliver_remote(self, msg: Message) -> None:
        """Hand ``msg`` to the port's unit (run now if quick and free, else queued); quick."""
        ...

    def forward_wire(self, data: Any, header: bytes) -> bool:
        """Pass a message on as it came, before it is decoded, when the port's unit only forwards
        (True); False leaves it to :meth:`deliver_remote`."""
        ...


class _Shared:
    """One Zenoh subscriber and the readers it feeds (a tuple, swapped whole)."""

    __slots__ = ("readers", "subscriber")

    def __init__(self) -> None:
        self.subscriber: Subscriber | None = None
        self.readers: tuple[Reader, ...] = ()

    def deliver(self, msg: Message) -> None:
        for reader in self.readers:
            reader.deliver_remote(msg)

    def forward(self, data: Any, header: bytes) -> bool:
        """A sole reader that only forwards passes the message on undecoded (see Reader)."""
        readers = self.readers
        return len(readers) == 1 and readers[0].forward_wire(data, header)


class Receiver:
    """The Zenoh subscribers of one manager (see the module doc). Thread-safe."""

    def __init__(self, session: Session, manager: str) -> None:
        self._session = session
        self._prefix = keys.default_key(manager, "", "")[:-1]  # "dyknow/<manager>/"
        self._pattern = self._prefix + "**"
        self._lock = threading.Lock()
        self._routes: dict[str, tuple[Reader, ...]] = {}  # concrete key in the namespace -> readers
        self._namespace: Subscriber | None = None
        self._shared: dict[str, _Shared] = {}  # any other key expression -> its subscriber

    def _local(self, key: str) -> bool:
        return key.startswith(self._prefix) and not is_wild(key)

    # ------------------------------------------------------------------ attaching

    def attach(self, readers: Sequence[Reader]) -> None:
        """Receive for ``readers`` on their keys. All or nothing: a subscriber that cannot be
        declared raises :class:`~dyknow.errors.TransportError` and nothing changes."""
        with self._lock:
            self._declare({r.key for r in readers})
            for reader in readers:
                self._add(reader, reader.key)

    def detach(self, readers: Sequence[Reader]) -> None:
        """Stop receiving for ``readers``; subscribers nobody reads any more are undeclared."""
        with self._lock:
            for reader in readers:
                self._remove(reader, reader.key)
            self._collect()

    def rebind(self, moves: Sequence[tuple[Reader, str]]) -> None:
        """Receive for each reader on its new key instead of its current one (the caller then
        sets ``reader.key``). All or nothing, like :meth:`attach`."""
        with self._lock:
            self._declare({key for _, key in moves})
            for reader, key in moves:
                self._remove(reader, reader.key)
                self._add(reader, key)
            self._collect()

    def close(self) -> None:
        """Undeclare every subscriber; safe twice."""
        with self._lock:
            subscribers = [s.subscriber for s in self._shared.values()] + [self._namespace]
            self._shared.clear()
            self._routes.clear()
            self._namespace = None
        for subscriber in subscribers:
            if subscriber is not None:
                subscriber.undeclare()

    def __len__(self) -> int:
        """How many Zenoh subscribers the receiver holds."""
        return len(self._shared) + (self._namespace is not None)

    def routes(self) -> int:
        """How many keys of the namespace have local readers."""
        return len(self._routes)

    # ------------------------------------------------------------------ under the lock

    def _declare(self, wanted: set[str]) -> None:
        """Declare the subscribers ``wanted`` keys need and lack, all or none."""
        new: list[tuple[str, Subscriber]] = []
        try:
            if self._namespace is None and any(self._local(k) for k in wanted):
                self._namespace = self._session.declare_subscriber(
                    self._pattern, self._route, self._on_error, inline=True, wanted=self._routes.get
                )
            for key in wanted:
                if not self._local(key) and key not in self._shared:
                    shared = _Shared()
                    subscriber = self._session.declare_subscriber(key, shared.deliver, self._on_error, inline=True, forward=shared.forward)
                    shared.subscriber = subscriber
                    self._shared[key] = shared
                    new.append((key, subscriber))
        except Exception:
            for key, subscriber in new:
                del self._shared[key]
                subscriber.undeclare()
            raise

    def _add(self, reader: Reader, key: str) -> None:
        if self._local(key):
            self._routes[key] = (*self._routes.get(key, ()), reader)
        else:
            shared = self._shared[key]
            shared.readers = (*shared.readers, reader)

    def _remove(self, reader: Reader, key: str) -> None:
        if self._local(key):
            left = tuple(r for r in self._routes.get(key, ()) if r is not reader)
            if left:
                self._routes[key] = left
            else:
                self._routes.pop(key, None)
        else:
            shared = self._shared.get(key)
            if shared is not None:
                shared.readers = tuple(r for r in shared.readers if r is not reader)

    def _collect(self) -> None:
        """Undeclare the per-key subscribers nobody reads (the namespace one stays: it is one)."""
        for key in [k for k, s in self._shared.items() if not s.readers]:
            subscriber = self._shared.pop(key).subscriber
            if subscriber is not None:
                subscriber.undeclare()

    # ------------------------------------------------------------------ on Zenoh's thread

    def _route(self, msg: Message) -> None:
        for reader in self._routes.get(msg.key, ()):
            reader.deliver_remote(msg)

    def _on_error(self, exc: BaseException) -> None:
        log.warning("a message from another process could not be decoded: %s", exc)
