"""Per-port statistics: counters on the hot path, percentiles on demand."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dyknow import Manager
from dyknow.stats import WINDOW, LatencySummary, PortCounters, summarize
from dyknow.testing import Sink, Source


def test_percentiles_are_nearest_rank_in_microseconds() -> None:
    samples = [i * 1000 for i in range(1, 101)]  # 1..100 us
    assert summarize(samples) == LatencySummary(100, 50.0, 90.0, 99.0, 100.0)
    assert summarize([]) == LatencySummary(0, 0.0, 0.0, 0.0, 0.0)
    assert summarize([7000]).p99_us == 7.0


def test_counters_keep_the_last_window_of_samples() -> None:
    counters = PortCounters()
    for i in range(WINDOW + 10):
        counters.arrived(nbytes=3, latency_ns=(i + 1) * 1000, hop_ns=500)
    counters.dropped += 2
    snapshot = counters.snapshot("in", "in", "a/b")
    assert (snapshot.messages, snapshot.bytes, snapshot.dropped) == (WINDOW + 10, 3 * (WINDOW + 10), 2)
    assert snapshot.latency.count == WINDOW and snapshot.latency.max_us == WINDOW + 10  # the oldest 10 are gone
    assert snapshot.hop.p50_us == 0.5
    assert snapshot.to_dict()["latency"]["count"] == WINDOW and snapshot.to_dict()["rejected"] == 0


def test_output_ports_report_no_latency() -> None:
    counters = PortCounters()
    counters.messages = 4
    assert counters.snapshot("out", "out", "x").to_dict() == {"direction": "out", "key": "x", "messages": 4, "bytes": 0, "unsized": 0, "dropped": 0}


def test_messages_whose_size_is_not_known_are_counted_as_unsized(make_manager: Callable[..., Manager]) -> None:
    """Between units of one manager a JSON value travels by reference, never encoded, so its size
    is not known: it is counted as unsized (not as 0 bytes); bytes and arrays are sized."""
    manager = make_manager()
    manager.spawn("publisher", "src", bindings={"out": "k/unsized"})
    manager.spawn("sink", "dst", bindings={"in": "k/unsized"})
    source, sink = manager.unit("src"), manager.unit("dst")
    assert isinstance(source, Source) and isinstance(sink, Sink)
    for payload in ({"celsius": 90.0}, [1, 2], b"12345678", np.zeros((2, 4), np.uint8)):
        source.emit(payload)
    sink.wait_for(4)
    ins = manager.get_statistics("dst").to_dict()["ports"]["in"]
    outs = manager.get_statistics("src").to_dict()["ports"]["out"]
    for port in (ins, outs):
        assert (port["messages"], port["unsized"], port["bytes"]) == (4, 2, 16), port
