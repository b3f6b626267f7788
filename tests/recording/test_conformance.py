"""The official MCAP conformance suite (shared/data/mcap/conformance, see SOURCES.md §1).

For each of the 416 variants the reader's records, in file order with chunks flattened and
MessageIndex records left out, must equal the variant's ``.json`` exactly (the suite's *streamed
reader* test). The player must deliver exactly the ``.json``'s messages sorted by log time, ties in
file order (the *indexed reader* order), through the same code that feeds Zenoh. A few variants
also go through real Zenoh sessions end to end.
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
from pathlib import Path
from typing import Any

import pytest

from dyknow.message import Message
from dyknow.recording import Player, RecordedMessage, Recording, key_for_topic
from dyknow.transport import Session, make_config
from tests.conftest import REPO, free_port

DATA = Path(os.environ.get("DYKNOW_DATA", REPO.parent / "shared" / "data"))
SUITE = DATA / "mcap" / "conformance"
VARIANTS = sorted(p.relative_to(SUITE).as_posix()[: -len(".mcap")] for p in SUITE.glob("*/*.mcap")) or ["(missing)"]


@pytest.fixture
def suite(data_dir: Path) -> Path:
    root = data_dir / "mcap" / "conformance"
    if not any(root.glob("*/*.mcap")):
        pytest.fail(f"no conformance files under {root}")
    return root


def expected(root: Path, variant: str) -> dict[str, Any]:
    return json.loads((root / f"{variant}.json").read_text())


def serialize(value: Any) -> Any:
    """A record field the way the suite's .json writes it: integers and bytes as decimal strings."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return [str(b) for b in bytes(value)]
    if isinstance(value, dict):
        return {str(k): str(v) for k, v in value.items()}
    if isinstance(value, int):
        return str(value)
    return value


def as_json(record: Any) -> dict[str, Any]:
    fields = sorted((f.name, serialize(getattr(record, f.name))) for f in dataclasses.fields(record))
    return {"type": type(record).__name__, "fields": [list(f) for f in fields]}


def expected_messages(spec: dict[str, Any]) -> list[tuple[str, int, int, int, bytes]]:
    """The .json's messages as (topic, sequence, log_time, publish_time, data), stably sorted by log time."""
    topics: dict[str, str] = {}
    messages = []
    for record in spec["records"]:
        fields = dict(record["fields"])
        if record["type"] == "Channel":
            topics[fields["id"]] = fields["topic"]
        elif record["type"] == "Message":
            data = bytes(int(b) for b in fields["data"])
            messages.append((topics[fields["channel_id"]], int(fields["sequence"]), int(fields["log_time"]), int(fields["publish_time"]), data))
    return sorted(messages, key=lambda m: m[2])


def test_the_suite_is_complete(suite: Path) -> None:
    variants = sorted(p.relative_to(suite).as_posix() for p in suite.glob("*/*.mcap"))
    assert len(variants) == 416
    assert {v.split("/")[0] for v in variants} == {"NoData", "OneAttachment", "OneMessage", "OneMetadata", "OneSchemalessMessage", "TenMessages"}
    assert all((suite / v).with_suffix(".json").is_file() for v in variants)


@pytest.mark.parametrize("variant", VARIANTS)
def test_streamed_records_match_the_suite(suite: Path, variant: str) -> None:
    spec = expected(suite, variant)
    with Recording(suite / f"{variant}.mcap") as recording:
        records = [as_json(r) for r in recording.records()]
    assert records == spec["records"]


@pytest.mark.parametrize("variant", VARIANTS)
def test_player_delivers_exactly_the_suites_messages(suite: Path, variant: str) -> None:
    spec = expected(suite, variant)
    want = expected_messages(spec)
    delivered: list[tuple[Message, RecordedMessage]] = []
    with Player(suite / f"{variant}.mcap", rate=float("inf")) as player:
        count = player.play(lambda msg, record: delivered.append((msg, record)))
        info = player.info
    got = [(r.topic, r.sequence, r.log_time_ns, r.publish_time_ns, r.data) for _, r in delivered]
    assert got == want
    assert count == len(want) == info.message_count
    # what would be published: the file's sequence and log time as the header, the data as payload
    assert [(m.key, m.seq, m.origin_ns, m.payload) for m, _ in delivered] == [(key_for_topic(t), s, lt, d) for t, s, lt, _, d in want]
    # files with statistics, chunk indexes and repeated channels are read through the summary;
    # every other variant through a scan of the file
    features = set(spec["meta"]["variant"]["features"])
    indexable = "st" in features and (not want or {"ch", "chx", "rch"} <= features)
    assert info.indexed == indexable


@pytest.mark.parametrize("variant", ["TenMessages/TenMessages-ch-chx-mx-pad-rch-rsh-st-sum", "TenMessages/TenMessages", "OneSchemalessMessage/OneSchemalessMessage-ch-pad"])
def test_replay_through_zenoh_end_to_end(suite: Path, variant: str) -> None:
    want = expected_messages(expected(suite, variant))
    port = free_port()
    received: list[Message] = []
    all_in = threading.Event()

    def on_message(msg: Message) -> None:
        received.append(msg)
        if len(received) == len(want):
            all_in.set()

    with Session(make_config(listen=[f"tcp/127.0.0.1:{port}"])) as session, session.declare_subscriber("**", on_message):
        with Player(suite / f"{variant}.mcap", rate=float("inf")) as player:
            published = player.publish(connect=[f"tcp/127.0.0.1:{port}"], wait_s=10.0)
        assert published == len(want)
        assert all_in.wait(10.0), f"received {len(received)} of {len(want)}"
    assert [(m.key, m.seq, m.origin_ns, m.payload) for m in received] == [(key_for_topic(t), s, lt, d) for t, s, lt, _, d in want]
