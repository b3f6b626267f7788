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
None), which may hold numpy arrays (a ROS 2 message's large arrays, say). Between units of one
manager a payload travels by reference (no copy, no serialization); only messages that leave the
process are encoded, by :func:`encode`:

- the Zenoh payload is the raw data: the bytes, the UTF-8 text, the JSON text, or the array's
  bytes in C order; for a JSON-like value holding arrays, the JSON text with ``null`` where each
  array is, then each array's bytes in C order, one after the other (so the JSON text is the
  payload but the arrays' bytes at its end);
- the Zenoh attachment is the header, ``HEADER``, followed for arrays by ``ndim`` u8, the length
  of the dtype string u8, the dtype string (numpy's, e.g. ``<f4``) and the shape (``ndim`` u64);
  for a JSON-like value holding arrays by their count u8 and, for each in the payload's order,
  the length of its path u16, its path (a JSON Pointer, RFC 6901, in UTF-8: ``/fields/0/data``)
  and then its ``ndim``, dtype and shape as for an array. At most 255 arrays travel so; beyond,
  the smallest go as JSON lists. ``HEADER`` is 41 bytes, little endian::

      offset  size  field
      0       2     magic, the bytes "DK"
      2       1     version: 3
      3       1     kind: 0 bytes, 1 text (UTF-8), 2 JSON, 3 array, 4 JSON with arrays
      4       8     seq, u64
      12      8     origin_ns, i64
      20      8     send_ns, i64
      28      4     source, u32
      32      4     origin_clock, u32
      36      4     send_clock, u32
      40      1     forwards, u8

  Versions 2 (``HEADER_V2``, the first 40 bytes: no forwards) and 1 (``HEADER_V1``, the first 28
  bytes, without source and clocks either) are still read: their forwards are 0, and a version 1
  header's source and clocks too.

Tools that know nothing of dyknow still see plain bytes, text or JSON on the key, with a matching
Zenoh encoding. Samples that arrive without a dyknow attachment (from plain Zenoh publishers) are
accepted too: their header is synthesised at arrival.
"""

from __future__ import annotations

import json
import json.scanner
import os
import struct
import sys
from typing import Any, Final

from dyknow.errors import PayloadError

__all__ = [
    "CLOCK_ID",
    "ENCODINGS",
    "HEADER",
    "HEADER_V1",
    "HEADER_V2",
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
_PARTS: Final = 4  # JSON with arrays
_MAGIC: Final = b"DK"
_VERSION: Final = 3
_V2: Final = 2
HEADER: Final = struct.Struct("<2sBBQqqIIIB")
HEADER_V2: Final = struct.Struct("<2sBBQqqIII")
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
_PATH_LENGTH: Final = struct.Struct("<H")
_MAX_PARTS: Final = 255

#: Zenoh encoding announced for each kind of payload, for tools that know nothing of dyknow.
ENCODINGS: Final = {
    _BYTES: "application/octet-stream",
    _TEXT: "text/plain;charset=utf-8",
    _JSON: "application/json",
    _ARRAY: "application/x-dyknow-ndarray",
    _PARTS: "application/x-dyknow-json-ndarrays",
}

_BYTES_ENCODING: Final = ENCODINGS[_BYTES]
_JSON_TYPES: Final = (dict, list, tuple, int, float, bool, type(None))


def _is_array(payload: Any) -> bool:
    """Whether ``payload`` is a numpy array. Only once numpy is imported can one be, so this module
    imports numpy only to decode an array: a process that never meets one (a command that fails
    at once, a tool of bytes and JSON) never pays for numpy's import (the larger part of the
    ``dyknow`` command's start-up)."""
    numpy = sys.modules.get("numpy")
    array = None if numpy is None else getattr(numpy, "ndarray", None)
    return array is not None and isinstance(payload, array)


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
    if _is_array(payload):
        return f"<ndarray {payload.dtype} {payload.shape}>"
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return f"<{len(payload)} bytes>"
    text = repr(payload)
    return text if len(text) <= 60 else text[:57] + "..."


def check_payload(payload: Any) -> None:
    """Raise :class:`PayloadError` unless ``payload`` is of a type dyknow can carry."""
    if isinstance(payload, (bytes, bytearray, memoryview, str, *_JSON_TYPES)):
        return
    if _is_array(payload):
        return
    raise PayloadError(
        f"cannot publish a payload of type {type(payload).__name__}",
        expected="bytes, str, a numpy array, or a JSON-like value (dict, list, number, bool, None)",
    )


def payload_nbytes(payload: Any) -> int:
    """Size of a payload in bytes where it is known without encoding (0 for JSON-like values)."""
    if isinstance(payload, (bytes, bytearray)):
        return len(payload)
    if isinstance(payload, memoryview):
        return payload.nbytes
    if isinstance(payload, str):
        return len(payload)
    if _is_array(payload):
        return int(payload.nbytes)
    return 0


def encode(msg: Message) -> tuple[Any, bytes, str]:
    """Encode a message for Zenoh: ``(payload, attachment, encoding)``.

    A message that forwards a payload received from Zenoh unchanged reuses its wire form (see
    ``Message.wire``), so relaying costs no re-encoding and no copy at any size.
    """
    wire = msg.wire
    if wire is not None:
        data, kind, extra = wire
        header = HEADER.pack(_MAGIC, _VERSION, kind, msg.seq, msg.origin_ns, msg.send_ns, msg.source, msg.origin_clock, msg.send_clock, min(msg.forwards, MAX_FORWARDS))
        return data, header + extra if extra else header, ENCODINGS[kind]
    payload = msg.payload
    extra = b""
    if isinstance(payload, (bytes, bytearray)):
        kind, data = _BYTES, payload
    elif isinstance(payload, memoryview):
        kind, data = _BYTES, payload.tobytes()
    elif isinstance(payload, str):
        kind, data = _TEXT, payload.encode()
    elif _is_array(payload):
        kind = _ARRAY
        extra = _array_meta(payload)
        data = sys.modules["numpy"].ascontiguousarray(payload).tobytes()  # (imported: the payload is an array)
    else:
        kind = _JSON
        try:
            data = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
        except TypeError as exc:  # arrays inside (else something JSON cannot hold: said again below)
            data, extra = _encode_parts(payload, exc)
            kind = _PARTS
        except ValueError as exc:
            raise PayloadError(f"cannot encode the payload as JSON: {exc}") from exc
    header = HEADER.pack(_MAGIC, _VERSION, kind, msg.seq, msg.origin_ns, msg.send_ns, msg.source, msg.origin_clock, msg.send_clock, min(msg.forwards, MAX_FORWARDS))
    return data, header + extra, ENCODINGS[kind]


def _array_meta(array: Any) -> bytes:
    dtype = array.dtype.str.encode()
    if array.ndim > 255 or array.dtype.hasobject:
        raise PayloadError(f"cannot send an array of dtype {array.dtype} with {array.ndim} dims", expected="numbers, at most 255 dims")
    return _ARRAY_META.pack(array.ndim, len(dtype)) + dtype + struct.pack(f"<{array.ndim}Q", *array.shape)


def _encode_parts(payload: Any, failure: TypeError) -> tuple[bytes, bytes]:
    """``(payload, attachment after the header)`` of a JSON-like value holding numpy arrays."""
    import numpy as np

    arrays: list[tuple[str, Any]] = []
    skeleton = _split(payload, "", arrays, 0)
    if not arrays:
        raise PayloadError(f"cannot encode the payload as JSON: {failure}") from failure
    if len(arrays) > _MAX_PARTS:  # the smallest go as JSON lists
        keep = {path for path, _ in sorted(arrays, key=lambda item: item[1].nbytes)[len(arrays) - _MAX_PARTS :]}
        listed = {path: array.tolist() for path, array in arrays if path not in keep}
        arrays = [(path, array) for path, array in arrays if path in keep]
        skeleton = _fill(skeleton, listed)
    try:
        text = json.dumps(skeleton, separators=(",", ":"), allow_nan=False).encode()
    except (TypeError, ValueError) as exc:
        raise PayloadError(f"cannot encode the payload as JSON: {exc}") from exc
    extra = [bytes([len(arrays)])]
    data: list[Any] = [text]
    for path, array in arrays:
        encoded = path.encode()
        extra += [_PATH_LENGTH.pack(len(encoded)), encoded, _array_meta(array)]
        data.append(np.ascontiguousarray(array).reshape(-1).view(np.uint8))  # a view: join copies it once
    return b"".join(data), b"".join(extra)


def _split(value: Any, path: str, arrays: list[tuple[str, Any]], depth: int) -> Any:
    """``value`` with each numpy array in it replaced by None, its path and itself in ``arrays``."""
    if _is_array(value):
        arrays.append((path, value))
        return None
    if depth > 64:
        raise PayloadError("a payload nested more than 64 levels deep", expected="JSON-like values at most 64 levels deep")
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise PayloadError(f"a key {key!r} of type {type(key).__name__} beside arrays", expected="text keys")
            out[key] = _split(item, f"{path}/{key.replace('~', '~0').replace('/', '~1')}", arrays, depth + 1)
        return out
    if isinstance(value, (list, tuple)):
        return [_split(item, f"{path}/{i}", arrays, depth + 1) for i, item in enumerate(value)]
    return value


def _fill(skeleton: Any, values: dict[str, Any]) -> Any:
    for path, value in values.items():
        _place(skeleton, path, value, "")
    return skeleton


def _place(root: Any, path: str, value: Any, key: str) -> None:
    """Put ``value`` where JSON Pointer ``path`` points in ``root``, in place of a null."""
    where = f"array {path[:80]!r} of the message on {key!r}"
    if not path.startswith("/"):
        raise PayloadError("a path not starting with /", where=where, expected="a JSON Pointer")
    parts = [p.replace("~1", "/").replace("~0", "~") for p in path[1:].split("/")]
    node = root
    for i, part in enumerate(parts):
        if isinstance(node, dict):
            index: Any = part
            found = part in node
        elif isinstance(node, list) and part.isascii() and part.isdigit() and len(part) < 10:
            index = int(part)
            found = index < len(node)
        else:
            found = False
        if not found:
            raise PayloadError("a path that leads nowhere in the JSON text", where=where, expected="the path of a null in it")
        if i == len(parts) - 1:
            if node[index] is not None:
                raise PayloadError("a path to a value that is not null", where=where, expected="the path of a null in it")
            node[index] = value
        else:
            node = node[index]


def _decode_parts(raw: bytes, attachment: bytes, at: int, key: str) -> Any:
    """The JSON-like value of a kind 4 payload, its arrays read-only views of ``raw``."""
    import numpy as np

    where = f"message on {key!r}"
    try:
        count = attachment[at]
        at += 1
        parts: list[tuple[str, Any, tuple[int, ...], int]] = []
        total = 0
        for _ in range(count):
            (length,) = _PATH_LENGTH.unpack_from(attachment, at)
            path = attachment[at + 2 : at + 2 + length].decode()
            at += 2 + length
            ndim, dlen = _ARRAY_META.unpack_from(attachment, at)
            at += _ARRAY_META.size
            dtype = np.dtype(attachment[at : at + dlen].decode())
            at += dlen
            shape = struct.unpack_from(f"<{ndim}Q", attachment, at)
            at += 8 * ndim
            if dtype.hasobject or dtype.itemsize == 0:
                raise PayloadError(f"an array of dtype {dtype}", where=where, expected="numbers")
            size = dtype.itemsize
            for n in shape:
                size *= n
            parts.append((path, dtype, shape, size))
            total += size
    except (struct.error, IndexError, TypeError, ValueError, SyntaxError) as exc:  # (numpy's dtype parser raises SyntaxError too)
        raise PayloadError(f"a malformed list of arrays ({type(exc).__name__}: {exc})", where=where, expected="kind 4's layout") from exc
    if total > len(raw):
        raise PayloadError(f"arrays of {total} bytes in {len(raw)}", where=where, expected="the arrays' bytes at the payload's end")
    text_end = len(raw) - total
    try:
        value = json_text(raw[:text_end])
    except (ValueError, RecursionError) as exc:
        raise PayloadError(f"JSON text that does not parse ({exc})", where=where, expected="JSON") from exc
    offset = text_end
    for path, dtype, shape, size in parts:
        array = np.frombuffer(raw, dtype=dtype, count=size // dtype.itemsize, offset=offset).reshape(shape)  # read-only: immutable bytes
        _place(value, path, array, key)
        offset += size
    return value


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


_SCAN: Final[Any] = json.scanner.make_scanner(json.JSONDecoder())  # type: ignore[arg-type]  # (json's C scanner, where there is one)


def json_text(raw: bytes) -> Any:
    """``json.loads(raw)``, the same value or the same error for any bytes, quicker for the JSON
    text of a message (UTF-8, as the wire format says): json's own scanner reads it without the
    Python steps of ``json.loads`` (guessing the encoding, a decoder's ``raw_decode``), 1.1 us
    instead of 2.6 for a small object. Text that may be in another encoding json.loads guesses
    (a byte order mark, a zero byte among the first two) goes to ``json.loads``."""
    if len(raw) < 2 or raw[0] in (0, 0xEF, 0xFE, 0xFF) or raw[1] == 0:
        return json.loads(raw)
    text = raw.decode("utf-8", "surrogatepass")
    try:
        value, end = _SCAN(text, _space(text, 0))
    except StopIteration as exc:
        raise json.JSONDecodeError("Expecting value", text, exc.value) from None
    end = _space(text, end)
    if end != len(text):
        raise json.JSONDecodeError("Extra data", text, end)
    return value


def _space(text: str, at: int) -> int:
    """Past the JSON whitespace from ``at``."""
    n = len(text)
    while at < n and text[at] in " \t\n\r":
        at += 1
    return at


def decode_dyknow(data: Any, attachment: bytes, key: str) -> Message:
    """:func:`decode` for a sample known to carry a dyknow header (the transport checked)."""
    raw = data if type(data) is bytes else data.to_bytes()
    version = attachment[2]
    forwards = 0
    if version == _VERSION and len(attachment) >= HEADER.size:
        _, _, kind, mseq, origin_ns, send_ns, source, origin_clock, send_clock, forwards = HEADER.unpack_from(attachment)
        size = HEADER.size
    elif version == _V2 and len(attachment) >= HEADER_V2.size:
        _, _, kind, mseq, origin_ns, send_ns, source, origin_clock, send_clock = HEADER_V2.unpack_from(attachment)
        size = HEADER_V2.size
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
        return Message(json_text(raw), mseq, origin_ns, send_ns, key, len(raw), None, source, origin_clock, send_clock, forwards)
    elif kind == _PARTS:  # mutable too
        value = _decode_parts(raw, attachment, size, key)
        return Message(value, mseq, origin_ns, send_ns, key, len(raw), None, source, origin_clock, send_clock, forwards)
    elif kind == _ARRAY:
        import numpy as np

        ndim, dlen = _ARRAY_META.unpack_from(attachment, size)
        pos = size + _ARRAY_META.size
        dtype = np.dtype(attachment[pos : pos + dlen].decode())
        shape = struct.unpack_from(f"<{ndim}Q", attachment, pos + dlen)
        payload = np.frombuffer(raw, dtype=dtype).reshape(shape)  # read-only: it views immutable bytes
        extra = attachment[size:]
    else:
        raise PayloadError(
            f"unknown payload kind {kind}", where=f"message on {key!r}", expected="0 to 4 (bytes, text, JSON, array, JSON with arrays)"
        )
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
    version = attachment[2]
    if version == _VERSION and len(attachment) == HEADER.size:
        _, _, kind, prev_seq, origin_ns, sent_ns, prev_source, origin_clock, sent_clock, forwards = HEADER.unpack_from(attachment)
    elif version == _V2 and len(attachment) == HEADER_V2.size:
        _, _, kind, prev_seq, origin_ns, sent_ns, prev_source, origin_clock, sent_clock = HEADER_V2.unpack_from(attachment)
        forwards = 0
    else:
        return None
    if kind != _BYTES:
        return None
    onward = min(forwards + 1, MAX_FORWARDS)
    header = HEADER.pack(_MAGIC, _VERSION, _BYTES, seq, origin_ns, send_ns, source, origin_clock, CLOCK_ID, onward)
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
