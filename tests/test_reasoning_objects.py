"""One monitor per object (dyknow.reasoning.objects): a foreach formula's verdicts per object and
life, against evaluate_objects_ns() and a naive evaluator written from the semantics' text; the
bounds on live objects; an object retired and seen again."""

from __future__ import annotations

import json
import random
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dyknow.errors import FormulaError
from dyknow.reasoning import parse
from dyknow.reasoning.objects import ObjectMonitor
from dyknow.reasoning.semantics import evaluate_objects_ns
from dyknow.reasoning.syntax import Formula, Quantifier, Stream
from dyknow.tags import Term
from tests.reasoning_support import MS, formulas, naive_evaluate_objects, naive_object_key

TRACK, ZONE = Term("Track", ("f",)), Term("Zone", ("z",))


def _trace(rng: random.Random, samples: int = 300, objects: tuple[Any, ...] = ("a", "b", 4, 4.0, "4", 2.5)) -> dict[Term, list[tuple[int, Any]]]:
    """Track samples naming objects (now and then none, or a bool: no object), zone samples between;
    one stream never sends two samples at one time (a monitor would count the second late), two
    streams often do."""
    t, track, zone = 0, [], []
    for _ in range(samples):
        t += rng.choice([0, 1, 1, 2, 3, 9]) * MS
        if rng.random() < 0.7 and (not track or track[-1][0] < t):
            ident = rng.choice([*objects, None, True]) if rng.random() < 0.95 else rng.choice(objects)
            track.append((t, {"id": ident, "v": rng.choice([0, 1, 2, 3, 2.5, None, True, "x"])}))
        elif not zone or zone[-1][0] < t:
            zone.append((t, rng.choice([0, 1, 2, 0.5, False, True])))
    return {TRACK: track, ZONE: zone}


def _run(monitor: ObjectMonitor, trace: dict[Term, list[tuple[int, Any]]], rng: random.Random) -> dict[str, list[tuple[int, bool]]]:
    merged = sorted(((t, rng.random(), term, v) for term, samples in trace.items() for t, v in samples), key=lambda s: (s[0], s[1]))
    # within one stream, equal times keep their order
    cursor = dict.fromkeys(trace, 0)
    got: dict[str, list[tuple[int, bool]]] = {}
    for _t, _r, term, _v in merged:
        t, v = trace[term][cursor[term]]
        cursor[term] += 1
        if str(term) not in monitor.terms:
            continue
        for key, verdict in monitor.push(str(term), t, v):
            got.setdefault(key, []).append((verdict.t_ns, verdict.verdict))
    for key, verdict in monitor.close():
        got.setdefault(key, []).append((verdict.t_ns, verdict.verdict))
    return got


@settings(max_examples=300, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(body=formulas((TRACK, ZONE), max_depth=3, rich=True, future=False) | formulas((TRACK, ZONE), max_depth=3), seed=st.integers(0, 10**6), idle=st.sampled_from([2, 5, 20]))
def test_an_object_monitor_returns_the_naive_evaluators_decided_verdicts_per_object(body: Formula, seed: int, idle: int) -> None:
    """Random bodies over the tracked stream and another, with the object's value read too
    (``t == "a"``): every instance's verdicts are the naive evaluator's decided ones, per object
    and life, and evaluate_objects_ns() agrees with the naive evaluator on every verdict."""
    from dyknow.reasoning.syntax import And, Atom, Or, Str, Var

    root = Or(body.root, Atom(Var("t"), "==", Str("a")))  # the variable as a value
    formula = Formula.of(Quantifier("foreach", "t", Stream(TRACK, ("id",)), And(root, root) if seed % 2 else root))
    rng = random.Random(seed)
    trace = _trace(rng)
    inner = Formula.of(formula.root.body)  # type: ignore[union-attr]
    naive = naive_evaluate_objects("t", Stream(TRACK, ("id",)), inner, trace, idle * MS)
    offline = evaluate_objects_ns(formula, {str(k): v for k, v in trace.items() if k in formula.terms}, idle_ns=idle * MS)
    assert offline == naive, str(formula)
    got = _run(ObjectMonitor(formula, idle_ns=idle * MS), trace, rng)
    want = {key: [(t, v) for life in lives for t, v in life if v is not None] for key, lives in naive.items()}
    assert {k: sorted(v) for k, v in got.items()} == {k: sorted(v) for k, v in want.items() if v}, str(formula)


@settings(max_examples=300, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(body=formulas((TRACK, ZONE), max_depth=3, rich=True, future=False) | formulas((TRACK, ZONE), max_depth=3), seed=st.integers(0, 10**6),
       idle=st.sampled_from([2, 5, 20]), ages=st.sampled_from([(1, None), (2, None), (0, 3), (4, 1)]))  # fmt: skip
def test_an_object_monitor_counts_the_outages_before_an_objects_first_sample(body: Formula, seed: int, idle: int, ages: tuple[int, int | None]) -> None:
    """Issue 54 item 3: with maximum ages, a window of an object's first states that reaches back
    before its first sample reaches the other terms' outages there (the span rule): unknown, not
    false. Every instance's verdicts are the naive evaluator's, which keeps every sample, and
    evaluate_objects_ns() (which keeps what the body's windows reach) agrees with it."""
    formula = Formula.of(Quantifier("foreach", "t", Stream(TRACK, ("id",)), body.root))
    rng = random.Random(seed)
    trace = _trace(rng)
    zone_age, track_age = ages
    max_age = {ZONE: zone_age * MS, **({TRACK: track_age * MS} if track_age is not None else {})}
    max_age = {term: age for term, age in max_age.items() if term in formula.terms}
    inner = Formula.of(formula.root.body)  # type: ignore[union-attr]
    naive = naive_evaluate_objects("t", Stream(TRACK, ("id",)), inner, trace, idle * MS, max_age=max_age)
    by_name = {str(term): age for term, age in max_age.items()}
    offline = evaluate_objects_ns(formula, {str(k): v for k, v in trace.items() if k in formula.terms}, idle_ns=idle * MS, max_age_ns=by_name)
    assert offline == naive, (str(formula), max_age)
    got = _run(ObjectMonitor(formula, idle_ns=idle * MS, max_age_ns=by_name), trace, rng)
    want = {key: [(t, v) for life in lives for t, v in life if v is not None] for key, lives in naive.items()}
    assert {k: sorted(v) for k, v in got.items()} == {k: sorted(v) for k, v in want.items() if v}, (str(formula), max_age)


@settings(max_examples=100, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(body=formulas((TRACK,), max_depth=3, rich=True, future=False) | formulas((TRACK,), max_depth=3), seed=st.integers(0, 10**6))
def test_one_objects_samples_change_no_other_objects_verdicts(body: Formula, seed: int) -> None:
    """Issue 54 item 11: every object's monitor is made from one plan of the body, worked out once
    per formula, and shares no state with the others: two objects' samples interleaved give each
    object the verdicts it gets alone."""
    formula = Formula.of(Quantifier("foreach", "t", Stream(TRACK, ("id",)), body.root))
    rng = random.Random(seed)
    samples, t = [], 0
    for _ in range(200):
        t += rng.choice([1, 1, 2, 3, 9]) * MS
        samples.append((t, rng.choice("ab"), rng.choice([0, 1, 2, 3, 2.5, None, "x"])))

    def verdicts(objects: str) -> list[tuple[str, int, int, bool, int]]:
        monitor = ObjectMonitor(formula, idle_ns=10**12)
        pairs = []
        for t, key, v in samples:
            if key in objects:
                pairs += monitor.push("Track(f)", t, {"id": key, "v": v})
        pairs += monitor.close()
        return sorted((key, v.state, v.t_ns, v.verdict, v.decided_ns) for key, v in pairs)

    both = verdicts("ab")
    assert [v for v in both if v[0] == "a"] == verdicts("a"), str(formula)
    assert [v for v in both if v[0] == "b"] == verdicts("b"), str(formula)


def test_an_objects_identity_is_its_json_type_and_value() -> None:
    """Issue 54 item 5: ``1`` and ``"1"`` were one object, ``1`` and ``1.0`` two. Identity is
    JSON's (the semantics page): a number is one value however written, a string is never a
    number; keys are the naive evaluator's, computed by way of the json module, for values
    written every way a JSON encoder may write them."""
    monitor = ObjectMonitor("foreach t in Track(f).id: Track(f).v > 1")
    written = ['1', '1.0', '1e0', '"1"', '"1.0"', '2.5', '"2.5"', '25e-1', '"\\"1\\""', '"r1"', '1e+100', '"1e+100"', '-0', '"-0"', '12345678901234567890']
    keys: dict[str, list[str]] = {}
    for i, text in enumerate(written):
        value = json.loads(text)
        (pushed,) = monitor.push("Track(f)", i * MS, {"id": value, "v": 2})
        assert pushed[0] == naive_object_key(value), text
        keys.setdefault(pushed[0], []).append(text)
    assert sorted(keys.values()) == sorted([
        ['1', '1.0', '1e0'], ['"1"'], ['"1.0"'], ['2.5', '25e-1'], ['"2.5"'], ['"\\"1\\""'], ['"r1"'], ['1e+100'], ['"1e+100"'],
        ['-0'], ['"-0"'], ['12345678901234567890'],
    ])  # fmt: skip
    assert keys["1"] == ['1', '1.0', '1e0'] and keys['"1"'] == ['"1"'] and keys["r1"] == ['"r1"'] and keys["1.0"] == ['"1.0"']
    assert keys["0"] == ["-0"] and keys["-0"] == ['"-0"']
    assert sorted(monitor.objects) == sorted(keys)


def test_at_most_max_objects_live_and_the_others_are_refused() -> None:
    monitor = ObjectMonitor("foreach t in Track(f).id: Track(f).v > 1", max_objects=3, idle_ns=100 * MS)
    out = []
    for i, ident in enumerate(["a", "b", "c", "d", "a", "e"]):
        out += monitor.push("Track(f)", i * MS, {"id": ident, "v": 2})
    assert sorted(monitor.objects) == ["a", "b", "c"] and monitor.refused == 2
    assert sorted({key for key, _ in out}) == ["a", "b", "c"]
    # once 'a' has been silent longer than idle, 'd' takes its place
    out = monitor.push("Track(f)", 150 * MS, {"id": "d", "v": 2})
    assert sorted(monitor.objects) == ["d"] and [(k, v.verdict) for k, v in out] == [("d", True)]


def test_an_object_seen_again_after_idle_starts_a_new_life() -> None:
    monitor = ObjectMonitor("foreach t in Track(f).id: once[0, 1s] Track(f).v > 1", idle_ns=10 * MS)
    assert [v.verdict for _, v in monitor.push("Track(f)", 0, {"id": "a", "v": 2})] == [True]
    assert [v.verdict for _, v in monitor.push("Track(f)", 5 * MS, {"id": "a", "v": 0})] == [True]  # the same life: once remembers
    assert [v.verdict for _, v in monitor.push("Track(f)", 30 * MS, {"id": "a", "v": 0})] == [False]  # a new life: it does not
    assert monitor.made == 2


def test_samples_naming_no_object_are_counted() -> None:
    monitor = ObjectMonitor("foreach t in Track(f).id: Track(f).v > 1")
    for value in ({"id": None, "v": 1}, {"v": 1}, {"id": True, "v": 1}, {"id": [1], "v": 1}, 7):
        assert monitor.push("Track(f)", 0, value) == []
    assert monitor.unassigned == 5 and monitor.objects == []


def test_a_plain_formula_is_no_object_monitors() -> None:
    with pytest.raises(FormulaError, match="an ObjectMonitor monitors a foreach formula"):
        ObjectMonitor(parse("Track(f).v > 1"))


def test_late_samples_are_counted_per_object_and_kept_after_it_retires() -> None:
    monitor = ObjectMonitor("foreach t in Track(f).id: Track(f).v > 1", idle_ns=100 * MS)
    monitor.push("Track(f)", 10 * MS, {"id": 1, "v": 2})
    monitor.push("Track(f)", 20 * MS, {"id": 2, "v": 2})
    assert monitor.push("Track(f)", 5 * MS, {"id": 1, "v": 2}) == [] and monitor.late == 1  # before object 1's last state
    monitor.push("Track(f)", 15 * MS, {"id": 2, "v": 2})
    assert monitor.late == 2
    monitor.push("Track(f)", 500 * MS, {"id": 3, "v": 2})  # 1 and 2 silent for longer than idle_ns: retired
    assert monitor.objects == ["3"] and monitor.late == 2 and monitor.made == 3


def test_the_instances_share_the_cells_and_keep_to_them_as_objects_come() -> None:
    monitor = ObjectMonitor("foreach t in Track(f).id: historically[0, 1s] Track(f).v > 1", max_cells=64_000, max_objects=100)
    shares = []
    for total in (1, 2, 3, 5, 17, 100):  # objects alive: together they keep at most the cells
        for k in range(len(monitor.objects), total):
            monitor.push("Track(f)", k * MS, {"id": k, "v": 2})
        live = [monitor.instance(key) for key in monitor.objects]
        assert len(live) == total
        assert sum(m.max_states * m.formula.nodes for m in live) <= 64_000
        shares.append(min(m.max_states for m in live))
    assert shares == sorted(shares, reverse=True) and shares[0] > shares[-1]


def test_a_frame_is_one_sample_per_object_at_its_time() -> None:
    # a tracker publishes all its tracks in one message: the monitor and evaluate_objects_ns() read
    # each element as its object's sample at the frame's time
    formula = "foreach t in Track(f).id: once[0, 20ms] Track(f).v > 1"
    frames: list[tuple[int, Any]] = [
        (0, [{"id": "a", "v": 2}, {"id": "b", "v": 0}]),
        (10 * MS, [{"id": "a", "v": 0}, {"id": "b", "v": 0}, {"id": "c", "v": 3}]),
        (40 * MS, [{"id": "a", "v": 0}, [1], {"v": 1}]),  # a list in a frame, a track without id: no object
    ]
    want = evaluate_objects_ns(formula, {"Track(f)": frames}, idle_ns=100 * MS)
    assert want == {"a": [[(0, True), (10 * MS, True), (40 * MS, False)]], "b": [[(0, False), (10 * MS, False)]], "c": [[(10 * MS, True)]]}
    monitor = ObjectMonitor(formula, idle_ns=100 * MS)
    got: dict[str, list[tuple[int, bool]]] = {}
    for t, frame in frames:
        for key, verdict in monitor.push("Track(f)", t, frame):
            got.setdefault(key, []).append((verdict.t_ns, verdict.verdict))
    assert got == {key: [pair for life in lives for pair in life] for key, lives in want.items()}
    assert monitor.unassigned == 2 and monitor.late == 0
