"""ROS 2 services on rmw_zenoh: a client that calls one and a server that answers, on a dyknow session.

As rmw_zenoh's ``docs/design.md`` states it (and ``rmw_zenoh_cpp`` does): a service server is a
Zenoh queryable, declared complete, on the service's key
``<domain>/<service name>/<pkg>::srv::dds_::<Name>_/<RIHS01 hash>``
(:func:`~dyknow.ros2.names.data_key`), announced by an ``SS`` liveliness token; a client is
announced by an ``SC`` token and sends each request as a query on that key (to the complete
queryables, replies not consolidated) whose payload is the request's CDR and whose attachment is
rmw_zenoh's (:mod:`~dyknow.ros2.attachment`): the request's sequence number, its source
timestamp and the client's GID. The server replies on the service's key with the response's CDR
and an attachment holding the request's sequence number and the client's GID, with the time of
the reply. A client takes the first reply whose attachment names its own GID and sequence number.

What arrives is bounded before it costs anything: a server drops unanswered a request over its
``max_bytes`` (before copying it), one whose attachment is malformed, and one that finds
``max_pending`` requests already waiting for the handler (counted in ``refused``, with
``last_refusal``); a client treats a reply over its ``max_bytes`` as an error reply, and drops
a reply whose attachment is not its call's before copying its payload. A server's
handler runs off Zenoh's thread, where ``call_soon`` runs what it is given (a unit's lane; by
default, :meth:`~dyknow.ros2.node.Ros2Node.create_service` gives each service a thread of its
own, one request at a time); an exception it raises answers nothing (the client
waits until its timeout, as an rmw_zenoh client of a server whose callback failed) and is logged
and counted in ``failed``, never raised into Zenoh's thread.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

from dyknow.errors import BindingError, ClosedError, DyKnowError, ServiceError
from dyknow.ros2 import names
from dyknow.ros2.attachment import Attachment
from dyknow.ros2.names import DEFAULT_QOS, QoS
from dyknow.ros2.types import MAX_CDR_BYTES, TypeSupport

if TYPE_CHECKING:
    from dyknow.transport import Session

__all__ = ["DEFAULT_MAX_PENDING", "DEFAULT_MAX_REQUEST_BYTES", "READ_ONLY_SERVICES", "RESEND_S", "Ros2Client", "Ros2Service", "ServiceNode", "as_message"]

log = logging.getLogger(__name__)

#: The largest request a server takes, and reply a client takes, unless told otherwise (bytes).
DEFAULT_MAX_REQUEST_BYTES = 1 << 20
#: The service types of ROS 2 whose calls change nothing (they read a node's state or
#: parameters), so a request may be written again when no answer came: over DDS a response is
#: lost when the server has not yet matched the client's reader (:meth:`dyknow.ros2.dds.DdsClient.call`).
READ_ONLY_SERVICES = frozenset({
    "lifecycle_msgs/srv/GetState", "lifecycle_msgs/srv/GetAvailableStates", "lifecycle_msgs/srv/GetAvailableTransitions",
    "rcl_interfaces/srv/GetParameters", "rcl_interfaces/srv/GetParameterTypes", "rcl_interfaces/srv/ListParameters",
    "rcl_interfaces/srv/DescribeParameters", "type_description_interfaces/srv/GetTypeDescription",
})  # fmt: skip
#: Seconds between two writes of a read-only request that no answer came to (over DDS).
RESEND_S = 1.0
#: How many requests a server keeps waiting for its handler before it drops the next ones.
DEFAULT_MAX_PENDING = 64
# when the first server of a call shows up during the call, how long the call lets its queryable's
# declaration follow the token (zenoh-ros2-sdk declares the token first, then the queryable)
_SETTLE_S = 0.05


class ServiceNode(Protocol):
    """What a client or server needs of its node (:class:`~dyknow.ros2.node.Ros2Node` provides it)."""

    session: Session
    domain: int
    name: str
    types: TypeSupport

    def entity(self, kind: names.EntityKind, topic: str, ros_type: str, type_hash: str, qos: QoS) -> names.Entity:
        """A new entity of the node."""
        ...

    def forget(self, entity: Any) -> None:
        """Called by an entity that closed itself."""
        ...


def as_message(value: Any, ros_type: str, types: TypeSupport, where: str) -> Any:
    """``value`` as a message object of ``ros_type``: a message object as it is, a dict of its
    fields built (:func:`~dyknow.ros2.convert.to_message`); else :class:`BindingError`."""
    from dyknow.ros2.convert import to_message

    if getattr(value, "__msgtype__", None) == ros_type:
        return value
    if isinstance(value, dict):
        return to_message(value, ros_type, types, origin_ns=0)
    raise BindingError(f"a {type(value).__name__}", where=where, expected=f"a {ros_type} message or a dict of its fields")


def _check_bytes(max_bytes: int, where: str) -> int:
    if not 0 < max_bytes <= MAX_CDR_BYTES:
        raise BindingError(f"max_bytes {max_bytes}", where=where, expected=f"from 1 to {MAX_CDR_BYTES}")
    return max_bytes


class Ros2Client:
    """Calls the ROS 2 service ``service`` of type ``srv_type`` (``pkg/srv/Name``) over rmw_zenoh.

    :meth:`call` sends a request and waits for its response; calls from several threads may be
    in flight at once. ``servers`` is the number of servers of this service and type whose
    tokens are up. A context manager; ``close()`` is safe twice and undeclares the ``SC`` token.
    """

    def __init__(
        self,
        node: ServiceNode,
        service: str,
        srv_type: str,
        *,
        humble: bool = False,
        qos: QoS = DEFAULT_QOS,
        max_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
    ) -> None:
        self.service = names.check_topic(service, "ROS 2 service")
        self.where = f"ROS 2 client of {self.service}"
        self.srv_type = srv_type
        self.request_type, self.response_type = node.types.service(srv_type)
        self.type_hash = node.types.type_hash(srv_type, humble=humble)
        self.key = names.data_key(node.domain, self.service, srv_type, self.type_hash)
        self.entity = node.entity(names.EntityKind.CLIENT, self.service, srv_type, self.type_hash, qos)
        self.gid = self.entity.gid()
        self.max_bytes = _check_bytes(max_bytes, self.where)
        self.refused = 0  # replies that named this client but did not decode
        self._node = node
        self._types = node.types
        self._lock = threading.Lock()
        self._seq = 0
        self._servers: set[str] = set()
        self._server_up = threading.Event()
        self._closed = False
        session = node.session
        self._token = session.declare_liveliness_token(self.entity.token())
        try:
            pattern = names.endpoint_pattern(node.domain, self.service, names.EntityKind.SERVICE, srv_type, self.type_hash)
            self._watch = session.declare_liveliness_subscriber(pattern, self._server_changed, inline=True)
        except BaseException:
            self._token.undeclare()
            raise

    def _server_changed(self, key: str, alive: bool) -> None:
        with self._lock:
            if alive and len(self._servers) < 1000:  # tokens come from the network: bounded
                self._servers.add(key)
            elif not alive:
                self._servers.discard(key)
            if self._servers:
                self._server_up.set()
            else:
                self._server_up.clear()

    @property
    def servers(self) -> int:
        """How many servers of this service and type are up (their ``SS`` tokens)."""
        with self._lock:
            return len(self._servers)

    def wait_for_service(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a server's token; whether one is up."""
        return self._server_up.wait(timeout_s)

    def request(self, **fields: Any) -> Any:
        """A request message of this service's type with ``fields`` (the others zero)."""
        return as_message(fields, self.request_type, self._types, self.where)

    def call(self, request: Any, timeout_s: float = 5.0) -> Any:
        """Send ``request`` (a request message, or a dict of its fields) and return the response
        message. Waits up to ``timeout_s`` in all: for a server to show up, then for its answer.
        Raises :class:`~dyknow.errors.ServiceError` naming the service and the time waited when
        nothing answers, or with the server's error reply."""
        if self._closed:
            raise ClosedError("the client is closed", where=self.where, expected="a new client")
        if not 0 < timeout_s <= 3600:
            raise BindingError(f"timeout {timeout_s} s", where=self.where, expected="from 0 to 3600 s")
        data = self._types.serialize(as_message(request, self.request_type, self._types, self.where), self.request_type)
        started = time.monotonic()
        deadline = started + timeout_s
        was_up = self._server_up.is_set()
        if not was_up:
            if not self._server_up.wait(timeout_s):
                raise self._no_answer(time.monotonic() - started, "no server of it came up")
            time.sleep(min(_SETTLE_S, max(0.0, deadline - time.monotonic())))
        with self._lock:
            self._seq += 1
            seq = self._seq
        answered = threading.Event()
        result: list[Any] = [None, None]  # the response's CDR, the first error reply

        def on_reply(_key: str, payload: bytes, attachment: bytes | None) -> None:
            # (wanted() let through only this call's replies: replies are not consolidated)
            with self._lock:
                if result[0] is None:
                    result[0] = payload
            answered.set()

        def wanted(attachment: bytes | None) -> bool:  # before the payload is copied
            try:
                meta = Attachment.decode(attachment)
            except BindingError as exc:
                self._refuse(f"a reply with {exc}")
                return False
            return meta.sequence_number == seq and meta.gid == self.gid

        def on_error(text: str) -> None:
            if text == "Timeout":  # Zenoh's own, as the query's time ran out: no server's answer
                return
            with self._lock:
                if result[1] is None:
                    result[1] = text

        left = max(0.01, deadline - time.monotonic())
        self._node.session.query_plain(
            self.key,
            data,
            Attachment(seq, time.time_ns(), self.gid).encode(),
            timeout_s=left,
            on_reply=on_reply,
            on_error=on_error,
            done=answered.set,
            max_bytes=self.max_bytes,
            wanted=wanted,
        )
        answered.wait(left + 1.0)  # the query's own timeout ends it; the second is a margin
        waited = time.monotonic() - started
        with self._lock:
            payload, error = result
        if payload is not None:
            return self._types.deserialize(payload, self.response_type)
        if error is not None:
            raise ServiceError(
                f"the server answered with an error after {waited:.1f} s: {error[:300]}",
                where=f"ROS 2 service {self.service} ({self.srv_type})",
            )
        if waited < timeout_s - 0.05:  # the query ended before its time: every server let it go, or a link's access control dropped it
            raise self._no_answer(waited, f"{self.servers} server(s) up ended the request without an answer", reason="dropped")
        raise self._no_answer(waited, f"{self.servers} server(s) up", reason="timeout")

    def _no_answer(self, waited_s: float, why: str, *, reason: str = "no-server") -> ServiceError:
        """``reason`` in the error's details: "no-server" (none came up), "dropped" (the request
        ended early without an answer: the servers dropped it, or an access control on the way
        did, which Zenoh does not tell apart) or "timeout"."""
        return ServiceError(
            f"no answer in {waited_s:.1f} s ({why})",
            details={"reason": reason},
            where=f"ROS 2 service {self.service} ({self.srv_type})",
            expected="a server of this name and type that answers (dyknow ros2 list shows the services), or a longer timeout",
        )

    def _refuse(self, why: str) -> None:
        with self._lock:
            self.refused += 1
            count = self.refused
        if count <= 3 or count % 100 == 0:
            log.warning("%s refused a reply (%d so far): %s", self.where, count, why)

    def close(self) -> None:
        """Undeclare the watch of the servers and the ``SC`` token; safe twice."""
        self._closed = True
        self._watch.undeclare()
        self._token.undeclare()
        self._node.forget(self)

    def __enter__(self) -> Ros2Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Ros2Service:
    """Serves the ROS 2 service ``service`` of type ``srv_type`` over rmw_zenoh:
    ``handler(request) -> response`` for each request (the request a message object; the
    response a message object or a dict of its fields). Bounded as the module documentation
    says (``max_bytes``, ``max_pending``); ``received``, ``answered``, ``refused`` and
    ``failed`` count the requests. A context manager; ``close()`` is safe twice and undeclares
    the ``SS`` token, then the queryable; requests still waiting are dropped unanswered.
    """

    def __init__(
        self,
        node: ServiceNode,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        *,
        humble: bool = False,
        qos: QoS = DEFAULT_QOS,
        max_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
        max_pending: int = DEFAULT_MAX_PENDING,
        call_soon: Callable[[Callable[[], None]], None],
        on_close: Callable[[], None] | None = None,
    ) -> None:
        self.service = names.check_topic(service, "ROS 2 service")
        self.where = f"ROS 2 service {self.service}"
        self.srv_type = srv_type
        self.request_type, self.response_type = node.types.service(srv_type)
        self.type_hash = node.types.type_hash(srv_type, humble=humble)
        self.key = names.data_key(node.domain, self.service, srv_type, self.type_hash)
        self.entity = node.entity(names.EntityKind.SERVICE, self.service, srv_type, self.type_hash, qos)
        self.gid = self.entity.gid()
        self.max_bytes = _check_bytes(max_bytes, self.where)
        if not 0 < max_pending <= 10_000:
            raise BindingError(f"max_pending {max_pending}", where=self.where, expected="from 1 to 10000")
        self.max_pending = max_pending
        self.received = 0
        self.answered = 0
        self.refused = 0
        self.failed = 0
        self.last_refusal: str | None = None
        self._node = node
        self._types = node.types
        self._handler = handler
        self._lock = threading.Lock()
        self._pending = 0
        self._closed = False
        self._call_soon = call_soon
        self._on_close = on_close
        session = node.session
        self._queryable = session.declare_plain_queryable(self.key, self._arrived, max_bytes=self.max_bytes, on_refused=self._oversize)
        try:
            self._token = session.declare_liveliness_token(self.entity.token())
        except BaseException:
            self._queryable.undeclare()
            raise

    def _refuse(self, why: str) -> None:
        with self._lock:
            self.refused += 1
            self.last_refusal = why
            count = self.refused
        if count <= 3 or count % 100 == 0:  # a stream of bad requests must not flood the log
            log.warning("%s refused a request (%d so far): %s", self.where, count, why)

    def _oversize(self, _key: str, why: str) -> None:  # on Zenoh's thread, before the payload is copied
        self._refuse(why)

    def _arrived(self, query: Any) -> None:
        # on Zenoh's thread: check, queue and return; the handler runs elsewhere
        try:
            meta = Attachment.decode(query.attachment)
        except BindingError as exc:
            self._refuse(str(exc))
            query.drop()
            return
        with self._lock:
            busy = self._closed or self._pending >= self.max_pending
            if not busy:
                self._pending += 1
                self.received += 1
        if busy:
            if not self._closed:
                self._refuse(f"{self.max_pending} requests already wait for the handler")
            query.drop()
            return
        self._call_soon(lambda: self._serve(query, meta))

    def _serve(self, query: Any, meta: Attachment) -> None:
        try:
            if self._closed:
                query.drop()
                return
            try:
                request = self._types.deserialize(query.payload, self.request_type)
            except BindingError as exc:
                self._refuse(str(exc))
                query.drop()
                return
            try:
                response = self._handler(request)
                data = self._types.serialize(as_message(response, self.response_type, self._types, self.where), self.response_type)
            except Exception as exc:  # the handler's: answer nothing, say why in the log
                with self._lock:
                    self.failed += 1
                level = logging.WARNING if isinstance(exc, DyKnowError) else logging.ERROR
                log.log(level, "%s: the handler failed on request #%d, answered nothing", self.where, meta.sequence_number, exc_info=True)
                query.drop()
                return
            with self._lock:  # (counted first: the caller may look as soon as it has the answer)
                self.answered += 1
            query.reply(data, Attachment(meta.sequence_number, time.time_ns(), meta.gid).encode())
        finally:
            with self._lock:
                self._pending -= 1

    def close(self) -> None:
        """Undeclare the ``SS`` token, then the queryable; drop what waits; safe twice."""
        with self._lock:
            self._closed = True
        self._token.undeclare()
        self._queryable.undeclare()
        if self._on_close is not None:
            self._on_close()
        self._node.forget(self)

    def __enter__(self) -> Ros2Service:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
