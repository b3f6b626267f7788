"""dyknow.ros2.convert: ROS 2 messages <-> the payloads dyknow's units use."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dyknow.errors import BindingError
from dyknow.ros2.convert import MAX_LISTED, compressed_size, from_message, stamp_ns, to_message
from dyknow.ros2.types import TypeSupport

IMAGE, COMPRESSED, CLOUD = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/PointCloud2"


@pytest.fixture(scope="module")
def types() -> TypeSupport:
    return TypeSupport()


def image(types: TypeSupport, encoding: str, height: int, width: int, step: int, data: bytes, bigendian: int = 0) -> object:
    msg = to_message(
        {"encoding": encoding, "height": height, "width": width, "step": step, "is_bigendian": bigendian, "data": list(data)},
        IMAGE,
        types,
        origin_ns=0,
    )
    return types.deserialize(types.serialize(msg, IMAGE), IMAGE)


def test_strings(types: TypeSupport) -> None:
    msg = to_message("hé", "std_msgs/msg/String", types, origin_ns=0)
    assert (
        from_message(types.deserialize(types.serialize(msg, "std_msgs/msg/String"), "std_msgs/msg/String"), "std_msgs/msg/String") == "hé"
    )
    with pytest.raises(BindingError, match="text"):
        to_message(b"bytes", "std_msgs/msg/String", types, origin_ns=0)


def test_rgb8_arrives_as_bgr_and_row_padding_is_cut(types: TypeSupport) -> None:
    rows = [bytes([1, 2, 3, 4, 5, 6]) + b"\xee\xee", bytes([7, 8, 9, 10, 11, 12]) + b"\xee\xee"]  # 2 px a row, step 8
    frame = from_message(image(types, "rgb8", 2, 2, 8, b"".join(rows)), IMAGE)
    assert frame.shape == (2, 2, 3) and frame.flags.c_contiguous
    assert frame[0, 0].tolist() == [3, 2, 1] and frame[1, 1].tolist() == [12, 11, 10]


@pytest.mark.parametrize(("encoding", "first"), [("bgr8", [1, 2, 3]), ("bgra8", [1, 2, 3]), ("rgba8", [3, 2, 1])])
def test_colour_encodings(types: TypeSupport, encoding: str, first: list[int]) -> None:
    channels = len(encoding) - 1
    frame = from_message(image(types, encoding, 1, 1, channels, bytes(range(1, channels + 1))), IMAGE)
    assert frame.shape == (1, 1, 3) and frame[0, 0].tolist() == first


def test_mono_images(types: TypeSupport) -> None:
    assert from_message(image(types, "mono8", 1, 3, 3, b"\x01\x02\x03"), IMAGE).tolist() == [[1, 2, 3]]
    assert from_message(image(types, "mono16", 1, 2, 4, b"\x01\x02\x03\x04", bigendian=1), IMAGE).tolist() == [[0x0102, 0x0304]]
    assert from_message(image(types, "16UC1", 1, 2, 4, b"\x01\x02\x03\x04"), IMAGE).tolist() == [[0x0201, 0x0403]]


@pytest.mark.parametrize(
    ("encoding", "height", "width", "step", "size", "problem"),
    [
        ("yuv422", 1, 1, 2, 2, "encoding"),
        ("rgb8", 2, 2, 6, 6, "step"),  # half the data
        ("rgb8", 2, 2, 5, 12, "step"),  # a step shorter than a row
        ("mono8", 0, 0, 0, 0, "step"),
        ("mono8", 1 << 16, 1, 1, 1, "step"),
    ],
)
def test_images_that_contradict_themselves_are_refused(
    types: TypeSupport, encoding: str, height: int, width: int, step: int, size: int, problem: str
) -> None:
    with pytest.raises(BindingError, match=problem):
        from_message(image(types, encoding, height, width, step, bytes(size)), IMAGE)


def test_frames_go_out_as_bgr8_or_mono_with_the_origin_as_stamp(types: TypeSupport) -> None:
    frame = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    msg = to_message(frame, IMAGE, types, origin_ns=3_000_000_007, frame_id="cam")
    assert (msg.encoding, msg.height, msg.width, msg.step, msg.header.frame_id) == ("bgr8", 2, 2, 6, "cam")
    assert stamp_ns(msg) == 3_000_000_007
    back = types.deserialize(types.serialize(msg, IMAGE), IMAGE)
    assert np.array_equal(from_message(back, IMAGE), frame)
    grey = to_message(np.zeros((3, 4), np.uint16), IMAGE, types, origin_ns=1)
    assert (grey.encoding, grey.step) == ("mono16", 8)
    with pytest.raises(BindingError, match="shape"):
        to_message(np.zeros((2, 2, 2), np.uint8), IMAGE, types, origin_ns=1)


def test_compressed_images_are_their_bytes(types: TypeSupport) -> None:
    jpeg = b"\xff\xd8\xff\xe0" + bytes(20)
    msg = to_message(jpeg, COMPRESSED, types, origin_ns=5)
    assert msg.format == "jpeg" and stamp_ns(msg) == 5
    assert from_message(types.deserialize(types.serialize(msg, COMPRESSED), COMPRESSED), COMPRESSED) == jpeg
    assert to_message(np.zeros((8, 8, 3), np.uint8), COMPRESSED, types, origin_ns=5).format == "jpeg"  # encoded with OpenCV
    with pytest.raises(BindingError, match="JPEG"):
        to_message(b"GIF89a", COMPRESSED, types, origin_ns=5)


def test_other_types_are_dicts_of_their_fields(types: TypeSupport) -> None:
    msg = to_message(
        {"header": {"frame_id": "map"}, "pose": {"position": {"x": 1.5}}}, "geometry_msgs/msg/PoseStamped", types, origin_ns=2_000_000_001
    )
    plain = from_message(
        types.deserialize(types.serialize(msg, "geometry_msgs/msg/PoseStamped"), "geometry_msgs/msg/PoseStamped"),
        "geometry_msgs/msg/PoseStamped",
    )
    assert plain["header"] == {"stamp": {"sec": 2, "nanosec": 1}, "frame_id": "map"}  # the origin as the stamp the payload left unset
    assert plain["pose"]["position"] == {"x": 1.5, "y": 0.0, "z": 0.0}
    assert plain["pose"]["orientation"]["w"] == 0.0


@pytest.mark.parametrize(
    ("payload", "problem"),
    [
        ({"linaer": {}}, "did you mean 'linear'"),
        ({"linear": 3}, "a dict of geometry_msgs/msg/Vector3"),
        ({"linear": {"x": "fast"}}, "linear.x"),
        ("text", "a dict of its fields"),
    ],
)
def test_payloads_that_do_not_fit_are_refused_naming_the_field(types: TypeSupport, payload: object, problem: str) -> None:
    with pytest.raises(BindingError, match=problem):
        to_message(payload, "geometry_msgs/msg/Twist", types, origin_ns=0)


def test_fixed_arrays_must_have_their_length(types: TypeSupport) -> None:
    with pytest.raises(BindingError, match="exactly 36"):
        to_message({"pose": {"covariance": [0.0] * 35}}, "geometry_msgs/msg/PoseWithCovarianceStamped", types, origin_ns=0)


def test_compressed_images_can_arrive_decoded(types: TypeSupport, data_dir: Path) -> None:
    jpeg = (data_dir / "images" / "ball" / "messi5.jpg").read_bytes()  # 548 x 342, a real photo
    assert compressed_size(jpeg) == (548, 342)
    msg = types.deserialize(types.serialize(to_message(jpeg, COMPRESSED, types, origin_ns=1), COMPRESSED), COMPRESSED)
    frame = from_message(msg, COMPRESSED, decode=True)
    assert frame.shape == (342, 548, 3) and frame.dtype == np.uint8
    png = cv2.imencode(".png", frame[:10, :20])[1].tobytes()
    assert compressed_size(png) == (20, 10)


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        (b"\xff\xd8\xff\xc0\x00\x11\x08\xff\xff\xff\xff\x03" + bytes(20), "65535x65535 declared"),  # a bomb's header
        (b"\x89PNG\r\n\x1a\n" + bytes(4) + b"IHDR" + (100000).to_bytes(4, "big") + (1).to_bytes(4, "big"), "100000x1"),
        (b"GIF89a" + bytes(20), "no JPEG or PNG header"),
        (b"\xff\xd8\xff\xe0\x00\x10" + bytes(14) + b"\xff\xc0\x00\x11\x08\x00\x10\x00\x10\x03" + bytes(30), "could not decode"),
    ],
)
def test_compressed_images_that_would_not_decode_safely_are_refused(types: TypeSupport, data: bytes, problem: str) -> None:
    msg = types.message_class(COMPRESSED)(
        header=types.message_class("std_msgs/msg/Header")(
            stamp=types.message_class("builtin_interfaces/msg/Time")(sec=0, nanosec=0), frame_id=""
        ),
        format="jpeg",
        data=np.frombuffer(data, np.uint8),
    )
    with pytest.raises(BindingError, match=problem):
        from_message(msg, COMPRESSED, decode=True)


def point_cloud(types: TypeSupport, points: int) -> bytes:
    t = types.message_class
    fields = [t("sensor_msgs/msg/PointField")(name=name, offset=4 * i, datatype=7, count=1) for i, name in enumerate("xyz")]
    header = t("std_msgs/msg/Header")(stamp=t("builtin_interfaces/msg/Time")(sec=4, nanosec=2), frame_id="lidar")
    message = t(CLOUD)(
        header=header,
        height=1,
        width=points,
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=12 * points,
        data=np.arange(points * 3, dtype=np.float32).view(np.uint8),
        is_dense=True,
    )
    return types.serialize(message, CLOUD)


def test_a_point_clouds_data_is_a_view_of_the_message_not_a_list(types: TypeSupport) -> None:
    cdr = point_cloud(types, 1000)
    plain = from_message(types.deserialize(cdr, CLOUD), CLOUD)
    data = plain["data"]
    assert isinstance(data, np.ndarray) and data.dtype == np.uint8 and data.size == 12_000 and not data.flags.writeable
    assert np.shares_memory(data, np.frombuffer(cdr, np.uint8))  # no copy, no Python object per byte
    assert plain["fields"][1] | {"name": "y", "offset": 4, "datatype": 7, "count": 1} == plain["fields"][1] and plain["width"] == 1000
    points = data.view(np.float32).reshape(-1, 3)
    assert points[999].tolist() == [2997.0, 2998.0, 2999.0]
    back = to_message(plain, CLOUD, types, origin_ns=0)  # out again as it came
    assert types.serialize(back, CLOUD) == cdr


@pytest.mark.parametrize(
    ("ros_type", "field", "values", "listed"),
    [
        ("std_msgs/msg/Float32MultiArray", "data", np.arange(MAX_LISTED, dtype=np.float32), True),  # a laser scan's ranges
        ("std_msgs/msg/Float32MultiArray", "data", np.arange(MAX_LISTED + 1, dtype=np.float32), False),
        ("std_msgs/msg/UInt8MultiArray", "data", np.arange(3, dtype=np.uint8), False),  # bytes: never a list
        ("std_msgs/msg/Int8MultiArray", "data", np.arange(3, dtype=np.int8), False),
    ],
)
def test_long_arrays_and_bytes_come_as_arrays(types: TypeSupport, ros_type: str, field: str, values: np.ndarray, listed: bool) -> None:
    msg = to_message({field: values}, ros_type, types, origin_ns=0)
    got = from_message(types.deserialize(types.serialize(msg, ros_type), ros_type), ros_type)[field]
    assert isinstance(got, list) == listed
    assert np.array_equal(np.asarray(got), values)


def test_fixed_arrays_stay_lists(types: TypeSupport) -> None:
    msg = to_message({"pose": {"covariance": [1.0] * 36}}, "geometry_msgs/msg/PoseWithCovarianceStamped", types, origin_ns=0)
    ros_type = "geometry_msgs/msg/PoseWithCovarianceStamped"
    got = from_message(types.deserialize(types.serialize(msg, ros_type), ros_type), ros_type)
    assert got["pose"]["covariance"] == [1.0] * 36
