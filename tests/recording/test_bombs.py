"""Decompression bombs (issue 38): every way of reading an MCAP file refuses them within its bounds.

The bombs are built here in a moment (:mod:`dyknow.testing.bombs` writes zstd RLE blocks and
copies of one lz4 block rather than compressing anything): chunks of a few KiB holding a GiB,
chunks whose declared size or frame header lies, overlapping chunks, floods of empty messages.
The commands run as real processes, and the peak memory of each is read from the kernel
(:func:`dyknow.testing.memory.peak_run`: ``ru_maxrss`` of that command alone, not of pytest): before these bounds the same commands peaked at 1.1
to 8.2 GiB on such files (``benchmarks/results/mcap_bombs.txt``), and some exited 0.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.records import Message as McapMessage

from dyknow.errors import RecordingError
from dyknow.recording import Player, ReadLimits, Recording
from dyknow.testing.bombs import BombChunk, lz4_zeros, write_bomb, zeros_message, zstd_empty_messages, zstd_zeros
from dyknow.testing.memory import peak_run
from tests.conftest import REPO, free_port, subprocess_env

GIB, MIB = 1 << 30, 1 << 20
HEAD = zeros_message(1, GIB - 62)  # a small message, then the header of one whose 1 GiB of zeros follow
RECOVER = "expected an intact MCAP file; replay the rest with recover=True (dyknow replay --recover)"
# What a refused command may peak at: the interpreter, numpy and Zenoh take about 90 MiB; the
# bombs would take 1 to 8 GiB.
SMALL_MIB = 256


def measured(*args: str, timeout_s: float = 120.0) -> tuple[int, str, float]:
    """Run ``dyknow ARGS``: its exit code, its stderr, and its peak resident memory in MiB."""
    with tempfile.TemporaryFile() as err:
        code, peak_mib = peak_run(
            [sys.executable, "-m", "dyknow.cli", *args], timeout_s=timeout_s, env=subprocess_env(), cwd=REPO, stderr=err
        )
        err.seek(0)
        return code, err.read().decode(), peak_mib


def refusal(code: int, stderr: str) -> str:
    """The one line of a refusal (exit code 1, no traceback)."""
    assert code == 1, stderr
    lines = [line for line in stderr.splitlines() if line]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def chunk_offsets(path: Path) -> list[int]:
    """The offsets of a file's Chunk records, walking its records."""
    data, pos, out = path.read_bytes(), 8, []
    while pos + 9 <= len(data) - 8:
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if opcode == 0x06:
            out.append(pos)
        pos += 9 + length
    return out


@pytest.fixture
def command() -> Callable[[str, Path], list[str]]:
    """The arguments of each command that reads a file, by name (replay: to a port nobody listens on)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"

    def args(name: str, path: Path) -> list[str]:
        return {
            "replay": ["replay", str(path), "--rate", "max", "--wait", "0", "--connect", endpoint],
            "replay --recover": ["replay", str(path), "--rate", "max", "--wait", "0", "--connect", endpoint, "--recover"],
            "mcap cat": ["mcap", "cat", str(path)],
            "mcap info": ["mcap", "info", str(path)],
            "monitor --mcap": ["monitor", "Battery(robot).value > 0.2", "--mcap", str(path), "--bind", "Battery(robot)=/bomb"],
        }[name]

    return args


# --- a chunk declaring more than the bound ----------------------------------------------------------


@pytest.mark.process
@pytest.mark.parametrize(
    ("name", "summary"),
    [("replay", True), ("replay --recover", True), ("mcap cat", True), ("mcap info", False), ("monitor --mcap", True), ("replay", False)],
    ids=["replay", "replay --recover", "mcap cat", "mcap info (scanned)", "monitor --mcap", "replay (scanned)"],
)
def test_a_chunk_declaring_a_gib_is_refused_before_it_is_read(
    tmp_path: Path, command: Callable[[str, Path], list[str]], name: str, summary: bool
) -> None:
    """33 KB of zstd holding 1 GiB, declared honestly: a reader trusting the declared size (the
    bound was 4 GiB) decompressed it all, and copied the message out: 2.2 GiB, exit 0."""
    path = write_bomb(tmp_path / "zstd-1g.mcap", [BombChunk(zstd_zeros(HEAD, GIB - len(HEAD), GIB), "zstd", GIB)], summary=summary)
    assert path.stat().st_size < 40_000
    code, stderr, peak = measured(*command(name, path))
    (offset,) = chunk_offsets(path)
    assert refusal(code, stderr) == (
        f"dyknow: error: {path}: the chunk at offset {offset} declares 1073741824 bytes (1 GiB) uncompressed, more than the bound "
        "of 268435456 bytes (256 MiB) per chunk; expected at most 268435456 bytes (256 MiB) per chunk; if you trust the file, "
        "raise the bound (--max-chunk-bytes N, or ReadLimits(max_chunk_bytes=N))"
    )
    assert peak < SMALL_MIB


@pytest.mark.process
def test_the_bound_on_a_chunk_is_an_option(tmp_path: Path) -> None:
    size = 16 * MIB
    path = write_bomb(tmp_path / "16m.mcap", [BombChunk(zstd_zeros(zeros_message(1, size - 62), size - 62, size), "zstd", size)])
    code, stderr, _ = measured("mcap", "cat", str(path), "--max-chunk-bytes", str(size - 1))
    assert "declares 16777216 bytes (16 MiB) uncompressed, more than the bound of 16777215 bytes" in refusal(code, stderr)
    result = subprocess.run(
        [sys.executable, "-m", "dyknow.cli", "mcap", "cat", str(path)], capture_output=True, text=True, env=subprocess_env(), cwd=REPO
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [
        "0 /bomb #0 [application/octet-stream] <0 bytes>",
        "10 /bomb #1 [application/octet-stream] <16777154 bytes>",
    ]


# --- chunks whose sizes lie ----------------------------------------------------------------------------


@pytest.mark.process
@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_frame_stating_another_size_than_its_chunk_is_refused_unread(
    tmp_path: Path, command: Callable[[str, Path], list[str]], compression: str
) -> None:
    """The chunk declares 8 MiB, its frame's own header states 1 GiB (and holds it): zstandard
    allocated what the frame states (1.1 GiB), lz4 decompressed it all before the sizes were
    compared (2.1 GiB)."""
    frame = (zstd_zeros if compression == "zstd" else lz4_zeros)(HEAD, GIB - len(HEAD), GIB)
    path = write_bomb(tmp_path / f"{compression}-lies.mcap", [BombChunk(frame, compression, 8 * MIB)])
    code, stderr, peak = measured(*command("replay", path))
    (offset,) = chunk_offsets(path)
    assert refusal(code, stderr) == (
        f"dyknow: error: {path}: corrupt at offset {offset}: the chunk's {compression} frame says it holds 1073741824 bytes; "
        f"the chunk's header declares 8388608; {RECOVER}"
    )
    assert peak < SMALL_MIB


@pytest.mark.process
@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_decompression_stops_one_byte_past_the_declared_size(
    tmp_path: Path, command: Callable[[str, Path], list[str]], compression: str
) -> None:
    """The chunk declares 8 MiB and holds 1 GiB, its frame stating no size: lz4 decompressed the
    GiB before comparing (2.1 GiB); now both stop at the 8 MiB and one byte."""
    frame = (zstd_zeros if compression == "zstd" else lz4_zeros)(HEAD, GIB - len(HEAD), None)
    path = write_bomb(tmp_path / f"{compression}-1g.mcap", [BombChunk(frame, compression, 8 * MIB)], summary=False)
    (offset,) = chunk_offsets(path)
    for name in ("replay", "mcap info"):
        code, stderr, peak = measured(*command(name, path))
        assert refusal(code, stderr) == (
            f"dyknow: error: {path}: corrupt at offset {offset}: the {compression} chunk decompresses to more than the 8388608 bytes "
            "its header declares (stopped at 8388609); expected an intact MCAP file; no message before it is readable"
        )
        assert peak < SMALL_MIB
    with pytest.raises(RecordingError, match="decompresses to more than the 8388608 bytes its header declares"):
        Recording(path)
    with Recording(path, recover=True) as recording:  # damage, not a bound: recovering skips the chunk
        assert list(recording.messages()) == [] and "stopped at 8388609" in str(recording.problem)


# --- what a reading pass holds at once -----------------------------------------------------------------


def overlapping(folder: Path, chunks: int, size: int, summary: bool = True) -> Path:
    """``chunks`` zstd chunks of ``size`` bytes each, all from log time 0 to 10: a small message
    at 0, one of ``size - 62`` zeros at 10. Merging them in log-time order holds them all."""
    chunk = BombChunk(zstd_zeros(zeros_message(1, size - 62), size - 62, size), "zstd", size)
    return write_bomb(folder / f"overlapping-{chunks}.mcap", [chunk] * chunks, summary=summary)


@pytest.mark.process
@pytest.mark.parametrize("name", ["replay", "mcap cat"])
def test_overlapping_chunks_are_bounded_together(tmp_path: Path, command: Callable[[str, Path], list[str]], name: str) -> None:
    """16 chunks of 64 MiB overlapping in time: a replay held them all (1 GiB; 3.5 GiB for 16 of
    200 MiB) and exited 0. With a bound of 256 MiB, the chunk that would go over is named."""
    path = overlapping(tmp_path, 16, 64 * MIB)
    code, stderr, peak = measured(*command(name, path), "--max-memory-bytes", str(256 * MIB))
    offsets = chunk_offsets(path)
    line = refusal(code, stderr)
    # two are held; the third would hold its data and the message copied out of it too
    assert line.startswith(f"dyknow: error: {path}: reading the chunk at offset {offsets[2]} would hold ")
    assert line.endswith(
        "more than the bound of 268435456 bytes (256 MiB); expected at most 268435456 bytes (256 MiB) held at once; "
        "if you trust the file, raise the bound (--max-memory-bytes N, or ReadLimits(max_memory_bytes=N))"
    )
    assert "the messages of chunks whose time ranges overlap" in line
    assert peak < 256 + SMALL_MIB


@pytest.mark.process
@pytest.mark.parametrize(("name", "summary"), [("mcap cat", True), ("mcap info", False)], ids=["mcap cat", "mcap info (scanned)"])
def test_a_flood_of_empty_messages_counts_against_the_bound(
    tmp_path: Path, command: Callable[[str, Path], list[str]], name: str, summary: bool
) -> None:
    """32 MiB of empty messages (1.1 million, 31 bytes each) in 3 KiB of zstd take some 300 bytes
    of Python objects each once read: each counts as 384 bytes against the bound."""
    count = (32 * MIB) // 31
    path = write_bomb(tmp_path / "empty.mcap", [BombChunk(zstd_empty_messages(count), "zstd", count * 31)], summary=summary)
    code, stderr, peak = measured(*command(name, path), "--max-memory-bytes", str(128 * MIB))
    (offset,) = chunk_offsets(path)
    assert refusal(code, stderr).startswith(f"dyknow: error: {path}: reading the chunk at offset {offset} would hold ")
    assert peak < 128 + SMALL_MIB


def test_a_bound_is_no_damage_and_recovering_does_not_skip_it(tmp_path: Path) -> None:
    path = overlapping(tmp_path, 4, MIB)
    for recover in (False, True):
        with Recording(path, recover=recover, limits=ReadLimits(max_memory_bytes=3 * MIB)) as recording:
            with pytest.raises(RecordingError, match=r"reading the chunk at offset \d+ would hold .* more than the bound of 3145728 bytes"):
                list(recording.messages())
    with Player(path, limits=ReadLimits(max_memory_bytes=3 * MIB), rate=float("inf")) as player, pytest.raises(RecordingError):
        player.play(lambda msg, record: None)
    with Recording(path, limits=ReadLimits(max_memory_bytes=8 * MIB)) as recording:  # room for all four
        assert [(m.log_time_ns, len(m.data)) for m in recording.messages()] == [(0, 0)] * 4 + [(10, MIB - 62)] * 4


@pytest.mark.parametrize("summary", [True, False], ids=["indexed", "scanned"])
def test_chunks_read_one_after_another_give_back_what_they_held(tmp_path: Path, summary: bool) -> None:
    """20 chunks of 1 MiB in turn, with room for 3 MiB: each chunk's messages are let go before
    the next is read, in every reading pass, so the bound is never reached."""
    chunks = [
        BombChunk(zstd_zeros(zeros_message(1, MIB - 62, 10 * i + 5, 10 * i), MIB - 62, MIB), "zstd", MIB, 10 * i, 10 * i + 5)
        for i in range(20)
    ]
    path = write_bomb(tmp_path / "sequential.mcap", chunks, summary=summary)
    limits = ReadLimits(max_chunk_bytes=MIB, max_memory_bytes=3 * MIB)
    with Recording(path, limits=limits) as recording:
        assert [m.log_time_ns for m in recording.messages()] == [t for i in range(20) for t in (10 * i, 10 * i + 5)]
        assert sum(isinstance(r, McapMessage) for r in recording.records()) == 40
    with pytest.raises(RecordingError, match="per chunk"):  # on opening when the file is scanned, else when read
        with Recording(path, limits=ReadLimits(max_chunk_bytes=MIB - 1)) as recording:
            list(recording.messages())


def test_read_limits_are_positive_whole_numbers() -> None:
    assert ReadLimits() == ReadLimits(max_chunk_bytes=256 * MIB, max_memory_bytes=GIB)
    for bad in (0, -1, 1.5, True, "1"):
        with pytest.raises(RecordingError, match=f"max_chunk_bytes: got {bad!r}; expected a positive whole number of bytes"):
            ReadLimits(max_chunk_bytes=bad)  # type: ignore[arg-type]
