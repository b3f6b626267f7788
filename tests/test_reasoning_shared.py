"""Many formulas served by one monitor unit (dyknow.reasoning.unit): a port per term they read,
each sample delivered once for all of them, each verdict named by its formula and equal to the
naive evaluator's over that formula's own terms; the spec's and the unit's errors name the
formula or the param."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from dyknow import Manager, parse_specs
from dyknow.errors import FormulaError
from dyknow.reasoning import FormulaMonitor, monitor_spec, term_ports
from dyknow.reasoning.syntax import Formula
from dyknow.reasoning.unit import MAX_FORMULAS, VERDICTS_PORT
from dyknow.security import Limits
from dyknow.testing import UnitHarness
from tests.reasoning_support import TERMS, formulas, naive_evaluate_ns, traces

MS = 1_000_000
T0 = 1_700_000_000 * 1_000_000_000


def test_formulas_that_share_a_term_share_its_port_and_name_their_verdicts() -> None:
    named = {"low": "Battery(robot) < 0.2", "falling": "Battery(robot) < prev(Battery(robot))", "slow": "Speed(robot).v < 1"}
    spec = monitor_spec(named, max_age_ms=-1)
    assert [(t.port, t.tag) for t in spec.tags] == [("t0", "Battery(robot)"), ("t1", "Speed(robot)")]
    assert term_ports(spec) == term_ports(named) == {"Battery(robot)": "t0", "Speed(robot)": "t1"}
    assert json.loads(spec.param_values()["formulas"]) == named and "formula" not in spec.param_values()
    (again,) = parse_specs(spec.to_xml())  # a remote manager takes it as XML
    assert (again.ports, again.tags, again.params) == (spec.ports, spec.tags, spec.params)
    with UnitHarness(spec, name="battery") as harness:
        for k, level in enumerate([0.9, 0.5, 0.1]):
            harness.send("t0", level, origin_ns=T0 + k * 10 * MS)
        harness.wait_for(VERDICTS_PORT, 5)
        harness.send("t1", {"v": 0.5}, origin_ns=T0 + 30 * MS)
        got = [m.payload for m in harness.wait_for(VERDICTS_PORT, 6)]
        unit = harness.unit
        assert isinstance(unit, FormulaMonitor) and set(unit.monitors) == set(named) and unit.terms == ("Battery(robot)", "Speed(robot)")
        port = harness.statistics().to_dict()["ports"]["t0"]
        assert port["messages"] == 3  # one delivery a sample, for both formulas that read it
    by_formula: dict[str, list[tuple[int, bool]]] = {}
    for verdict in got:
        by_formula.setdefault(verdict["formula"], []).append((verdict["t_ns"] - T0, verdict["verdict"]))
    assert by_formula == {
        "low": [(0, False), (10 * MS, False), (20 * MS, True)],
        "falling": [(10 * MS, True), (20 * MS, True)],  # (the first state has no previous sample: unknown, never published)
        "slow": [(30 * MS, True)],
    }


def test_a_list_names_each_formula_by_its_text() -> None:
    spec = monitor_spec(["p > 1", "q > 1"])
    with UnitHarness(spec, name="m") as harness:
        harness.send("t1", 2, origin_ns=T0)
        (verdict,) = [m.payload for m in harness.wait_for(VERDICTS_PORT, 1)]
    assert verdict["formula"] == "q > 1" and verdict["verdict"] is True


def _cases(count: int) -> settings:
    return settings(
        max_examples=count,
        derandomize=True,
        deadline=None,
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


@_cases(25)
@given(chosen=st.lists(formulas(TERMS, rich=True, max_depth=3), min_size=2, max_size=5), data=st.data())
def test_each_formula_of_a_shared_unit_equals_the_naive_evaluator_over_its_own_terms(chosen: list[Formula], data: st.DataObject) -> None:
    """Random formulas (expressions, aggregates, edges, past and future operators) in one unit;
    the terms interleaved in time as their producers would send them, with samples at equal
    times. Each formula's verdicts are those of its own states: its terms' samples, not the others'."""
    chosen = [f for f in {str(f): f for f in chosen}.values() if f.terms]
    if len(chosen) < 2:
        return
    named = {f"f{k}": formula for k, formula in enumerate(chosen)}
    spec = monitor_spec(named, reorder_ms=50, flush_ms=300, max_age_ms=-1)
    ports = term_ports(spec)
    terms = [term for term in TERMS if str(term) in ports]
    trace = data.draw(traces(terms))
    expected = {}
    for name, formula in named.items():
        verdicts = naive_evaluate_ns(formula, {term: trace[term] for term in formula.terms})
        expected[name] = {T0 + t: v for t, v in verdicts if v is not None}
    merged = sorted(((t, k, term, value) for term in terms for k, (t, value) in enumerate(trace[term])), key=lambda s: (s[0], s[1]))
    with UnitHarness(spec, name="m") as harness:
        for t, _, term, value in merged:
            harness.send(ports[str(term)], value, origin_ns=T0 + t)
        total = sum(len(v) for v in expected.values())
        got = [m.payload for m in harness.wait_for(VERDICTS_PORT, total, timeout_s=20)] if total else []
        time.sleep(0.4)  # past the flush: nothing more may come
        assert len(harness.received(VERDICTS_PORT)) == total
    published: dict[str, dict[int, bool]] = {name: {} for name in named}
    for verdict in got:
        assert verdict["t_ns"] not in published[verdict["formula"]], "a state's verdict was published twice"
        published[verdict["formula"]][verdict["t_ns"]] = verdict["verdict"]
    assert published == expected, {name: str(f) for name, f in named.items()}


def test_a_foreach_formula_beside_a_plain_one_publishes_changes_per_formula_and_object() -> None:
    """A tracker's frame (a list of tracks) is one sample per object for the foreach formula;
    the plain formula reads its own stream; changes only, per formula and per object."""
    named = {"slow": "foreach t in Track(field).id: Track(field).speed < 3", "auto": 'Mode(robot) == "auto"'}
    spec = monitor_spec(named, changes_only=True, max_age_ms=-1)
    assert term_ports(spec) == {"Track(field)": "t0", "Mode(robot)": "t1"}
    with UnitHarness(spec, name="m") as harness:
        frames = [[{"id": 1, "speed": 1}, {"id": 2, "speed": 5}], [{"id": 1, "speed": 2}, {"id": 2, "speed": 4}], [{"id": 1, "speed": 4}]]
        for k, (frame, mode) in enumerate(zip(frames, ["auto", "auto", "manual"], strict=True)):
            harness.send("t0", frame, origin_ns=T0 + k * 50 * MS)
            harness.send("t1", mode, origin_ns=T0 + k * 50 * MS)
        harness.wait_for(VERDICTS_PORT, 5)
        time.sleep(0.2)  # (nothing more comes)
    seen = sorted(
        (v["formula"], v.get("object"), v["t_ns"] - T0, v["verdict"]) for v in harness.received(VERDICTS_PORT) for v in [v.payload]
    )
    assert seen == [
        ("auto", None, 0, True),
        ("auto", None, 100 * MS, False),
        ("slow", "1", 0, True),
        ("slow", "1", 100 * MS, False),
        ("slow", "2", 0, False),
    ]


def test_foreach_formulas_over_one_stream_each_read_their_own_objects() -> None:
    """Three foreach formulas over one stream in one unit, two naming objects by ``id`` and one
    by ``name``: each sample's object is read once for the formulas of the same field (the unit
    reads it once, dyknow.reasoning.served), and each formula's objects are its own field's."""
    named = {
        "by_id": "foreach t in Track(field).id: Track(field).speed < 3",
        "by_name": "foreach t in Track(field).name: Track(field).speed < 3",
        "fast_id": "foreach t in Track(field).id: Track(field).speed > 1",
    }
    spec = monitor_spec(named, max_age_ms=-1)
    samples = [{"id": 1, "name": "a", "speed": 2}, {"id": 2, "name": "a", "speed": 4}, {"id": 1, "name": "b", "speed": 0.5}]
    with UnitHarness(spec, name="m") as harness:
        for k, sample in enumerate(samples):
            harness.send("t0", sample, origin_ns=T0 + k * 50 * MS)
        harness.wait_for(VERDICTS_PORT, 9)
        time.sleep(0.2)  # (nothing more comes)
    seen = sorted(
        (v["formula"], v["object"], (v["t_ns"] - T0) // MS, v["verdict"]) for v in harness.received(VERDICTS_PORT) for v in [v.payload]
    )
    assert seen == [
        ("by_id", "1", 0, True), ("by_id", "1", 100, True), ("by_id", "2", 50, False),
        ("by_name", "a", 0, True), ("by_name", "a", 50, False), ("by_name", "b", 100, True),
        ("fast_id", "1", 0, True), ("fast_id", "1", 100, False), ("fast_id", "2", 50, True),
    ]  # fmt: skip


def test_the_formulas_of_a_unit_join_the_managers_budget_together(make_manager: Callable[..., Manager]) -> None:
    """The nodes of every formula a unit serves count against Limits.max_monitor_nodes, and are
    given back together when it ends (or fails to start)."""
    manager = make_manager(limits=Limits(max_monitor_nodes=8))
    spec = monitor_spec({"a": "p > 1", "b": "always[0, 1s] (p > 1 and q < 2)"}, label="two")  # 1 + 4 nodes
    manager.add_transformation(spec)
    assert manager.spawn("two", "m", bindings={"t0": "x/p", "t1": "x/q", "verdicts": "x/v"}).state == "running"
    again = manager.spawn("two", "again", bindings={"t0": "y/p", "t1": "y/q", "verdicts": "y/v"})
    assert again.state == "failed"
    assert "the manager's monitors hold 5 formula nodes, and these formulas have 5; expected at most 8 nodes in all" in (again.error or "")
    manager.destroy("again")
    manager.destroy("m")
    assert manager.spawn("two", "third", bindings={"t0": "z/p", "t1": "z/q", "verdicts": "z/v"}).state == "running"


@pytest.mark.parametrize(
    ("formulas_param", "error"),
    [
        ("{", "the param formulas is not JSON"),
        ('["p > 1"]', "the param formulas holds a JSON list"),
        ('{"a": "p > 1", "a": "q > 1"}', "the name 'a' is given twice"),
        ('{"a": "p > 1", "b": "p >"}', "formula 'b', formula column 4: unexpected end of formula"),
        ("{}", "no formula given"),
        ("[" * 100_000 + "]" * 100_000, "the param formulas is not JSON (maximum recursion depth exceeded"),
        ('{"": "p > 1"}', "a formula named ''"),
        ('{"a": "always[0, 100000000s] p > 1"}', "formula 'a', formula column 7: 'always[0, 100000000s]' has the bound"),
    ],
)
def test_a_bad_formulas_param_fails_the_unit_naming_the_formula(formulas_param: str, error: str) -> None:
    with UnitHarness(monitor_spec({"a": "p > 1", "b": "q > 1"}), params={"formulas": formulas_param}, name="m") as harness:
        assert harness.info.state == "failed" and error in (harness.info.error or ""), harness.info.error
        assert "unit 'm'" in (harness.info.error or "")


def test_monitor_spec_refuses_what_it_cannot_serve() -> None:
    with pytest.raises(FormulaError, match="formula 'b', formula column 4"):
        monitor_spec({"a": "p > 1", "b": "q >"})
    with pytest.raises(FormulaError, match="the formula 'p > 1' is given twice"):
        monitor_spec(["p > 1", "p > 1"])
    with pytest.raises(FormulaError, match="no formula given"):
        monitor_spec({})
    with pytest.raises(FormulaError, match=f"at most {MAX_FORMULAS:,} formulas a unit"):
        monitor_spec({f"f{k}": "p > 1" for k in range(MAX_FORMULAS + 1)})
    with pytest.raises(FormulaError, match="the formula mentions no stream"):
        monitor_spec({"a": "true", "b": "false or true"})
