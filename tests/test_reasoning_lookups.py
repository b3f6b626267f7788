"""Lookups and geometry in formulas (issue 54 item 2): a limit looked up by the zone a robot is in,
``sqrt``, ``hypot``, ``pow`` and ``dist``, each three-valued. The random formulas against the naive
evaluator and the monitor are in test_reasoning_semantics.py and test_reasoning_progression.py;
here the cases a user states, with the verdicts worked out by hand."""

from __future__ import annotations

from typing import Any

import pytest

from dyknow.errors import FormulaError
from dyknow.reasoning import Monitor, parse
from dyknow.reasoning.semantics import evaluate_ns, evaluate_objects_ns, evaluate_values_ns
from dyknow.reasoning.syntax import Index, Num, Str, Stream, parse_value
from dyknow.tags import Term

S = 1_000_000_000
LIMITS = {"dock": 0.5, "aisle": 2.0, "3": 1.0, "ramp": {"up": 0.3, "down": 0.8}}


def values(expression: str, **streams: list[Any]) -> list[Any]:
    """The expression's value at each state; one sample per stream at each second."""
    got = evaluate_values_ns(expression, {name.replace("_", "(", 1) + ")" if "_" in name else name: [(i * S, v) for i, v in enumerate(samples)]
                                          for name, samples in streams.items()})  # fmt: skip
    return [v for _, v in got]


def test_the_speed_limit_of_the_zone_the_robot_is_in() -> None:
    """``Speed(r) < Limits(floor)[State(r).zone]``: the limit changes with the zone; a zone the
    map does not have, or a state without a zone, is unknown (never false)."""
    formula = "Speed(r1) < Limits(floor)[State(r1).zone]"
    streams = {
        "Limits(floor)": [(0, LIMITS)],
        "State(r1)": [(0, {"zone": "aisle"}), (1 * S, {"zone": "dock"}), (3 * S, {"zone": "yard"}), (4 * S, {"moving": True}), (5 * S, {"zone": "dock"})],
        "Speed(r1)": [(0, 1.5), (2 * S, 0.4), (5 * S, 0.7)],
    }
    got = evaluate_ns(formula, streams)
    # t=0 aisle 1.5<2; t=1 dock 1.5<0.5 no; t=2 dock 0.4<0.5; t=3 yard: no limit; t=4 no zone; t=5 dock 0.7<0.5 no
    assert got == [(0, True), (1 * S, False), (2 * S, True), (3 * S, None), (4 * S, None), (5 * S, False)]
    monitor = Monitor(formula)  # live, the same
    samples = sorted((t, k, term, v) for k, (term, trace) in enumerate(streams.items()) for t, v in trace)
    verdicts = [v for t, _, term, value in samples for v in monitor.push(term, t, value)] + monitor.flush()
    assert [(v.t_ns, v.verdict) for v in verdicts] == [(t, v) for t, v in got if v is not None]


def test_a_lookup_per_object_and_after_the_key_a_field() -> None:
    """The warehouse's rule over every robot of one stream, and a nested limit (``.up``)."""
    frames = [(0, {"id": "r1", "zone": "aisle", "speed": 1.0}), (0, {"id": "r2", "zone": "dock", "speed": 1.0}),
              (1 * S, {"id": "r1", "zone": "ramp", "speed": 0.5}), (1 * S, {"id": "r2", "zone": "dock", "speed": 0.2})]  # fmt: skip
    streams = {"Limits(floor)": [(0, LIMITS)], "Robots(floor)": frames}
    got = evaluate_objects_ns("foreach r in Robots(floor).id: Robots(floor).speed < Limits(floor)[Robots(floor).zone]", streams, idle_ns=10 * S)
    assert got == {"r1": [[(0, True), (1 * S, None)]], "r2": [[(0, False), (1 * S, True)]]}  # r1 on the ramp: an object is no number
    got = evaluate_objects_ns("foreach r in Robots(floor).id: Robots(floor).speed < Limits(floor)[Robots(floor).zone].up", streams, idle_ns=10 * S)
    assert got == {"r1": [[(0, None), (1 * S, False)]], "r2": [[(0, None), (1 * S, None)]]}


@pytest.mark.parametrize(
    ("expression", "expected"),
    [
        ('Limits(floor)["dock"]', 0.5),
        ("Limits(floor)[3]", 1.0),  # JSON's keys are strings: the number 3 finds "3"
        ("Limits(floor)[3.0]", 1.0),  # and so does 3.0, the same number
        ('Limits(floor)["ramp"]["down"]', 0.8),
        ('Limits(floor)["ramp"].down', 0.8),
        ('Limits(floor)["ramp"]', None),  # an object is no value of the semantics
        ('Limits(floor)["yard"]', None),
        ("Limits(floor)[Key(k)]", None),  # a boolean is no key
        ("Limits(floor)[Limits(floor).nothing]", None),  # an unknown key
        ("Lists(floor)[1]", "b"),
        ("Lists(floor)[1.0]", "b"),
        ("Lists(floor)[-1]", None),  # no counting from the end
        ("Lists(floor)[1.5]", None),
        ("Lists(floor)[3]", None),  # out of range
        ('Lists(floor)["1"]', None),  # an array takes numbers
        ("Lists(floor)[2][0]", 7),
    ],
)
def test_what_a_lookup_finds(expression: str, expected: Any) -> None:
    streams = {"Limits_floor": [LIMITS], "Lists_floor": [["a", "b", [7, 8]]], "Key_k": [True]}
    assert values(expression, **{name: trace for name, trace in streams.items() if name.split("_")[0] in expression}) == [expected]


@pytest.mark.parametrize(
    ("expression", "expected"),
    [
        ("sqrt(X(a))", [2.0, None, 0.0, None]),  # sqrt(-1) is no real number: unknown
        ("hypot(X(a), 3)", [5.0, 3.1622776601683795, 3.0, None]),
        ("pow(X(a), 0.5)", [2.0, None, 0.0, None]),  # (-1) ** 0.5 is no real number
        ("pow(X(a), -1)", [0.25, -1.0, None, None]),  # 0 ** -1: a division by zero
        ("pow(10, X(a) * 100)", [None, 1e-100, 1.0, None]),  # 10 ** 400 overflows: unknown
        ("pow(2, 3) + 0 * X(a) == 8", [True, True, True, None]),  # (8.0: pow computes in floats)
    ],
)
def test_functions_are_unknown_where_they_give_no_finite_real_number(expression: str, expected: list[Any]) -> None:
    assert values(expression, X_a=[4, -1, 0, "four"]) == expected


@pytest.mark.parametrize(
    ("p", "q", "expected"),
    [
        ({"x": 0, "y": 0}, {"x": 3, "y": 4}, 5.0),
        ({"x": 0, "y": 0, "z": 0, "w": 9}, {"x": 2, "y": 3, "z": 6}, 7.0),  # other members ignored
        ({"x": 0, "y": 0}, {"x": 3, "y": 4, "z": 1}, None),  # z on one only
        ([1, 1], [4, 5], 5.0),
        ([1], [4], 3.0),
        ([1, 1], [4, 5, 0], None),
        ([], [], None),
        ({"x": True, "y": 0}, {"x": 0, "y": 0}, None),  # a boolean is no coordinate
        ({"x": 1e308, "y": 0}, {"x": -1e308, "y": 0}, None),  # not finite
        (5, 5, None),
    ],
)
def test_the_distance_of_two_points(p: Any, q: Any, expected: Any) -> None:
    assert values("dist(P(a), Q(b))", P_a=[p], Q_b=[q]) == [expected]


def test_dist_reads_points_down_field_paths_and_lookups() -> None:
    pose = {"position": {"x": 1, "y": 2}, "frame": "map"}
    home = {"home": {"x": 4, "y": 6}}
    assert values('dist(Pose(r1).position, Places(floor)["home"])', Pose_r1=[pose], Places_floor=[home]) == [5.0]
    assert values('dist(Pose(r1), Places(floor)["home"])', Pose_r1=[pose], Places_floor=[home]) == [None]  # the pose itself has no x


def test_the_text_of_lookups_and_functions_parses_back() -> None:
    for text in [
        "Speed(r) < Limits(floor)[State(r).zone]",
        'Speed(r) < Limits(floor)[State(r).zone].up and Limits["a"][0] > 1',
        "dist(Pose(a).position, Pose(b).position) < hypot(1, pow(2, 3)) + sqrt(X(a))",
        "always[0, 1s] Limits(floor)[State(r).zone + 1] > 0",
        'Limits(floor)[State(r).zone]["a b"] > 0',  # a key no field can spell stays in brackets
    ]:
        formula = parse(text)
        assert str(formula) == text
        assert parse(str(formula)).root == formula.root
    tree = parse_value('Limits(floor)[State(r).zone].up')
    assert tree.root == Index(Stream(Term("Limits", ("floor",))), (Stream(Term("State", ("r",)), ("zone",)), Str("up")))
    assert parse_value("Limits[2]").root == Index(Stream(Term("Limits")), (Num(2),))
    assert parse_value("Limits (floor) [ State(r).zone ] [2]").root == parse_value("Limits(floor)[State(r).zone][2]").root  # whitespace is free


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("dist(1, P(a)) < 2", r"column 6: '1' is a number, and dist takes points.*dist\(Pose\(r1\)\.position"),
        ('dist(P(a), "home") < 2', r"column 12: '\"home\"' is a string, and dist takes points"),
        ("Limits[X(a) > 1] > 0", r"column 8: 'X\(a\) > 1' is a condition, and a key is a value"),
        ("Limits(floor)[true] > 0", r"column 15: 'true' is a condition, and a key is a value.*expected a string \(an object's key\) or a number"),
        ("Limits[X(a)", r"column 12: .*expected '\]' closing the key"),
        ("sqrt(1, 2) > 0", r"column 1: sqrt of 2 operands in .*; expected sqrt of 1: sqrt\(x\)"),
        ("pow(2) > 0", r"pow of 1 operand in .*; expected pow of 2: pow\(x, y\)"),
        ("alwyas[0, 1s] X(a) > 0", r"column 1: 'alwyas' is not a temporal operator.*did you mean 'always'"),
        ('sqrt("a") > 0', r"'\"a\"' is a string, and sqrt takes numbers"),
        ("Limits[1]. > 0", r"a field name after '\.'"),
    ],
)
def test_mistakes_name_their_column(text: str, message: str) -> None:
    with pytest.raises(FormulaError, match=message):
        parse(text)
