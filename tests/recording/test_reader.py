"""Tests for dyknow.recording.reader (with framing and scan): reading MCAP files, and damaged files
named by file and offset, recovered when asked."""

from __future__ import annotations

import json
import logging
import random
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from dyknow.errors import RecordingError
from dyknow.message import Message
from dyknow.recording import Player, Recorder, Recording
from tests.recording.support import INF, play_all, real

# --- reading -------------------------------------------------------------------------------------


def test_json_channels_in_zstd_chunks(data_dir: Path) -> None:
    delivered = play_all(real(data_dir, "example.mcap"))
    assert len(delivered) == 111 and delivered[0][0].payload == {"clientX": 1511, "clientY": 974}
    assert {m.key for m, _ in delivered} == {"mouse"}
    with Recording(real(data_dir, "example.mcap")) as recording:
        info = recording.info
    assert (info.chunk_count, info.compressions, info.start_ns, info.end_ns) == (2, ("zstd",), 1740566235448000000, 1740566238556000000)


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
        (b"PK\x03\x04 a zip file, not MCAP", "not an MCAP file: it does not begin with the MCAP magic; expected the MCAP magic b'\\x89MCAP0\\r\\n'"),
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
    with pytest.raises(RecordingError, match=r"^/nonexistent/x\.mcap: cannot read the file: No such file or directory$"):
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


def records_of(path: Path) -> list[Any]:
    """The records of a file, read with ``recover``."""
    with Recording(path, recover=True) as recording:
        return list(recording.records())


def test_records_name_the_damage_and_stop_there_when_recovering(recorded: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The streamed records (read by the mcap library's StreamReader) of a damaged file: an error
    naming the file and offset, or, recovering, every record before the damage and a warning."""
    intact = records_of(recorded)
    offsets = chunk_offsets(recorded)
    data = bytearray(recorded.read_bytes())
    data[offsets[2] + 60] ^= 0xFF  # inside the third chunk's compressed data
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(bytes(data))
    with Recording(corrupt) as recording, pytest.raises(RecordingError) as info:  # indexed: opens, damage shows when read
        list(recording.records())
    assert str(info.value).startswith(f"{corrupt}: corrupt at offset {offsets[2]}: cannot decompress the zstd chunk")
    with caplog.at_level(logging.WARNING, logger="dyknow.recording.reader"):
        got = records_of(corrupt)
    assert 0 < len(got) < len(intact) and got == intact[: len(got)]
    assert f"corrupt at offset {offsets[2]}: cannot decompress the zstd chunk" in caplog.text and "stopping there" in caplog.text
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recorded.read_bytes()[: offsets[4] + 30])
    got = records_of(cut)
    assert 0 < len(got) < len(intact) and got == intact[: len(got)]  # a prefix: nothing made up
    extra = tmp_path / "extra.mcap"
    extra.write_bytes(recorded.read_bytes() + b"more")
    assert records_of(extra) == intact  # the footer is the last record; what follows it is the damage
    assert "expected the MCAP magic (and nothing else) after the footer" in caplog.text


def test_a_corrupt_length_field_is_damage_not_a_memory_error(recorded: Path, tmp_path: Path) -> None:
    """A chunk claiming 2**60 bytes of data: the mcap library would try to allocate them."""
    offsets = chunk_offsets(recorded)
    data = bytearray(recorded.read_bytes())
    header = offsets[1] + 9 + 8 + 8 + 8 + 4  # start, end, uncompressed size, CRC
    name_length = int.from_bytes(data[header : header + 4], "little")
    data[header + 4 + name_length : header + 4 + name_length + 8] = (2**60).to_bytes(8, "little")
    path = tmp_path / "long.mcap"
    path.write_bytes(bytes(data))
    with Recording(path) as recording:
        for read in (recording.messages, recording.records):
            with pytest.raises(RecordingError, match=rf"^{path}: corrupt at offset {offsets[1]}: the Chunk record holds \d+ bytes of data; its header says {2**60}"):
                list(read())


def test_a_summary_whose_crc_does_not_match_is_damage(recorded: Path, tmp_path: Path) -> None:
    data = bytearray(recorded.read_bytes())
    summary_start = int.from_bytes(data[-8 - 20 : -8 - 12], "little")  # the footer's summary start
    data[summary_start + 20] ^= 0xFF
    path = tmp_path / "summary.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=rf"^{path}: corrupt at offset {summary_start}: the summary's CRC does not match"):
        Recording(path)
    with Recording(path, recover=True) as recording:  # the data section is scanned instead
        assert not recording.info.indexed and recording.info.message_count == 300
        assert [json.loads(m.data)["i"] for m in recording.messages()] == list(range(300))


def test_an_unknown_chunk_compression_is_named_not_read_as_raw(tmp_path: Path) -> None:
    """The mcap library reads a chunk whose compression it does not know as uncompressed."""
    path = tmp_path / "plain.mcap"
    with Recorder((), path, compression="none", chunk_size=1500) as rec:
        for i in range(100):
            rec.write(Message({"i": i}, i + 1, i, i, "c/x"))
    offsets = chunk_offsets(path)
    data = bytearray(path.read_bytes())
    name = offsets[1] + 9 + 8 + 8 + 8 + 4  # the compression's length (0: none), then the data's length and the data
    length = int.from_bytes(data[name + 4 : name + 12], "little")
    chunk_data = data[name + 12 : name + 12 + length]
    # "brot" takes the place of the data's first 4 bytes, so that the record keeps its length
    data[name : name + 12 + length] = (4).to_bytes(4, "little") + b"brot" + (length - 4).to_bytes(8, "little") + chunk_data[4:]
    path.write_bytes(bytes(data))
    with Recording(path) as recording, pytest.raises(RecordingError) as info:
        list(recording.messages())
    assert str(info.value).startswith(f"{path}: corrupt at offset {offsets[1]}: unknown chunk compression 'brot'; expected zstd, lz4 or none")
    with Recording(path, recover=True) as recording:
        got = [json.loads(m.data)["i"] for m in recording.messages()]
    missing = sorted(set(range(100)) - set(got))
    assert got == sorted(got) and missing and missing == list(range(missing[0], missing[-1] + 1))  # that chunk only


def test_a_corrupt_summary_without_crc_is_damage(tmp_path: Path) -> None:
    """Nothing vouches for a summary written without a CRC: a Schema in it claiming 1 GiB of data
    is damage at the summary's offset (the library alone would allocate the GiB first), and a
    scan reads the data instead."""
    path = tmp_path / "nocrc.mcap"
    with open(path, "wb") as file:
        writer = Writer(file, compression=CompressionType.ZSTD, enable_crcs=False)
        writer.start(profile="", library="test")
        channel = writer.register_channel("/t", "json", writer.register_schema("S", "jsonschema", b"{}"))
        for i in range(10):
            writer.add_message(channel, log_time=i, data=b"{}", publish_time=i)
        writer.finish()
    data = bytearray(path.read_bytes())
    summary_start = int.from_bytes(data[-8 - 20 : -8 - 12], "little")
    assert data[summary_start] == 0x03  # the summary starts with the Schema: id, name, encoding, then the data's length
    length_at = summary_start + 9 + 2 + 4 + 1 + 4 + len("jsonschema")
    data[length_at : length_at + 4] = (2**30).to_bytes(4, "little")  # a uint32 length field: at most 4 GiB
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=rf"^{path}: corrupt at offset {summary_start}: the summary cannot be read \(EndOfFile"):
        Recording(path)
    with Recording(path, recover=True) as recording:
        assert not recording.info.indexed and [m.log_time_ns for m in recording.messages()] == list(range(10))
