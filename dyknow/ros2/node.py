"""A ROS 2 node on a dyknow Zenoh session, speaking rmw_zenoh's protocol.

The node announces itself with a ``NN`` liveliness token and each of its publishers,
subscriptions, service clients and servers with an ``MP``/``MS``/``SC``/``SS`` token (services:
:mod:`dyknow.ros2.services`) (:mod:`dyknow.ros2.names`), so ``ros2 node list`` and
``ros2 topic list`` over rmw_zenoh see them. A publisher puts CDR on the topic's data key with
rmw_zenoh's attachment (:mod:`dyknow.ros2.attachment`); a subscription takes CDR from it. Every
entity is a context manager; closing the node undeclares what it declared, in reverse order.

A subscription created without a type takes it from the topic's publishers when their tokens
show exactly one known type; else it subscribes to the topic's key of *any* type
(``<domain>/<topic>/*/*``), reads the type from each sample's key and declares its ``MS`` token
once the first message told the type; the publishers chose that type, so such a subscription
takes messages of at most :data:`UNTYPED_MAX_MESSAGE_BYTES` unless told otherwise. A sample whose
type is unknown or another than the subscription took, whose hash differs from this process's
hash of that type, whose attachment is malformed or whose CDR does not parse is counted in
``refused`` (with ``last_refusal``) and dropped: never raised into Zenoh's thread.

What crosses the network is bounded before it costs anything: a subscription drops a message
over its ``max_bytes`` before copying it, and decodes off Zenoh's thread, from a bounded queue
(:class:`Ros2Subscription`); the node watches the publishers of the topics it is asked about and
no others (:class:`~dyknow.ros2.graph.PublisherWatch`).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dyknow.errors import BindingError, ClosedError
from dyknow.ros2 import names
from dyknow.ros2.attachment import Attachment
from dyknow.ros2.names import HASH_NOT_SUPPORTED, QoS, Reliability
from dyknow.ros2.services import DEFAULT_MAX_PENDING, DEFAULT_MAX_REQUEST_BYTES, Ros2Client, Ros2Service
from dyknow.ros2.types import MAX_CDR_BYTES, TypeSupport
from dyknow.transport import Session

__all__ = ["DEFAULT_MAX_MESSAGE_BYTES", "UNTYPED_MAX_MESSAGE_BYTES", "Received", "Ros2Node", "Ros2Publisher", "Ros2Subscription"]

log = logging.getLogger(__name__)

#: The largest message a subscription takes unless told otherwise (bytes): a 1080p RGB image
#: (6 MB) and a lidar sweep of some 500,000 points (16 bytes each) fit. A manager's
#: ``--max-ros2-message-bytes`` (:class:`~dyknow.security.Limits`) sets it for its node.
DEFAULT_MAX_MESSAGE_BYTES = 16 << 20
#: The largest message a subscription takes when its type was not declared (its publishers chose it).
UNTYPED_MAX_MESSAGE_BYTES = 1 << 20
_KEEP_ALL_DEPTH = 1000  # the queue of a keep-all subscription (messages)


@dataclass(frozen=True, slots=True)
class Received:
    """One message taken from a topic: the decoded message object, its type, rmw_zenoh's
    attachment and when it arrived (``arrival_ns``, this host's clock)."""

    message: Any
    ros_type: str
    attachment: Attachment
    arrival_ns: int
    key: str


class Ros2Publisher:
    """Publishes messages of one type on one topic. A context manager; ``close()`` is safe twice."""

    def __init__(self, node: Ros2Node, topic: str, ros_type: str, qos: QoS, *, humble: bool) -> None:
        self.topic = names.check_topic(topic)
        self.ros_type = node.types.check(ros_type)
        self.qos = qos
        self.type_hash = node.types.type_hash(ros_type, humble=humble)
        self.key = names.data_key(node.domain, topic, ros_type, self.type_hash)
        self.entity = node.entity(names.EntityKind.PUBLISHER, topic, ros_type, self.type_hash, qos)
        self.gid = self.entity.gid()
        self._types = node.types
        self._seq = 0
        self._lock = threading.Lock()
        cache = qos.depth if qos.durability is names.Durability.TRANSIENT_LOCAL else 0
        # as rmw_zenoh: only a reliable keep-all publisher blocks when the network is congested; the
        # others drop (a 30 Hz camera must not stall its unit behind a slow reader)
        block = qos.reliability is Reliability.RELIABLE and qos.keep_all
        self._publisher = node.session.declare_plain_publisher(self.key, block=block, cache=cache)
        try:
            self._token = node.session.declare_liveliness_token(self.entity.token())
        except BaseException:
            self._publisher.undeclare()
            raise
        self._node = node
        self._closed = False

    def publish(self, message: Any) -> int:
        """Serialize and send a message object; returns its sequence number."""
        return self.publish_cdr(self._types.serialize(message, self.ros_type))

    def publish_cdr(self, data: bytes) -> int:
        """Send CDR bytes as they are (with their encapsulation header); returns the sequence number."""
        if self._closed:
            raise ClosedError("the publisher is closed", where=f"ROS 2 publisher on {self.topic}", expected="a new publisher")
        with self._lock:
            self._seq += 1
            seq = self._seq
        self._publisher.put(data, Attachment(seq, time.time_ns(), self.gid).encode())
        return seq

    def close(self) -> None:
        """Undeclare the token, then the publisher; safe twice."""
        self._closed = True
        self._token.undeclare()
        self._publisher.undeclare()
        self._node.forget(self)

    def __enter__(self) -> Ros2Publisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Ros2Subscription:
    """Takes messages from one topic and calls ``on_message(Received)`` for each, off Zenoh's thread.

    Zenoh's thread only checks a message's size and queues its bytes: a message over
    ``max_bytes`` is dropped there, before it is copied (counted in ``refused`` and ``oversized``,
    and logged naming the topic, the size and the bound), and the queue keeps the newest
    ``qos.depth`` messages (1,000 for keep-all) and at most twice ``max_bytes`` (the oldest go
    first, counted in ``dropped``). Decoding runs where ``call_soon`` runs what it is given (a
    unit's lane), else on the node's delivery thread, in batches of what was queued.
    """

    def __init__(
        self,
        node: Ros2Node,
        topic: str,
        ros_type: str | None,
        qos: QoS,
        on_message: Callable[[Received], None],
        *,
        humble: bool,
        max_bytes: int | None = None,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
        where: str | None = None,
    ) -> None:
        self.topic = names.check_topic(topic)
        self.where = where or f"ROS 2 subscription on {self.topic}"
        declared = ros_type is not None
        if ros_type is None:
            ros_type = _published_type(node, self.topic)
        self.ros_type = node.types.check(ros_type) if ros_type is not None else None
        self.qos = qos
        if max_bytes is None:  # a type the publishers chose gets the tighter bound
            max_bytes = node.max_message_bytes if declared else min(node.max_message_bytes, UNTYPED_MAX_MESSAGE_BYTES)
        if not 0 < max_bytes <= MAX_CDR_BYTES:
            raise BindingError(f"max_bytes {max_bytes}", where=self.where, expected=f"from 1 to {MAX_CDR_BYTES}")
        self.max_bytes = max_bytes
        self.received = 0
        self.refused = 0
        self.oversized = 0
        self.dropped = 0
        self.last_refusal: str | None = None
        self._node = node
        self._humble = humble
        self._on_message = on_message
        self._call_soon = call_soon or node.call_soon
        self._lock = threading.Lock()
        self._queue: deque[tuple[str, bytes, bytes | None, int]] = deque()
        self._queued_bytes = 0
        self._depth = _KEEP_ALL_DEPTH if qos.keep_all else qos.depth
        self._pending = False  # a drain is scheduled and has not emptied the queue yet
        self._closed = False
        self._token: Any = None
        if self.ros_type is not None:
            key = names.data_key(node.domain, topic, self.ros_type, node.types.type_hash(self.ros_type, humble=humble))
            self._declare_token(self.ros_type)
        else:
            key = names.topic_pattern(node.domain, topic)
        self.key = key
        history = qos.durability is names.Durability.TRANSIENT_LOCAL
        try:
            self._subscriber = node.session.declare_sample_subscriber(
                key, self._arrived, history=history, max_bytes=max_bytes, on_refused=self._oversize
            )
        except BaseException:
            if self._token is not None:
                self._token.undeclare()
            raise

    def _declare_token(self, ros_type: str) -> None:
        type_hash = self._node.types.type_hash(ros_type, humble=self._humble)
        entity = self._node.entity(names.EntityKind.SUBSCRIPTION, self.topic, ros_type, type_hash, self.qos)
        self._token = self._node.session.declare_liveliness_token(entity.token())

    def _refuse(self, why: str, *, oversized: bool = False) -> None:
        with self._lock:
            self.refused += 1
            self.oversized += oversized
            self.last_refusal = why
            count = self.refused
        if count <= 3 or count % 100 == 0:  # a stream of bad messages must not flood the log
            log.warning("%s refused a message (%d so far): %s", self.where, count, why)

    def _oversize(self, _key: str, why: str) -> None:  # on Zenoh's thread, before the payload is copied
        self._refuse(f"{why} (raise it with max_bytes= in the binding)", oversized=True)

    def _arrived(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        # on Zenoh's thread: queue the bytes and return; never decode here (a large message would
        # hold the thread, and with it every sample behind it in Zenoh's queue)
        arrival = time.time_ns()
        with self._lock:
            if self._closed:
                return
            queue = self._queue
            queue.append((key, payload, attachment, arrival))
            self._queued_bytes += len(payload)
            dropped = self.dropped
            while len(queue) > self._depth or (self._queued_bytes > 2 * self.max_bytes and len(queue) > 1):
                self._queued_bytes -= len(queue.popleft()[1])
                self.dropped += 1
            schedule = not self._pending
            self._pending = True
        if self.dropped != dropped and (dropped == 0 or self.dropped // 1000 != dropped // 1000):  # the first, then every 1,000th
            log.info(
                "%s dropped %d undecoded messages so far: newer ones filled its queue (depth %d)", self.where, self.dropped, self._depth
            )
        if schedule:
            self._call_soon(self._drain)

    def _drain(self) -> None:
        """Decode and deliver what was queued when it started, then schedule itself again if more came."""
        with self._lock:
            batch = len(self._queue)
        for _ in range(batch):
            with self._lock:
                if self._closed or not self._queue:
                    break
                key, payload, attachment, arrival = self._queue.popleft()
                self._queued_bytes -= len(payload)
            self._deliver(key, payload, attachment, arrival)
        with self._lock:
            more = bool(self._queue) and not self._closed
            self._pending = more
        if more:
            self._call_soon(self._drain)

    def _deliver(self, key: str, payload: bytes, attachment: bytes | None, arrival: int) -> None:
        try:
            _domain, _topic, ros_type, type_hash = names.parse_data_key(key)
            types = self._node.types
            if self.ros_type is not None and ros_type != self.ros_type:
                raise BindingError(
                    f"a message of type {ros_type}",
                    where=self.where,
                    expected=f"{self.ros_type}, the type it takes (declare ?type= to choose another)",
                )
            types.check(ros_type, where=self.where)
            if type_hash != HASH_NOT_SUPPORTED and type_hash != types.type_hash(ros_type):
                raise BindingError(
                    f"type hash {type_hash}",
                    where=f"{ros_type} on {self.topic}",
                    expected=f"{types.type_hash(ros_type)} (another definition of the type)",
                )
            meta = Attachment.decode(attachment)
            message = types.deserialize(payload, ros_type)
        except BindingError as exc:
            self._refuse(str(exc))
            return
        if self.ros_type is None:
            with self._lock:
                learned = self.ros_type is None
                if learned:
                    self.ros_type = ros_type
            if learned:
                self._declare_token(ros_type)
        with self._lock:
            self.received += 1
        try:
            self._on_message(Received(message, ros_type, meta, arrival, key))
        except Exception:
            log.exception("%s: on_message failed", self.where)

    def close(self) -> None:
        """Undeclare the subscriber, then the token; drop what is queued; safe twice."""
        self._subscriber.undeclare()
        with self._lock:
            self._closed = True
            self._queue.clear()
            self._queued_bytes = 0
        if self._token is not None:
            self._token.undeclare()
        self._node.forget(self)

    def __enter__(self) -> Ros2Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _published_type(node: Ros2Node, topic: str) -> str | None:
    """The one known type the publishers of ``topic`` announce now, else None (a bounded answer
    about this topic alone: tokens of other topics are not asked for)."""
    from dyknow.ros2.graph import MAX_TOPIC_PUBLISHERS

    pattern = names.publisher_pattern(node.domain, topic)
    found = set()
    for key in node.session.alive(pattern, timeout_s=0.3)[:MAX_TOPIC_PUBLISHERS]:
        try:
            found.add(names.parse_token(key).ros_type)
        except BindingError:
            continue
    if len(found) == 1:
        (ros_type,) = found
        if ros_type is not None and node.types.known(ros_type):
            return ros_type
    return None


class _Deliveries:
    """The thread that decodes and delivers for the node's subscriptions that were given no
    ``call_soon`` (tools, tests): one per node, started on first use."""

    def __init__(self, name: str) -> None:
        self._name = name
        self._calls: deque[Callable[[], None]] = deque()
        self._ready = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closed = False

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the thread (started now if it is not yet); dropped once closed."""
        with self._ready:
            if self._closed:
                return
            self._calls.append(fn)
            if self._thread is None:
                self._thread = threading.Thread(target=self._serve, name=f"dyknow-ros2-{self._name}", daemon=True)
                self._thread.start()
            self._ready.notify()

    def _serve(self) -> None:
        while True:
            with self._ready:
                while not self._calls and not self._closed:
                    self._ready.wait()
                if self._closed:
                    return
                fn = self._calls.popleft()
            try:
                fn()
            except Exception:
                log.exception("a ROS 2 delivery failed")

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the thread (waiting up to ``timeout_s`` for what it runs now); safe twice."""
        with self._ready:
            self._closed = True
            self._calls.clear()
            self._ready.notify()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)


class Ros2Node:
    """A ROS 2 node: ``name`` in ``namespace`` on ROS domain ``domain``, on a dyknow session.

    The session is the caller's (a manager's) and stays open when the node closes.
    """

    def __init__(
        self,
        session: Session,
        name: str,
        *,
        namespace: str = "/",
        domain: int = 0,
        types: TypeSupport | None = None,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    ) -> None:
        if not names.check_topic("/" + name, "ROS 2 node name").count("/") == 1:
            raise BindingError(f"node name {name!r}", where="ROS 2 node", expected="one name part, like 'dyknow_robot'")
        if namespace != "/":
            names.check_topic(namespace, "ROS 2 node namespace")
        if not 0 <= int(domain) <= 232:
            raise BindingError(f"domain {domain}", where="ROS 2 node", expected="a ROS_DOMAIN_ID from 0 to 232")
        if not 0 < max_message_bytes <= MAX_CDR_BYTES:
            raise BindingError(
                f"max_message_bytes {max_message_bytes}",
                where="ROS 2 node (--max-ros2-message-bytes)",
                expected=f"from 1 to {MAX_CDR_BYTES}",
            )
        self.session = session
        self.max_message_bytes = max_message_bytes
        self.name = name
        self.namespace = namespace
        self.domain = int(domain)
        self.types = types or TypeSupport()
        self._ids = itertools.count(1)
        self.node_id = 0
        self._entities: list[Any] = []  # publishers, subscriptions, clients and services
        self._lock = threading.Lock()
        self.entity_token = names.Entity(self.domain, session.zid, self.node_id, self.node_id, names.EntityKind.NODE, namespace, name)
        self._token: Any = session.declare_liveliness_token(self.entity_token.token())
        # one PublisherWatch per (topic, type, hash) watched, shared by its watchers (see watch_publishers)
        self._watches: dict[tuple[str, str | None, str | None], tuple[Any, dict[int, Callable[[names.Entity, bool], None]]]] = {}
        self._watch_ids = itertools.count(1)
        self._deliveries = _Deliveries(name)

    def entity(self, kind: names.EntityKind, topic: str, ros_type: str, type_hash: str, qos: QoS) -> names.Entity:
        """A new entity of this node (its id taken from the node's counter)."""
        return names.Entity(
            self.domain,
            self.session.zid,
            self.node_id,
            next(self._ids),
            kind,
            self.namespace,
            self.name,
            "/",
            topic,
            ros_type,
            type_hash,
            qos,
        )

    def _check_open(self) -> None:
        if self._token is None:
            raise ClosedError("the ROS 2 node is closed", where=f"node {self.name!r}", expected="a new node")

    def create_publisher(self, topic: str, ros_type: str, qos: QoS = names.DEFAULT_QOS, *, humble: bool = False) -> Ros2Publisher:
        """A publisher of ``ros_type`` on ``topic``."""
        self._check_open()
        pub = Ros2Publisher(self, topic, ros_type, qos, humble=humble)
        with self._lock:
            self._entities.append(pub)
        return pub

    def create_subscription(
        self,
        topic: str,
        ros_type: str | None,
        on_message: Callable[[Received], None],
        qos: QoS = names.DEFAULT_QOS,
        *,
        humble: bool = False,
        max_bytes: int | None = None,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
        where: str | None = None,
    ) -> Ros2Subscription:
        """A subscription to ``topic``; ``ros_type`` None: of whatever type its publishers send.

        ``max_bytes``: the largest message taken (default: the node's ``max_message_bytes``, and
        at most :data:`UNTYPED_MAX_MESSAGE_BYTES` without ``ros_type``); ``call_soon``: runs the
        decoding and ``on_message`` (a unit's :meth:`~dyknow.unit.Unit.call_soon`; default: the
        node's delivery thread); ``where``: how log lines and refusals name it."""
        self._check_open()
        sub = Ros2Subscription(self, topic, ros_type, qos, on_message, humble=humble, max_bytes=max_bytes, call_soon=call_soon, where=where)
        with self._lock:
            self._entities.append(sub)
        return sub

    def create_client(
        self, service: str, srv_type: str, *, humble: bool = False, max_bytes: int = DEFAULT_MAX_REQUEST_BYTES
    ) -> Ros2Client:
        """A client of the service ``service`` of type ``srv_type`` (``pkg/srv/Name``): its
        :meth:`~dyknow.ros2.services.Ros2Client.call` returns the response. ``max_bytes``: the
        largest reply taken."""
        self._check_open()
        client = Ros2Client(self, service, srv_type, humble=humble, max_bytes=max_bytes)
        with self._lock:
            self._entities.append(client)
        return client

    def create_service(
        self,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        *,
        humble: bool = False,
        max_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
        max_pending: int = DEFAULT_MAX_PENDING,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
    ) -> Ros2Service:
        """Serve the service ``service`` of type ``srv_type``: ``handler(request) -> response``
        (a message object or a dict of its fields) for each request, where ``call_soon`` runs
        it (a unit's :meth:`~dyknow.unit.Unit.call_soon`; default: a thread of the service's
        own). ``max_bytes``: the largest request taken; ``max_pending``: how many requests may
        wait for the handler (more are dropped unanswered). An exception of the handler answers
        nothing and is logged."""
        self._check_open()
        worker = None
        if call_soon is None:
            worker = _Deliveries(f"{self.name}-{names.check_topic(service, 'ROS 2 service').rsplit('/', 1)[1]}")
            call_soon = worker.call_soon
        try:
            server = Ros2Service(
                self,
                service,
                srv_type,
                handler,
                humble=humble,
                max_bytes=max_bytes,
                max_pending=max_pending,
                call_soon=call_soon,
                on_close=worker.close if worker is not None else None,
            )
        except BaseException:
            if worker is not None:
                worker.close()
            raise
        with self._lock:
            self._entities.append(server)
        return server

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the node's delivery thread (started on first use)."""
        self._deliveries.call_soon(fn)

    def watch_publishers(
        self,
        topic: str,
        on_change: Callable[[names.Entity, bool], None],
        *,
        ros_type: str | None = None,
        type_hash: str | None = None,
    ) -> Callable[[], None]:
        """Call ``on_change(entity, alive)`` as publishers of ``topic`` (of ``ros_type`` with
        ``type_hash``, when given) appear and vanish (their tokens; those up now first), on a
        Zenoh thread; returns the function that stops it. Watchers of the same publishers share
        one :class:`~dyknow.ros2.graph.PublisherWatch`, which sees no other topic's tokens."""
        from dyknow.ros2.graph import PublisherWatch

        self._check_open()
        which = (names.check_topic(topic), ros_type, type_hash)
        with self._lock:
            ident = next(self._watch_ids)
            shared = self._watches.get(which)
            if shared is None:  # its history brings the tokens up now to the watcher
                watchers = {ident: on_change}
                watch = PublisherWatch(
                    self.session,
                    self.domain,
                    topic,
                    lambda entity, alive: self._publisher_changed(which, entity, alive),
                    ros_type=ros_type,
                    type_hash=type_hash,
                )
                self._watches[which] = (watch, watchers)
            else:
                watch, watchers = shared
                watchers[ident] = on_change
        if shared is not None:
            for entity in watch.view():
                on_change(entity, True)

        def stop() -> None:
            with self._lock:
                held = self._watches.get(which)
                if held is None:
                    return
                held[1].pop(ident, None)
                last = not held[1]
                if last:
                    del self._watches[which]
            if last:
                held[0].close()

        return stop

    def _publisher_changed(self, which: tuple[str, str | None, str | None], entity: names.Entity, alive: bool) -> None:
        with self._lock:
            held = self._watches.get(which)
            watchers = list(held[1].values()) if held is not None else []
        for fn in watchers:
            try:
                fn(entity, alive)
            except Exception:
                log.exception("a watcher of %s failed", entity.topic)

    def forget(self, entity: Any) -> None:
        """Called by an entity that closed itself."""
        with self._lock:
            if entity in self._entities:
                self._entities.remove(entity)

    def close(self) -> None:
        """Close every publisher, subscription, client and service (the latest first), then the
        node's token; safe twice."""
        with self._lock:
            entities = list(reversed(self._entities))
        for entity in entities:
            entity.close()
        with self._lock:
            watches, self._watches = list(self._watches.values()), {}
        for watch, _ in watches:
            watch.close()
        self._deliveries.close()
        token, self._token = self._token, None
        if token is not None:
            token.undeclare()

    def __enter__(self) -> Ros2Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
