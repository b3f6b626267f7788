"""dyknow.metrics: a manager's figures in one snapshot (get_metrics, dyknow top), and scraped by
Prometheus's own text parser from --metrics-port (loopback by default)."""

from __future__ import annotations

import logging
import os
import socket
import threading
import urllib.error
import urllib.request
from collections.abc import Callable

import pytest
from prometheus_client.parser import text_string_to_metric_families

from dyknow import Client, Limits, Manager
from dyknow.metrics import BUCKETS_S, MAX_CONNECTIONS, MetricsExporter
from dyknow.resources import specs_dir
from dyknow.testing import SCENARIO_SPECS, Sink
from tests.conftest import ManagerProcess, free_port, run_cli, wait_until


def _scrape(url: str) -> dict[str, list[tuple[str, dict[str, str], float]]]:
    """metric family -> [(sample name, labels, value)], parsed by prometheus_client's parser."""
    text = urllib.request.urlopen(url, timeout=10).read().decode()
    found: dict[str, list[tuple[str, dict[str, str], float]]] = {}
    for family in text_string_to_metric_families(text):  # (a counter's samples come as a family of their own, NAME_total)
        found.setdefault(family.name.removesuffix("_total"), []).extend((s.name, s.labels, s.value) for s in family.samples)
    return found


def _series(url: str) -> set[tuple[str, frozenset[tuple[str, str]]]]:
    """Every series a scrape serves: (sample name, labels)."""
    return {(name, frozenset(labels.items())) for samples in _scrape(url).values() for name, labels, _ in samples}


def test_get_metrics_is_every_unit_in_one_call(manager: Manager) -> None:
    manager.spawn("periodic-source", "src", params={"rate_hz": 100}, bindings={"out": "m/a"})
    manager.spawn("relay", "r1", bindings={"in": "m/a"})
    wait_until(lambda: manager.get_statistics("r1").ports[0].messages >= 20, "messages through the relay")
    with Client(manager.name, connect=manager.endpoints) as client:
        snap = client.call_manager(manager.name, "get_metrics", {})
    assert snap["manager"] == manager.name and snap["cpu_s"] > 0 and snap["threads"] > 1
    units = {u["name"]: u for u in snap["units"]}
    assert set(units) == {"src", "r1"} and units["r1"]["ports"]["in"]["queued"] >= 0
    assert units["r1"]["ports"]["in"]["messages"] >= 20 and units["r1"]["ports"]["in"]["hop"]["count"] >= 20
    assert "traceback" not in units["r1"]


def test_prometheus_scrapes_rates_drops_hops_adaptations_and_verdicts() -> None:
    with Manager("robot", specs=[SCENARIO_SPECS], ontology=[specs_dir() / "dyknow.ttl"], dwell_s=0.2) as robot:
        with MetricsExporter(robot.metrics, 0) as exporter:
            assert exporter.url.startswith("http://127.0.0.1:")
            monitor = robot.monitor("historically[0, 1s] BallTrack(field).tracked > 0")
            robot.spawn("consumer", "verdicts", bindings={"in": monitor})
            first = _scrape(exporter.url)  # the metrics see the monitor from here on
            sink = robot.unit("verdicts")
            assert isinstance(sink, Sink) and sink.wait_for(3)
            robot.request("BallTrack(field)", require=["BallTrack(field).camera == 3"])  # moves the track: an adaptation
            wait_until(lambda: any(e.cause.startswith("requirement violated") for e in robot.get_adaptations()), "the adaptation")
            found = _scrape(exporter.url)
            events = robot.get_adaptations()
    assert {"dyknow_unit_up", "dyknow_port_messages", "dyknow_port_hop_seconds", "dyknow_adaptations", "dyknow_verdicts"} <= set(found)
    messages = {(labels["unit"], labels["port"]): value for _, labels, value in found["dyknow_port_messages"]}
    assert messages[("verdicts", "in")] >= 3
    hops = [(name, labels, value) for name, labels, value in found["dyknow_port_hop_seconds"] if labels["unit"] == "verdicts"]
    buckets = [value for name, labels, value in hops if name.endswith("_bucket")]
    (count,) = [value for name, _, value in hops if name.endswith("_count")]
    assert len(buckets) == len(BUCKETS_S) + 1 and buckets == sorted(buckets) and buckets[-1] == count >= 3  # cumulative, +Inf = count
    adaptations = {labels["kind"]: value for _, labels, value in found["dyknow_adaptations"]}
    assert sum(adaptations.values()) == len(events) >= 1 and set(adaptations) <= {"adapted", "recovered", "degraded"}
    verdicts = {(labels["monitor"], labels["formula"], labels["verdict"]): value for _, labels, value in found["dyknow_verdicts"]}
    formula = "historically[0, 1s] BallTrack(field).tracked > 0"  # (issue 54 item 7: the formula, not only the unit's name)
    assert verdicts[("monitor-1", formula, "true")] + verdicts[("monitor-1", formula, "false")] >= 1, verdicts
    assert "dyknow_verdicts" in first  # (listed from the first scrape on, counted since)
    assert all(labels["manager"] == "robot" for _, labels, _ in found["dyknow_unit_up"])


@pytest.mark.process
def test_a_manager_serves_metrics_on_loopback_when_asked() -> None:
    proc = ManagerProcess("metered", free_port(), "--metrics-port", "0")
    try:
        ready = proc.wait_ready()
        url = ready["metrics"]
        assert url.startswith("http://127.0.0.1:") and url.endswith("/metrics")
        assert run_cli("spawn", "periodic-source", "src", "--param", "rate_hz=50", *proc.client_args()).returncode == 0
        assert run_cli("spawn", "relay", "r1", "--bind", "in=dyknow/metered/src/out", *proc.client_args()).returncode == 0

        def relayed() -> float:
            found = _scrape(url).get("dyknow_port_messages", [])
            return max((v for _, labels, v in found if labels["unit"] == "r1" and labels["port"] == "in"), default=0.0)

        wait_until(lambda: relayed() >= 10, "messages through r1, as Prometheus scrapes them")
        assert proc.stop() == 0
    finally:
        proc.close()
    plain = ManagerProcess("unmetered", free_port())
    try:
        assert "metrics" not in plain.wait_ready()  # opt-in: nothing served unless asked
    finally:
        plain.close()


def test_the_documented_grafana_dashboard_asks_for_what_is_served(manager: Manager) -> None:
    """Every metric docs/howto/dyknow-grafana.json queries is one the exporter serves."""
    import json
    import re

    from tests.conftest import REPO

    dashboard = json.loads((REPO / "docs" / "howto" / "dyknow-grafana.json").read_text())
    queried = {name for panel in dashboard["panels"] for target in panel["targets"] for name in re.findall(r"\bdyknow_\w+", target["expr"])}
    manager.spawn("periodic-source", "src", params={"rate_hz": 100}, bindings={"out": "g/a"})
    manager.spawn("relay", "r1", bindings={"in": "g/a"})
    wait_until(lambda: manager.get_statistics("r1").ports[0].messages >= 5, "messages through the relay")
    with MetricsExporter(manager.metrics, 0) as exporter:
        text = urllib.request.urlopen(exporter.url, timeout=10).read().decode()
    served = set()
    for family in text_string_to_metric_families(text):  # (a counter with no sample yet is declared all the same)
        served |= {s.name for s in family.samples} | {family.name + {"counter": "_total", "histogram": "_bucket"}.get(family.type, "")}
    assert len(queried) >= 8 and queried <= served, queried - served


def test_monitors_made_and_released_leave_no_series_behind() -> None:
    """Issue 51: every monitor released (each a unit of its own) left its verdict series in the
    scrape and in get_metrics, and its histograms in memory, for the life of the manager. Made
    and released through the service, each seen by get_metrics and a scrape while it runs, they
    now leave the scrape, get_metrics and what the metrics keep as they were."""
    with (
        Manager("robot", specs=[SCENARIO_SPECS], ontology=[specs_dir() / "dyknow.ttl"]) as robot,
        MetricsExporter(robot.metrics, 0) as exporter,
        Client(robot.name, connect=robot.endpoints) as client,
    ):
        robot.request("BallTrack(field)")  # the stream every monitor reads, up all along
        running = {u.name for u in robot.units()}
        before = _series(exporter.url)
        for _ in range(25):
            key = client.monitor("BallTrack(field).tracked > 0")
            (monitor,) = {u.name for u in robot.units()} - running
            assert monitor in client.call_manager(robot.name, "get_metrics", {})["verdicts"]
            assert {labels["monitor"] for _, labels, _ in _scrape(exporter.url)["dyknow_verdicts"]} == {monitor}
            client.release(key)
        snap = client.call_manager(robot.name, "get_metrics", {})
        assert snap["verdicts"] == {} and {u["name"] for u in snap["units"]} == running
        assert _series(exporter.url) == before  # no series of a unit gone
        assert robot.resources().get("metrics_units") == len(running)  # nor anything kept for one


def test_a_unit_spawned_again_under_its_name_starts_its_histograms_anew(manager: Manager) -> None:
    """What the metrics keep of a unit belongs to that unit: another spawned under its name
    starts from nothing (its hop histogram counts its own messages only)."""
    manager.spawn("periodic-source", "src", params={"rate_hz": 200}, bindings={"out": "again/a"})
    manager.spawn("relay", "r1", bindings={"in": "again/a"})
    with MetricsExporter(manager.metrics, 0) as exporter:

        def hops() -> float:
            found = _scrape(exporter.url)["dyknow_port_hop_seconds"]
            return next(v for name, labels, v in found if labels["unit"] == "r1" and name.endswith("_count"))

        wait_until(lambda: hops() >= 50, "50 messages through r1")
        manager.destroy("r1")
        forgotten = manager.resources().get("metrics_units")  # as it went, before any scrape
        manager.spawn("relay", "r1", bindings={"in": "again/b"})  # fed by nothing
        assert hops() == 0
        assert forgotten == 1


def test_a_scrape_serves_at_most_max_metric_series(make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture) -> None:
    """Limits.max_metric_series bounds a scrape: the units past it, the latest spawned, are left
    out whole, logged and counted; they come in again when others go."""
    manager = make_manager(limits=Limits(max_metric_series=100))  # 3 of the manager's, 42 a relay (1 in, 1 out)
    for i in range(1, 6):
        manager.spawn("relay", f"r{i}", bindings={"in": f"capped/{i}"})
    with MetricsExporter(manager.metrics, 0) as exporter, caplog.at_level(logging.WARNING, logger="dyknow.metrics"):
        found = _scrape(exporter.url)
        assert sum(len(samples) for samples in found.values()) <= 100
        assert {labels["unit"] for _, labels, _ in found["dyknow_unit_up"]} == {"r1", "r2"}
        assert [v for _, _, v in found["dyknow_metrics_refused_units"]] == [3]
        assert [v for _, _, v in found["dyknow_metrics_refused_series"]] == [3 * 42]
        assert any("left 3 units (126 series) out" in r.message and "Limits.max_metric_series" in r.message for r in caplog.records)
        manager.destroy("r1")
        found = _scrape(exporter.url)
        assert {labels["unit"] for _, labels, _ in found["dyknow_unit_up"]} == {"r2", "r3"}
        assert [v for _, _, v in found["dyknow_metrics_refused_series"]] == [3 * 42 + 2 * 42]  # counted over the scrapes


def _half_open(port: int, n: int) -> list[socket.socket]:
    """``n`` connections that start a request head and never finish it."""
    opened = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=10)
        s.sendall(b"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        opened.append(s)
    return opened


def test_half_open_connections_to_the_metrics_port_hold_no_thread(manager: Manager) -> None:
    """Issue 51: the metrics port held a thread per connection until its request head came, so
    1,000 half-open connections made 1,000 threads. They hold none now, and an honest scrape
    still answers while they stay open (the oldest still sending a head make room for it)."""
    with MetricsExporter(manager.metrics, 0) as exporter:
        assert "dyknow_manager_cpu_seconds" in _scrape(exporter.url)  # (its threads started)
        before = threading.active_count()
        opened = _half_open(exporter.port, 1000)
        try:
            assert "dyknow_manager_cpu_seconds" in _scrape(exporter.url)  # accepted after them all
            assert threading.active_count() <= before + 2, threading.active_count() - before
            assert exporter.dropped >= 1000 - MAX_CONNECTIONS
        finally:
            for s in opened:
                s.close()


def test_the_metrics_port_closes_slow_heads_and_refuses_large_ones_and_other_hosts(manager: Manager) -> None:
    """A head must come whole within the head timeout and under MAX_HEAD_BYTES; on loopback a
    Host that is not one of this host's names (a DNS-rebound web page) is refused."""
    with MetricsExporter(manager.metrics, 0, head_timeout_s=0.3) as exporter:
        (silent,) = _half_open(exporter.port, 1)
        with silent:
            assert silent.recv(1) == b""  # closed by the server (the socket's own timeout is 10 s)
        with socket.create_connection(("127.0.0.1", exporter.port), timeout=10) as large:
            large.sendall(b"GET /metrics HTTP/1.1\r\nX: " + b"a" * 20_000)
            assert large.recv(100).startswith(b"HTTP/1.1 431 ")
        request = urllib.request.Request(exporter.url, headers={"Host": f"evil.example:{exporter.port}"})
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(request, timeout=10)
        assert refused.value.code == 403 and "evil.example" in refused.value.read().decode()
        assert exporter.dropped == 2
        assert "dyknow_manager_cpu_seconds" in _scrape(exporter.url.replace("127.0.0.1", "localhost"))


@pytest.mark.process
def test_half_open_connections_to_a_manager_process_hold_no_thread() -> None:
    """The same, on the port a ``dyknow manager --metrics-port`` process serves: its threads
    (Zenoh's included, counted by the kernel) stay as they were."""
    proc = ManagerProcess("halfopen", free_port(), "--metrics-port", "0")
    try:
        url = proc.wait_ready()["metrics"]
        port = int(url.rsplit(":", 1)[1].split("/")[0])
        _scrape(url)

        def threads() -> int:
            return len(os.listdir(f"/proc/{proc.proc.pid}/task"))

        before = threads()
        opened = _half_open(port, 500)
        try:
            assert "dyknow_manager_cpu_seconds" in _scrape(url)
            assert threads() <= before + 8, threads() - before
        finally:
            for s in opened:
                s.close()
        assert proc.stop() == 0
    finally:
        proc.close()


def test_a_long_formula_labels_its_verdicts_cut_and_apart_from_another_alike() -> None:
    """A verdict series is labelled with its formula's text; one over 200 characters is cut to
    200 and ended with a digest of the whole, so two alike over their first 200 stay apart."""
    from dyknow.metrics import MAX_FORMULA_LABEL, formula_label

    short = "Battery(r1) > 0.2"
    base = " and ".join(f"Level{k}(x) > 0" for k in range(30))
    one, two = base + " and a > 1", base + " and a > 2"
    assert formula_label(short) == short and len(one) > MAX_FORMULA_LABEL
    assert len(formula_label(one)) == MAX_FORMULA_LABEL and formula_label(one).startswith(one[:150])
    assert formula_label(one) != formula_label(two) and formula_label(one) == formula_label(one)
