"""Messages: a payload plus a small header, and their wire encoding.

Every message carries a header:

- ``seq``: the sequence number of the output port that published it (1, 2, 3, ...);
- ``origin_ns``: when the data was captured, taken by the source and propagated unchanged through
  every hop (unless a unit passes its own ``origin_ns`` when it publishes);
- ``send_ns``: when the last hop published it;
- ``source``: which output port sent it, a random 32-bit id the port draws when it is bound to its
  key (again at each rebinding): a reader follows each sender's ``seq`` and counts the gaps as
  messages lost on the way (Zenoh's publishers drop under congestion rather than block);
- ``origin_clock`` and ``send_clock``: whose clock took ``origin_ns`` and ``send_ns``, the random
  32-bit :data:`CLOCK_ID` of that process (0: unknown). An id, not a name: nothing is trusted
  because of it; it says which clock offset applies to a time from another host;
- ``forwards``: how many forwarding units (``forward_to``, such as the shipped relay) passed the
  message on since a unit last published it. A forwarding unit drops a message that
  :data:`MAX_FORWARDS` of them passed on already, so forwarding units bound into a cycle across
  processes (which no manager alone can see) carry each message round at most that often
  instead of for ever.

Times are wall-clock integer nanoseconds (``time.time_ns()``).

Payloads are ``bytes``, ``str``, numpy arrays, or JSON-like values (dict, list, numbers, bool,
None). Between units of one manager a payload travels by reference (no copy, no serialization);
only messages that leave the process are encoded, by :func:`encode`:

- the Zenoh payload is the raw data: the bytes, the UTF-8 text, the JSON text, or the array's
  bytes in C order;
- the Zenoh attachment is the header, ``HEADER``, followed for arrays by ``ndim`` u8, the length
  of the dtype string u8, the dtype string (numpy's, e.g. ``<f4``) and the shape (``ndim`` u64).
  ``HEADER`` is 40 bytes, little endian::

      offset  size  field
      0       2     magic, the bytes "DK"
      2       1     version: 3
      3       1     kind (bits 0-1): 0 bytes, 1 text (UTF-8), 2 JSON, 3 array; forwards (bits 2-7)
      4       8     seq, u64
      12      8     origin_ns, i64
      20      8     send_ns, i64
      28      4     source, u32
      32      4     origin_clock, u32
      36      4     send_clock, u32

  Versions 2 (the same layout, the whole byte 3 the kind: no forwards) and 1 (``HEADER_V1``, the
  first 28 bytes, without the last three fields) are still read: their forwards are 0, and a
  version 1 header's source and clocks too.

Tools that know nothing of dyknow still see plain bytes, text or JSON on the key, with a matching
Zenoh encoding. Samples that arrive without a dyknow attachment (from plain Zenoh publishers) are
accepted too: their header is synthesised at arrival.
"""

from __future__ import annotations

import json
import os
import struct
from typing import Any, Final

import numpy as np

from dyknow.errors import PayloadError

__all__ = [
    "CLOCK_ID",
    "ENCODINGS",
    "HEADER",
    "HEADER_V1",
    "MAX_FORWARDS",
    "Message",
    "PayloadError",
    "check_payload",
    "decode",
    "decode_dyknow",
    "describe_payload",
    "encode",
    "is_dyknow",
    "new_id",
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
_VERSION: Final = 3
_V2: Final = 2
HEADER: Final = struct.Struct("<2sBBQqqIII")
HEADER_V1: Final = struct.Struct("<2sBBQqq")
_V1: Final = 1
#: The most forwarding units that pass one message on (see the module documentation).
MAX_FORWARDS: Final = 63


def new_id() -> int:
    """A random 32-bit id, never 0 (0 means unknown): a port's ``source``, a process's clock id."""
    return int.from_bytes(os.urandom(4), "little") or 1


#: This process's clock id (see the module documentation).
CLOCK_ID: Final = new_id()
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

    __slots__ = ("forwards", "key", "nbytes", "origin_clock", "origin_ns", "payload", "send_clock", "send_ns", "seq", "source", "wire")

    def __init__(
        self,
        payload: Any,
        seq: int,
        origin_ns: int,
        send_ns: int,
        key: str,
        nbytes: int = 0,
        wire: tuple[Any, int, bytes] | None = None,
        source: int = 0,
        origin_clock: int = CLOCK_ID,
        send_clock: int = CLOCK_ID,
        forwards: int = 0,
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
        self.source = source  # the sending output port's id (0: unknown)
        self.origin_clock = origin_clock  # whose clock took origin_ns (CLOCK_ID: this process's)
        self.send_clock = send_clock  # whose clock took send_ns
        self.forwards = forwards  # forwarding units that passed it on since a unit published it

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
        header = HEADER.pack(_MAGIC, _VERSION, kind | min(msg.forwards, MAX_FORWARDS) << 2, msg.seq, msg.origin_ns, msg.send_ns, msg.source, msg.origin_clock, msg.send_clock)
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
    header = HEADER.pack(_MAGIC, _VERSION, kind | min(msg.forwards, MAX_FORWARDS) << 2, msg.seq, msg.origin_ns, msg.send_ns, msg.source, msg.origin_clock, msg.send_clock)
    return data, header + extra, ENCODINGS[kind]


def is_dyknow(attachment: bytes | None) -> bool:
    """Whether a Zenoh attachment is a dyknow header (the sample came from a dyknow unit)."""
    return attachment is not None and len(attachment) >= HEADER_V1.size and attachment[:2] == _MAGIC


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
    version = attachment[2]
    forwards = 0
    if (version == _VERSION or version == _V2) and len(attachment) >= HEADER.size:
        _, _, kind, mseq, origin_ns, send_ns, source, origin_clock, send_clock = HEADER.unpack_from(attachment)
        if version == _VERSION:
            forwards = kind >> 2
            kind &= 3
        size = HEADER.size
    elif version == _V1:
        _, _, kind, mseq, origin_ns, send_ns = HEADER_V1.unpack_from(attachment)
        source = origin_clock = send_clock = 0
        size = HEADER_V1.size
    else:
        raise PayloadError(f"header version {version} of {len(attachment)} bytes", where=f"message on {key!r}", expected="version 3 (or 2, 1)")
    extra = b""
    if kind == _BYTES:
        payload: Any = raw
    elif kind == _TEXT:
        payload = raw.decode()
    elif kind == _JSON:  # mutable: no wire reuse
        return Message(json.loads(raw), mseq, origin_ns, send_ns, key, len(raw), None, source, origin_clock, send_clock, forwards)
    elif kind == _ARRAY:
        ndim, dlen = _ARRAY_META.unpack_from(attachment, size)
        pos = size + _ARRAY_META.size
        dtype = np.dtype(attachment[pos : pos + dlen].decode())
        shape = struct.unpack_from(f"<{ndim}Q", attachment, pos + dlen)
        payload = np.frombuffer(raw, dtype=dtype).reshape(shape)  # read-only: it views immutable bytes
        extra = attachment[size:]
    else:
        raise PayloadError(f"unknown payload kind {kind}", where=f"message on {key!r}", expected="0 to 3 (bytes, text, JSON, array)")
    return Message(payload, mseq, origin_ns, send_ns, key, len(raw), (data, kind, extra), source, origin_clock, send_clock, forwards)


def reheader(attachment: bytes, seq: int, send_ns: int, source: int) -> tuple[bytes, int, int, int, int, int, int, str, int] | None:
    """The header of a received message of raw bytes made the header of the next hop, for a unit
    that forwards it as it came (no :class:`Message`, no copy of the payload): the same origin and
    origin clock, one more forward, a new ``seq``, ``send_ns`` and ``source``, this process's
    send clock. Returns ``(attachment, origin_ns, origin_clock, previous send_ns, previous send
    clock, previous source, previous seq, encoding, forwards so far)`` (the caller drops the
    message when the forwards so far reach :data:`MAX_FORWARDS`), or None for any other
    header: text, JSON and arrays are decoded first (which checks them, so that a relay never
    passes on what its readers would refuse), and so is a header of another version (decoding
    reads it, or reports what is wrong with it)."""
    if len(attachment) != HEADER.size:
        return None
    version = attachment[2]
    if version != _VERSION and version != _V2:
        return None
    _, _, byte, prev_seq, origin_ns, sent_ns, prev_source, origin_clock, sent_clock = HEADER.unpack_from(attachment)
    forwards = byte >> 2 if version == _VERSION else 0
    if byte & 3 != _BYTES or (version == _V2 and byte != _BYTES):
        return None
    onward = min(forwards + 1, MAX_FORWARDS)
    header = HEADER.pack(_MAGIC, _VERSION, _BYTES | onward << 2, seq, origin_ns, send_ns, source, origin_clock, CLOCK_ID)
    return header, origin_ns, origin_clock, sent_ns, sent_clock, prev_source, prev_seq, _BYTES_ENCODING, forwards


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
