"""ROS 2 messages <-> dyknow payloads.

- ``std_msgs/msg/String`` <-> ``str``;
- ``sensor_msgs/msg/Image`` <-> a numpy image as dyknow's vision units use them: ``H x W x 3``
  uint8 **BGR** or ``H x W`` grey. In: ``bgr8`` and ``mono8`` as they are, ``rgb8`` turned into
  BGR, ``rgba8``/``bgra8`` without their alpha, ``mono16``/``16UC1`` as ``H x W`` uint16; rows
  padded beyond ``width`` (``step``) are cut. Out: ``H x W x 3`` uint8 as ``bgr8``, ``H x W``
  uint8 as ``mono8``, uint16 as ``mono16``;
- ``sensor_msgs/msg/CompressedImage`` <-> the compressed bytes (JPEG or PNG); in, with
  ``decode=True``, a BGR array decoded by OpenCV instead, once the image's header says it is at
  most :data:`MAX_DECODED_SIDE` pixels a side (a small file can declare a huge image); out, a
  numpy image is JPEG-encoded first (OpenCV, imported then);
- any other type <-> a ``dict`` of its fields (nested messages as dicts, ``time`` fields as
  ``{"sec", "nanosec"}``); out, fields left out keep their zero value and an unknown field is
  refused naming it. Numeric arrays come as lists, but arrays of bytes (``uint8[]``, ``int8[]``,
  ``byte[]``, ``char[]``: a ``PointCloud2``'s or an ``OccupancyGrid``'s ``data``) and arrays of
  more than :data:`MAX_LISTED` numbers come as read-only numpy arrays, views of the message's
  bytes: no Python object per element, and they cross to other processes as binary
  (:mod:`dyknow.message`, JSON with arrays), never as JSON lists. Out, a field takes a list or an
  array alike.

Times: :func:`stamp_ns` reads a message's ``header.stamp`` (the time its data was taken, by ROS
convention); out, a message whose type has a header and whose payload gave no stamp gets the
dyknow message's origin time.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from dyknow.errors import BindingError, did_you_mean
from dyknow.ros2.types import TypeSupport

__all__ = ["MAX_DECODED_SIDE", "MAX_LISTED", "compressed_size", "from_message", "stamp_ns", "to_message"]

STRING, IMAGE, COMPRESSED = "std_msgs/msg/String", "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
HEADER = "std_msgs/msg/Header"
_MAX_SIDE = 1 << 15
#: The largest width or height of a compressed image decoded for a unit.
MAX_DECODED_SIDE = 8192
#: The most numbers an array of a message field may hold to come as a list (bytes never do):
#: a laser scan's ranges and a covariance do, a point cloud's or a map's data do not.
MAX_LISTED = 4096
_CHANNELS = {"bgr8": 3, "rgb8": 3, "mono8": 1, "8UC1": 1, "8UC3": 3, "rgba8": 4, "bgra8": 4, "mono16": 1, "16UC1": 1}


def stamp_ns(message: Any) -> int | None:
    """The ``header.stamp`` of ``message`` in nanoseconds, None when it has none or it is zero."""
    header = getattr(message, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    value = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return value if value > 0 else None


def from_message(message: Any, ros_type: str, *, decode: bool = False) -> Any:
    """The dyknow payload of a ROS 2 message object; raises :class:`BindingError` when the message
    is not usable (an image whose sizes and data disagree, an unsupported encoding).
    ``decode``: a compressed image as a BGR array rather than its bytes."""
    if ros_type == STRING:
        return str(message.data)
    if ros_type == IMAGE:
        return _image_from(message)
    if ros_type == COMPRESSED:
        data = bytes(np.asarray(message.data, dtype=np.uint8).tobytes())
        return _decode(data) if decode else data
    return _to_plain(message)


def compressed_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` a PNG's or JPEG's header declares, None when it declares none."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] != b"\xff\xd8":
        return None
    at = 2
    while at + 4 <= len(data):  # JPEG markers up to the frame header (SOF0..SOF15 but DHT, JPG, DAC)
        if data[at] != 0xFF:
            return None
        marker, length = data[at + 1], int.from_bytes(data[at + 2 : at + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and at + 9 <= len(data):
            return int.from_bytes(data[at + 7 : at + 9], "big"), int.from_bytes(data[at + 5 : at + 7], "big")
        at += 2 + length
    return None


def _decode(data: bytes) -> np.ndarray:
    where = f"{COMPRESSED} of {len(data)} bytes"
    size = compressed_size(data)
    if size is None:
        raise BindingError("no JPEG or PNG header", where=where, expected="JPEG or PNG bytes")
    if not (0 < size[0] <= MAX_DECODED_SIDE and 0 < size[1] <= MAX_DECODED_SIDE):
        raise BindingError(f"an image of {size[0]}x{size[1]} declared", where=where, expected=f"at most {MAX_DECODED_SIDE} pixels a side")
    import cv2  # only for compressed images decoded for a unit

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise BindingError("OpenCV could not decode it", where=where, expected="a valid JPEG or PNG")
    return np.asarray(image)


def _image_from(msg: Any) -> np.ndarray:
    where = f"sensor_msgs/msg/Image ({msg.encoding!r}, {msg.width}x{msg.height})"
    encoding = str(msg.encoding)
    channels = _CHANNELS.get(encoding)
    if channels is None:
        raise BindingError(f"encoding {encoding!r}", where=where, expected=f"one of {', '.join(_CHANNELS)}")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    depth = 2 if encoding in ("mono16", "16UC1") else 1
    data = np.asarray(msg.data, dtype=np.uint8)
    if not (0 < height <= _MAX_SIDE and 0 < width <= _MAX_SIDE) or step < width * channels * depth or data.size < step * height:
        raise BindingError(
            f"step {step} and {data.size} bytes of data", where=where, expected="step >= width x channels x bytes and height x step bytes"
        )
    rows = data[: step * height].reshape(height, step)[:, : width * channels * depth]
    if depth == 2:
        dtype = np.dtype(">u2" if msg.is_bigendian else "<u2")
        return rows.copy().view(dtype).reshape(height, width).astype(np.uint16)
    image = rows.reshape(height, width, channels) if channels > 1 else rows.reshape(height, width)
    if encoding == "rgb8":
        image = image[:, :, ::-1]
    elif encoding == "rgba8":
        image = image[:, :, 2::-1]
    elif encoding == "bgra8":
        image = image[:, :, :3]
    return np.ascontiguousarray(image)


def _to_plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        if (value.dtype.kind in "ui" and value.dtype.itemsize == 1) or value.size > MAX_LISTED:
            value.flags.writeable = False  # every receiver shares it (a view of the message's bytes, mostly)
            return value
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_to_plain(v) for v in value]
    if dataclasses.is_dataclass(value):
        return {f.name: _to_plain(getattr(value, f.name)) for f in dataclasses.fields(value) if _carried(f)}
    if isinstance(value, np.generic):
        return value.item()
    return value


def _carried(field: dataclasses.Field[Any]) -> bool:
    """Whether a field of a rosbags message class is one a message carries: not rosbags'
    ``__msgtype__``, nor a constant (a ``ClassVar``, which dataclasses take for a field when the
    annotation is text), which a message does not carry and ``to_message`` would refuse."""
    return not field.name.startswith("__") and not str(field.type).startswith(("ClassVar", "typing.ClassVar"))


def to_message(payload: Any, ros_type: str, types: TypeSupport, *, origin_ns: int, frame_id: str = "") -> Any:
    """The ROS 2 message object for a dyknow payload; raises :class:`BindingError` naming what
    does not fit ``ros_type``."""
    if ros_type == STRING:
        if not isinstance(payload, str):
            raise BindingError(f"a {type(payload).__name__} payload", where=f"a {STRING} output", expected="text (str)")
        return types.message_class(STRING)(data=payload)
    if ros_type == IMAGE and isinstance(payload, np.ndarray):
        return _image_to(payload, types, origin_ns, frame_id)
    if ros_type == COMPRESSED and isinstance(payload, (bytes, np.ndarray)):
        return _compressed_to(payload, types, origin_ns, frame_id)
    if not isinstance(payload, dict):
        raise BindingError(f"a {type(payload).__name__} payload", where=f"a {ros_type} output", expected="a dict of its fields")
    message = _build(payload, ros_type, types, ros_type)
    if hasattr(message, "header") and stamp_ns(message) is None:
        _set_header(message.header, origin_ns, message.header.frame_id or frame_id)
    return message


def _set_header(header: Any, origin_ns: int, frame_id: str) -> None:
    header.stamp.sec, header.stamp.nanosec = divmod(int(origin_ns), 1_000_000_000)
    header.frame_id = frame_id


def _header(types: TypeSupport, origin_ns: int, frame_id: str) -> Any:
    header = _default(HEADER, types)
    _set_header(header, origin_ns, frame_id)
    return header


def _image_to(image: np.ndarray, types: TypeSupport, origin_ns: int, frame_id: str) -> Any:
    where = f"a {IMAGE} output"
    if image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8:
        encoding = "bgr8"
    elif image.ndim == 2 and image.dtype == np.uint8:
        encoding = "mono8"
    elif image.ndim == 2 and image.dtype == np.uint16:
        encoding = "mono16"
    else:
        raise BindingError(
            f"an array of shape {image.shape} and type {image.dtype}", where=where, expected="H x W x 3 uint8 (BGR), H x W uint8 or uint16"
        )
    data = np.ascontiguousarray(image)
    height, width = image.shape[:2]
    raw = data.astype("<u2").view(np.uint8).reshape(-1) if image.dtype == np.uint16 else data.reshape(-1)
    return types.message_class(IMAGE)(
        header=_header(types, origin_ns, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=raw.size // height,
        data=raw,
    )


def _compressed_to(payload: bytes | np.ndarray, types: TypeSupport, origin_ns: int, frame_id: str) -> Any:
    if isinstance(payload, np.ndarray):
        import cv2  # only for an array published as a compressed image

        ok, encoded = cv2.imencode(".jpg", payload)
        if not ok:
            raise BindingError(
                f"OpenCV could not encode an array of shape {payload.shape}", where=f"a {COMPRESSED} output", expected="an image"
            )
        payload = encoded.tobytes()
    fmt = "png" if payload[:8] == b"\x89PNG\r\n\x1a\n" else "jpeg" if payload[:2] == b"\xff\xd8" else None
    if fmt is None:
        raise BindingError(f"bytes starting {payload[:4].hex()}", where=f"a {COMPRESSED} output", expected="JPEG (ffd8...) or PNG bytes")
    return types.message_class(COMPRESSED)(
        header=_header(types, origin_ns, frame_id), format=fmt, data=np.frombuffer(payload, dtype=np.uint8)
    )


_NUMERIC = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}


def _default(ros_type: str, types: TypeSupport) -> Any:
    return _build({}, ros_type, types, ros_type)


def _build(values: dict[str, Any], ros_type: str, types: TypeSupport, where: str) -> Any:
    from rosbags.interfaces import Nodetype

    fielddefs = types.field_definitions(ros_type)
    names = [name for name, _ in fielddefs]
    unknown = [k for k in values if k not in names]
    if unknown:
        raise BindingError(
            f"no field {unknown[0]!r}",
            where=where,
            expected=f"fields of {ros_type}: {', '.join(names) or 'none'}{did_you_mean(unknown[0], names)}",
        )
    kwargs: dict[str, Any] = {}
    for name, desc in fielddefs:
        given = name in values
        value = values.get(name)
        node, rest = desc
        here = f"{where}.{name}"
        try:
            if node == Nodetype.NAME:
                if given and not isinstance(value, dict):
                    raise BindingError(f"a {type(value).__name__}", where=here, expected=f"a dict of {rest}'s fields")
                kwargs[name] = _build(value or {}, rest, types, here)
            elif node == Nodetype.BASE:
                base = rest[0]
                if base in ("string", "wstring"):
                    kwargs[name] = str(value) if given else ""
                else:
                    kwargs[name] = _NUMERIC[base](value if given else 0).item()
            else:  # array or sequence
                (inner, inner_rest), count = rest
                if inner == Nodetype.BASE and inner_rest[0] in _NUMERIC:
                    arr: np.ndarray = np.asarray(value if given else np.zeros(count), dtype=_NUMERIC[inner_rest[0]])
                    kwargs[name] = arr.reshape(-1)
                elif inner == Nodetype.BASE:
                    kwargs[name] = [str(v) for v in (value or [""] * count)]
                else:
                    items: list[Any] = list(value) if given and value is not None else [{}] * count
                    kwargs[name] = [_build(v, inner_rest, types, f"{here}[{i}]") for i, v in enumerate(items)]
                if node == Nodetype.ARRAY and len(kwargs[name]) != count:
                    raise BindingError(f"{len(kwargs[name])} items", where=here, expected=f"exactly {count}")
        except BindingError:
            raise
        except (TypeError, ValueError, OverflowError) as exc:
            raise BindingError(f"{value!r:.80}: {exc}", where=here, expected=f"a value of the field's type ({desc})") from exc
    return types.message_class(ros_type)(**kwargs)
