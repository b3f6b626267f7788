"""rmw_zenoh's names on the wire: topic keys, liveliness tokens, QoS strings and GIDs.

The one home of rmw_zenoh's key layout in dyknow (the rest builds keys through here). As
rmw_zenoh's ``docs/design.md`` states it (and ``liveliness_utils.cpp`` writes it):

- a topic's data key is ``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``, the name
  without its leading ``/``, the type as DDS names it (``std_msgs::msg::dds_::String_``) and the
  hash as REP-2016 writes it (``RIHS01_<64 hex>``; Humble writes ``TypeHashNotSupported``);
- an entity's liveliness token is
  ``@ros2_lv/<domain_id>/<session_id>/<node_id>/<entity_id>/<kind>/<enclave>/<namespace>/<node_name>``
  for a node (``NN``; ``<entity_id>`` is the node's id), followed by
  ``/<topic>/<type_name>/<type_hash>/<qos>`` for a publisher (``MP``), subscription (``MS``),
  service (``SS``) or client (``SC``); names are *mangled*: every ``/`` becomes ``%`` (so an empty
  namespace or enclave is ``%``);
- ``<qos>`` is ``R:D:H,DEPTH:DS,DNS:LS,LNS:L,LLS,LLNS`` where each field that equals rmw_zenoh's
  default (reliable, volatile, keep-last, depth 42, infinite durations, automatic liveliness) is
  left empty; the enum values are rmw's (reliable 1, best effort 2; transient local 1, volatile 2;
  keep last 1, keep all 2);
- a service's key is a topic's (``<domain_id>/<service name>/<type_name>/<type_hash>``), with the
  service type's DDS name (``lifecycle_msgs::srv::dds_::ChangeState_``) and its hash: a server is
  a queryable there, a client's request a query carrying the attachment, and the reply carries
  it back (:mod:`dyknow.ros2.services`);
- over DDS, a service ``/a/b`` is the request topic ``rq/a/bRequest`` and the reply topic
  ``rr/a/bReply``, of the types ``pkg::srv::dds_::Name_Request_`` and ``..._Response_``;
- an entity's GID is the XXH3 128-bit hash of its token: the low 64 bits then the high 64 bits,
  each in the machine's (little-endian) byte order, 16 bytes.

Everything parsed here comes from the network: tokens and keys are bounded and checked part by
part, and a bad one raises :class:`~dyknow.errors.BindingError` naming the part.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import Enum, StrEnum

from dyknow.errors import BindingError

__all__ = [
    "ADMIN_SPACE",
    "DEFAULT_QOS",
    "HASH_NOT_SUPPORTED",
    "MAX_TOKEN_BYTES",
    "Durability",
    "EntityKind",
    "Entity",
    "QoS",
    "Reliability",
    "check_topic",
    "data_key",
    "dds_type_name",
    "dds_reply_topic",
    "dds_request_topic",
    "demangle",
    "endpoint_pattern",
    "entity_gid",
    "every_service",
    "every_token",
    "mangle",
    "parse_data_key",
    "parse_token",
    "publisher_pattern",
    "ros_type_name",
    "topic_pattern",
]

#: The admin space of rmw_zenoh's liveliness tokens (a verbatim chunk).
ADMIN_SPACE = "@ros2_lv"
#: What Humble (no type hashes) writes in place of a type hash.
HASH_NOT_SUPPORTED = "TypeHashNotSupported"
#: The longest token or key read from the network (bytes).
MAX_TOKEN_BYTES = 2048

_TOPIC_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_ROS_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Z][A-Za-z0-9_]*)")
_DDS_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)::(msg|srv|action)::dds_::([A-Z][A-Za-z0-9_]*)_")
_HASH = re.compile(r"RIHS01_[0-9a-f]{64}")
_NUMBER = re.compile(r"[0-9]{1,20}")


class EntityKind(StrEnum):
    """The kinds of entity a token announces."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class Reliability(int, Enum):
    """rmw's reliability values."""

    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(int, Enum):
    """rmw's durability values."""

    TRANSIENT_LOCAL = 1
    VOLATILE = 2


_KEEP_LAST, _KEEP_ALL = 1, 2
_INFINITE = (9223372036, 854775807)  # RMW_DURATION_INFINITE as (sec, nsec)


@dataclass(frozen=True, slots=True)
class QoS:
    """The QoS of a publisher or subscription, as far as dyknow uses it (reliability, durability,
    keep-last depth or keep-all); deadline, lifespan and liveliness stay rmw_zenoh's defaults."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    depth: int = 10
    keep_all: bool = False

    def encode(self) -> str:
        """The token's QoS field, default fields left empty as rmw_zenoh writes them."""
        rel = "" if self.reliability is Reliability.RELIABLE else str(int(self.reliability))
        dur = "" if self.durability is Durability.VOLATILE else str(int(self.durability))
        history = str(_KEEP_ALL) if self.keep_all else ""
        depth = "" if self.depth == 42 else str(self.depth)
        return f"{rel}:{dur}:{history},{depth}:,:,:,,"

    @classmethod
    def decode(cls, text: str) -> QoS:
        """Read a token's QoS field; raises :class:`BindingError` naming the bad part."""
        parts = text.split(":")
        if len(parts) != 6:
            raise BindingError(f"QoS {text[:80]!r} has {len(parts)} ':'-separated fields", where="liveliness token", expected="6")
        history = parts[2].split(",")
        if len(history) != 2:
            raise BindingError(f"QoS history {parts[2][:40]!r}", where="liveliness token", expected="KIND,DEPTH")
        try:
            reliability = Reliability(int(parts[0])) if parts[0] else Reliability.RELIABLE
            durability = Durability(int(parts[1])) if parts[1] else Durability.VOLATILE
            kind = int(history[0]) if history[0] else _KEEP_LAST
            if not history[1]:
                depth = 42
            elif _NUMBER.fullmatch(history[1]):
                depth = int(history[1])
            else:
                raise ValueError(history[1])
        except ValueError as exc:
            raise BindingError(f"QoS {text[:80]!r}: {exc}", where="liveliness token", expected="rmw's enum values and a depth") from exc
        if kind not in (_KEEP_LAST, _KEEP_ALL):
            raise BindingError(f"QoS history kind {kind}", where="liveliness token", expected="1 (keep last) or 2 (keep all)")
        return cls(reliability, durability, depth, kind == _KEEP_ALL)


#: rclpy's and rclcpp's default for a publisher or subscription given a depth of 10.
DEFAULT_QOS = QoS()


def check_topic(topic: str, what: str = "ROS 2 topic") -> str:
    """Return ``topic`` if it is a fully qualified ROS 2 topic name (``/ns/name``); else raise
    :class:`BindingError` naming ``what``."""
    if not isinstance(topic, str) or not topic.startswith("/") or topic == "/" or topic.endswith("/") or len(topic) > 512:
        raise BindingError(
            f"{str(topic)[:80]!r} is not a fully qualified topic name",
            where=what,
            expected="a name like '/chatter' or '/robot1/camera/image_raw'",
        )
    bad = next((t for t in topic[1:].split("/") if not _TOPIC_TOKEN.fullmatch(t)), None)
    if bad is not None:
        raise BindingError(
            f"{topic[:80]!r} has the part {bad[:40]!r}",
            where=what,
            expected="parts of letters, digits and '_', not starting with a digit, separated by single '/'",
        )
    return topic


def dds_type_name(ros_type: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs::msg::dds_::String_``."""
    m = _ROS_TYPE.fullmatch(ros_type)
    if m is None:
        raise BindingError(f"type {ros_type[:80]!r}", where="ROS 2 type", expected="a name like 'std_msgs/msg/String'")
    return f"{m[1]}::{m[2]}::dds_::{m[3]}_"


def ros_type_name(dds_type: str) -> str:
    """``std_msgs::msg::dds_::String_`` -> ``std_msgs/msg/String``."""
    m = _DDS_TYPE.fullmatch(dds_type)
    if m is None:
        raise BindingError(f"type {dds_type[:80]!r}", where="ROS 2 type on the wire", expected="a name like 'std_msgs::msg::dds_::String_'")
    return f"{m[1]}/{m[2]}/{m[3]}"


def _check_hash(type_hash: str, where: str) -> str:
    if type_hash != HASH_NOT_SUPPORTED and not _HASH.fullmatch(type_hash):
        raise BindingError(f"type hash {type_hash[:80]!r}", where=where, expected=f"RIHS01_ and 64 hex digits, or {HASH_NOT_SUPPORTED}")
    return type_hash


def data_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The Zenoh key a topic's messages travel on (``0/chatter/std_msgs::msg::dds_::String_/RIHS01_...``)."""
    return f"{int(domain)}/{check_topic(topic)[1:]}/{dds_type_name(ros_type)}/{_check_hash(type_hash, 'data key')}"


def topic_pattern(domain: int, topic: str) -> str:
    """A key expression for a topic's messages of any type: ``<domain>/<topic>/*/*``."""
    return f"{int(domain)}/{check_topic(topic)[1:]}/*/*"


def publisher_pattern(domain: int, topic: str, ros_type: str | None = None, type_hash: str | None = None) -> str:
    """A key expression for the liveliness tokens of ``topic``'s publishers (of ``ros_type`` with
    ``type_hash`` when given, else of any type): what a watch of one topic subscribes to, so that
    tokens of other topics never reach it."""
    kind = f"{ADMIN_SPACE}/{int(domain)}/*/*/*/{EntityKind.PUBLISHER.value}/*/*/*/{mangle(check_topic(topic))}"
    if ros_type is None:
        return f"{kind}/*/*/*"
    return f"{kind}/{dds_type_name(ros_type)}/{_check_hash(type_hash or '', 'publisher pattern')}/*"


def endpoint_pattern(domain: int, name: str, kind: EntityKind, ros_type: str | None = None, type_hash: str | None = None) -> str:
    """A key expression for the liveliness tokens of the endpoints of ``kind`` on topic or
    service ``name`` (of ``ros_type`` with ``type_hash`` when given, else of any type)."""
    head = f"{ADMIN_SPACE}/{int(domain)}/*/*/*/{kind.value}/*/*/*/{mangle(check_topic(name))}"
    if ros_type is None:
        return f"{head}/*/*/*"
    return f"{head}/{dds_type_name(ros_type)}/{_check_hash(type_hash or '', 'endpoint pattern')}/*"


def every_service(last: str) -> str:
    """A key expression for every node's service whose name ends in ``last``
    (``change_state``), in any domain and of any type: ``*/**/change_state/*/*``. Each node serves
    its lifecycle, parameter and mode services under its own name (``/camera_top/change_state``),
    so this is how an access control names one kind of them (:mod:`dyknow.access`)."""
    if not _TOPIC_TOKEN.fullmatch(last):
        raise BindingError(f"{last[:80]!r}", where="ROS 2 service name", expected="the last part of a service's name, such as change_state")
    return f"*/**/{last}/*/*"


def every_token(kind: EntityKind | None = None) -> str:
    """A key expression for the liveliness tokens of every entity of ``kind`` (None: of every
    kind, the whole graph) in any domain: ``@ros2_lv/*/*/*/*/SC/**``."""
    return f"{ADMIN_SPACE}/**" if kind is None else f"{ADMIN_SPACE}/*/*/*/*/{kind.value}/**"


def dds_request_topic(service: str) -> str:
    """The DDS topic of a service's requests: ``/a/b`` -> ``rq/a/bRequest``."""
    return f"rq{check_topic(service, 'ROS 2 service')}Request"


def dds_reply_topic(service: str) -> str:
    """The DDS topic of a service's replies: ``/a/b`` -> ``rr/a/bReply``."""
    return f"rr{check_topic(service, 'ROS 2 service')}Reply"


def parse_data_key(key: str) -> tuple[int, str, str, str]:
    """``(domain, topic, ros_type, type_hash)`` of a data key; raises :class:`BindingError`."""
    if len(key) > MAX_TOKEN_BYTES:
        raise BindingError(f"a key of {len(key)} bytes", where="ROS 2 data key", expected=f"at most {MAX_TOKEN_BYTES}")
    parts = key.split("/")
    if len(parts) < 4 or not _NUMBER.fullmatch(parts[0]):
        raise BindingError(f"{key[:120]!r}", where="ROS 2 data key", expected="<domain>/<topic>/<type>/<hash>")
    topic = check_topic("/" + "/".join(parts[1:-2]), "ROS 2 data key")
    return int(parts[0]), topic, ros_type_name(parts[-2]), _check_hash(parts[-1], "ROS 2 data key")


def mangle(name: str) -> str:
    """A name as a token chunk: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def demangle(chunk: str) -> str:
    """A token chunk back as a name: every ``%`` becomes ``/``."""
    return chunk.replace("%", "/")


@dataclass(frozen=True, slots=True)
class Entity:
    """One entity of the ROS 2 graph, as its liveliness token announces it.

    ``topic``, ``ros_type``, ``type_hash`` and ``qos`` are set for every kind but a node.
    """

    domain: int
    session_id: str
    node_id: int
    entity_id: int
    kind: EntityKind
    namespace: str
    node_name: str
    enclave: str = "/"
    topic: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None
    qos: QoS | None = None

    @property
    def node(self) -> str:
        """The node's fully qualified name (``/ns/name``)."""
        return self.namespace.rstrip("/") + "/" + self.node_name

    def token(self) -> str:
        """The liveliness token's key expression."""
        head = (
            f"{ADMIN_SPACE}/{self.domain}/{self.session_id}/{self.node_id}/{self.entity_id}/{self.kind.value}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.node_name)}"
        )
        if self.kind is EntityKind.NODE:
            return head
        assert self.topic is not None and self.ros_type is not None and self.type_hash is not None and self.qos is not None
        return f"{head}/{mangle(self.topic)}/{dds_type_name(self.ros_type)}/{self.type_hash}/{self.qos.encode()}"

    def gid(self) -> bytes:
        """The entity's 16-byte GID, as rmw_zenoh derives it from the token."""
        return entity_gid(self.token())


def entity_gid(token: str) -> bytes:
    """XXH3-128 of ``token``: low 64 bits then high 64 bits, little-endian (rmw_zenoh's GID)."""
    import xxhash  # the ros2 extra; only GIDs need it

    return int(xxhash.xxh3_128_intdigest(token.encode())).to_bytes(16, "little")


def parse_token(key: str) -> Entity:
    """The entity a liveliness token announces; raises :class:`BindingError` naming the bad part."""
    if len(key) > MAX_TOKEN_BYTES:
        raise BindingError(f"a token of {len(key)} bytes", where="liveliness token", expected=f"at most {MAX_TOKEN_BYTES}")
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        raise BindingError(
            f"{key[:120]!r}", where="liveliness token", expected=f"{ADMIN_SPACE}/<domain>/<zid>/<nid>/<id>/<kind>/... (9 or 13 parts)"
        )
    for index, what in ((1, "domain"), (3, "node id"), (4, "entity id")):
        if not _NUMBER.fullmatch(parts[index]):
            raise BindingError(f"{what} {parts[index][:40]!r}", where="liveliness token", expected="a number")
    try:
        kind = EntityKind(parts[5])
    except ValueError:
        raise BindingError(f"entity kind {parts[5][:20]!r}", where="liveliness token", expected="NN, MP, MS, SS or SC") from None
    common = dict(
        domain=int(parts[1]),
        session_id=parts[2],
        node_id=int(parts[3]),
        entity_id=int(parts[4]),
        kind=kind,
        enclave=demangle(parts[6]),
        namespace=demangle(parts[7]),
        node_name=demangle(parts[8]),
    )
    if kind is EntityKind.NODE:
        if len(parts) != 9:
            raise BindingError(f"a node token of {len(parts)} parts", where="liveliness token", expected="9")
        return Entity(**common)  # type: ignore[arg-type]
    if len(parts) != 13:
        raise BindingError(f"a {kind.name.lower()} token of {len(parts)} parts", where="liveliness token", expected="13")
    return Entity(
        **common,  # type: ignore[arg-type]
        topic=demangle(parts[9]),
        ros_type=ros_type_name(parts[10]),
        type_hash=_check_hash(parts[11], "liveliness token"),
        qos=QoS.decode(parts[12]),
    )
