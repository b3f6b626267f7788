"""The :class:`Recording`: an MCAP file read in log-time order, whoever wrote it.

A recording reads files from dyknow, Foxglove, rosbag2 and the MCAP libraries. It reads through
the summary and chunk indexes when the file has them. Otherwise, and for damaged files, it scans
the file from the start (:mod:`dyknow.recording.scan`). Messages come out in log-time order (ties
in file order), and only the chunks being merged are held in memory. A truncated or corrupt file
raises :class:`~dyknow.errors.RecordingError` naming the file and the offset of the damage. With
``recover=True`` the valid part is read instead, with a warning (:attr:`Recording.problem` says
what was skipped). What a reading pass holds in memory is bounded by its
:class:`~dyknow.recording.framing.ReadLimits`: a chunk over them is refused, ``recover`` or not
(the file is not damaged, only larger than allowed), and never decompressed past its declared size.

What the ``mcap`` library (1.6) does, and why the rest is ours. Each point was checked against
the library with truncated, corrupt and summary-less files:

- *The summary* is read by ``SeekingReader.get_summary()``. The library reads whatever 28 bytes
  end the file as the footer: a file cut short or without a footer (a recorder killed with
  SIGKILL) fails with ``EndOfFile()`` or "MESSAGE_INDEX record has length 4397202086173868032
  that exceeds limit", and it never checks the closing magic or the summary's CRC. So the footer,
  the closing magic and the CRC are checked here first (and, for a summary without a CRC, that
  its records fit in it), and a library error becomes damage at the summary's offset, naming the
  record at fault when a record-by-record check finds it.
- *Messages* are not read with ``iter_messages(log_time_order=True)``. It reads the summary
  first, so it fails on every file without a footer instead of reading it linearly; it stops at
  the first damaged chunk (a generator that raised cannot go on, so ``recover`` could not skip
  the chunk); it reads a chunk with an unknown compression as uncompressed, and a record running
  past the end of its chunk short; its errors name no offset (``ZstdError``, ``KeyError`` for a
  message on a channel it has not seen); and its queue of ``_Orderable`` objects makes it four
  times slower for small messages (200,000 JSON messages: 1.6 s against 0.4 s here). Chunks are
  therefore located by the summary's chunk indexes or by a scan, read and checked by
  :mod:`~dyknow.recording.framing`, and merged here with a heap of tuples, in the library's very
  order (log time, then chunk offset, then position in the chunk).
- *Records* (:meth:`Recording.records`, the conformance suite's streamed reader) come from
  ``StreamReader``, which parses each record, skips unknown ones and reads padding. It is given a
  file whose reads never ask for more than the file holds (a corrupt length field would otherwise
  make it allocate that much first), each record's framing is checked before it reads it, a
  record it fails on or reads past is read from its own bytes instead (and the library restarts
  after it), chunks are decompressed and checked here, and the footer must be followed by the
  magic and nothing else.
"""

from __future__ import annotations

import base64
import logging
import os
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from heapq import heapify, heappop, heappush
from types import MappingProxyType
from typing import Any, BinaryIO, cast

from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Chunk, Footer, Header, McapRecord
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader

from dyknow.errors import ClosedError, RecordingError
from dyknow.recording.framing import (
    FOOTER,
    FOOTER_SIZE,
    LIBRARY_ERRORS,
    MAGIC,
    MESSAGE,
    PARSERS,
    RECORD,
    RECORD_COST,
    UNCLOSED,
    Budget,
    Clamped,
    Damage,
    ReadLimits,
    RecordFile,
    cost,
    parse,
    record_name,
)
from dyknow.recording.scan import Index, Loose, scan

__all__ = ["ChannelInfo", "ReadLimits", "RecordedMessage", "Recording", "RecordingInfo"]

log = logging.getLogger(__name__)

_RECOVER = "replay them with recover=True (dyknow replay --recover)"


@dataclass(frozen=True, slots=True)
class ChannelInfo:
    """One channel of a recording: its topic, encodings and schema, and how many messages it has."""

    id: int
    topic: str
    message_encoding: str
    schema_id: int
    schema_name: str
    schema_encoding: str
    schema_data: bytes = field(repr=False)
    metadata: Mapping[str, str] = field(hash=False)
    message_count: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (``dyknow mcap info --json``), schema data left out."""
        return {
            "id": self.id,
            "topic": self.topic,
            "message_encoding": self.message_encoding,
            "schema": self.schema_name,
            "schema_encoding": self.schema_encoding,
            "metadata": dict(self.metadata),
            "message_count": self.message_count,
        }


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One message as stored in a recording: its channel, header fields and data bytes."""

    channel: ChannelInfo
    sequence: int
    log_time_ns: int
    publish_time_ns: int
    data: bytes = field(repr=False)

    @property
    def topic(self) -> str:
        """The channel's topic, as written in the file."""
        return self.channel.topic

    def to_dict(self) -> dict[str, Any]:
        """The ``dyknow mcap cat --json`` form: data in base64."""
        return {
            "topic": self.channel.topic,
            "sequence": self.sequence,
            "log_time": self.log_time_ns,
            "publish_time": self.publish_time_ns,
            "schema": self.channel.schema_name,
            "message_encoding": self.channel.message_encoding,
            "data_b64": base64.b64encode(self.data).decode(),
        }


@dataclass(frozen=True, slots=True)
class RecordingInfo:
    """A summary of a recording: channels, counts, time range, chunks, and any damage found."""

    path: str
    size: int
    profile: str
    library: str
    message_count: int
    start_ns: int | None
    end_ns: int | None
    channels: tuple[ChannelInfo, ...]
    chunk_count: int
    compressions: tuple[str, ...]
    attachment_count: int
    metadata_count: int
    indexed: bool
    problem: str | None

    @property
    def duration_s(self) -> float:
        """Seconds from the first to the last log time (0 without messages)."""
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (``dyknow mcap info --json``)."""
        return {
            "path": self.path,
            "size": self.size,
            "profile": self.profile,
            "library": self.library,
            "message_count": self.message_count,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": self.duration_s,
            "channels": [c.to_dict() for c in self.channels],
            "chunk_count": self.chunk_count,
            "compressions": list(self.compressions),
            "attachment_count": self.attachment_count,
            "metadata_count": self.metadata_count,
            "indexed": self.indexed,
            "problem": self.problem,
        }


class Recording:
    """An MCAP file opened for reading. A context manager; ``close()`` is safe twice.

    Opening reads the summary, or scans the file when it has none. A truncated or corrupt file
    raises :class:`RecordingError` naming the file and offset. With ``recover=True`` the valid
    part is read instead, :attr:`problem` says what is wrong, and a warning is logged.
    ``limits`` bound what each reading pass (the scan, :meth:`messages`, :meth:`records`) holds
    in memory (:class:`ReadLimits`; a chunk over them raises :class:`RecordingError`, with
    ``recover`` too).
    """

    def __init__(self, path: str | os.PathLike[str], *, recover: bool = False, limits: ReadLimits | None = None) -> None:
        self.path = os.fspath(path)
        self.recover = recover
        self.limits = ReadLimits() if limits is None else limits
        self.problem: str | None = None
        self._kept = 0  # what the Schema and Channel records learnt from chunks hold (in every pass's budget)
        self._index = Index()
        self._indexed = False
        self._header = Header(profile="", library="")
        self._infos: dict[int, ChannelInfo] = {}
        self._file = RecordFile(self.path)
        try:
            self._open()
        except BaseException:
            self._file.close()
            raise

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Recording({self.path!r}, {sum(self._index.counts.values())} messages)"

    def close(self) -> None:
        """Close the file; safe to call twice. Waits for a chunk being read to finish."""
        self._file.close()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._file.closed

    # ------------------------------------------------------------------ opening

    def _open(self) -> None:
        file = self._file
        if file.size == 0:
            raise RecordingError("the file is empty (0 bytes)", where=self.path, expected="an MCAP file")
        head = file.read(0, min(len(MAGIC), file.size), "the MCAP magic")
        if head != MAGIC:
            if MAGIC.startswith(head):
                raise RecordingError("truncated at offset 0: the file ends inside the MCAP magic; nothing is readable", where=self.path)
            # the file's own bytes are not quoted: the caller may not be allowed to read them
            raise RecordingError(
                "not an MCAP file: it does not begin with the MCAP magic", where=self.path, expected=f"the MCAP magic {MAGIC!r}"
            )
        try:
            opcode, length = file.record_at(len(MAGIC), file.size)
            if opcode != Opcode.HEADER:
                raise Damage(len(MAGIC), f"expected the Header record, found a {record_name(opcode)} record")
            self._header = parse(opcode, file.read(len(MAGIC) + RECORD.size, length, "the Header record"), len(MAGIC))
        except Damage as damage:
            raise RecordingError(f"{damage.problem}; nothing is readable", where=self.path) from None
        data_start = len(MAGIC) + RECORD.size + length
        footer_offset = file.size - len(MAGIC) - FOOTER_SIZE
        problem: Damage | None = None
        footer = None
        try:
            footer = self._footer(footer_offset, data_start)
            if footer.summary_start and self._use_summary(footer, footer_offset):
                self._indexed = True
                return
        except Damage as damage:
            problem = damage
        data_end = footer_offset if footer is not None else file.size
        if footer is not None and footer.summary_start:
            data_end = footer.summary_start
        budget = Budget(self.path, self.limits)
        self._index, damages = scan(file, data_start, data_end, footer is not None, budget)
        self._kept = budget.held
        if problem is not None and not damages:  # the scan says more precisely what is wrong
            damages.append(problem)
        if damages:
            self._damaged(damages)

    def _footer(self, offset: int, data_start: int) -> Footer:
        file = self._file
        if offset < data_start:
            raise Damage(file.size, UNCLOSED, truncated=True)
        tail = file.read(offset, FOOTER_SIZE + len(MAGIC), "the footer")
        opcode, length = RECORD.unpack_from(tail)
        if tail[-len(MAGIC) :] != MAGIC or opcode != Opcode.FOOTER or length != FOOTER.size:
            raise Damage(file.size, UNCLOSED, truncated=True)
        start, offsets_start, crc = FOOTER.unpack_from(tail, RECORD.size)
        footer = Footer(summary_start=start, summary_offset_start=offsets_start, summary_crc=crc)
        if start and not data_start <= start <= offset:
            raise Damage(offset, f"the footer points to a summary at offset {start}, outside the file's data")
        if start and crc:
            section = file.read(start, offset + RECORD.size + 16 - start, "the summary")
            if zlib.crc32(section) != crc:
                raise Damage(start, "the summary's CRC does not match (the summary is corrupt)")
        return footer

    def _use_summary(self, footer: Footer, footer_offset: int) -> bool:
        """Read the summary; False if it lacks what an indexed read needs (then the file is scanned)."""
        if not footer.summary_crc:  # nothing vouches for its framing, which the library does not check
            self._check_summary(footer.summary_start, footer_offset, contents=False)
        try:
            with self._file.lend() as stream:
                summary = SeekingReader(stream).get_summary()
        except LIBRARY_ERRORS as exc:
            self._check_summary(footer.summary_start, footer_offset, contents=True)  # which record, and what is wrong
            raise Damage(footer.summary_start, f"the summary cannot be read ({type(exc).__name__}: {exc})") from exc
        statistics = summary.statistics if summary is not None else None
        if summary is None or statistics is None or statistics.chunk_count != len(summary.chunk_indexes):
            return False
        chunk_indexes = summary.chunk_indexes
        if statistics.message_count and not chunk_indexes:
            return False  # messages outside chunks: only a scan finds them
        if not set(statistics.channel_message_counts) <= set(summary.channels):
            return False
        for index in chunk_indexes:
            if index.chunk_start_offset + index.chunk_length > footer.summary_start:
                raise Damage(footer.summary_start, f"a chunk index points past the data (to offset {index.chunk_start_offset})")
        self._index = Index(
            schemas=summary.schemas,
            channels=summary.channels,
            chunks=[(i.message_start_time, i.chunk_start_offset, i.message_end_time) for i in chunk_indexes],
            counts={cid: n for cid, n in statistics.channel_message_counts.items() if n},
            compressions={i.compression or "none" for i in chunk_indexes},
            attachments=statistics.attachment_count,
            metadata=statistics.metadata_count,
        )
        if statistics.message_count:
            self._index.start_ns, self._index.end_ns = statistics.message_start_time, statistics.message_end_time
        return True

    def _check_summary(self, start: int, end: int, *, contents: bool) -> None:
        """Check the summary record by record: the framing, and with ``contents`` each record's
        content too; raises :class:`Damage` for the first record found damaged."""
        while start < end:
            opcode, length = self._file.record_at(start, end)
            if contents and opcode in PARSERS:
                parse(opcode, self._file.read(start + RECORD.size, length, f"a {record_name(opcode)} record"), start)
            start += RECORD.size + length

    def _damaged(self, damages: list[Damage]) -> None:
        first = damages[0]
        readable = sum(self._index.counts.values())
        more = f" (and {len(damages) - 1} more problems)" if len(damages) > 1 else ""
        self.problem = f"{first.problem}{more}"
        if not self.recover:
            hint = f"{readable} messages are readable: {_RECOVER}" if readable else "no message before it is readable"
            raise RecordingError(self.problem, where=self.path, expected=f"{_whole(first)}; {hint}")
        log.warning("%s: %s; reading the %d messages that are readable", self.path, self.problem, readable)

    # ------------------------------------------------------------------ information

    @property
    def header(self) -> Header:
        """The file's Header record: profile and writing library."""
        return self._header

    @property
    def channels(self) -> tuple[ChannelInfo, ...]:
        """Every channel, by id (those without messages too)."""
        return tuple(self._info(cid) for cid in sorted(self._index.channels))

    def _info(self, channel_id: int) -> ChannelInfo:
        info = self._infos.get(channel_id)
        if info is None:
            channel = self._index.channels[channel_id]
            schema = self._index.schemas.get(channel.schema_id) if channel.schema_id else None
            info = self._infos[channel_id] = ChannelInfo(
                id=channel.id,
                topic=channel.topic,
                message_encoding=channel.message_encoding,
                schema_id=channel.schema_id,
                schema_name=schema.name if schema else "",
                schema_encoding=schema.encoding if schema else "",
                schema_data=bytes(schema.data) if schema else b"",
                metadata=MappingProxyType(dict(channel.metadata)),
                message_count=self._index.counts.get(channel.id, 0),
            )
        return info

    @property
    def info(self) -> RecordingInfo:
        """Channels, counts, time range, chunks, and any damage found (``dyknow mcap info``)."""
        index = self._index
        return RecordingInfo(
            path=self.path,
            size=self._file.size,
            profile=self._header.profile,
            library=self._header.library,
            message_count=sum(index.counts.values()),
            start_ns=index.start_ns,
            end_ns=index.end_ns,
            channels=self.channels,
            chunk_count=len(index.chunks),
            compressions=tuple(sorted(index.compressions)),
            attachment_count=index.attachments,
            metadata_count=index.metadata,
            indexed=self._indexed,
            problem=self.problem,
        )

    # ------------------------------------------------------------------ messages

    def messages(
        self,
        channel_ids: Iterable[int] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RecordedMessage]:
        """The messages in log-time order (ties in file order), optionally of some channels and
        with ``start_ns <= log_time <= end_ns``.

        Chunks are read when their turn comes. A chunk found damaged now raises
        :class:`RecordingError`, or is skipped with a warning when reading with ``recover``. The
        messages of chunks whose time ranges overlap wait together: when they would hold more
        than :attr:`limits` allow, :class:`RecordingError` is raised (``recover`` or not).
        """
        wanted = None if channel_ids is None else set(channel_ids)
        index = self._index
        budget = Budget(self.path, self.limits, self._kept)

        def keep(channel_id: int, log_time: int) -> bool:
            return (
                (wanted is None or channel_id in wanted)
                and (start_ns is None or log_time >= start_ns)
                and (end_ns is None or log_time <= end_ns)
            )

        # Heap entries sort by (log time, file offset, index in chunk); a chunk not yet read sorts
        # by its first log time and index -1, so it is opened before any message that could follow
        # one of its own. That gives a stable sort by log time in file order.
        heap: list[tuple[int, int, int, Any]] = []
        for first, offset, last in index.chunks:
            if (start_ns is None or last >= start_ns) and (end_ns is None or first <= end_ns):
                heap.append((first, offset, -1, None))
        for loose in index.loose:
            if keep(loose.channel_id, loose.log_time):
                heap.append((loose.log_time, loose.offset, 0, loose))
        heapify(heap)
        while heap:
            log_time, offset, position, item = heappop(heap)
            if position == -1:
                for i, record in enumerate(self._load_chunk(offset, budget)):  # each charged to the budget
                    if isinstance(record, tuple):
                        if keep(record[0], record[2]):
                            heappush(heap, (record[2], offset, i, record))  # until it is popped
                            continue
                    elif index.register(record):
                        self._kept += cost(record)  # for good
                        continue
                    budget.give(cost(record))
                continue
            if isinstance(item, Loose):
                data = self._file.read(item.offset + RECORD.size + MESSAGE.size, item.length - MESSAGE.size, "a Message record")
                item = (item.channel_id, item.sequence, item.log_time, item.publish_time, data)
            else:
                budget.give(len(item[4]) + RECORD_COST)
            channel_id, sequence, log_time, publish_time, data = item
            if channel_id not in index.channels:
                self._bad(Damage(offset, f"a message refers to channel {channel_id}, which no Channel record defines", fatal=False))
                continue
            yield RecordedMessage(self._info(channel_id), sequence, log_time, publish_time, data)

    def _load_chunk(self, offset: int, budget: Budget) -> list[Any]:
        try:
            return self._file.chunk(offset, budget)[1]
        except Damage as damage:
            self._bad(damage)
            return []

    def _bad(self, damage: Damage) -> None:
        if not self.recover:
            raise RecordingError(
                damage.problem, where=self.path, expected=f"{_whole(damage)}; replay the rest with recover=True (dyknow replay --recover)"
            )
        log.warning("%s: %s; skipped", self.path, damage.problem)
        if self.problem is None:
            self.problem = damage.problem

    # ------------------------------------------------------------------ records

    def records(self) -> Iterator[McapRecord]:
        """Every record in file order, as the ``mcap`` library's record objects.

        Chunks are replaced by the Schema, Channel and Message records inside them, and
        MessageIndex records are left out: the form of the MCAP conformance suite's streamed
        reader. Raises :class:`RecordingError` at damage (with ``recover``: stops there, warning)
        and at a chunk over :attr:`limits`.
        """
        size = self._file.size
        budget = Budget(self.path, self.limits, self._kept)
        with open(self.path, "rb") as file:  # a file of its own: records are read in turn
            stream = cast(BinaryIO, Clamped(file, size))
            reader: Iterator[McapRecord] | None = StreamReader(stream, emit_chunks=True).records
            offset = len(MAGIC)  # the library's first read takes the magic (checked on opening) with the Header
            while True:
                try:
                    if self.closed:
                        raise ClosedError("the recording is closed; open it again", where=self.path)
                    opcode, length = self._file.record_at(offset, size)
                    end = offset + RECORD.size + length
                    if opcode not in _STREAMED:  # MessageIndex (left out) or unknown: skipped unread
                        offset, reader = end, None
                        continue
                    if reader is None:
                        stream.seek(offset)
                        reader = StreamReader(stream, skip_magic=True, emit_chunks=True).records
                    record = _next_or_none(reader, stream, end)
                    if record is None:  # the library fails on it or reads past it: read it as it is
                        record, reader = self._file.record(offset), None
                    inner = None
                    if isinstance(record, Chunk):
                        inner = self._file.chunk(offset, budget, record)[1]
                except Damage as damage:
                    self._stop_records(damage)
                    return
                if inner is None:
                    yield record
                for item in inner or ():
                    if isinstance(item, tuple):
                        channel_id, sequence, log_time, publish_time, data = item
                        yield McapMessage(channel_id=channel_id, sequence=sequence, log_time=log_time, publish_time=publish_time, data=data)
                    else:
                        yield item
                if inner is not None:
                    budget.give(sum(map(cost, inner)))  # let go (the next chunk is read after inner is)
                if isinstance(record, Footer):
                    if self._file.read(end, min(len(MAGIC), size - end), "the closing magic") != MAGIC or end + len(MAGIC) != size:
                        self._stop_records(Damage(end, "expected the MCAP magic (and nothing else) after the footer"))
                    return
                offset = end

    def _stop_records(self, damage: Damage) -> None:
        if not self.recover:
            raise RecordingError(damage.problem, where=self.path, expected=_whole(damage)) from None
        log.warning("%s: %s; stopping there", self.path, damage.problem)


_STREAMED = {*PARSERS, Opcode.MESSAGE, Opcode.CHUNK}  # the records that records() has the library read


def _next_or_none(reader: Iterator[McapRecord], stream: BinaryIO, end: int) -> McapRecord | None:
    """The library's next record if it reads it without error and exactly up to ``end``, else None."""
    try:
        record = next(reader)
    except LIBRARY_ERRORS:
        return None
    return record if stream.tell() == end else None


def _whole(damage: Damage) -> str:
    """What a damaged file should have been: the ``expected`` of the error about it."""
    return "a complete MCAP file" if damage.truncated else "an intact MCAP file"
