"""Per-port statistics: counters on the hot path, percentiles on demand."""

from __future__ import annotations

from dyknow.stats import WINDOW, LatencySummary, PortCounters, summarize


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
    assert counters.snapshot("out", "out", "x").to_dict() == {"direction": "out", "key": "x", "messages": 4, "bytes": 0, "dropped": 0}
