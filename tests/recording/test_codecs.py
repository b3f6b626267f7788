"""Tests for dyknow.recording.codecs: how payloads map to MCAP encodings and schemas that other tools
understand, and how other writers' files (ROS 2, Foxglove, JSON) become dyknow payloads.

Files are read back with the official ``mcap`` reader (what other tools see) as well as with
dyknow's own reader.
"""

from __future__ import annotations

import base64
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from dyknow.errors import RecordingError
from dyknow.message import Message
from dyknow.recording import (
    COMPRESSED_IMAGE,
    NDARRAY,
    PAYLOAD_METADATA,
    PROTOBUF_SCHEMAS,
    RAW_IMAGE,
    Player,
    Recorder,
    Recording,
    image_array,
    image_encoding,
    protobuf,
)
from dyknow.recording.codecs import compressed_image, encode, raw_image
from tests.recording.support import FOREIGN, official, play_all, real, same_payload, write_mcap

# --- dyknow payloads -> MCAP ------------------------------------------------------------------


PAYLOADS: dict[str, Any] = {
    "m/bytes": b"\x00\x01binary",
    "m/text": "héllo wörld",
    "m/json": {"x": 1, "y": [1.5, None], "nested": {"ok": True}},
    "m/scalar": 3.25,
    "m/bgr": np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3),
    "m/mono": np.arange(6, dtype=np.uint8).reshape(2, 3),
    "m/bgra": np.arange(2 * 2 * 4, dtype=np.uint8).reshape(2, 2, 4),
    "m/mono16": np.arange(12, dtype="<u2").reshape(3, 4),
    "m/matrix": np.linspace(0.0, 1.0, 6).reshape(2, 3),
    "m/vector": np.arange(5, dtype=np.int32),
    "m/onechannel": np.zeros((2, 3, 1), np.uint8),
    "m/jpeg": b"\xff\xd8\xff\xe0fake-jpeg",
    "m/png": b"\x89PNG\r\n\x1a\nfake-png",
}


MAPPING = {  # key -> (message encoding, schema name, schema encoding, dyknow.payload)
    "m/bytes": ("application/octet-stream", None, None, "bytes"),
    "m/text": ("text/plain;charset=utf-8", None, None, "text"),
    "m/json": ("json", "m/json", "jsonschema", "json"),
    "m/scalar": ("json", "m/scalar", "jsonschema", "json"),
    "m/bgr": ("protobuf", RAW_IMAGE, "protobuf", "ndarray"),
    "m/mono": ("protobuf", RAW_IMAGE, "protobuf", "ndarray"),
    "m/bgra": ("protobuf", RAW_IMAGE, "protobuf", "ndarray"),
    "m/mono16": ("protobuf", RAW_IMAGE, "protobuf", "ndarray"),
    "m/matrix": ("protobuf", NDARRAY, "protobuf", "ndarray"),
    "m/vector": ("protobuf", NDARRAY, "protobuf", "ndarray"),
    "m/onechannel": ("protobuf", NDARRAY, "protobuf", "ndarray"),
    "m/jpeg": ("protobuf", COMPRESSED_IMAGE, "protobuf", "bytes"),
    "m/png": ("protobuf", COMPRESSED_IMAGE, "protobuf", "bytes"),
}


def test_payloads_map_to_schemas_other_tools_understand(tmp_path: Path) -> None:
    path = tmp_path / "mapping.mcap"
    with Recorder((), path) as rec:
        for i, (key, payload) in enumerate(PAYLOADS.items()):
            rec.write(Message(payload, 100 + i, 5_000 + i, 6_000 + i, key))
    assert rec.count == len(PAYLOADS) and rec.topics == {key: 1 for key in PAYLOADS}

    summary, triples = official(path)
    assert [c.topic for _, c, _ in triples] == list(PAYLOADS)  # one channel per key, in arrival order
    for i, (schema, channel, message) in enumerate(triples):
        encoding, schema_name, schema_encoding, kind = MAPPING[channel.topic]
        assert (channel.message_encoding, channel.metadata) == (encoding, {PAYLOAD_METADATA: kind}), channel.topic
        assert (schema.name if schema else None, schema.encoding if schema else None) == (schema_name, schema_encoding), channel.topic
        # the header: origin time as log_time, send time as publish_time, the sequence number
        assert (message.log_time, message.publish_time, message.sequence) == (5_000 + i, 6_000 + i, 100 + i)
        if schema_encoding == "protobuf":
            assert schema.data == PROTOBUF_SCHEMAS[schema_name]
    by_key = {c.topic: (s, m) for s, c, m in triples}
    assert by_key["m/bytes"][1].data == b"\x00\x01binary"
    assert by_key["m/text"][1].data == "héllo wörld".encode()
    assert by_key["m/json"][1].data == b'{"x":1,"y":[1.5,null],"nested":{"ok":true}}'  # what dyknow sends on the wire
    schema = json.loads(by_key["m/json"][0].data)
    assert schema["type"] == "object" and set(schema["properties"]) == {"x", "y", "nested"}
    assert schema["properties"]["nested"]["properties"]["ok"] == {"type": "boolean"}
    # images: width, height, encoding and step, and the pixels unchanged, in foxglove.RawImage
    image = protobuf.decode(by_key["m/bgr"][1].data)
    assert (image[2], image[3], bytes(image[4][0]), image[5]) == ([5], [4], b"bgr8", [15])
    assert bytes(image[6][0]) == PAYLOADS["m/bgr"].tobytes()
    assert bytes(protobuf.decode(by_key["m/mono16"][1].data)[4][0]) == b"mono16"
    compressed = protobuf.decode(by_key["m/jpeg"][1].data)
    assert (bytes(compressed[2][0]), bytes(compressed[3][0])) == (PAYLOADS["m/jpeg"], b"jpeg")
    array = protobuf.decode(by_key["m/matrix"][1].data)
    assert bytes(array[1][0]) == b"<f8" and bytes(array[3][0]) == PAYLOADS["m/matrix"].tobytes()
    assert summary.statistics.message_count == len(PAYLOADS)

    # and dyknow's replay gives back exactly what was published
    with Player(path, rate=float("inf")) as player:
        replayed = {}
        player.play(lambda msg, record: replayed.setdefault(msg.key, msg))
    for key, payload in PAYLOADS.items():
        assert same_payload(replayed[key].payload, payload), key


@pytest.mark.parametrize(
    ("array", "encoding"),
    [
        (np.zeros((4, 5), np.uint8), "mono8"),
        (np.zeros((4, 5, 3), np.uint8), "bgr8"),
        (np.zeros((4, 5, 4), np.uint8), "bgra8"),
        (np.zeros((4, 5), "<u2"), "mono16"),
        (np.zeros((4, 5), ">u2"), None),  # would not come back as the same dtype
        (np.zeros((4, 5, 1), np.uint8), None),  # would come back as H x W
        (np.zeros((4, 5, 2), np.uint8), None),
        (np.zeros((4, 5), np.float32), None),
        (np.zeros((0, 5), np.uint8), None),
        (np.zeros(5, np.uint8), None),
    ],
)
def test_which_arrays_are_images(array: np.ndarray, encoding: str | None) -> None:
    assert image_encoding(array) == encoding


def test_image_encoding_matches_the_official_protobuf_serializer() -> None:
    """tests/mcap/foxglove-protobuf.mcap holds messages serialized by protobuf from Foxglove's
    published schemas; dyknow's encoder must produce the same bytes and compatible schemas."""
    with Recording(FOREIGN) as recording:
        theirs = {m.topic: m for m in recording.messages()}
    assert raw_image(np.arange(18, dtype=np.uint8).reshape(2, 3, 3), "bgr8", 1030) == theirs["/same/raw"].data
    png = bytes(protobuf.decode(theirs["/same/png"].data)[2][0])
    assert compressed_image(png, "png", 1040) == theirs["/same/png"].data
    for name in (RAW_IMAGE, COMPRESSED_IMAGE):
        official_fields = descriptor_fields(theirs["/same/raw" if name == RAW_IMAGE else "/same/png"].channel.schema_data, name)
        assert descriptor_fields(PROTOBUF_SCHEMAS[name], name) == {k: v for k, v in official_fields.items() if k in descriptor_fields(PROTOBUF_SCHEMAS[name], name)}
        assert {"timestamp", "frame_id", "data"} <= set(official_fields)


def descriptor_fields(descriptor_set: bytes, full_name: str) -> dict[str, tuple[int, int, int, str]]:
    """{field: (number, label, type, type name)} of a message in a FileDescriptorSet."""
    package, _, message = full_name.rpartition(".")
    for file in protobuf.decode(descriptor_set)[1]:
        proto = protobuf.decode(file)
        if bytes(proto.get(2, [b""])[0]).decode() != package:
            continue
        for message_type in proto.get(4, []):
            desc = protobuf.decode(message_type)
            if bytes(desc[1][0]).decode() == message:
                out = {}
                for f in desc.get(2, []):
                    fd = protobuf.decode(f)
                    out[bytes(fd[1][0]).decode()] = (fd[3][0], fd[4][0], fd[5][0], bytes(fd.get(6, [b""])[0]).decode())
                return out
    raise AssertionError(f"{full_name} is not in the descriptor set")


# --- MCAP from other writers -> payloads ---------------------------------------------------------


def test_ros2_talker_messages_become_json_values(data_dir: Path) -> None:
    delivered = play_all(real(data_dir, "talker.mcap"))
    topic = [m for m, r in delivered if r.topic == "/topic"]
    assert [m.payload for m in topic] == [{"data": f"Hello, world! {i}"} for i in range(10)]
    assert [m.key for m in topic] == ["topic"] * 10
    rosout = [m.payload for m, r in delivered if r.topic == "/rosout"]
    assert len(rosout) == 10 and rosout[3]["msg"] == "Publishing: 'Hello, world! 3'" and rosout[3]["stamp"]["sec"] == 1585866236
    assert [r.log_time_ns for _, r in delivered] == sorted(r.log_time_ns for _, r in delivered)
    assert [m.origin_ns for m, _ in delivered] == [r.log_time_ns for _, r in delivered]


def test_ros2_cdr_bytes_pass_through_unchanged_without_decoding(data_dir: Path) -> None:
    path = real(data_dir, "talker.mcap")
    with open(path, "rb") as file:
        theirs = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(file).iter_messages()]
    assert [(r.topic, r.log_time_ns, m.payload) for m, r in play_all(path, decode=False)] == theirs


def test_ros2_test_types_from_a_cpp_writer(data_dir: Path) -> None:
    delivered = play_all(real(data_dir, "cdr_test_0.mcap"))
    assert [r.topic for _, r in delivered].count("/test_topic") == 3
    basic = [m.payload for m, r in delivered if r.topic == "/test_topic"]
    assert all(b["int32_value"] == 123 and b["bool_value"] is False for b in basic)
    arrays = [m.payload for m, r in delivered if r.topic == "/array_topic"][0]
    assert arrays["uint64_values_default"] == [0, 1, 18446744073709551615]
    assert arrays["string_values"] == ["Complex Hello1", "Complex Hello2", "Complex Hello3"]
    assert arrays["byte_values"] == [0, 0, 0]  # byte arrays become lists: JSON values
    json.dumps([m.payload for m, _ in delivered], allow_nan=False)  # publishable as dyknow JSON


def test_json_compressed_images_with_base64_jpeg_become_arrays(data_dir: Path) -> None:
    pytest.importorskip("cv2")
    delivered = play_all(real(data_dir, "custom-camera-model.mcap"))
    images = [m for m, r in delivered if r.topic == "/image/compressed"]
    assert len(images) == 10
    assert all(isinstance(m.payload, np.ndarray) and m.payload.shape == (360, 520, 3) and m.payload.dtype == np.uint8 for m in images)
    # the red "SAMPLE" stamp: in BGR order, some pixels are strongly red
    red = (images[0].payload[..., 2] > 150) & (images[0].payload[..., 1] < 100) & (images[0].payload[..., 0] < 100)
    assert red.sum() > 100
    calibration = [m.payload for m, r in delivered if r.topic == "/camera_calibration"]
    assert len(calibration) == 10 and calibration[0]["distortion_model"] == "plumb_bob" and len(calibration[0]["K"]) == 9
    assert {m.key for m in images} == {"image/compressed"}


def test_foxglove_protobuf_images_written_by_other_tools() -> None:
    pytest.importorskip("cv2")
    delivered = {}
    for msg, record in play_all(FOREIGN):
        delivered.setdefault(record.topic, []).append(msg.payload)
    for i, image in enumerate(delivered["/camera/rgb"]):  # rgb8 with padded rows, delivered as BGR
        want = np.array([[[200, 100 + y, 10 * i + x] for x in range(4)] for y in range(3)], np.uint8)
        assert image.dtype == np.uint8 and np.array_equal(image, want)
    (depth,) = delivered["/camera/depth"]
    assert depth.dtype == np.uint16 and np.array_equal(depth, [[1000 * y + x for x in range(5)] for y in range(2)])
    (grey,) = delivered["/camera/png"]
    assert np.array_equal(grey, [[16 * y + x for x in range(4)] for y in range(4)])


def test_ros2_images_from_the_official_ros2_writer(tmp_path: Path) -> None:
    pytest.importorskip("cv2")
    import cv2
    from mcap_ros2.writer import Writer as Ros2Writer

    header = "\n".join([
        "================================================================================", "MSG: std_msgs/Header",
        "builtin_interfaces/Time stamp", "string frame_id",
        "================================================================================", "MSG: builtin_interfaces/Time",
        "int32 sec", "uint32 nanosec",
    ])  # fmt: skip
    image_def = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n" + header
    compressed_def = "std_msgs/Header header\nstring format\nuint8[] data\n" + header
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    depth = np.array([[1, 2], [3, 65535]], ">u2")  # big-endian, as is_bigendian says
    png = cv2.imencode(".png", np.full((5, 6, 3), (10, 20, 30), np.uint8))[1].tobytes()
    stamp = {"header": {"stamp": {"sec": 1, "nanosec": 2}, "frame_id": "cam"}}
    path = tmp_path / "ros2.mcap"
    with open(path, "wb") as file, Ros2Writer(file) as writer:
        image_schema = writer.register_msgdef("sensor_msgs/msg/Image", image_def)
        compressed_schema = writer.register_msgdef("sensor_msgs/msg/CompressedImage", compressed_def)
        writer.write_message("/cam/rgb", image_schema, {**stamp, "height": 2, "width": 3, "encoding": "rgb8", "is_bigendian": 0, "step": 9, "data": rgb.tobytes()}, log_time=10)
        writer.write_message("/cam/depth", image_schema, {**stamp, "height": 2, "width": 2, "encoding": "16UC1", "is_bigendian": 1, "step": 4, "data": depth.tobytes()}, log_time=20)
        writer.write_message("/cam/png", compressed_schema, {**stamp, "format": "png", "data": png}, log_time=30)
    payloads = {record.topic: msg.payload for msg, record in play_all(path)}
    assert np.array_equal(payloads["/cam/rgb"], rgb[..., ::-1])  # BGR, as OpenCV and dyknow's units use
    assert payloads["/cam/depth"].dtype == np.dtype("=u2") and np.array_equal(payloads["/cam/depth"], [[1, 2], [3, 65535]])
    assert payloads["/cam/png"].shape == (5, 6, 3) and tuple(payloads["/cam/png"][0, 0]) == (10, 20, 30)


def test_json_raw_images_and_undecodable_messages(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    def raw_image(width: int, height: int, step: int, data: bytes) -> bytes:
        fields = {"timestamp": {"sec": 0, "nsec": 0}, "frame_id": "", "width": width, "height": height, "encoding": "mono8", "step": step}
        return json.dumps({**fields, "data": base64.b64encode(data).decode()}).encode()

    schema = ("json", "foxglove.RawImage", "jsonschema", b'{"type":"object"}')
    path = write_mcap(tmp_path / "json-images.mcap", {"/raw": schema}, [
        ("/raw", 1, raw_image(3, 2, 4, bytes(range(8)))),  # rows padded to 4 bytes
        ("/raw", 2, raw_image(3, 2, 2, bytes(6))),  # step shorter than a row: undecodable
    ])  # fmt: skip
    with caplog.at_level(logging.WARNING, logger="dyknow.recording.codecs"):
        first, second = (m.payload for m, _ in play_all(path))
    assert np.array_equal(first, [[0, 1, 2], [4, 5, 6]])
    assert second == raw_image(3, 2, 2, bytes(6))  # delivered as its bytes ...
    assert "cannot decode foxglove.RawImage messages on '/raw'" in caplog.text  # ... with a warning


@pytest.mark.parametrize(
    ("encoding", "step", "data", "want"),
    [
        ("mono8", 2, bytes([1, 2, 3, 4]), [[1, 2], [3, 4]]),
        ("8UC1", 3, bytes([1, 2, 0, 3, 4, 0]), [[1, 2], [3, 4]]),  # padded rows
        ("bgr8", 6, bytes(range(12)), [[[0, 1, 2], [3, 4, 5]], [[6, 7, 8], [9, 10, 11]]]),
        ("rgb8", 6, bytes(range(12)), [[[2, 1, 0], [5, 4, 3]], [[8, 7, 6], [11, 10, 9]]]),
        ("rgba8", 8, bytes(range(16)), [[[2, 1, 0, 3], [6, 5, 4, 7]], [[10, 9, 8, 11], [14, 13, 12, 15]]]),
        ("mono16", 4, np.array([[1, 2], [3, 4]], "<u2").tobytes(), [[1, 2], [3, 4]]),
        ("32FC1", 8, np.array([[0.5, 1], [2, 4]], "<f4").tobytes(), [[0.5, 1], [2, 4]]),
    ],
)
def test_image_array_layouts(encoding: str, step: int, data: bytes, want: list[Any]) -> None:
    array = image_array(2, 2, encoding, step, data)
    assert array.tolist() == want and array.flags.c_contiguous


def test_image_array_refuses_what_it_cannot_read() -> None:
    with pytest.raises(ValueError, match="image encoding 'bayer_rggb8' is not supported"):
        image_array(2, 2, "bayer_rggb8", 2, bytes(4))
    with pytest.raises(ValueError, match="are too few"):
        image_array(4, 4, "mono8", 4, bytes(15))


def test_arrays_inside_a_json_value_are_recorded_as_lists() -> None:
    """A ROS 2 message's large arrays come as numpy arrays inside its dict: recorded as JSON
    lists, as such a message was before they did."""
    kind, encoding, schema, data = encode({"width": 3, "data": np.arange(3, dtype=np.uint8)}, 0)
    assert (kind, encoding, schema, json.loads(data)) == ("json", "json", "", {"width": 3, "data": [0, 1, 2]})
    with pytest.raises(RecordingError, match="cannot record a payload of type dict"):
        encode({"x": object()}, 0)
