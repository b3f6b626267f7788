"""dyknow.ros2.attachment against rmw_zenoh's documented layout (design.md, "Publishers": 8 bytes
of sequence number, 8 of source timestamp, little-endian int64, 1 byte of GID length, 16 of GID)
and against zenoh-ros2-sdk's own encoder and decoder, an implementation dyknow did not write."""

from __future__ import annotations

import pytest
from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment

from dyknow.errors import BindingError
from dyknow.ros2.attachment import ATTACHMENT_SIZE, Attachment

GID = bytes(range(16))


def test_layout_is_the_documented_one() -> None:
    data = Attachment(7, 1_700_000_000_123_456_789, GID).encode()
    assert ATTACHMENT_SIZE == 33 and len(data) == 33
    assert data[:8] == (7).to_bytes(8, "little")
    assert data[8:16] == (1_700_000_000_123_456_789).to_bytes(8, "little")
    assert data[16] == 16 and data[17:] == GID


def test_the_sdk_reads_ours_and_we_read_the_sdks() -> None:
    ours = Attachment(42, 1_234_567_890, GID)
    theirs = SdkAttachment.from_bytes(ours.encode())
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (42, 1_234_567_890, GID)
    assert Attachment.decode(SdkAttachment(sequence_id=3, timestamp_ns=99, gid=GID[::-1]).to_bytes()) == Attachment(3, 99, GID[::-1])


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        (None, "no attachment"),
        (b"", "0 bytes"),
        (bytes(32), "32 bytes"),
        (bytes(34), "34 bytes"),
        (bytes(16) + b"\x0f" + bytes(16), "GID length of 15"),
        (b"DK" + bytes(31), "GID length"),  # a dyknow header is no rmw_zenoh attachment
    ],
)
def test_malformed_attachments_are_refused(data: bytes | None, problem: str) -> None:
    with pytest.raises(BindingError, match=problem):
        Attachment.decode(data)


def test_a_gid_of_another_size_is_not_sent() -> None:
    with pytest.raises(BindingError, match="GID of 24 bytes"):
        Attachment(1, 1, bytes(24)).encode()  # Humble's RMW_GID_STORAGE_SIZE
