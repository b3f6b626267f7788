"""Tests for dyknow.recording.writer: the Recorder, durability and errors, the recorder unit.

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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from dyknow import Manager
from dyknow.errors import BindingError, ClosedError, RecordingError
from dyknow.message import Message
from dyknow.recording import (
    Player,
    Recorder,
    Recording,
)
from dyknow.transport import Session
from tests.conftest import REPO, UNIT_SPECS, subprocess_env, wait_until
from tests.recording.support import MIXED, SPECS, official, same_payload, wait_matched

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
        # reliable: Zenoh blocks rather than drops when its queue is full, so a loss would be the recorder's
        publishers = [session.declare_publisher(k, reliable=True) for k in keys]
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
    assert str(info.value) == f"{tmp_path / 'missing' / 'out.mcap'}: cannot create the file: No such file or directory (does the folder exist?)"
    with pytest.raises(RecordingError, match=r"^.*file\.txt/out\.mcap: cannot create the file: Not a directory$"):
        Recorder((), tmp_path / "file.txt" / "out.mcap")
    with pytest.raises(RecordingError, match=r"^.*: cannot create the file: Is a directory$"):
        Recorder((), tmp_path)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_a_full_disk_is_a_clear_error() -> None:
    with pytest.raises(RecordingError) as info:
        Recorder((), "/dev/full")
    assert str(info.value) == "/dev/full: cannot write the file: No space left on device (the disk is full); nothing was recorded"


@pytest.mark.process
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
    assert report["first"].startswith(f"{path}: cannot write the file: File too large; recording stopped after ")
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


def test_close_with_a_huge_backlog_is_bounded_and_still_finalizes(tmp_path: Path) -> None:
    """close() never hangs: a huge backlog is cut at the timeout and still gives a valid file."""
    path = tmp_path / "backlog.mcap"
    rec = Recorder((), path, compression="zstd")
    frame = np.random.default_rng(1).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    for i in range(400):
        rec.write(Message(frame, i + 1, i, i, "big/x"))
    with pytest.raises(RecordingError, match="writing did not finish within 0.05 s; the rest was dropped"):
        rec.close(timeout_s=0.05)
    assert rec.dropped > 0 and rec.count + rec.dropped == 400
    with Recording(path) as recording:  # finalized: readable without recovery
        assert recording.info.message_count == rec.count


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
