"""MCAP records read from a file with every bound checked, and the :class:`Damage` found on the way.

The ``mcap`` library parses records (``mcap.records``) and this module uses its parsers, but the
library trusts the framing around them. ``ReadDataStream.read`` fails only when nothing at all is
left, so a record cut off inside a chunk is read short without a word, and one cut off by the end
of the file fails with a bare ``EndOfFile()``. A chunk with a compression it does not know is
taken as uncompressed, a chunk's sizes are not checked against its data, a corrupt length field
makes it allocate that many bytes before reading (a ``MemoryError``), and its errors say neither
where nor what (``EndOfFile()``, ``struct.error``). :class:`RecordFile` reads a record only after
checking that it lies within the file (or its chunk), and raises :class:`Damage` with the offset
and a sentence about what is wrong. Chunks are decompressed, checked and split here too, which is
also three times faster than ``mcap.stream_reader.breakup_chunk`` for small messages: a message
is one ``struct.unpack_from`` and one slice rather than a record object built field by field.
:class:`Clamped` is the file to lend the library's readers.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import threading
import zlib
from collections.abc import Iterator
from typing import Any, BinaryIO, cast

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.records import Message as McapMessage

from dyknow.errors import ClosedError, RecordingError

MAGIC = b"\x89MCAP0\r\n"
RECORD = struct.Struct("<BQ")  # opcode, content length
MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
FOOTER = struct.Struct("<QQI")  # summary start, summary offset start, summary CRC
FOOTER_SIZE = RECORD.size + FOOTER.size
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size, uncompressed CRC, compression length
_MAX_CHUNK = 4 * 2**30  # larger (uncompressed) chunks are taken for corruption
_NAMES = {op.value: "".join(part.title() for part in op.name.split("_")) for op in Opcode}
PARSERS: dict[int, Any] = {
    Opcode.ATTACHMENT: Attachment,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex,
    Opcode.CHANNEL: Channel,
    Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.DATA_END: DataEnd,
    Opcode.FOOTER: Footer,
    Opcode.HEADER: Header,
    Opcode.METADATA: Metadata,
    Opcode.METADATA_INDEX: MetadataIndex,
    Opcode.SCHEMA: Schema,
    Opcode.STATISTICS: Statistics,
    Opcode.SUMMARY_OFFSET: SummaryOffset,
}

#: What the mcap library's parsers raise on malformed bytes (``EndOfFile`` among the McapErrors).
LIBRARY_ERRORS = (McapError, struct.error, ValueError, OverflowError)

#: A message as read from a chunk: (channel id, sequence, log time, publish time, data).
MessageTuple = tuple[int, int, int, int, bytes]

UNCLOSED = "the file ends without a footer: it was not closed (was the recorder killed?)"


def record_name(opcode: int) -> str:
    """The record type's name (``ChunkIndex``), or says that the opcode is unknown."""
    return _NAMES.get(opcode, f"unknown (opcode 0x{opcode:02x})")


class Damage(Exception):
    """A problem at an offset of the file.

    ``fatal``: nothing after it can be read; ``truncated``: the file ends too early (rather than
    holding corrupt data).
    """

    def __init__(self, offset: int, reason: str, *, fatal: bool = True, truncated: bool = False) -> None:
        super().__init__(f"offset {offset}: {reason}")
        self.offset = offset
        self.reason = reason
        self.fatal = fatal
        self.truncated = truncated

    @property
    def kind(self) -> str:
        """``truncated`` or ``corrupt``."""
        return "truncated" if self.truncated else "corrupt"

    @property
    def problem(self) -> str:
        """``KIND at offset N: REASON``, the form every message about damage uses."""
        return f"{self.kind} at offset {self.offset}: {self.reason}"


class RecordFile:
    """An MCAP file opened for reading records at offsets, any thread. ``close()`` is safe twice.

    Raises :class:`RecordingError` when the file cannot be opened; reading after close raises
    :class:`ClosedError`.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._closed = False
        try:
            self._file = open(path, "rb")  # noqa: SIM115 (closed by close())
        except OSError as exc:
            raise RecordingError(f"cannot read the file: {exc.strerror or exc}", where=path) from exc
        try:
            self.size = os.fstat(self._file.fileno()).st_size
        except OSError as exc:
            self._file.close()
            raise RecordingError(f"cannot read the file: {exc.strerror or exc}", where=path) from exc

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    @contextlib.contextmanager
    def lend(self) -> Iterator[BinaryIO]:
        """The open file at offset 0, for one of the mcap library's readers; other reads wait."""
        with self._lock:
            if self._closed:
                raise ClosedError("the recording is closed; open it again", where=self.path)
            self._file.seek(0)
            yield cast(BinaryIO, Clamped(self._file, self.size))

    def close(self) -> None:
        """Close the file; waits for a read under way to finish."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._file.close()

    def read(self, offset: int, size: int, what: str) -> bytes:
        """``size`` bytes at ``offset``; :class:`Damage` (truncated) when the file ends before."""
        with self._lock:
            if self._closed:
                raise ClosedError("the recording is closed; open it again", where=self.path)
            self._file.seek(offset)
            data = self._file.read(size)
        if len(data) < size:
            raise Damage(offset, f"the file ends inside {what} ({len(data)} of {size} bytes)", truncated=True)
        return data

    def record_at(self, offset: int, limit: int) -> tuple[int, int]:
        """``(opcode, length)`` of the record at ``offset``, which must end by ``limit``."""
        if offset >= self.size:
            raise Damage(offset, UNCLOSED, truncated=True)
        if offset + RECORD.size > self.size:
            raise Damage(offset, f"the file ends inside a record header ({self.size - offset} of 9 bytes)", truncated=True)
        opcode, length = RECORD.unpack(self.read(offset, RECORD.size, "a record header"))
        if opcode == 0:
            raise Damage(offset, "invalid record opcode 0x00")
        if offset + RECORD.size + length > limit:
            if limit == self.size:
                raise Damage(
                    offset,
                    f"a {record_name(opcode)} record of {length} bytes runs past the end of the file ({limit} bytes)",
                    truncated=True,
                )
            raise Damage(offset, f"a {record_name(opcode)} record of {length} bytes runs past offset {limit}")
        return opcode, length

    def record(self, offset: int) -> Any:
        """The record at ``offset``, parsed from its content alone: a Chunk (see :meth:`chunk_record`),
        or a record of :data:`PARSERS` or a Message."""
        opcode, length = self.record_at(offset, self.size)
        if opcode == Opcode.CHUNK:
            return self.chunk_record(offset)
        return parse(opcode, self.read(offset + RECORD.size, length, f"a {record_name(opcode)} record"), offset)

    def chunk(self, offset: int) -> tuple[str, bytes | memoryview]:
        """The compression (``none`` for none) and the uncompressed, CRC-checked data of the chunk
        at ``offset`` (:func:`split_chunk` gives its records)."""
        chunk = self.chunk_record(offset)
        return chunk.compression or "none", unpack_chunk(
            offset, chunk.compression, chunk.data, chunk.uncompressed_size, chunk.uncompressed_crc
        )

    def chunk_record(self, offset: int) -> Chunk:
        """The Chunk record at ``offset``, its data still compressed."""
        opcode, length = self.record_at(offset, self.size)
        if opcode != Opcode.CHUNK:
            raise Damage(offset, f"expected a Chunk record, found a {record_name(opcode)} record", fatal=False)
        content = memoryview(self.read(offset + RECORD.size, length, "a Chunk record"))
        try:
            first, last, size, crc, name_length = _CHUNK.unpack_from(content)
            compression = bytes(content[_CHUNK.size : _CHUNK.size + name_length]).decode()
            (data_length,) = struct.unpack_from("<Q", content, _CHUNK.size + name_length)
        except (struct.error, UnicodeDecodeError) as exc:
            raise Damage(offset, f"malformed Chunk record header ({exc})", fatal=False) from exc
        start = _CHUNK.size + name_length + 8
        data = content[start : start + data_length]
        if len(data) != data_length:
            raise Damage(offset, f"the Chunk record holds {len(data)} bytes of data; its header says {data_length}", fatal=False)
        return Chunk(
            compression=compression,
            data=data,  # type: ignore[arg-type]  # a view of what was read: no copy
            message_start_time=first,
            message_end_time=last,
            uncompressed_crc=crc,
            uncompressed_size=size,
        )


class Clamped:
    """A file for the mcap library's readers whose reads never ask for more than the file holds.

    The library reads a length field's worth of bytes in one call, and Python allocates that
    much before reading: a corrupt length of 2**60 would be a ``MemoryError`` rather than a
    short read that the checks around the library report as damage.
    """

    def __init__(self, file: BinaryIO, size: int) -> None:
        self._file = file
        self._size = size

    def read(self, size: int = -1) -> bytes:
        """At most ``size`` bytes (all that is left if negative), never more than the file holds."""
        if size > 65536:  # the library reads field by field: only a large read needs the position
            size = min(size, max(0, self._size - self._file.tell()))
        return self._file.read(size)

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        """Move to ``offset`` (from ``whence``), as a file does."""
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        """The current offset."""
        return self._file.tell()

    def seekable(self) -> bool:
        """True: the library then reads the summary by seeking."""
        return True


def parse(opcode: int, content: bytes | memoryview, offset: int) -> Any:
    """A record's content as the mcap library's record object; :class:`Damage` if malformed."""
    try:
        if opcode == Opcode.MESSAGE:
            return McapMessage.read(ReadDataStream(io.BytesIO(content)), len(content))
        return PARSERS[opcode].read(ReadDataStream(io.BytesIO(content)))
    except LIBRARY_ERRORS as exc:
        raise Damage(offset, f"malformed {record_name(opcode)} record ({type(exc).__name__}: {exc})", fatal=False) from exc


def unpack_chunk(offset: int, compression: str, data: bytes | memoryview, size: int, crc: int) -> bytes | memoryview:
    """A chunk's ``data`` uncompressed (``compression``; ``size`` bytes uncompressed with CRC32
    ``crc``, or 0 for none), checked. ``offset`` is the chunk's, for :class:`Damage`."""
    raw = _decompress(offset, compression, data, size)
    if crc and zlib.crc32(raw) != crc:
        raise Damage(offset, f"the chunk's CRC does not match its data (CRC32 {zlib.crc32(raw)}; expected {crc})", fatal=False)
    return raw


def split_chunk(offset: int, data: bytes | memoryview) -> list[Any]:
    """The records of a chunk's uncompressed ``data``, checked: Schema, Channel and
    :data:`MessageTuple`, in order (others are left out). ``offset`` is the chunk's, for :class:`Damage`."""
    raw = memoryview(data)
    out: list[Any] = []
    pos, end = 0, len(raw)
    while pos < end:
        if pos + RECORD.size > end:
            raise Damage(offset, f"a record header at byte {pos} of the chunk's data is cut off", fatal=False)
        opcode, length = RECORD.unpack_from(raw, pos)
        stop = pos + RECORD.size + length
        if stop > end:
            raise Damage(offset, f"a {record_name(opcode)} record at byte {pos} of the chunk's data runs past its end", fatal=False)
        if opcode == Opcode.MESSAGE:
            if length < MESSAGE.size:
                raise Damage(offset, f"a Message record at byte {pos} of the chunk's data is too short ({length} bytes)", fatal=False)
            out.append((*MESSAGE.unpack_from(raw, pos + RECORD.size), bytes(raw[pos + RECORD.size + MESSAGE.size : stop])))
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            out.append(parse(opcode, raw[pos + RECORD.size : stop], offset))
        pos = stop
    return out


def _decompress(offset: int, compression: str, data: bytes | memoryview, size: int) -> bytes | memoryview:
    if size > _MAX_CHUNK:
        raise Damage(offset, f"the chunk claims {size} uncompressed bytes (corrupt?)", fatal=False)
    try:
        if compression == "":
            raw: bytes | memoryview = data
        elif compression == "zstd":
            raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        elif compression == "lz4":
            raw = lz4.frame.decompress(data)
        else:
            raise Damage(offset, f"unknown chunk compression {compression!r}; expected zstd, lz4 or none", fatal=False)
    except Damage:
        raise
    except Exception as exc:  # zstandard and lz4 raise their own (and RuntimeError)
        raise Damage(offset, f"cannot decompress the {compression} chunk ({type(exc).__name__}: {exc})", fatal=False) from exc
    if len(raw) != size:
        raise Damage(offset, f"the chunk decompressed to {len(raw)} bytes; its header says {size}", fatal=False)
    return raw
