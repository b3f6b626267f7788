"""Messages: a payload plus a small header, and their wire encoding.

Every message carries a header:

- ``seq``: the sequence number of the output port that published it (1, 2, 3, ...);
- ``origin_ns``: when the data was captured, taken by the source and propagated unchanged through
  every hop (unless a unit passes its own ``origin_ns`` when it publishes);
- ``send_ns``: when the last hop published it.

Times are wall-clock integer nanoseconds (``time.time_ns()``) so that they compare across processes
on one host.

Payloads are ``bytes``, ``str``, numpy arrays, or JSON-like values (dict, list, numbers, bool,
None). Between units of one manager a payload travels by reference (no copy, no serialization);
only messages that leave the process are encoded, by :func:`encode`:

- the Zenoh payload is the raw data: the bytes, the UTF-8 text, the JSON text, or the array's
  bytes in C order;
- the Zenoh attachment is the header, ``HEADER`` (little endian: magic ``b"DK"``, version, kind,
  seq u64, origin_ns i64, send_ns i64), followed for arrays by the dtype string and the shape.

Tools that know nothing of dyknow still see plain bytes, text or JSON on the key, with a matching
Zenoh encoding. Samples that arrive without a dyknow attachment (from plain Zenoh publishers) are
accepted too: their header is synthesised at arrival.
"""

from __future__ import annotations

import json
import struct
from typing import Any, Final

import numpy as np

from dyknow.errors import PayloadError

__all__ = [
    "ENCODINGS",
    "HEADER",
    "Message",
    "PayloadError",
    "check_payload",
    "decode",
    "decode_dyknow",
    "describe_payload",
    "encode",
    "is_dyknow",
    "payload_nbytes",
    "reheader",
]


# Module constants are Final: compiled (see setup.py), a Final name is a C constant rather than a
# lookup in the module's dictionary on every message.

# kind codes in the attachment
_BYTES: Final = 0
_TEXT: Final = 1
_JSON: Final = 2
_ARRAY: Final = 3
_MAGIC: Final = b"DK"
_VERSION: Final = 1
HEADER: Final = struct.Struct("<2sBBQqq")
_ARRAY_META: Final = struct.Struct("<BB")  # ndim, len(dtype string)

#: Zenoh encoding announced for each kind of payload, for tools that know nothing of dyknow.
ENCODINGS: Final = {
    _BYTES: "application/octet-stream",
    _TEXT: "text/plain;charset=utf-8",
    _JSON: "application/json",
    _ARRAY: "application/x-dyknow-ndarray",
}

_BYTES_ENCODING: Final = ENCODINGS[_BYTES]
_JSON_TYPES: Final = (dict, list, tuple, int, float, bool, type(None))


class Message:
    """A payload and its header, as handed to ``Unit.on_message``.

    Treat it as read-only: the same object (and the same payload object) reaches every local
    receiver of the stream. Numpy payloads are marked read-only when published.

    This is a plain ``__slots__`` class rather than a frozen dataclass because one is created per
    hop and frozen dataclasses cost several times more to construct.
    """

    __slots__ = ("key", "nbytes", "origin_ns", "payload", "send_ns", "seq", "wire")

    def __init__(
        self,
        payload: Any,
        seq: int,
        origin_ns: int,
        send_ns: int,
        key: str,
        nbytes: int = 0,
        wire: tuple[Any, int, bytes] | None = None,
    ) -> None:
        self.payload = payload
        self.seq = seq
        self.origin_ns = origin_ns
        self.send_ns = send_ns
        self.key = key
        self.nbytes = nbytes  # payload size where known without encoding (for statistics)
        # For an immutable payload received from Zenoh: (transport buffer, kind, header extra), so
        # a unit that forwards the payload unchanged sends the same bytes without re-encoding.
        self.wire = wire

    def __repr__(self) -> str:
        return (
            f"Message(key={self.key!r}, seq={self.seq}, origin_ns={self.origin_ns}, "
            f"send_ns={self.send_ns}, payload={describe_payload(self.payload)})"
        )


def describe_payload(payload: Any) -> str:
    """A short, printable description of a payload (arrays by dtype and shape)."""
    if isinstance(payload, np.ndarray):
        return f"<ndarray {payload.dtype} {payload.shape}>"
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return f"<{len(payload)} bytes>"
    text = repr(payload)
    return text if len(text) <= 60 else text[:57] + "..."


def check_payload(payload: Any) -> None:
    """Raise :class:`PayloadError` unless ``payload`` is of a type dyknow can carry."""
    if isinstance(payload, (bytes, bytearray, memoryview, str, np.ndarray, *_JSON_TYPES)):
        return
    raise PayloadError(
        f"cannot publish a payload of type {type(payload).__name__}",
        expected="bytes, str, a numpy array, or a JSON-like value (dict, list, number, bool, None)",
    )


def payload_nbytes(payload: Any) -> int:
    """Size of a payload in bytes where it is known without encoding (0 for JSON-like values)."""
    if isinstance(payload, (bytes, bytearray)):
        return len(payload)
    if isinstance(payload, np.ndarray):
        return payload.nbytes
    if isinstance(payload, memoryview):
        return payload.nbytes
    if isinstance(payload, str):
        return len(payload)
    return 0


def encode(msg: Message) -> tuple[Any, bytes, str]:
    """Encode a message for Zenoh: ``(payload, attachment, encoding)``.

    A message that forwards a payload received from Zenoh unchanged reuses its wire form (see
    ``Message.wire``), so relaying costs no re-encoding and no copy at any size.
    """
    wire = msg.wire
    if wire is not None:
        data, kind, extra = wire
        header = HEADER.pack(_MAGIC, _VERSION, kind, msg.seq, msg.origin_ns, msg.send_ns)
        return data, header + extra if extra else header, ENCODINGS[kind]
    payload = msg.payload
    extra = b""
    if isinstance(payload, (bytes, bytearray)):
        kind, data = _BYTES, payload
    elif isinstance(payload, memoryview):
        kind, data = _BYTES, payload.tobytes()
    elif isinstance(payload, str):
        kind, data = _TEXT, payload.encode()
    elif isinstance(payload, np.ndarray):
        kind = _ARRAY
        dtype = payload.dtype.str.encode()
        if payload.ndim > 255 or payload.dtype.hasobject:
            raise PayloadError(
                f"cannot send an array of dtype {payload.dtype} with {payload.ndim} dims", expected="numbers, at most 255 dims"
            )
        extra = _ARRAY_META.pack(payload.ndim, len(dtype)) + dtype + struct.pack(f"<{payload.ndim}Q", *payload.shape)
        data = np.ascontiguousarray(payload).tobytes()
    else:
        kind = _JSON
        try:
            data = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
        except (TypeError, ValueError) as exc:
            raise PayloadError(f"cannot encode the payload as JSON: {exc}") from exc
    header = HEADER.pack(_MAGIC, _VERSION, kind, msg.seq, msg.origin_ns, msg.send_ns)
    return data, header + extra, ENCODINGS[kind]


def is_dyknow(attachment: bytes | None) -> bool:
    """Whether a Zenoh attachment is a dyknow header (the sample came from a dyknow unit)."""
    return attachment is not None and len(attachment) >= HEADER.size and attachment[:2] == _MAGIC


def decode(
    data: Any,
    attachment: bytes | None,
    key: str,
    *,
    encoding: str = "",
    arrival_ns: int = 0,
    seq: int = 0,
) -> Message:
    """Decode a Zenoh sample into a :class:`Message`.

    ``data`` is the payload as bytes or as the transport's own buffer (anything with
    ``to_bytes()``). Samples without a dyknow attachment come from plain Zenoh publishers: their
    payload is decoded from the Zenoh ``encoding`` (JSON, text, else bytes) and the header is
    synthesised from ``arrival_ns`` and the subscriber's own count ``seq``.
    """
    if not is_dyknow(attachment):
        raw = data if isinstance(data, bytes) else data.to_bytes()
        return Message(_decode_foreign(raw, encoding), seq, arrival_ns, arrival_ns, key, len(raw))
    assert attachment is not None
    return decode_dyknow(data, attachment, key)


def decode_dyknow(data: Any, attachment: bytes, key: str) -> Message:
    """:func:`decode` for a sample known to carry a dyknow header (the transport checked)."""
    raw = data if type(data) is bytes else data.to_bytes()
    _, version, kind, mseq, origin_ns, send_ns = HEADER.unpack_from(attachment)
    if version != _VERSION:
        raise PayloadError(f"header version {version}", where=f"message on {key!r}", expected=str(_VERSION))
    extra = b""
    if kind == _BYTES:
        payload: Any = raw
    elif kind == _TEXT:
        payload = raw.decode()
    elif kind == _JSON:
        return Message(json.loads(raw), mseq, origin_ns, send_ns, key, len(raw))  # mutable: no wire reuse
    elif kind == _ARRAY:
        ndim, dlen = _ARRAY_META.unpack_from(attachment, HEADER.size)
        pos = HEADER.size + _ARRAY_META.size
        dtype = np.dtype(attachment[pos : pos + dlen].decode())
        shape = struct.unpack_from(f"<{ndim}Q", attachment, pos + dlen)
        payload = np.frombuffer(raw, dtype=dtype).reshape(shape)  # read-only: it views immutable bytes
        extra = attachment[HEADER.size :]
    else:
        raise PayloadError(f"unknown payload kind {kind}", where=f"message on {key!r}", expected="0 to 3 (bytes, text, JSON, array)")
    return Message(payload, mseq, origin_ns, send_ns, key, len(raw), (data, kind, extra))


def reheader(attachment: bytes, seq: int, send_ns: int) -> tuple[bytes, int, int, str] | None:
    """The header of a received message of raw bytes made the header of the next hop, for a unit
    that forwards it as it came (no :class:`Message`, no copy of the payload): the same origin, a
    new ``seq`` and ``send_ns``. Returns ``(attachment, origin_ns, previous send_ns, encoding)``,
    or None for any other header: text, JSON and arrays are decoded first (which checks them, so
    that a relay never passes on what its readers would refuse), and so is a header this version
    does not write (decoding reports what is wrong with it)."""
    _, version, kind, _, origin_ns, sent_ns = HEADER.unpack_from(attachment)
    if kind != _BYTES or version != _VERSION or len(attachment) != HEADER.size:
        return None
    return HEADER.pack(_MAGIC, _VERSION, _BYTES, seq, origin_ns, send_ns), origin_ns, sent_ns, _BYTES_ENCODING


def _decode_foreign(data: bytes, encoding: str) -> Any:
    if encoding.startswith("application/json") or encoding.startswith("text/json"):
        try:
            return json.loads(data)
        except ValueError:
            return data
    if encoding.startswith("text/") or encoding.startswith("zenoh/string"):
        try:
            return data.decode()
        except UnicodeDecodeError:
            return data
    return data
