"""The little of protobuf's wire format that dyknow's recordings need, written and read by hand.

Writing: the three messages dyknow records (``foxglove.RawImage``, ``foxglove.CompressedImage``,
``dyknow.NDArray``, see :mod:`dyknow.recording.codecs`) and the ``FileDescriptorSet`` schemas that
describe them. Reading: any message as ``{field number: [values]}``, which is all the decoders
need to get those fields back. The protobuf package would do the same at the cost of a dependency
and of generated code.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any

# FieldDescriptorProto types and labels
INT64, UINT64, INT32, FIXED32, STRING, MESSAGE, BYTES = 3, 4, 5, 7, 9, 11, 12
OPTIONAL, REPEATED = 1, 3

# --------------------------------------------------------------------------- writing


def varint(value: int) -> bytes:
    """``value`` as a protobuf varint (a negative int64 takes ten bytes, as in protobuf)."""
    value &= 0xFFFFFFFFFFFFFFFF
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def length_prefix(number: int, size: int) -> bytes:
    """The key and length of a length-delimited field of ``size`` bytes (its data follows)."""
    return varint(number << 3 | 2) + varint(size)


def bytes_field(number: int, data: bytes) -> bytes:
    """A length-delimited field: bytes, a string or an embedded message."""
    return length_prefix(number, len(data)) + data


def string_field(number: int, text: str) -> bytes:
    """A string field; empty (as protobuf leaves out a default value) when ``text`` is empty."""
    return bytes_field(number, text.encode()) if text else b""


def uint_field(number: int, value: int) -> bytes:
    """A varint field; empty when ``value`` is 0."""
    return varint(number << 3) + varint(value) if value else b""


def fixed32_field(number: int, value: int) -> bytes:
    """A fixed32 field (written even when 0, as Foxglove's own writers do)."""
    return varint(number << 3 | 5) + struct.pack("<I", value)


def timestamp_field(number: int, time_ns: int) -> bytes:
    """A ``google.protobuf.Timestamp`` field from integer nanoseconds."""
    seconds, nanos = divmod(time_ns, 1_000_000_000)
    return bytes_field(number, uint_field(1, seconds) + uint_field(2, nanos))


def field_descriptor(name: str, number: int, type_: int, label: int = OPTIONAL, type_name: str = "") -> bytes:
    """A ``FieldDescriptorProto``."""
    json_name = name.split("_")[0] + "".join(part.title() for part in name.split("_")[1:])
    return (
        string_field(1, name) + uint_field(3, number) + uint_field(4, label) + uint_field(5, type_)
        + string_field(6, type_name) + string_field(10, json_name)
    )  # fmt: skip


def file_descriptor(name: str, package: str, message: str, fields: Sequence[bytes], dependencies: Sequence[str] = ()) -> bytes:
    """A proto3 ``FileDescriptorProto`` holding one message made of ``fields``."""
    body = b"".join(bytes_field(2, f) for f in fields)
    return (
        string_field(1, name) + string_field(2, package) + b"".join(string_field(3, d) for d in dependencies)
        + bytes_field(4, string_field(1, message) + body) + string_field(12, "proto3")
    )  # fmt: skip


# --------------------------------------------------------------------------- reading


def decode(data: bytes | memoryview) -> dict[int, list[Any]]:
    """A protobuf message as ``{field number: [values]}`` (ints, or memoryviews for length-delimited fields).

    Raises ``ValueError`` for a truncated message or a wire type it does not read (groups).
    """
    view = memoryview(data)
    end = len(view)
    pos = 0
    fields: dict[int, list[Any]] = {}
    while pos < end:
        key, pos = read_varint(view, pos)
        number, wire = key >> 3, key & 7
        value: Any
        if wire == 0:
            value, pos = read_varint(view, pos)
        elif wire == 1:
            value, pos = int.from_bytes(view[pos : pos + 8], "little"), pos + 8
        elif wire == 2:
            size, pos = read_varint(view, pos)
            value, pos = view[pos : pos + size], pos + size
        elif wire == 5:
            value, pos = int.from_bytes(view[pos : pos + 4], "little"), pos + 4
        else:
            raise ValueError(f"protobuf wire type {wire} at byte {pos} is not supported")
        if pos > end:
            raise ValueError("the protobuf message is truncated")
        fields.setdefault(number, []).append(value)
    return fields


def read_varint(view: memoryview, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it; ``ValueError`` if malformed."""
    result = 0
    for i in range(10):
        if pos + i >= len(view):
            break
        byte = view[pos + i]
        result |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            return result, pos + i + 1
    raise ValueError("malformed protobuf varint")


def last(fields: dict[int, list[Any]], number: int, default: Any) -> Any:
    """The value of a singular field (the last one, as protobuf merges), or ``default``."""
    values = fields.get(number)
    return values[-1] if values else default


def text(fields: dict[int, list[Any]], number: int) -> str:
    """A string field ("" when absent)."""
    return bytes(last(fields, number, b"")).decode()


def uints(values: list[Any]) -> list[int]:
    """A repeated integer field, packed or not."""
    out: list[int] = []
    for value in values:
        if isinstance(value, int):
            out.append(value)
            continue
        pos = 0
        while pos < len(value):
            number, pos = read_varint(value, pos)
            out.append(number)
    return out
