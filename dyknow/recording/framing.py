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

A chunk is a decompression bomb waiting to go off: 33 KB of zstd data declare and hold 1 GiB of
zeros, and the libraries trust it. ``zstandard``'s ``decompress`` allocates whatever size the
frame's own header states, ``lz4.frame.decompress`` has no bound at all (its output was checked
against the chunk's header only afterwards), and a reader merging chunks whose time ranges
overlap holds all of them at once. So what one reading pass may hold is bounded
(:class:`ReadLimits`, counted by a :class:`Budget`): a chunk declaring more than
``max_chunk_bytes`` uncompressed is refused before any of its data is read; a chunk is
decompressed as a stream (:func:`unpack_chunk`), never past the size its header declares (one
byte more and it is refused); a frame whose own header states another size is refused unread;
and the chunk being read plus the messages waiting in the merge, each counted with
:data:`RECORD_COST` bytes of Python objects, may not exceed ``max_memory_bytes``. Going over a
limit raises :class:`~dyknow.errors.RecordingError` naming the file, the chunk's offset, the
sizes and the option that raises the bound; a chunk whose sizes lie is :class:`Damage`.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import threading
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
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
_PIECE = 1 << 20  # a chunk is decompressed this many bytes at a time
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

#: What each record split from a chunk costs in memory beyond its data, as a :class:`Budget`
#: counts it: a message is a tuple of five, three large integers, a bytes object and an entry of
#: the reader's merge heap, measured at 296 bytes with ``tracemalloc`` (a parsed Channel record:
#: 184), rounded up.
RECORD_COST = 384

#: What a Channel record may cost in memory per byte of it, before it is parsed: a metadata
#: entry takes 8 bytes of the record at least, and a dict slot and two strings (:func:`cost`
#: counts ``RECORD_COST // 2``).
_METADATA_FACTOR = 32


@dataclass(frozen=True, slots=True)
class ReadLimits:
    """What reading an MCAP file may hold in memory; a file over a limit is refused, not read.

    ``max_chunk_bytes``: the largest uncompressed size a chunk may declare (default 256 MiB;
    writers make chunks of 1 to 4 MiB, and a chunk holds one raw 4K image at least). A larger one
    is refused before any of its data is read.

    ``max_memory_bytes``: the most one reading pass (a replay, ``mcap cat``, the scan of a file
    without a summary) holds at once (default 1 GiB): the chunk being decompressed, its
    compressed data, and the messages of the chunks whose time ranges overlap, which wait in the
    log-time merge together, each message counted as its data and 384 bytes of Python objects.

    ``dyknow replay``, ``mcap cat``, ``mcap info`` and ``monitor --mcap`` set them with
    ``--max-chunk-bytes`` and ``--max-memory-bytes``. Going over one raises
    :class:`~dyknow.RecordingError` naming the file, the chunk's offset, the sizes and the option,
    with ``recover`` too. Raises :class:`~dyknow.RecordingError` for a limit that is not a
    positive whole number.

    >>> ReadLimits(max_memory_bytes=256 << 20)
    ReadLimits(max_chunk_bytes=268435456, max_memory_bytes=268435456)
    """

    max_chunk_bytes: int = 256 << 20
    max_memory_bytes: int = 1 << 30

    def __post_init__(self) -> None:
        for name in ("max_chunk_bytes", "max_memory_bytes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise RecordingError(f"got {value!r}", where=name, expected="a positive whole number of bytes")


def _size(n: int) -> str:
    """``n`` bytes for a reader: ``268435456 bytes (256 MiB)``."""
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if n >= 1 << shift:
            return f"{n} bytes ({n / (1 << shift):.4g} {unit})"
    return f"{n} bytes"


class Budget:
    """The memory one reading pass of ``path`` holds, counted against ``limits``.

    :meth:`chunk` reserves room for decompressing a chunk, :func:`split_chunk` charges each
    record it makes (:func:`cost`), and :meth:`give` gives back what was let go. ``held``
    starts at what the reader keeps for good (Schema and Channel records learnt from chunks).
    Going over a limit raises :class:`RecordingError`: the file is not damaged, only larger
    than allowed, so reading with ``recover`` refuses it too.
    """

    def __init__(self, path: str, limits: ReadLimits, held: int = 0) -> None:
        self.path = path
        self.limits = limits
        self.held = held

    def chunk(self, offset: int, compression: str, size: int, packed: int) -> int:
        """Reserve room to decompress the chunk at ``offset``: ``size`` bytes uncompressed, held
        as ``packed`` bytes of ``compression`` data. Returns the bytes reserved, to :meth:`give`
        back once its records are split."""
        bound = self.limits.max_chunk_bytes
        if size > bound:
            raise RecordingError(
                f"the chunk at offset {offset} declares {_size(size)} uncompressed, more than the bound of {_size(bound)} per chunk",
                where=self.path,
                expected=f"at most {_size(bound)} per chunk; if you trust the file, raise the bound "
                "(--max-chunk-bytes N, or ReadLimits(max_chunk_bytes=N))",
            )
        need = size + packed if compression else size  # uncompressed, the data is the chunk's own
        self.take(offset, need)
        return need

    def take(self, offset: int, n: int) -> None:
        """Charge ``n`` bytes for the chunk at ``offset``; raises when over ``max_memory_bytes``."""
        if self.held + n > self.limits.max_memory_bytes:
            raise self.over(offset, n)
        self.held += n

    def room(self) -> int:
        """How many more bytes may be held."""
        return self.limits.max_memory_bytes - self.held

    def over(self, offset: int, n: int) -> RecordingError:
        """The error for holding ``n`` more bytes, for the chunk at ``offset``, when too few are left."""
        bound = self.limits.max_memory_bytes
        already = ""
        if self.held:
            already = (
                f", with {_size(self.held)} held already (the chunk's data, and the messages of chunks whose time ranges overlap, "
                "which wait together for their turn)"
            )
        return RecordingError(
            f"reading the chunk at offset {offset} would hold {_size(self.held + n)} at once{already}: more than the bound of {_size(bound)}",
            where=self.path,
            expected=f"at most {_size(bound)} held at once; if you trust the file, raise the bound "
            "(--max-memory-bytes N, or ReadLimits(max_memory_bytes=N))",
        )

    def give(self, n: int) -> None:
        """Give back ``n`` bytes that are no longer held."""
        self.held -= n


def cost(record: Any) -> int:
    """What a record from :func:`split_chunk` holds in memory, as a :class:`Budget` counts it."""
    if isinstance(record, tuple):
        return len(record[4]) + RECORD_COST
    if isinstance(record, Schema):
        return RECORD_COST + len(record.name) + len(record.encoding) + len(record.data)
    metadata = sum(len(k) + len(v) + RECORD_COST // 2 for k, v in record.metadata.items())
    return RECORD_COST + len(record.topic) + len(record.message_encoding) + metadata


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

    def chunk(self, offset: int, budget: Budget, record: Chunk | None = None) -> tuple[str, list[Any]]:
        """The compression (``none`` for none) and the records (:func:`split_chunk`) of the chunk
        at ``offset`` (``record`` when it was read already), its data decompressed and checked
        within ``budget``: what the records :func:`cost` stays charged to it (the caller gives it
        back as it lets them go). The chunk's declared size is checked before its data is read."""
        if record is None:
            chunk, start, length = self._chunk_head(offset)
        else:
            chunk, start, length = record, -1, len(record.data)
            if chunk.compression not in _DECOMPRESSORS:
                raise Damage(offset, f"unknown chunk compression {chunk.compression!r}; expected zstd, lz4 or none", fatal=False)
        compression, size = chunk.compression, chunk.uncompressed_size
        reserved = budget.chunk(offset, compression, size, length)
        try:
            data = chunk.data if record is not None else self.read(start, length, "a Chunk record")
            raw = unpack_chunk(offset, compression, data, size, chunk.uncompressed_crc)
            del data
            return compression or "none", split_chunk(offset, raw, budget)
        finally:
            budget.give(reserved)

    def chunk_record(self, offset: int) -> Chunk:
        """The Chunk record at ``offset``, its data still compressed."""
        chunk, start, length = self._chunk_head(offset)
        chunk.data = self.read(start, length, "a Chunk record")
        return chunk

    def _chunk_head(self, offset: int) -> tuple[Chunk, int, int]:
        """The Chunk record at ``offset`` without its data, the data's offset and its length,
        checked against the chunk's declared size: nothing of the data is read."""
        opcode, length = self.record_at(offset, self.size)
        if opcode != Opcode.CHUNK:
            raise Damage(offset, f"expected a Chunk record, found a {record_name(opcode)} record", fatal=False)
        start = offset + RECORD.size
        try:
            first, last, size, crc, name_length = _CHUNK.unpack(self.read(start, min(length, _CHUNK.size), "a Chunk record"))
            if _CHUNK.size + name_length + 8 > length:
                raise Damage(
                    offset,
                    f"malformed Chunk record header (a compression name of {name_length} bytes in a record of {length})",
                    fatal=False,
                )
            head = self.read(start + _CHUNK.size, name_length + 8, "a Chunk record")
            compression = head[:name_length].decode()
            (data_length,) = struct.unpack_from("<Q", head, name_length)
        except (struct.error, UnicodeDecodeError) as exc:
            raise Damage(offset, f"malformed Chunk record header ({exc})", fatal=False) from exc
        start += _CHUNK.size + name_length + 8
        left = offset + RECORD.size + length - start
        if data_length > left:
            raise Damage(offset, f"the Chunk record holds {left} bytes of data; its header says {data_length}", fatal=False)
        if compression not in _DECOMPRESSORS:
            raise Damage(offset, f"unknown chunk compression {compression!r}; expected zstd, lz4 or none", fatal=False)
        if compression == "" and data_length != size:
            raise Damage(offset, f"the uncompressed chunk holds {data_length} bytes; its header says {size}", fatal=False)
        if data_length > size + size // 128 + 4096:  # more than zstd or lz4 makes of any data of that size
            raise Damage(
                offset,
                f"the chunk holds {data_length} bytes of {compression} data, too many for the {size} bytes its header declares",
                fatal=False,
            )
        chunk = Chunk(
            compression=compression, data=b"", message_start_time=first, message_end_time=last, uncompressed_crc=crc, uncompressed_size=size
        )
        return chunk, start, data_length


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


def unpack_chunk(offset: int, compression: str, data: bytes | memoryview, size: int, crc: int) -> bytes | bytearray | memoryview:
    """A chunk's ``data`` uncompressed (``compression``; ``size`` bytes uncompressed with CRC32
    ``crc``, or 0 for none), checked. ``offset`` is the chunk's, for :class:`Damage`.

    Decompression is a stream that stops one byte past ``size``: however much the data would
    expand to, no more than ``size + 1`` bytes of it are ever made. The caller bounds ``size``
    first (:meth:`Budget.chunk`)."""
    decompress = _DECOMPRESSORS.get(compression)
    if decompress is None:
        raise Damage(offset, f"unknown chunk compression {compression!r}; expected zstd, lz4 or none", fatal=False)
    try:
        raw = decompress(offset, data, size)
    except Damage:
        raise
    except Exception as exc:  # zstandard and lz4 raise their own (and RuntimeError)
        raise Damage(offset, f"cannot decompress the {compression} chunk ({type(exc).__name__}: {exc})", fatal=False) from exc
    if len(raw) > size:
        raise Damage(
            offset,
            f"the {compression} chunk decompresses to more than the {size} bytes its header declares (stopped at {len(raw)})",
            fatal=False,
        )
    if len(raw) != size:
        raise Damage(offset, f"the chunk decompressed to {len(raw)} bytes; its header says {size}", fatal=False)
    if crc and zlib.crc32(raw) != crc:
        raise Damage(offset, f"the chunk's CRC does not match its data (CRC32 {zlib.crc32(raw)}; expected {crc})", fatal=False)
    return raw


def split_chunk(offset: int, data: bytes | bytearray | memoryview, budget: Budget) -> list[Any]:
    """The records of a chunk's uncompressed ``data``, checked: Schema, Channel and
    :data:`MessageTuple`, in order (others are left out). ``offset`` is the chunk's, for :class:`Damage`.

    What each record :func:`cost` is charged to ``budget`` as it is made (the caller gives it
    back), and the chunk is refused once they would hold more than its room."""
    raw = memoryview(data)
    out: list[Any] = []
    pos, end = 0, len(raw)
    room = budget.room()
    spent = 0
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
            spent += length - MESSAGE.size + RECORD_COST
            if spent > room:
                raise budget.over(offset, spent)
            out.append((*MESSAGE.unpack_from(raw, pos + RECORD.size), bytes(raw[pos + RECORD.size + MESSAGE.size : stop])))
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            most = RECORD_COST + length * (_METADATA_FACTOR if opcode == Opcode.CHANNEL else 1)  # what parsing it may take
            if spent + most > room:
                raise budget.over(offset, spent + most)
            record = parse(opcode, raw[pos + RECORD.size : stop], offset)
            spent += cost(record)
            if spent > room:
                raise budget.over(offset, spent)
            out.append(record)
        pos = stop
    budget.held += spent
    return out


def _zstd(offset: int, data: bytes | memoryview, size: int) -> bytearray:
    try:
        declared = zstandard.get_frame_parameters(data).content_size
    except zstandard.ZstdError as exc:
        raise Damage(offset, f"cannot decompress the zstd chunk (ZstdError: {exc})", fatal=False) from exc
    if declared != zstandard.CONTENTSIZE_UNKNOWN and declared != size:
        raise Damage(offset, f"the chunk's zstd frame says it holds {declared} bytes; the chunk's header declares {size}", fatal=False)
    out = bytearray()
    with zstandard.ZstdDecompressor().stream_reader(data) as reader:  # the first frame, as the mcap library reads it
        while len(out) <= size:
            piece = reader.read(min(_PIECE, size + 1 - len(out)))
            if not piece:
                break
            out += piece
    return out


def _lz4(offset: int, data: bytes | memoryview, size: int) -> bytearray:
    declared = lz4.frame.get_frame_info(data)["content_size"]  # 0: not stated
    if declared and declared != size:
        raise Damage(offset, f"the chunk's lz4 frame says it holds {declared} bytes; the chunk's header declares {size}", fatal=False)
    # The frame functions rather than LZ4FrameDecompressor, which copies the input left over at
    # every call (quadratic in pieces) and the whole output once more.
    context = lz4.frame.create_decompression_context()
    view = memoryview(data)
    out = bytearray()
    pos = 0
    while len(out) <= size:
        piece, used, end = lz4.frame.decompress_chunk(context, view[pos:], max_length=min(_PIECE, size + 1 - len(out)))
        pos += used
        out += piece
        if end or not (piece or used):
            break
    return out


def _none(offset: int, data: bytes | memoryview, size: int) -> bytes | memoryview:
    return data


_DECOMPRESSORS: dict[str, Any] = {"": _none, "zstd": _zstd, "lz4": _lz4}
