"""Messages and their wire encoding."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dyknow.message import CLOCK_ID, HEADER, HEADER_V1, HEADER_V2, Message, PayloadError, check_payload, decode, encode, reheader


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
    assert len(attachment) == HEADER.size == 41 and HEADER_V2.size == 40 and HEADER_V1.size == 28 and attachment[:2] == b"DK"
    assert encoding == "application/octet-stream"


def _parse_header(attachment: bytes) -> dict[str, int]:
    """The header taken apart as the module's documentation lays it out (written from its table,
    not from the module's code)."""
    little = "little"
    return {
        "version": attachment[2],
        "kind": attachment[3],
        "seq": int.from_bytes(attachment[4:12], little),
        "origin_ns": int.from_bytes(attachment[12:20], little, signed=True),
        "send_ns": int.from_bytes(attachment[20:28], little, signed=True),
        "source": int.from_bytes(attachment[28:32], little),
        "origin_clock": int.from_bytes(attachment[32:36], little),
        "send_clock": int.from_bytes(attachment[36:40], little),
        "forwards": attachment[40],
    }


def test_the_header_is_what_the_documentation_says() -> None:
    """Every field at its documented offset; a version-1 header (the first 28 bytes) still reads,
    with no source and no clocks; a message made here carries this process's clock."""
    msg = Message(b"x", 2**40 + 5, -7, 1_800_000_000_000_000_000, "k", source=0xDEADBEEF, origin_clock=17, send_clock=CLOCK_ID, forwards=5)
    _, attachment, _ = encode(msg)
    assert attachment[:2] == b"DK" and _parse_header(attachment) == {
        "version": 3, "kind": 0, "forwards": 5, "seq": 2**40 + 5, "origin_ns": -7, "send_ns": 1_800_000_000_000_000_000,
        "source": 0xDEADBEEF, "origin_clock": 17, "send_clock": CLOCK_ID,
    }  # fmt: skip
    assert decode(b"x", attachment, "k").forwards == 5
    for payload, kind in (("text", 1), ({"j": 1}, 2), (np.zeros(3, np.uint8), 3)):  # forwards beside every kind
        back = _parse_header(encode(Message(payload, 1, 1, 1, "k", forwards=63))[1])
        assert (back["kind"], back["forwards"]) == (kind, 63)
    v2 = attachment[:2] + bytes([2]) + attachment[3:40]  # version 2: the first 40 bytes, no forwards
    assert (decode(b"x", v2, "k").payload, decode(b"x", v2, "k").forwards, decode(b"x", v2, "k").source) == (b"x", 0, 0xDEADBEEF)
    for payload, kind in (("text", 1), ({"j": 1}, 2), (np.zeros(3, np.uint8), 3)):
        assert _parse_header(encode(Message(payload, 1, 1, 1, "k"))[1])["kind"] == kind
    assert Message(b"x", 1, 1, 1, "k").origin_clock == CLOCK_ID != 0
    old = b"DK" + bytes([1, 0]) + (9).to_bytes(8, "little") + (10).to_bytes(8, "little") + (11).to_bytes(8, "little")
    back = decode(b"old", old, "k")
    assert (back.payload, back.seq, back.origin_ns, back.send_ns, back.source, back.origin_clock, back.send_clock) == (b"old", 9, 10, 11, 0, 0, 0)
    array = np.arange(6, dtype="<i2").reshape(2, 3)
    data, attachment, _ = encode(Message(array, 1, 1, 1, "k"))
    ndim, dlen = attachment[41], attachment[42]
    assert (ndim, attachment[43 : 43 + dlen]) == (2, b"<i2")
    assert [int.from_bytes(attachment[43 + dlen + 8 * i : 51 + dlen + 8 * i], "little") for i in range(2)] == [2, 3]
    old_array = old + attachment[41:]
    old_array = old_array[:3] + bytes([3]) + old_array[4:]
    np.testing.assert_array_equal(decode(bytes(data), old_array, "k").payload, array)


def test_bad_payloads_are_refused_clearly() -> None:
    with pytest.raises(PayloadError, match="cannot publish a payload of type set"):
        check_payload({1, 2})
    with pytest.raises(PayloadError, match="cannot encode the payload as JSON"):
        encode(Message({"x": object()}, 1, 1, 1, "k"))
    with pytest.raises(PayloadError, match="cannot send an array of dtype object"):
        encode(Message(np.array([object()]), 1, 1, 1, "k"))
    _, attachment, _ = encode(Message(b"x", 1, 1, 1, "k"))
    bad_version = attachment[:2] + bytes([99]) + attachment[3:]
    with pytest.raises(PayloadError, match="header version 99 of 41 bytes"):
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
    raw = Message(b"data", 7, 111, 222, "k", 4, source=41, origin_clock=5, send_clock=6, forwards=2)
    _, header, _ = encode(raw)
    rewritten = reheader(header, 8, 333, 42)
    assert rewritten is not None
    attachment, origin_ns, origin_clock, sent_ns, sent_clock, source, seq, encoding, forwards = rewritten
    assert (origin_ns, origin_clock, sent_ns, sent_clock, source, seq, encoding, forwards) == (111, 5, 222, 6, 41, 7, "application/octet-stream", 2)
    msg = decode(b"data", attachment, "k")
    assert (msg.payload, msg.seq, msg.origin_ns, msg.send_ns, msg.forwards) == (b"data", 8, 111, 333, 3)  # one more forward
    assert (msg.source, msg.origin_clock, msg.send_clock) == (42, 5, CLOCK_ID)  # the origin's clock goes on; the send is ours
    for payload in ("text", {"json": 1}, np.zeros((2, 2), dtype=np.uint8)):
        _, header, _ = encode(Message(payload, 1, 1, 1, "k"))
        assert reheader(header, 2, 2, 1) is None, payload
    assert reheader(HEADER.pack(b"DK", 9, 0, 1, 1, 1, 1, 1, 1, 0), 2, 2, 1) is None
    assert reheader(HEADER_V1.pack(b"DK", 1, 0, 1, 1, 1), 2, 2, 1) is None  # an older version: decoded first
    assert reheader(HEADER_V2.pack(b"DK", 2, 0, 1, 1, 1, 1, 1, 1), 2, 2, 1) is not None  # version 2: no forwards yet
    assert reheader(header_of_bytes := HEADER.pack(b"DK", 3, 0, 1, 1, 1, 1, 1, 1, 0), 2, 2, 1) is not None
    assert reheader(header_of_bytes + b"extra", 2, 2, 1) is None


def _parse_parts(data: bytes, attachment: bytes) -> tuple[object, list[tuple[str, str, list[int], bytes]]]:
    """A payload of kind 4 taken apart as the module's documentation lays it out (written from
    its text, not from the module's code): the JSON text, and each array's path, dtype, shape
    and bytes."""
    at, count = 42, attachment[41]
    arrays = []
    for _ in range(count):
        length = int.from_bytes(attachment[at : at + 2], "little")
        path = attachment[at + 2 : at + 2 + length].decode()
        at += 2 + length
        ndim, dlen = attachment[at], attachment[at + 1]
        dtype = attachment[at + 2 : at + 2 + dlen].decode()
        at += 2 + dlen
        shape = [int.from_bytes(attachment[at + 8 * i : at + 8 * i + 8], "little") for i in range(ndim)]
        at += 8 * ndim
        arrays.append((path, dtype, shape))
    sizes = [int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize for _, dtype, shape in arrays]
    end = len(data) - sum(sizes)
    parts, offset = [], end
    for (path, dtype, shape), size in zip(arrays, sizes, strict=True):
        parts.append((path, dtype, shape, data[offset : offset + size]))
        offset += size
    return json.loads(data[:end]), parts


def test_json_with_arrays_keeps_them_binary_as_documented() -> None:
    """A ROS 2 message's payload: JSON-like, with numpy arrays inside (any depth, any dtype, a
    key to escape); the arrays travel as their bytes after the JSON text, not as JSON lists."""
    cloud = np.arange(3000, dtype=np.uint8)
    grid = np.arange(12, dtype=">i4").reshape(3, 4)[:, ::2]  # big-endian, not contiguous
    payload = {
        "header": {"frame_id": "lidar"},
        "width": 1000,
        "data": cloud,
        "fields": [{"a/b~c": grid}, {"empty": np.zeros((0, 3), np.float32)}],
    }
    data, attachment, encoding = encode(Message(payload, 3, 4, 5, "k"))
    assert encoding == "application/x-dyknow-json-ndarrays" and _parse_header(attachment)["kind"] == 4
    assert len(data) < len(b'{"header":{"frame_id":"lidar"},"width":1000}') + 3000 + 24 + 100  # bytes, not 3,000 numbers in text
    text, parts = _parse_parts(bytes(data), attachment)
    assert text == {"header": {"frame_id": "lidar"}, "width": 1000, "data": None, "fields": [{"a/b~c": None}, {"empty": None}]}
    assert [(p, d, s) for p, d, s, _ in parts] == [
        ("/data", "|u1", [3000]),
        ("/fields/0/a~1b~0c", ">i4", [3, 2]),
        ("/fields/1/empty", "<f4", [0, 3]),
    ]
    assert parts[0][3] == cloud.tobytes() and parts[1][3] == np.ascontiguousarray(grid).tobytes()
    back = decode(bytes(data), attachment, "k")
    assert back.wire is None and back.nbytes == len(data)  # a mutable value: never forwarded as its wire form
    got = back.payload
    assert got["header"] == {"frame_id": "lidar"} and got["width"] == 1000
    for mine, theirs in (
        (got["data"], cloud),
        (got["fields"][0]["a/b~c"], grid),
        (got["fields"][1]["empty"], payload["fields"][1]["empty"]),
    ):
        assert mine.dtype == theirs.dtype and mine.shape == theirs.shape and np.array_equal(mine, theirs) and not mine.flags.writeable


def test_past_255_arrays_the_smallest_go_as_lists() -> None:
    payload = [np.full(i + 1, i, np.int16) for i in range(300)]
    data, attachment, _ = encode(Message(payload, 1, 1, 1, "k"))
    assert attachment[41] == 255
    back = decode(bytes(data), attachment, "k").payload
    assert back[0] == [0] and isinstance(back[44], list) and isinstance(back[45], np.ndarray)
    assert all(np.array_equal(np.asarray(b), a) for a, b in zip(payload, back, strict=True))


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        (lambda d, a: (d, a[:42] + (5).to_bytes(2, "little") + b"/nope" + a[49:]), "leads nowhere"),
        (lambda d, a: (d, a[:42] + (2).to_bytes(2, "little") + b"/w" + a[49:]), "not null"),
        (lambda d, a: (d[-10:], a), "arrays of 3000 bytes in 10"),
        (lambda d, a: (d, a.replace(b"|u1", b"|O8")), "dtype object|malformed"),
        (lambda d, a: (d, a[:-4]), "malformed"),
        (lambda d, a: (b"[" + d[1:], a), "does not parse"),
    ],
    ids=["nowhere", "not-null", "too-short", "objects", "truncated", "not-json"],
)
def test_json_with_arrays_from_the_network_is_checked(change: object, problem: str) -> None:
    data, attachment, _ = encode(Message({"data": np.zeros(3000, np.uint8), "w": 1}, 1, 1, 1, "k"))
    bad_data, bad_attachment = change(bytes(data), attachment)  # type: ignore[operator]
    with pytest.raises(PayloadError, match=problem):
        decode(bad_data, bad_attachment, "k")


def _loaded(load: Any, raw: bytes) -> tuple[str, Any]:
    try:
        value = load(raw)
    except (ValueError, RecursionError) as exc:  # (JSONDecodeError and UnicodeDecodeError are ValueErrors)
        return type(exc).__name__, str(exc)
    return "value", json.dumps(value, sort_keys=True)  # (NaN == NaN is false: compare the texts)


_JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=12,
)


@settings(max_examples=600, deadline=None)
@given(
    st.one_of(
        st.binary(max_size=40),  # anything a peer may send
        st.builds(lambda v, a, b: (a + json.dumps(v, ensure_ascii=False) + b).encode(), _JSON_VALUES, st.sampled_from(["", " ", "\n\t"]), st.sampled_from(["", " ", "x", " 1", "\r\n"])),
        st.builds(lambda v, enc: json.dumps(v).encode(enc), _JSON_VALUES, st.sampled_from(["utf-8-sig", "utf-16", "utf-16-le", "utf-32-be"])),
    )
)
def test_a_message_s_json_text_reads_as_json_loads_reads_it(raw: bytes) -> None:
    """The decoder's quicker JSON reading (json's scanner without json.loads' Python steps) gives
    what json.loads gives, value or error, for any bytes: valid texts with spaces around and
    trailing data, the encodings json.loads guesses (byte order marks, UTF-16 and 32), and random
    bytes (invalid UTF-8, lone surrogates, NaN)."""
    from dyknow.message import json_text

    assert _loaded(json_text, raw) == _loaded(json.loads, raw)
