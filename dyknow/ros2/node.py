"""A ROS 2 node on a dyknow Zenoh session, speaking rmw_zenoh's protocol.

The node announces itself with a ``NN`` liveliness token and each of its publishers and
subscriptions with an ``MP``/``MS`` token (:mod:`dyknow.ros2.names`), so ``ros2 node list`` and
``ros2 topic list`` over rmw_zenoh see them. A publisher puts CDR on the topic's data key with
rmw_zenoh's attachment (:mod:`dyknow.ros2.attachment`); a subscription takes CDR from it. Every
entity is a context manager; closing the node undeclares what it declared, in reverse order.

A subscription created without a type takes it from the topic's publishers when their tokens
show exactly one known type; else it subscribes to the topic's key of *any* type
(``<domain>/<topic>/*/*``), reads the type from each sample's key and declares its ``MS`` token
once the first message told the type. A sample whose type is unknown, whose hash differs from
this process's hash of that type, whose attachment is malformed or whose CDR does not parse is
counted in ``refused`` (with ``last_refusal``) and dropped: never raised into Zenoh's thread.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dyknow.errors import BindingError, ClosedError
from dyknow.ros2 import names
from dyknow.ros2.attachment import Attachment
from dyknow.ros2.names import HASH_NOT_SUPPORTED, QoS, Reliability
from dyknow.ros2.types import MAX_CDR_BYTES, TypeSupport
from dyknow.transport import Session

__all__ = ["Received", "Ros2Node", "Ros2Publisher", "Ros2Subscription"]

log = logging.getLogger(__name__)


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
    """Takes messages from one topic and calls ``on_message(Received)`` on a Zenoh thread."""

    def __init__(
        self, node: Ros2Node, topic: str, ros_type: str | None, qos: QoS, on_message: Callable[[Received], None], *, humble: bool
    ) -> None:
        self.topic = names.check_topic(topic)
        if ros_type is None:
            ros_type = _published_type(node, self.topic)
        self.ros_type = node.types.check(ros_type) if ros_type is not None else None
        self.qos = qos
        self.received = 0
        self.refused = 0
        self.last_refusal: str | None = None
        self._node = node
        self._humble = humble
        self._on_message = on_message
        self._lock = threading.Lock()
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
                key, self._arrived, history=history, max_bytes=MAX_CDR_BYTES, on_refused=lambda _k, why: self._refuse(why)
            )
        except BaseException:
            if self._token is not None:
                self._token.undeclare()
            raise

    def _declare_token(self, ros_type: str) -> None:
        type_hash = self._node.types.type_hash(ros_type, humble=self._humble)
        entity = self._node.entity(names.EntityKind.SUBSCRIPTION, self.topic, ros_type, type_hash, self.qos)
        self._token = self._node.session.declare_liveliness_token(entity.token())

    def _refuse(self, why: str) -> None:
        with self._lock:
            self.refused += 1
            self.last_refusal = why
            count = self.refused
        if count <= 3 or count % 100 == 0:  # a stream of bad messages must not flood the log
            log.warning("ROS 2 subscription on %s refused a message (%d so far): %s", self.topic, count, why)

    def _arrived(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        arrival = time.time_ns()
        try:
            _domain, _topic, ros_type, type_hash = names.parse_data_key(key)
            types = self._node.types
            if self.ros_type is not None and ros_type != self.ros_type:
                raise BindingError(f"type {ros_type}", where=f"topic {self.topic}", expected=self.ros_type)
            types.check(ros_type, where=f"topic {self.topic}")
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
            log.exception("ROS 2 subscription on %s: on_message failed", self.topic)

    def close(self) -> None:
        """Undeclare the subscriber, then the token; safe twice."""
        self._subscriber.undeclare()
        if self._token is not None:
            self._token.undeclare()
        self._node.forget(self)

    def __enter__(self) -> Ros2Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _published_type(node: Ros2Node, topic: str) -> str | None:
    """The one known type the publishers of ``topic`` announce now, else None."""
    from dyknow.ros2.graph import snapshot

    found = {e.ros_type for e in snapshot(node.session, node.domain, timeout_s=0.3).publishers(topic)}
    if len(found) == 1:
        (ros_type,) = found
        if ros_type is not None and node.types.known(ros_type):
            return ros_type
    return None


class Ros2Node:
    """A ROS 2 node: ``name`` in ``namespace`` on ROS domain ``domain``, on a dyknow session.

    The session is the caller's (a manager's) and stays open when the node closes.
    """

    def __init__(self, session: Session, name: str, *, namespace: str = "/", domain: int = 0, types: TypeSupport | None = None) -> None:
        if not names.check_topic("/" + name, "ROS 2 node name").count("/") == 1:
            raise BindingError(f"node name {name!r}", where="ROS 2 node", expected="one name part, like 'dyknow_robot'")
        if namespace != "/":
            names.check_topic(namespace, "ROS 2 node namespace")
        if not 0 <= int(domain) <= 232:
            raise BindingError(f"domain {domain}", where="ROS 2 node", expected="a ROS_DOMAIN_ID from 0 to 232")
        self.session = session
        self.name = name
        self.namespace = namespace
        self.domain = int(domain)
        self.types = types or TypeSupport()
        self._ids = itertools.count(1)
        self.node_id = 0
        self._entities: list[Ros2Publisher | Ros2Subscription] = []
        self._lock = threading.Lock()
        self.entity_token = names.Entity(self.domain, session.zid, self.node_id, self.node_id, names.EntityKind.NODE, namespace, name)
        self._token: Any = session.declare_liveliness_token(self.entity_token.token())
        self._graph: Any = None  # one Graph for every watcher of this node (see watch_publishers)
        self._watchers: dict[int, tuple[str, Callable[[names.Entity, bool], None]]] = {}
        self._watch_ids = itertools.count(1)

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
    ) -> Ros2Subscription:
        """A subscription to ``topic``; ``ros_type`` None: of whatever type its publishers send."""
        self._check_open()
        sub = Ros2Subscription(self, topic, ros_type, qos, on_message, humble=humble)
        with self._lock:
            self._entities.append(sub)
        return sub

    def watch_publishers(self, topic: str, on_change: Callable[[names.Entity, bool], None]) -> Callable[[], None]:
        """Call ``on_change(entity, alive)`` as publishers of ``topic`` appear and vanish (their
        tokens; those up now first), on a Zenoh thread; returns the function that stops it. The
        node keeps one watch of the graph for all its watchers."""
        from dyknow.ros2.graph import Graph

        self._check_open()
        with self._lock:
            ident = next(self._watch_ids)
            self._watchers[ident] = (topic, on_change)
            graph = self._graph
            if graph is None:  # its history brings the tokens up now to every watcher
                self._graph = Graph(self.session, self.domain, self._graph_changed)
        if graph is not None:
            for entity in graph.view().publishers(topic):
                on_change(entity, True)

        def stop() -> None:
            with self._lock:
                self._watchers.pop(ident, None)

        return stop

    def _graph_changed(self, entity: names.Entity, alive: bool) -> None:
        if entity.kind is not names.EntityKind.PUBLISHER:
            return
        with self._lock:
            watchers = [fn for topic, fn in self._watchers.values() if topic == entity.topic]
        for fn in watchers:
            try:
                fn(entity, alive)
            except Exception:
                log.exception("a watcher of %s failed", entity.topic)

    def forget(self, entity: Ros2Publisher | Ros2Subscription) -> None:
        """Called by an entity that closed itself."""
        with self._lock:
            if entity in self._entities:
                self._entities.remove(entity)

    def close(self) -> None:
        """Close every publisher and subscription (the latest first), then the node's token; safe twice."""
        with self._lock:
            entities = list(reversed(self._entities))
        for entity in entities:
            entity.close()
        graph, self._graph = self._graph, None
        if graph is not None:
            graph.close()
        token, self._token = self._token, None
        if token is not None:
            token.undeclare()

    def __enter__(self) -> Ros2Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
