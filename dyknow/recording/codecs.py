"""How dyknow payloads map to MCAP message encodings and schemas, and back.

Recording (:func:`encode`), as ``dyknow mcap cat`` shows the ``data`` column:

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
frame. The schema (a protobuf ``FileDescriptorSet``, :data:`PROTOBUF_SCHEMAS`) is embedded in the
file, so Foxglove shows the images with nothing else installed. Each channel's metadata records
:data:`PAYLOAD_METADATA` (``bytes``, ``text``, ``json`` or ``ndarray``), so that replay gives back
exactly the payload type that was published: JPEG bytes stay bytes, while a foreign compressed
image is decoded to an array.

Replaying (:class:`Decoders`), from any writer's files:

- dyknow recordings give back exactly the payload type that was published: bytes, text, JSON
  values and numpy arrays;
- ``json`` messages give JSON values;
- ``foxglove.RawImage`` (protobuf or JSON) and ROS 2 ``sensor_msgs/msg/Image`` give numpy arrays.
  ``rgb8`` and ``rgba8`` images are turned into OpenCV's BGR(A) order, as dyknow's vision units
  expect;
- ``foxglove.CompressedImage`` (protobuf, or JSON with base64 data) and ROS 2
  ``sensor_msgs/msg/CompressedImage`` are decoded to numpy arrays with OpenCV when it is
  installed. Without ``cv2`` they are delivered as their JPEG/PNG bytes;
- other ROS 2 CDR messages (``std_msgs/msg/String``, ``rcl_interfaces/msg/Log``, ...) give JSON
  values (dicts of their fields; byte arrays become lists of numbers, NaN and infinities None);
- anything else (other encodings, a message that fails to decode) is delivered as its bytes,
  with one warning per channel.
"""

from __future__ import annotations

import base64
import json
import logging
import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from mcap.records import Schema

from dyknow.errors import RecordingError
from dyknow.recording import protobuf as pb

if TYPE_CHECKING:
    from dyknow.recording.reader import ChannelInfo

__all__ = [
    "COMPRESSED_IMAGE",
    "NDARRAY",
    "PAYLOAD_METADATA",
    "PROTOBUF_SCHEMAS",
    "RAW_IMAGE",
    "image_array",
    "image_encoding",
]

log = logging.getLogger(__name__)

#: Schema names of the protobuf messages dyknow writes.
RAW_IMAGE = "foxglove.RawImage"
COMPRESSED_IMAGE = "foxglove.CompressedImage"
NDARRAY = "dyknow.NDArray"

#: The channel metadata entry that records the kind of payload published (bytes, text, json, ndarray).
PAYLOAD_METADATA = "dyknow.payload"

TEXT_ENCODING = "text/plain;charset=utf-8"
BYTES_ENCODING = "application/octet-stream"

# Image arrays and the Foxglove/ROS encoding they are recorded as, by (dtype, channels). Only
# layouts that replay back to the very same dtype and shape are images; the rest are NDArrays.
_IMAGE_ENCODINGS = {
    ("|u1", 0): "mono8",
    ("|u1", 3): "bgr8",
    ("|u1", 4): "bgra8",
    ("<u2", 0): "mono16",
}

# --------------------------------------------------------------------------- schemas

_TIMESTAMP_FILE = pb.file_descriptor(
    "google/protobuf/timestamp.proto", "google.protobuf", "Timestamp",
    [pb.field_descriptor("seconds", 1, pb.INT64), pb.field_descriptor("nanos", 2, pb.INT32)],
)  # fmt: skip
_TIMESTAMP_FIELD = pb.field_descriptor("timestamp", 1, pb.MESSAGE, type_name=".google.protobuf.Timestamp")

#: FileDescriptorSets (the schema data of a ``protobuf`` schema) by schema name.
PROTOBUF_SCHEMAS: Mapping[str, bytes] = {
    RAW_IMAGE: pb.bytes_field(1, _TIMESTAMP_FILE) + pb.bytes_field(1, pb.file_descriptor(
        "foxglove/RawImage.proto", "foxglove", "RawImage",
        [
            _TIMESTAMP_FIELD,
            pb.field_descriptor("frame_id", 7, pb.STRING),
            pb.field_descriptor("width", 2, pb.FIXED32),
            pb.field_descriptor("height", 3, pb.FIXED32),
            pb.field_descriptor("encoding", 4, pb.STRING),
            pb.field_descriptor("step", 5, pb.FIXED32),
            pb.field_descriptor("data", 6, pb.BYTES),
        ],
        ["google/protobuf/timestamp.proto"],
    )),
    COMPRESSED_IMAGE: pb.bytes_field(1, _TIMESTAMP_FILE) + pb.bytes_field(1, pb.file_descriptor(
        "foxglove/CompressedImage.proto", "foxglove", "CompressedImage",
        [
            _TIMESTAMP_FIELD,
            pb.field_descriptor("frame_id", 4, pb.STRING),
            pb.field_descriptor("data", 2, pb.BYTES),
            pb.field_descriptor("format", 3, pb.STRING),
        ],
        ["google/protobuf/timestamp.proto"],
    )),
    NDARRAY: pb.bytes_field(1, pb.file_descriptor(
        "dyknow/NDArray.proto", "dyknow", "NDArray",
        [
            pb.field_descriptor("dtype", 1, pb.STRING),
            pb.field_descriptor("shape", 2, pb.UINT64, pb.REPEATED),
            pb.field_descriptor("data", 3, pb.BYTES),
        ],
    )),
}  # fmt: skip

# --------------------------------------------------------------------------- payload -> MCAP


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


def image_format(data: bytes) -> str | None:
    """``jpeg``, ``png`` or ``webp`` when ``data`` starts like such a file, else None."""
    if data[:3] == b"\xff\xd8\xff":
        return "jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "webp"
    return None


def raw_image(array: np.ndarray, encoding: str, time_ns: int) -> bytes:
    """A ``foxglove.RawImage`` message holding the array's pixels unchanged."""
    height, width = array.shape[:2]
    data = np.ascontiguousarray(array).data
    step = data.nbytes // height
    head = (
        pb.timestamp_field(1, time_ns) + pb.fixed32_field(2, width) + pb.fixed32_field(3, height)
        + pb.string_field(4, encoding) + pb.fixed32_field(5, step) + pb.length_prefix(6, data.nbytes)
    )  # fmt: skip
    return b"".join((head, data))


def compressed_image(data: bytes, image_format: str, time_ns: int) -> bytes:
    """A ``foxglove.CompressedImage`` message holding JPEG, PNG or WebP bytes."""
    return b"".join((pb.timestamp_field(1, time_ns), pb.length_prefix(2, len(data)), data, pb.string_field(3, image_format)))


def ndarray(array: np.ndarray) -> bytes:
    """A ``dyknow.NDArray`` message: dtype, shape and the bytes in C order."""
    data = np.ascontiguousarray(array).data
    shape = b"".join(pb.varint(n) for n in array.shape)
    head = pb.string_field(1, array.dtype.str) + (pb.bytes_field(2, shape) if shape else b"") + pb.length_prefix(3, data.nbytes)
    return b"".join((head, data))


def json_schema(value: Any, depth: int = 0) -> dict[str, Any]:
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
        return {"type": "object", "properties": {str(k): json_schema(v, depth + 1) for k, v in value.items()}}
    if isinstance(value, dict):
        return {"type": "object"}
    return {}


def encode(payload: Any, time_ns: int) -> tuple[str, str, str, bytes]:
    """``(kind, message encoding, schema name, data)`` for a payload; ``time_ns`` stamps images.

    Raises :class:`RecordingError` for a payload that cannot be recorded.
    """
    if isinstance(payload, np.ndarray):
        if payload.dtype.hasobject:
            raise RecordingError(f"cannot record an array of dtype {payload.dtype}", expected="numbers")
        encoding = image_encoding(payload)
        if encoding is not None:
            return "ndarray", "protobuf", RAW_IMAGE, raw_image(payload, encoding, time_ns)
        return "ndarray", "protobuf", NDARRAY, ndarray(payload)
    if isinstance(payload, (bytes, bytearray, memoryview)):
        data = bytes(payload)
        kind = image_format(data)
        if kind is not None:
            return "bytes", "protobuf", COMPRESSED_IMAGE, compressed_image(data, kind, time_ns)
        return "bytes", BYTES_ENCODING, "", data
    if isinstance(payload, str):
        return "text", TEXT_ENCODING, "", payload.encode()
    try:  # the very text dyknow puts on the wire (message.encode), so replay is byte-identical;
        # arrays inside (a ROS 2 message's data) are recorded as JSON lists, and replayed so
        data = json.dumps(payload, separators=(",", ":"), allow_nan=False, default=_listed).encode()
    except (TypeError, ValueError) as exc:
        raise RecordingError(
            f"cannot record a payload of type {type(payload).__name__}: {exc}", expected="bytes, str, a numpy array or a JSON value"
        ) from exc
    return "json", "json", "", data


def _listed(value: Any) -> Any:
    if isinstance(value, np.ndarray) and not value.dtype.hasobject:
        return value.tolist()
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


# --------------------------------------------------------------------------- MCAP -> payload

# Image encodings (lower case) -> (numpy type code, channels); 1 channel gives an H x W array.
_IMAGE_LAYOUTS = {
    "mono8": ("u1", 1), "8uc1": ("u1", 1), "bgr8": ("u1", 3), "rgb8": ("u1", 3), "8uc3": ("u1", 3),
    "bgra8": ("u1", 4), "rgba8": ("u1", 4), "8uc4": ("u1", 4), "mono16": ("u2", 1), "16uc1": ("u2", 1),
    "16sc1": ("i2", 1), "32sc1": ("i4", 1), "32fc1": ("f4", 1), "64fc1": ("f8", 1), "8sc1": ("i1", 1),
}  # fmt: skip


def image_array(width: int, height: int, encoding: str, step: int, data: bytes | memoryview, bigendian: bool = False) -> np.ndarray:
    """A raw image (ROS ``sensor_msgs/Image`` or ``foxglove.RawImage`` fields) as a numpy array.

    Colour images come in OpenCV's BGR(A) order: ``rgb8`` and ``rgba8`` are converted. Multi-byte
    pixels come in the machine's byte order. Raises ``ValueError`` for encodings it does not know
    (Bayer and YUV among them) and for data too short for the size given.
    """
    layout = _IMAGE_LAYOUTS.get(encoding.lower())
    if layout is None:
        raise ValueError(f"image encoding {encoding!r} is not supported; expected one of {', '.join(sorted(_IMAGE_LAYOUTS))}")
    code, channels = layout
    dtype = np.dtype((">" if bigendian else "<") + code)
    row = width * channels * dtype.itemsize
    buffer = np.frombuffer(data, np.uint8)
    if step < row or buffer.size < step * height:
        raise ValueError(f"{encoding} image of {width}x{height}: {buffer.size} bytes with step {step} are too few")
    rows = buffer[: step * height].reshape(height, step)[:, :row]
    if step != row:
        rows = np.ascontiguousarray(rows)
    array = rows.view(dtype).reshape((height, width, channels) if channels > 1 else (height, width))
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    if encoding.lower() == "rgb8":
        array = np.ascontiguousarray(array[..., ::-1])
    elif encoding.lower() == "rgba8":
        array = np.ascontiguousarray(array[..., [2, 1, 0, 3]])
    return array


def _cv2() -> Any:
    """OpenCV, imported on first use; None when it is not installed."""
    try:
        import cv2
    except ImportError:
        return None
    return cv2


def _pb_raw_image(data: bytes) -> np.ndarray:
    f = pb.decode(data)
    return image_array(pb.last(f, 2, 0), pb.last(f, 3, 0), pb.text(f, 4), pb.last(f, 5, 0), pb.last(f, 6, b""))


def _pb_compressed_bytes(data: bytes) -> bytes:
    return bytes(pb.last(pb.decode(data), 2, b""))


def _pb_ndarray(data: bytes) -> np.ndarray:
    f = pb.decode(data)
    dtype = np.dtype(pb.text(f, 1))
    shape = pb.uints(f.get(2, []))
    return np.frombuffer(pb.last(f, 3, b""), dtype).reshape(shape)


def _json_raw_image(data: bytes) -> np.ndarray:
    obj = json.loads(data)
    return image_array(int(obj["width"]), int(obj["height"]), str(obj["encoding"]), int(obj["step"]), base64.b64decode(obj["data"]))


def _ros_image(msg: Any) -> np.ndarray:
    return image_array(msg.width, msg.height, msg.encoding, msg.step, bytes(msg.data), bool(msg.is_bigendian))


def _plain(value: Any) -> Any:
    """A decoded ROS 2 message as JSON-like values."""
    if isinstance(value, (str, bool, int)) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (bytes, bytearray, memoryview)):
        return list(bytes(value))
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    slots = getattr(value, "__slots__", None)
    if slots is not None:
        return {name: _plain(getattr(value, name)) for name in slots}
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    try:
        return [_plain(v) for v in value]  # array.array and the like
    except TypeError:
        return str(value)


class Decoders:
    """Turns message data into dyknow payloads, with one decoding function per channel.

    ``path`` names the file in the warnings. A message that cannot be decoded is delivered as
    its bytes, with one warning per channel.
    """

    def __init__(self, path: str) -> None:
        self._path = path
        self._by_channel: dict[int, Callable[[bytes], Any]] = {}
        self._warned: set[int] = set()
        self._ros: Any = None

    def payload(self, channel: ChannelInfo, data: bytes) -> Any:
        """The payload of one message of ``channel``."""
        decode = self._by_channel.get(channel.id)
        try:
            if decode is None:
                decode = self._by_channel[channel.id] = self._decoder(channel)
            return decode(data)
        except Exception as exc:
            if channel.id not in self._warned:
                self._warned.add(channel.id)
                log.warning(
                    "%s: cannot decode %s messages on %r (%s: %s); delivering their bytes",
                    self._path, channel.schema_name or channel.message_encoding, channel.topic, type(exc).__name__, exc,
                )  # fmt: skip
            return data

    def _decoder(self, channel: ChannelInfo) -> Callable[[bytes], Any]:
        kind = channel.metadata.get(PAYLOAD_METADATA)
        encoding, schema = channel.message_encoding, channel.schema_name
        if encoding == "protobuf":
            if schema == RAW_IMAGE:
                return _pb_raw_image
            if schema == COMPRESSED_IMAGE:
                return _pb_compressed_bytes if kind == "bytes" else lambda d: self._compressed(_pb_compressed_bytes(d))
            if schema == NDARRAY:
                return _pb_ndarray
        elif encoding == "json":
            if kind is None and schema == COMPRESSED_IMAGE:
                return lambda d: self._compressed(base64.b64decode(json.loads(d)["data"]))
            if kind is None and schema == RAW_IMAGE:
                return _json_raw_image
            return json.loads
        elif encoding == "cdr" and channel.schema_encoding == "ros2msg":
            return self._ros2(channel)
        elif encoding.startswith("text/") or kind == "text":
            return lambda d: d.decode()
        return bytes

    def _ros2(self, channel: ChannelInfo) -> Callable[[bytes], Any]:
        if self._ros is None:
            from mcap_ros2.decoder import DecoderFactory  # imported on first use: it parses schemas

            self._ros = DecoderFactory()
        schema = Schema(id=channel.schema_id, name=channel.schema_name, encoding="ros2msg", data=channel.schema_data)
        decode = self._ros.decoder_for("cdr", schema)
        if decode is None:
            raise ValueError(f"no ROS 2 decoder for {channel.schema_name!r}")
        if channel.schema_name == "sensor_msgs/msg/Image":
            return lambda d: _ros_image(decode(d))
        if channel.schema_name == "sensor_msgs/msg/CompressedImage":
            return lambda d: self._compressed(bytes(decode(d).data))
        return lambda d: _plain(decode(d))

    def _compressed(self, data: bytes) -> Any:
        cv2 = _cv2()
        if cv2 is None:
            if -1 not in self._warned:
                self._warned.add(-1)
                log.warning("OpenCV (cv2) is not installed: compressed images are delivered as their JPEG/PNG bytes")
            return bytes(data)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"OpenCV cannot decode the compressed image ({len(data)} bytes)")
        return image
