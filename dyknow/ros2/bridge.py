"""The units between dyknow streams and ROS 2 topics, on their manager's ROS 2 node.

- :class:`Ros2Source` takes a ROS 2 topic and publishes each message on its output ``out``;
- :class:`Ros2Sink` takes what arrives on its input ``in`` and publishes it on a ROS 2 topic;
- :class:`Ros2Server` serves a ROS 2 service on rmw_zenoh: a unit subclasses it and answers in
  :meth:`Ros2Server.handle`, on its own thread, beside its messages.

Both read the param ``binding``, a ``ros2:`` binding (:mod:`dyknow.ros2.binding`). A spec may
name them directly, so a ROS 2 topic becomes a tagged source the planner plans with::

    <transformation type="unit">
      <label>ros2-camera(top)</label>
      <source>dyknow.ros2.bridge:Ros2Source</source>
      <params><param name="binding" type="string">ros2:/camera/image_raw?type=sensor_msgs/msg/Image</param></params>
      <ports><port type="out">out</port></ports>
      <tags><tag port="out">RawRGB(top)</tag></tags>
    </transformation>

and a port bound to ``ros2:/TOPIC`` (in a spawn, ``set_config`` or ``--bind``) is wired by its
manager through one of them, spawned beside the unit as ``<unit>.<port>.ros2``.

Times. dyknow's header cannot ride on a ROS-facing key (ROS subscribers need rmw_zenoh's
attachment there), so the times travel by ROS's own fields: a message taken from ROS gets as its
origin time its ``header.stamp`` when its type has one and it is set, else the attachment's
source timestamp (when the ROS publisher sent it), else its arrival; dyknow's input ports then
measure age since that origin as for any stream. A message given to ROS gets the dyknow message's
origin time as its ``header.stamp`` when its type has a header the payload left unset, and the
send time as the attachment's source timestamp.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from dyknow.errors import BindingError
from dyknow.message import Message
from dyknow.ros2.binding import Ros2Binding, parse_binding
from dyknow.ros2.convert import COMPRESSED, from_message, stamp_ns, to_message
from dyknow.ros2.dds import DdsNode, DdsPublisher, DdsSubscription
from dyknow.ros2.names import Entity
from dyknow.ros2.node import Received, Ros2Node, Ros2Publisher, Ros2Subscription
from dyknow.ros2.services import Ros2Service
from dyknow.unit import Unit

__all__ = ["Ros2Provider", "Ros2Server", "Ros2Sink", "Ros2Source", "UsesRos2"]


class Ros2Provider(Protocol):
    """What a manager gives its ROS 2 units: its rmw_zenoh node and its DDS participant, each
    made on first use."""

    def ros2_node(self) -> Ros2Node:
        """The node on the manager's Zenoh session."""

    def dds_node(self) -> DdsNode:
        """The DDS participant."""


@runtime_checkable
class UsesRos2(Protocol):
    """A unit that needs its manager's ROS 2 middleware: the manager calls ``use_ros2`` before ``setup()``."""

    def use_ros2(self, provider: Ros2Provider) -> None:
        """Take the provider of the node or participant to declare publishers and subscriptions on."""


class _Ros2Unit(Unit):
    _provider: Ros2Provider | None = None

    def use_ros2(self, provider: Ros2Provider) -> None:
        """Take the manager's ROS 2 middleware (called by the manager before ``setup()``)."""
        self._provider = provider

    def _binding(self) -> tuple[Ros2Node | DdsNode, Ros2Binding]:
        binding = parse_binding(str(self.params.get("binding", "")), where=f"param 'binding' of unit {self.name!r}")
        provider = self._provider
        if provider is None:
            raise BindingError(
                "no ROS 2 middleware to publish or subscribe on", where=f"unit {self.name!r}", expected="a unit spawned by a manager"
            )
        return (provider.dds_node() if binding.dds else provider.ros2_node()), binding


class Ros2Source(_Ros2Unit):
    """Publishes on ``out`` every message of a ROS 2 topic, converted (:mod:`dyknow.ros2.convert`).

    ``refused`` counts the messages that could not be used (undecodable, of another type, an
    image that contradicts its sizes); ``last_refusal`` says why the latest was. ``publishers``
    is how many ROS 2 publishers of the topic are up (their liveliness tokens; on DDS, the
    matched writers). A message over the binding's ``max_bytes`` is dropped before it is copied
    (``oversized``), and messages are decoded and converted on the unit's own thread (its
    :meth:`~dyknow.unit.Unit.call_soon`), never on Zenoh's: see :class:`~dyknow.ros2.node.Ros2Subscription`.

    By default the source waits for publishers, and across their restarts (a port bound to a
    topic keeps its binding). With the param ``require_publisher`` true (a spec that offers a
    ROS 2 topic as a producer) it is a producer only while one is up: it waits up to ``wait_s``
    (default 2) for one at start and fails without, and fails when the last one goes, so the
    adaptation loop moves what it fed to another producer, keeps it in back-off while its
    publisher is gone and returns to it once it is back. Only publishers whose messages can reach
    it count (of its type and hash), and tokens of other topics are never looked at, so a flood
    of tokens cannot hide a real publisher (:class:`~dyknow.ros2.graph.PublisherWatch`).
    """

    refused = 0
    last_refusal: str | None = None
    _sub: Ros2Subscription | DdsSubscription | None = None
    _stop_watch: tuple[Callable[[], None], ...] = ()

    def setup(self) -> None:
        """Subscribe to the topic and watch its publishers (their tokens; on DDS, the matched writers)."""
        node, binding = self._binding()
        self.binding = binding
        self._publishers: set[tuple[str, int, int]] = set()
        self._present = threading.Event()
        self._seen_dds = 0
        self._mismatched = 0
        self._required = self.params.get("require_publisher") in (True, "true", "1")
        self._expected: tuple[str, str] | None = None  # (type, hash) a publisher must announce to reach us
        where = f"{binding.uri()} (unit {self.name!r})"
        if isinstance(node, DdsNode):
            self._sub = node.create_subscription(
                binding.topic,
                binding.ros_type,
                self._arrived,
                binding.qos,
                self._dds_matched,
                max_bytes=binding.max_bytes,
                call_soon=self.call_soon,
            )
        else:
            self._sub = node.create_subscription(
                binding.topic,
                binding.ros_type,
                self._arrived,
                binding.qos,
                humble=binding.humble,
                max_bytes=binding.max_bytes,
                call_soon=self.call_soon,
                where=where,
            )
            ros_type = self._sub.ros_type
            if ros_type is None:
                self._stop_watch = (node.watch_publishers(binding.topic, self._graph_changed),)
            else:
                type_hash = node.types.type_hash(ros_type, humble=binding.humble)
                self._expected = (ros_type, type_hash)
                self._stop_watch = (
                    node.watch_publishers(binding.topic, self._graph_changed, ros_type=ros_type, type_hash=type_hash),
                    node.watch_publishers(binding.topic, self._other_publisher),
                )
        if self._required:
            wait_s = float(self.params.get("wait_s", 2.0))
            if not self._present.wait(wait_s):
                self.teardown()
                raise BindingError(
                    f"no publisher of {binding.topic} within {wait_s} s",
                    where=f"unit {self.name!r}",
                    expected="a ROS 2 node publishing it (its liveliness token)"
                    + ("" if self._expected is None else f" of {self._expected[0]} with hash {self._expected[1]}"),
                )

    def _dds_matched(self, count: int) -> None:
        if count == 0 and self._seen_dds > 0 and self._required:
            self.fail(f"the DDS writers of rt{self.binding.topic} are gone")
        self._seen_dds = count
        if count:
            self._present.set()

    def _other_publisher(self, entity: Entity, alive: bool) -> None:
        expected = self._expected
        if not alive or expected is None or (entity.ros_type, entity.type_hash) == expected:
            return
        # its messages travel on another key: none will arrive here; say why (the first few, then
        # every 100th: tokens come from the network, and a flood of them must not flood the log)
        self._mismatched += 1
        if self._mismatched <= 3 or self._mismatched % 100 == 0:
            self.log.warning(
                "publisher %s of %s announces %s %s; this input takes %s %s, so none of its messages will match (%d such so far)",
                entity.node, self.binding.topic, entity.ros_type, entity.type_hash, *expected, self._mismatched,
            )  # fmt: skip

    def _graph_changed(self, entity: Entity, alive: bool) -> None:
        ident = (entity.session_id, entity.node_id, entity.entity_id)
        if alive:
            self._publishers.add(ident)
            self._present.set()
        elif ident in self._publishers:
            self._publishers.discard(ident)
            if not self._publishers and self._required:
                self.fail(f"the ROS 2 publishers of {self.binding.topic} are gone (their liveliness tokens vanished)")

    @property
    def publishers(self) -> int:
        """How many ROS 2 publishers of the topic are alive now."""
        return self._seen_dds if isinstance(self._sub, DdsSubscription) else len(self._publishers)

    def _arrived(self, received: Received) -> None:  # on the unit's thread (call_soon)
        try:
            payload = from_message(received.message, received.ros_type, decode=self.binding.decode)
        except BindingError as exc:
            self.refused += 1
            self.last_refusal = str(exc)
            self.log.warning("refused a message from %s: %s", self.binding.topic, exc)
            return
        origin = stamp_ns(received.message) or received.attachment.source_timestamp_ns or received.arrival_ns
        self.publish("out", payload, origin_ns=origin)

    @property
    def oversized(self) -> int:
        """Messages dropped for being over the binding's ``max_bytes``, before they were copied."""
        return self._sub.oversized if self._sub is not None else 0

    @property
    def max_bytes(self) -> int:
        """The largest message taken: the binding's ``max_bytes``, else the manager's bound."""
        return self._sub.max_bytes if self._sub is not None else 0

    @property
    def dropped(self) -> int:
        """Messages dropped undecoded because newer ones filled the queue (rmw_zenoh; keep-last ``depth``)."""
        sub = self._sub
        return sub.dropped if isinstance(sub, Ros2Subscription) else 0

    @property
    def transport_refused(self) -> int:
        """Messages the subscription refused before conversion (too large, bad key, hash, attachment or CDR)."""
        return self._sub.refused if self._sub is not None else 0

    def teardown(self) -> None:
        """Stop watching, unsubscribe; safe twice."""
        stops, self._stop_watch = self._stop_watch, ()
        for stop in stops:
            stop()
        sub, self._sub = self._sub, None
        if sub is not None:
            sub.close()


class Ros2Sink(_Ros2Unit):
    """Publishes on a ROS 2 topic every message arriving on ``in``, converted; a payload that does
    not fit the type is rejected (counted on ``in``) and the unit carries on. ``bytes`` for a type
    other than ``CompressedImage`` are taken as CDR of that type: checked, then sent as they are."""

    _pub: Ros2Publisher | DdsPublisher | None = None

    def setup(self) -> None:
        """Declare the publisher."""
        node, binding = self._binding()
        if binding.ros_type is None:
            raise BindingError(
                f"{binding.uri()} names no type",
                where=f"unit {self.name!r}",
                expected=f"ros2:{binding.topic}?type=pkg/msg/Type for an output",
            )
        self.binding = binding
        self._types = node.types
        if isinstance(node, DdsNode):
            self._pub = node.create_publisher(binding.topic, binding.ros_type, binding.qos)
        else:
            self._pub = node.create_publisher(binding.topic, binding.ros_type, binding.qos, humble=binding.humble)

    def on_message(self, port: str, msg: Message) -> None:
        """Convert and publish."""
        pub = self._pub
        if pub is None:
            return
        ros_type = self.binding.ros_type
        assert ros_type is not None
        payload: Any = msg.payload
        try:
            if isinstance(payload, bytes) and ros_type != COMPRESSED:
                self._types.deserialize(payload, ros_type)  # checked before it goes out
                pub.publish_cdr(payload)
                return
            message = to_message(payload, ros_type, self._types, origin_ns=msg.origin_ns, frame_id=self.binding.frame_id)
            pub.publish(message)
        except BindingError as exc:
            self.reject(port, str(exc))

    def teardown(self) -> None:
        """Undeclare the publisher."""
        if self._pub is not None:
            self._pub.close()


class Ros2Server(_Ros2Unit):
    """A unit that serves one ROS 2 service on its manager's rmw_zenoh node: the params
    ``service`` (its name, like ``/robot/get_state``) and ``type`` (``pkg/srv/Name``) choose it,
    and a subclass answers each request in :meth:`handle`. ``handle`` runs on the unit's own
    thread (its :meth:`~dyknow.unit.Unit.call_soon`), between its messages, so it may read and
    change the unit's state and publish; what it raises answers nothing and is logged (the
    caller's timeout tells it). ``ros2_service`` is the :class:`~dyknow.ros2.services.Ros2Service`
    (its counters: ``received``, ``answered``, ``refused``, ``failed``). Any other unit serves a
    service the same way: implement ``use_ros2`` (:class:`UsesRos2`) and call
    ``provider.ros2_node().create_service(..., call_soon=self.call_soon)`` in ``setup``, closing it
    in ``teardown``. (Over DDS, rclpy's clients on Fast DDS would not take the answers: see
    :class:`~dyknow.ros2.dds.DdsService`.)
    """

    ros2_service: Ros2Service | None = None

    def setup(self) -> None:
        """Declare the service."""
        provider = self._provider
        if provider is None:
            raise BindingError("no ROS 2 node to serve on", where=f"unit {self.name!r}", expected="a unit spawned by a manager")
        service, srv_type = str(self.params.get("service", "")), str(self.params.get("type", ""))
        self.ros2_service = provider.ros2_node().create_service(service, srv_type, self.handle, call_soon=self.call_soon)

    def handle(self, request: Any) -> Any:
        """Answer ``request`` (a message object of the request type): return the response, a
        message object or a dict of its fields. Subclasses implement it."""
        raise NotImplementedError(f"{type(self).__name__}.handle: a Ros2Server subclass answers the requests")

    def teardown(self) -> None:
        """Undeclare the service (its token, then its queryable)."""
        if self.ros2_service is not None:
            self.ros2_service.close()
