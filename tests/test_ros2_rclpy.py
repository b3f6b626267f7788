"""CDR bytes against ROS 2's own client library: ``rclpy.serialization`` (the ``ros-rclpy``
wheel of the package index, with ``rmw_fastrtps_cpp``) as a byte oracle, both ways.

CDR leaves alignment padding unspecified and rclpy leaves what was in memory there (seen: the
two bytes after an Image's ``encoding``), so bytes are compared outside padding: every byte
either side differs only where dyknow wrote a zero, and each side decodes the other's bytes.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pytest

with warnings.catch_warnings():  # ROS 2's parser (lark 0.12) imports the deprecated sre_parse
    warnings.simplefilter("ignore", DeprecationWarning)
    import rosidl_generator_py  # noqa: F401
    from rclpy.serialization import deserialize_message, serialize_message

from dyknow.ros2.convert import from_message, to_message
from dyknow.ros2.types import TypeSupport


@pytest.fixture(scope="module")
def types() -> TypeSupport:
    return TypeSupport()


def same_but_padding(ours: bytes, theirs: bytes) -> None:
    assert len(ours) == len(theirs)
    differing = [i for i, (a, b) in enumerate(zip(ours, theirs, strict=True)) if a != b]
    # padding: zeros on our side, in runs of at most 3 bytes (alignment to 4 or 8 bytes)
    runs = [i for i in differing if i - 1 not in differing]
    assert all(ours[i] == 0 for i in differing) and all(i + 3 not in differing for i in runs), differing


def rclpy_messages() -> list[tuple[str, Any, Any]]:
    """(type, an rclpy message, the same as a dyknow payload)."""
    from geometry_msgs.msg import PoseStamped, Twist
    from sensor_msgs.msg import CompressedImage, Image
    from std_msgs.msg import String

    image = Image(height=2, width=3, encoding="bgr8", step=9, data=bytes(range(18)))
    image.header.stamp.sec, image.header.stamp.nanosec, image.header.frame_id = 12, 34, "cam"
    jpeg = CompressedImage(format="jpeg", data=b"\xff\xd8\xff\xe0" + bytes(12))
    jpeg.header.stamp.sec = 1
    twist = Twist()
    twist.linear.x, twist.angular.z = 0.5, -1.25
    pose = PoseStamped()
    pose.header.frame_id, pose.header.stamp.sec = "map", 3
    pose.pose.position.y, pose.pose.orientation.w = 2.0, 1.0
    return [
        ("std_msgs/msg/String", String(data="hello, wörld"), "hello, wörld"),
        ("sensor_msgs/msg/Image", image, np.arange(18, dtype=np.uint8).reshape(2, 3, 3)),
        ("sensor_msgs/msg/CompressedImage", jpeg, b"\xff\xd8\xff\xe0" + bytes(12)),
        ("geometry_msgs/msg/Twist", twist, {"linear": {"x": 0.5}, "angular": {"z": -1.25}}),
        (
            "geometry_msgs/msg/PoseStamped",
            pose,
            {"header": {"frame_id": "map", "stamp": {"sec": 3}}, "pose": {"position": {"y": 2.0}, "orientation": {"w": 1.0}}},
        ),
    ]


@pytest.mark.parametrize("case", range(5))
def test_our_cdr_is_rclpys(types: TypeSupport, case: int) -> None:
    ros_type, rclpy_message, payload = rclpy_messages()[case]
    theirs = serialize_message(rclpy_message)
    stamp = getattr(getattr(rclpy_message, "header", None), "stamp", None)
    origin = stamp.sec * 1_000_000_000 + stamp.nanosec if stamp is not None else 0
    frame_id = rclpy_message.header.frame_id if hasattr(rclpy_message, "header") else ""
    ours = types.serialize(to_message(payload, ros_type, types, origin_ns=origin, frame_id=frame_id), ros_type)
    same_but_padding(ours, theirs)
    same_but_padding(ours, serialize_message(deserialize_message(ours, type(rclpy_message))))


@pytest.mark.parametrize("case", range(5))
def test_we_read_rclpys_cdr(types: TypeSupport, case: int) -> None:
    ros_type, rclpy_message, payload = rclpy_messages()[case]
    got = from_message(types.deserialize(serialize_message(rclpy_message), ros_type), ros_type)
    if isinstance(payload, np.ndarray):
        assert np.array_equal(got, payload)
    elif isinstance(payload, dict):
        assert got == from_message(
            to_message(payload, ros_type, types, origin_ns=0, frame_id=got.get("header", {}).get("frame_id", "")), ros_type
        ) | ({"header": got["header"]} if "header" in got else {})
    else:
        assert got == payload


def test_a_point_cloud_both_ways(types: TypeSupport) -> None:
    """A PointCloud2 of 500 points: its data comes as a numpy array (a view of the CDR, not a list
    of 8,000 numbers) holding rclpy's bytes, and the dict goes out as the bytes rclpy writes."""
    from sensor_msgs.msg import PointCloud2, PointField

    points = np.arange(500 * 4, dtype=np.float32)
    cloud = PointCloud2(height=1, width=500, is_bigendian=False, point_step=16, row_step=8000, data=points.tobytes(), is_dense=True)
    cloud.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate(("x", "y", "z", "i"))]
    cloud.header.frame_id, cloud.header.stamp.sec = "lidar", 9
    theirs = serialize_message(cloud)
    got = from_message(types.deserialize(theirs, "sensor_msgs/msg/PointCloud2"), "sensor_msgs/msg/PointCloud2")
    assert isinstance(got["data"], np.ndarray) and got["data"].tobytes() == points.tobytes()
    assert [f["name"] for f in got["fields"]] == ["x", "y", "z", "i"] and got["row_step"] == 8000
    ours = types.serialize(to_message(got, "sensor_msgs/msg/PointCloud2", types, origin_ns=0), "sensor_msgs/msg/PointCloud2")
    same_but_padding(ours, theirs)


def rclpy_service_messages() -> list[tuple[str, Any]]:
    """(request or response type, an rclpy message of it)."""
    from lifecycle_msgs.msg import State, Transition
    from lifecycle_msgs.srv import ChangeState, GetState
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue, SetParametersResult
    from rcl_interfaces.srv import SetParameters

    value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=[0.5, 1.5])
    return [
        ("lifecycle_msgs/srv/ChangeState_Request", ChangeState.Request(transition=Transition(id=3, label="activate"))),
        ("lifecycle_msgs/srv/ChangeState_Response", ChangeState.Response(success=True)),
        ("lifecycle_msgs/srv/GetState_Request", GetState.Request()),
        ("lifecycle_msgs/srv/GetState_Response", GetState.Response(current_state=State(id=3, label="active"))),
        ("rcl_interfaces/srv/SetParameters_Request", SetParameters.Request(parameters=[Parameter(name="gain", value=value)])),
        ("rcl_interfaces/srv/SetParameters_Response", SetParameters.Response(results=[SetParametersResult(successful=False, reason="no")])),
    ]


@pytest.mark.parametrize("case", range(6))
def test_service_requests_and_responses_are_rclpys_cdr(types: TypeSupport, case: int) -> None:
    ros_type, rclpy_message = rclpy_service_messages()[case]
    types.service(ros_type.rsplit("_", 1)[0])
    theirs = serialize_message(rclpy_message)
    ours = types.serialize(to_message(from_message(types.deserialize(theirs, ros_type), ros_type), ros_type, types, origin_ns=0), ros_type)
    # rclpy pads its buffer to 4 bytes, and left 8 more after a SetParameters request: bytes after
    # the message, which dyknow reads past; the message itself is the same outside padding
    assert len(theirs) - len(ours) in (0, 3, 8) and set(theirs[len(ours) + 8 :]) <= {0}
    same_but_padding(ours, theirs[: len(ours)])
    assert deserialize_message(ours, type(rclpy_message)) == rclpy_message
