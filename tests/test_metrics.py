"""dyknow.metrics: a manager's figures in one snapshot (get_metrics, dyknow top), and scraped by
Prometheus's own text parser from --metrics-port (loopback by default)."""

from __future__ import annotations

import urllib.request

import pytest
from prometheus_client.parser import text_string_to_metric_families

from dyknow import Client, Manager
from dyknow.metrics import BUCKETS_S, MetricsExporter
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
    verdicts = {(labels["monitor"], labels["verdict"]): value for _, labels, value in found["dyknow_verdicts"]}
    assert verdicts[("monitor-1", "true")] + verdicts[("monitor-1", "false")] >= 1, verdicts
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
