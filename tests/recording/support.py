"""Helpers shared by the recording tests: the test files, reading and writing MCAP, waiting."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from dyknow.message import Message
from dyknow.recording import Player, RecordedMessage
from dyknow.transport import Publisher
from tests.conftest import REPO, wait_until

SPECS = REPO / "specs" / "recording.xml"
MIXED = REPO / "tests" / "mcap" / "units.xml"
FOREIGN = REPO / "tests" / "mcap" / "foxglove-protobuf.mcap"
INF = float("inf")


def official(path: Path) -> tuple[Any, list[tuple[Any, Any, Any]]]:
    """The summary and (schema, channel, message) triples as the official mcap reader sees them."""
    with open(path, "rb") as file:
        reader = make_reader(file, validate_crcs=True)
        return reader.get_summary(), list(reader.iter_messages(log_time_order=False))


def wait_matched(publisher: Publisher, timeout_s: float = 10.0) -> None:
    """Wait until a subscriber in another session matches ``publisher``."""
    wait_until(lambda: publisher.matched, f"a subscriber for {publisher.key}", timeout_s)


def same_payload(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and bool((a == b).all())
    return type(a) is type(b) and a == b


def real(data_dir: Path, name: str) -> Path:
    return data_dir / "mcap" / "real" / name


def play_all(path: Path, **kwargs: Any) -> list[tuple[Message, RecordedMessage]]:
    with Player(path, rate=kwargs.pop("rate", INF), **kwargs) as player:
        out: list[tuple[Message, RecordedMessage]] = []
        player.play(lambda msg, record: out.append((msg, record)))
    return out


def write_mcap(path: Path, topics: dict[str, tuple[str, str, str, bytes]], messages: list[tuple[str, int, bytes]]) -> Path:
    """A file from the official writer: topics map to (message encoding, schema name, schema encoding, schema data)."""
    with open(path, "wb") as file:
        writer = Writer(file, compression=CompressionType.NONE)
        writer.start(profile="", library="test")
        channels = {}
        for topic, (encoding, schema_name, schema_encoding, schema_data) in topics.items():
            schema_id = writer.register_schema(schema_name, schema_encoding, schema_data) if schema_name else 0
            channels[topic] = writer.register_channel(topic, encoding, schema_id)
        for i, (topic, log_time, data) in enumerate(messages):
            writer.add_message(channels[topic], log_time=log_time, data=data, publish_time=log_time, sequence=i)
        writer.finish()
    return path
