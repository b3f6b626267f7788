"""A manager's figures for operators: one snapshot for ``dyknow top``, and Prometheus.

- :meth:`Metrics.snapshot`: every unit's state and statistics (messages, bytes, drops, lost,
  queue depth, hop and age percentiles, callback time), the manager process's CPU time, its
  adaptations by kind and its monitors' verdicts, as one JSON object: what the ``get_metrics``
  service answers, so ``dyknow top`` asks each manager once per refresh whatever its number of
  units.
- :class:`MetricsExporter`: the same figures for Prometheus, on an HTTP port of the manager's
  own (``dyknow manager --metrics-port PORT``; loopback unless ``--metrics-host`` says
  otherwise: the figures name every unit and key). Counters are ``*_total``, so Prometheus
  computes rates (``rate(dyknow_port_messages_total[1m])``); hop and age are histograms.

The hop and age histograms are built from the samples each input port keeps for its percentiles
(the last :data:`dyknow.stats.WINDOW`): at each scrape the samples since the previous one are
added, so every message counts as long as fewer than 1024 arrive on a port between two scrapes
(68 a second at Prometheus's usual 15 s); beyond that the histogram counts the latest 1024 of
them, and ``dyknow_port_messages_total`` stays exact. Nothing is added to the message path.

Verdicts are counted from when the metrics first see a monitor (the first scrape or
``get_metrics`` call after it was spawned): a monitor that published verdicts before was
counted from then on.

The manager provides what this module reads through :class:`MetricsSource`.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from dyknow.adaptation import AdaptationEvent
    from dyknow.model import Model
    from dyknow.proxy import UnitStatistics
    from dyknow.reasoning.progression import Verdict
    from dyknow.stats import PortCounters
    from dyknow.unit import Unit

__all__ = ["BUCKETS_S", "Metrics", "MetricsExporter", "MetricsSource"]

#: The histograms' bucket bounds, in seconds (hop and age): 50 µs to 1 s.
BUCKETS_S: tuple[float, ...] = (50e-6, 100e-6, 250e-6, 500e-6, 1e-3, 2.5e-3, 5e-3, 10e-3, 25e-3, 50e-3, 100e-3, 250e-3, 1.0)


class MetricsSource(Protocol):
    """What the metrics read of a manager (:class:`dyknow.Manager` provides it)."""

    @property
    def name(self) -> str:
        """The manager's name."""
        ...

    def get_model(self) -> Model:
        """The units and specs."""
        ...

    def get_statistics(self, name: str) -> UnitStatistics:
        """One unit's statistics."""
        ...

    def get_adaptations(self) -> list[AdaptationEvent]:
        """The adaptations so far."""
        ...

    def queue_depths(self, name: str) -> dict[str, int]:
        """How many messages each input port of a unit holds."""
        ...

    def port_counters(self, name: str) -> dict[str, PortCounters]:
        """Each input port's counters."""
        ...

    def unit(self, name: str) -> Unit:
        """A unit's object."""
        ...


class _Histogram:
    """Cumulative bucket counts of one port's samples (hop or age), fed at each scrape."""

    __slots__ = ("buckets", "count", "sum_s")

    def __init__(self) -> None:
        self.buckets = [0] * len(BUCKETS_S)
        self.count = 0
        self.sum_s = 0.0

    def add(self, samples_ns: list[int]) -> None:
        for ns in samples_ns:
            s = ns / 1e9
            self.count += 1
            self.sum_s += s
            for i, bound in enumerate(BUCKETS_S):
                if s <= bound:
                    self.buckets[i] += 1
                    break

    def cumulative(self) -> list[tuple[str, float]]:
        """Prometheus's buckets: ``(le, count at or below)``, ``+Inf`` last."""
        out, total = [], 0
        for bound, n in zip(BUCKETS_S, self.buckets, strict=True):
            total += n
            out.append((repr(bound), float(total)))
        return [*out, ("+Inf", float(self.count))]


def _counter(counts: Counter[str]) -> Callable[[Verdict], None]:
    def count(verdict: Verdict) -> None:  # on the monitor's thread: one dictionary update
        counts["true" if verdict.verdict else "false"] += 1

    return count


class Metrics:
    """A manager's figures: :meth:`snapshot` (JSON), and the state Prometheus's histograms and
    verdict counts keep between scrapes. Thread-safe: scrapes and service calls may overlap."""

    def __init__(self, source: MetricsSource) -> None:
        self._source = source
        self._lock = threading.Lock()
        self._verdicts: dict[str, Counter[str]] = {}  # monitor unit -> "true"/"false" -> count
        self._watched: dict[str, int] = {}  # monitor unit -> id of the object listened to
        self._seen: dict[tuple[str, str], int] = {}  # (unit, port) -> samples taken into the histograms
        self._histograms: dict[tuple[str, str, str], _Histogram] = {}  # (unit, port, "hop"/"age")

    def _watch_monitors(self, names: list[str]) -> None:
        from dyknow.reasoning.unit import FormulaMonitor

        for name in names:
            try:
                unit = self._source.unit(name)
            except Exception:  # gone since the model was taken
                continue
            if not isinstance(unit, FormulaMonitor) or self._watched.get(name) == id(unit):
                continue
            counts: Counter[str] = Counter()
            self._verdicts[name] = counts
            self._watched[name] = id(unit)
            unit.listen(_counter(counts))

    def snapshot(self) -> dict[str, Any]:
        """Every unit's figures and the manager's, as JSON (what ``get_metrics`` answers)."""
        source = self._source
        model = source.get_model()
        units = []
        for info in model.units:
            try:
                stats = source.get_statistics(info.name).to_dict()
                queued = source.queue_depths(info.name)
            except Exception:  # destroyed between the model and now
                continue
            for port, figures in stats["ports"].items():
                figures["queued"] = queued.get(port, 0)
            stats.pop("traceback", None)
            units.append(stats)
        with self._lock:
            self._watch_monitors([u["name"] for u in units])
            verdicts = {name: dict(counts) for name, counts in self._verdicts.items()}
        adaptations = Counter(event.kind for event in source.get_adaptations())
        return {
            "manager": source.name,
            "time_ns": time.time_ns(),
            "cpu_s": round(time.process_time(), 6),
            "threads": threading.active_count(),
            "units": units,
            "adaptations": dict(adaptations),
            "verdicts": verdicts,
        }

    def histograms(self, unit: str) -> dict[tuple[str, str], _Histogram]:
        """``(port, "hop"/"age") -> histogram`` of a unit's input ports, fed with the samples
        recorded since the previous call."""
        found: dict[tuple[str, str], _Histogram] = {}
        try:
            counters = self._source.port_counters(unit)
        except Exception:
            return found
        with self._lock:
            for port, c in counters.items():
                n, ages, hops = c.samples_since(self._seen.get((unit, port), 0))
                self._seen[(unit, port)] = n
                for kind, samples in (("hop", hops), ("age", ages)):
                    histogram = self._histograms.setdefault((unit, port, kind), _Histogram())
                    histogram.add(samples)
                    found[(port, kind)] = histogram
        return found


class _Collector:
    """A prometheus_client collector over :class:`Metrics`: read at each scrape."""

    def __init__(self, metrics: Metrics) -> None:
        self.metrics = metrics

    def describe(self) -> list[Any]:
        return []  # (figured at each scrape: nothing to check at registration)

    def collect(self) -> Iterator[Any]:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

        snap = self.metrics.snapshot()
        manager = snap["manager"]
        up = GaugeMetricFamily("dyknow_unit_up", "1 per unit, labelled with its spec's label and its state", labels=["manager", "unit", "label", "state"])
        callback = GaugeMetricFamily("dyknow_unit_callback_seconds", "a unit's callback time (moving average)", labels=["manager", "unit"])
        port_labels = ["manager", "unit", "port", "direction", "key"]
        messages = CounterMetricFamily("dyknow_port_messages", "messages through a port", labels=port_labels)
        nbytes = CounterMetricFamily("dyknow_port_bytes", "bytes through a port (messages of known size)", labels=port_labels)
        dropped = CounterMetricFamily("dyknow_port_dropped", "messages a port dropped (its queue was full)", labels=port_labels)
        lost = CounterMetricFamily("dyknow_port_lost", "messages another process sent an input that never arrived", labels=port_labels)
        queued = GaugeMetricFamily("dyknow_port_queued", "messages an input port holds, waiting for its unit", labels=port_labels)
        hop = HistogramMetricFamily("dyknow_port_hop_seconds", "time from the previous hop's send to the unit", labels=["manager", "unit", "port"])
        age = HistogramMetricFamily("dyknow_port_age_seconds", "time from the data's origin to the unit", labels=["manager", "unit", "port"])
        for unit in snap["units"]:
            name = unit["name"]
            up.add_metric([manager, name, unit["label"], unit["state"]], 1)
            callback.add_metric([manager, name], unit["callback_avg_us"] / 1e6)
            for port, p in unit["ports"].items():
                labels = [manager, name, port, p["direction"], p["key"]]
                messages.add_metric(labels, p["messages"])
                nbytes.add_metric(labels, p["bytes"])
                dropped.add_metric(labels, p["dropped"])
                if p["direction"] == "in":
                    lost.add_metric(labels, p.get("lost", 0))
                    queued.add_metric(labels, p.get("queued", 0))
            for (port, kind), histogram in self.metrics.histograms(name).items():
                (hop if kind == "hop" else age).add_metric([manager, name, port], histogram.cumulative(), histogram.sum_s)
        adaptations = CounterMetricFamily("dyknow_adaptations", "adaptations of the manager's requests, by kind", labels=["manager", "kind"])
        for kind, n in snap["adaptations"].items():
            adaptations.add_metric([manager, kind], n)
        verdicts = CounterMetricFamily("dyknow_verdicts", "verdicts of the manager's monitors", labels=["manager", "monitor", "verdict"])
        for monitor, counts in snap["verdicts"].items():
            for verdict in ("true", "false"):
                verdicts.add_metric([manager, monitor, verdict], counts.get(verdict, 0))
        cpu = CounterMetricFamily("dyknow_manager_cpu_seconds", "CPU time of the manager's process", labels=["manager"])
        cpu.add_metric([manager], snap["cpu_s"])
        yield from (up, callback, messages, nbytes, dropped, lost, queued, hop, age, adaptations, verdicts, cpu)


class MetricsExporter:
    """Serve a manager's :class:`Metrics` to Prometheus on ``http://HOST:PORT/metrics`` until closed.

    ``host`` is loopback by default: the figures name every unit and key, and the endpoint has no
    access control; expose it beyond the host deliberately (a Prometheus on another machine), or
    through a reverse proxy. ``port`` 0 picks a free one (:attr:`port` says which).
    """

    def __init__(self, metrics: Metrics, port: int, host: str = "127.0.0.1") -> None:
        from prometheus_client import CollectorRegistry, start_http_server

        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(_Collector(metrics))  # type: ignore[arg-type]
        try:
            self._server, self._thread = start_http_server(port, addr=host, registry=self.registry)
        except OSError as exc:
            from dyknow.errors import DyKnowError

            raise DyKnowError(f"cannot serve metrics on {host}:{port}: {exc.strerror or exc}", where="--metrics-port",
                              expected="a free port (0: any)") from exc  # fmt: skip
        self.host = host
        self.port = int(self._server.server_address[1])
        self._closed = False

    @property
    def url(self) -> str:
        """Where Prometheus scrapes: ``http://HOST:PORT/metrics``."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/metrics"

    def close(self) -> None:
        """Stop serving (safe twice)."""
        if self._closed:
            return
        self._closed = True
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(5)

    def __enter__(self) -> MetricsExporter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
