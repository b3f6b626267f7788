"""Tests for dyknow.recording.player: topics, remapping, windows, pace, the replay unit, and the round
trip live pipeline -> recording -> replay through real Zenoh sessions."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dyknow import Manager
from dyknow.errors import ClosedError, RecordingError
from dyknow.message import Message
from dyknow.recording import (
    Player,
    RecordedMessage,
    Recorder,
    Recording,
    key_for_topic,
)
from dyknow.transport import Session
from tests.conftest import UNIT_SPECS
from tests.mcap.units import PORTS, frame
from tests.recording.support import FOREIGN, INF, MIXED, SPECS, play_all, real, same_payload, write_mcap

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
        f"{four_topics}: no topic matches '/imu2'; expected one of its topics '/camera/image', '/camera/info', '/imu', 'robot*1' (did you mean '/imu'?)"
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


def test_key_for_topic() -> None:
    assert key_for_topic("/camera/image") == "camera/image"
    assert key_for_topic("//a//b/") == "a/b"
    assert key_for_topic("x/*/$y?#") == "x/_/_y__"
    assert key_for_topic("/") == ""


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
        assert same_payload(published[f"dyknow/{manager.name}/src/image"][i][1], frame(i, "image"))

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
            assert same_payload(payload, want_payload), key

    # recording the replay gives the very same file content: data bytes, log times, sequences
    again = tmp_path / "again.mcap"
    with Player(path, rate=INF) as player, Recorder((), again) as rec2:
        player.play(lambda msg, record: rec2.write(msg))
    with Recording(path) as first, Recording(again) as second:
        one = [(m.topic, m.sequence, m.log_time_ns, m.channel.schema_name, m.data) for m in first.messages()]
        two = [(m.topic, m.sequence, m.log_time_ns, m.channel.schema_name, m.data) for m in second.messages()]
    assert one == two and len(one) == total
