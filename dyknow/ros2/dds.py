"""ROS 2 over DDS (its default middleware), through Cyclone DDS's Python binding.

ROS 2's DDS conventions (rmw_fastrtps and rmw_cyclonedds alike): a topic ``/chatter`` is the DDS
topic ``rt/chatter``; its type is named ``std_msgs::msg::dds_::String_``; samples are the same
CDR (XCDR1, with the encapsulation header) as on rmw_zenoh. The DDS types are built on the fly
from the definitions of :class:`~dyknow.ros2.types.TypeSupport` (one ``IdlStruct`` per ROS type,
nested types included), and a sample is handed over as its CDR bytes, so one codec
(:mod:`dyknow.ros2.types`) reads and writes both middlewares.

Discovery stays on loopback unless told otherwise (dyknow's default): a participant uses
:data:`LOOPBACK_CONFIG` (unicast to 127.0.0.1, no multicast), which ROS 2 nodes reach with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; give a Cyclone XML configuration to join a network.
DDS has no rmw_zenoh attachment: a received sample's :class:`Received` carries the DDS source
timestamp, sequence number 0 and a zero GID.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dyknow.errors import BindingError, ClosedError
from dyknow.ros2.attachment import Attachment
from dyknow.ros2.names import DEFAULT_QOS, Durability, QoS, Reliability, check_topic, dds_type_name, ros_type_name
from dyknow.ros2.node import DEFAULT_MAX_MESSAGE_BYTES, UNTYPED_MAX_MESSAGE_BYTES, Received
from dyknow.ros2.types import MAX_CDR_BYTES, TypeSupport

__all__ = ["FASTDDS_PROFILE", "LOOPBACK_CONFIG", "DdsNode", "DdsPublisher", "DdsSubscription"]

log = logging.getLogger(__name__)

#: A Fast DDS profile for the ROS 2 nodes that talk to dyknow over DDS
#: (``FASTDDS_DEFAULT_PROFILES_FILE``): it turns Fast DDS's type propagation off. Fast DDS 3
#: sends type objects for sequences of plain types (an Image's ``data``) that Cyclone 11 refuses
#: ("invalid type object"), and then such a topic never matches; without type objects it matches
#: by type name, as ROS 2 names types. Strings and other types without such sequences need it not.
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_profile.xml")

#: The most publications and subscriptions :meth:`DdsNode.topics` reads.
MAX_DISCOVERED = 10_000

#: Cyclone DDS on loopback only: unicast discovery to 127.0.0.1 (participant indices 0 to 30), and
#: datagrams of up to 64 kB (loopback's MTU; Cyclone's default 14 kB made a 640x480 image some 700
#: datagrams, and cost the relay of benchmarks/ros2.py about 0.4 ms more CPU per frame). A
#: configuration for a real network keeps Cyclone's defaults there (an Ethernet MTU is 1,500).
LOOPBACK_CONFIG = (
    '<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
    "<AllowMulticast>false</AllowMulticast><MaxMessageSize>65500B</MaxMessageSize><FragmentSize>64000B</FragmentSize></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    '<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
)


@functools.cache
def _raw_entities() -> tuple[Any, Any]:
    """Cyclone's DataWriter and DataReader with a raw CDR write and take: what ``write`` and
    ``take`` do around the ``IdlStruct`` (de)serialization they skip, through the same C layer.
    An ``IdlStruct`` costs a Python int per byte of an image (15 ms a 640x480 frame)."""
    from cyclonedds._clayer import ddspy_take, ddspy_write  # type: ignore[import-not-found]  # (Cyclone's C layer ships no stubs)
    from cyclonedds.core import InstanceState, SampleState, ViewState
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader

    class RawWriter(DataWriter):  # type: ignore[misc]
        def write_cdr(self, data: bytes) -> int:
            return int(ddspy_write(self._ref, data.ljust((len(data) + 3) & ~3, b"\0")))

    class RawReader(DataReader):  # type: ignore[misc]
        def take_cdr(self, n: int) -> list[tuple[bytes, Any]]:
            taken = ddspy_take(self._ref, SampleState.Any | ViewState.Any | InstanceState.Any, n)
            return [] if isinstance(taken, int) else [(bytes(data), info) for data, info in taken]

    return RawWriter, RawReader


# Cyclone configures a domain once per process: every participant of it shares that configuration
_domains: dict[int, tuple[str, Any]] = {}
_domains_lock = threading.Lock()


def _domain(domain: int, config: str) -> Any:
    from cyclonedds.domain import Domain

    with _domains_lock:
        found = _domains.get(domain)
        if found is None:
            found = _domains[domain] = (config, Domain(domain, config))
        elif found[0] != config:
            raise BindingError(
                f"DDS domain {domain} is configured already in this process, otherwise",
                where="DDS participant",
                expected="the same Cyclone configuration for every manager of this process on that domain",
            )
        return found[1]


def _qos(qos: QoS) -> Any:
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    return Qos(
        Policy.Reliability.Reliable(duration(seconds=1)) if qos.reliability is Reliability.RELIABLE else Policy.Reliability.BestEffort,
        Policy.Durability.TransientLocal if qos.durability is Durability.TRANSIENT_LOCAL else Policy.Durability.Volatile,
        Policy.History.KeepAll if qos.keep_all else Policy.History.KeepLast(qos.depth),
        # XCDR1, as ROS 2's DDS middlewares write; and match by type name when the peer's type
        # object cannot be read (Cyclone refuses Fast DDS's for sequences of plain types)
        Policy.DataRepresentation(use_cdrv0_representation=True),
        Policy.TypeConsistency.AllowTypeCoercion(force_type_validation=False),
    )


class DdsPublisher:
    """Writes one ROS 2 topic of one type. A context manager; ``close()`` is safe twice."""

    def __init__(self, node: DdsNode, topic: str, ros_type: str, qos: QoS) -> None:
        raw_writer, _ = _raw_entities()
        self.topic = check_topic(topic)
        self.ros_type = node.types.check(ros_type)
        self._types = node.types
        self._writer: Any = raw_writer(node.participant, node.dds_topic(topic, ros_type), qos=_qos(qos))
        self._node = node

    def publish(self, message: Any) -> None:
        """Serialize and write a message object."""
        self.publish_cdr(self._types.serialize(message, self.ros_type))

    def publish_cdr(self, data: bytes) -> None:
        """Write CDR bytes (with their encapsulation header) as they are."""
        writer = self._writer
        if writer is None:
            raise ClosedError("the writer is closed", where=f"DDS writer on rt{self.topic}", expected="a new publisher")
        ret = writer.write_cdr(data)
        if ret < 0:
            raise BindingError(f"Cyclone DDS returned {ret}", where=f"writing rt{self.topic}")

    def close(self) -> None:
        """Delete the writer; safe twice."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.__del__()  # Cyclone deletes an entity there (idempotent); dropping the reference may not
        self._node.forget(self)

    def __enter__(self) -> DdsPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DdsSubscription:
    """Reads one ROS 2 topic of one type: ``on_message(Received)`` for each sample; samples that
    do not decode, or are over ``max_bytes`` (dropped before they are decoded), are counted in
    ``refused``. ``publishers`` is the number of matched writers; ``on_publishers(count)`` is
    called when it changes. With ``call_soon`` (a unit's), Cyclone's thread only says that data
    is there and the samples are taken and decoded where ``call_soon`` runs them; without, on
    Cyclone's thread."""

    def __init__(
        self,
        node: DdsNode,
        topic: str,
        ros_type: str,
        qos: QoS,
        on_message: Callable[[Received], None],
        on_publishers: Callable[[int], None] | None = None,
        *,
        max_bytes: int | None = None,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
    ) -> None:
        from cyclonedds.core import Listener

        _, raw_reader = _raw_entities()

        self.topic = check_topic(topic)
        self.ros_type = node.types.check(ros_type)
        self.max_bytes = node.max_message_bytes if max_bytes is None else max_bytes
        if not 0 < self.max_bytes <= MAX_CDR_BYTES:
            raise BindingError(
                f"max_bytes {self.max_bytes}", where=f"DDS subscription on {self.topic}", expected=f"from 1 to {MAX_CDR_BYTES}"
            )
        self.received = 0
        self.refused = 0
        self.oversized = 0
        self.last_refusal: str | None = None
        self.publishers = 0
        self._types = node.types
        self._on_message = on_message
        self._lock = threading.Lock()
        self._pending = False
        key = "rt" + topic
        subscription = self

        def take() -> None:
            with subscription._lock:
                subscription._pending = False
            reader = subscription._reader
            if reader is not None:
                subscription._take(reader, key)

        class _Listener(Listener):  # type: ignore[misc]
            def on_data_available(self, reader: Any) -> None:
                if call_soon is None:
                    subscription._take(reader, key)
                    return
                with subscription._lock:
                    schedule = not subscription._pending
                    subscription._pending = True
                if schedule:
                    call_soon(take)

            def on_subscription_matched(self, reader: Any, status: Any) -> None:
                subscription.publishers = int(status.current_count)
                if on_publishers is not None:
                    on_publishers(subscription.publishers)

        self._reader: Any = raw_reader(node.participant, node.dds_topic(topic, ros_type), qos=_qos(qos), listener=_Listener())
        self._node = node

    def _refuse(self, why: str, *, oversized: bool = False) -> None:
        with self._lock:
            self.refused += 1
            self.oversized += oversized
            self.last_refusal = why
            count = self.refused
        if count <= 3 or count % 100 == 0:  # a stream of bad samples must not flood the log
            log.warning("DDS subscription on %s refused a sample (%d so far): %s", self.topic, count, why)

    def _take(self, reader: Any, key: str) -> None:
        while True:
            taken = reader.take_cdr(64)  # raw CDR: the one codec reads it
            if not taken:
                return
            for data, info in taken:
                arrival = time.time_ns()
                try:
                    if not info.valid_data:
                        continue
                    if len(data) > self.max_bytes:
                        self._refuse(
                            f"a sample of {len(data)} bytes, over the limit of {self.max_bytes} (raise it with max_bytes= in the binding)",
                            oversized=True,
                        )
                        continue
                    message = self._types.deserialize(data, self.ros_type)
                except BindingError as exc:
                    self._refuse(str(exc))
                    continue
                except Exception as exc:  # the binding's own errors: counted the same way
                    self._refuse(f"{type(exc).__name__}: {exc}")
                    continue
                with self._lock:
                    self.received += 1
                try:
                    self._on_message(Received(message, self.ros_type, Attachment(0, int(info.source_timestamp), bytes(16)), arrival, key))
                except Exception:
                    log.exception("DDS subscription on %s: on_message failed", self.topic)
            if len(taken) < 64:
                return

    def close(self) -> None:
        """Delete the reader; safe twice."""
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.__del__()  # as DdsPublisher.close
        self._node.forget(self)

    def __enter__(self) -> DdsSubscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DdsNode:
    """A DDS domain participant for ROS 2 topics of ROS domain ``domain``.

    ``config``: a Cyclone DDS XML configuration (default :data:`LOOPBACK_CONFIG`);
    ``max_message_bytes``: the largest sample a subscription decodes unless told otherwise.
    """

    def __init__(
        self,
        *,
        domain: int = 0,
        config: str | None = None,
        types: TypeSupport | None = None,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    ) -> None:
        try:
            from cyclonedds.domain import DomainParticipant
        except ImportError as exc:
            raise BindingError(
                "Cyclone DDS's Python binding is not installed", where="ros2dds binding", expected="pip install 'dyknow[ros2]'"
            ) from exc
        if not 0 <= int(domain) <= 232:
            raise BindingError(f"domain {domain}", where="DDS participant", expected="a ROS_DOMAIN_ID from 0 to 232")
        self.domain = int(domain)
        self.types = types or TypeSupport()
        self.max_message_bytes = max_message_bytes  # what a subscription takes unless told otherwise
        self._domain = _domain(self.domain, config or LOOPBACK_CONFIG)
        self.participant: Any = DomainParticipant(self.domain)
        self._classes: dict[str, Any] = {}
        self._topics: dict[tuple[str, str], Any] = {}
        self._entities: list[DdsPublisher | DdsSubscription] = []
        self._lock = threading.RLock()
        self._closed = False

    def idl_type(self, ros_type: str) -> Any:
        """The Cyclone ``IdlStruct`` class of ``ros_type`` (built once, nested types first)."""
        from cyclonedds.idl import make_idl_struct
        from cyclonedds.idl import types as t
        from rosbags.interfaces import Nodetype

        with self._lock:
            cls = self._classes.get(ros_type)
            if cls is not None:
                return cls
            base = {
                "bool": bool,
                "byte": t.byte,
                "char": t.uint8,
                "int8": t.int8,
                "uint8": t.uint8,
                "int16": t.int16,
                "uint16": t.uint16,
                "int32": t.int32,
                "uint32": t.uint32,
                "int64": t.int64,
                "uint64": t.uint64,
                "float32": t.float32,
                "float64": t.float64,
                "string": str,
            }

            def field_type(desc: Any) -> Any:
                node, rest = desc
                if node == Nodetype.NAME:
                    return self.idl_type(rest)
                if node == Nodetype.BASE:
                    if rest[0] == "string" and rest[1]:
                        return t.bounded_str[rest[1]]  # type: ignore[misc]  # (cyclonedds's IDL types are generic at run time; its stubs do not say so)
                    if rest[0] not in base:
                        raise BindingError(f"field type {rest[0]}", where=f"type {ros_type}", expected="a type DDS can carry here")
                    return base[rest[0]]
                inner, count = rest
                if node == Nodetype.ARRAY:
                    return t.array[field_type(inner), count]  # type: ignore[misc]  # (cyclonedds's IDL types are generic at run time; its stubs do not say so)
                return t.sequence[field_type(inner), count] if count else t.sequence[field_type(inner)]  # type: ignore[misc]  # (cyclonedds's IDL types are generic at run time; its stubs do not say so)

            fields = {name: field_type(desc) for name, desc in self.types.field_definitions(ros_type)} or {
                "structure_needs_at_least_one_member": t.uint8
            }
            name = ros_type.rsplit("/", 1)[1] + "_"
            cls = make_idl_struct(name, dds_type_name(ros_type), fields)
            self._classes[ros_type] = cls
            return cls

    def dds_topic(self, topic: str, ros_type: str) -> Any:
        """The DDS topic ``rt<topic>`` of ``ros_type`` (one per name and type)."""
        from cyclonedds.topic import Topic

        with self._lock:
            if self._closed:
                raise ClosedError("the DDS participant is closed", where="ros2dds", expected="a new participant")
            found = self._topics.get((topic, ros_type))
            if found is None:
                found = self._topics[(topic, ros_type)] = Topic(self.participant, "rt" + check_topic(topic), self.idl_type(ros_type))
            return found

    def topics(self, *, wait_s: float = 1.0) -> dict[str, list[str]]:
        """The ROS 2 topics the DDS writers and readers of this domain carry (``rt/`` topics with
        ROS type names), topic -> types, after discovery had ``wait_s`` to bring them."""
        from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription

        with self._lock:
            if self._closed:
                raise ClosedError("the DDS participant is closed", where="ros2dds", expected="a new participant")
            readers = [BuiltinDataReader(self.participant, t) for t in (BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription)]
        time.sleep(wait_s)  # DDS discovery has no "done": what came within the wait
        found: dict[str, set[str]] = {}
        for reader in readers:
            for sample in reader.read(N=MAX_DISCOVERED):
                name, type_name = str(getattr(sample, "topic_name", "")), str(getattr(sample, "type_name", ""))
                if not name.startswith("rt/"):
                    continue  # not a ROS 2 topic (rq/, rr/ are services; others are not ROS's)
                try:
                    found.setdefault(check_topic(name[2:]), set()).add(ros_type_name(type_name))
                except BindingError:
                    log.debug("ignoring DDS topic %r of type %r", name[:200], type_name[:200])
            reader.__del__()  # as DdsPublisher.close
        return {topic: sorted(types) for topic, types in sorted(found.items())}

    def create_publisher(self, topic: str, ros_type: str, qos: QoS = DEFAULT_QOS) -> DdsPublisher:
        """A writer of ``ros_type`` on ``topic``."""
        pub = DdsPublisher(self, topic, ros_type, qos)
        with self._lock:
            self._entities.append(pub)
        return pub

    def create_subscription(
        self,
        topic: str,
        ros_type: str | None,
        on_message: Callable[[Received], None],
        qos: QoS = DEFAULT_QOS,
        on_publishers: Callable[[int], None] | None = None,
        *,
        max_bytes: int | None = None,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
    ) -> DdsSubscription:
        """A reader of ``topic``; ``ros_type`` None: the one known type its writers announce
        (discovery is given 2 s), else :class:`BindingError`. ``max_bytes`` and ``call_soon``:
        as :class:`DdsSubscription` takes them."""
        if ros_type is None:
            announced = [t for t in self.topics(wait_s=2.0).get(check_topic(topic), []) if self.types.known(t)]
            if len(announced) != 1:
                raise BindingError(
                    f"ros2dds:{topic} names no type, and its DDS writers announced {announced or 'none'} within 2 s",
                    where="DDS subscription",
                    expected=f"ros2dds:{topic}?type=pkg/msg/Type",
                )
            ros_type = announced[0]
            if max_bytes is None:  # the writers chose the type: the tighter bound
                max_bytes = min(self.max_message_bytes, UNTYPED_MAX_MESSAGE_BYTES)
        sub = DdsSubscription(self, topic, ros_type, qos, on_message, on_publishers, max_bytes=max_bytes, call_soon=call_soon)
        with self._lock:
            self._entities.append(sub)
        return sub

    def forget(self, entity: DdsPublisher | DdsSubscription) -> None:
        """Called by an entity that closed itself."""
        with self._lock:
            if entity in self._entities:
                self._entities.remove(entity)

    def close(self) -> None:
        """Close every reader and writer (the latest first), then the participant; safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = list(reversed(self._entities))
        for entity in entities:
            entity.close()
        self._topics.clear()
        participant, self.participant = self.participant, None
        participant.__del__()  # deletes what is left under it

    def __enter__(self) -> DdsNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
