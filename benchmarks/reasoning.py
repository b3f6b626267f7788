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
import random
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dyknow.reasoning import Monitor, parse
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

from harness import machine, write_json

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


def per_state_us(make: Callable[[], Run], window: int, states: int, repeat: int, budget_s: float) -> tuple[float, int]:
    """The best of ``repeat`` runs, in microseconds per state, timed after the first window of
    states (the steady state), over at most ``budget_s`` seconds of each run; and how many
    states that best figure was measured over."""
    best, measured = float("inf"), 0
    chunk = 200
    for _ in range(repeat):
        run = make()
        run.feed(0, window)  # the windows fill: not timed
        lo, elapsed = window, 0.0
        while lo < states and (elapsed < budget_s or lo - window < chunk):
            hi = min(states, lo + chunk)
            t0 = time.perf_counter()
            run.feed(lo, hi)
            elapsed += time.perf_counter() - t0
            lo = hi
        if elapsed / (lo - window) < best:
            best, measured = elapsed / (lo - window), lo - window
    return best * 1e6, measured


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
        check = min(n, 2 * window + 400)
        for name, kind, text in formulas(window):
            formula = parse(text)
            future = kind == "future"
            row: dict[str, Any] = {"formula": name, "kind": kind, "operators": formula.operators, "window": window, "text": text}
            makers: dict[str, Callable[[], Run]] = {"dyknow": functools.partial(DyknowRun, formula, xs, ys)}
            if reelay is not None and not future:
                makers["reelay"] = functools.partial(ReelayRun, reelay, formula, xs, ys)
            if rtamt is not None:
                makers["rtamt"] = functools.partial(RtamtRun, rtamt, formula, xs, ys, future=future)
            # the same verdicts first, on the trace's start
            runs = {peer: make() for peer, make in makers.items()}
            for run in runs.values():
                run.feed(0, check)
            row["agree"] = {
                peer: _agreement(runs["dyknow"].verdicts[:check], run.verdicts[:check]) for peer, run in runs.items() if peer != "dyknow"
            }
            for peer, make in makers.items():
                us, measured = per_state_us(make, window, n, repeat, budget_s)
                row[f"{peer}_us"], row[f"{peer}_states"] = round(us, 3), measured
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


def main(argv: list[str] | None = None) -> int:
    """Run the per-state comparison (default) or the end-to-end run of many monitors (``--monitors``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--windows", default="10,100,1000", help="window lengths in states (default 10,100,1000)")
    parser.add_argument("--states", type=int, default=20_000, help="states timed per run, after the first window (default 20,000)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure, the best kept (default 3)")
    parser.add_argument("--budget", type=float, default=5.0, metavar="S", help="seconds timed per run at most (RTAMT is slow; default 5)")
    parser.add_argument("--quick", action="store_true", help="a short run: 1,000 states after the window, one run each, 0.5 s budget")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}")
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
