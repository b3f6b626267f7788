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

What the figures keep and serve is bounded by what runs:

- a unit's series (its ports, histograms and verdicts) go with it: what the metrics keep of a
  unit is forgotten when it is destroyed (or replaced by another of the same name), so making
  and releasing monitors or units leaves nothing behind, in the scrape, in ``get_metrics`` or
  in memory;
- label values are only the names of what runs (the manager, its units, their spec labels,
  ports and keys, each bounded by :class:`~dyknow.security.Limits`) and small fixed sets (unit
  states, directions, adaptation kinds, ``true``/``false``), never object ids or values taken
  from the data (a ``foreach`` monitor's objects are not labels);
- a scrape serves at most ``Limits.max_metric_series`` series (each histogram bucket is one, as
  Prometheus counts them): the units past it, the latest spawned, are left out whole, a warning
  says so (at most once a minute) and ``dyknow_metrics_refused_units`` (this scrape) and
  ``dyknow_metrics_refused_series_total`` (every scrape so far) count them.

The exporter's port holds no thread per connection: one thread serves every connection
(asyncio) and another renders the scrapes, one at a time. A connection must send its request
head within :data:`~dyknow.webguard.HEAD_TIMEOUT_S` (at most
:data:`~dyknow.webguard.MAX_HEAD_BYTES`), and at most :data:`MAX_CONNECTIONS` are open at once:
one more closes the oldest that is still sending its head (an honest scraper sends it at once),
or, when every one is being answered, is answered 503. On loopback, a ``Host`` other than this
host's names is refused (a web page on a DNS-rebound name cannot read the figures).

The manager provides what this module reads through :class:`MetricsSource`.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Protocol

from dyknow.webguard import HEAD_TIMEOUT_S, MAX_HEAD_BYTES, host_name, served_hosts

if TYPE_CHECKING:
    from dyknow.adaptation import AdaptationEvent
    from dyknow.model import Model, UnitEvent
    from dyknow.proxy import UnitStatistics
    from dyknow.reasoning.progression import Verdict
    from dyknow.security import Limits
    from dyknow.stats import PortCounters
    from dyknow.unit import Unit

__all__ = ["BUCKETS_S", "MAX_CONNECTIONS", "Metrics", "MetricsExporter", "MetricsSource"]

log = logging.getLogger(__name__)

#: The histograms' bucket bounds, in seconds (hop and age): 50 µs to 1 s.
BUCKETS_S: tuple[float, ...] = (50e-6, 100e-6, 250e-6, 500e-6, 1e-3, 2.5e-3, 5e-3, 10e-3, 25e-3, 50e-3, 100e-3, 250e-3, 1.0)

#: The most connections the metrics port holds open at once (a Prometheus needs one or two).
MAX_CONNECTIONS = 64
#: How long a scrape's answer may take to be read by its client before the connection is dropped.
SEND_TIMEOUT_S = 30.0

_HISTOGRAM_SERIES = len(BUCKETS_S) + 3  # its buckets, +Inf, _sum and _count
_MANAGER_SERIES = 3  # the manager's CPU time and the two refusal counts (its adaptations besides)
#: The longest formula a verdict series is labelled with as it is; a longer one is cut (see :func:`formula_label`).
MAX_FORMULA_LABEL = 200
_WARN_EVERY_S = 60.0  # a refusal is logged at most this often


class MetricsSource(Protocol):
    """What the metrics read of a manager (:class:`dyknow.Manager` provides it)."""

    @property
    def name(self) -> str:
        """The manager's name."""
        ...

    @property
    def limits(self) -> Limits:
        """What the manager bounds (``max_metric_series``: what a scrape serves)."""
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

    def on_unit_event(self, listener: Callable[[UnitEvent], None]) -> Callable[[], None]:
        """Call ``listener`` when a unit is spawned, fails or is destroyed."""
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


class _Tracked:
    """What the metrics keep of one unit: which of its lives (``started_ns``), its verdict counts
    (a monitor's), and its input ports' histograms and the samples already taken into them."""

    __slots__ = ("histograms", "seen", "started_ns", "verdicts")

    def __init__(self, started_ns: int) -> None:
        self.started_ns = started_ns
        self.verdicts: dict[str, Counter[str]] | None = None  # formula -> "true"/"false" -> count, for a monitor
        self.seen: dict[str, int] = {}  # port -> samples taken into its histograms
        self.histograms: dict[tuple[str, str], _Histogram] = {}  # (port, "hop"/"age")


def _counter(counts: dict[str, Counter[str]]) -> Callable[[str, Verdict], None]:
    def count(formula: str, verdict: Verdict) -> None:  # on the monitor's thread: two dictionary look-ups
        by = counts.get(formula)
        if by is None:
            by = counts[formula] = Counter()
        by["true" if verdict.verdict else "false"] += 1

    return count


def formula_label(formula: str) -> str:
    """A formula as a label's value: its text, at most :data:`MAX_FORMULA_LABEL` characters (a
    longer one cut and ended with a digest of the whole, so two alike at the start stay apart)."""
    if len(formula) <= MAX_FORMULA_LABEL:
        return formula
    digest = hashlib.sha256(formula.encode()).hexdigest()[:12]
    return f"{formula[: MAX_FORMULA_LABEL - 17]}... #{digest}"


def unit_series(unit: dict[str, Any], formulas: int) -> int:
    """The series one unit of a :meth:`Metrics.snapshot` adds to a scrape, as Prometheus counts
    them (each histogram bucket is one): up and callback time, 3 per output port, 5 and two
    histograms per input port, and a monitor's two verdict counts per formula (of ``formulas``
    that gave verdicts)."""
    n = 2 + 2 * formulas
    for port in unit["ports"].values():
        n += 5 + 2 * _HISTOGRAM_SERIES if port["direction"] == "in" else 3
    return n


class Metrics:
    """A manager's figures: :meth:`snapshot` (JSON), and the state Prometheus's histograms and
    verdict counts keep between scrapes. Thread-safe: scrapes and service calls may overlap.

    It keeps state only for the units that run: a unit's is forgotten when the manager says it
    was destroyed, and at every snapshot for any unit no longer in the model."""

    def __init__(self, source: MetricsSource) -> None:
        self._source = source
        self._lock = threading.Lock()
        self._units: dict[str, _Tracked] = {}  # unit name -> what is kept of it
        self.refused_series = 0  # series left out of scrapes so far (over max_metric_series)
        self._warned: float | None = None  # when a refusal was last logged (monotonic)
        source.on_unit_event(self._unit_event)

    @property
    def max_series(self) -> int:
        """The most series a scrape serves (``Limits.max_metric_series``)."""
        return self._source.limits.max_metric_series

    def tracked(self) -> int:
        """How many units the metrics keep state for (never more than run, once a snapshot saw
        them go or the manager said so)."""
        with self._lock:
            return len(self._units)

    def forget(self, name: str) -> None:
        """Drop what is kept of unit ``name`` (its verdict counts, histograms): it is gone."""
        with self._lock:
            self._units.pop(name, None)

    def _unit_event(self, event: UnitEvent) -> None:
        if event.kind == "destroyed":
            self.forget(event.unit)

    def _track(self, live: dict[str, int]) -> None:
        """Keep state for the units of ``live`` (name -> started_ns), and only for them: what
        is kept of a unit gone, or replaced by another of its name, is dropped; a new monitor's
        verdicts are counted from now on."""
        from dyknow.reasoning.unit import FormulaMonitor

        with self._lock:
            for name in [n for n, t in self._units.items() if live.get(n) != t.started_ns]:
                del self._units[name]
            new = [(name, started) for name, started in live.items() if name not in self._units]
        for name, started in new:
            try:
                unit = self._source.unit(name)
            except Exception:  # gone since the model was taken
                continue
            with self._lock:
                if name in self._units:  # (another snapshot, meanwhile)
                    continue
                tracked = self._units[name] = _Tracked(started)
                if isinstance(unit, FormulaMonitor):
                    tracked.verdicts = {name: Counter() for name in getattr(unit, "monitors", {})}  # (listed from the first scrape on)
                    unit.listen_formulas(_counter(tracked.verdicts))

    def snapshot(self) -> dict[str, Any]:
        """Every unit's figures and the manager's, as JSON (what ``get_metrics`` answers)."""
        source = self._source
        model = source.get_model()
        units = []
        live: dict[str, int] = {}
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
            live[info.name] = info.started_ns
        self._track(live)
        with self._lock:
            by_formula = {name: {f: dict(c) for f, c in list(t.verdicts.items())} for name, t in self._units.items() if t.verdicts is not None and name in live}
        verdicts = {name: dict(sum((Counter(c) for c in formulas.values()), Counter())) for name, formulas in by_formula.items()}
        adaptations = Counter(event.kind for event in source.get_adaptations())
        return {
            "manager": source.name,
            "time_ns": time.time_ns(),
            "cpu_s": round(time.process_time(), 6),
            "threads": threading.active_count(),
            "units": units,
            "adaptations": dict(adaptations),
            "verdicts": verdicts,  # by unit, its formulas' together
            "verdicts_by_formula": by_formula,
            "requests": [r.brief() for r in model.requests],  # (their state and why, beside the figures: dyknow top)
            "lost": [dict(m) for m in model.lost],
            "modes": [{k: m[k] for k in ("system", "mode", "since_ns", "why")} for m in model.modes],
        }

    def admit(self, snap: dict[str, Any]) -> tuple[list[dict[str, Any]], int]:
        """The units of ``snap`` (a :meth:`snapshot`) a scrape serves within
        :attr:`max_series`, in the model's order (the earliest spawned first), and how many
        series were left out. A refusal is counted (:attr:`refused_series`) and logged."""
        limit = self.max_series
        used = _MANAGER_SERIES + len(snap["adaptations"])
        admitted: list[dict[str, Any]] = []
        refused_units = refused = 0
        for unit in snap["units"]:
            cost = unit_series(unit, len(snap.get("verdicts_by_formula", {}).get(unit["name"], ())))
            if used + cost > limit:
                refused_units += 1
                refused += cost
                continue
            used += cost
            admitted.append(unit)
        if refused:
            now = time.monotonic()
            with self._lock:
                self.refused_series += refused
                warn = self._warned is None or now - self._warned >= _WARN_EVERY_S
                if warn:
                    self._warned = now
            if warn:
                log.warning(
                    "metrics of manager %r: left %d units (%d series) out of the scrape: it would serve over %d series, "
                    "the most (Limits.max_metric_series; dyknow_metrics_refused_series_total counts them): destroy units "
                    "or raise it (dyknow manager --max-metric-series N)",
                    snap["manager"], refused_units, refused, limit,
                )  # fmt: skip
        return admitted, refused

    def histograms(self, unit: str) -> dict[tuple[str, str], _Histogram]:
        """``(port, "hop"/"age") -> histogram`` of a unit's input ports, fed with the samples
        recorded since the previous call (empty for a unit the metrics do not track)."""
        found: dict[tuple[str, str], _Histogram] = {}
        try:
            counters = self._source.port_counters(unit)
        except Exception:
            return found
        with self._lock:
            tracked = self._units.get(unit)
            if tracked is None:  # gone, or not seen by a snapshot yet: nothing kept for it
                return found
            for port, c in counters.items():
                n, ages, hops = c.samples_since(tracked.seen.get(port, 0))
                tracked.seen[port] = n
                for kind, samples in (("hop", hops), ("age", ages)):
                    histogram = tracked.histograms.setdefault((port, kind), _Histogram())
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
        admitted, _ = self.metrics.admit(snap)
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
        verdicts = CounterMetricFamily(
            "dyknow_verdicts", "verdicts of the manager's monitors, by formula (its name, else its text)", labels=["manager", "monitor", "formula", "verdict"]
        )
        for unit in admitted:
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
            for formula, counts in sorted(snap.get("verdicts_by_formula", {}).get(name, {}).items()):
                for verdict in ("true", "false"):
                    verdicts.add_metric([manager, name, formula_label(formula), verdict], counts.get(verdict, 0))
        adaptations = CounterMetricFamily("dyknow_adaptations", "adaptations of the manager's requests, by kind", labels=["manager", "kind"])
        for kind, n in snap["adaptations"].items():
            adaptations.add_metric([manager, kind], n)
        cpu = CounterMetricFamily("dyknow_manager_cpu_seconds", "CPU time of the manager's process", labels=["manager"])
        cpu.add_metric([manager], snap["cpu_s"])
        modes = GaugeMetricFamily("dyknow_system_mode", "1 per system in a mode (a spec's <system>), labelled with the mode", labels=["manager", "system", "mode"])
        since = GaugeMetricFamily("dyknow_system_mode_since_seconds", "when a system entered its mode (Unix time)", labels=["manager", "system", "mode"])
        for mode in snap.get("modes", ()):
            modes.add_metric([manager, mode["system"], mode["mode"]], 1)
            since.add_metric([manager, mode["system"], mode["mode"]], mode["since_ns"] / 1e9)
        refused_units = GaugeMetricFamily("dyknow_metrics_refused_units", "units left out of this scrape (over Limits.max_metric_series)", labels=["manager"])
        refused_units.add_metric([manager], len(snap["units"]) - len(admitted))
        refused = CounterMetricFamily("dyknow_metrics_refused_series", "series left out of scrapes so far (over Limits.max_metric_series)", labels=["manager"])
        refused.add_metric([manager], self.metrics.refused_series)
        yield from (up, callback, messages, nbytes, dropped, lost, queued, hop, age, adaptations, verdicts, cpu, modes, since, refused_units, refused)


class MetricsExporter:
    """Serve a manager's :class:`Metrics` to Prometheus on ``http://HOST:PORT/metrics`` until closed.

    ``host`` is loopback by default: the figures name every unit and key, and the endpoint has no
    access control; expose it beyond the host deliberately (a Prometheus on another machine), or
    through a reverse proxy. ``port`` 0 picks a free one (:attr:`port` says which). Connections
    are bounded as the module documentation says; ``head_timeout_s`` is how long one may take to
    send its request head. Raises :class:`~dyknow.errors.DyKnowError` when it cannot listen.
    """

    def __init__(self, metrics: Metrics, port: int, host: str = "127.0.0.1", *, head_timeout_s: float = HEAD_TIMEOUT_S) -> None:
        from prometheus_client import CollectorRegistry

        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(_Collector(metrics))  # type: ignore[arg-type]
        self.host = host
        self._hosts = served_hosts(host)
        self._head_timeout_s = head_timeout_s
        #: Connections closed without an answer: over :data:`MAX_CONNECTIONS` while still sending
        #: their head, too slow to send it, or with one too large.
        self.dropped = 0
        self._warned: float | None = None  # when a refused Host was last logged (monotonic)
        self._tasks: set[asyncio.Task[None]] = set()  # every connection's, to cancel at close
        self._open: dict[asyncio.Task[None], None] = {}  # the connections counted against MAX_CONNECTIONS
        self._waiting: dict[asyncio.Task[None], None] = {}  # those still sending their head, oldest first
        self._renderer = ThreadPoolExecutor(1, thread_name_prefix="dyknow-metrics-render")  # one scrape at a time
        self._loop = asyncio.new_event_loop()
        try:
            listener = _listen(host, port)
            self._server = self._loop.run_until_complete(asyncio.start_server(self._serve, sock=listener, limit=MAX_HEAD_BYTES))
        except OSError as exc:
            from dyknow.errors import DyKnowError

            self._loop.close()
            self._renderer.shutdown()
            raise DyKnowError(f"cannot serve metrics on {host}:{port}: {exc.strerror or exc}", where="--metrics-port",
                              expected="a free port (0: any) on an address of this host (--metrics-host)") from exc  # fmt: skip
        self.port = int(listener.getsockname()[1])
        self._closed = False
        self._thread = threading.Thread(target=self._loop.run_forever, name="dyknow-metrics", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """Where Prometheus scrapes: ``http://HOST:PORT/metrics``."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/metrics"

    def close(self) -> None:
        """Stop serving and drop every connection (safe twice; bounded by a few seconds)."""
        if self._closed:
            return
        self._closed = True

        async def stop() -> None:
            self._server.close()
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)

        with contextlib.suppress(RuntimeError, TimeoutError):
            asyncio.run_coroutine_threadsafe(stop(), self._loop).result(5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)
        if not self._thread.is_alive():
            self._loop.close()
        self._renderer.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> MetricsExporter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            if len(self._open) >= MAX_CONNECTIONS:
                if not self._waiting:  # every one is being answered
                    await self._send(writer, 503, f"the metrics port has {MAX_CONNECTIONS} connections open, its most; try again\n")
                    return
                oldest = next(iter(self._waiting))  # the oldest still sending its head (an honest scraper sends it at once)
                del self._waiting[oldest], self._open[oldest]
                oldest.cancel()
                self.dropped += 1
            self._open[task] = None
            self._waiting[task] = None
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), self._head_timeout_s)
            except asyncio.LimitOverrunError:
                self.dropped += 1
                await self._send(writer, 431, f"the request head is over {MAX_HEAD_BYTES} bytes; expected a scrape's GET\n")
                return
            except TimeoutError:
                self.dropped += 1
                return
            except (asyncio.IncompleteReadError, ConnectionError):
                return
            finally:
                self._waiting.pop(task, None)
            await self._answer(head, writer)
        except asyncio.CancelledError:  # dropped for a newer connection, or closing
            pass
        finally:
            if writer.transport.get_write_buffer_size():  # a client that does not read: drop what it did not take
                writer.transport.abort()
            else:
                writer.close()
            self._open.pop(task, None)
            self._tasks.discard(task)

    async def _answer(self, head: bytes, writer: asyncio.StreamWriter) -> None:
        lines = head.decode("latin-1").split("\r\n")
        method, _, rest = lines[0].partition(" ")
        path = rest.partition(" ")[0]
        headers: dict[str, str] = {}
        for line in lines[1:]:
            name, sep, value = line.partition(":")
            if sep:
                headers.setdefault(name.strip().lower(), value.strip())
        host = headers.get("host")
        if self._hosts is not None and host is not None and host_name(host) not in self._hosts:
            listing = ", ".join(sorted(self._hosts))
            now = time.monotonic()
            if self._warned is None or now - self._warned >= _WARN_EVERY_S:  # (a page may ask again and again)
                self._warned = now
                log.warning("metrics: refused a request for Host %r, not a name of this server (a web page on a DNS-rebound name?)", host[:200])
            await self._send(writer, 403, f"refused: the Host {host[:200]!r} is not a name of this server; expected one of {listing}\n")
            return
        if method not in ("GET", "HEAD"):
            await self._send(writer, 405, f"{method[:20]!r} is not served; expected GET {self.url}\n")
            return
        if path.partition("?")[0] == "/favicon.ico":
            await self._send(writer, 200, "", head_only=method == "HEAD")
            return
        loop = asyncio.get_running_loop()
        try:
            body, content_type, encoding = await loop.run_in_executor(
                self._renderer, _render, self.registry, headers.get("accept", ""), headers.get("accept-encoding", "")
            )
        except Exception as exc:
            log.exception("metrics: a scrape failed")
            await self._send(writer, 500, f"the scrape failed: {type(exc).__name__}: {exc}\n")
            return
        extra = [("Content-Encoding", encoding)] if encoding else []
        await self._send(writer, 200, body, content_type=content_type, headers=extra, head_only=method == "HEAD")

    async def _send(
        self,
        writer: asyncio.StreamWriter,
        status: int,
        body: bytes | str,
        *,
        content_type: str = "text/plain; charset=utf-8",
        headers: list[tuple[str, str]] | None = None,
        head_only: bool = False,
    ) -> None:
        """Answer and close (no keep-alive: a scraper opens one connection per scrape)."""
        data = body.encode() if isinstance(body, str) else body
        lines = [f"HTTP/1.1 {status} {_REASONS.get(status, '')}", f"Content-Type: {content_type}", f"Content-Length: {len(data)}",
                 "Connection: close", *(f"{k}: {v}" for k, v in headers or [])]  # fmt: skip
        writer.write(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + (b"" if head_only else data))
        with contextlib.suppress(ConnectionError, TimeoutError):
            await asyncio.wait_for(writer.drain(), SEND_TIMEOUT_S)


_REASONS = {200: "OK", 403: "Forbidden", 405: "Method Not Allowed", 431: "Request Header Fields Too Large",
            500: "Internal Server Error", 503: "Service Unavailable"}  # fmt: skip


def _render(registry: Any, accept: str, accept_encoding: str) -> tuple[bytes, str, str | None]:
    """A scrape's body in the format its ``Accept`` asks for (Prometheus's text format, or
    OpenMetrics), gzipped when ``Accept-Encoding`` allows: as prometheus_client's own server
    answers. On the renderer's thread."""
    import gzip

    from prometheus_client.exposition import choose_encoder, gzip_accepted

    encoder, content_type = choose_encoder(accept)
    body = encoder(registry)
    if gzip_accepted(accept_encoding):
        return gzip.compress(body), content_type, "gzip"
    return body, content_type, None


def _listen(host: str, port: int) -> socket.socket:
    """A listening socket on ``host``:``port`` (its first address family, as prometheus_client
    chooses: one port even when ``host`` has several addresses)."""
    family, kind, proto, _, address = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
    listener = socket.socket(family, kind, proto)
    try:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(address)
        listener.listen(128)
        listener.setblocking(False)
    except OSError:
        listener.close()
        raise
    return listener
