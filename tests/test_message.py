"""Messages and their wire encoding."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dyknow.message import HEADER, Message, PayloadError, check_payload, decode, encode


@pytest.mark.parametrize(
    "payload",
    [b"\x00\x01raw", "text é", {"x": [1, 2.5, None, True]}, [1, 2, 3], 42, None],
    ids=["bytes", "text", "dict", "list", "int", "none"],
)
def test_round_trip(payload: object) -> None:
    msg = Message(payload, 7, 1000, 2000, "a/b")
    data, attachment, encoding = encode(msg)
    back = decode(bytes(data), attachment, encoding, "a/b", 3000, 1)
    assert (back.payload, back.seq, back.origin_ns, back.send_ns, back.key) == (payload, 7, 1000, 2000, "a/b")


@pytest.mark.parametrize("dtype", ["uint8", "float32", ">i4", "complex64"])
def test_arrays_keep_dtype_and_shape(dtype: str) -> None:
    array = np.arange(2 * 3 * 4).astype(dtype).reshape(2, 3, 4)
    data, attachment, encoding = encode(Message(array[:, ::2], 1, 1, 1, "k"))  # non-contiguous view
    assert encoding == "application/x-dyknow-ndarray"
    back = decode(bytes(data), attachment, encoding, "k", 2, 1).payload
    assert back.dtype == np.dtype(dtype) and back.shape == (2, 2, 4)
    np.testing.assert_array_equal(back, array[:, ::2])


def test_plain_zenoh_samples_are_accepted() -> None:
    msg = decode(b'{"speed": 3}', None, "application/json", "car/speed", 555, 9)
    assert (msg.payload, msg.seq, msg.origin_ns, msg.send_ns) == ({"speed": 3}, 9, 555, 555)
    assert decode(b"hello", None, "text/plain", "k", 1, 1).payload == "hello"
    assert decode(b"\xff\xfe", None, "text/plain", "k", 1, 1).payload == b"\xff\xfe"
    assert decode(b"\x01\x02", b"not ours", "zenoh/bytes", "k", 1, 1).payload == b"\x01\x02"


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
        decode(b"x", bad_version, "", "k", 1, 1)
    assert json.loads(encode(Message({"a": 1}, 1, 1, 1, "k"))[0]) == {"a": 1}
