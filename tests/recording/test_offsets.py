"""Times of other clocks in a recording (dyknow.recording.offsets): records, and a replay that corrects.

The records and their rules are checked on their own; then a real recording: a ``dyknow manager``
process whose wall clock runs 250 ms ahead (libfaketime) publishes, a recorder in this process
(with its own clock tracker) records it, and a player gives every origin back on the
recording's clock, within the recorded uncertainty of the truth (known exactly: the manager
runs through tests/clocked.py, which prints its wall clock beside the monotonic clock).
"""

from __future__ import annotations

import json
import math
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dyknow import Client, Message
from dyknow.errors import RecordingError
from dyknow.message import CLOCK_ID
from dyknow.recording import CLOCK_METADATA, CLOCKS_TOPIC, PAYLOAD_METADATA, Player, RecordedMessage, Recorder, Recording
from dyknow.recording.offsets import MAX_CLOCKS, ClockRecord, OffsetLog, Offsets
from tests.conftest import GENERIC_SPECS, REPO, end_process, faked_clock, free_port, subprocess_env, wait_until

OWN, OTHER = 0x0000AAAA, 0x0000BBBB
MS = 1_000_000
T0 = 1_780_000_000_000_000_000


# ---------------------------------------------------------------------------- records


def test_a_record_round_trips_as_documented() -> None:
    record = ClockRecord(OTHER, 250 * MS, 150_000, T0)
    assert json.loads(record.to_json()) == {"clock": "0000bbbb", "offset_ns": 250 * MS, "uncertainty_ns": 150_000, "at_ns": T0}
    assert ClockRecord.from_json(record.to_json(), "here") == record
    unknown = ClockRecord(OTHER, None, None, T0)
    assert json.loads(unknown.to_json())["offset_ns"] is None and ClockRecord.from_json(unknown.to_json(), "here") == unknown


@pytest.mark.parametrize(
    "data",
    [
        b"not json",
        b"[1]",
        b'{"clock": "0000bbbb", "offset_ns": 1, "uncertainty_ns": 1}',  # no at_ns
        b'{"clock": "bbbb", "offset_ns": 1, "uncertainty_ns": 1, "at_ns": 1}',
        b'{"clock": "0000zzzz", "offset_ns": 1, "uncertainty_ns": 1, "at_ns": 1}',
        b'{"clock": "0000bbbb", "offset_ns": 1, "uncertainty_ns": null, "at_ns": 1}',  # half known
        b'{"clock": "0000bbbb", "offset_ns": 1.5, "uncertainty_ns": 1, "at_ns": 1}',
        b'{"clock": "0000bbbb", "offset_ns": true, "uncertainty_ns": 1, "at_ns": 1}',
        b'{"clock": "0000bbbb", "offset_ns": 1, "uncertainty_ns": -1, "at_ns": 1}',
        b'{"clock": "0000bbbb", "offset_ns": 1, "uncertainty_ns": 1, "at_ns": 99999999999999999999999}',
        b'{"clock": "0000bbbb", "offset_ns": 1, "uncertainty_ns": 1, "at_ns": 1, "pad": "' + b"x" * 2000 + b'"}',
    ],
)
def test_a_malformed_record_is_refused_saying_where_and_what(data: bytes) -> None:
    with pytest.raises(RecordingError) as info:
        ClockRecord.from_json(data, "run.mcap: dyknow/clocks #3")
    assert "run.mcap: dyknow/clocks #3" in str(info.value) and "clock record" in str(info.value)


def test_the_recorder_writes_a_record_when_a_clock_is_new_changed_or_became_known() -> None:
    log = OffsetLog(OWN)
    assert log.note(OWN, 0, 0, T0) == []  # its own clock needs none
    first = log.note(OTHER, None, None, T0)
    assert first == [ClockRecord(OWN, 0, 0, T0), ClockRecord(OTHER, None, None, T0)]  # its own clock first, then the unknown one
    assert log.note(OTHER, None, None, T0 + 1) == []
    assert log.note(OTHER, 250 * MS, 100_000, T0 + 2) == [ClockRecord(OTHER, 250 * MS, 100_000, T0 + 2)]  # became known
    assert log.note(OTHER, 250 * MS + 90_000, 100_000, T0 + 3) == []  # within its uncertainty
    assert log.note(OTHER, 250 * MS + 150_000, 100_000, T0 + 4) == [ClockRecord(OTHER, 250 * MS + 150_000, 100_000, T0 + 4)]
    assert log.note(OTHER, None, None, T0 + 5) == [ClockRecord(OTHER, None, None, T0 + 5)]  # forgotten (the peer left)
    assert log.note(0, 5, 5, T0 + 6) == [ClockRecord(0, None, None, T0 + 6)]  # clock 0 is never known


def test_past_max_clocks_messages_go_to_clock_zero() -> None:
    log = OffsetLog(OWN)
    for clock in range(1, MAX_CLOCKS + 1):
        assert log.clock_of(clock) == clock
        log.note(clock, 0, 0, T0)
    assert log.clock_of(MAX_CLOCKS + 1) == 0 and log.clock_of(1) == 1 and log.clock_of(OWN) == OWN


def test_an_origin_is_corrected_by_the_record_current_then() -> None:
    offsets = Offsets([
        ClockRecord(OTHER, 250 * MS, 100_000, T0 + 10 * MS),
        ClockRecord(OTHER, None, None, T0),
        ClockRecord(OTHER, 251 * MS, 120_000, T0 + 5_000 * MS),
        ClockRecord(OWN, 0, 0, T0),
    ])  # fmt: skip
    assert offsets.clocks() == [OWN, OTHER]
    stamped = T0 + 250 * MS  # on OTHER's clock: T0 on the recording's, before the first record
    assert offsets.corrected(OTHER, stamped) is None  # the recorder did not know it yet
    assert offsets.corrected(OTHER, stamped + 20 * MS) == (T0 + 20 * MS, 100_000)
    assert offsets.corrected(OTHER, T0 + 6_000 * MS) == (T0 + 6_000 * MS - 251 * MS, 120_000)
    assert offsets.corrected(0x1234, T0) is None and not Offsets([])


# ---------------------------------------------------------------------------- a recording of another clock, replayed


class Faked:
    """A ``dyknow manager`` process on loopback whose wall clock is faked, and its clock line."""

    def __init__(self, name: str, env: dict[str, str]) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        argv = [sys.executable, "-m", "tests.clocked", "manager", "--name", name, "--listen", self.endpoint, "--specs", str(GENERIC_SPECS), "--json"]
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**subprocess_env(), **env}, cwd=REPO)
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        self.clock = self.next("clock")
        self.next("ready")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.lines.put(json.loads(line))

    def next(self, event: str) -> dict[str, Any]:
        while True:
            try:
                line = self.lines.get(timeout=30)
            except queue.Empty:
                self.proc.kill()
                raise AssertionError(f"no {event} line; stderr: {self.proc.stderr.read()[-2000:] if self.proc.stderr else ''}") from None
            if line.get("event") == event:
                return line

    def injected(self) -> int:
        """Its clock minus this process's (a constant offset: no rate)."""
        before, realtime, after = time.monotonic_ns(), time.time_ns(), time.monotonic_ns()
        return int(self.clock["realtime_ns"] - self.clock["monotonic_ns"] - (realtime - (before + after) // 2))

    def close(self) -> None:
        end_process(self.proc)


@pytest.fixture
def ahead(faketime: Path) -> Iterator[Faked]:
    manager = Faked("ahead", faked_clock(faketime, "+0.25"))
    try:
        yield manager
    finally:
        manager.close()


@pytest.mark.process
def test_a_replay_corrects_origins_of_another_clock_by_the_recorded_offset(ahead: Faked, tmp_path: Path) -> None:
    path = tmp_path / "ahead.mcap"
    injected = ahead.injected()
    assert abs(injected - 250 * MS) < MS
    slack = ahead.clock["read_ns"] // 2 + 1_000  # how sure the clock line is
    with Client("ahead", connect=[ahead.endpoint]) as client:
        client.spawn("periodic-source", "src", params={"rate_hz": 200})
        with Recorder(["dyknow/ahead/src/out"], path, connect=[ahead.endpoint]) as recorder:
            wait_until(lambda: recorder.count >= 400, "400 messages recorded")

    with Recording(path) as recording:
        raw = [r for r in recording.messages() if r.topic == CLOCKS_TOPIC]
    records = [ClockRecord.from_json(r.data, "test") for r in raw]
    assert records[0] == ClockRecord(CLOCK_ID, 0, 0, records[0].at_ns)  # the recorder's own clock first
    known = [r for r in records[1:] if r.offset_ns is not None]
    assert known and {r.clock for r in records[1:]} == {known[0].clock} != {CLOCK_ID}
    for record in known:  # as the recorder's tracker estimated it: within its uncertainty of the truth
        assert record.offset_ns is not None and record.uncertainty_ns is not None
        assert abs(record.offset_ns - injected) <= record.uncertainty_ns + slack, (record, injected)

    with Player(path, rate=math.inf) as player:
        assert [c.topic for c in player.channels] == ["dyknow/ahead/src/out"]  # the records are not a stream to replay
        assert player.channels[0].metadata[CLOCK_METADATA] == f"{known[0].clock:08x}"
        replayed: list[tuple[Message, RecordedMessage]] = []
        assert player.play(lambda m, r: replayed.append((m, r))) >= 400
        corrected = 0
        for message, stored in replayed:
            origin = player.corrected_origin(stored)
            record = Offsets(records).record(known[0].clock, stored.log_time_ns)
            assert record is not None
            if origin is None:  # recorded before the tracker knew the clock: as stamped, and marked unknown
                assert record.offset_ns is None and (message.origin_ns, message.origin_clock) == (stored.log_time_ns, 0)
                continue
            corrected += 1
            assert record.uncertainty_ns is not None
            assert abs(origin - (stored.log_time_ns - injected)) <= record.uncertainty_ns + slack  # the true time of the stamp
            assert (message.origin_ns, message.origin_clock) == (origin, CLOCK_ID)
        assert corrected > 0

    with Player(path, correct_clocks=False) as player:
        assert all(player.corrected_origin(r) is None for r in player.messages())  # as stamped, and marked so


def test_a_recording_of_its_own_clock_has_no_clock_records(tmp_path: Path) -> None:
    """Messages stamped by the recorder's own clock: the file is as before (no records, no clock metadata)."""
    path = tmp_path / "own.mcap"
    with Recorder(path=path) as recorder:
        for seq in range(1, 4):
            recorder.write(Message({"n": seq}, seq, T0 + seq, T0 + seq, "own/key"))
    with Recording(path) as recording:
        assert [(c.topic, dict(c.metadata)) for c in recording.channels] == [("own/key", {PAYLOAD_METADATA: "json"})]
    with Player(path) as player:
        assert [player.corrected_origin(r) for r in player.messages()] == [T0 + 1, T0 + 2, T0 + 3]


def test_a_message_of_a_clock_nobody_knows_is_recorded_unknown_and_replayed_so(tmp_path: Path) -> None:
    path = tmp_path / "unknown.mcap"
    with Recorder(path=path) as recorder:
        recorder.write(Message({"n": 1}, 1, T0, T0, "other/key", origin_clock=OTHER))
        recorder.write(Message({"n": 2}, 2, T0 + 1, T0 + 1, "other/key"))  # the same key, this process's clock: a channel of its own
    with Recording(path) as recording:
        assert sorted((c.topic, c.metadata.get(CLOCK_METADATA, "")) for c in recording.channels) == [
            (CLOCKS_TOPIC, ""), ("other/key", ""), ("other/key", f"{OTHER:08x}"),
        ]  # fmt: skip
    with Player(path, rate=math.inf) as player:
        got: list[Message] = []
        player.play(lambda m, r: got.append(m))
        assert [(m.payload["n"], m.origin_ns, m.origin_clock) for m in got] == [(1, T0, 0), (2, T0 + 1, CLOCK_ID)]
