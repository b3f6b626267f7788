"""The attachment rmw_zenoh puts on every message: sequence number, source timestamp, GID.

As rmw_zenoh's ``docs/design.md`` states it (``AttachmentData::serialize_to_zbytes`` writes it
with Zenoh's serializer): 8 bytes of sequence number (int64, little-endian), 8 bytes of source
timestamp (int64 nanoseconds since the UNIX epoch, little-endian), 1 byte of GID length (always
16) and the 16 bytes of the publisher's GID: 33 bytes in all. The length byte is a LEB128 varint
in Zenoh's serializer; a GID of 16 bytes keeps it one byte, and anything else is refused here.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from dyknow.errors import BindingError

__all__ = ["ATTACHMENT_SIZE", "GID_SIZE", "Attachment"]

#: The GID's length in bytes (RMW_GID_STORAGE_SIZE since Jazzy).
GID_SIZE = 16
#: The attachment's length in bytes.
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
_LAYOUT = struct.Struct("<qqB16s")


@dataclass(frozen=True, slots=True)
class Attachment:
    """rmw_zenoh's attachment: ``sequence_number``, ``source_timestamp_ns`` and ``gid``."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        """The 33 bytes on the wire."""
        if len(self.gid) != GID_SIZE:
            raise BindingError(f"a GID of {len(self.gid)} bytes", where="rmw_zenoh attachment", expected=f"{GID_SIZE} bytes")
        return _LAYOUT.pack(self.sequence_number, self.source_timestamp_ns, GID_SIZE, self.gid)

    @classmethod
    def decode(cls, data: bytes | None) -> Attachment:
        """Read the 33 bytes; raises :class:`BindingError` saying what is wrong."""
        if data is None:
            raise BindingError("no attachment", where="rmw_zenoh message", expected=f"an attachment of {ATTACHMENT_SIZE} bytes")
        if len(data) != ATTACHMENT_SIZE:
            raise BindingError(f"an attachment of {len(data)} bytes", where="rmw_zenoh message", expected=f"{ATTACHMENT_SIZE} bytes")
        seq, stamp, size, gid = _LAYOUT.unpack(data)
        if size != GID_SIZE:
            raise BindingError(f"a GID length of {size}", where="rmw_zenoh attachment", expected=str(GID_SIZE))
        return cls(seq, stamp, gid)
