"""``ros2:`` and ``ros2dds:`` bindings: a port bound to a ROS 2 topic instead of a dyknow key.

``ros2:/TOPIC[?OPTION=VALUE&...]`` is the topic on rmw_zenoh (ROS 2's Zenoh middleware, spoken
natively on the manager's session); ``ros2dds:/TOPIC?...`` is the same topic on DDS (ROS 2's
default middleware, through Cyclone DDS: :mod:`dyknow.ros2.dds`). The middleware is chosen per
binding, not per manager, so one manager can read from one and write to the other. Options:

- ``type=pkg/msg/Type``: the message type. Required for an output; an input without it takes the
  type its publishers announce (rmw_zenoh: their tokens, else each message's key; DDS: the
  writers discovery shows within 2 s, else it fails).
- ``reliability=reliable|best_effort`` (default reliable), ``durability=volatile|transient_local``
  (default volatile; transient-local outputs keep ``depth`` messages for late subscribers, as
  rmw_zenoh's do), ``depth=N`` (default 10), ``history=keep_last|keep_all``;
- ``frame_id=NAME``: the ``header.frame_id`` of messages dyknow builds (images);
- ``decode=bgr``: an input of ``CompressedImage`` delivers BGR arrays, decoded, not JPEG bytes;
- ``hash=none``: no type hash in keys and tokens (``TypeHashNotSupported``, as Humble writes);
- ``max_bytes=N``: an input drops a larger message before copying or decoding it (counted and
  logged). Default: the manager's ``--max-ros2-message-bytes`` (16 MiB) for a typed input, 1 MiB
  for an untyped one (whose publishers choose the type); at most
  :data:`~dyknow.ros2.types.MAX_CDR_BYTES`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from urllib.parse import parse_qsl

from dyknow.errors import BindingError, did_you_mean
from dyknow.keys import ROS2_SCHEMES
from dyknow.ros2.names import Durability as _Durability
from dyknow.ros2.names import QoS, Reliability, check_topic, dds_type_name
from dyknow.ros2.types import MAX_CDR_BYTES

__all__ = ["DDS_SCHEME", "SCHEME", "Ros2Binding", "is_ros2", "parse_binding"]

#: The prefix of a ROS 2 binding on rmw_zenoh, and on DDS (their home: :data:`dyknow.keys.ROS2_SCHEMES`).
SCHEME, DDS_SCHEME = ROS2_SCHEMES
_OPTIONS = ("type", "reliability", "durability", "depth", "history", "frame_id", "hash", "decode", "max_bytes")
_WHOLE = re.compile(r"[0-9]{1,9}")


def is_ros2(binding: object) -> bool:
    """Whether ``binding`` is a ``ros2:`` or ``ros2dds:`` binding."""
    return isinstance(binding, str) and (binding.startswith(SCHEME) or binding.startswith(DDS_SCHEME))


@dataclass(frozen=True, slots=True)
class Ros2Binding:
    """A parsed ``ros2:`` binding."""

    topic: str
    ros_type: str | None = None
    qos: QoS = QoS()
    frame_id: str = ""
    humble: bool = False
    dds: bool = False
    decode: bool = False
    max_bytes: int | None = None  # None: the node's default (see the module documentation)

    def uri(self) -> str:
        """The binding written back (options in a fixed order, defaults left out)."""
        options = []
        if self.ros_type:
            options.append(f"type={self.ros_type}")
        if self.qos.reliability is Reliability.BEST_EFFORT:
            options.append("reliability=best_effort")
        if self.qos.durability is _Durability.TRANSIENT_LOCAL:
            options.append("durability=transient_local")
        if self.qos.keep_all:
            options.append("history=keep_all")
        if self.qos.depth != 10:
            options.append(f"depth={self.qos.depth}")
        if self.frame_id:
            options.append(f"frame_id={self.frame_id}")
        if self.humble:
            options.append("hash=none")
        if self.decode:
            options.append("decode=bgr")
        if self.max_bytes is not None:
            options.append(f"max_bytes={self.max_bytes}")
        return (DDS_SCHEME if self.dds else SCHEME) + self.topic + ("?" + "&".join(options) if options else "")


def parse_binding(text: str, *, where: str = "binding") -> Ros2Binding:
    """Parse ``ros2:/TOPIC?...``; raises :class:`BindingError` naming the option at fault."""
    if not is_ros2(text):
        raise BindingError(
            f"{str(text)[:80]!r}", where=where, expected="ros2:/TOPIC, ros2:/TOPIC?type=pkg/msg/Type or ros2dds:/TOPIC?type=..."
        )
    if len(text) > 1024:
        raise BindingError(f"a binding of {len(text)} characters", where=where, expected="at most 1024")
    dds = text.startswith(DDS_SCHEME)
    topic, _, query = text[len(DDS_SCHEME if dds else SCHEME) :].partition("?")
    check_topic(topic, where)
    options: dict[str, str] = {}
    for name, value in parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)):
        if name not in _OPTIONS:
            raise BindingError(f"option {name!r}", where=where, expected=f"one of {', '.join(_OPTIONS)}{did_you_mean(name, _OPTIONS)}")
        if name in options:
            raise BindingError(f"option {name!r} twice", where=where, expected="each option once")
        options[name] = value
    ros_type = options.get("type") or None
    if ros_type is not None:
        dds_type_name(ros_type)
    choices = {
        "reliability": ("reliable", "best_effort"),
        "durability": ("volatile", "transient_local"),
        "history": ("keep_last", "keep_all"),
        "hash": ("none",),
        "decode": ("bgr",),
    }
    for name, allowed in choices.items():
        if name in options and options[name] not in allowed:
            raise BindingError(f"{name}={options[name]!r}", where=where, expected=" or ".join(allowed))
    depth = options.get("depth", "10")
    if not depth.isdigit() or not 1 <= int(depth) <= 10_000:
        raise BindingError(f"depth={depth!r}", where=where, expected="a whole number from 1 to 10000")
    max_bytes = options.get("max_bytes")
    if max_bytes is not None and (not _WHOLE.fullmatch(max_bytes) or not 1 <= int(max_bytes) <= MAX_CDR_BYTES):
        raise BindingError(f"max_bytes={max_bytes[:40]!r}", where=where, expected=f"a whole number of bytes from 1 to {MAX_CDR_BYTES}")
    qos = QoS(
        Reliability.BEST_EFFORT if options.get("reliability") == "best_effort" else Reliability.RELIABLE,
        _Durability.TRANSIENT_LOCAL if options.get("durability") == "transient_local" else _Durability.VOLATILE,
        int(depth),
        options.get("history") == "keep_all",
    )
    if dds and "hash" in options:
        raise BindingError("hash=none on a DDS binding", where=where, expected="hash only on ros2: bindings (DDS names no hash)")
    return Ros2Binding(
        topic,
        ros_type,
        qos,
        options.get("frame_id", ""),
        options.get("hash") == "none",
        dds,
        "decode" in options,
        None if max_bytes is None else int(max_bytes),
    )
