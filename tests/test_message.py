"""Messages and their wire encoding."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dyknow.message import HEADER, Message, PayloadError, check_payload, decode, encode, reheader


@pytest.mark.parametrize(
    "payload",
    [b"\x00\x01raw", "text é", {"x": [1, 2.5, None, True]}, [1, 2, 3], 42, None],
    ids=["bytes", "text", "dict", "list", "int", "none"],
)
def test_round_trip(payload: object) -> None:
    msg = Message(payload, 7, 1000, 2000, "a/b")
    data, attachment, encoding = encode(msg)
    back = decode(bytes(data), attachment, "a/b")
    assert (back.payload, back.seq, back.origin_ns, back.send_ns, back.key) == (payload, 7, 1000, 2000, "a/b")


@pytest.mark.parametrize("dtype", ["uint8", "float32", ">i4", "complex64"])
def test_arrays_keep_dtype_and_shape(dtype: str) -> None:
    array = np.arange(2 * 3 * 4).astype(dtype).reshape(2, 3, 4)
    data, attachment, encoding = encode(Message(array[:, ::2], 1, 1, 1, "k"))  # non-contiguous view
    assert encoding == "application/x-dyknow-ndarray"
    back = decode(bytes(data), attachment, "k").payload
    assert back.dtype == np.dtype(dtype) and back.shape == (2, 2, 4)
    np.testing.assert_array_equal(back, array[:, ::2])


def test_plain_zenoh_samples_are_accepted() -> None:
    msg = decode(b'{"speed": 3}', None, "car/speed", encoding="application/json", arrival_ns=555, seq=9)
    assert (msg.payload, msg.seq, msg.origin_ns, msg.send_ns, msg.wire) == ({"speed": 3}, 9, 555, 555, None)
    assert decode(b"hello", None, "k", encoding="text/plain").payload == "hello"
    assert decode(b"\xff\xfe", None, "k", encoding="text/plain").payload == b"\xff\xfe"
    assert decode(b"\x01\x02", b"not ours", "k", encoding="zenoh/bytes").payload == b"\x01\x02"


def test_header_layout_is_documented_size() -> None:
    _, attachment, encoding = encode(Message(b"x", 1, 2, 3, "k"))
    assert len(attachment) == HEADER.size == 28 and attachment[:2] == b"DK"
    assert encoding == "application/octet-stream"


def test_bad_payloads_are_refused_clearly() -> None:
    with pytest.raises(PayloadError, match="cannot publish a payload of type set"):
        check_payload({1, 2})
    with pytest.raises(PayloadError, match="cannot encode the payload as JSON"):
        encode(Message({"x": object()}, 1, 1, 1, "k"))
    with pytest.raises(PayloadError, match="cannot send an array of dtype object"):
        encode(Message(np.array([object()]), 1, 1, 1, "k"))
    _, attachment, _ = encode(Message(b"x", 1, 1, 1, "k"))
    bad_version = attachment[:2] + bytes([99]) + attachment[3:]
    with pytest.raises(PayloadError, match="header version 99"):
        decode(b"x", bad_version, "k")
    assert json.loads(encode(Message({"a": 1}, 1, 1, 1, "k"))[0]) == {"a": 1}


class Buffer:
    """Stands in for the transport's own buffer type (anything with to_bytes())."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


def test_forwarded_payloads_reuse_their_wire_form() -> None:
    array = np.arange(12, dtype=np.float32).reshape(3, 4)
    data, attachment, _ = encode(Message(array, 1, 10, 20, "k"))
    buffer = Buffer(bytes(data))
    received = decode(buffer, attachment, "k")
    assert not received.payload.flags.writeable
    forwarded = Message(received.payload, 5, received.origin_ns, 30, "k2", wire=received.wire)
    data2, attachment2, encoding2 = encode(forwarded)
    assert data2 is buffer  # the same transport buffer goes out again: no copy, no re-encoding
    again = decode(bytes(data2.to_bytes()), attachment2, "k2")
    assert (again.seq, again.origin_ns, again.send_ns) == (5, 10, 30)
    np.testing.assert_array_equal(again.payload, array)
    assert decode(Buffer(b'{"a": 1}'), encode(Message({"a": 1}, 1, 1, 1, "k"))[1], "k").wire is None  # JSON is mutable


def test_reheader_rewrites_a_bytes_header_for_the_next_hop_and_nothing_else() -> None:
    """A relay passes raw bytes on under a header with its own seq and send time, the origin
    kept; any other kind (or version) is left to decoding, which checks it."""
    raw = Message(b"data", 7, 111, 222, "k", 4)
    _, header, _ = encode(raw)
    rewritten = reheader(header, 8, 333)
    assert rewritten is not None
    attachment, origin_ns, sent_ns, encoding = rewritten
    assert (origin_ns, sent_ns, encoding) == (111, 222, "application/octet-stream")
    msg = decode(b"data", attachment, "k")
    assert (msg.payload, msg.seq, msg.origin_ns, msg.send_ns) == (b"data", 8, 111, 333)
    for payload in ("text", {"json": 1}, np.zeros((2, 2), dtype=np.uint8)):
        _, header, _ = encode(Message(payload, 1, 1, 1, "k"))
        assert reheader(header, 2, 2) is None, payload
    assert reheader(HEADER.pack(b"DK", 9, 0, 1, 1, 1), 2, 2) is None
    assert reheader(header_of_bytes := HEADER.pack(b"DK", 1, 0, 1, 1, 1), 2, 2) is not None
    assert reheader(header_of_bytes + b"extra", 2, 2) is None
