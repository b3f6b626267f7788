"""MCAP decompression bombs: small files that would take gigabytes to read, built in a moment.

For the tests that show a reader refuses them within its bounds
(:class:`~dyknow.recording.framing.ReadLimits`), and for measuring what reading them costs. Every
file is a valid MCAP file around its chunks (a channel ``/bomb``, a summary with chunk indexes
unless ``summary=False``); only the chunks are hostile:

- :func:`zstd_zeros` and :func:`lz4_zeros` make a frame of given bytes then a run of zeros,
  written block by block without compressing anything (a zstd RLE block is 4 bytes for 128 KiB;
  an lz4 block of 4 MiB of zeros, compressed once, is repeated), and state in the frame's header
  whatever content size they are told to (or none);
- :func:`zeros_message` is the uncompressed start of a chunk: small messages, then the header of
  a message whose data is the zeros that follow;
- :func:`zstd_empty_messages` compresses a run of empty messages (31 bytes each in the file,
  some 300 bytes each once read: a bomb of Python objects rather than of bytes);
- :func:`write_bomb` writes the file, each :class:`BombChunk` declaring the uncompressed size it
  is told to, true or not.

The bombs of issue 38 (:func:`write_bombs`)::

    from dyknow.testing.bombs import write_bombs
    paths = write_bombs("out/")   # name -> path
"""

from __future__ import annotations

import io
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import lz4.block
import lz4.frame
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Statistics

__all__ = ["BombChunk", "lz4_zeros", "write_bomb", "write_bombs", "zeros_message", "zstd_empty_messages", "zstd_zeros"]

MAGIC = b"\x89MCAP0\r\n"
_MESSAGE = struct.Struct("<BQHIQQ")  # opcode, length, channel id, sequence, log time, publish time
_ZSTD_BLOCK = 128 << 10  # the largest zstd block
_LZ4_BLOCK = 4 << 20  # the largest lz4 block
_LZ4_ZEROS = lz4.block.compress(bytes(_LZ4_BLOCK), store_size=False)  # about 16 KiB


@dataclass(frozen=True, slots=True)
class BombChunk:
    """One chunk of a bomb: its compressed ``data``, its ``compression`` (``zstd``, ``lz4`` or
    ``""``), the uncompressed size it declares, and the log times its index states."""

    data: bytes
    compression: str
    declared_size: int
    start_ns: int = 0
    end_ns: int = 10


def zeros_message(small: int, zeros: int, log_time_ns: int = 10, start_ns: int = 0) -> bytes:
    """The start of a chunk's uncompressed data: ``small`` empty messages (log times
    ``start_ns`` on) on channel 1, then the header of a message at ``log_time_ns`` whose
    ``zeros`` bytes of data are to follow."""
    head = b"".join(_MESSAGE.pack(5, 22, 1, i, start_ns + i, start_ns + i) for i in range(small))
    return head + _MESSAGE.pack(5, 22 + zeros, 1, small, log_time_ns, log_time_ns)


def zstd_zeros(data: bytes, zeros: int, stated: int | None) -> bytes:
    """A zstd frame of ``data`` then ``zeros`` zero bytes, its header stating the content size
    ``stated`` (None: not stated). ``data`` goes in raw blocks, the zeros in RLE blocks."""
    if stated is None:
        header = bytes([0x00, 0x38])  # no content size, not single-segment; a window of 128 KiB
    else:
        header = bytes([0xC0, 0x38]) + struct.pack("<Q", stated)  # an 8-byte content size
    blocks = []
    for at in range(0, len(data), _ZSTD_BLOCK):
        piece = data[at : at + _ZSTD_BLOCK]
        blocks.append((len(piece) << 3 | 0 << 1, piece))  # raw
    full, rest = divmod(zeros, _ZSTD_BLOCK)
    blocks += [(_ZSTD_BLOCK << 3 | 1 << 1, b"\0")] * full  # RLE: the byte, repeated block size times
    if rest:
        blocks.append((rest << 3 | 1 << 1, b"\0"))
    if not blocks:
        blocks.append((0, b""))
    last = len(blocks) - 1
    body = b"".join((head | (i == last)).to_bytes(3, "little") + piece for i, (head, piece) in enumerate(blocks))
    return struct.pack("<I", 0xFD2FB528) + header + body


def lz4_zeros(data: bytes, zeros: int, stated: int | None) -> bytes:
    """An lz4 frame of ``data`` (at most 4 MiB) then ``zeros`` zero bytes, its header stating the
    content size ``stated`` (None: not stated). ``data`` goes in an uncompressed block, the zeros
    in copies of one compressed block of 4 MiB (and one of the rest)."""
    compressor = lz4.frame.LZ4FrameCompressor(block_size=lz4.frame.BLOCKSIZE_MAX4MB, block_linked=False)
    header = compressor.begin(source_size=stated or 0)
    blocks = [struct.pack("<I", 0x80000000 | len(data)) + data] if data else []
    full, rest = divmod(zeros, _LZ4_BLOCK)
    zero_block = struct.pack("<I", len(_LZ4_ZEROS)) + _LZ4_ZEROS
    if rest:
        tail = lz4.block.compress(bytes(rest), store_size=False)
        blocks.append(struct.pack("<I", len(tail)) + tail)
    return header + b"".join(blocks) + zero_block * full + b"\0\0\0\0"


def zstd_empty_messages(count: int) -> bytes:
    """A zstd frame of ``count`` empty messages on channel 1 at log time 5 (31 bytes each), its
    content size stated."""
    record = _MESSAGE.pack(5, 22, 1, 0, 5, 5)
    out = io.BytesIO()
    full, rest = divmod(count, 1 << 15)
    with zstandard.ZstdCompressor(level=1).stream_writer(out, size=count * len(record), closefd=False) as writer:
        piece = record * (1 << 15)
        for _ in range(full):
            writer.write(piece)
        writer.write(record * rest)
    return out.getvalue()


def write_bomb(path: str | os.PathLike[str], chunks: Sequence[BombChunk], *, summary: bool = True) -> Path:
    """An MCAP file at ``path`` with channel 1 (``/bomb``, ``application/octet-stream``) and
    ``chunks`` as they are; with ``summary``, a summary whose chunk indexes and statistics say
    what the chunks declare (two messages each)."""
    out = RecordBuilder()
    Header(profile="", library="dyknow bombs").write(out)
    channel = Channel(id=1, schema_id=0, topic="/bomb", message_encoding="application/octet-stream", metadata={})
    channel.write(out)
    indexes = []
    for chunk in chunks:
        start = len(MAGIC) + out.count
        Chunk(
            compression=chunk.compression,
            data=chunk.data,
            message_start_time=chunk.start_ns,
            message_end_time=chunk.end_ns,
            uncompressed_crc=0,
            uncompressed_size=chunk.declared_size,
        ).write(out)
        indexes.append(
            ChunkIndex(
                message_start_time=chunk.start_ns,
                message_end_time=chunk.end_ns,
                chunk_start_offset=start,
                chunk_length=len(MAGIC) + out.count - start,
                message_index_offsets={},
                message_index_length=0,
                compression=chunk.compression,
                compressed_size=len(chunk.data),
                uncompressed_size=chunk.declared_size,
            )
        )
    DataEnd(data_section_crc=0).write(out)
    summary_start = 0
    if summary:
        summary_start = len(MAGIC) + out.count
        channel.write(out)
        count = 2 * len(chunks)
        Statistics(
            message_count=count,
            schema_count=0,
            channel_count=1,
            attachment_count=0,
            metadata_count=0,
            chunk_count=len(chunks),
            message_start_time=min((c.start_ns for c in chunks), default=0),
            message_end_time=max((c.end_ns for c in chunks), default=0),
            channel_message_counts={1: count},
        ).write(out)
        for index in indexes:
            index.write(out)
    Footer(summary_start=summary_start, summary_offset_start=0, summary_crc=0).write(out)
    target = Path(path)
    target.write_bytes(MAGIC + out.end() + MAGIC)
    return target


def write_bombs(folder: str | os.PathLike[str]) -> dict[str, Path]:
    """The bombs of issue 38, in ``folder``, by name:

    - ``zstd-1g``: a zstd chunk of 32 KiB declaring (and holding) 1 GiB;
    - ``zstd-4g``: one of 128 KiB declaring and holding 4 GiB less 1 KiB;
    - ``zstd-frame-lies``: a chunk declaring 1 MiB whose zstd frame states, and holds, 1 GiB;
    - ``zstd-1g-declares-1m``: a chunk declaring 1 MiB whose zstd frame holds 1 GiB, stating no size;
    - ``lz4-1g-declares-8m``: a chunk declaring 8 MiB that holds 1 GiB of lz4 (4.2 MiB), its
      frame stating no size;
    - ``overlapping-16x200m``: 16 zstd chunks of 200 MiB each, their time ranges overlapping, so
      that a reader merging them in log-time order holds them all;
    - ``empty-messages-256m``: a zstd chunk of 24 KiB declaring and holding 256 MiB of empty
      messages (8.7 million).
    """
    where = Path(folder)
    gib, mib = 1 << 30, 1 << 20
    head = zeros_message(1, gib - 62)  # 62: the two message headers
    four = (4 << 30) - 1024
    big = 200 << 20
    count = (256 << 20) // 31
    chunks = {
        "zstd-1g": BombChunk(zstd_zeros(head, gib - len(head), gib), "zstd", gib),
        "zstd-4g": BombChunk(zstd_zeros(zeros_message(1, four - 62), four - 62, four), "zstd", four),
        "zstd-frame-lies": BombChunk(zstd_zeros(head, gib - len(head), gib), "zstd", mib),
        "zstd-1g-declares-1m": BombChunk(zstd_zeros(head, gib - len(head), None), "zstd", mib),
        "lz4-1g-declares-8m": BombChunk(lz4_zeros(head, gib - len(head), None), "lz4", 8 * mib),
        "empty-messages-256m": BombChunk(zstd_empty_messages(count), "zstd", count * 31),
    }
    paths = {name: write_bomb(where / f"{name}.mcap", [chunk]) for name, chunk in chunks.items()}
    overlapping = BombChunk(zstd_zeros(zeros_message(1, big - 62), big - 62, big), "zstd", big)
    paths["overlapping-16x200m"] = write_bomb(where / "overlapping-16x200m.mcap", [overlapping] * 16)
    return paths
