"""ROS 2 message types: their definitions, RIHS01 type hashes and CDR bytes.

Definitions and CDR come from ``rosbags`` (pure Python, the ROS 2 Jazzy interfaces built in;
other types are registered from their ``.msg`` text with :meth:`TypeSupport.register_msg`).

The type hash is REP-2016's ``RIHS01_`` + SHA-256 of the type description as JSON (``json.dumps``
with its default separators): ``{"type_description": T, "referenced_type_descriptions": [R...]}``
where each description is ``{"type_name", "fields": [{"name", "type": {"type_id", "capacity",
"string_capacity", "nested_type_name"}}]}``, the referenced types sorted by name, a type without
fields given one ``uint8 structure_needs_at_least_one_member``, and ``type_id`` the field type
(``rosidl_generator_type_description``: +48 for a fixed array, +96 for a bounded sequence, +144
for an unbounded one). It is computed here rather than by ``rosbags.hash_rihs01``, which gives a
``char`` field type 13 where ROS 2's generated ``share/<pkg>/msg/*.json`` give 3 (``uint8``: a
``.msg`` ``char`` is an IDL ``uint8``), and so a wrong hash for ``std_msgs/msg/Char`` and every
type holding a char (``tests/test_ros2_types.py`` checks every hash against ROS 2's own files).

Service types (``pkg/srv/Name``) are two messages, ``pkg/srv/Name_Request`` and
``pkg/srv/Name_Response``, read from the ``.srv`` text (the part before and after its ``---``
line) with :meth:`TypeSupport.register_srv`, else found on first use: in
``<prefix>/share/<pkg>/srv/<Name>.srv`` of the ROS 2 installations on ``AMENT_PREFIX_PATH`` and of
this Python's prefix (the ROS 2 wheels install there), else among the definitions dyknow ships
(``lifecycle_msgs`` and ``rcl_interfaces``, copied from ROS 2 Jazzy, Apache License 2.0: what a
managing system calls). A service type's hash is ROS 2's: the description of ``pkg/srv/Name``
with the fields ``request_message``, ``response_message`` and ``event_message`` (nested types
``Name_Request``, ``Name_Response`` and ``Name_Event``), where ``Name_Event`` holds
``service_msgs/msg/ServiceEventInfo info`` and ``Name_Request[<=1] request``,
``Name_Response[<=1] response``.

CDR payloads start with the 4-byte encapsulation header (``00 01 00 00``: CDR, little-endian;
``00 00 00 00``: big-endian); both are read, little-endian is written. Bytes after the message
are ignored (rclpy's ``serialize_message`` leaves 8 after an ``rcl_interfaces/srv/SetParameters``
request holding a ``double[]``, which rosbags alone refuses). Payloads from the network
are bounded before they are parsed and any failure is raised as
:class:`~dyknow.errors.BindingError` naming the type.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import threading
from pathlib import Path
from typing import Any

from dyknow.errors import BindingError, did_you_mean
from dyknow.ros2.names import HASH_NOT_SUPPORTED, dds_type_name

__all__ = ["MAX_CDR_BYTES", "SHIPPED_SRV", "TypeSupport"]

#: The largest CDR payload decoded (bytes): a 4K RGB frame fits.
MAX_CDR_BYTES = 64 * 1024 * 1024
#: The ``.srv`` definitions dyknow ships (``<pkg>/<Name>.srv``): lifecycle and parameter services.
SHIPPED_SRV = Path(__file__).with_name("srv")
_SRV_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/srv/([A-Z][A-Za-z0-9]*)")
_SEPARATOR = re.compile(r"^---[ \t]*$", re.MULTILINE)
_MAX_SRV_TEXT = 1 << 20

_TYPE_IDS = {
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "float128": 12,
    "char": 3,  # ROS 2's .msg char is an IDL uint8 (rosbags says 13)
    "bool": 15,
    "byte": 16,
    "string": 17,
    "wstring": 18,
}
_BOUNDED_STRING, _BOUNDED_WSTRING = 21, 22
_NESTED = 1
_ARRAY, _BOUNDED_SEQUENCE, _SEQUENCE = 48, 96, 144


class TypeSupport:
    """The message types one process knows: hashes, CDR, message objects. Thread-safe."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore  # the ros2 extra

        self._store = get_typestore(Stores.ROS2_JAZZY)
        self._lock = threading.Lock()
        self._hashes: dict[str, str] = {}
        self._services: dict[str, tuple[str, str]] = {}

    # -- what is known

    def known(self, ros_type: str) -> bool:
        """Whether ``ros_type`` (``pkg/msg/Type``) is known."""
        return ros_type in self._store.fielddefs

    def check(self, ros_type: str, where: str = "ROS 2 type") -> str:
        """Return ``ros_type`` if known; else raise :class:`BindingError` with close matches."""
        dds_type_name(ros_type)  # the form first
        if not self.known(ros_type):
            raise BindingError(
                f"unknown type {ros_type!r}",
                where=where,
                expected=f"a ROS 2 Jazzy interface, or one registered with TypeSupport.register_msg{did_you_mean(ros_type, self._store.fielddefs)}",
            )
        return ros_type

    def register_msg(self, ros_type: str, text: str) -> None:
        """Teach a type from its ``.msg`` definition (its nested types must be known or given)."""
        from rosbags.typesys import get_types_from_msg

        dds_type_name(ros_type)
        try:
            types = get_types_from_msg(text, ros_type)
        except Exception as exc:  # rosbags raises its own parse errors
            raise BindingError(f"cannot read the definition: {exc}", where=f"type {ros_type!r}", expected="a .msg text") from exc
        with self._lock:
            self._store.register(types)
            self._hashes.clear()

    # -- services

    def register_srv(self, srv_type: str, text: str) -> None:
        """Teach a service type (``pkg/srv/Name``) from its ``.srv`` definition: the request's
        fields, a ``---`` line, the response's (their nested types must be known)."""
        from rosbags.typesys import get_types_from_msg

        pkg, name = self._srv_parts(srv_type)
        parts = _SEPARATOR.split(text, maxsplit=1)
        if len(parts) != 2:
            raise BindingError("no '---' line", where=f"service type {srv_type!r}", expected="request fields, '---', response fields")
        types: dict[str, Any] = {}
        for part, suffix in zip(parts, ("Request", "Response"), strict=True):
            # read as a message of the package (so that relative names resolve to pkg/msg/...),
            # then named as ROS 2 names it (rosbags would make pkg/srv/msg/... of a srv name)
            as_msg = f"{pkg}/msg/{name}_{suffix}"
            try:
                parsed = get_types_from_msg(part, as_msg)
            except Exception as exc:  # rosbags raises its own parse errors
                raise BindingError(f"cannot read the {suffix.lower()}: {exc}", where=f"service type {srv_type!r}", expected="a .srv text") from exc
            types[f"{pkg}/srv/{name}_{suffix}"] = parsed.pop(as_msg)
            types.update(parsed)
        with self._lock:
            self._store.register(types)
            self._services[srv_type] = (f"{pkg}/srv/{name}_Request", f"{pkg}/srv/{name}_Response")
            self._hashes.clear()
        for ros_type in self._services[srv_type]:
            self.check(ros_type)  # its nested types are known

    def service(self, srv_type: str) -> tuple[str, str]:
        """``(request type, response type)`` of the service type ``srv_type`` (``pkg/srv/Name``),
        its definition found as the module documentation says; else :class:`BindingError`."""
        pkg, name = self._srv_parts(srv_type)
        with self._lock:
            found = self._services.get(srv_type)
        if found is not None:
            return found
        for path in [*(folder / pkg / "srv" / f"{name}.srv" for folder in _share_folders()), SHIPPED_SRV / pkg / f"{name}.srv"]:
            if path.is_file() and path.stat().st_size <= _MAX_SRV_TEXT:
                self.register_srv(srv_type, path.read_text(encoding="utf-8"))
                return self._services[srv_type]
        shipped = sorted(f"{p.parent.name}/srv/{p.stem}" for p in SHIPPED_SRV.glob("*/*.srv"))
        with self._lock:
            known = sorted(set(shipped) | set(self._services))
        raise BindingError(
            f"unknown service type {srv_type!r}",
            where="ROS 2 service type",
            expected=(
                f"a type whose {pkg}/srv/{name}.srv is under share/ of AMENT_PREFIX_PATH, one dyknow ships, "
                f"or one registered with TypeSupport.register_srv{did_you_mean(srv_type, known)}"
            ),
        )

    @staticmethod
    def _srv_parts(srv_type: str) -> tuple[str, str]:
        m = _SRV_TYPE.fullmatch(srv_type) if isinstance(srv_type, str) else None
        if m is None:
            raise BindingError(f"service type {str(srv_type)[:80]!r}", where="ROS 2 service type", expected="a name like 'std_srvs/srv/Trigger'")
        return m[1], m[2]

    def fields(self, ros_type: str) -> list[str]:
        """The names of the fields of ``ros_type``."""
        return [name for name, _ in self.field_definitions(ros_type)]

    def field_definitions(self, ros_type: str) -> list[tuple[str, Any]]:
        """``(name, description)`` of each field, as rosbags describes them (``Nodetype`` trees)."""
        return list(self._store.fielddefs[self.check(ros_type)][1])

    # -- hashes

    def type_hash(self, ros_type: str, *, humble: bool = False) -> str:
        """The RIHS01 hash of ``ros_type``; ``humble``: ``TypeHashNotSupported``, as Humble writes."""
        if humble:
            return HASH_NOT_SUPPORTED
        if _SRV_TYPE.fullmatch(ros_type):
            self.service(ros_type)
        elif ros_type.endswith("_Event") and _SRV_TYPE.fullmatch(ros_type[: -len("_Event")]):
            self.service(ros_type[: -len("_Event")])
        else:
            self.check(ros_type)
        with self._lock:
            cached = self._hashes.get(ros_type)
        if cached is not None:
            return cached
        described: dict[str, dict[str, Any]] = {}
        self._describe(ros_type, described)
        text = json.dumps(
            {
                "type_description": described[ros_type],
                "referenced_type_descriptions": [d for name, d in sorted(described.items()) if name != ros_type],
            }
        )
        value = "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()
        with self._lock:
            self._hashes[ros_type] = value
        return value

    def _describe(self, ros_type: str, described: dict[str, dict[str, Any]]) -> None:
        if ros_type in described:
            return
        if ros_type in self._services or ros_type.endswith("_Event") and ros_type[: -len("_Event")] in self._services:
            self._describe_service(ros_type, described)
            return
        fielddefs = self._store.fielddefs[self.check(ros_type)][1]
        fields: list[dict[str, Any]] = []
        described[ros_type] = {"type_name": ros_type, "fields": fields}
        for name, desc in fielddefs:
            fields.append({"name": name, "type": self._field_type(desc, described)})
        if not fields:  # as rosidl describes an empty message
            empty = {"type_id": _TYPE_IDS["uint8"], "capacity": 0, "string_capacity": 0, "nested_type_name": ""}
            fields.append({"name": "structure_needs_at_least_one_member", "type": empty})

    def _describe_service(self, ros_type: str, described: dict[str, dict[str, Any]]) -> None:
        """The two types rosidl makes of a service beside its messages: ``pkg/srv/Name`` and
        ``pkg/srv/Name_Event`` (see the module documentation)."""

        def nested(name: str, type_id: int = _NESTED, capacity: int = 0) -> dict[str, Any]:
            self._describe(name, described)
            return {"type_id": type_id, "capacity": capacity, "string_capacity": 0, "nested_type_name": name}

        if ros_type.endswith("_Event"):
            request, response = self._services[ros_type[: -len("_Event")]]
            fields = [
                ("info", nested("service_msgs/msg/ServiceEventInfo")),
                ("request", nested(request, _BOUNDED_SEQUENCE + _NESTED, 1)),
                ("response", nested(response, _BOUNDED_SEQUENCE + _NESTED, 1)),
            ]
        else:
            request, response = self._services[ros_type]
            fields = [
                ("request_message", nested(request)),
                ("response_message", nested(response)),
                ("event_message", nested(ros_type + "_Event")),
            ]
        described[ros_type] = {"type_name": ros_type, "fields": [{"name": n, "type": t} for n, t in fields]}

    def _field_type(self, desc: Any, described: dict[str, dict[str, Any]]) -> dict[str, Any]:
        from rosbags.interfaces import Nodetype

        increment = capacity = string_capacity = 0
        nested = ""
        if desc[0] == Nodetype.ARRAY:
            increment, capacity = _ARRAY, desc[1][1]
            desc = desc[1][0]
        elif desc[0] == Nodetype.SEQUENCE:
            capacity = desc[1][1]
            increment = _BOUNDED_SEQUENCE if capacity else _SEQUENCE
            desc = desc[1][0]
        node, rest = desc
        if node == Nodetype.NAME:
            nested = rest
            self._describe(rest, described)
            type_id = increment + _NESTED
        elif rest[0] in ("string", "wstring") and rest[1]:
            string_capacity = rest[1]
            type_id = increment + (_BOUNDED_STRING if rest[0] == "string" else _BOUNDED_WSTRING)
        else:
            type_id = increment + _TYPE_IDS[rest[0]]
        return {"type_id": type_id, "capacity": capacity, "string_capacity": string_capacity, "nested_type_name": nested}

    # -- CDR and message objects

    def message_class(self, ros_type: str) -> Any:
        """The dataclass rosbags generates for ``ros_type``."""
        return self._store.types[self.check(ros_type)]

    def serialize(self, message: Any, ros_type: str) -> bytes:
        """CDR bytes (little-endian, with the encapsulation header) of a message object."""
        try:
            return bytes(self._store.serialize_cdr(message, ros_type))
        except Exception as exc:
            raise BindingError(f"cannot serialize: {type(exc).__name__}: {exc}", where=f"message of type {ros_type!r}") from exc

    def deserialize(self, data: bytes, ros_type: str) -> Any:
        """The message object in CDR ``data``; a payload too large, too short, with an unknown
        encapsulation or that does not parse as ``ros_type`` raises :class:`BindingError`.
        Numeric arrays in it are read-only views of ``data``, not copies."""
        where = f"CDR payload of type {ros_type!r}"
        if len(data) > MAX_CDR_BYTES:
            raise BindingError(f"{len(data)} bytes", where=where, expected=f"at most {MAX_CDR_BYTES}")
        if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
            raise BindingError(
                f"encapsulation header {bytes(data[:4]).hex()}",
                where=where,
                expected="00010000 (CDR little-endian) or 00000000 (big-endian)",
            )
        self.check(ros_type)
        view = memoryview(data)  # a view: rosbags cuts the header off by slicing, which would copy bytes whole
        try:
            return self._store.deserialize_cdr(view, ros_type)
        except Exception as exc:
            if "size mismatch" in str(exc):  # bytes after the message: read it without them
                try:
                    msgdef = self._store.get_msgdef(ros_type)
                    read = msgdef.deserialize_cdr_le if data[1] == 1 else msgdef.deserialize_cdr_be
                    return read(view[4:], 0, msgdef.cls, self._store)[0]
                except Exception:
                    pass  # the first error says it
            raise BindingError(f"does not parse: {type(exc).__name__}: {exc}", where=where, expected="CDR of this type") from exc


def _share_folders() -> list[Path]:
    """The ``share`` folders searched for ``.srv`` files: those of ``AMENT_PREFIX_PATH`` (a ROS 2
    installation), then this Python's prefix (the ROS 2 wheels)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return [*(Path(p) / "share" for p in prefixes), Path(sys.prefix) / "share"]
