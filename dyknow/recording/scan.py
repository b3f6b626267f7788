"""Scanning an MCAP file's data section record by record: what a file without a usable summary
holds, and where it is damaged.

The ``mcap`` library reads a file without a summary (a recorder killed with SIGKILL, a writer
that writes none) only as a stream: ``NonSeekingReader`` sorts every message of the file in
memory to give them in log-time order, and stops at the first damage with an exception that
neither names the offset nor lets it go on. :func:`scan` instead walks the data section once,
checking each record's framing (:mod:`dyknow.recording.framing`), and builds an :class:`Index`:
the channels, each chunk's offset and log-time range, the messages outside chunks, counts and
times. It records what is damaged and carries on after damage that leaves the rest readable (a
corrupt chunk, a malformed record), so a recovering reader replays everything valid. The reader
then loads chunks only when their turn comes. Chunks are read one at a time within a
:class:`~dyknow.recording.framing.Budget`: what the scan keeps of them (their Schema and Channel
records) stays charged to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mcap.opcode import Opcode
from mcap.records import Channel, Schema

from dyknow.recording.framing import MESSAGE, RECORD, UNCLOSED, Budget, Damage, RecordFile, cost, parse


@dataclass(frozen=True, slots=True)
class Loose:
    """A message record outside any chunk, read when its turn comes."""

    offset: int
    length: int
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int


@dataclass(slots=True)
class Index:
    """What a recording holds and where, from its summary or from a :func:`scan`.

    ``chunks`` holds ``(first log time, offset, last log time)`` per chunk; ``counts`` the
    messages per channel id.
    """

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[tuple[int, int, int]] = field(default_factory=list)
    loose: list[Loose] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    compressions: set[str] = field(default_factory=set)
    attachments: int = 0
    metadata: int = 0

    def register(self, record: Schema | Channel) -> bool:
        """Learn a Schema or Channel record (the first one with an id wins); True if it is new."""
        known: dict[int, Any] = self.schemas if isinstance(record, Schema) else self.channels
        if record.id in known:
            return False
        known[record.id] = record
        return True

    def count(self, channel_id: int, log_time: int, offset: int) -> None:
        """Count a message of ``channel_id``; :class:`Damage` if no channel record before it defines it."""
        if channel_id not in self.channels:
            raise Damage(offset, f"a message refers to channel {channel_id}, which no Channel record before it defines", fatal=False)
        self.counts[channel_id] = self.counts.get(channel_id, 0) + 1
        self.start_ns = log_time if self.start_ns is None else min(self.start_ns, log_time)
        self.end_ns = log_time if self.end_ns is None else max(self.end_ns, log_time)


def scan(file: RecordFile, start: int, end: int, closed: bool, budget: Budget) -> tuple[Index, list[Damage]]:
    """Index the data section from ``start`` to ``end``, and list what is damaged in it.

    ``closed``: the file has a footer; otherwise reaching ``end`` without a DataEnd record means
    the file was not closed, which is damage too. Chunks are read within ``budget`` (a chunk
    over its limits raises :class:`~dyknow.errors.RecordingError`).
    """
    index = Index()
    damages: list[Damage] = []
    pos = start
    while pos < end:
        try:
            opcode, length = file.record_at(pos, end)
            if opcode == Opcode.DATA_END or opcode == Opcode.FOOTER:
                break
            if opcode == Opcode.CHUNK:
                _scan_chunk(file, pos, index, budget)
            elif opcode == Opcode.MESSAGE:
                _scan_message(file, pos, length, index)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                index.register(parse(opcode, file.read(pos + RECORD.size, length, "a record"), pos))
            elif opcode == Opcode.ATTACHMENT:
                index.attachments += 1
            elif opcode == Opcode.METADATA:
                index.metadata += 1
        except Damage as damage:
            damages.append(damage)
            if damage.fatal:
                return index, damages
        pos += RECORD.size + length
    else:
        if not closed:
            damages.append(Damage(pos, UNCLOSED, truncated=True))
    return index, damages


def _scan_chunk(file: RecordFile, offset: int, index: Index, budget: Budget) -> None:
    compression, records = file.chunk(offset, budget)
    index.compressions.add(compression)
    first = last = None
    kept = 0  # the new Schema and Channel records stay in the index, and charged
    try:
        for record in records:
            if isinstance(record, tuple):
                index.count(record[0], record[2], offset)
                first = record[2] if first is None else min(first, record[2])
                last = record[2] if last is None else max(last, record[2])
            elif index.register(record):
                kept += cost(record)
    finally:
        budget.give(sum(map(cost, records)) - kept)
    if first is not None and last is not None:
        index.chunks.append((first, offset, last))


def _scan_message(file: RecordFile, offset: int, length: int, index: Index) -> None:
    if length < MESSAGE.size:
        raise Damage(offset, f"a Message record of {length} bytes is too short", fatal=False)
    channel_id, sequence, log_time, publish_time = MESSAGE.unpack(file.read(offset + RECORD.size, MESSAGE.size, "a Message record"))
    index.count(channel_id, log_time, offset)
    index.loose.append(Loose(offset, length, channel_id, sequence, log_time, publish_time))
