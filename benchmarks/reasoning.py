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
    python benchmarks/reasoning.py --step 1000 --formulas 10   # the monitor unit's own step, no transport
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
import tracemalloc
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
    Num,
    Once,
    Or,
    Since,
    Stream,
    Until,
)

from harness import Proc, cpu_seconds, free_ports, machine, percentile, sleep_until, write_json

MS = 1_000_000


STEP_NS = 10 * MS
"""The trace's sample period: 100 Hz, what a robot's fast streams run at."""

WINDOWS = {"10ms": 10 * MS, "1s": 1000 * MS, "100s": 100_000 * MS}
"""The windows every formula is measured with (item 7: within 1.5x of each other)."""


def _ms(ns: int) -> str:
    return f"{ns // MS}ms" if ns % MS == 0 else f"{ns}ns"


def formulas(window_ns: int) -> list[tuple[str, str, str]]:
    """``(name, kind, formula)`` for a window of ``window_ns``: 1, 5 and 20 operators, past and
    future (the future ones mirror the past ones operator for operator); the response property
    ``always[0, W] (p implies eventually[0, W/5] q)``; and the aggregate ``avg[0, W] x < 0.5``."""
    w, h = _ms(window_ns), _ms(max(MS, window_ns // 2))
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
    out.append(("response", "future", f"always[0, {w}] (x > 0.9 implies eventually[0, {_ms(window_ns // 5)}] y > 0.5)"))
    out.append(("avg", "aggregate", f"avg[0, {w}] x < 0.5"))
    return out


def _atom(node: Atom) -> tuple[str, str, str]:
    """``(stream, op, number)`` of an atom comparing a stream with a number (all the benchmark writes)."""
    left, right = node.left, node.right
    if not isinstance(left, Stream) or left.fields or node.op is None or not isinstance(right, Num):
        raise ValueError(f"the peers' form is written for 'stream OP number' atoms only, not {node}")
    return str(left.term), node.op, str(right)


def _steps(interval: Interval, step_ns: int) -> tuple[int, int]:
    """The interval in whole steps: the states at ``k`` steps from now for ``k`` in it."""
    hi = interval.hi_ns
    assert hi is not None, "the benchmark's formulas are bounded"
    return -(-interval.lo_ns // step_ns), hi // step_ns


def horizon_steps(node: Node, step_ns: int = STEP_NS) -> int:
    """How many states ahead a verdict of ``node`` reads, in the peers' step units."""
    if isinstance(node, Atom | Const):
        return 0
    if isinstance(node, Not | Historically | Once):
        return horizon_steps(node.arg, step_ns)
    if isinstance(node, And | Or | Implies | Since):
        return max(horizon_steps(node.left, step_ns), horizon_steps(node.right, step_ns))
    if isinstance(node, Always | Eventually):
        return _steps(node.interval, step_ns)[1] + horizon_steps(node.arg, step_ns)
    if isinstance(node, Until):
        return _steps(node.interval, step_ns)[1] + max(horizon_steps(node.left, step_ns), horizon_steps(node.right, step_ns))
    raise ValueError(f"no horizon for {type(node).__name__}")


def to_reelay(node: Node, step_ns: int = STEP_NS, delay: int = 0) -> str:
    """The formula in reelay's syntax, fully parenthesised, intervals in steps. A future formula
    is written in its past form, as a user of reelay (past-time only) would write it: evaluated
    ``delay`` states late (its horizon, at the root), each future operator ``[a, b]`` becomes
    the past one over ``[0, b - a]`` of its operand ``b`` states less late, and an atom still
    ``d`` states late reads ``once[d:d]``. ``until`` has no such form here (it raises). A window
    of one state, ``[0:0]``, is written as its operand: reelay 25 reads ``once[0:0]`` and
    ``historically[0:0]`` as unbounded (``once[0:0] p`` true ever after the first true p)."""
    r = lambda n, d=delay: to_reelay(n, step_ns, d)  # noqa: E731
    if isinstance(node, Atom):
        name, op, number = _atom(node)
        text = f"{{{name} {op} {number}}}"
        return f"once[{delay}:{delay}]({text})" if delay else text
    if isinstance(node, Not):
        return f"not({r(node.arg)})"
    if isinstance(node, And | Or | Implies):
        word = "and" if isinstance(node, And) else "or" if isinstance(node, Or) else "implies"
        return f"({r(node.left)} {word} {r(node.right)})"
    if isinstance(node, Historically | Once):  # a past window commutes with the delay
        lo, hi = _steps(node.interval, step_ns)
        word = "historically" if isinstance(node, Historically) else "once"
        return r(node.arg) if hi == 0 else f"{word}[{lo}:{hi}]({r(node.arg)})"
    if isinstance(node, Since):
        lo, hi = _steps(node.interval, step_ns)
        return f"({r(node.left)} since[{lo}:{hi}] {r(node.right)})"
    if isinstance(node, Always | Eventually):
        lo, hi = _steps(node.interval, step_ns)
        assert delay >= hi, "the delay covers the horizon"
        word = "historically" if isinstance(node, Always) else "once"
        return r(node.arg, delay - hi) if hi == lo else f"{word}[0:{hi - lo}]({r(node.arg, delay - hi)})"
    raise ValueError(f"no past form written for {type(node).__name__}")


def to_rtamt(node: Node, step_ns: int = STEP_NS) -> str:
    """The formula in RTAMT's STL syntax, fully parenthesised, intervals in steps; ``a implies b``
    as ``not a or b`` (RTAMT 0.4.10 pastifies ``->`` wrongly: see monitoring-facts)."""
    r = lambda n: to_rtamt(n, step_ns)  # noqa: E731
    if isinstance(node, Atom):
        name, op, number = _atom(node)
        return f"({name} {op} {number})"
    if isinstance(node, Const):
        return "true" if node.value else "false"
    if isinstance(node, Not):
        return f"not({r(node.arg)})"
    if isinstance(node, And | Or):
        return f"({r(node.left)} {'and' if isinstance(node, And) else 'or'} {r(node.right)})"
    if isinstance(node, Implies):
        return f"(not({r(node.left)}) or {r(node.right)})"
    if isinstance(node, Always | Eventually | Historically | Once):
        word = {Always: "always", Eventually: "eventually", Historically: "historically", Once: "once"}[type(node)]
        lo, hi = _steps(node.interval, step_ns)
        return f"{word}[{lo}:{hi}]({r(node.arg)})"
    if isinstance(node, Until | Since):
        word = "until" if isinstance(node, Until) else "since"
        lo, hi = _steps(node.interval, step_ns)
        return f"({r(node.left)} {word}[{lo}:{hi}] {r(node.right)})"
    raise ValueError(f"no RTAMT form for {type(node).__name__}")


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
    (None: not decided, or not yet), indexed by the state it is about."""

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
                for verdict in push(0, i * STEP_NS, series[i]):
                    out[verdict.state] = verdict.verdict
        else:
            push_all, pairs = self.monitor.push_all, self.pairs
            for i in range(lo, hi):
                for verdict in push_all(i * STEP_NS, pairs[i]):
                    out[verdict.state] = verdict.verdict


class ReelayRun(Run):
    """reelay's discrete-time Boolean monitor (``condense=False``: a verdict every update), of the
    formula or, for a future one, of its past form (:func:`to_reelay`): its verdict at state
    ``i`` is the formula's at ``i - delay``."""

    def __init__(self, reelay: Any, formula: Formula, xs: list[float], ys: list[float]) -> None:
        super().__init__(len(xs))
        self.delay = horizon_steps(formula.root)
        self.pattern = to_reelay(formula.root, STEP_NS, self.delay)
        self.monitor = reelay.discrete_timed_monitor(pattern=self.pattern, condense=False)
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
        update, inputs, out, delay = self.monitor.update, self.inputs, self.verdicts, self.delay
        for i in range(lo, hi):
            value = update(inputs[i])["value"]
            if i >= delay:
                out[i - delay] = value


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
        self.shift = horizon_steps(formula.root) if future else 0
        self.inputs = [[("x", x), ("y", y)] for x, y in zip(xs, ys, strict=True)]

    def feed(self, lo: int, hi: int) -> None:
        """Update the specification at each step, record the verdicts its robustness gives."""
        update, inputs, out, shift = self.spec.update, self.inputs, self.verdicts, self.shift
        for i in range(lo, hi):
            robustness = update(i, inputs[i])
            if i >= shift:
                out[i - shift] = None if robustness == 0 else robustness > 0


def interleaved(
    makers: dict[Any, tuple[Callable[[], Run], int]], states: int, repeat: int, budget_s: float
) -> tuple[dict[Any, float], dict[Any, int], dict[Any, Run]]:
    """Every run's cost per state, in microseconds, measured in one interleaved run: each is
    built and given its first ``fill`` states (its windows fill: not timed), then each is given
    its next chunk of 200 states in turn, each chunk timed, so a change in the machine's load
    falls on all of them alike (every peer, every window). A run is given ``states`` states, or
    fewer when its timed total passes ``budget_s``. Of ``repeat`` such runs, the best per run is
    kept (the machine is shared: the least disturbed). Also how many states each figure was
    measured over, and the first run of each (its verdicts)."""
    best = {key: float("inf") for key in makers}
    measured = dict.fromkeys(makers, 0)
    first: dict[Any, Run] = {}
    chunk = 200
    for _ in range(repeat):
        runs = {key: make() for key, (make, _fill) in makers.items()}
        for key, run in runs.items():
            fill = makers[key][1]
            run.feed(0, fill)
            run.fed = fill
        elapsed = dict.fromkeys(runs, 0.0)
        active = list(runs)
        j = 0
        while active:
            for key in list(active):
                run, fill = runs[key], makers[key][1]
                lo, hi = fill + j * chunk, min(fill + states, fill + (j + 1) * chunk)
                if lo >= hi:
                    active.remove(key)
                    continue
                t0 = time.perf_counter()
                run.feed(lo, hi)
                elapsed[key] += time.perf_counter() - t0
                run.fed = hi
                if elapsed[key] > budget_s:
                    active.remove(key)
            j += 1
        for key, run in runs.items():
            first.setdefault(key, run)
            cost = elapsed[key] / (run.fed - makers[key][1])
            if cost < best[key]:
                best[key], measured[key] = cost, run.fed - makers[key][1]
    return {key: us * 1e6 for key, us in best.items()}, measured, first


def _agreement(ours: list[bool | None], theirs: list[bool | None]) -> bool:
    """Whether two runs agree on every state both decided (and there are some)."""
    pairs = [(a, b) for a, b in zip(ours, theirs, strict=True) if a is not None and b is not None]
    return len(pairs) > 0 and all(a == b for a, b in pairs)


def _figure(row: dict[str, Any], key: str, width: int) -> str:
    return f"{row[key]:>{width - 2}.2f}us" if key in row else f"{'-':>{width}}"


def per_state(windows: list[str], states: int, repeat: int, budget_s: float, rtamt_max: int) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """Measure every formula at every window on every monitor that supports it, all windows and
    peers of one formula interleaved; print a table."""
    reelay, rtamt = _import("reelay"), _import("rtamt")
    peers = {
        "reelay": "reelay 25 (C++), discrete time; future formulas in their past form" if reelay else "not installed",
        "rtamt": f"RTAMT 0.4.10 (Python), discrete time, pastified; windows up to {rtamt_max} states" if rtamt else "not installed",
    }
    print(
        f"per state, 100 Hz data, {states:,} states timed after the windows fill, best of {repeat} runs, each formula's windows and peers interleaved; load {_load()}"
    )
    print(f"{'formula':>10} {'window':>6} {'dyknow':>9} {'reelay':>9} {'RTAMT':>10} {'target':>32}  verdicts")
    rows = []
    fills = {label: 2 * (WINDOWS[label] // STEP_NS) + 2 for label in windows}  # the nested windows full: the steady state
    xs, ys = trace(max(fills.values()) + states)
    names = [(name, kind) for name, kind, _text in formulas(WINDOWS[windows[0]])]
    for index, (name, kind) in enumerate(names):
        makers: dict[tuple[str, str], tuple[Callable[[], Run], int]] = {}
        by_window: dict[str, dict[str, Any]] = {}
        for label in windows:
            text = formulas(WINDOWS[label])[index][2]
            formula = parse(text)
            fill = fills[label]
            row: dict[str, Any] = {"formula": name, "kind": kind, "operators": formula.operators, "window": label, "text": text}
            makers[(label, "dyknow")] = (functools.partial(DyknowRun, formula, xs, ys), fill)
            if reelay is not None and kind != "aggregate":
                try:
                    row["reelay_form"] = to_reelay(formula.root, STEP_NS, horizon_steps(formula.root))
                    makers[(label, "reelay")] = (functools.partial(ReelayRun, reelay, formula, xs, ys), fill)
                except ValueError as exc:
                    row["reelay_form"] = str(exc)
            if rtamt is not None and kind != "aggregate" and WINDOWS[label] // STEP_NS <= rtamt_max:
                makers[(label, "rtamt")] = (functools.partial(RtamtRun, rtamt, formula, xs, ys, future=kind == "future"), fill)
            by_window[label] = row
        costs, measured, runs = interleaved(makers, states, repeat, budget_s)
        for label, row in by_window.items():
            here = [peer for (w, peer) in makers if w == label]
            for peer in here:
                row[f"{peer}_us"], row[f"{peer}_states"] = round(costs[(label, peer)], 3), measured[(label, peer)]
            # the same verdicts, where both decided, over the states both were given
            ours = runs[(label, "dyknow")]
            row["agree"] = {}
            for peer in here:
                if peer != "dyknow":
                    run = runs[(label, peer)]
                    fed = min(ours.fed, run.fed)
                    row["agree"][peer] = _agreement(ours.verdicts[:fed], run.verdicts[:fed])
            theirs = {peer: row[f"{peer}_us"] for peer in here if peer != "dyknow"}
            if theirs:
                fastest = min(theirs, key=lambda p: theirs[p])
                row["target_us"], row["target_peer"] = theirs[fastest], fastest
                row["met"] = row["dyknow_us"] <= row["target_us"]
            row["load"] = _load()
            rows.append(row)
    rows = [row for label in windows for row in rows if row["window"] == label]  # window by window
    for row in rows:
        label = row["window"]
        target = (
            f"<= {row['target_us']:.2f}us ({row['target_peer']}): {'met' if row['met'] else 'MISSED'}" if "target_us" in row else "no peer"
        )
        agree = ", ".join(f"{p} {'agree' if ok else 'DIFFER'}" for p, ok in row["agree"].items()) or "-"
        figures = f"{_figure(row, 'dyknow_us', 9)} {_figure(row, 'reelay_us', 9)} {_figure(row, 'rtamt_us', 10)}"
        print(f"{row['formula']:>10} {label:>6} {figures} {target:>32}  {agree}", flush=True)
    return rows, peers


def flatness(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per formula measured at several windows: the largest cost over the smallest (target <= 1.5);
    and the aggregate at the longest window over it at 1 s (target: no slower, within 10 %, the
    run-to-run noise of these figures on a shared machine)."""
    out = []
    by_name: dict[str, dict[str, float]] = {}
    for row in rows:
        by_name.setdefault(row["formula"], {})[row["window"]] = row["dyknow_us"]
    for name, costs in by_name.items():
        if len(costs) < 2:
            continue
        ratio = max(costs.values()) / min(costs.values())
        item = {"formula": name, "costs_us": costs, "ratio": round(ratio, 2), "target": 1.5, "met": ratio <= 1.5}
        out.append(item)
        print(
            f"flat in the window: {name:>10} {' '.join(f'{w} {c:.2f}us' for w, c in costs.items())}: max/min {ratio:.2f} (target <= 1.5: {'met' if ratio <= 1.5 else 'MISSED'})"
        )
    avg = by_name.get("avg", {})
    if "1s" in avg and "100s" in avg:
        ratio = avg["100s"] / avg["1s"]
        met = ratio <= 1.1
        out.append({"formula": "avg", "aggregate_100s_over_1s": round(ratio, 2), "target": "no slower (within 10 %)", "met": met})
        print(
            f"aggregate avg[0, 100s] {avg['100s']:.2f}us against avg[0, 1s] {avg['1s']:.2f}us: {ratio:.2f}x (target no slower, within the 10 % noise: {'met' if met else 'MISSED'})"
        )
    return out


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


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
OBJECTS_FORMULA = "foreach t in Track(field).id: historically[0, 1s] Track(field).speed < 3"
"""Objects' speeds are uniform in [0, 1) but one sample in 500, 3.5: each object's verdict
turns false for a second now and then (what ``--changes-only`` publishes)."""


KEEPING_UP_MS = 100.0
"""End to end, a monitor keeps up when its sample-to-verdict p50 is under this (a backlog grows it
to seconds); with less than all of a core, that is "within one core"."""


def objects_formula(k: int) -> str:
    """The ``k``-th of ``--formulas`` over the one tracker stream: :data:`OBJECTS_FORMULA` with
    its bound raised by ``k`` tenths (each its own monitor of every object)."""
    return OBJECTS_FORMULA if k == 0 else OBJECTS_FORMULA.replace("< 3", f"< {3 + k / 10:g}")


def _drive(sources: list[Any], rate_hz: float, stop: threading.Event, sent: list[int], objects: int, frame: int = 1) -> None:
    """Every source (or, with ``objects``, every object of the one source, ``frame`` objects a
    message) once per period, spread evenly over it, until ``stop``; counts samples into ``sent``."""
    rng = random.Random(3)
    values = [rng.random() for _ in range(4096)]
    speeds = [3.5 if rng.random() < 1 / 500 else rng.random() for _ in range(4096)]
    period = 1.0 / rate_hz
    messages = -(-objects // frame) if objects else len(sources)  # per period
    start = time.perf_counter()
    i = samples = 0
    while not stop.is_set():
        cycle, k = divmod(i, messages)
        sleep_until(start + cycle * period + k * period / messages)
        if objects and frame > 1:
            tracks = [{"id": j, "speed": speeds[(samples + j) % 4096]} for j in range(k * frame, min(objects, (k + 1) * frame))]
            sources[0].emit(tracks)
            samples += len(tracks)
        elif objects:
            sources[0].emit({"id": k, "speed": speeds[i % 4096]})
            samples += 1
        else:
            sources[k].emit(values[i % 4096])
            samples += 1
        i += 1
    sent[0] = samples


def _feed(
    manager: Manager,
    count: int,
    rate_hz: float,
    seconds: float,
    warmup_s: float,
    on_record: Callable[[bool], None],
    objects: bool,
    frame: int = 1,
) -> dict[str, Any]:
    """Spawn the sources and the latency sink in ``manager``, drive them, record the latencies
    for ``seconds`` after ``warmup_s`` (``on_record(True/False)`` around the recording)."""
    manager.spawn("latency-sink", "sink", bindings={"in": "bench/verdicts/**"})
    sources = []
    for k in range(1 if objects else count):
        manager.spawn("bench-source", f"s{k}", bindings={"out": "bench/track" if objects else f"bench/term/{k}"})
        sources.append(manager.unit(f"s{k}"))
    deadline = time.monotonic() + 60
    while not all(source.has_subscribers("out") for source in sources):  # every monitor is listening
        if time.monotonic() > deadline:
            raise RuntimeError("the monitors did not subscribe within 60 s")
        time.sleep(0.05)
    receiver: Any = manager.unit("sink")  # a LatencySink of the module "reasoning" (this script runs as __main__)
    stop, sent = threading.Event(), [0]
    driver = threading.Thread(
        target=_drive, args=(sources, rate_hz, stop, sent, count if objects else 0, frame), name="bench-driver", daemon=True
    )
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
        monitor_spec(OBJECTS_FORMULA, label="objects-monitor", queue=1 << 17),
    ]


def _rss_bytes() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def monitors(
    count: int,
    rate_hz: float,
    seconds: float,
    warmup_s: float,
    core: int,
    remote: bool,
    *,
    objects: bool = False,
    changes_only: bool = False,
    frame: int = 1,
    formulas: int = 1,
    separate: bool = False,
) -> dict[str, Any]:
    """``count`` monitors of a past formula, each fed by its own source at ``rate_hz`` (or, with
    ``objects``, one ``foreach`` monitor of ``count`` objects, each sampled at ``rate_hz`` on one
    stream; ``formulas`` such formulas over that stream, served by one unit, or with
    ``separate`` by a unit each), in one manager whose process runs on CPU ``core``; the latency
    from each sample to its verdict, the verdicts decided per second, the CPU the process took,
    its memory.

    ``remote``: the sources and the sink run in another process (on another core when there is
    one), so each sample and each verdict crosses Zenoh over loopback; else all in one process.
    """
    os.sched_setaffinity(0, {core})  # before any thread starts: Zenoh's, the lanes', the driver's
    limits = Limits(max_units=2 * count + 10)
    listen = [f"tcp/127.0.0.1:{free_ports(1)[0]}"] if remote else []
    with Manager("reasoning-bench", specs=_specs(), listen=listen, serve=False, limits=limits) as manager:
        rss0 = _rss_bytes()
        t0 = time.perf_counter()
        if objects and formulas > 1 and not separate:
            named = {f"f{k}": objects_formula(k) for k in range(formulas)}
            manager.add_transformation(
                monitor_spec(named, label="shared-monitor", queue=1 << 17, max_objects=count, changes_only=changes_only)
            )
            manager.spawn("shared-monitor", "m0", bindings={"t0": "bench/track", "verdicts": "bench/verdicts/0"})
        elif objects:
            for k in range(formulas):
                params = {"formula": objects_formula(k), "max_objects": count, "changes_only": changes_only}
                manager.spawn("objects-monitor", f"m{k}", params=params, bindings={"t0": "bench/track", "verdicts": f"bench/verdicts/{k}"})
        else:
            for k in range(count):
                bindings = {"t0": f"bench/term/{k}", "verdicts": f"bench/verdicts/{k}"}
                manager.spawn(
                    "monitor", f"m{k}", params={"formula": MONITORS_FORMULA.format(k=k), "changes_only": changes_only}, bindings=bindings
                )
        spawn_s = time.perf_counter() - t0
        units: list[Any] = (
            [manager.unit(f"m{k}") for k in range(formulas if separate else 1)]
            if objects
            else [manager.unit(f"m{k}") for k in range(count)]
        )
        watched = [m for unit in units for m in unit.monitors.values()]  # every formula's monitor
        cpu: dict[bool, tuple[float, float, int]] = {}

        def on_record(start: bool) -> None:
            cpu[start] = (cpu_seconds([os.getpid()]), time.perf_counter(), sum(m.states for m in watched))

        if remote:
            argv = [
                sys.executable,
                __file__,
                "--feeder",
                listen[0],
                "--objects" if objects else "--monitors",
                str(count),
                "--rate-hz",
                str(rate_hz),
            ]
            argv += [
                "--seconds",
                str(seconds),
                "--warmup",
                str(warmup_s),
                "--core",
                str((core + 1) % (os.cpu_count() or 1)),
                "--frame",
                str(frame),
            ]
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
            fed = _feed(manager, count, rate_hz, seconds, warmup_s, on_record, objects, frame)
        rss1 = _rss_bytes()
        stats = [manager.get_statistics(f"m{k}") for k in range(len(units))]
        dropped = sum(p.dropped for s in stats for p in s.ports)
        late = sum(p.rejected for s in stats for p in s.ports)
        retained = sum(m.retained() for m in watched)
        live = sum(len(m.objects) for m in watched) if objects else count
        refused = sum(m.refused for m in watched) if objects else 0
        nodes = units[0].monitor.body.nodes if objects else units[0].monitor.formula.nodes
    (cpu0, wall0, states0), (cpu1, wall1, states1) = cpu[True], cpu[False]
    return {
        "kind": "objects" if objects else "monitors",
        "monitors": 1 if objects else count,
        "formulas": formulas,
        "units": len(units),
        "instances": live,
        "refused": refused,
        "rate_hz": rate_hz,
        "formula": OBJECTS_FORMULA if objects else MONITORS_FORMULA,
        "changes_only": changes_only,
        "frame": frame,
        "remote": remote,
        "core": core,
        "spawn_s": round(spawn_s, 2),
        **{k: v for k, v in fed.items() if k != "phase"},
        "expected_per_s": count * rate_hz * formulas,
        "decided_per_s": round((states1 - states0) / (wall1 - wall0), 1),
        "cpu_percent": round(100 * (cpu1 - cpu0) / (wall1 - wall0), 1),
        "load": _load(),
        "dropped": dropped + fed["sink_dropped"],
        "late": late,
        "target_p99_ms": 1.0,
        "rss_growth_bytes": rss1 - rss0,
        "retained_states": retained,
        "cells": retained * nodes,
        "bound_bytes": 250 * retained * nodes,
    }


def instance_memory(count: int, rate_hz: float, seconds: float) -> dict[str, Any]:
    """The memory of one ``foreach`` monitor of ``count`` objects at ``rate_hz`` after ``seconds``
    of samples (its window full), measured with ``tracemalloc`` beside the bound stated from the
    formula and the rate: each instance's constant part (measured here, after its first sample)
    plus 250 bytes a cell (:mod:`dyknow.reasoning.progression`), a cell per node and per state
    its windows hold (its past reach over the sample period, and the newest)."""
    from dyknow.reasoning.objects import ObjectMonitor

    tracemalloc.start()
    try:
        monitor = ObjectMonitor(OBJECTS_FORMULA, max_objects=count)
        period = round(1e9 / rate_hz)
        base = tracemalloc.get_traced_memory()[0]
        rng = random.Random(5)
        for k in range(count):
            monitor.push("Track(field)", k * period // count, {"id": k, "speed": rng.random()})
        constant = tracemalloc.get_traced_memory()[0] - base
        for cycle in range(1, round(seconds * rate_hz)):
            for k in range(count):
                monitor.push("Track(field)", cycle * period + k * period // count, {"id": k, "speed": rng.random()})
        used = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    # the states an instance's windows hold at this rate: its reach over the sample period, and the
    # newest; a cell per node and state
    reach = monitor.body.reach_ns or 0
    cells = count * monitor.body.nodes * (reach // period + 2)
    bound = constant + 250 * cells
    return {
        "objects": count,
        "rate_hz": rate_hz,
        "seconds": seconds,
        "bytes": used,
        "bytes_per_object": round(used / count),
        "constant_per_object": round(constant / count),
        "cells": cells,
        "bound_bytes": bound,
        "met": used <= bound,
    }


def feeder(
    endpoint: str, count: int, rate_hz: float, seconds: float, warmup_s: float, core: int, *, objects: bool = False, frame: int = 1
) -> int:
    """The other process of ``--remote``: sources and the sink, connected to the monitors' manager;
    prints JSON lines as it starts and stops recording, then its figures."""
    os.sched_setaffinity(0, {core})

    def on_record(start: bool) -> None:
        print(json.dumps({"phase": "recording" if start else "recorded"}), flush=True)

    with Manager(
        "reasoning-feeder", specs=_specs(), connect=[endpoint], listen=[], serve=False, limits=Limits(max_units=count + 10)
    ) as manager:
        result = _feed(manager, count, rate_hz, seconds, warmup_s, on_record, objects, frame)
    print(json.dumps({"phase": "done", **result}), flush=True)
    return 0


def end_to_end(args: argparse.Namespace) -> dict[str, Any]:
    """``--monitors`` or ``--objects``: run, print the figures beside their targets."""
    objects = bool(args.objects)
    count = args.objects or args.monitors
    result = monitors(
        count,
        args.rate_hz,
        args.seconds,
        args.warmup,
        args.core,
        args.remote,
        objects=objects,
        changes_only=args.changes_only,
        frame=args.frame,
        formulas=args.formulas,
        separate=args.separate,
    )
    met = result["latency_p99_ms"] <= result["target_p99_ms"]
    where = "sources and sink in another process, over Zenoh" if result["remote"] else "sources and sink in the same process"
    what = f"one foreach monitor of {count} objects" if objects else f"{count} monitors"
    if objects and args.formulas > 1:
        served = f"a unit each ({args.formulas} units)" if args.separate else "one unit"
        what = f"{args.formulas} foreach formulas of {count} objects each ({args.formulas * count} instances), served by {served},"
    if objects and args.frame > 1:
        what += f" ({args.frame} a message: a tracker's frame)"
    publish = "changed verdicts only" if args.changes_only else "every verdict"
    # within one core: under 100 % of it, and keeping up (a backlog shows as sample-to-verdict
    # times that grow: p50 over KEEPING_UP_MS); unknown when no verdict was published to time
    p50 = result["latency_p50_ms"]
    cpu_met = None if p50 != p50 else result["cpu_percent"] < 100 and p50 <= KEEPING_UP_MS
    cpu_verdict = {True: "met", False: "MISSED", None: "unknown: no verdict published to time"}[cpu_met]
    print(
        f"{what} at {result['rate_hz']:g} Hz in one manager on core {result['core']} ({where}; {publish} published): "
        f"{result['decided_per_s']:.0f} verdicts decided/s (expected {result['expected_per_s']:.0f}), {result['verdicts_per_s']:.0f} published/s, "
        f"CPU {result['cpu_percent']:.0f}% of a core (target: one core, keeping up: {cpu_verdict}), "
        f"dropped {result['dropped']}, late {result['late']}, refused {result['refused']}; load {result['load']}"
    )
    print(
        f"sample to verdict: p50 {result['latency_p50_ms']:.3f} ms, p99 {result['latency_p99_ms']:.3f} ms (target <= 1 ms: "
        f"{'met' if met else 'MISSED'}), max {result['latency_max_ms']:.3f} ms"
        if result["latency_p99_ms"] == result["latency_p99_ms"]
        else "sample to verdict: no verdict changed while recording, so none was published (run without --changes-only for latencies)"
    )
    result["met"] = met
    result["cpu_met"] = cpu_met
    if objects:
        memory = instance_memory(count, args.rate_hz, 2.0)
        print(
            f"memory of {count} objects{' (of one formula)' if args.formulas > 1 else ''} after 2 s at {args.rate_hz:g} Hz (tracemalloc): {memory['bytes'] / 1e6:.2f} MB, "
            f"{memory['bytes_per_object']} B per object, against the stated bound {memory['bound_bytes'] / 1e6:.2f} MB "
            f"({memory['constant_per_object']} B per object constant + 250 B a cell, {memory['cells']:,} cells for a reach of 1 s): {'met' if memory['met'] else 'MISSED'}; "
            f"the manager's RSS grew {result['rss_growth_bytes'] / 1e6:.1f} MB over the run"
        )
        result["memory"] = memory
    return result


#: Issue 54's target for an object's monitor: made (and ended) in at most this much CPU.
CHURN_TARGET_US = 5.0


def object_churn(count: int, repeat: int = 3) -> dict[str, float]:
    """CPU per object of a ``foreach`` monitor (:data:`OBJECTS_FORMULA`) whose objects each send
    one sample and go (made, pushed, ended by their idle time), and per sample of ten objects
    that stay; the difference is what making and ending an object's monitor costs. The best of
    ``repeat`` runs (process CPU time, so a loaded machine's waits are not counted)."""
    from dyknow.reasoning.objects import ObjectMonitor
    from dyknow.reasoning.syntax import parse

    formula = parse(OBJECTS_FORMULA)

    def per_sample(ids: Callable[[int], str], base: int, idle_ns: int) -> float:
        monitor = ObjectMonitor(formula, reorder_ns=0, max_cells=10**7, idle_ns=idle_ns, max_objects=1_000_000)
        start = time.process_time()
        for i in range(count):  # 1 ms apart
            monitor.push_index(0, base + i * 1_000_000, {"id": ids(i), "speed": 0.4})
        return (time.process_time() - start) / count * 1e6

    # an object silent for 2 ms is ended (each sends one sample); ten objects 10 ms apart stay (idle 10 s)
    churn = min(per_sample(lambda i: f"o{i}", 10**12 * (k + 1), 2_000_000) for k in range(repeat))
    stay = min(per_sample(lambda i: f"o{i % 10}", 10**12 * (k + 1), 10_000_000_000) for k in range(repeat))
    made = churn - stay
    print(f"objects that come and go ({OBJECTS_FORMULA}): {churn:.1f} us CPU per object (one sample each); "
          f"a sample of an object that stays {stay:.1f} us; an object's monitor made and ended {made:.1f} us "
          f"(target <= {CHURN_TARGET_US:g} us: {'met' if made <= CHURN_TARGET_US else 'not met'})")  # fmt: skip
    return {"per_new_object_us": round(churn, 2), "per_sample_us": round(stay, 2), "made_and_ended_us": round(made, 2),
            "target_us": CHURN_TARGET_US, "objects": count}  # fmt: skip


def unit_step(count: int, formulas: int, rounds: int, per_round: int = 10_000) -> dict[str, Any]:
    """The monitor unit's own step per message, without any transport: ``formulas`` foreach
    formulas (:func:`objects_formula`) over ``count`` objects served by one unit, changes only,
    each message one object's sample 50 us after the last (20 Hz per object at 1,000), handed to
    the unit's ``on_message`` directly on this thread. Process CPU per message, the best of
    ``rounds`` rounds of ``per_round`` messages (a loaded machine's waits are not counted); what
    the end-to-end runs cost beyond it is receiving, decoding and handing the message over."""
    from dyknow.testing import UnitHarness

    named = {f"f{k}": objects_formula(k) for k in range(formulas)}
    spec = monitor_spec(named, label="shared-monitor", queue=1 << 17, max_objects=count, changes_only=True)
    rng = random.Random(3)
    speeds = [3.5 if rng.random() < 1 / 500 else rng.random() for _ in range(4096)]
    start = time.time_ns() - 10**12  # (in the past: no sample is ahead of the clock)
    with UnitHarness(spec, name="m0") as harness:
        warm = 2 * count  # every object made, its freshness derived, through the unit's lane
        for i in range(warm):
            harness.send("t0", {"id": i % count, "speed": speeds[i % 4096]}, origin_ns=start + i * 50_000)
        unit: Any = harness.unit
        deadline = time.monotonic() + 60
        while sum(m.states for m in unit.monitors.values()) < warm * formulas:
            if time.monotonic() > deadline:
                raise RuntimeError("the monitor unit did not take the warm-up samples within 60 s")
            time.sleep(0.05)
        best, i = float("inf"), warm
        for _ in range(rounds):
            messages = []
            for _ in range(per_round):
                t_ns = start + i * 50_000
                messages.append(Message({"id": i % count, "speed": speeds[i % 4096]}, i + 1, t_ns, t_ns, "bench/track"))
                i += 1
            on_message = unit.on_message
            cpu = time.process_time()
            for message in messages:
                on_message("t0", message)
            best = min(best, (time.process_time() - cpu) / per_round * 1e6)
        decided = sum(m.states for m in unit.monitors.values())
    if decided != i * formulas:
        raise RuntimeError(f"{decided} instance states decided of {i * formulas}")
    print(f"the monitor unit's step ({formulas} foreach formulas of {count} objects, one sample a message, changes only; "
          f"on_message called directly): {best:.1f} us CPU per message, {best / formulas:.2f} us per formula "
          f"(best of {rounds} rounds of {per_round:,}); load {_load()}")  # fmt: skip
    return {"objects": count, "formulas": formulas, "rounds": rounds, "per_message_us": round(best, 2), "load": _load()}


def main(argv: list[str] | None = None) -> int:
    """Run the per-state comparison (default) or the end-to-end runs (``--monitors``, ``--objects``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--windows", default="10ms,1s,100s", help=f"windows, of {', '.join(WINDOWS)} (default all)")
    parser.add_argument("--states", type=int, default=20_000, help="states timed per run, after the windows fill (default 20,000)")
    parser.add_argument("--repeat", type=int, default=3, help="interleaved runs per formula, the best kept per peer (default 3)")
    parser.add_argument(
        "--budget", type=float, default=5.0, metavar="S", help="seconds timed per peer and run at most (RTAMT is slow; default 5)"
    )
    parser.add_argument("--rtamt-max", type=int, default=100, metavar="STATES",
                        help="run RTAMT on windows of at most this many states (its cost grows with the window; default 100: 1 s)")  # fmt: skip
    parser.add_argument("--smoke", "--quick", action="store_true", help="a short run of every part, for the tests")
    parser.add_argument("--monitors", type=int, metavar="N", help="instead: N monitors at --rate-hz in one manager on one core, end to end")
    parser.add_argument("--objects", type=int, metavar="N", help="instead: one foreach monitor of N objects at --rate-hz, end to end")
    parser.add_argument("--changes-only", action="store_true", help="with --objects: publish a verdict only when it changes")
    parser.add_argument(
        "--formulas",
        type=int,
        default=1,
        metavar="K",
        help="with --objects: K foreach formulas over the one stream, served by one unit (default 1)",
    )
    parser.add_argument("--separate", action="store_true", help="with --formulas: a unit each (what a unit of one formula costs)")
    parser.add_argument(
        "--frame", type=int, default=1, metavar="N", help="with --objects: N objects' samples a message, a list (default 1)"
    )
    parser.add_argument("--rate-hz", type=float, default=20.0, help="samples per second per monitor or object (default 20)")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long latencies are recorded end to end (default 10)")
    parser.add_argument("--warmup", type=float, default=3.0, metavar="S", help="seconds before recording end to end (default 3)")
    parser.add_argument("--core", type=int, default=0, help="the CPU an end-to-end run's manager is pinned to (default 0)")
    parser.add_argument("--remote", action="store_true", help="end to end: sources and sink in another process, over Zenoh")
    parser.add_argument("--feeder", metavar="ENDPOINT", help=argparse.SUPPRESS)  # the other process of --remote
    parser.add_argument("--churn", type=int, metavar="N", help="instead: the CPU an object's monitor costs to make, over N objects")
    parser.add_argument("--step", type=int, metavar="N",
                        help="instead: the monitor unit's own step per message, --formulas foreach formulas over N objects, no transport")  # fmt: skip
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    if args.feeder:
        return feeder(
            args.feeder,
            args.monitors or args.objects,
            args.rate_hz,
            args.seconds,
            args.warmup,
            args.core,
            objects=bool(args.objects),
            frame=args.frame,
        )
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}; load {_load()}")
    if args.step:
        step = unit_step(args.step, args.formulas, 3 if args.smoke else args.repeat * 2 - 1)
        if args.json:
            write_json(args.json, {"machine": info, "step": step})
        return 0
    if args.churn:
        churn = object_churn(args.churn)
        if args.json:
            write_json(args.json, {"machine": info, "churn": churn})
        return 0
    if args.monitors or args.objects:
        result = end_to_end(args)
        if args.json:
            write_json(args.json, {"machine": info, "monitors" if args.monitors else "objects": result})
        return 0
    windows = [w.strip() for w in args.windows.split(",")]
    unknown = [w for w in windows if w not in WINDOWS]
    if unknown:
        parser.error(f"unknown window {unknown[0]!r}: one of {', '.join(WINDOWS)}")
    states, repeat, budget = (300, 1, 0.3) if args.smoke else (args.states, args.repeat, args.budget)
    rows, peers = per_state(windows, states, repeat, budget, args.rtamt_max)
    checked = [r for r in rows if "met" in r]
    met = sum(1 for r in checked if r["met"])
    print(f"target (dyknow at most the faster peer per state): met on {met} of {len(checked)} formulas and windows")
    flat = flatness(rows)
    if args.json:
        write_json(
            args.json,
            {
                "machine": info,
                "peers": peers,
                "step_ns": STEP_NS,
                "states": states,
                "repeat": repeat,
                "budget_s": budget,
                "load": _load(),
                "results": rows,
                "targets_met": met,
                "targets": len(checked),
                "flatness": flat,
            },
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
