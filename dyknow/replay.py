"""Reading MCAP recordings and replaying them into dyknow streams.

:class:`Recording` reads an MCAP file, whoever wrote it (dyknow, Foxglove, rosbag2, the MCAP
libraries). It reads through the summary and chunk indexes when the file has them. Otherwise,
and for damaged files, it scans the file from the start. Messages come out in log-time order
(ties in file order), and only the chunks being merged are held in memory.

:class:`Player` replays a recording: in log-time order at the original pace, scaled by ``rate``,
or as fast as possible (``rate=math.inf``); once or in a loop; limited to some topics and a time
window, with topics remapped to other keys::

    from dyknow.replay import Player

    with Player("run.mcap", rate=2.0, topics=["/camera/image"], remap={"/camera/image": "replay/image"}) as player:
        player.publish(connect=["tcp/127.0.0.1:7447"])    # into Zenoh, until the end of the file

Each replayed :class:`~dyknow.message.Message` carries the file's sequence number, the message's
``log_time`` as its origin timestamp (it stays as in the file, also when looping) and the replay
time as its send timestamp. A topic replays on the key :func:`key_for_topic` gives, such as
``camera/image`` for ``/camera/image``, unless it is remapped.

Payloads are decoded from the file's encodings:

- dyknow recordings give back exactly the payload type that was published (see
  :mod:`dyknow.recording`): bytes, text, JSON values and numpy arrays;
- ``json`` messages give JSON values;
- ``foxglove.RawImage`` (protobuf or JSON) and ROS 2 ``sensor_msgs/msg/Image`` give numpy arrays.
  ``rgb8`` and ``rgba8`` images are turned into OpenCV's BGR(A) order, as dyknow's vision units
  expect;
- ``foxglove.CompressedImage`` (protobuf, or JSON with base64 data) and ROS 2
  ``sensor_msgs/msg/CompressedImage`` are decoded to numpy arrays with OpenCV when it is
  installed. Without ``cv2`` they are delivered as their JPEG/PNG bytes;
- other ROS 2 CDR messages (``std_msgs/msg/String``, ``rcl_interfaces/msg/Log``, ...) give JSON
  values (dicts of their fields; byte arrays become lists of numbers, NaN and infinities None);
- anything else (other encodings, a message that fails to decode) is delivered as its bytes,
  with one warning per channel.

``decode=False`` delivers every message as the bytes stored in the file.

A truncated or corrupt file raises :class:`~dyknow.errors.RecordingError` naming the file and
the offset of the damage. With ``recover=True`` the valid part is replayed, with a warning
(``problem`` says what was skipped). A file whose writer was killed, so it has no summary,
replays every complete chunk this way.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import math
import os
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from heapq import heapify, heappop, heappush
from types import MappingProxyType
from typing import Any

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.records import (
    Message as McapMessage,
)

from dyknow.errors import BindingError, ClosedError, RecordingError, did_you_mean
from dyknow.message import Message
from dyknow.recording import COMPRESSED_IMAGE, NDARRAY, PAYLOAD_METADATA, RAW_IMAGE
from dyknow.transport import Session, check_key_expr, is_wild, key_exprs_intersect, make_config

__all__ = [
    "ChannelInfo",
    "Player",
    "RecordedMessage",
    "Recording",
    "RecordingInfo",
    "image_array",
    "key_for_topic",
]

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")  # opcode, content length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size, uncompressed CRC, compression length
_FOOTER = struct.Struct("<QQI")  # summary start, summary offset start, summary CRC
_FOOTER_SIZE = _RECORD.size + _FOOTER.size
_INT64_MAX = 2**63 - 1
_MAX_CHUNK = 4 * 2**30  # larger (uncompressed) chunks are taken for corruption
_NAMES = {op.value: "".join(part.title() for part in op.name.split("_")) for op in Opcode}
_PARSERS: dict[int, Any] = {
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


_UNCLOSED = "the file ends without a footer: it was not closed (was the recorder killed?)"


def _name(opcode: int) -> str:
    return _NAMES.get(opcode, f"unknown (opcode 0x{opcode:02x})")


# --------------------------------------------------------------------------- plain data


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


@dataclass(frozen=True, slots=True)
class _Loose:
    """A message record outside any chunk, read when its turn comes."""

    offset: int
    length: int
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int


class _Damage(Exception):
    """A problem at an offset of the file. ``fatal``: nothing after it can be read;
    ``truncated``: the file ends too early (rather than holding corrupt data)."""

    def __init__(self, offset: int, reason: str, *, fatal: bool = True, truncated: bool = False) -> None:
        super().__init__(f"offset {offset}: {reason}")
        self.offset = offset
        self.reason = reason
        self.fatal = fatal
        self.truncated = truncated

    @property
    def what(self) -> str:
        return "truncated" if self.truncated else "corrupt"


# --------------------------------------------------------------------------- reading


class Recording:
    """An MCAP file opened for reading. A context manager; ``close()`` is safe twice.

    Opening reads the summary, or scans the file when it has none. A truncated or corrupt file
    raises :class:`RecordingError` naming the file and offset. With ``recover=True`` the valid
    part is read instead, :attr:`problem` says what is wrong, and a warning is logged.
    """

    def __init__(self, path: str | os.PathLike[str], *, recover: bool = False) -> None:
        self.path = os.fspath(path)
        self.recover = recover
        self.problem: str | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunks: list[tuple[int, int, int]] = []  # (start ns, offset, end ns)
        self._loose: list[_Loose] = []
        self._counts: dict[int, int] = {}
        self._start_ns: int | None = None
        self._end_ns: int | None = None
        self._compressions: set[str] = set()
        self._attachments = 0
        self._metadata = 0
        self._indexed = False
        self._header = Header(profile="", library="")
        self._infos: dict[int, ChannelInfo] = {}
        try:
            self._file = open(self.path, "rb")  # noqa: SIM115 (closed by close())
        except OSError as exc:
            raise RecordingError(f"cannot read {self.path}: {exc.strerror or exc}") from exc
        try:
            self._size = os.fstat(self._file.fileno()).st_size
            self._open()
        except BaseException:
            self._file.close()
            raise

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Recording({self.path!r}, {sum(self._counts.values())} messages)"

    def close(self) -> None:
        """Close the file; safe to call twice. Waits for a chunk being read to finish."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._file.close()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    # ------------------------------------------------------------------ low level

    def _read(self, offset: int, size: int, what: str) -> bytes:
        if self._closed:
            raise ClosedError(f"the recording {self.path} is closed; open it again")
        self._file.seek(offset)
        data = self._file.read(size)
        if len(data) < size:
            raise _Damage(offset, f"the file ends inside {what} ({len(data)} of {size} bytes)", truncated=True)
        return data

    def _record_at(self, offset: int, limit: int) -> tuple[int, int]:
        """``(opcode, length)`` of the record at ``offset``, which must end by ``limit``."""
        if offset >= self._size:
            raise _Damage(offset, _UNCLOSED, truncated=True)
        if offset + _RECORD.size > self._size:
            raise _Damage(offset, f"the file ends inside a record header ({self._size - offset} of 9 bytes)", truncated=True)
        opcode, length = _RECORD.unpack(self._read(offset, _RECORD.size, "a record header"))
        if opcode == 0:
            raise _Damage(offset, "invalid record opcode 0x00")
        if offset + _RECORD.size + length > limit:
            if limit == self._size:
                raise _Damage(offset, f"a {_name(opcode)} record of {length} bytes runs past the end of the file ({limit} bytes)", truncated=True)
            raise _Damage(offset, f"a {_name(opcode)} record of {length} bytes runs past offset {limit}")
        return opcode, length

    def _parse(self, opcode: int, content: bytes | memoryview, offset: int) -> Any:
        """A record's content as the mcap library's record object."""
        try:
            if opcode == Opcode.MESSAGE:
                return McapMessage.read(ReadDataStream(io.BytesIO(content)), len(content))
            return _PARSERS[opcode].read(ReadDataStream(io.BytesIO(content)))
        except (McapError, struct.error, UnicodeDecodeError, ValueError, OverflowError) as exc:
            raise _Damage(offset, f"malformed {_name(opcode)} record ({type(exc).__name__}: {exc})", fatal=False) from exc

    def _chunk(self, offset: int) -> list[Any]:
        """The records of the chunk at ``offset``: Schema, Channel and message tuples, in order."""
        opcode, length = self._record_at(offset, self._size)
        if opcode != Opcode.CHUNK:
            raise _Damage(offset, f"expected a Chunk record, found a {_name(opcode)} record", fatal=False)
        content = memoryview(self._read(offset + _RECORD.size, length, "a Chunk record"))
        try:
            _, _, size, crc, name_length = _CHUNK.unpack_from(content)
            compression = bytes(content[_CHUNK.size : _CHUNK.size + name_length]).decode()
            (data_length,) = struct.unpack_from("<Q", content, _CHUNK.size + name_length)
        except (struct.error, UnicodeDecodeError) as exc:
            raise _Damage(offset, f"malformed Chunk record header ({exc})", fatal=False) from exc
        start = _CHUNK.size + name_length + 8
        data = content[start : start + data_length]
        if len(data) != data_length:
            raise _Damage(offset, f"the Chunk record holds {len(data)} bytes of data; its header says {data_length}", fatal=False)
        raw = self._decompress(offset, compression, data, size)
        if crc and zlib.crc32(raw) != crc:
            raise _Damage(offset, f"the chunk's CRC does not match its data (CRC32 {zlib.crc32(raw)}; expected {crc})", fatal=False)
        self._compressions.add(compression or "none")
        return self._chunk_records(offset, memoryview(raw))

    def _decompress(self, offset: int, compression: str, data: memoryview, size: int) -> bytes | memoryview:
        if size > _MAX_CHUNK:
            raise _Damage(offset, f"the chunk claims {size} uncompressed bytes (corrupt?)", fatal=False)
        try:
            if compression == "":
                raw: bytes | memoryview = data
            elif compression == "zstd":
                raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
            elif compression == "lz4":
                raw = lz4.frame.decompress(data)
            else:
                raise _Damage(offset, f"unknown chunk compression {compression!r}; expected zstd, lz4 or none", fatal=False)
        except _Damage:
            raise
        except Exception as exc:  # zstandard and lz4 raise their own (and RuntimeError)
            raise _Damage(offset, f"cannot decompress the {compression} chunk ({type(exc).__name__}: {exc})", fatal=False) from exc
        if len(raw) != size:
            raise _Damage(offset, f"the chunk decompressed to {len(raw)} bytes; its header says {size}", fatal=False)
        return raw

    def _chunk_records(self, offset: int, raw: memoryview) -> list[Any]:
        out: list[Any] = []
        pos, end = 0, len(raw)
        while pos < end:
            if pos + _RECORD.size > end:
                raise _Damage(offset, f"a record header at byte {pos} of the chunk's data is cut off", fatal=False)
            opcode, length = _RECORD.unpack_from(raw, pos)
            stop = pos + _RECORD.size + length
            if stop > end:
                raise _Damage(offset, f"a {_name(opcode)} record at byte {pos} of the chunk's data runs past its end", fatal=False)
            if opcode == Opcode.MESSAGE:
                if length < _MESSAGE.size:
                    raise _Damage(offset, f"a Message record at byte {pos} of the chunk's data is too short ({length} bytes)", fatal=False)
                out.append((*_MESSAGE.unpack_from(raw, pos + _RECORD.size), bytes(raw[pos + _RECORD.size + _MESSAGE.size : stop])))
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                out.append(self._parse(opcode, raw[pos + _RECORD.size : stop], offset))
            pos = stop
        return out

    def _register(self, record: Schema | Channel) -> None:
        if isinstance(record, Schema):
            self._schemas.setdefault(record.id, record)
        else:
            self._channels.setdefault(record.id, record)

    # ------------------------------------------------------------------ opening

    def _open(self) -> None:
        if self._size == 0:
            raise RecordingError(f"{self.path}: the file is empty (0 bytes); expected an MCAP file")
        self._file.seek(0)
        head = self._file.read(len(MAGIC))
        if head != MAGIC:
            if MAGIC.startswith(head):
                raise RecordingError(f"{self.path}: truncated at offset 0: the file ends inside the MCAP magic; nothing is readable")
            raise RecordingError(f"{self.path}: not an MCAP file: it begins with {head!r}; expected the MCAP magic {MAGIC!r}")
        try:
            opcode, length = self._record_at(len(MAGIC), self._size)
            if opcode != Opcode.HEADER:
                raise _Damage(len(MAGIC), f"expected the Header record, found a {_name(opcode)} record")
            self._header = self._parse(opcode, self._read(len(MAGIC) + _RECORD.size, length, "the Header record"), len(MAGIC))
        except _Damage as damage:
            raise RecordingError(f"{self.path}: {damage.what} at offset {damage.offset}: {damage.reason}; nothing is readable") from None
        data_start = len(MAGIC) + _RECORD.size + length
        footer_offset = self._size - len(MAGIC) - _FOOTER_SIZE
        problem: _Damage | None = None
        footer = None
        try:
            footer = self._footer(footer_offset, data_start)
            if footer.summary_start and self._use_summary(footer, footer_offset):
                self._indexed = True
                return
        except _Damage as damage:
            problem = damage
        data_end = footer_offset if footer is not None else self._size
        if footer is not None and footer.summary_start:
            data_end = footer.summary_start
        damages = self._scan(data_start, data_end, footer is not None)
        if problem is not None and not damages:  # the scan says more precisely what is wrong
            damages.append(problem)
        if damages:
            self._damaged(damages)

    def _footer(self, offset: int, data_start: int) -> Footer:
        if offset < data_start:
            raise _Damage(self._size, _UNCLOSED, truncated=True)
        tail = self._read(offset, _FOOTER_SIZE + len(MAGIC), "the footer")
        opcode, length = _RECORD.unpack_from(tail)
        if tail[-len(MAGIC) :] != MAGIC or opcode != Opcode.FOOTER or length != _FOOTER.size:
            raise _Damage(self._size, _UNCLOSED, truncated=True)
        start, offsets_start, crc = _FOOTER.unpack_from(tail, _RECORD.size)
        footer = Footer(summary_start=start, summary_offset_start=offsets_start, summary_crc=crc)
        if start and not data_start <= start <= offset:
            raise _Damage(offset, f"the footer points to a summary at offset {start}, outside the file's data")
        if start and crc:
            section = self._read(start, offset + _RECORD.size + 16 - start, "the summary")
            if zlib.crc32(section) != crc:
                raise _Damage(start, "the summary's CRC does not match (the summary is corrupt)")
        return footer

    def _use_summary(self, footer: Footer, footer_offset: int) -> bool:
        """Read the summary; False if it lacks what an indexed read needs (then the file is scanned)."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        chunk_indexes: list[ChunkIndex] = []
        statistics: Statistics | None = None
        pos = footer.summary_start
        while pos < footer_offset:
            opcode, length = self._record_at(pos, footer_offset)
            content = self._read(pos + _RECORD.size, length, f"a {_name(opcode)} record")
            if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.CHUNK_INDEX, Opcode.STATISTICS):
                record = self._parse(opcode, content, pos)
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, ChunkIndex):
                    chunk_indexes.append(record)
                else:
                    statistics = record
            pos += _RECORD.size + length
        if statistics is None or statistics.chunk_count != len(chunk_indexes):
            return False
        if statistics.message_count and not chunk_indexes:
            return False  # messages outside chunks: only a scan finds them
        if not set(statistics.channel_message_counts) <= set(channels):
            return False
        for index in chunk_indexes:
            if index.chunk_start_offset + index.chunk_length > footer.summary_start:
                raise _Damage(footer.summary_start, f"a chunk index points past the data (to offset {index.chunk_start_offset})")
        self._schemas, self._channels = schemas, channels
        self._chunks = [(i.message_start_time, i.chunk_start_offset, i.message_end_time) for i in chunk_indexes]
        self._compressions = {i.compression or "none" for i in chunk_indexes}
        self._counts = {cid: n for cid, n in statistics.channel_message_counts.items() if n}
        if statistics.message_count:
            self._start_ns, self._end_ns = statistics.message_start_time, statistics.message_end_time
        self._attachments, self._metadata = statistics.attachment_count, statistics.metadata_count
        return True

    def _scan(self, pos: int, end: int, closed: bool) -> list[_Damage]:
        """Index the data section from ``pos`` to ``end``; returns what was found damaged."""
        damages: list[_Damage] = []
        while pos < end:
            try:
                opcode, length = self._record_at(pos, end)
                if opcode == Opcode.DATA_END or opcode == Opcode.FOOTER:
                    break
                if opcode == Opcode.CHUNK:
                    self._scan_chunk(pos)
                elif opcode == Opcode.MESSAGE:
                    self._scan_message(pos, length)
                elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                    self._register(self._parse(opcode, self._read(pos + _RECORD.size, length, "a record"), pos))
                elif opcode == Opcode.ATTACHMENT:
                    self._attachments += 1
                elif opcode == Opcode.METADATA:
                    self._metadata += 1
            except _Damage as damage:
                damages.append(damage)
                if damage.fatal:
                    return damages
            pos += _RECORD.size + length
        else:
            if not closed:
                damages.append(_Damage(pos, _UNCLOSED, truncated=True))
        return damages

    def _scan_chunk(self, offset: int) -> None:
        records = self._chunk(offset)
        start = end = None
        for record in records:
            if isinstance(record, tuple):
                self._count(record[0], record[2], offset)
                start = record[2] if start is None else min(start, record[2])
                end = record[2] if end is None else max(end, record[2])
            else:
                self._register(record)
        if start is not None and end is not None:
            self._chunks.append((start, offset, end))

    def _scan_message(self, offset: int, length: int) -> None:
        if length < _MESSAGE.size:
            raise _Damage(offset, f"a Message record of {length} bytes is too short", fatal=False)
        channel_id, sequence, log_time, publish_time = _MESSAGE.unpack(self._read(offset + _RECORD.size, _MESSAGE.size, "a Message record"))
        self._count(channel_id, log_time, offset)
        self._loose.append(_Loose(offset, length, channel_id, sequence, log_time, publish_time))

    def _count(self, channel_id: int, log_time: int, offset: int) -> None:
        if channel_id not in self._channels:
            raise _Damage(offset, f"a message refers to channel {channel_id}, which no Channel record before it defines", fatal=False)
        self._counts[channel_id] = self._counts.get(channel_id, 0) + 1
        self._start_ns = log_time if self._start_ns is None else min(self._start_ns, log_time)
        self._end_ns = log_time if self._end_ns is None else max(self._end_ns, log_time)

    def _damaged(self, damages: list[_Damage]) -> None:
        first = damages[0]
        readable = sum(self._counts.values())
        more = f" (and {len(damages) - 1} more problems)" if len(damages) > 1 else ""
        self.problem = f"{first.what} at offset {first.offset}: {first.reason}{more}"
        if not self.recover:
            hint = f"{readable} messages are readable: replay them with recover=True (dyknow replay --recover)" if readable else "no message before it is readable"
            raise RecordingError(f"{self.path}: {self.problem}; {hint}")
        log.warning("%s: %s; reading the %d messages that are readable", self.path, self.problem, readable)

    # ------------------------------------------------------------------ information

    @property
    def header(self) -> Header:
        """The file's Header record: profile and writing library."""
        return self._header

    @property
    def channels(self) -> tuple[ChannelInfo, ...]:
        """Every channel, by id (those without messages too)."""
        return tuple(self._info(cid) for cid in sorted(self._channels))

    def _info(self, channel_id: int) -> ChannelInfo:
        info = self._infos.get(channel_id)
        if info is None:
            channel = self._channels[channel_id]
            schema = self._schemas.get(channel.schema_id) if channel.schema_id else None
            info = self._infos[channel_id] = ChannelInfo(
                id=channel.id,
                topic=channel.topic,
                message_encoding=channel.message_encoding,
                schema_id=channel.schema_id,
                schema_name=schema.name if schema else "",
                schema_encoding=schema.encoding if schema else "",
                schema_data=bytes(schema.data) if schema else b"",
                metadata=MappingProxyType(dict(channel.metadata)),
                message_count=self._counts.get(channel.id, 0),
            )
        return info

    @property
    def info(self) -> RecordingInfo:
        """Channels, counts, time range, chunks, and any damage found (``dyknow mcap info``)."""
        return RecordingInfo(
            path=self.path,
            size=self._size,
            profile=self._header.profile,
            library=self._header.library,
            message_count=sum(self._counts.values()),
            start_ns=self._start_ns,
            end_ns=self._end_ns,
            channels=self.channels,
            chunk_count=len(self._chunks),
            compressions=tuple(sorted(self._compressions)),
            attachment_count=self._attachments,
            metadata_count=self._metadata,
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
        :class:`RecordingError`, or is skipped with a warning when reading with ``recover``.
        """
        wanted = None if channel_ids is None else set(channel_ids)

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
        for first, offset, last in self._chunks:
            if (start_ns is None or last >= start_ns) and (end_ns is None or first <= end_ns):
                heap.append((first, offset, -1, None))
        for loose in self._loose:
            if keep(loose.channel_id, loose.log_time):
                heap.append((loose.log_time, loose.offset, 0, loose))
        heapify(heap)
        while heap:
            log_time, offset, index, item = heappop(heap)
            if index == -1:
                for i, record in enumerate(self._load_chunk(offset)):
                    if isinstance(record, tuple):
                        if keep(record[0], record[2]):
                            heappush(heap, (record[2], offset, i, record))
                    else:
                        self._register(record)
                continue
            if isinstance(item, _Loose):
                with self._lock:
                    data = self._read(item.offset + _RECORD.size + _MESSAGE.size, item.length - _MESSAGE.size, "a Message record")
                item = (item.channel_id, item.sequence, item.log_time, item.publish_time, data)
            channel_id, sequence, log_time, publish_time, data = item
            if channel_id not in self._channels:
                self._bad(_Damage(offset, f"a message refers to channel {channel_id}, which no Channel record defines", fatal=False))
                continue
            yield RecordedMessage(self._info(channel_id), sequence, log_time, publish_time, data)

    def _load_chunk(self, offset: int) -> list[Any]:
        try:
            with self._lock:
                return self._chunk(offset)
        except _Damage as damage:
            self._bad(damage)
            return []

    def _bad(self, damage: _Damage) -> None:
        problem = f"{damage.what} at offset {damage.offset}: {damage.reason}"
        if not self.recover:
            raise RecordingError(f"{self.path}: {problem}; replay the rest with recover=True (dyknow replay --recover)")
        log.warning("%s: %s; skipped", self.path, problem)
        if self.problem is None:
            self.problem = problem

    def records(self) -> Iterator[McapRecord]:
        """Every record in file order, as the ``mcap`` library's record objects.

        Chunks are replaced by the Schema, Channel and Message records inside them, and
        MessageIndex records are left out: the form of the MCAP conformance suite's streamed
        reader. Raises :class:`RecordingError` at damage (with ``recover``: stops there, warning).
        """
        pos = len(MAGIC)
        footer_offset = self._size - len(MAGIC) - _FOOTER_SIZE
        while True:
            try:
                opcode, length = self._record_at(pos, self._size)
                if opcode == Opcode.CHUNK:
                    with self._lock:
                        inner = self._chunk(pos)
                    for record in inner:
                        if isinstance(record, tuple):
                            channel_id, sequence, log_time, publish_time, data = record
                            yield McapMessage(channel_id=channel_id, sequence=sequence, log_time=log_time, publish_time=publish_time, data=data)
                        else:
                            yield record
                elif opcode != Opcode.MESSAGE_INDEX and (opcode in _PARSERS or opcode == Opcode.MESSAGE):
                    with self._lock:
                        content = self._read(pos + _RECORD.size, length, f"a {_name(opcode)} record")
                    record = self._parse(opcode, content, pos)
                    yield record
                    if opcode == Opcode.FOOTER:
                        end = pos + _RECORD.size + length
                        with self._lock:
                            tail = self._read(end, min(len(MAGIC), self._size - end), "the closing magic")
                        if pos != footer_offset or tail != MAGIC:
                            raise _Damage(end, "expected the MCAP magic (and nothing else) after the footer")
                        return
            except _Damage as damage:
                message = f"{self.path}: {damage.what} at offset {damage.offset}: {damage.reason}"
                if not self.recover:
                    raise RecordingError(message) from None
                log.warning("%s; stopping there", message)
                return
            pos += _RECORD.size + length


# --------------------------------------------------------------------------- payloads


# Image encodings (lower case) -> (numpy type code, channels); 1 channel gives an H x W array.
_IMAGE_LAYOUTS = {
    "mono8": ("u1", 1), "8uc1": ("u1", 1), "bgr8": ("u1", 3), "rgb8": ("u1", 3), "8uc3": ("u1", 3),
    "bgra8": ("u1", 4), "rgba8": ("u1", 4), "8uc4": ("u1", 4), "mono16": ("u2", 1), "16uc1": ("u2", 1),
    "16sc1": ("i2", 1), "32sc1": ("i4", 1), "32fc1": ("f4", 1), "64fc1": ("f8", 1), "8sc1": ("i1", 1),
}  # fmt: skip


def image_array(width: int, height: int, encoding: str, step: int, data: bytes | memoryview, bigendian: bool = False) -> np.ndarray:
    """A raw image (ROS ``sensor_msgs/Image`` or ``foxglove.RawImage`` fields) as a numpy array.

    Colour images come in OpenCV's BGR(A) order: ``rgb8`` and ``rgba8`` are converted. Multi-byte
    pixels come in the machine's byte order. Raises ``ValueError`` for encodings it does not know
    (Bayer and YUV among them) and for data too short for the size given.
    """
    layout = _IMAGE_LAYOUTS.get(encoding.lower())
    if layout is None:
        raise ValueError(f"image encoding {encoding!r} is not supported; expected one of {', '.join(sorted(_IMAGE_LAYOUTS))}")
    code, channels = layout
    dtype = np.dtype((">" if bigendian else "<") + code)
    row = width * channels * dtype.itemsize
    buffer = np.frombuffer(data, np.uint8)
    if step < row or buffer.size < step * height:
        raise ValueError(f"{encoding} image of {width}x{height}: {buffer.size} bytes with step {step} are too few")
    rows = buffer[: step * height].reshape(height, step)[:, :row]
    if step != row:
        rows = np.ascontiguousarray(rows)
    array = rows.view(dtype).reshape((height, width, channels) if channels > 1 else (height, width))
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    if encoding.lower() == "rgb8":
        array = np.ascontiguousarray(array[..., ::-1])
    elif encoding.lower() == "rgba8":
        array = np.ascontiguousarray(array[..., [2, 1, 0, 3]])
    return array


def _cv2() -> Any:
    """OpenCV, imported on first use; None when it is not installed."""
    try:
        import cv2
    except ImportError:
        return None
    return cv2


def _pb_fields(data: bytes | memoryview) -> dict[int, list[Any]]:
    """A protobuf message as ``{field number: [values]}`` (ints, or memoryviews for bytes)."""
    view = memoryview(data)
    end = len(view)
    pos = 0
    fields: dict[int, list[Any]] = {}
    while pos < end:
        key, pos = _varint(view, pos)
        number, wire = key >> 3, key & 7
        value: Any
        if wire == 0:
            value, pos = _varint(view, pos)
        elif wire == 1:
            value, pos = int.from_bytes(view[pos : pos + 8], "little"), pos + 8
        elif wire == 2:
            size, pos = _varint(view, pos)
            value, pos = view[pos : pos + size], pos + size
        elif wire == 5:
            value, pos = int.from_bytes(view[pos : pos + 4], "little"), pos + 4
        else:
            raise ValueError(f"protobuf wire type {wire} at byte {pos} is not supported")
        if pos > end:
            raise ValueError("the protobuf message is truncated")
        fields.setdefault(number, []).append(value)
    return fields


def _varint(view: memoryview, pos: int) -> tuple[int, int]:
    result = 0
    for i in range(10):
        if pos + i >= len(view):
            break
        byte = view[pos + i]
        result |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            return result, pos + i + 1
    raise ValueError("malformed protobuf varint")


def _pb_one(fields: dict[int, list[Any]], number: int, default: Any) -> Any:
    values = fields.get(number)
    return values[-1] if values else default


def _pb_text(fields: dict[int, list[Any]], number: int) -> str:
    return bytes(_pb_one(fields, number, b"")).decode()


def _pb_uints(values: list[Any]) -> list[int]:
    """A repeated integer field, packed or not."""
    out: list[int] = []
    for value in values:
        if isinstance(value, int):
            out.append(value)
            continue
        pos = 0
        while pos < len(value):
            number, pos = _varint(value, pos)
            out.append(number)
    return out


def _plain(value: Any) -> Any:
    """A decoded ROS 2 message as JSON-like values."""
    if isinstance(value, (str, bool, int)) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (bytes, bytearray, memoryview)):
        return list(bytes(value))
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    slots = getattr(value, "__slots__", None)
    if slots is not None:
        return {name: _plain(getattr(value, name)) for name in slots}
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    try:
        return [_plain(v) for v in value]  # array.array and the like
    except TypeError:
        return str(value)


class _Decoders:
    """Turns message data into dyknow payloads, with one decoding function per channel."""

    def __init__(self, path: str) -> None:
        self._path = path
        self._by_channel: dict[int, Callable[[bytes], Any]] = {}
        self._warned: set[int] = set()
        self._ros: Any = None

    def payload(self, channel: ChannelInfo, data: bytes) -> Any:
        decode = self._by_channel.get(channel.id)
        try:
            if decode is None:
                decode = self._by_channel[channel.id] = self._decoder(channel)
            return decode(data)
        except Exception as exc:
            if channel.id not in self._warned:
                self._warned.add(channel.id)
                log.warning(
                    "%s: cannot decode %s messages on %r (%s: %s); delivering their bytes",
                    self._path, channel.schema_name or channel.message_encoding, channel.topic, type(exc).__name__, exc,
                )
            return data

    def _decoder(self, channel: ChannelInfo) -> Callable[[bytes], Any]:
        kind = channel.metadata.get(PAYLOAD_METADATA)
        encoding, schema = channel.message_encoding, channel.schema_name
        if encoding == "protobuf":
            if schema == RAW_IMAGE:
                return _pb_raw_image
            if schema == COMPRESSED_IMAGE:
                return _pb_compressed_bytes if kind == "bytes" else lambda d: self._compressed(_pb_compressed_bytes(d))
            if schema == NDARRAY:
                return _pb_ndarray
        elif encoding == "json":
            if kind is None and schema == COMPRESSED_IMAGE:
                return lambda d: self._compressed(base64.b64decode(json.loads(d)["data"]))
            if kind is None and schema == RAW_IMAGE:
                return _json_raw_image
            return json.loads
        elif encoding == "cdr" and channel.schema_encoding == "ros2msg":
            return self._ros2(channel)
        elif encoding.startswith("text/") or kind == "text":
            return lambda d: d.decode()
        return bytes

    def _ros2(self, channel: ChannelInfo) -> Callable[[bytes], Any]:
        if self._ros is None:
            from mcap_ros2.decoder import DecoderFactory  # imported on first use: it parses schemas

            self._ros = DecoderFactory()
        schema = Schema(id=channel.schema_id, name=channel.schema_name, encoding="ros2msg", data=channel.schema_data)
        decode = self._ros.decoder_for("cdr", schema)
        if decode is None:
            raise ValueError(f"no ROS 2 decoder for {channel.schema_name!r}")
        if channel.schema_name == "sensor_msgs/msg/Image":
            return lambda d: _ros_image(decode(d))
        if channel.schema_name == "sensor_msgs/msg/CompressedImage":
            return lambda d: self._compressed(bytes(decode(d).data))
        return lambda d: _plain(decode(d))

    def _compressed(self, data: bytes) -> Any:
        cv2 = _cv2()
        if cv2 is None:
            if -1 not in self._warned:
                self._warned.add(-1)
                log.warning("OpenCV (cv2) is not installed: compressed images are delivered as their JPEG/PNG bytes")
            return bytes(data)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"OpenCV cannot decode the compressed image ({len(data)} bytes)")
        return image


def _pb_raw_image(data: bytes) -> np.ndarray:
    f = _pb_fields(data)
    return image_array(_pb_one(f, 2, 0), _pb_one(f, 3, 0), _pb_text(f, 4), _pb_one(f, 5, 0), _pb_one(f, 6, b""))


def _pb_compressed_bytes(data: bytes) -> bytes:
    return bytes(_pb_one(_pb_fields(data), 2, b""))


def _pb_ndarray(data: bytes) -> np.ndarray:
    f = _pb_fields(data)
    dtype = np.dtype(_pb_text(f, 1))
    shape = _pb_uints(f.get(2, []))
    return np.frombuffer(_pb_one(f, 3, b""), dtype).reshape(shape)


def _json_raw_image(data: bytes) -> np.ndarray:
    obj = json.loads(data)
    return image_array(int(obj["width"]), int(obj["height"]), str(obj["encoding"]), int(obj["step"]), base64.b64decode(obj["data"]))


def _ros_image(msg: Any) -> np.ndarray:
    return image_array(msg.width, msg.height, msg.encoding, msg.step, bytes(msg.data), bool(msg.is_bigendian))


# --------------------------------------------------------------------------- topics and keys


def key_for_topic(topic: str) -> str:
    """The Zenoh key a recorded topic replays on, unless remapped.

    Leading, trailing and doubled slashes go (ROS's ``/camera/image`` becomes ``camera/image``)
    and characters Zenoh keys cannot hold (``* $ ? #``) become ``_``.

    >>> key_for_topic("/camera/image")
    'camera/image'
    """
    chunks = [c for c in topic.split("/") if c]
    return "/".join(c.translate(_KEY_UNSAFE) for c in chunks)


_KEY_UNSAFE = str.maketrans({c: "_" for c in "*$?#"})


def _matches(pattern: str, topic: str) -> bool:
    """Whether a ``topics`` entry selects ``topic``: the topic itself, its key, or a key expression."""
    if pattern == topic:
        return True
    key = key_for_topic(topic)
    if not key:
        return False
    if pattern.strip("/") == key:
        return True
    if is_wild(pattern):
        try:
            return key_exprs_intersect(pattern.strip("/"), key)
        except Exception:
            return False
    return False


def _remapped(remap: Mapping[str, str], topic: str) -> str | None:
    key = key_for_topic(topic)
    for source, target in remap.items():
        if source == topic or (key and source.strip("/") == key):
            return target
    for source, target in remap.items():  # prefixes: "robot/**=replay/**"
        if source.endswith("/**") and target.endswith("/**"):
            prefix = source[:-3].strip("/")
            if key == prefix or key.startswith(prefix + "/"):
                return target[:-3] + key[len(prefix) :]
    return None


# --------------------------------------------------------------------------- the player


_Sink = Callable[[Message, RecordedMessage], None]


class Player:
    """Replays an MCAP recording. A context manager; ``close()`` is safe twice and stops a replay.

    ``rate`` scales the pace (2.0: twice as fast; ``math.inf``: as fast as possible). ``loop``
    starts over at the end. ``start_s``/``end_s`` select a window in seconds from the first
    message. ``topics`` selects topics: a topic name, its key, or a key expression such as
    ``camera/**``. ``remap`` maps a topic (or a ``prefix/**``) to the key it replays on.
    ``recover`` reads what is valid in a damaged file. ``decode=False`` delivers the stored bytes.

    Raises :class:`RecordingError` for a file that cannot be read, a topic or remap that matches
    nothing, or a topic that cannot be a Zenoh key (remap it).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        rate: float = 1.0,
        loop: bool = False,
        start_s: float | None = None,
        end_s: float | None = None,
        topics: Sequence[str] = (),
        remap: Mapping[str, str] | None = None,
        recover: bool = False,
        decode: bool = True,
    ) -> None:
        if not (isinstance(rate, (int, float)) and rate > 0):
            raise RecordingError(f"rate: got {rate!r}; expected a positive number (2.0 is twice as fast; math.inf as fast as possible)")
        if start_s is not None and not start_s >= 0:
            raise RecordingError(f"start: got {start_s!r}; expected seconds from the first message, 0 or more")
        if end_s is not None and not end_s >= (start_s or 0.0):
            raise RecordingError(f"end: got {end_s!r}; expected seconds from the first message, not before start ({start_s or 0.0:g})")
        self.rate = float(rate)
        self.loop = loop
        self.decode = decode
        self._stop = threading.Event()
        self._playing = threading.Lock()
        self.recording = Recording(path, recover=recover)
        try:
            self._select(list(topics), dict(remap or {}), start_s, end_s)
        except BaseException:
            self.recording.close()
            raise
        self._decoders = _Decoders(self.recording.path)

    def _select(self, topics: list[str], remap: dict[str, str], start_s: float | None, end_s: float | None) -> None:
        path = self.recording.path
        everything = self.recording.channels
        names = sorted({c.topic for c in everything})
        for pattern in topics:
            if not any(_matches(pattern, c.topic) for c in everything):
                listing = ", ".join(map(repr, names)) or "none"
                raise RecordingError(f"{path}: no topic matches {pattern!r}; its topics are {listing}{did_you_mean(pattern, names)}")
        chosen = [c for c in everything if not topics or any(_matches(p, c.topic) for p in topics)]
        for source, target in remap.items():
            if not any(_remapped({source: target}, c.topic) is not None for c in chosen):
                listing = ", ".join(repr(c.topic) for c in chosen) or "none"
                raise RecordingError(f"remap {source}={target}: no replayed topic of {path} is {source!r}; expected one of {listing}{did_you_mean(source, names)}")
        self._keys: dict[int, str] = {}
        self._bad_keys: list[str] = []  # only publish() needs valid keys; reading and play() do not
        for channel in chosen:
            key = _remapped(remap, channel.topic)
            if key is None:
                key = key_for_topic(channel.topic)
            try:
                check_key_expr(key, what=f"the key for topic {channel.topic!r}", concrete=True)
            except BindingError as exc:
                self._bad_keys.append(f"{path}: {exc}; remap the topic to a key, e.g. --remap '{channel.topic}=replay/topic'")
            self._keys[channel.id] = key
        self.channels: tuple[ChannelInfo, ...] = tuple(chosen)
        first = self.recording.info.start_ns or 0
        self._start_ns = None if start_s is None else first + round(start_s * 1e9)
        self._end_ns = None if end_s is None else first + round(end_s * 1e9)

    def __enter__(self) -> Player:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Player({self.recording.path!r}, {len(self.channels)} topics, rate={self.rate:g})"

    @property
    def info(self) -> RecordingInfo:
        """The recording's summary (all its channels, not only the selected ones)."""
        return self.recording.info

    @property
    def problem(self) -> str | None:
        """What is damaged in the file, when it was opened with ``recover``."""
        return self.recording.problem

    @property
    def keys(self) -> dict[str, str]:
        """The key each replayed topic is published on."""
        return {c.topic: self._keys[c.id] for c in self.channels}

    def stop(self) -> None:
        """Make a running :meth:`play` return soon (any thread)."""
        self._stop.set()

    def close(self, timeout: float = 2.0) -> None:
        """Stop a running replay (waiting up to ``timeout`` s for it) and close the file."""
        self._stop.set()
        if self._playing.acquire(timeout=timeout):
            self._playing.release()
        self.recording.close()

    # ------------------------------------------------------------------ reading

    def messages(self) -> Iterator[RecordedMessage]:
        """The selected messages once, in log-time order, without pacing (``dyknow mcap cat``)."""
        if self.recording.closed:
            raise ClosedError(f"the player of {self.recording.path} is closed; open a new one")
        return self.recording.messages(self._keys, self._start_ns, self._end_ns)

    def payload(self, record: RecordedMessage) -> Any:
        """The dyknow payload of a recorded message (its bytes with ``decode=False``)."""
        return self._decoders.payload(record.channel, record.data) if self.decode else record.data

    # ------------------------------------------------------------------ replaying

    def play(self, sink: _Sink, *, stop: threading.Event | None = None) -> int:
        """Replay at the set pace, calling ``sink(message, record)`` for each message.

        ``message`` is the dyknow :class:`~dyknow.message.Message` a publisher would send (the
        decoded payload, the file's sequence number, log time as origin, now as send time, the
        replay key); ``record`` is the message as stored. Returns how many were delivered, when
        the file ends (without ``loop``), ``stop`` is set, or :meth:`stop`/:meth:`close` is called.
        """
        with self._playing:
            if self.recording.closed:
                raise ClosedError(f"the player of {self.recording.path} is closed; open a new one")
            self._stop.clear()  # stop() and close() end the replay running when they are called
            count = 0
            while True:
                delivered = 0
                first: tuple[int, int] | None = None
                for record in self.messages():
                    if self._stopped(stop):
                        return count
                    key = self._keys[record.channel.id]
                    payload = self.payload(record)
                    if self.rate != math.inf:
                        if first is None:
                            first = (record.log_time_ns, time.monotonic_ns())
                        due = first[1] + int((record.log_time_ns - first[0]) / self.rate)
                        while (now := time.monotonic_ns()) < due:  # never early, even if a wait wakes up early
                            if self._wait((due - now) / 1e9, stop):
                                return count
                    origin = min(record.log_time_ns, _INT64_MAX)
                    sink(Message(payload, record.sequence, origin, time.time_ns(), key), record)
                    count += 1
                    delivered += 1
                if not self.loop or not delivered or self._stopped(stop):
                    return count

    def _stopped(self, stop: threading.Event | None) -> bool:
        return self._stop.is_set() or (stop is not None and stop.is_set())

    def _wait(self, seconds: float, stop: threading.Event | None) -> bool:
        """Sleep ``seconds`` unless stopped first; True if stopped."""
        if stop is None:
            return self._stop.wait(seconds)
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return self._stopped(stop)
            if stop.wait(min(left, 0.05)) or self._stop.is_set():
                return True

    def publish(
        self,
        session: Session | None = None,
        *,
        connect: Iterable[str] = (),
        zenoh_config: str | os.PathLike[str] | None = None,
        stop: threading.Event | None = None,
        wait_s: float = 0.0,
    ) -> int:
        """Replay into Zenoh: each topic on its key, through ``session`` or a session of its own.

        ``wait_s``: first wait up to that long for every key to have a subscriber, so that
        consumers that are starting up get the first messages. Returns how many were published.
        Raises :class:`RecordingError` when a topic cannot be a Zenoh key (remap it).
        """
        if self._bad_keys:
            raise RecordingError(self._bad_keys[0])
        if self.recording.closed:
            raise ClosedError(f"the player of {self.recording.path} is closed; open a new one")
        self._stop.clear()
        own = session is None
        if session is None:
            session = Session(make_config(connect=list(connect), config_file=zenoh_config))
        publishers = {}
        try:
            for key in dict.fromkeys(self._keys.values()):
                publishers[key] = session.declare_publisher(key, reliable=True)  # a replay loses nothing
            deadline = time.monotonic() + wait_s
            while not all(p.matched for p in publishers.values()) and time.monotonic() < deadline:
                if self._wait(min(0.02, max(0.0, deadline - time.monotonic())), stop):
                    return 0
            def send(msg: Message, record: RecordedMessage) -> None:
                publishers[msg.key].put(msg)

            return self.play(send, stop=stop)
        finally:
            for publisher in reversed(publishers.values()):
                publisher.undeclare()
            if own:
                session.close()
