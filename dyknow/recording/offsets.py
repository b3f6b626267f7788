"""Times of other clocks in a recording: each origin time as stamped, and the offsets to correct it.

A message's ``log_time`` is its origin time as its source stamped it, on the source's clock (the
header's ``origin_clock``, :mod:`dyknow.message`): the recorder keeps it so. A message stamped by
another process's clock goes to a channel whose metadata names that clock
(:data:`CLOCK_METADATA`: 8 hex digits; one key's messages from two clocks go to two channels);
the recorder's own clock's channels have none. The offsets the recorder knew
(:mod:`dyknow.clocks`: the process's table, or its own tracker's) go on a channel of their own,
:data:`CLOCKS_TOPIC`, one JSON record per message::

    {"clock": "1b0a53c9", "offset_ns": 250000123, "uncertainty_ns": 150000, "at_ns": 1780000000000000000}

``offset_ns`` is that clock minus the recorder's, ``uncertainty_ns`` how far it may be off, both
at ``at_ns`` of the recorder's clock (the record's log time too); both null when the recorder did
not know the clock's offset. The recorder's own clock gets a record with offset 0 before the
first record of another. A clock's record is written before its first message, and again when
its offset changed by more than its uncertainty since the last record, or became known or
unknown; at most :data:`MAX_CLOCKS` clocks other than the recorder's are kept apart (the
messages of any more go to channels of clock ``00000000``, which is never known).

A replay corrects an origin by the record of its clock that was current then (the last one
before the corrected time, or the first): ``origin - offset``, a time of the recording's clock;
an origin whose clock's offset was not known stays as stamped, and is marked so
(:meth:`dyknow.recording.Player.corrected_origin` returns None).
"""

from __future__ import annotations

import bisect
import json
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Final

from dyknow.errors import RecordingError

__all__ = ["CLOCKS_SCHEMA", "CLOCKS_TOPIC", "CLOCK_METADATA", "MAX_CLOCKS", "ClockRecord", "OffsetLog", "Offsets"]

#: The topic of the clock records.
CLOCKS_TOPIC: Final = "dyknow/clocks"
#: The channel metadata that names the clock of its messages' origin times (8 hex digits).
CLOCK_METADATA: Final = "dyknow.origin_clock"
#: Clocks other than the recorder's that a recording keeps apart.
MAX_CLOCKS: Final = 64
#: The JSON schema of a clock record (for MCAP tools).
CLOCKS_SCHEMA: Final = {
    "title": CLOCKS_TOPIC,
    "type": "object",
    "properties": {
        "clock": {"type": "string"},
        "offset_ns": {"type": ["integer", "null"]},
        "uncertainty_ns": {"type": ["integer", "null"]},
        "at_ns": {"type": "integer"},
    },
}
_MAX_RECORD_BYTES: Final = 1024
_LIMIT: Final = 1 << 63


@dataclass(frozen=True, slots=True)
class ClockRecord:
    """The offset of ``clock`` from the recorder's (ns; None: not known) at ``at_ns`` of the recorder's clock."""

    clock: int
    offset_ns: int | None
    uncertainty_ns: int | None
    at_ns: int

    def to_json(self) -> bytes:
        """The record as it is stored."""
        return json.dumps(
            {"clock": f"{self.clock:08x}", "offset_ns": self.offset_ns, "uncertainty_ns": self.uncertainty_ns, "at_ns": self.at_ns}
        ).encode()

    @classmethod
    def from_json(cls, data: bytes, where: str) -> ClockRecord:
        """A stored record; :class:`RecordingError` naming ``where`` when it is not one."""
        expected = 'a JSON object {"clock": 8 hex digits, "offset_ns": int or null, "uncertainty_ns": int or null, "at_ns": int}'
        if len(data) > _MAX_RECORD_BYTES:
            raise RecordingError(f"a clock record of {len(data)} bytes", where=where, expected=f"at most {_MAX_RECORD_BYTES} bytes")
        try:
            raw = json.loads(data)
            clock, offset, uncertainty, at = raw["clock"], raw["offset_ns"], raw["uncertainty_ns"], raw["at_ns"]
            if not (isinstance(clock, str) and len(clock) == 8):
                raise ValueError(f"clock {clock!r}")
            number = int(clock, 16)
            if (offset is None) != (uncertainty is None) or not all(_int(v) for v in (offset, uncertainty) if v is not None) or not _int(at):
                raise ValueError("times that are not integers")
            if uncertainty is not None and uncertainty < 0:
                raise ValueError(f"uncertainty {uncertainty}")
        except (ValueError, TypeError, KeyError, RecursionError) as exc:
            raise RecordingError(f"a malformed clock record ({str(exc)[:100]}): {data[:120]!r}", where=where, expected=expected) from exc
        return cls(number, offset, uncertainty, at)


def _int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and -_LIMIT <= value < _LIMIT


class OffsetLog:
    """The recorder's side: which clock records to write, as messages of other clocks come."""

    def __init__(self, own: int) -> None:
        self.own = own
        self._last: dict[int, ClockRecord] = {}

    def clock_of(self, clock: int) -> int:
        """The clock a message's channel names: its own, or 0 past :data:`MAX_CLOCKS` clocks."""
        if clock == self.own or clock in self._last or len(self._last) < MAX_CLOCKS:
            return clock
        return 0

    def note(self, clock: int, offset_ns: int | None, uncertainty_ns: int | None, now_ns: int) -> list[ClockRecord]:
        """The records to write before a message of ``clock`` (another's), whose offset is now as given."""
        if clock == self.own:
            return []
        out = []
        if not self._last:
            out.append(ClockRecord(self.own, 0, 0, now_ns))
        if clock == 0:  # (never known: a header without a clock, or past MAX_CLOCKS)
            offset_ns = uncertainty_ns = None
        last = self._last.get(clock)
        changed = (
            last is None
            or (offset_ns is None) != (last.offset_ns is None)
            or (offset_ns is not None and last.offset_ns is not None and abs(offset_ns - last.offset_ns) > (uncertainty_ns or 0))
        )
        if changed:
            record = ClockRecord(clock, offset_ns, uncertainty_ns if offset_ns is not None else None, now_ns)
            self._last[clock] = record
            out.append(record)
        return out


class Offsets:
    """The player's side: the offsets of a recording's clocks, to correct origin times by."""

    def __init__(self, records: Iterable[ClockRecord]) -> None:
        by_clock: dict[int, list[ClockRecord]] = {}
        for record in records:
            by_clock.setdefault(record.clock, []).append(record)
        self._records = {clock: sorted(found, key=lambda r: r.at_ns) for clock, found in by_clock.items()}
        self._times = {clock: [r.at_ns for r in found] for clock, found in self._records.items()}

    def __bool__(self) -> bool:
        return bool(self._records)

    def clocks(self) -> list[int]:
        """The clocks the recording has records of."""
        return sorted(self._records)

    def record(self, clock: int, origin_ns: int) -> ClockRecord | None:
        """The record of ``clock`` current when a message was stamped ``origin_ns`` on it."""
        found = self._records.get(clock)
        if not found:
            return None
        first = next((r.offset_ns for r in found if r.offset_ns is not None), 0)
        i = bisect.bisect_right(self._times[clock], origin_ns - first) - 1  # (the records are on the recorder's clock)
        return found[max(0, i)]

    def corrected(self, clock: int, origin_ns: int) -> tuple[int, int] | None:
        """``origin_ns`` of ``clock`` on the recording's clock and its uncertainty (ns), or None when not known."""
        record = self.record(clock, origin_ns)
        if record is None or record.offset_ns is None or record.uncertainty_ns is None:
            return None
        return origin_ns - record.offset_ns, record.uncertainty_ns
