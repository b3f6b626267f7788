"""Recording dyknow streams to MCAP files that Foxglove and other MCAP tools can read.

A :class:`Recorder` subscribes to key expressions (or a unit feeds it messages) and writes each
message to an MCAP file. Every key gets its own channel. The message header goes into the MCAP
message: ``log_time`` is the origin timestamp, ``publish_time`` the send timestamp and
``sequence`` the sequence number. The file is chunked and compressed (zstd by default, or lz4 or
none) and has a summary with statistics and chunk, message and metadata indexes::

    from dyknow.recording import Recorder

    with Recorder(["robot/**"], "run.mcap", connect=["tcp/127.0.0.1:7447"]) as rec:
        rec.wait(10.0)        # wait for max_messages, or do something else, then close
    print(rec.count, rec.topics)

Payloads are stored as follows (``dyknow mcap cat`` prints the ``data`` column):

======================  ===============================  ============================  ======================================
payload                 schema (schema encoding)         message encoding              data
======================  ===============================  ============================  ======================================
JSON-like value         named after the key, derived     ``json``                      the compact JSON text dyknow sends
                        from its first message
                        (``jsonschema``)
``str``                 none                             ``text/plain;charset=utf-8``  UTF-8 text
``bytes``               none                             ``application/octet-stream``  the bytes
JPEG, PNG, WebP bytes   ``foxglove.CompressedImage``     ``protobuf``                  Foxglove's message; format jpeg/png/webp
image array             ``foxglove.RawImage``            ``protobuf``                  Foxglove's message: mono8, bgr8, ...
other numpy array       ``dyknow.NDArray``               ``protobuf``                  dtype, shape, bytes in C order
======================  ===============================  ============================  ======================================

An *image array* is a ``uint8`` array of shape H×W (recorded as ``mono8``), H×W×3 (``bgr8``, the
channel order OpenCV uses) or H×W×4 (``bgra8``), or a little-endian ``uint16`` H×W array
(``mono16``). Any other array is a ``dyknow.NDArray``: ``string dtype = 1`` (numpy's dtype string,
such as ``<f8``), ``repeated uint64 shape = 2`` and ``bytes data = 3``.

Why protobuf for images: Foxglove ships ``foxglove.RawImage`` and ``foxglove.CompressedImage``
as protobuf schemas. The pixel bytes are stored unchanged, so recording a frame costs one copy.
JSON would need base64, which makes frames a third larger and costs an extra pass over every
frame. The schema (a protobuf ``FileDescriptorSet``) is embedded in the file, so Foxglove shows
the images with nothing else installed.

A key whose payloads change kind (JSON, then bytes, say) gets one channel per kind, all with the
key as topic. Each channel's metadata records ``dyknow.payload`` (``bytes``, ``text``, ``json`` or
``ndarray``). Replay uses it to give back exactly the payload type that was published. For
example, JPEG bytes stay bytes, while a foreign compressed image is decoded to an array.

Nothing is lost on the way to the disk. A Zenoh callback only puts the message on a queue, and a
writer thread of its own encodes and writes it. Chunks are handed to the operating system as they
fill, and at least every ``flush_interval_s``. So a recorder killed with SIGKILL leaves a file
whose complete chunks a recovering reader (``Player(..., recover=True)``, ``dyknow replay
--recover``) still replays. :meth:`Recorder.close` writes the summary and the footer. A write
that fails, for example on a full disk, stops the recorder with a :class:`RecordingError` that
names the file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import queue
import struct
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from importlib import metadata as _metadata
from typing import Any

import numpy as np
from mcap.writer import CompressionType, IndexType, Writer

from dyknow.errors import ClosedError, RecordingError
from dyknow.message import Message
from dyknow.transport import Session, Subscriber, check_key_expr, make_config

__all__ = [
    "COMPRESSIONS",
    "COMPRESSED_IMAGE",
    "NDARRAY",
    "PAYLOAD_METADATA",
    "PROTOBUF_SCHEMAS",
    "RAW_IMAGE",
    "Recorder",
    "RecordingError",
    "image_encoding",
]

log = logging.getLogger(__name__)

#: The chunk compressions :class:`Recorder` accepts.
COMPRESSIONS: tuple[str, ...] = ("zstd", "lz4", "none")

#: Schema names of the protobuf messages dyknow writes.
RAW_IMAGE = "foxglove.RawImage"
COMPRESSED_IMAGE = "foxglove.CompressedImage"
NDARRAY = "dyknow.NDArray"

#: The channel metadata entry that records the kind of payload published (bytes, text, json, ndarray).
PAYLOAD_METADATA = "dyknow.payload"

_TEXT_ENCODING = "text/plain;charset=utf-8"
_BYTES_ENCODING = "application/octet-stream"
_COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

# Image arrays and the Foxglove/ROS encoding they are recorded as, by (dtype, channels). Only
# layouts that replay back to the very same dtype and shape are images; the rest are NDArrays.
_IMAGE_ENCODINGS = {
    ("|u1", 0): "mono8",
    ("|u1", 3): "bgr8",
    ("|u1", 4): "bgra8",
    ("<u2", 0): "mono16",
}

_STOP = object()


def image_encoding(array: np.ndarray) -> str | None:
    """The ``foxglove.RawImage`` encoding an array is recorded as, or None if it is no image.

    >>> image_encoding(np.zeros((480, 640, 3), np.uint8))
    'bgr8'
    """
    if array.ndim == 2:
        channels = 0
    elif array.ndim == 3 and array.shape[2] in (3, 4):
        channels = array.shape[2]
    else:
        return None
    if array.shape[0] == 0 or array.shape[1] == 0:
        return None
    return _IMAGE_ENCODINGS.get((array.dtype.str, channels))


def _image_format(data: bytes) -> str | None:
    """``jpeg``, ``png`` or ``webp`` when ``data`` starts like such a file, else None."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    return None


# --------------------------------------------------------------------------- protobuf, minimal
#
# Only what the three messages above need: writing them and their FileDescriptorSets (replay.py
# reads them). The protobuf package would do the same at the cost of a dependency and of
# generated code.


def _varint(value: int) -> bytes:
    value &= 0xFFFFFFFFFFFFFFFF  # negative int64 values take ten bytes, as in protobuf
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _pb_len(number: int, data: bytes) -> bytes:
    return _varint(number << 3 | 2) + _varint(len(data)) + data


def _pb_str(number: int, text: str) -> bytes:
    return _pb_len(number, text.encode()) if text else b""


def _pb_uint(number: int, value: int) -> bytes:
    return _varint(number << 3) + _varint(value) if value else b""


def _pb_fixed32(number: int, value: int) -> bytes:
    return _varint(number << 3 | 5) + struct.pack("<I", value)


def _pb_timestamp(number: int, time_ns: int) -> bytes:
    seconds, nanos = divmod(time_ns, 1_000_000_000)
    return _pb_len(number, _pb_uint(1, seconds) + _pb_uint(2, nanos))


# FieldDescriptorProto types and labels
_INT64, _UINT64, _INT32, _FIXED32, _STRING, _MESSAGE, _BYTES = 3, 4, 5, 7, 9, 11, 12
_OPTIONAL, _REPEATED = 1, 3


def _field_descriptor(name: str, number: int, type_: int, label: int = _OPTIONAL, type_name: str = "") -> bytes:
    json_name = name.split("_")[0] + "".join(part.title() for part in name.split("_")[1:])
    return (
        _pb_str(1, name) + _pb_uint(3, number) + _pb_uint(4, label) + _pb_uint(5, type_)
        + _pb_str(6, type_name) + _pb_str(10, json_name)
    )  # fmt: skip


def _file_descriptor(name: str, package: str, message: str, fields: Sequence[bytes], dependencies: Sequence[str] = ()) -> bytes:
    body = b"".join(_pb_len(2, f) for f in fields)
    return (
        _pb_str(1, name) + _pb_str(2, package) + b"".join(_pb_str(3, d) for d in dependencies)
        + _pb_len(4, _pb_str(1, message) + body) + _pb_str(12, "proto3")
    )  # fmt: skip


_TIMESTAMP_FILE = _file_descriptor(
    "google/protobuf/timestamp.proto", "google.protobuf", "Timestamp",
    [_field_descriptor("seconds", 1, _INT64), _field_descriptor("nanos", 2, _INT32)],
)  # fmt: skip
_TIMESTAMP_FIELD = _field_descriptor("timestamp", 1, _MESSAGE, type_name=".google.protobuf.Timestamp")

#: FileDescriptorSets (the schema data of a ``protobuf`` schema) by schema name.
PROTOBUF_SCHEMAS: Mapping[str, bytes] = {
    RAW_IMAGE: _pb_len(1, _TIMESTAMP_FILE) + _pb_len(1, _file_descriptor(
        "foxglove/RawImage.proto", "foxglove", "RawImage",
        [
            _TIMESTAMP_FIELD,
            _field_descriptor("frame_id", 7, _STRING),
            _field_descriptor("width", 2, _FIXED32),
            _field_descriptor("height", 3, _FIXED32),
            _field_descriptor("encoding", 4, _STRING),
            _field_descriptor("step", 5, _FIXED32),
            _field_descriptor("data", 6, _BYTES),
        ],
        ["google/protobuf/timestamp.proto"],
    )),
    COMPRESSED_IMAGE: _pb_len(1, _TIMESTAMP_FILE) + _pb_len(1, _file_descriptor(
        "foxglove/CompressedImage.proto", "foxglove", "CompressedImage",
        [
            _TIMESTAMP_FIELD,
            _field_descriptor("frame_id", 4, _STRING),
            _field_descriptor("data", 2, _BYTES),
            _field_descriptor("format", 3, _STRING),
        ],
        ["google/protobuf/timestamp.proto"],
    )),
    NDARRAY: _pb_len(1, _file_descriptor(
        "dyknow/NDArray.proto", "dyknow", "NDArray",
        [
            _field_descriptor("dtype", 1, _STRING),
            _field_descriptor("shape", 2, _UINT64, _REPEATED),
            _field_descriptor("data", 3, _BYTES),
        ],
    )),
}  # fmt: skip


def _raw_image(array: np.ndarray, encoding: str, time_ns: int) -> bytes:
    height, width = array.shape[:2]
    data = np.ascontiguousarray(array).data
    step = data.nbytes // height
    head = (
        _pb_timestamp(1, time_ns) + _pb_fixed32(2, width) + _pb_fixed32(3, height) + _pb_str(4, encoding)
        + _pb_fixed32(5, step) + _varint(6 << 3 | 2) + _varint(data.nbytes)
    )  # fmt: skip
    return b"".join((head, data))


def _compressed_image(data: bytes, image_format: str, time_ns: int) -> bytes:
    return b"".join((_pb_timestamp(1, time_ns), _varint(2 << 3 | 2), _varint(len(data)), data, _pb_str(3, image_format)))


def _ndarray(array: np.ndarray) -> bytes:
    data = np.ascontiguousarray(array).data
    shape = b"".join(_varint(n) for n in array.shape)
    head = _pb_str(1, array.dtype.str) + (_pb_len(2, shape) if shape else b"") + _varint(3 << 3 | 2) + _varint(data.nbytes)
    return b"".join((head, data))


# --------------------------------------------------------------------------- payload -> MCAP


def _json_schema(value: Any, depth: int = 0) -> dict[str, Any]:
    """A permissive JSON schema describing ``value``: field names and types, nothing required."""
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, (int, float)):
        return {"type": "number"}
    if isinstance(value, str):
        return {"type": "string"}
    if isinstance(value, (list, tuple)):
        return {"type": "array"}
    if isinstance(value, dict) and depth < 8:
        return {"type": "object", "properties": {str(k): _json_schema(v, depth + 1) for k, v in value.items()}}
    if isinstance(value, dict):
        return {"type": "object"}
    return {}


def _encode(payload: Any, time_ns: int) -> tuple[str, str, str, bytes]:
    """``(kind, message encoding, schema name, data)`` for a payload."""
    if isinstance(payload, np.ndarray):
        if payload.dtype.hasobject:
            raise RecordingError(f"cannot record an array of dtype {payload.dtype}; expected numbers")
        encoding = image_encoding(payload)
        if encoding is not None:
            return "ndarray", "protobuf", RAW_IMAGE, _raw_image(payload, encoding, time_ns)
        return "ndarray", "protobuf", NDARRAY, _ndarray(payload)
    if isinstance(payload, (bytes, bytearray, memoryview)):
        data = bytes(payload)
        image_format = _image_format(data)
        if image_format is not None:
            return "bytes", "protobuf", COMPRESSED_IMAGE, _compressed_image(data, image_format, time_ns)
        return "bytes", _BYTES_ENCODING, "", data
    if isinstance(payload, str):
        return "text", _TEXT_ENCODING, "", payload.encode()
    try:  # the very text dyknow puts on the wire (message.encode), so replay is byte-identical
        data = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"cannot record a payload of type {type(payload).__name__}: {exc}") from exc
    return "json", "json", "", data


class _Output:
    """The file under the MCAP writer: every write goes to the operating system at once.

    The writer writes a whole chunk (and its message indexes) per call, so flushing each write
    costs little and a process killed at any moment leaves every complete chunk on disk.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self._file = open(path, "wb")  # noqa: SIM115 (closed by close())
        self.written = 0

    def write(self, data: bytes) -> int:
        count = self._file.write(data)
        self._file.flush()
        self.written += len(data)
        return count

    def tell(self) -> int:
        return self._file.tell()

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def _write_error(path: str, exc: OSError, what: str) -> RecordingError:
    reason = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return RecordingError(f"cannot write {path}: {reason} (the disk is full); {what}")
    return RecordingError(f"cannot write {path}: {reason}; {what}")


def _library() -> str:
    try:
        version = _metadata.version("dyknow")
    except _metadata.PackageNotFoundError:
        version = "dev"
    return f"dyknow {version}"


class Recorder:
    """Records dyknow streams to an MCAP file. A context manager; ``close()`` finalizes the file.

    ``key_exprs``: key expressions to subscribe to (wildcards allowed). They are received through
    ``session``, or through a session of the recorder's own connected to ``connect`` (or set up
    by ``zenoh_config``). Zenoh delivers a session only what *other* sessions publish, so pass a
    session other than the publishers'. With no key expressions the recorder takes messages
    through :meth:`write` only, which is how the ``recorder`` unit feeds it.

    ``compression`` is one of :data:`COMPRESSIONS`. ``chunk_size`` is the uncompressed size at
    which a chunk is written. ``flush_interval_s`` bounds how long a message stays in memory
    before its chunk goes to disk. ``max_messages`` stops the recording after that many messages
    (:meth:`wait` returns then). ``metadata`` goes into an MCAP metadata record named ``dyknow``.

    Raises :class:`RecordingError` when the file cannot be created or written.
    """

    def __init__(
        self,
        key_exprs: Sequence[str] | str = (),
        path: str | os.PathLike[str] = "recording.mcap",
        *,
        session: Session | None = None,
        connect: Iterable[str] = (),
        zenoh_config: str | os.PathLike[str] | None = None,
        compression: str = "zstd",
        chunk_size: int = 1024 * 1024,
        flush_interval_s: float = 1.0,
        max_messages: int | None = None,
        metadata: Mapping[str, str] | None = None,
    ) -> None:
        keys = [key_exprs] if isinstance(key_exprs, str) else list(key_exprs)
        for key in keys:
            check_key_expr(key, what="key expression to record")
        if compression not in _COMPRESSIONS:
            raise RecordingError(f"compression: got {compression!r}; expected one of {', '.join(COMPRESSIONS)}")
        if chunk_size < 1:
            raise RecordingError(f"chunk_size: got {chunk_size}; expected a positive number of bytes")
        if not flush_interval_s > 0:
            raise RecordingError(f"flush_interval_s: got {flush_interval_s}; expected a positive number of seconds")
        if max_messages is not None and max_messages < 1:
            raise RecordingError(f"max_messages: got {max_messages}; expected a positive number")
        self.path = os.fspath(path)
        self.key_exprs: tuple[str, ...] = tuple(keys)
        self.max_messages = max_messages
        self._flush_interval_s = flush_interval_s
        self._lock = threading.Lock()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._done = threading.Event()
        self._closed = False
        self._accepted = 0
        self._count = 0
        self._dropped = 0
        self._topics: dict[str, int] = {}
        self._error: RecordingError | None = None
        self._subscribers: list[Subscriber] = []
        self._session: Session | None = None
        self._own_session = False
        try:
            self._out = _Output(self.path)
        except OSError as exc:
            hint = " (does the folder exist?)" if isinstance(exc, FileNotFoundError) else ""
            raise RecordingError(f"cannot create {self.path}: {exc.strerror or exc}{hint}") from exc
        try:
            self._writer = Writer(
                self._out,  # type: ignore[arg-type]
                chunk_size=chunk_size,
                compression=_COMPRESSIONS[compression],
                index_types=IndexType.ALL,
                repeat_channels=True,
                repeat_schemas=True,
                use_chunking=True,
                use_statistics=True,
                use_summary_offsets=True,
                enable_crcs=True,
            )
            self._writer.start(profile="", library=_library())
            info = {"key_exprs": json.dumps(list(keys)), "started_ns": str(time.time_ns())}
            self._writer.add_metadata("dyknow", {**info, **dict(metadata or {})})
        except OSError as exc:
            with contextlib.suppress(OSError):  # the same error again, flushing what the failed write left
                self._out.close()
            raise _write_error(self.path, exc, "nothing was recorded") from exc
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[tuple[str, str, str, str], int] = {}
        self._thread = threading.Thread(target=self._run, name=f"dyknow-recorder:{os.path.basename(self.path)}", daemon=True)
        self._thread.start()
        if keys:
            try:
                if session is None:
                    session = Session(make_config(connect=list(connect), config_file=zenoh_config))
                    self._own_session = True
                self._session = session
                for key in keys:
                    self._subscribers.append(session.declare_subscriber(key, self.write, self._on_error))
            except BaseException:
                self.close()
                with contextlib.suppress(OSError):
                    os.remove(self.path)  # nothing was recorded: leave no empty file behind
                raise
        log.info("recording %s to %s", ", ".join(keys) or "(fed by write())", self.path)

    # ------------------------------------------------------------------ state

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "recording"
        return f"Recorder({self.path!r}, {state}, {self._count} messages)"

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    @property
    def count(self) -> int:
        """Messages written to the file so far (all of them once closed)."""
        return self._count

    @property
    def topics(self) -> dict[str, int]:
        """Messages written so far per key."""
        return dict(self._topics)

    @property
    def dropped(self) -> int:
        """Messages that arrived but are not in the file: after a write error, or at a close that timed out."""
        return self._dropped

    @property
    def error(self) -> RecordingError | None:
        """The error that stopped the recording, if any."""
        return self._error

    @property
    def bytes_written(self) -> int:
        """Bytes handed to the file so far (its size once closed)."""
        return self._out.written

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until ``max_messages`` were received or the recording failed; True if so."""
        return self._done.wait(timeout)

    # ------------------------------------------------------------------ recording

    def write(self, msg: Message) -> None:
        """Record one message (any thread). Its key names the channel.

        Raises :class:`ClosedError` after close and the recording's error after a failed write.
        """
        with self._lock:
            if self._closed:
                raise ClosedError(f"the recorder of {self.path} is closed; start a new one")
            if self._error is not None:
                raise self._error
            if self.max_messages is not None and self._accepted >= self.max_messages:
                return
            self._accepted += 1
            self._queue.put(msg)
            if self._accepted == self.max_messages:
                self._done.set()

    def _on_error(self, exc: BaseException) -> None:
        # After a failed write or during close every message raises the same error: say it once.
        if exc is not self._error and not isinstance(exc, ClosedError):
            log.warning("recorder %s: %s", self.path, exc)

    def _run(self) -> None:
        """The writer thread: encodes and writes messages, flushes chunks that get old."""
        interval = self._flush_interval_s
        deadline = time.monotonic() + interval
        pending = False
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            if item is not None:
                if self._error is not None:
                    self._dropped += 1
                else:
                    self._write(item)
                    pending = True
            if time.monotonic() >= deadline:
                if pending and self._error is None:
                    try:
                        self._writer.flush()
                    except OSError as exc:
                        self._fail(exc)
                    pending = False
                deadline = time.monotonic() + interval

    def _write(self, msg: Message) -> None:
        try:
            kind, encoding, schema_name, data = _encode(msg.payload, msg.origin_ns)
        except RecordingError as exc:
            self._dropped += 1
            log.warning("recorder %s: message on %s not recorded: %s", self.path, msg.key, exc)
            return
        try:
            channel = self._channel(msg.key, kind, encoding, schema_name, msg.payload)
            self._writer.add_message(
                channel_id=channel,
                log_time=max(0, msg.origin_ns),
                publish_time=max(0, msg.send_ns),
                sequence=msg.seq & 0xFFFFFFFF,
                data=data,
            )
        except OSError as exc:
            self._dropped += 1
            self._fail(exc)
            return
        self._count += 1
        self._topics[msg.key] = self._topics.get(msg.key, 0) + 1

    def _fail(self, exc: OSError) -> None:
        with self._lock:
            if self._error is None:
                what = f"recording stopped after {self._count} messages; the complete chunks before it are readable"
                self._error = _write_error(self.path, exc, what)
                self._error.__cause__ = exc
                log.error("%s", self._error)
        self._done.set()

    def _channel(self, key: str, kind: str, encoding: str, schema_name: str, payload: Any) -> int:
        signature = (key, kind, encoding, schema_name)
        channel = self._channels.get(signature)
        if channel is not None:
            return channel
        schema_id = 0
        if encoding == "json":
            schema = (key, "jsonschema", json.dumps({"title": key, **_json_schema(payload)}).encode())
        elif encoding == "protobuf":
            schema = (schema_name, "protobuf", PROTOBUF_SCHEMAS[schema_name])
        else:
            schema = None
        if schema is not None:
            schema_id = self._schemas.get(schema, 0)
            if not schema_id:
                schema_id = self._schemas[schema] = self._writer.register_schema(*schema)
        channel = self._channels[signature] = self._writer.register_channel(key, encoding, schema_id, {PAYLOAD_METADATA: kind})
        return channel

    # ------------------------------------------------------------------ closing

    def close(self, timeout: float = 30.0) -> None:
        """Stop receiving, write what is queued, then the summary and footer. Safe to call twice.

        Waits up to ``timeout`` seconds for the queue to drain; what is still queued then is
        dropped (and counted in :attr:`dropped`) so that close never hangs. Raises the
        recording's :class:`RecordingError` if a write failed.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for sub in reversed(self._subscribers):
            sub.undeclare()
        self._subscribers.clear()
        if self._own_session and self._session is not None:
            self._session.close()
        self._session = None
        self._queue.put(_STOP)
        self._thread.join(timeout)
        if self._thread.is_alive():
            # Too much queued: keep what is written, drop the rest, and still finalize the file.
            with self._lock:
                if self._error is None:
                    self._error = RecordingError(f"{self.path}: writing did not finish within {timeout:g} s; the rest was dropped")
            self._thread.join(2.0)
        if self._thread.is_alive():
            log.error("recorder %s: the writer thread is stuck; the file is left without its summary", self.path)
            self._done.set()
            raise RecordingError(f"cannot finish {self.path}: its writer is stuck (a hung disk?); the complete chunks are readable")
        while True:
            try:
                if self._queue.get_nowait() is not _STOP:
                    self._dropped += 1
            except queue.Empty:
                break
        self._done.set()
        error = self._error
        try:
            self._writer.finish()
        except OSError as exc:
            if error is None:
                error = _write_error(self.path, exc, "the file has no summary; its complete chunks are readable")
        finally:
            try:
                self._out.close()
            except OSError as exc:
                if error is None:
                    error = _write_error(self.path, exc, "the file may be incomplete")
        self._error = error
        log.info("recorded %d messages to %s", self._count, self.path)
        if error is not None:
            raise error
