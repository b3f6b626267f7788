"""Tests for dyknow.recording: the Recorder, its MCAP mapping, durability and errors.

Files are read back with the official ``mcap`` reader (what other tools see) as well as with
dyknow's own reader. Messages travel through real Zenoh sessions on loopback.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from dyknow import Manager
from dyknow.errors import BindingError, ClosedError, RecordingError
from dyknow.message import Message
from dyknow.recording import (
    COMPRESSED_IMAGE,
    NDARRAY,
    PAYLOAD_METADATA,
    PROTOBUF_SCHEMAS,
    RAW_IMAGE,
    Recorder,
    _compressed_image,
    _raw_image,
    image_encoding,
)
from dyknow.replay import Player, Recording, _pb_fields
from dyknow.transport import Publisher, Session, make_config
from tests.conftest import REPO, UNIT_SPECS, free_port, subprocess_env

SPECS = REPO / "specs" / "recording.xml"
MIXED = REPO / "tests" / "mcap" / "units.xml"
FOREIGN = REPO / "tests" / "mcap" / "foxglove-protobuf.mcap"


def official(path: Path) -> tuple[Any, list[tuple[Any, Any, Any]]]:
    """The summary and (schema, channel, message) triples as the official mcap reader sees them."""
    with open(path, "rb") as file:
        reader = make_reader(file, validate_crcs=True)
        return reader.get_summary(), list(reader.iter_messages(log_time_order=False))


@pytest.fixture
def listening() -> Iterator[tuple[Session, str]]:
    """A session listening on a free loopback port, and its endpoint (for recorders to connect to)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Session(make_config(listen=[endpoint])) as session:
        yield session, endpoint


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    """Wait for state another thread or process changes and that has no event of its own."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"{what} within {timeout} s"
        time.sleep(0.005)


def wait_matched(publisher: Publisher, timeout: float = 10.0) -> None:
    wait_until(lambda: publisher.matched, f"a subscriber for {publisher.key}", timeout)


# --- the MCAP mapping ----------------------------------------------------------------------------

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


def same_payload(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and bool((a == b).all())
    return type(a) is type(b) and a == b


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
    image = _pb_fields(by_key["m/bgr"][1].data)
    assert (image[2], image[3], bytes(image[4][0]), image[5]) == ([5], [4], b"bgr8", [15])
    assert bytes(image[6][0]) == PAYLOADS["m/bgr"].tobytes()
    assert bytes(_pb_fields(by_key["m/mono16"][1].data)[4][0]) == b"mono16"
    compressed = _pb_fields(by_key["m/jpeg"][1].data)
    assert (bytes(compressed[2][0]), bytes(compressed[3][0])) == (PAYLOADS["m/jpeg"], b"jpeg")
    array = _pb_fields(by_key["m/matrix"][1].data)
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
    assert _raw_image(np.arange(18, dtype=np.uint8).reshape(2, 3, 3), "bgr8", 1030) == theirs["/same/raw"].data
    png = bytes(_pb_fields(theirs["/same/png"].data)[2][0])
    assert _compressed_image(png, "png", 1040) == theirs["/same/png"].data
    for name in (RAW_IMAGE, COMPRESSED_IMAGE):
        official_fields = descriptor_fields(theirs["/same/raw" if name == RAW_IMAGE else "/same/png"].channel.schema_data, name)
        assert descriptor_fields(PROTOBUF_SCHEMAS[name], name) == {k: v for k, v in official_fields.items() if k in descriptor_fields(PROTOBUF_SCHEMAS[name], name)}
        assert {"timestamp", "frame_id", "data"} <= set(official_fields)


def descriptor_fields(descriptor_set: bytes, full_name: str) -> dict[str, tuple[int, int, int, str]]:
    """{field: (number, label, type, type name)} of a message in a FileDescriptorSet."""
    package, _, message = full_name.rpartition(".")
    for file in _pb_fields(descriptor_set)[1]:
        proto = _pb_fields(file)
        if bytes(proto.get(2, [b""])[0]).decode() != package:
            continue
        for message_type in proto.get(4, []):
            desc = _pb_fields(message_type)
            if bytes(desc[1][0]).decode() == message:
                out = {}
                for f in desc.get(2, []):
                    fd = _pb_fields(f)
                    out[bytes(fd[1][0]).decode()] = (fd[3][0], fd[4][0], fd[5][0], bytes(fd.get(6, [b""])[0]).decode())
                return out
    raise AssertionError(f"{full_name} is not in the descriptor set")


# --- recording from Zenoh ------------------------------------------------------------------------


def test_header_fields_come_from_the_dyknow_header(tmp_path: Path, listening: tuple[Session, str]) -> None:
    session, endpoint = listening
    path = tmp_path / "header.mcap"
    with Recorder(["h/**"], path, connect=[endpoint], max_messages=3) as rec, session.declare_publisher("h/x") as pub:
        wait_matched(pub)
        for seq, origin, send in [(7, 1_000, 2_000), (8, 1_500, 2_600), (9, 1_200, 2_700)]:
            pub.put(Message({"seq": seq}, seq, origin, send, "h/x"))
        assert rec.wait(10.0)
    _, triples = official(path)
    assert [(m.sequence, m.log_time, m.publish_time, m.data) for _, _, m in triples] == [
        (7, 1_000, 2_000, b'{"seq":7}'), (8, 1_500, 2_600, b'{"seq":8}'), (9, 1_200, 2_700, b'{"seq":9}'),
    ]  # fmt: skip
    with Recording(path) as recording:  # replay order is log-time order, not arrival order
        assert [m.sequence for m in recording.messages()] == [7, 9, 8]


def test_plain_zenoh_samples_are_recorded_too(tmp_path: Path, listening: tuple[Session, str]) -> None:
    session, endpoint = listening
    path = tmp_path / "raw.mcap"
    before = time.time_ns()
    with Recorder(["plain/**"], path, connect=[endpoint], max_messages=3) as rec:
        deadline = time.monotonic() + 10
        with session.declare_publisher("plain/probe") as probe:
            wait_matched(probe)  # the recorder is subscribed once a publisher sees it
        session.put("plain/json", b'{"a": 1}', encoding="application/json")
        session.put("plain/text", "hi", encoding="text/plain")
        session.put("plain/bin", b"\x01\x02", encoding="application/octet-stream")
        assert rec.wait(max(0.0, deadline - time.monotonic()))
    with Player(path, rate=float("inf")) as player:
        got = []
        player.play(lambda msg, record: got.append((msg.key, msg.payload, record.sequence, record.log_time_ns)))
    assert sorted((k, p) for k, p, _, _ in got) == [("plain/bin", b"\x01\x02"), ("plain/json", {"a": 1}), ("plain/text", "hi")]
    assert sorted(s for _, _, s, _ in got) == [1, 2, 3]  # the subscriber's own count, synthesised
    assert all(before <= t <= time.time_ns() for _, _, _, t in got)  # the arrival time


def test_every_message_published_under_load_is_in_the_file(tmp_path: Path, listening: tuple[Session, str]) -> None:
    session, endpoint = listening
    path = tmp_path / "load.mcap"
    keys = ["load/a", "load/b", "load/c"]
    per_key = 3000
    image = np.zeros((120, 160, 3), np.uint8)
    with Recorder(["load/**"], path, connect=[endpoint], chunk_size=256 * 1024, max_messages=per_key * len(keys)) as rec:
        publishers = [session.declare_publisher(k) for k in keys]
        for pub in publishers:
            wait_matched(pub)
        for seq in range(1, per_key + 1):  # as fast as the publishers go, three streams interleaved
            publishers[0].put(Message(image if seq % 100 == 0 else b"x" * 200, seq, time.time_ns(), time.time_ns(), keys[0]))
            publishers[1].put(Message({"seq": seq}, seq, time.time_ns(), time.time_ns(), keys[1]))
            publishers[2].put(Message(f"text {seq}", seq, time.time_ns(), time.time_ns(), keys[2]))
        assert rec.wait(30.0), f"recorded {rec.count} of {per_key * len(keys)}"
        for pub in publishers:
            pub.undeclare()
    assert rec.count == per_key * len(keys) and rec.dropped == 0
    summary, triples = official(path)
    assert summary.statistics.message_count == per_key * len(keys)
    for key in keys:
        assert [m.sequence for _, c, m in triples if c.topic == key] == list(range(1, per_key + 1)), key


@pytest.mark.parametrize(("compression", "stored"), [("zstd", "zstd"), ("lz4", "lz4"), ("none", "")])
def test_files_are_chunked_compressed_and_indexed(tmp_path: Path, compression: str, stored: str) -> None:
    path = tmp_path / f"{compression}.mcap"
    with Recorder((), path, compression=compression, chunk_size=4096) as rec:
        for i in range(500):
            rec.write(Message({"i": i, "text": "a fairly compressible payload " * 3}, i + 1, 10_000 + i, 20_000 + i, f"c/{i % 3}"))
    with open(path, "rb") as file:
        reader = make_reader(file, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 500 and summary.statistics.chunk_count == len(summary.chunk_indexes) > 5
        assert {ci.compression for ci in summary.chunk_indexes} == {stored}
        assert all(ci.message_index_offsets for ci in summary.chunk_indexes)  # message indexes follow each chunk
        assert (summary.statistics.message_start_time, summary.statistics.message_end_time) == (10_000, 10_499)
        assert [m.log_time for _, _, m in reader.iter_messages()] == list(range(10_000, 10_500))
    if compression != "none":
        assert path.stat().st_size < 500 * 80  # smaller than the data itself
    with Recording(path) as recording:
        assert recording.info.indexed and recording.info.compressions == ((stored or "none"),)


# --- durability and errors -----------------------------------------------------------------------


def test_unwritable_paths_are_clear_errors(tmp_path: Path) -> None:
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(RecordingError) as info:
        Recorder((), tmp_path / "missing" / "out.mcap")
    assert str(info.value) == f"cannot create {tmp_path / 'missing' / 'out.mcap'}: No such file or directory (does the folder exist?)"
    with pytest.raises(RecordingError, match=r"cannot create .*file\.txt/out\.mcap: Not a directory$"):
        Recorder((), tmp_path / "file.txt" / "out.mcap")
    with pytest.raises(RecordingError, match=r"cannot create .*: Is a directory$"):
        Recorder((), tmp_path)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_a_full_disk_is_a_clear_error() -> None:
    with pytest.raises(RecordingError) as info:
        Recorder((), "/dev/full")
    assert str(info.value) == "cannot write /dev/full: No space left on device (the disk is full); nothing was recorded"


def test_a_write_failing_mid_recording_stops_it_and_keeps_the_complete_chunks(tmp_path: Path) -> None:
    """The file size limit (RLIMIT_FSIZE) makes writes fail the way a full disk does, mid-recording."""
    path = tmp_path / "limited.mcap"
    script = textwrap.dedent(f"""
        import json, resource, signal
        from dyknow.errors import RecordingError
        from dyknow.message import Message
        from dyknow.recording import Recorder
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
        rec = Recorder((), {str(path)!r}, chunk_size=1000)
        sent = 0
        try:
            for i in range(2000):
                rec.write(Message({{"i": i, "pad": "p" * 200}}, i + 1, 1000 + i, 1000 + i, "lim/x"))
                sent += 1
        except RecordingError as exc:
            first = str(exc)
        else:
            rec.wait(10)
            first = str(rec.error)
        try:
            rec.close()
            closed = "closed without error"
        except RecordingError as exc:
            closed = str(exc)
        print(json.dumps({{"first": first, "closed": closed, "count": rec.count, "sent": sent}}))
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, env=subprocess_env(), cwd=REPO)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["first"].startswith(f"cannot write {path}: File too large; recording stopped after ")
    assert report["closed"] == report["first"]  # close raises the recording's error
    assert 0 < report["count"] < 2000
    with pytest.raises(RecordingError, match=rf"^{path}: truncated at offset \d+"):
        Recording(path)
    with Recording(path, recover=True) as recording:
        got = [json.loads(m.data)["i"] for m in recording.messages()]
    assert got == list(range(len(got))) and 0 < len(got) <= report["count"]


def test_use_after_close_and_close_twice(tmp_path: Path) -> None:
    rec = Recorder((), tmp_path / "c.mcap")
    rec.write(Message(b"1", 1, 1, 1, "c/x"))
    rec.close()
    rec.close()
    assert rec.closed and rec.count == 1
    with pytest.raises(ClosedError, match="is closed"):
        rec.write(Message(b"2", 2, 2, 2, "c/x"))
    with Recording(tmp_path / "c.mcap") as recording:
        assert recording.info.message_count == 1


def test_max_messages_stops_the_recording(tmp_path: Path) -> None:
    with Recorder((), tmp_path / "max.mcap", max_messages=5) as rec:
        assert not rec.wait(0)
        for i in range(12):
            rec.write(Message(i, i + 1, i, i, "max/x"))
        assert rec.wait(0)
    with Recording(tmp_path / "max.mcap") as recording:
        assert [json.loads(m.data) for m in recording.messages()] == [0, 1, 2, 3, 4]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"compression": "gzip"}, "compression: got 'gzip'; expected one of zstd, lz4, none"),
        ({"chunk_size": 0}, "chunk_size: got 0; expected a positive number of bytes"),
        ({"max_messages": 0}, "max_messages: got 0; expected a positive number"),
    ],
)
def test_bad_arguments_are_refused_before_anything_is_written(tmp_path: Path, kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(RecordingError) as info:
        Recorder((), tmp_path / "bad.mcap", **kwargs)
    assert str(info.value) == message
    assert not (tmp_path / "bad.mcap").exists()


def test_a_bad_key_expression_is_refused(tmp_path: Path) -> None:
    with pytest.raises(BindingError, match="key expression to record"):
        Recorder(["robot//x"], tmp_path / "k.mcap")


def test_import_does_not_pull_opencv() -> None:
    code = "import sys, dyknow.recording, dyknow.replay, transformations.recording; print('cv2' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=subprocess_env(), cwd=REPO)
    assert out.stdout.strip() == "False"


# --- the recorder unit ---------------------------------------------------------------------------


def test_recorder_unit_attaches_to_any_stream_at_runtime(tmp_path: Path, make_manager: Callable[..., Manager]) -> None:
    manager = make_manager(specs=[UNIT_SPECS, SPECS, MIXED])
    path = tmp_path / "unit.mcap"
    manager.spawn("publisher", "pub")  # another stream, to move the recorder to later
    info = manager.spawn("recorder", "rec", params={"path": str(path)}, bindings={"in": f"dyknow/{manager.name}/src/*"})
    assert info.state == "running"
    manager.spawn("mixed-source", "src", params={"count": 5, "rate_hz": 500})
    source = manager.unit("src")
    assert source.done.wait(10.0)  # the recorder is a local subscriber: the source starts at once
    recorder = manager.unit("rec").recorder
    wait_until(lambda: recorder.count == 40, "40 messages recorded")
    manager.set_config("rec", {"in": f"dyknow/{manager.name}/pub/out"})  # rebind at runtime
    manager.unit("pub").emit(b"later")
    wait_until(lambda: recorder.count == 41, "the message on the new binding recorded")
    manager.destroy("rec")  # finalizes the file
    with Player(path, rate=float("inf")) as player:
        assert player.info.indexed and player.problem is None
        replayed: dict[str, list[Any]] = {}
        player.play(lambda msg, record: replayed.setdefault(msg.key, []).append(msg.payload))
    published: dict[str, list[Any]] = {}
    for port, payload, _ in source.published:
        published.setdefault(f"dyknow/{manager.name}/src/{port}", []).append(payload)
    assert set(replayed) == set(published) | {f"dyknow/{manager.name}/pub/out"}
    for key, payloads in published.items():
        assert len(replayed[key]) == 5 and all(same_payload(a, b) for a, b in zip(replayed[key], payloads, strict=True)), key
    assert replayed[f"dyknow/{manager.name}/pub/out"] == [b"later"]


def test_recorder_unit_with_an_unwritable_path_fails_with_the_reason(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    manager = make_manager(specs=[SPECS])
    info = manager.spawn("recorder", "rec", params={"path": str(tmp_path / "no" / "such" / "dir.mcap")})
    assert info.state == "failed"
    assert "cannot create" in (info.error or "") and "No such file or directory" in (info.error or "")


def test_close_with_a_huge_backlog_is_bounded_and_still_finalizes(tmp_path: Path) -> None:
    """close() never hangs: a huge backlog is cut at the timeout and still gives a valid file."""
    path = tmp_path / "backlog.mcap"
    rec = Recorder((), path, compression="zstd")
    frame = np.random.default_rng(1).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    for i in range(400):
        rec.write(Message(frame, i + 1, i, i, "big/x"))
    with pytest.raises(RecordingError, match="writing did not finish within 0.05 s; the rest was dropped"):
        rec.close(timeout=0.05)
    assert rec.dropped > 0 and rec.count + rec.dropped == 400
    with Recording(path) as recording:  # finalized: readable without recovery
        assert recording.info.message_count == rec.count
