"""Tests for dyknow.replay: reading MCAP files from any writer, the player, damaged files, the
replay unit, and the round trip live pipeline -> recording -> replay."""

from __future__ import annotations

import base64
import json
import logging
import random
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from dyknow import Manager
from dyknow.errors import ClosedError, RecordingError
from dyknow.message import Message
from dyknow.recording import Recorder
from dyknow.replay import Player, RecordedMessage, Recording, image_array, key_for_topic
from dyknow.transport import Session, make_config
from tests.conftest import REPO, UNIT_SPECS, free_port
from tests.mcap.units import PORTS, frame

SPECS = REPO / "specs" / "recording.xml"
MIXED = REPO / "tests" / "mcap" / "units.xml"
FOREIGN = REPO / "tests" / "mcap" / "foxglove-protobuf.mcap"
INF = float("inf")


def real(data_dir: Path, name: str) -> Path:
    return data_dir / "mcap" / "real" / name


def play_all(path: Path, **kwargs: Any) -> list[tuple[Message, RecordedMessage]]:
    with Player(path, rate=kwargs.pop("rate", INF), **kwargs) as player:
        out: list[tuple[Message, RecordedMessage]] = []
        player.play(lambda msg, record: out.append((msg, record)))
    return out


def write_mcap(path: Path, topics: dict[str, tuple[str, str, str, bytes]], messages: list[tuple[str, int, bytes]]) -> Path:
    """A file from the official writer: topics map to (message encoding, schema name, schema encoding, schema data)."""
    with open(path, "wb") as file:
        writer = Writer(file, compression=CompressionType.NONE)
        writer.start(profile="", library="test")
        channels = {}
        for topic, (encoding, schema_name, schema_encoding, schema_data) in topics.items():
            schema_id = writer.register_schema(schema_name, schema_encoding, schema_data) if schema_name else 0
            channels[topic] = writer.register_channel(topic, encoding, schema_id)
        for i, (topic, log_time, data) in enumerate(messages):
            writer.add_message(channels[topic], log_time=log_time, data=data, publish_time=log_time, sequence=i)
        writer.finish()
    return path


# --- files from other writers --------------------------------------------------------------------


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


def test_json_channels_in_zstd_chunks(data_dir: Path) -> None:
    delivered = play_all(real(data_dir, "example.mcap"))
    assert len(delivered) == 111 and delivered[0][0].payload == {"clientX": 1511, "clientY": 974}
    assert {m.key for m, _ in delivered} == {"mouse"}
    with Recording(real(data_dir, "example.mcap")) as recording:
        info = recording.info
    assert (info.chunk_count, info.compressions, info.start_ns, info.end_ns) == (2, ("zstd",), 1740566235448000000, 1740566238556000000)


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
    with caplog.at_level(logging.WARNING, logger="dyknow.replay"):
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


# --- topics, remapping, windows, pace --------------------------------------------------------------

TOPICS = ["/camera/image", "/camera/info", "/imu", "robot*1"]


@pytest.fixture
def four_topics(tmp_path: Path) -> Path:
    schema = ("json", "", "", b"")
    messages = [(topic, 1_000_000_000 * (i + 1) + j, json.dumps({"t": topic, "i": i}).encode()) for i in range(5) for j, topic in enumerate(TOPICS)]
    return write_mcap(tmp_path / "four.mcap", {t: schema for t in TOPICS}, messages)


@pytest.mark.parametrize(
    ("remap", "keys"),
    [
        ({}, {"/camera/image": "camera/image", "/camera/info": "camera/info", "/imu": "imu", "robot*1": "robot_1"}),
        ({"/imu": "robot/imu"}, {"/imu": "robot/imu"}),
        ({"imu": "robot/imu"}, {"/imu": "robot/imu"}),  # the topic's key names it too
        ({"camera/**": "replay/cam/**"}, {"/camera/image": "replay/cam/image", "/camera/info": "replay/cam/info", "/imu": "imu"}),
        ({"/camera/image": "a/b", "camera/**": "c/**"}, {"/camera/image": "a/b", "/camera/info": "c/info"}),  # exact wins
        ({"robot*1": "robot/one"}, {"robot*1": "robot/one"}),
    ],
)
def test_remapping(four_topics: Path, remap: dict[str, str], keys: dict[str, str]) -> None:
    with Player(four_topics, remap=remap) as player:
        assert {t: k for t, k in player.keys.items() if t in keys} == keys


@pytest.mark.parametrize(
    ("topics", "selected"),
    [
        ([], TOPICS),
        (["/imu"], ["/imu"]),
        (["imu"], ["/imu"]),
        (["camera/**"], ["/camera/image", "/camera/info"]),
        (["camera/*", "/imu"], ["/camera/image", "/camera/info", "/imu"]),
        (["robot*1"], ["robot*1"]),
    ],
)
def test_topic_selection(four_topics: Path, topics: list[str], selected: list[str]) -> None:
    with Player(four_topics, topics=topics) as player:
        assert [c.topic for c in player.channels] == selected
        assert sorted({r.topic for r in player.messages()}) == sorted(selected)


def test_unknown_topics_and_remaps_are_clear_errors(four_topics: Path) -> None:
    with pytest.raises(RecordingError) as info:
        Player(four_topics, topics=["/imu2"])
    assert str(info.value) == (
        f"{four_topics}: no topic matches '/imu2'; its topics are '/camera/image', '/camera/info', '/imu', 'robot*1' (did you mean '/imu'?)"
    )
    with pytest.raises(RecordingError, match=r"^remap /cam=x: no replayed topic of .* is '/cam'"):
        Player(four_topics, remap={"/cam": "x"})
    with Player(four_topics, topics=["/imu"], remap={"/imu": "a/*"}) as player:
        assert [r.topic for r in player.messages()] == ["/imu"] * 5  # reading needs no valid key ...
        with pytest.raises(RecordingError, match=r"key for topic '/imu'.*remap the topic to a key"):
            player.publish()  # ... publishing does


def test_start_and_end_select_a_window(four_topics: Path) -> None:
    first = 1_000_000_000
    window = [r.log_time_ns for _, r in play_all(four_topics, start_s=1.0, end_s=3.0)]
    everything = [r.log_time_ns for _, r in play_all(four_topics)]
    assert window == [t for t in everything if first + 1_000_000_000 <= t <= first + 3_000_000_000] and len(window) == 9
    with pytest.raises(RecordingError, match=r"end: got 1.0; expected seconds from the first message, not before start \(2\)"):
        Player(four_topics, start_s=2.0, end_s=1.0)
    with pytest.raises(RecordingError, match="rate: got 0"):
        Player(four_topics, rate=0)


def test_replay_keeps_the_original_pace_scaled_by_rate(data_dir: Path) -> None:
    rate = 20.0
    started = time.monotonic_ns()
    delivered: list[tuple[int, int]] = []
    with Player(real(data_dir, "example.mcap"), rate=rate) as player:
        player.play(lambda msg, record: delivered.append((time.monotonic_ns(), record.log_time_ns)))
    first_log = delivered[0][1]
    assert len(delivered) == 111
    # never early: each message is delivered at least its log-time offset (scaled) after the start
    assert all(at - started >= (log_time - first_log) / rate for at, log_time in delivered)
    assert delivered[-1][0] - started >= (1740566238556000000 - 1740566235448000000) / rate


def test_loop_starts_over_until_stopped() -> None:
    stop = threading.Event()
    seen: list[tuple[str, int]] = []

    def sink(msg: Message, record: RecordedMessage) -> None:
        seen.append((record.topic, record.log_time_ns))
        if len(seen) == 17:
            stop.set()

    with Player(FOREIGN, rate=INF, loop=True) as player:
        count = player.play(sink, stop=stop)
    one_pass = [(r.topic, r.log_time_ns) for _, r in play_all(FOREIGN)]
    assert count == 17 and seen == (one_pass * 3)[:17]


def test_close_stops_a_running_replay(data_dir: Path) -> None:
    player = Player(real(data_dir, "example.mcap"), rate=1.0, loop=True)
    first = threading.Event()
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(player.play(lambda msg, record: first.set())))
    thread.start()
    assert first.wait(5.0)
    player.close()
    thread.join(5.0)
    assert not thread.is_alive() and 1 <= result[0] < 111
    player.close()  # twice is fine
    with pytest.raises(ClosedError, match="is closed"):
        list(player.messages())


# --- damaged files -------------------------------------------------------------------------------


@pytest.fixture
def recorded(tmp_path: Path) -> Path:
    """300 JSON messages in small zstd chunks, 1 per ms of log time."""
    path = tmp_path / "recorded.mcap"
    with Recorder((), path, chunk_size=2000) as rec:
        for i in range(300):
            rec.write(Message({"i": i, "pad": "x" * 50}, i + 1, 1_000_000 * i, 1_000_000 * i, "d/x"))
    return path


def chunk_offsets(path: Path) -> list[int]:
    with open(path, "rb") as file:
        return sorted(ci.chunk_start_offset for ci in make_reader(file).get_summary().chunk_indexes)


def test_truncated_files_name_the_file_and_offset_and_recover_their_complete_chunks(recorded: Path, tmp_path: Path) -> None:
    data = recorded.read_bytes()
    offsets = chunk_offsets(recorded)
    cuts = {
        "inside the 5th chunk": offsets[4] + 30,
        "right after the 5th chunk's message index": offsets[5],
        "inside the summary": len(data) - 100,
        "the footer missing": len(data) - 37,
    }
    for what, cut in cuts.items():
        path = tmp_path / "cut.mcap"
        path.write_bytes(data[:cut])
        with pytest.raises(RecordingError) as info:
            Recording(path)
        message = str(info.value)
        assert message.startswith(f"{path}: truncated at offset "), (what, message)
        offset = int(message.split("offset ")[1].split(":")[0])
        assert offset <= cut, what
        with Player(path, recover=True, rate=INF) as player:
            got = [json.loads(r.data)["i"] for r in player.messages()]
            assert player.problem is not None and player.problem.startswith("truncated at offset")
        assert got == list(range(len(got))), what  # a prefix, in order, nothing made up
        assert f"{len(got)} messages are readable: replay them with recover=True (dyknow replay --recover)" in message
        if cut >= offsets[5]:
            assert len(got) >= 5 * 300 // len(offsets), what  # every complete chunk
        if cut >= len(data) - 100:
            assert len(got) == 300, what


def test_a_corrupt_chunk_is_named_and_recovery_skips_only_that_chunk(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    with Recorder((), path, compression="none", chunk_size=1500) as rec:
        for i in range(100):
            rec.write(Message({"i": i}, i + 1, i, i, "c/x"))
    offsets = chunk_offsets(path)
    data = bytearray(path.read_bytes())
    data[offsets[2] + 200] ^= 0xFF  # inside the third chunk's messages
    path.write_bytes(bytes(data))
    with Recording(path) as recording, pytest.raises(RecordingError) as info:  # the damage shows when the chunk is read
        list(recording.messages())
    assert str(info.value).startswith(f"{path}: corrupt at offset {offsets[2]}: the chunk's CRC does not match its data")
    with Recording(path, recover=True) as recording:
        got = [json.loads(r.data)["i"] for r in recording.messages()]
        assert recording.problem is not None and recording.problem.startswith(f"corrupt at offset {offsets[2]}")
    missing = sorted(set(range(100)) - set(got))
    assert got == sorted(got) and missing and missing == list(range(missing[0], missing[-1] + 1))  # one run: that chunk


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "the file is empty (0 bytes); expected an MCAP file"),
        (b"\x89MCA", "truncated at offset 0: the file ends inside the MCAP magic; nothing is readable"),
        (b"PK\x03\x04 a zip file, not MCAP", "not an MCAP file: it begins with b'PK\\x03\\x04 a z'; expected the MCAP magic b'\\x89MCAP0\\r\\n'"),
        (b"\x89MCAP0\r\n\x02", "truncated at offset 8: the file ends inside a record header (1 of 9 bytes); nothing is readable"),
        (b"\x89MCAP0\r\n\x06" + bytes(8), "corrupt at offset 8: expected the Header record, found a Chunk record; nothing is readable"),
    ],
)
def test_files_that_are_not_mcap(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    for recover in (False, True):
        with pytest.raises(RecordingError) as info:
            Recording(path, recover=recover)
        assert str(info.value) == f"{path}: {message}"


def test_a_missing_file() -> None:
    with pytest.raises(RecordingError, match=r"^cannot read /nonexistent/x\.mcap: No such file or directory$"):
        Player("/nonexistent/x.mcap")


def test_damaged_files_never_hang_nor_raise_anything_else(recorded: Path, tmp_path: Path, data_dir: Path) -> None:
    rnd = random.Random(7)
    sources = [recorded.read_bytes(), real(data_dir, "talker.mcap").read_bytes(), real(data_dir, "cdr_test_0.mcap").read_bytes()]
    outcomes = {"read": 0, "refused": 0}
    path = tmp_path / "fuzz.mcap"
    for n in range(300):
        data = bytearray(sources[n % len(sources)])
        if n % 3 == 0:
            data = data[: rnd.randrange(len(data))]
        else:
            for _ in range(rnd.randrange(1, 6)):
                data[rnd.randrange(len(data))] = rnd.randrange(256)
        path.write_bytes(bytes(data))
        for recover in (False, True):
            try:
                with Player(path, recover=recover, rate=INF) as player:
                    player.play(lambda msg, record: None)
                    outcomes["read"] += 1
            except RecordingError as exc:
                assert str(exc).startswith((f"{path}: ", f"cannot read {path}")), str(exc)
                outcomes["refused"] += 1
    assert outcomes["read"] > 0 and outcomes["refused"] > 0


# --- the replay unit -----------------------------------------------------------------------------


def test_replay_unit_stands_in_for_a_live_sensor(data_dir: Path, make_manager: Callable[..., Manager]) -> None:
    pytest.importorskip("cv2")
    manager = make_manager(specs=[UNIT_SPECS, SPECS])
    spec = manager.library.get("replay(Recorded)")
    assert spec.tags_for("out") == ("Recorded",)
    manager.spawn("sink", "sink", bindings={"in": "camera/image"})
    path = real(data_dir, "custom-camera-model.mcap")
    info = manager.spawn("replay(Recorded)", "cam", params={"file": str(path), "topic": "/image/compressed", "rate": 0}, bindings={"out": "camera/image"})
    assert info.state == "running"
    messages = manager.unit("sink").wait_for(10, timeout_s=10.0)
    with Recording(path) as recording:
        log_times = [m.log_time_ns for m in recording.messages() if m.topic == "/image/compressed"]
    assert [m.origin_ns for m in messages] == log_times
    assert all(isinstance(m.payload, np.ndarray) and m.payload.shape == (360, 520, 3) for m in messages)
    assert manager.unit("cam").finished.wait(5.0) and manager.unit("cam").replayed == 10


def test_replay_unit_needs_one_topic(data_dir: Path, make_manager: Callable[..., Manager]) -> None:
    manager = make_manager(specs=[SPECS])
    info = manager.spawn("replay(Recorded)", "r", params={"file": str(real(data_dir, "talker.mcap"))})
    assert info.state == "failed"
    assert "replays one topic, and 'no topic' selects 3: '/rosout', '/parameter_events', '/topic'; set param topic to one of them" in (info.error or "")


# --- round trip ----------------------------------------------------------------------------------


class Collector:
    """Collects messages from a Zenoh subscriber; tests wait on it."""

    def __init__(self) -> None:
        self.messages: list[Message] = []
        self._cond = threading.Condition()

    def __call__(self, msg: Message) -> None:
        with self._cond:
            self.messages.append(msg)
            self._cond.notify_all()

    def wait_for(self, count: int, timeout: float = 10.0) -> list[Message]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.messages) >= count, timeout), f"got {len(self.messages)} of {count}"
            return list(self.messages)


def same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and bool((a == b).all())
    return type(a) is type(b) and a == b


@pytest.fixture
def listening() -> Iterator[tuple[Session, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Session(make_config(listen=[endpoint])) as session:
        yield session, endpoint


def test_round_trip_live_pipeline_record_replay(tmp_path: Path, make_manager: Callable[..., Manager], listening: tuple[Session, str]) -> None:
    """A live pipeline (images included) is recorded through Zenoh, replayed through Zenoh, and what
    arrives equals what was published: payloads, sequence numbers, origin times, order per key."""
    manager = make_manager(specs=[MIXED])
    rounds = 12
    total = rounds * len(PORTS)
    path = tmp_path / "live.mcap"
    with Recorder([f"dyknow/{manager.name}/**"], path, connect=manager.endpoints, max_messages=total) as rec:
        manager.spawn("mixed-source", "src", params={"count": rounds, "rate_hz": 100})
        source = manager.unit("src")  # it starts once the recorder subscribes to every port
        assert source.done.wait(20.0)
        assert rec.wait(20.0), f"recorded {rec.count} of {total}"
    published: dict[str, list[tuple[int, Any, int]]] = {}
    for port, payload, origin_ns in source.published:
        key = f"dyknow/{manager.name}/src/{port}"
        published.setdefault(key, []).append((len(published.get(key, [])) + 1, payload, origin_ns))
    for i in range(rounds):  # sanity: the source published what tests.mcap.units.frame says
        assert same(published[f"dyknow/{manager.name}/src/image"][i][1], frame(i, "image"))

    session, endpoint = listening
    arrived = Collector()
    with session.declare_subscriber("replayed/**", arrived):
        with Player(path, rate=INF, remap={f"dyknow/{manager.name}/src/**": "replayed/**"}) as player:
            assert player.publish(connect=[endpoint], wait_s=10.0) == total
        messages = arrived.wait_for(total)
    assert [m.origin_ns for m in messages] == sorted(m.origin_ns for m in messages)  # log-time order
    for key, want in published.items():
        got = [(m.seq, m.payload, m.origin_ns) for m in messages if m.key == key.replace(f"dyknow/{manager.name}/src", "replayed")]
        assert len(got) == rounds, key
        for (seq, payload, origin), (want_seq, want_payload, want_origin) in zip(got, want, strict=True):
            assert (seq, origin) == (want_seq, want_origin), key
            assert same(payload, want_payload), key

    # recording the replay gives the very same file content: data bytes, log times, sequences
    again = tmp_path / "again.mcap"
    with Player(path, rate=INF) as player, Recorder((), again) as rec2:
        player.play(lambda msg, record: rec2.write(msg))
    with Recording(path) as first, Recording(again) as second:
        one = [(m.topic, m.sequence, m.log_time_ns, m.channel.schema_name, m.data) for m in first.messages()]
        two = [(m.topic, m.sequence, m.log_time_ns, m.channel.schema_name, m.data) for m in second.messages()]
    assert one == two and len(one) == total


def test_key_for_topic() -> None:
    assert key_for_topic("/camera/image") == "camera/image"
    assert key_for_topic("//a//b/") == "a/b"
    assert key_for_topic("x/*/$y?#") == "x/_/_y__"
    assert key_for_topic("/") == ""
