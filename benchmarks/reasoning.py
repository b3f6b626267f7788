"""Per-state cost of dyknow's temporal monitor beside RTAMT's and reelay's, on the same formulas
and traces; and, with ``--monitors``, 1,000 monitors at 20 Hz in one manager, end to end.

**Per state.** Formulas of 1, 5 and 20 operators (connectives and temporal operators; atoms are
not counted), past-only and future, with windows of 10, 100 and 1,000 states, over one trace of
two random streams ``x`` and ``y`` sampled together every millisecond. Each monitor gets the same
samples through its own interface, one state per call (dyknow: ``Monitor.push_all``, or
``push_index`` for one stream; reelay: ``update({...})`` of its discrete-time monitor; RTAMT:
``update(i, [...])`` of its discrete-time specification, pastified for future formulas), and the
time per state is the wall time of the whole trace divided by its length, the best of
``--repeat`` runs (the machine is shared: the best run is the one least disturbed). Before
timing, a short run checks that the three agree on the verdicts where their semantics coincide
(RTAMT's sign, a horizon late for future formulas; see :mod:`dyknow.reasoning.semantics`).
reelay is past-time only, so the target beside each figure is "at most the faster of the two
where they support the formula": reelay's or RTAMT's for past formulas, RTAMT's for future ones.

**End to end** (``--monitors N``): one manager runs N formula monitors (a past formula over one
term each) fed by N sources at 20 Hz, all in one process, on one core (``os.sched_setaffinity``);
the latency is from a sample's origin time to the arrival of its verdict at a subscriber of the
monitors' ``verdicts`` keys (a sink unit in the same manager), p50 and p99 beside the 1 ms target.

    python benchmarks/reasoning.py --json benchmarks/results/reasoning.json
    python benchmarks/reasoning.py --quick
    python benchmarks/reasoning.py --monitors 1000 --seconds 20
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import random
import sys
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dyknow import Limits, Manager, Message, Port, TransformationSpec, Unit
from dyknow.reasoning import Monitor, monitor_spec, parse
from dyknow.reasoning.syntax import (
    Always,
    And,
    Atom,
    Const,
    Eventually,
    Formula,
    Historically,
    Implies,
    Interval,
    Node,
    Not,
    Once,
    Or,
    Since,
    Until,
)

from harness import Proc, cpu_seconds, free_ports, machine, percentile, sleep_until, write_json

MS = 1_000_000


def formulas(window: int) -> list[tuple[str, str, str]]:
    """``(name, kind, formula)`` for a window of ``window`` states (1 ms each): 1, 5 and 20
    operators, past and future; the future ones mirror the past ones operator for operator."""
    w, h = f"{window}ms", f"{max(1, window // 2)}ms"
    past = {
        1: f"once[0, {w}] x > 0.9",
        5: f"historically[0, {w}] (x < 0.1 or once[0, {w}] y > 0.9) or once[0, {w}] x > 0.99",
        20: (
            f"(historically[0, {w}] (x < 0.1 or once[0, {w}] y > 0.9) and once[0, {w}] (x > 0.5 and y < 0.5))"
            f" or (x > 0.2 since[0, {w}] (y > 0.8 and x < 0.9))"
            f" or not historically[0, {w}] (x > 0.05 or y > 0.01)"
            f" or (once[0, {h}] x > 0.95 and historically[0, {h}] y < 0.99)"
            f" or not (y > 0.3 since[0, {w}] x > 0.97)"
        ),
    }
    out = []
    for ops, text in past.items():
        mirrored = text.replace("historically", "always").replace("once", "eventually").replace("since", "until")
        out.append((f"{ops}-past", "past", text))
        out.append((f"{ops}-future", "future", mirrored))
    return out


def _interval(interval: Interval, step_ns: int) -> str:
    hi = interval.hi_ns
    assert hi is not None, "the benchmark's formulas are bounded"
    return f"[{interval.lo_ns // step_ns}:{hi // step_ns}]"


def to_reelay(node: Node, step_ns: int = MS) -> str:
    """The formula in reelay's syntax, fully parenthesised, intervals in steps (past only)."""
    r = lambda n: to_reelay(n, step_ns)  # noqa: E731
    if isinstance(node, Atom):
        return f"{{{node.term} {node.op} {node.number}}}"
    if isinstance(node, Not):
        return f"not({r(node.arg)})"
    if isinstance(node, And | Or | Implies):
        word = "and" if isinstance(node, And) else "or" if isinstance(node, Or) else "implies"
        return f"({r(node.left)} {word} {r(node.right)})"
    if isinstance(node, Historically | Once):
        word = "historically" if isinstance(node, Historically) else "once"
        return f"{word}{_interval(node.interval, step_ns)}({r(node.arg)})"
    if isinstance(node, Since):
        return f"({r(node.left)} since{_interval(node.interval, step_ns)} {r(node.right)})"
    raise ValueError(f"reelay is past-time only: no {type(node).__name__}")


def to_rtamt(node: Node, step_ns: int = MS) -> str:
    """The formula in RTAMT's STL syntax, fully parenthesised, intervals in steps."""
    r = lambda n: to_rtamt(n, step_ns)  # noqa: E731
    if isinstance(node, Atom):
        return f"({node.term} {node.op} {node.number})"
    if isinstance(node, Const):
        return "true" if node.value else "false"
    if isinstance(node, Not):
        return f"not({r(node.arg)})"
    if isinstance(node, And | Or):
        return f"({r(node.left)} {'and' if isinstance(node, And) else 'or'} {r(node.right)})"
    if isinstance(node, Always | Eventually | Historically | Once):
        word = {Always: "always", Eventually: "eventually", Historically: "historically", Once: "once"}[type(node)]
        return f"{word}{_interval(node.interval, step_ns)}({r(node.arg)})"
    if isinstance(node, Until | Since):
        word = "until" if isinstance(node, Until) else "since"
        return f"({r(node.left)} {word}{_interval(node.interval, step_ns)} {r(node.right)})"
    raise ValueError(f"no RTAMT form for {type(node).__name__}")  # implies: see the 0.4.10 bug


def trace(states: int, seed: int = 1) -> tuple[list[float], list[float]]:
    """Two streams of uniform random values, one sample each per state."""
    rng = random.Random(seed)
    return [rng.random() for _ in range(states)], [rng.random() for _ in range(states)]


def _import(name: str) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # RTAMT's ANTLR 4.7 imports typing.io
        try:
            return __import__(name)
        except ImportError:
            return None


class Run:
    """One monitor over the trace, built but not fed: :meth:`feed` gives it states ``lo`` to
    ``hi - 1`` in one loop of the peer's own calls; ``verdicts`` collects each state's verdict
    (None: not decided, or not yet)."""

    def __init__(self, states: int) -> None:
        self.verdicts: list[bool | None] = [None] * states
        self.fed = 0  # how many states it was given

    def feed(self, lo: int, hi: int) -> None:
        """Hand states ``lo`` to ``hi - 1`` to the monitor."""
        raise NotImplementedError


class DyknowRun(Run):
    """dyknow's :class:`~dyknow.reasoning.Monitor`: ``push_index`` for one stream, ``push_all`` for two."""

    def __init__(self, formula: Formula, xs: list[float], ys: list[float]) -> None:
        super().__init__(len(xs))
        self.monitor = Monitor(formula)
        terms = self.monitor.terms
        self.one = len(terms) == 1
        self.series = xs if terms[0] == "x" else ys
        self.pairs = list(zip(xs, ys, strict=True)) if terms[0] == "x" else list(zip(ys, xs, strict=True))

    def feed(self, lo: int, hi: int) -> None:
        """Push the states, record the verdicts returned."""
        out = self.verdicts
        if self.one:
            push, series = self.monitor.push_index, self.series
            for i in range(lo, hi):
                for verdict in push(0, i * MS, series[i]):
                    out[verdict.state] = verdict.verdict
        else:
            push_all, pairs = self.monitor.push_all, self.pairs
            for i in range(lo, hi):
                for verdict in push_all(i * MS, pairs[i]):
                    out[verdict.state] = verdict.verdict


class ReelayRun(Run):
    """reelay's discrete-time Boolean monitor (``condense=False``: a verdict every update)."""

    def __init__(self, reelay: Any, formula: Formula, xs: list[float], ys: list[float]) -> None:
        super().__init__(len(xs))
        self.monitor = reelay.discrete_timed_monitor(pattern=to_reelay(formula.root), condense=False)
        names = {str(t) for t in formula.terms}
        self.inputs = (
            [{"x": x} for x in xs]
            if names == {"x"}
            else [{"y": y} for y in ys]
            if names == {"y"}
            else [{"x": x, "y": y} for x, y in zip(xs, ys, strict=True)]
        )

    def feed(self, lo: int, hi: int) -> None:
        """Update the monitor with each state's values, record its verdicts."""
        update, inputs, out = self.monitor.update, self.inputs, self.verdicts
        for i in range(lo, hi):
            out[i] = update(inputs[i])["value"]


class RtamtRun(Run):
    """RTAMT's discrete-time STL specification (pastified for a future formula): the sign of its
    robustness is the verdict, of the state ``horizon`` steps back for a future formula."""

    def __init__(self, rtamt: Any, formula: Formula, xs: list[float], ys: list[float], *, future: bool) -> None:
        super().__init__(len(xs))
        spec = rtamt.StlDiscreteTimeSpecification()
        spec.declare_var("x", "float")
        spec.declare_var("y", "float")
        spec.spec = to_rtamt(formula.root)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            spec.parse()
            if future:
                spec.pastify()
        self.spec = spec
        self.shift = formula.horizon_ns // MS if future else 0
        self.inputs = [[("x", x), ("y", y)] for x, y in zip(xs, ys, strict=True)]

    def feed(self, lo: int, hi: int) -> None:
        """Update the specification at each step, record the verdicts its robustness gives."""
        update, inputs, out, shift = self.spec.update, self.inputs, self.verdicts, self.shift
        for i in range(lo, hi):
            robustness = update(i, inputs[i])
            if i >= shift:
                out[i - shift] = None if robustness == 0 else robustness > 0


def per_state_us(make: Callable[[], Run], window: int, states: int, repeat: int, budget_s: float) -> tuple[float, int, Run]:
    """The best of ``repeat`` runs, in microseconds per state, timed after the first window of
    states (the steady state), over at most ``budget_s`` seconds of each run; how many states
    that figure was measured over; and the first run (its verdicts). A monitor so slow that its
    first run took ten budgets is run once."""
    best, measured = float("inf"), 0
    first: Run | None = None
    chunk = 200
    for _ in range(repeat):
        started = time.perf_counter()
        run = make()
        run.feed(0, window)  # the windows fill: not timed
        lo, elapsed = window, 0.0
        while lo < states and (elapsed < budget_s or lo - window < chunk):
            hi = min(states, lo + chunk)
            t0 = time.perf_counter()
            run.feed(lo, hi)
            elapsed += time.perf_counter() - t0
            lo = hi
        run.fed = lo
        first = first or run
        if elapsed / (lo - window) < best:
            best, measured = elapsed / (lo - window), lo - window
        if time.perf_counter() - started > 10 * budget_s:
            break
    assert first is not None
    return best * 1e6, measured, first


def _agreement(ours: list[bool | None], theirs: list[bool | None]) -> bool:
    """Whether two runs agree on every state both decided (and there are some)."""
    pairs = [(a, b) for a, b in zip(ours, theirs, strict=True) if a is not None and b is not None]
    return len(pairs) > 0 and all(a == b for a, b in pairs)


def _figure(row: dict[str, Any], key: str, width: int) -> str:
    return f"{row[key]:>{width - 2}.2f}us" if key in row else f"{'-':>{width}}"


def per_state(windows: list[int], states: int, repeat: int, budget_s: float) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """Measure every formula and window on every monitor that supports it; print a table."""
    reelay, rtamt = _import("reelay"), _import("rtamt")
    peers = {
        "reelay": "reelay 25 (C++), discrete time" if reelay else "not installed",
        "rtamt": "RTAMT 0.4.10 (Python), discrete time" if rtamt else "not installed",
    }
    print(f"{'formula':>10} {'window':>6} {'dyknow':>9} {'reelay':>9} {'RTAMT':>10} {'target':>32}  verdicts")
    rows = []
    for window in windows:
        n = window + states
        xs, ys = trace(n)
        for name, kind, text in formulas(window):
            formula = parse(text)
            future = kind == "future"
            row: dict[str, Any] = {"formula": name, "kind": kind, "operators": formula.operators, "window": window, "text": text}
            makers: dict[str, Callable[[], Run]] = {"dyknow": functools.partial(DyknowRun, formula, xs, ys)}
            if reelay is not None and not future:
                makers["reelay"] = functools.partial(ReelayRun, reelay, formula, xs, ys)
            if rtamt is not None:
                makers["rtamt"] = functools.partial(RtamtRun, rtamt, formula, xs, ys, future=future)
            runs: dict[str, Run] = {}
            for peer, make in makers.items():
                us, measured, runs[peer] = per_state_us(make, window, n, repeat, budget_s)
                row[f"{peer}_us"], row[f"{peer}_states"] = round(us, 3), measured
            # the same verdicts, where both decided, over the states both were given
            ours = runs["dyknow"]
            row["agree"] = {
                peer: _agreement(ours.verdicts[: run.fed], run.verdicts[: run.fed]) for peer, run in runs.items() if peer != "dyknow"
            }
            theirs = {peer: row[f"{peer}_us"] for peer in makers if peer != "dyknow"}
            if theirs:
                fastest = min(theirs, key=lambda p: theirs[p])
                row["target_us"], row["target_peer"] = theirs[fastest], fastest
                row["met"] = row["dyknow_us"] <= row["target_us"]
            rows.append(row)
            target = (
                f"<= {row['target_us']:.2f}us ({row['target_peer']}): {'met' if row['met'] else 'MISSED'}"
                if "target_us" in row
                else "no peer"
            )
            agree = ", ".join(f"{p} {'agree' if ok else 'DIFFER'}" for p, ok in row["agree"].items()) or "-"
            figures = f"{_figure(row, 'dyknow_us', 9)} {_figure(row, 'reelay_us', 9)} {_figure(row, 'rtamt_us', 10)}"
            print(f"{name:>10} {window:>6} {figures} {target:>32}  {agree}", flush=True)
    return rows, peers


class LatencySink(Unit):
    """Receives the verdicts; while ``recording`` is set, keeps each one's age since its origin
    (the time the term's sample was published) at arrival, in nanoseconds."""

    def setup(self) -> None:
        """Start empty, not recording."""
        self.latencies_ns: list[int] = []
        self.count = 0
        self.recording = False

    def on_message(self, port: str, msg: Message) -> None:
        """Count the verdict and, while recording, keep its latency."""
        self.count += 1
        if self.recording:
            self.latencies_ns.append(time.time_ns() - msg.origin_ns)


MONITORS_FORMULA = "historically[0, 1s] Battery(r{k}) > 0.2"


def _drive(sources: list[Any], rate_hz: float, stop: threading.Event, sent: list[int]) -> None:
    """Every source once per period, spread evenly over it, until ``stop``; counts into ``sent``."""
    rng = random.Random(3)
    values = [rng.random() for _ in range(4096)]
    period, count = 1.0 / rate_hz, len(sources)
    start = time.perf_counter()
    i = 0
    while not stop.is_set():
        cycle, k = divmod(i, count)
        sleep_until(start + cycle * period + k * period / count)
        sources[k].emit(values[i % 4096])
        i += 1
    sent[0] = i


def _feed(manager: Manager, count: int, rate_hz: float, seconds: float, warmup_s: float, on_record: Callable[[bool], None]) -> dict[str, Any]:
    """Spawn the sources and the latency sink in ``manager``, drive them, record the latencies
    for ``seconds`` after ``warmup_s`` (``on_record(True/False)`` around the recording)."""
    manager.spawn("latency-sink", "sink", bindings={"in": "bench/verdicts/**"})
    sources = []
    for k in range(count):
        manager.spawn("bench-source", f"s{k}", bindings={"out": f"bench/term/{k}"})
        sources.append(manager.unit(f"s{k}"))
    deadline = time.monotonic() + 60
    while not all(source.has_subscribers("out") for source in sources):  # every monitor is listening
        if time.monotonic() > deadline:
            raise RuntimeError("the monitors did not subscribe within 60 s")
        time.sleep(0.05)
    receiver: Any = manager.unit("sink")  # a LatencySink of the module "reasoning" (this script runs as __main__)
    stop, sent = threading.Event(), [0]
    driver = threading.Thread(target=_drive, args=(sources, rate_hz, stop, sent), name="bench-driver", daemon=True)
    driver.start()
    time.sleep(warmup_s)
    on_record(True)
    receiver.recording = True
    wall0, got0 = time.perf_counter(), receiver.count
    time.sleep(seconds)
    receiver.recording = False
    wall1, got1 = time.perf_counter(), receiver.count
    on_record(False)
    stop.set()
    driver.join(5)
    latencies_ms = [ns / 1e6 for ns in receiver.latencies_ns]
    return {
        "seconds": round(wall1 - wall0, 2),
        "samples_sent": sent[0],
        "verdicts_per_s": round((got1 - got0) / (wall1 - wall0), 1),
        "latency_p50_ms": percentile(latencies_ms, 50),
        "latency_p99_ms": percentile(latencies_ms, 99),
        "latency_max_ms": round(max(latencies_ms), 3) if latencies_ms else float("nan"),
        "sink_dropped": sum(p.dropped for p in manager.get_statistics("sink").ports),
    }


def _specs() -> list[TransformationSpec]:
    return [
        TransformationSpec(label="bench-source", source="dyknow.testing:Source", ports=(Port("out", "out"),)),
        TransformationSpec(label="latency-sink", source="reasoning:LatencySink", ports=(Port("in", "in", queue=1 << 20),)),
        monitor_spec(MONITORS_FORMULA.format(k=0), label="monitor"),
    ]


def monitors(count: int, rate_hz: float, seconds: float, warmup_s: float, core: int, remote: bool) -> dict[str, Any]:
    """``count`` monitors of a past formula, each fed by its own source at ``rate_hz``, in one
    manager whose process runs on CPU ``core``; the latency from each sample to its verdict.

    ``remote``: the sources and the sink run in another process (on another core when there is
    one), so each sample and each verdict crosses Zenoh over loopback; else all in one process.
    """
    os.sched_setaffinity(0, {core})  # before any thread starts: Zenoh's, the lanes', the driver's
    limits = Limits(max_units=2 * count + 10)
    listen = [f"tcp/127.0.0.1:{free_ports(1)[0]}"] if remote else []
    with Manager("reasoning-bench", specs=_specs(), listen=listen, serve=False, limits=limits) as manager:
        t0 = time.perf_counter()
        for k in range(count):
            bindings = {"t0": f"bench/term/{k}", "verdicts": f"bench/verdicts/{k}"}
            manager.spawn("monitor", f"m{k}", params={"formula": MONITORS_FORMULA.format(k=k)}, bindings=bindings)
        spawn_s = time.perf_counter() - t0
        cpu: dict[bool, tuple[float, float]] = {}

        def on_record(start: bool) -> None:
            cpu[start] = (cpu_seconds([os.getpid()]), time.perf_counter())

        if remote:
            argv = [sys.executable, __file__, "--feeder", listen[0], "--monitors", str(count), "--rate-hz", str(rate_hz)]
            argv += ["--seconds", str(seconds), "--warmup", str(warmup_s), "--core", str((core + 1) % (os.cpu_count() or 1))]
            feeder = Proc(argv)
            try:
                feeder.next_json(120, phase="recording")
                on_record(True)
                fed = feeder.next_json(seconds + 30, phase="recorded")
                on_record(False)
                fed = feeder.next_json(60, phase="done")
            finally:
                feeder.close()
        else:
            fed = _feed(manager, count, rate_hz, seconds, warmup_s, on_record)
        dropped = sum(p.dropped for k in range(count) for p in manager.get_statistics(f"m{k}").ports)
        late = sum(p.rejected for k in range(count) for p in manager.get_statistics(f"m{k}").ports)
    (cpu0, wall0), (cpu1, wall1) = cpu[True], cpu[False]
    return {
        "monitors": count,
        "rate_hz": rate_hz,
        "formula": MONITORS_FORMULA,
        "remote": remote,
        "core": core,
        "spawn_s": round(spawn_s, 2),
        **{k: v for k, v in fed.items() if k != "phase"},
        "expected_per_s": count * rate_hz,
        "cpu_percent": round(100 * (cpu1 - cpu0) / (wall1 - wall0), 1),
        "dropped": dropped + fed["sink_dropped"],
        "late": late,
        "target_p99_ms": 1.0,
    }


def feeder(endpoint: str, count: int, rate_hz: float, seconds: float, warmup_s: float, core: int) -> int:
    """The other process of ``--remote``: sources and the sink, connected to the monitors' manager;
    prints JSON lines as it starts and stops recording, then its figures."""
    os.sched_setaffinity(0, {core})

    def on_record(start: bool) -> None:
        print(json.dumps({"phase": "recording" if start else "recorded"}), flush=True)

    with Manager("reasoning-feeder", specs=_specs(), connect=[endpoint], listen=[], serve=False, limits=Limits(max_units=count + 10)) as manager:
        result = _feed(manager, count, rate_hz, seconds, warmup_s, on_record)
    print(json.dumps({"phase": "done", **result}), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the per-state comparison (default) or the end-to-end run of many monitors (``--monitors``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--windows", default="10,100,1000", help="window lengths in states (default 10,100,1000)")
    parser.add_argument("--states", type=int, default=20_000, help="states timed per run, after the first window (default 20,000)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure, the best kept (default 3)")
    parser.add_argument("--budget", type=float, default=5.0, metavar="S", help="seconds timed per run at most (RTAMT is slow; default 5)")
    parser.add_argument("--quick", action="store_true", help="a short run: 1,000 states after the window, one run each, 0.5 s budget")
    parser.add_argument("--monitors", type=int, metavar="N", help="instead: N monitors at --rate-hz in one manager on one core, end to end")
    parser.add_argument("--rate-hz", type=float, default=20.0, help="samples per second per monitor (default 20)")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long latencies are recorded with --monitors (default 10)")
    parser.add_argument("--warmup", type=float, default=3.0, metavar="S", help="seconds before recording with --monitors (default 3)")
    parser.add_argument("--core", type=int, default=0, help="the CPU the --monitors run is pinned to (default 0)")
    parser.add_argument("--remote", action="store_true", help="with --monitors: sources and sink in another process, over Zenoh")
    parser.add_argument("--feeder", metavar="ENDPOINT", help=argparse.SUPPRESS)  # the other process of --remote
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    if args.feeder:
        return feeder(args.feeder, args.monitors, args.rate_hz, args.seconds, args.warmup, args.core)
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}")
    if args.monitors:
        result = monitors(args.monitors, args.rate_hz, args.seconds, args.warmup, args.core, args.remote)
        met = result["latency_p99_ms"] <= result["target_p99_ms"]
        where = "sources and sink in another process, over Zenoh" if result["remote"] else "sources and sink in the same process"
        print(
            f"{result['monitors']} monitors at {result['rate_hz']:g} Hz in one manager on core {result['core']} ({where}): {result['verdicts_per_s']:.0f} verdicts/s "
            f"(expected {result['expected_per_s']:.0f}), CPU {result['cpu_percent']:.0f}%, dropped {result['dropped']}, late {result['late']}"
        )
        print(
            f"sample to verdict: p50 {result['latency_p50_ms']:.3f} ms, p99 {result['latency_p99_ms']:.3f} ms (target <= 1 ms: "
            f"{'met' if met else 'MISSED'}), max {result['latency_max_ms']:.3f} ms"
        )
        if args.json:
            write_json(args.json, {"machine": info, "monitors": {**result, "met": met}})
        return 0
    windows = [int(w) for w in args.windows.split(",")]
    states, repeat, budget = (1_000, 1, 0.5) if args.quick else (args.states, args.repeat, args.budget)
    rows, peers = per_state(windows, states, repeat, budget)
    checked = [r for r in rows if "met" in r]
    met = sum(1 for r in checked if r["met"])
    print(f"target (dyknow at most the faster peer per state): met on {met} of {len(checked)} formulas and windows")
    if args.json:
        write_json(
            args.json,
            {
                "machine": info,
                "peers": peers,
                "states": states,
                "repeat": repeat,
                "budget_s": budget,
                "results": rows,
                "targets_met": met,
                "targets": len(checked),
            },
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
