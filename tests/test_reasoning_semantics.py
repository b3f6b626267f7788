"""The semantics of formulas (dyknow.reasoning.semantics): evaluate() against a naive evaluator on
thousands of random formulas and irregular traces, the decisions the issue leaves open, pinned,
and where reelay and RTAMT agree with it (and where they do not, and why).

Where the other monitors differ (also stated in the semantics module's documentation):

- reelay is past-time only and has no unknown. In discrete time (one update per state, intervals
  counted in updates) it agrees with us on regular traces, empty windows included. Its dense-time
  monitor reads the held value between samples, so on irregular traces it differs on purpose.
- RTAMT gives robustness, not verdicts: the sign is the verdict unless it is 0 (a value equal to
  the threshold; the traces here avoid it). Future formulas are monitored online only after
  ``pastify()``: the output at step k is the verdict of step k - horizon, and its first outputs
  (for steps before the trace) have no counterpart here. The 0.4.10 wheel mis-pastifies
  ``->`` over a future operator (every output ``inf``) and ``or`` over operands of different
  horizons (some outputs wrong); the past form written by hand agrees.
"""

from __future__ import annotations

import math
import random
import warnings
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dyknow.errors import FormulaError
from dyknow.reasoning import evaluate, parse
from dyknow.reasoning.semantics import evaluate_ns, evaluate_values_ns
from dyknow.reasoning.syntax import Formula
from tests.reasoning_support import (
    TERMS,
    family_formulas,
    family_traces,
    formulas,
    lookup_formulas,
    lookup_traces,
    naive_evaluate_ns,
    seconds,
    traces,
)


def cases(count: int) -> settings:
    """Reproducible Hypothesis settings: ``count`` examples, derandomized, no deadline."""
    return settings(
        max_examples=count, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
    )


def _check_against_naive(data: st.DataObject, formula: Formula, numeric: bool = False) -> None:
    trace = data.draw(traces(formula.terms, numeric=numeric))
    expected = naive_evaluate_ns(formula, trace)
    got = evaluate(formula, seconds(trace))
    assert [(round(t * 1e9), v) for t, v in got] == expected, str(formula)
    assert evaluate_ns(str(formula), {str(term): samples for term, samples in trace.items()}) == expected


@cases(1000)
@given(formula=formulas(past=True, future=False), data=st.data())
def test_past_formulas_agree_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    _check_against_naive(data, formula)


@cases(1000)
@given(formula=formulas(past=False, future=True), data=st.data())
def test_future_formulas_agree_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    _check_against_naive(data, formula)


@cases(1000)
@given(formula=formulas(max_depth=5), data=st.data())
def test_mixed_formulas_agree_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    _check_against_naive(data, formula)


@cases(1500)
@given(formula=formulas(past=True, future=False, rich=True), data=st.data())
def test_expressions_edges_and_aggregates_agree_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    """Comparisons of two expressions, arithmetic, strings, booleans, prev, rise/fall, count and
    every aggregate of a past window, over traces of numbers, strings, booleans and junk (and
    over traces of mostly numbers, where aggregates are decided)."""
    _check_against_naive(data, formula, numeric=data.draw(st.booleans()))


@cases(800)
@given(formula=formulas(max_depth=4, rich=True), data=st.data())
def test_expressions_under_future_operators_agree_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    _check_against_naive(data, formula, numeric=data.draw(st.booleans()))


@cases(800)
@given(formula=formulas(max_depth=4, rich=True), data=st.data())
def test_robustness_agrees_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    """Every state's robustness (None where undefined) is the naive evaluator's, exactly: the same
    differences, least and greatest values."""
    trace = data.draw(traces(formula.terms, numeric=data.draw(st.booleans())))
    expected = naive_evaluate_ns(formula, trace, robustness=True)
    got = evaluate_ns(formula, {str(term): samples for term, samples in trace.items()}, robustness=True)
    assert got == expected, str(formula)
    for (_t, verdict, margin) in got:  # the sign is the verdict where it is not 0
        if margin is not None and margin != 0:
            assert verdict == (margin > 0), (str(formula), verdict, margin)


@cases(600)
@given(formula=formulas(max_depth=3, rich=True), data=st.data())
def test_a_stale_term_is_unknown_as_the_naive_evaluator_says(formula: Formula, data: st.DataObject) -> None:
    trace = data.draw(traces(formula.terms))
    ages = {term: data.draw(st.sampled_from([0, 1, 2, 3])) * 1_000_000 for term in formula.terms if data.draw(st.booleans())}
    expected = naive_evaluate_ns(formula, trace, max_age=ages)
    got = evaluate_ns(formula, {str(term): samples for term, samples in trace.items()}, max_age_ns={str(t): a for t, a in ages.items()})
    assert got == expected, (str(formula), ages)


@cases(1500)
@given(formula=lookup_formulas(), data=st.data())
def test_lookups_functions_and_distances_agree_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    """Lookups by keys of every kind (strings, numbers written as ints and floats, booleans,
    unknowns; chained; after a field path), sqrt, hypot, pow and dist over objects, arrays and
    junk, their verdicts and robustness, some terms stale: exactly the naive evaluator's."""
    trace = data.draw(lookup_traces(formula.terms))
    ages = {term: data.draw(st.sampled_from([0, 1, 2])) * 1_000_000 for term in formula.terms if data.draw(st.sampled_from([False, False, True]))}
    expected = naive_evaluate_ns(formula, trace, max_age=ages, robustness=True)
    got = evaluate_ns(formula, {str(term): samples for term, samples in trace.items()}, max_age_ns={str(t): a for t, a in ages.items()}, robustness=True)
    assert got == expected, (str(formula), ages)
    assert parse(str(formula)).root == formula.root


def test_the_written_text_parses_back_to_the_same_formula_it_was_evaluated_as() -> None:
    formula = parse("Battery(robot) > 0.2 since[0, inf] (p or not q) implies eventually[0, 5ms] q")
    assert parse(str(formula)).root == formula.root
    assert formula.terms == (TERMS[1], TERMS[0], TERMS[2])


# -- the decisions the issue leaves to us, pinned


def test_states_start_when_every_stream_has_a_value_and_hold_the_latest() -> None:
    streams = {"p": [(0.0, 1), (1.0, 2), (3.0, 3)], "q": [(2.0, 10), (2.0, 11), (3.0, 12)]}
    got = evaluate("p >= 2 and q > 10", streams)
    assert got == [(2.0, True), (3.0, True)]  # no state before 2.0; at 2.0 p holds 2 and q the later 11
    assert evaluate("p > 0 and q > 0", {"p": [(0.0, 1)], "q": []}) == []
    assert evaluate("true", {}) == []  # no stream: no state


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (3, True),
        (3.5, True),
        (1, False),
        (True, None),  # a boolean is not a number
        ("3", None),
        (None, None),
        (float("nan"), None),
        ({"v": 3}, None),  # an object where a number was expected
        ([3], None),
    ],
)
def test_a_comparison_is_unknown_on_anything_but_a_number(value: Any, expected: bool | None) -> None:
    assert evaluate("x > 2", {"x": [(0.0, value)]}) == [(0.0, expected)]


@pytest.mark.parametrize(
    ("formula", "value", "expected"),
    [
        ("x.speed > 1", {"speed": 2}, True),
        ("x.speed > 1", {"speed": "fast"}, None),
        ("x.speed > 1", {"velocity": 2}, None),  # a missing field
        ("x.speed > 1", 2, None),  # not an object
        ("x.pose.y < 0", {"pose": {"y": -1}}, True),
        ("x.pose.y < 0", {"pose": 3}, None),
        ("x", True, True),
        ("x", False, False),
        ("x", 1, None),  # 1 is not true
        ("x.ok", {"ok": False}, False),
        ("x.ok", {"ok": None}, None),
    ],
)
def test_fields_and_boolean_atoms(formula: str, value: Any, expected: bool | None) -> None:
    assert evaluate(formula, {"x": [(0.0, value)]}) == [(0.0, expected)]


def test_kleene_connectives_and_implies() -> None:
    # x is unknown at 0 (a string), false at 1, true at 2
    streams = {"x": [(0.0, "?"), (1.0, 0), (2.0, 5)], "y": [(0.0, 5), (1.0, "?"), (2.0, 0)]}
    assert [v for _, v in evaluate("x > 1 and y > 1", streams)] == [None, False, False]
    assert [v for _, v in evaluate("x > 1 or y > 1", streams)] == [True, None, True]
    assert [v for _, v in evaluate("not x > 1", streams)] == [None, True, False]
    assert [v for _, v in evaluate("x > 1 implies y > 1", streams)] == [True, True, False]


def test_empty_windows_are_false_for_or_and_true_for_and() -> None:
    streams = {"p": [(0.0, True), (0.5, True), (3.0, False), (10.0, True)]}
    assert evaluate("once[1s, 2s] p", streams) == [(0.0, False), (0.5, False), (3.0, False), (10.0, False)]
    assert evaluate("historically[1s, 2s] not p", streams) == [(0.0, True), (0.5, True), (3.0, True), (10.0, True)]
    # a complete future window holding no state: false for eventually, true for always
    assert evaluate("eventually[1s, 2s] p", streams)[2] == (3.0, False)
    assert evaluate("always[1s, 2s] not p", streams)[2] == (3.0, True)


def test_an_incomplete_future_window_is_one_more_unknown() -> None:
    streams = {"p": [(0.0, False), (1.0, True), (1.5, False)]}
    assert evaluate("eventually[0, 1s] p", streams) == [(0.0, True), (1.0, True), (1.5, None)]
    assert evaluate("always[0, 1s] not p", streams) == [(0.0, False), (1.0, False), (1.5, None)]
    # decided even though incomplete: one false term is enough for always
    assert evaluate("always[0, 5s] p", streams) == [(0.0, False), (1.0, False), (1.5, False)]


def test_until_and_since_windows_and_chains() -> None:
    streams = {
        "f": [(0.0, True), (1.0, True), (2.0, False), (3.0, True), (4.0, True)],
        "g": [(0.0, False), (1.0, False), (2.0, False), (3.0, True), (4.0, False)],
    }
    # until at 0: g first true at 3, but f fails at 2 < 3. At 1 and 2 the false f at 2 dooms every
    # later term, but the window [t, t + 4s] is incomplete: its unknown rest is one more term
    assert [v for _, v in evaluate("f until[0, 4s] g", streams)] == [False, None, None, True, None]
    # since at 4: g at 3, f at 4 holds
    assert [v for _, v in evaluate("f since[0, inf] g", streams)] == [False, False, False, True, True]
    assert [v for _, v in evaluate("f since[2s, inf] g", streams)] == [False, False, False, False, False]


def test_times_are_whole_nanoseconds() -> None:
    streams = {"p": [(0.1, True), (0.2, False), (0.3, False)]}
    # 0.3 - 0.1 is 0.19999999999999998 in floats, but 200 ms here
    assert evaluate("once[200ms, 200ms] p", streams) == [(0.1, False), (0.2, False), (0.3, True)]
    assert evaluate_ns("once[200ms, 200ms] p", {"p": [(100_000_000, True), (300_000_000, False)]}) == [
        (100_000_000, False),
        (300_000_000, True),
    ]


def test_evaluate_says_what_is_wrong_with_its_streams() -> None:
    with pytest.raises(FormulaError) as missing:
        evaluate("Battery(robot) > 0.2", {"Battery(robto)": [(0.0, 1)]})
    assert missing.value.what == "no samples for the term 'Battery(robot)' of the formula"
    assert "did you mean 'Battery(robto)'" in (missing.value.expected or "")
    with pytest.raises(FormulaError) as back:
        evaluate("p", {"p": [(1.0, True), (0.5, True)]})
    assert back.value.where == "stream 'p'" and "go back in time at position 1" in back.value.what
    with pytest.raises(FormulaError) as syntax:
        evaluate("p and", {"p": []})
    assert syntax.value.where == "formula column 6"
    # spacing inside a term does not matter; other streams are ignored
    assert evaluate("Battery(robot) > 1", {"Battery( robot )": [(0.0, 2)], "noise": [(0.0, 1)]}) == [(0.0, True)]


# -- the other monitors, where their semantics coincide with ours


def _reelay() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return pytest.importorskip("reelay")


def _rtamt() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # antlr4 4.7 imports typing.io
        return pytest.importorskip("rtamt")


# (ours, reelay's) on the same 1 Hz trace of x and y; past-only
REELAY_CASES = [
    ("historically[0, 2s] x > 3", "historically[0:2]{x > 3}"),
    ("once[1s, 3s] x > 3", "once[1:3]{x > 3}"),
    ("x > 3 since[1s, 3s] y > 3", "{x > 3} since[1:3] {y > 3}"),
    ("x > 3 since[0, inf] y > 3", "{x > 3} since {y > 3}"),
    ("historically[0, 4s] (x > 3 implies once[0, 2s] y > 3)", "historically[0:4]({x > 3} implies once[0:2]{y > 3})"),
    ("not once[2s, 2s] y > 3 or x <= 3", "not(once[2:2]{y > 3}) or {x <= 3}"),  # reelay: no bare not before a temporal operator
]


@pytest.mark.parametrize(("ours", "theirs"), REELAY_CASES, ids=[c[0] for c in REELAY_CASES])
def test_reelay_discrete_time_agrees_on_regular_traces(ours: str, theirs: str) -> None:
    reelay = _reelay()
    rng = random.Random(ours)
    for _ in range(20):
        xs = [rng.choice([1, 5]) for _ in range(40)]
        ys = [rng.choice([1, 1, 5]) for _ in range(40)]
        monitor = reelay.discrete_timed_monitor(pattern=theirs, condense=False)
        theirs_out = [monitor.update({"x": x, "y": y})["value"] for x, y in zip(xs, ys, strict=True)]
        mine = [
            v for _, v in evaluate(ours, {"x": [(float(i), x) for i, x in enumerate(xs)], "y": [(float(i), y) for i, y in enumerate(ys)]})
        ]
        assert mine == theirs_out


def test_reelay_dense_time_reads_between_samples_where_we_do_not() -> None:
    reelay = _reelay()
    samples = [(0.0, 5), (0.5, 1), (1.6, 1), (2.0, 1)]
    monitor = reelay.dense_timed_monitor(pattern="once[1:1.2]{x > 3}")
    segments = [segment for t, x in samples for segment in monitor.update({"time": t, "x": x})]

    def dense_at(t: float) -> bool:
        return bool([s["value"] for s in segments if s["time"] <= t][-1])

    ours = dict(evaluate("once[1s, 1.2s] x > 3", {"x": samples}))
    # at 1.6, dense time sees x > 3 held on [0, 0.5), which meets [0.4, 0.6]; no state of ours lies
    # in [0.4, 0.6] but the one at 0.5, where x is 1
    assert dense_at(1.6) is True and ours[1.6] is False
    # at 2.0 both see nothing true 1 to 1.2 s before
    assert dense_at(2.0) is False and ours[2.0] is False
    # and reelay's dense time is single precision: its segment boundary 1.7 comes back as 1.70000005
    assert any(s["time"] != round(s["time"], 6) for s in segments)


RTAMT_PAST = [
    ("once[0, 2s] x > 3", "once[0:2](x > 3)"),
    ("historically[1s, 3s] x > 3", "historically[1:3](x > 3)"),
    ("x > 3 since[0, 3s] y > 3", "(x > 3) since[0:3] (y > 3)"),
]
RTAMT_FUTURE = [  # (ours, RTAMT's, horizon in steps)
    ("eventually[0, 2s] x > 3", "eventually[0:2](x > 3)", 2),
    ("always[1s, 3s] x > 3", "always[1:3](x > 3)", 3),
    ("x > 3 until[1s, 2s] y > 3", "(x > 3) until[1:2] (y > 3)", 2),
    ("always[0, 4s] (not x > 3 or eventually[0, 2s] y > 3)", "always[0:4]((not (x > 3)) or eventually[0:2](y > 3))", 6),
    ("eventually[0, 2s] x > 3 and eventually[0, 2s] y > 3", "(eventually[0:2](x > 3)) and (eventually[0:2](y > 3))", 2),
]


def _rtamt_monitor(rtamt: Any, formula: str, *, pastify: bool) -> Any:
    spec = rtamt.StlDiscreteTimeSpecification()
    spec.declare_var("x", "float")
    spec.declare_var("y", "float")
    spec.spec = formula
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        spec.parse()
        if pastify:
            spec.pastify()
    return spec


@pytest.mark.parametrize(("ours", "theirs"), RTAMT_PAST, ids=[c[0] for c in RTAMT_PAST])
def test_rtamt_past_robustness_has_our_verdicts_as_its_sign(ours: str, theirs: str) -> None:
    rtamt = _rtamt()
    rng = random.Random(ours)
    xs = [rng.choice([1, 5]) for _ in range(60)]
    ys = [rng.choice([1, 1, 5]) for _ in range(60)]
    spec = _rtamt_monitor(rtamt, theirs, pastify=False)
    robustness = [spec.update(i, [("x", x), ("y", y)]) for i, (x, y) in enumerate(zip(xs, ys, strict=True))]
    mine = [v for _, v in evaluate(ours, {"x": [(float(i), x) for i, x in enumerate(xs)], "y": [(float(i), y) for i, y in enumerate(ys)]})]
    assert mine == [r > 0 for r in robustness]


@pytest.mark.parametrize(("ours", "theirs", "horizon"), RTAMT_FUTURE, ids=[c[0] for c in RTAMT_FUTURE])
def test_rtamt_pastified_future_verdicts_come_a_horizon_late_and_agree(ours: str, theirs: str, horizon: int) -> None:
    rtamt = _rtamt()
    rng = random.Random(ours)
    xs = [rng.choice([1, 5]) for _ in range(60)]
    ys = [rng.choice([1, 1, 5]) for _ in range(60)]
    spec = _rtamt_monitor(rtamt, theirs, pastify=True)
    robustness = [spec.update(i, [("x", x), ("y", y)]) for i, (x, y) in enumerate(zip(xs, ys, strict=True))]
    mine = [v for _, v in evaluate(ours, {"x": [(float(i), x) for i, x in enumerate(xs)], "y": [(float(i), y) for i, y in enumerate(ys)]})]
    # RTAMT's output at step k is the verdict of step k - horizon; its first `horizon` outputs are warm-up
    assert [r > 0 for r in robustness[horizon:]] == mine[: len(mine) - horizon]
    assert None in mine[len(mine) - horizon :]  # the end: windows incomplete, unknown here


def test_rtamt_0_4_10_mispastifies_implies_over_a_future_operator() -> None:
    rtamt = _rtamt()
    xs, ys = [5, 1, 1, 1, 1, 1, 1, 1, 1, 1], [1] * 10
    spec = _rtamt_monitor(rtamt, "(x >= 3) -> eventually[0:5](y >= 3)", pastify=True)
    robustness = [spec.update(i, [("x", x), ("y", y)]) for i, (x, y) in enumerate(zip(xs, ys, strict=True))]
    ours = evaluate(
        "x >= 3 implies eventually[0, 5s] y >= 3",
        {"x": [(float(i), x) for i, x in enumerate(xs)], "y": [(float(i), y) for i, y in enumerate(ys)]},
    )
    assert ours[0] == (0.0, False)  # the request at 0 is never granted
    if all(math.isinf(r) and r > 0 for r in robustness):  # the 0.4.10 bug: no violation at all
        return
    assert robustness[5] < 0  # a fixed RTAMT reports it, a horizon late


def test_rtamt_0_4_10_mispastifies_operands_of_different_horizons_and_the_past_form_by_hand_agrees() -> None:
    rtamt = _rtamt()
    rng = random.Random(1)
    xs = [rng.choice([1, 5]) for _ in range(60)]
    ys = [rng.choice([1, 1, 5]) for _ in range(60)]
    streams = {"x": [(float(i), x) for i, x in enumerate(xs)], "y": [(float(i), y) for i, y in enumerate(ys)]}
    ours = [v for _, v in evaluate("x > 3 or eventually[0, 2s] y > 3", streams)]

    def robustness(formula: str, pastify: bool) -> list[float]:
        spec = _rtamt_monitor(rtamt, formula, pastify=pastify)
        return [spec.update(i, [("x", x), ("y", y)]) for i, (x, y) in enumerate(zip(xs, ys, strict=True))]

    pastified = robustness("(x > 3) or eventually[0:2](y > 3)", True)
    by_hand = robustness("once[2:2](x > 3) or once[0:2](y > 3)", False)  # the same formula, 2 steps late
    # step k says what holds at k - 2 (the horizon); ours is decided there
    assert [r > 0 for r in by_hand[2:]] == ours[:-2]
    wrong = [k for k in range(2, 60) if (pastified[k] > 0) != ours[k - 2]]
    assert wrong, "RTAMT's pastifier agrees now: update the semantics module's note"


# ---------------------------------------------------------------------- aggregates against numpy


def _numpy_aggregate(kind: str, times: Any, xs: Any, i: int, lo: int, hi: int | None) -> float | None:
    """An aggregate at state i from numpy over the window's own arrays (the integral from the pieces
    numpy cuts with np.clip)."""
    import numpy as np

    if kind == "integral":
        start = times[0] if hi is None else max(times[0], times[i] - hi)
        end = times[i] - lo
        if end <= start:
            return 0.0
        ends = np.append(times[1 : i + 1], times[i])
        pieces = np.clip(ends, start, end) - np.clip(times[: i + 1], start, end)
        return float(np.sum(xs[: i + 1] * pieces)) / 1e9
    inside = (times[i] - times >= lo) & ((times[i] - times <= hi) if hi is not None else True)
    inside[i + 1 :] = False
    w = xs[inside]
    if kind == "count":
        return float(np.count_nonzero(w > 1.0))
    if kind == "rate":
        if len(w) < 2:
            return None
        ts = times[inside]
        return float((w[-1] - w[0]) / ((ts[-1] - ts[0]) / 1e9))
    if len(w) == 0:
        return 0.0 if kind == "sum" else None
    return float({"sum": np.sum, "avg": np.mean, "min": np.min, "max": np.max}[kind](w))


@pytest.mark.parametrize("kind", ["count", "sum", "avg", "min", "max", "rate", "integral"])
def test_aggregates_equal_numpys_over_the_same_windows(kind: str) -> None:
    """Every aggregate of 2,000 irregular samples at every state, over bounded, unbounded and
    delayed windows, is numpy's over the same window (within 1e-9, relative: numpy sums pairwise,
    the semantics exactly)."""
    import numpy as np

    rng = random.Random(kind)
    t, times, xs = 0, [], []
    for _ in range(2000):
        t += rng.choice([1, 1, 2, 5, 13]) * 1_000_000
        times.append(t)
        xs.append(rng.choice([rng.uniform(-5, 5), rng.randint(-3, 9), rng.uniform(0, 1e6)]))
    arr_t, arr_x = np.array(times), np.array(xs, dtype=float)
    for lo, hi in [(0, 50_000_000), (0, None), (20_000_000, 300_000_000), (7_000_000, None)]:
        interval = f"[{lo // 1_000_000}ms, {'inf' if hi is None else f'{hi // 1_000_000}ms'}]"
        text = f"{kind}{interval} (x > 1)" if kind == "count" else f"{kind}{interval} x"
        got = evaluate_values_ns(text, {"x": list(zip(times, xs, strict=True))})
        for i, (_, value) in enumerate(got):
            want = _numpy_aggregate(kind, arr_t, arr_x, i, lo, hi)
            if want is None:
                assert value is None, (text, i)
            else:
                assert value is not None and math.isclose(value, want, rel_tol=1e-9, abs_tol=1e-9), (text, i, value, want)


# ---------------------------------------------------------------------- robustness against RTAMT


@st.composite
def _stl(draw: st.DrawFn, depth: int) -> tuple[str, str, bool]:
    """A random STL formula over x and y: (ours, RTAMT's, whether it looks into the future), the
    same tree written twice (rise and fall only over operands that do not: ours refuses those)."""
    if depth == 0 or draw(st.integers(0, 3)) == 0:
        left = draw(st.sampled_from([("x", "x"), ("y", "y"), ("x - y", "(x - y)"), ("abs(x)", "abs(x)"), ("x + y * 2", "(x + (y * 2))")]))
        op = draw(st.sampled_from(["<", "<=", ">", ">="]))
        c = draw(st.sampled_from([0, 1, 2.5, -1, 3]))
        return f"{left[0]} {op} {c}", f"({left[1]} {op} {c})", False
    kind = draw(st.sampled_from(["not", "and", "or", "implies", "always", "eventually", "once", "historically", "until", "since", "rise", "fall"]))
    a = draw(st.integers(0, 2))
    b = a + draw(st.integers(0, 3))
    x = draw(_stl(depth - 1))
    if kind in ("rise", "fall") and x[2]:
        kind = "not"
    if kind == "not":
        return f"not ({x[0]})", f"(not {x[1]})", x[2]
    if kind in ("rise", "fall"):
        return f"{kind}({x[0]})", f"{kind}({x[1]})", False
    if kind in ("always", "eventually", "once", "historically"):
        return f"{kind}[{a}s, {b}s] ({x[0]})", f"{kind}[{a}:{b}]({x[1]})", x[2] or kind in ("always", "eventually")
    y = draw(_stl(depth - 1))
    future = x[2] or y[2]
    if kind in ("until", "since"):
        return f"({x[0]}) {kind}[{a}s, {b}s] ({y[0]})", f"({x[1]} {kind}[{a}:{b}] {y[1]})", future or kind == "until"
    return f"({x[0]}) {kind} ({y[0]})", f"({x[1]} {'->' if kind == 'implies' else kind} {y[1]})", future


@cases(600)
@given(pair=_stl(3), seed=st.integers(0, 10**6))
def test_robustness_is_rtamts_discrete_time_robustness(pair: tuple[str, str, bool], seed: int) -> None:
    """Random STL formulas (arithmetic, abs, not/and/or/implies, the six temporal operators with
    bounds, rise and fall) over regular 1 Hz traces of numbers: our robustness is RTAMT's offline
    discrete-time robustness at every state where ours is defined, within 1e-9. Ours is undefined
    where RTAMT makes something up: a future window past the trace's end (RTAMT truncates it) and
    the first state of rise and fall (RTAMT takes the operand as false before the trace)."""
    rtamt = _rtamt()
    ours, theirs, _ = pair
    rng = random.Random(seed)
    n = 24
    xs = [rng.choice([-2, 0, 1, 2.5, 3, 4.25, 6]) for _ in range(n)]
    ys = [rng.choice([-1, 0, 0.5, 2, 3]) for _ in range(n)]
    spec = _rtamt_monitor(rtamt, theirs, pastify=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        expected = [r for _, r in spec.evaluate({"time": list(range(n)), "x": xs, "y": ys})]
    got = evaluate(ours, {"x": [(float(i), x) for i, x in enumerate(xs)], "y": [(float(i), y) for i, y in enumerate(ys)]}, robustness=True)
    compared = 0
    for (t, _verdict, mine), theirs_r in zip(got, expected, strict=True):
        if mine is None:
            continue
        compared += 1
        assert (mine == theirs_r) if math.isinf(mine) or math.isinf(theirs_r) else math.isclose(mine, theirs_r, rel_tol=1e-9, abs_tol=1e-9), (ours, t, mine, theirs_r)
    assert compared or any(k in ours for k in ("always", "eventually", "until", "rise", "fall")), ours


def test_the_evaluate_functions_say_their_time_unit_in_their_names() -> None:
    """Issue 54 item 12: ``evaluate`` takes and gives float seconds (as ``time.time``), every
    function whose name ends in ``_ns`` integer nanoseconds (as ``time.time_ns``); the names of
    0.1 that said nothing (``evaluate_values``, ``evaluate_objects``: nanoseconds) still work, with
    a DeprecationWarning naming the new one."""
    import dyknow.reasoning as reasoning
    from dyknow.reasoning import evaluate, evaluate_ns, evaluate_objects_ns, evaluate_values_ns

    seconds = {"X(a)": [(0.0, 1), (0.25, 5)]}
    nanos = {"X(a)": [(0, 1), (250_000_000, 5)]}
    assert evaluate("X(a) > 3", seconds) == [(0.0, False), (0.25, True)]
    assert evaluate_ns("X(a) > 3", nanos) == [(0, False), (250_000_000, True)]
    assert evaluate_values_ns("X(a) * 2", nanos) == [(0, 2), (250_000_000, 10)]
    tracks = {"T(f)": [(0, {"id": "a", "v": 1}), (250_000_000, {"id": "b", "v": 5})]}
    assert evaluate_objects_ns("foreach t in T(f).id: T(f).v > 3", tracks, idle_ns=10**9) == {"a": [[(0, False)]], "b": [[(250_000_000, True)]]}
    for old, new in (("evaluate_values", evaluate_values_ns), ("evaluate_objects", evaluate_objects_ns)):
        with pytest.warns(DeprecationWarning, match=f"dyknow.reasoning.{old} is now {old}_ns"):
            assert getattr(reasoning, old) is new


def test_an_outage_before_the_first_state_is_reached_by_the_windows_that_reach_back_into_it() -> None:
    """Issue 54 item 3: A(x) is silent from 0 s to 5 s (maximum age 1 s: stale in (1 s, 5 s));
    B(x)'s first sample at 6 s makes the first state. ``once[0, 10s] A(x) > B(x)`` is false at
    every state, but a window that reaches back before 5 s reaches the outage: unknown until the
    window starts at 5 s (state 15 s), as the span rule says, in evaluate, the naive evaluator,
    the monitor, and per object (the outage before the object's first sample)."""
    from dyknow.reasoning import Monitor
    from dyknow.reasoning.objects import ObjectMonitor
    from dyknow.reasoning.semantics import evaluate_objects_ns
    from dyknow.tags import Term
    from tests.reasoning_support import naive_evaluate_ns

    s = 1_000_000_000
    a = [(0, 1)] + [(t * s, 1) for t in range(5, 17)]
    b = [(6 * s, 5), (16 * s, 5)]
    expected = [(t * s, None) for t in range(6, 15)] + [(15 * s, False), (16 * s, False)]
    formula = parse("once[0, 10s] A(x) > B(x)")
    ages = {"A(x)": s}
    assert evaluate_ns(formula, {"A(x)": a, "B(x)": b}, max_age_ns=ages) == expected
    assert naive_evaluate_ns(formula, {Term("A", ("x",)): a, Term("B", ("x",)): b}, max_age={Term("A", ("x",)): s}) == expected
    monitor = Monitor(formula, max_age_ns=ages)
    pushed = sorted([(t, 0, "A(x)", v) for t, v in a] + [(t, 1, "B(x)", v) for t, v in b])
    verdicts = [v for t, _, term, value in pushed for v in monitor.push(term, t, value)] + monitor.flush()
    assert [(v.t_ns, v.verdict) for v in verdicts] == [(15 * s, False), (16 * s, False)]
    # the same per object: the robot's first sample at 6 s, the limit silent before it
    robots = [(6 * s, {"id": "r1", "speed": 1}), (16 * s, {"id": "r1", "speed": 1})]
    rule = "foreach r in Robots(f).id: once[0, 10s] Robots(f).speed > Limit(f)"
    limit = [(t, 5) for t, _ in a]
    got = evaluate_objects_ns(rule, {"Robots(f)": robots, "Limit(f)": limit}, idle_ns=20 * s, max_age_ns={"Limit(f)": s})
    assert got == {"r1": [[(t * s, None) for t in range(6, 15)] + [(15 * s, False), (16 * s, False)]]}
    objects = ObjectMonitor(rule, idle_ns=20 * s, max_age_ns={"Limit(f)": s})
    pushed = sorted([(t, 0, "Limit(f)", v) for t, v in limit] + [(t, 1, "Robots(f)", v) for t, v in robots])
    out = [pair for t, _, term, value in pushed for pair in objects.push(term, t, value)] + objects.close()
    assert [(key, v.t_ns, v.verdict) for key, v in out] == [("r1", 15 * s, False), ("r1", 16 * s, False)]


@cases(1000)
@given(formula=family_formulas(), data=st.data())
def test_parameterized_terms_agree_with_the_naive_evaluator(formula: Formula, data: st.DataObject) -> None:
    """``Limit(Zone(r))``: at each state the member the argument names, as the naive evaluator
    reads it from the members' own samples (not from a family's value made of them); members
    missing, junk arguments, a field after the term, some terms stale; verdicts and robustness."""
    trace = data.draw(family_traces())
    ages = {term: data.draw(st.sampled_from([0, 1, 2])) * 1_000_000 for term in formula.terms if data.draw(st.sampled_from([False, False, True]))}
    expected = naive_evaluate_ns(formula, trace, max_age=ages, robustness=True)
    got = evaluate_ns(formula, {str(term): samples for term, samples in trace.items()}, max_age_ns={str(t): a for t, a in ages.items()}, robustness=True)
    assert got == expected, (str(formula), ages)
    assert parse(str(formula)).root == formula.root
