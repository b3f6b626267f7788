"""The formula language (dyknow.reasoning.syntax): what parses to what, what is refused and how
the error says so (column, what was expected), and that the written form parses back."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings

from dyknow.errors import DyKnowError, FormulaError
from dyknow.reasoning import Formula, Monitor, check_formula, evaluate_ns, monitor_spec, parse, term_ports
from dyknow.reasoning.syntax import (
    MAX_DEPTH,
    MAX_FORMULA_CHARS,
    Aggregate,
    Always,
    And,
    Arith,
    Atom,
    Call,
    Const,
    Eventually,
    Fall,
    Historically,
    Implies,
    Interval,
    Neg,
    Not,
    Num,
    Once,
    Or,
    Prev,
    Quantifier,
    Rise,
    Since,
    Str,
    Stream,
    Until,
    Var,
)
from dyknow.tags import Term
from tests.reasoning_support import formulas

S = 1_000_000_000
MS = 1_000_000
P, Q, R = Term("p"), Term("q"), Term("r")
BATTERY = Term("Battery", ("robot",))


def cmp(term: Term, fields: tuple[str, ...], op: str, number: float | int) -> Atom:
    """``TERM.FIELDS OP NUMBER``, the comparison of a stream with a number."""
    return Atom(Stream(term, fields), op, Num(number))


def bare(term: Term, fields: tuple[str, ...] = ()) -> Atom:
    """A stream read as a condition."""
    return Atom(Stream(term, fields))


def s_(name: str, *args: str, fields: tuple[str, ...] = ()) -> Stream:
    return Stream(Term(name, tuple(args)), fields)


@pytest.mark.parametrize(
    ("text", "root"),
    [
        ("Battery(robot) > 0.2", cmp(BATTERY, (), ">", 0.2)),
        ("Battery( robot )>=-1e-3", cmp(BATTERY, (), ">=", -0.001)),
        ("BallTrack(field).speed < 3", cmp(Term("BallTrack", ("field",)), ("speed",), "<", 3.0)),
        ("Pose(robot).position.x != 0", cmp(Term("Pose", ("robot",)), ("position", "x"), "!=", 0.0)),
        ("Stalled(robot)", bare(Term("Stalled", ("robot",)))),
        ("Door(hall).open", bare(Term("Door", ("hall",)), ("open",))),
        ("Ticks.count == 2", cmp(Term("Ticks"), ("count",), "==", 2.0)),  # the name ends at the first dot
        ("`cam.left`.exposure <= 3", cmp(Term("cam.left"), ("exposure",), "<=", 3.0)),  # a tag with a dot
        ("`once` and p", And(bare(Term("once")), bare(P))),  # a tag spelled like a keyword
        ("dk:Battery(robot) < 1", cmp(Term("dk:Battery", ("robot",)), (), "<", 1.0)),
        ("<http://x.org/B>(r) < 1", cmp(Term("<http://x.org/B>", ("r",)), (), "<", 1.0)),
        ("true or false", Or(Const(True), Const(False))),
        ("not not p", Not(Not(bare(P)))),
        ("p and q or r", Or(And(bare(P), bare(Q)), bare(R))),
        ("p or q and r", Or(bare(P), And(bare(Q), bare(R)))),
        ("p implies q implies r", Implies(bare(P), Implies(bare(Q), bare(R)))),  # right-associative
        ("p and q implies r or p", Implies(And(bare(P), bare(Q)), Or(bare(R), bare(P)))),
        ("always[0, 1s] p and q", And(Always(Interval(0, S), bare(P)), bare(Q))),  # unary binds tightest
        ("eventually[500ms, 2s] (p and q)", Eventually(Interval(500 * MS, 2 * S), And(bare(P), bare(Q)))),
        ("historically[0,0] p", Historically(Interval(0, 0), bare(P))),
        ("once[1.5s, inf] p", Once(Interval(1500 * MS, None), bare(P))),
        ("p until[0, 10ms] q and r", And(Until(bare(P), bare(Q), Interval(0, 10 * MS)), bare(R))),
        ("not p since[0, inf] q", Since(Not(bare(P)), bare(Q), Interval(0, None))),
        ("(p until[0, 1s] q) until[0, 1s] r", Until(Until(bare(P), bare(Q), Interval(0, S)), bare(R), Interval(0, S))),
        ("once[0, 0.000000001s] p", Once(Interval(0, 1), bare(P))),
        # issue 39: two streams, arithmetic, strings, booleans, edges, aggregates, quantifiers
        ("Speed(robot) < SpeedLimit(zone)", Atom(s_("Speed", "robot"), "<", s_("SpeedLimit", "zone"))),
        ("Pose(robot).x - Goal(robot).x < 0.1", Atom(Arith("-", s_("Pose", "robot", fields=("x",)), s_("Goal", "robot", fields=("x",))), "<", Num(0.1))),
        ("abs(Error(robot)) < 0.1", Atom(Call("abs", (s_("Error", "robot"),)), "<", Num(0.1))),
        ("a + b * c - -d / 2 >= min(a, max(b, 3))", Atom(Arith("-", Arith("+", s_("a"), Arith("*", s_("b"), s_("c"))), Arith("/", Neg(s_("d")), Num(2))), ">=", Call("min", (s_("a"), Call("max", (s_("b"), Num(3))))))),
        ("(a + b) * c > 1", Atom(Arith("*", Arith("+", s_("a"), s_("b")), s_("c")), ">", Num(1))),
        ('Mode(robot) == "manual"', Atom(s_("Mode", "robot"), "==", Str("manual"))),
        ("Mode(robot) != 'it\\'s'", Atom(s_("Mode", "robot"), "!=", Str("it's"))),
        ("Door(hall).open == true", Atom(s_("Door", "hall", fields=("open",)), "==", Const(True))),
        ("Pose(robot).x > Pose(robot).y", Atom(s_("Pose", "robot", fields=("x",)), ">", s_("Pose", "robot", fields=("y",)))),
        ("prev(Speed(robot)) > 1", Atom(Prev(s_("Speed", "robot")), ">", Num(1))),
        ("prev(p and q)", Prev(And(bare(P), bare(Q)))),
        ("rise(Door(hall).open) implies eventually[0, 2s] Alarm(hall)", Implies(Rise(bare(Term("Door", ("hall",)), ("open",))), Eventually(Interval(0, 2 * S), bare(Term("Alarm", ("hall",)))))),
        ("not fall(p)", Not(Fall(bare(P)))),
        ("avg[0, 1s] Speed(robot) < 0.5", Atom(Aggregate("avg", Interval(0, S), s_("Speed", "robot")), "<", Num(0.5))),
        ("avg[0, 1s] x + 1 > 2", Atom(Arith("+", Aggregate("avg", Interval(0, S), s_("x")), Num(1)), ">", Num(2))),  # an aggregate binds its operand
        ("count[0, 10s] rise(Bump(robot)) <= 3", Atom(Aggregate("count", Interval(0, 10 * S), Rise(bare(Term("Bump", ("robot",))))), "<=", Num(3))),
        ("integral[0, 60s] Current(motor) < 120", Atom(Aggregate("integral", Interval(0, 60 * S), s_("Current", "motor")), "<", Num(120))),
        ("rate[1s, inf] Odo(r) > 0", Atom(Aggregate("rate", Interval(S, None), s_("Odo", "r")), ">", Num(0))),
        ("count(x) > 1", cmp(Term("count", ("x",)), (), ">", 1)),  # a tag named count: no window, no aggregate
        ("robustness(historically[0, 1s] Speed(r) < 2) >= 0.1", Atom(Call("robustness", (Historically(Interval(0, S), Atom(s_("Speed", "r"), "<", Num(2))),)), ">=", Num(0.1))),
        ("forall c in Camera: Fresh(c)", Quantifier("forall", "c", "Camera", bare(Term("Fresh", ("c",))))),
        ("forall a in Robot: forall b in Robot: D(a) > D(b) or a == b", Quantifier("forall", "a", "Robot", Quantifier("forall", "b", "Robot", Or(Atom(s_("D", "a"), ">", s_("D", "b")), Atom(Var("a"), "==", Var("b")))))),
        ("always[0, 1s] (exists c in dk:Camera: Fresh(c))", Always(Interval(0, S), Quantifier("exists", "c", "dk:Camera", bare(Term("Fresh", ("c",)))))),
        ("foreach t in Track(f).id: Track(f).speed < 3 and t != \"ghost\"", Quantifier("foreach", "t", s_("Track", "f", fields=("id",)), And(Atom(s_("Track", "f", fields=("speed",)), "<", Num(3)), Atom(Var("t"), "!=", Str("ghost"))))),
    ],
)
def test_what_parses_to_what(text: str, root: object) -> None:
    formula = parse(text)
    assert formula.root == root
    assert formula.text == text
    assert parse(str(formula)).root == root  # the canonical text reads back the same


def test_terms_past_horizon_and_operators() -> None:
    formula = parse(
        "Battery(robot).level > 0.2 since[0, inf] (eventually[0, 2s] p and always[1s, 3s] eventually[0, 500ms] Battery(robot).ok)"
    )
    assert formula.terms == (BATTERY, P)  # distinct, in order of first appearance
    assert not formula.past_only
    assert formula.horizon_ns == 3 * S + 500 * MS  # always[1s, 3s] eventually[0, 500ms]: the longest path
    assert formula.operators == 5  # since, eventually, and, always, eventually
    assert parse("historically[0, 1s] p since[0, inf] q").past_only
    assert parse("p").horizon_ns == 0 and parse("p").operators == 0
    assert Formula.of(And(bare(P), bare(Q))).text == "p and q"


ERRORS = [
    # (text, column, what starts with, expected contains)
    ("", 1, "unexpected end of formula", "a condition"),
    ("always p", 8, "unexpected 'p'", "'[' after 'always'"),
    ("always[0, 1s]", 14, "unexpected end of formula", "a condition"),
    ("x >", 4, "unexpected end of formula", "a value"),
    ("x > 3s", 5, "'3s' is neither a number nor a stream", "a value"),
    ("3", 1, "'3' is a number, not a condition", "a comparison"),
    ("3 and p", 1, "'3' is a number, not a condition", "a comparison"),
    ('Speed(r) + "fast" > 1', 12, "'\"fast\"' is a string, and '+' takes numbers", "a number"),
    ('"a" < 1', 1, "'\"a\"' is a string, and '<' takes numbers", "a number"),
    ('1 == "a"', 3, "'1' is a number and '\"a\"' a string: they are never equal", "two values of one kind"),
    ("x > 3 > 2", 7, "a second comparison right after '>'", "one comparison per atom"),
    ("avg[0, 1s] (p and q) > 1", 13, "'p and q' is a condition, and avg takes numbers", "a number"),
    ("avg[0, 1s] (eventually[0, 1s] x > 0) > 1", 13, "'eventually[0, 1s] x > 0' is a condition", "a number"),
    ("count[0, 1s] (eventually[0, 1s] p) > 1", 15, "count reads values decided by its state, and 'eventually[0, 1s] p' looks into the future", "an operand without always"),
    ("rise(eventually[0, 1s] p)", 6, "rise reads values decided by its state", "outside the future operator"),
    ("(eventually[0, 1s] p) == true", 2, "'==' reads values decided by its state", "outside the future operator"),
    ("avg[0, inf] x > 1 and sum[0, 1s] x < eventually[0,1s] p", 38, "unexpected keyword 'eventually'", "a value"),
    ("min(x) > 1", 1, "min of 1 operand", "min of 2: min(x, y)"),
    ("robustness(eventually[0, 1s] p) > 0", 12, "robustness reads values decided by its state", "outside the future operator"),
    ("abs(x, y) > 1", 1, "abs of 2 operands", "abs of 1: abs(x)"),
    ("abs(x > 1) > 1", 5, "'x > 1' is a condition, and abs takes numbers", "a number"),
    ("mode == 'manual", 9, "the string opened by ' is never closed", "a closing '"),
    ("forall c in Camera: p", 1, "the variable 'c' is not used in the formula", "Fresh(c)"),
    ("forall c Camera: Fresh(c)", 10, "unexpected 'Camera:'", "'in' after the variable"),
    ("forall c in Camera Fresh(c)", 20, "unexpected 'Fresh'", "':' before the quantifier's formula"),
    ("forall c in A: forall c in B: Fresh(c)", 23, "the variable 'c' is bound already", "another name"),
    ("p and forall c in C: Fresh(c)", 7, "'forall' inside an operator", "parentheses around the quantified formula"),
    ("always[0, 1s] (foreach t in T.id: t == 1)", 16, "'foreach' inside the formula", "foreach first"),
    ("foreach t in T: t == 1", 14, "foreach over the stream T itself", "a field that names the object"),
    ("foreach t in T(x).id: Speed(t, t) > 1", 32, "a second computed argument of Speed(...)", "one argument computed at each state"),
    ("forall c in C: c.x > 1", 17, "a field of the variable 'c'", "the variable alone"),
    ("x = 3", 3, "unexpected '='", "=="),
    ("x => 3", 3, "unexpected '='", "=="),
    ("always[0, inf] p", 11, "'inf' as the upper bound of the future operator 'always'", "only past windows"),
    ("p until[0, inf] q", 12, "'inf' as the upper bound of the future operator 'until'", "finite upper bound"),
    ("once[inf, inf] p", 6, "'inf' as a lower bound", "finite lower bound"),
    ("once[1s, 0] p", 6, "the interval's lower bound 1s is above its upper bound 0", "a <= b"),
    ("once[1, 2s] p", 6, "the duration 1 has no unit", "1s or 1ms"),
    ("once[0 2s] p", 8, "unexpected '2s'", "','"),
    ("once[0, 2s p", 12, "unexpected 'p'", "']'"),
    ("once[0, 0.0000000001s] p", 9, "the duration 0.0000000001s is finer than a nanosecond", "whole number of nanoseconds"),
    ("a until[0,1s] b until[0,1s] c", 17, "'until' right after 'until'", "parentheses"),
    ("(a and b", 9, "unexpected end of formula", "')'"),
    ("a b", 3, "unexpected 'b'", "the end of the formula"),
    ("p untill[0, 1s] q", 3, "unexpected 'untill'", "did you mean 'until'"),
    ("evenutally[0, 1s] p", 1, "'evenutally' is not a temporal operator", "did you mean 'eventually'"),
    ("Always[0, 1s] p", 1, "'Always' is not a temporal operator", "did you mean 'always'"),
    ("and x", 1, "unexpected keyword 'and'", "a value"),
    ("p and", 6, "unexpected end of formula", "a condition"),
    ("once[0, 1s] p)", 14, "unexpected ')'", "the end of the formula"),
    ("x.", 3, "unexpected end of formula", "a field name after '.'"),
    ("Battery(robot", 8, "unbalanced parenthesis", "')'"),
    ("Bat(a b) > 1", 7, "unexpected 'b'", "',' or ')' after argument 1 of Bat(...)"),
    ("Bat(a, Zone(r).z, Zone(r).y) > 1", 19, "a second computed argument of Bat(...)", "one argument computed at each state"),
    ("Bat(once[0, 1s] Zone(r).z) > 1", 5, "'once[0, 1s] Zone(r).z' is a condition", "a string naming the member"),
    ("Bat(prev(Zone(r).z)) > 1", 5, "an argument of Bat(...) reads 'prev(Zone(r).z)', more than the state", "no windows, aggregates, prev"),
    ("Bat(Lim(Zone(r).z)) > 1", 5, "an argument of Bat(...) is itself a parameterized term", "an argument over plain streams"),
    ('Bat("z1") > 1', 5, "an argument of Bat(...) is the constant '\"z1\"'", "a name, written as it is (Bat(z1))"),
    ("`cam.left > 1", 1, "'`' is never closed", "backquotes"),
    ("<http://x", 1, "'<' opens an IRI that is never closed", "a term such as"),
    ("<http://x y>(r) > 1", 1, "term '<http://x y>(r)' is not a tag", "without spaces"),
]


@pytest.mark.parametrize(("text", "column", "what", "expected"), ERRORS, ids=[e[0] or "empty" for e in ERRORS])
def test_parse_errors_name_the_column_and_what_was_expected(text: str, column: int, what: str, expected: str) -> None:
    with pytest.raises(FormulaError) as caught:
        parse(text)
    error = caught.value
    assert isinstance(error, DyKnowError)
    assert (error.where, error.column, error.formula) == (f"formula column {column}", column, text)
    assert error.what.startswith(what), error.what
    assert expected in (error.expected or ""), error.expected
    assert str(error).startswith(f"formula column {column}: ")
    assert error.to_dict()["column"] == column


def test_untrusted_formulas_are_bounded() -> None:
    with pytest.raises(FormulaError) as long:
        parse("p or " * (MAX_FORMULA_CHARS // 5) + "p")
    assert long.value.what.startswith("the formula has") and long.value.expected == f"at most {MAX_FORMULA_CHARS}"
    with pytest.raises(FormulaError) as deep:
        parse("(" * (MAX_DEPTH + 5) + "p" + ")" * (MAX_DEPTH + 5))
    assert "nests deeper than" in deep.value.what
    with pytest.raises(FormulaError) as nots:
        parse("not " * (MAX_DEPTH + 5) + "p")
    assert "nests deeper than" in nots.value.what
    with pytest.raises(FormulaError) as wrong_type:
        parse(42)  # type: ignore[arg-type]
    assert wrong_type.value.what == "a formula is text, got int"
    assert parse("not " * (MAX_DEPTH - 5) + "p").operators == MAX_DEPTH - 5  # deep but allowed


@settings(max_examples=800, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(formula=formulas(max_depth=6, rich=True, future=False) | formulas(max_depth=6))
def test_every_formula_written_out_parses_back_to_itself(formula: Formula) -> None:
    text = str(formula)
    again = parse(text)
    assert again.root == formula.root, text
    assert again.terms == formula.terms
    assert str(again) == text


# -- formulas from callers the manager does not trust (issue 38)


def _every_walk(formula: Formula) -> None:
    """What the manager and the monitor do with a formula: write it, compare, hash, show it, build
    its spec and its monitor, evaluate it."""
    text = str(formula)
    again = parse(text)
    assert again == formula and hash(again) == hash(formula) and again.root == formula.root
    assert repr(formula.root).startswith(type(formula.root).__name__ + "(")
    spec = monitor_spec(formula)
    assert term_ports(spec) == term_ports(formula)
    monitor = Monitor(formula)
    assert monitor.push_all(0, [0.5] * len(monitor.terms)) is not None
    assert len(evaluate_ns(formula, {str(t): [(0, 0.5)] for t in formula.terms})) == 1


@pytest.mark.parametrize(
    "text",
    [
        " or ".join(f"P(x{i % 7})" for i in range(830)),  # a chain nests to the left, 830 deep
        " and ".join("p" for _ in range(1500)),
        " or ".join("p until[0, 1s] q" for _ in range(500)),
    ],
    ids=["or-830", "and-1500", "until-500"],
)
def test_long_chains_are_walked_without_recursion(text: str) -> None:
    """Parsing reads a chain in a loop, and nothing that walks the tree recurses: an 830-deep
    ``or`` chain is written, compared, hashed, monitored and evaluated (it raised RecursionError
    from str() before); a manager's bounds then refuse it for its size, as a FormulaError."""
    formula = parse(text)
    _every_walk(formula)
    with pytest.raises(FormulaError) as refused:
        check_formula(text)
    assert refused.value.what.startswith("the formula has more than 500 nodes")
    assert refused.value.expected == "at most 500 atoms and operators (Limits.max_formula_nodes)"
    assert refused.value.column is not None and refused.value.where == f"formula column {refused.value.column}"


def test_a_chain_of_200_disjuncts_is_within_the_bounds() -> None:
    text = " or ".join(f"Fresh(cam{i}) > 0.5" for i in range(200))
    formula = check_formula(text)
    assert formula.operators == 199 and len(formula.terms) == 200
    _every_walk(formula)


@pytest.mark.parametrize(
    "text",
    ["not " * 830 + "p", "(" * 830 + "p" + ")" * 830, "p implies " * 830 + "p", "always[0, 1s] " * 500 + "p", "p until[0, 1s] (" * 400 + "p" + ")" * 400],
    ids=["not", "parentheses", "implies", "always", "until"],
)
def test_deep_nesting_is_refused_with_its_column(text: str) -> None:
    for read in (parse, check_formula):
        with pytest.raises(FormulaError) as deep:
            read(text)
        assert deep.value.what.startswith(f"the formula nests deeper than {MAX_DEPTH} levels"), deep.value.what
        assert deep.value.expected == f"at most {MAX_DEPTH} levels of operators and parentheses"
        assert deep.value.column is not None and deep.value.column > 1


def test_a_caller_deep_in_its_stack_gets_a_formula_error_not_a_recursion_error() -> None:
    import sys
    from types import FrameType

    text = "(" * (MAX_DEPTH - 1) + "p" + ")" * (MAX_DEPTH - 1)  # five frames a level
    caught: list[BaseException] = []
    frame: FrameType | None = sys._getframe()
    depth = 0
    while frame is not None:
        frame, depth = frame.f_back, depth + 1

    def descend(levels: int) -> None:
        if levels:
            descend(levels - 1)
            return
        try:
            parse(text)
        except BaseException as exc:  # noqa: BLE001  # what it raises is the point
            caught.append(exc)

    descend(sys.getrecursionlimit() - depth - 100)  # the parser needs more than 100 frames
    (error,) = caught
    assert isinstance(error, FormulaError), repr(error)
    assert error.what.startswith("the formula nests deeper than this thread's stack allows")


@pytest.mark.parametrize(
    ("text", "column", "what", "expected"),
    [
        ("always[0, 100000000000000000000000000000s] p", 7, "'always[0, 100000000000000000000000000000s]' has the bound 100000000000000000000000000000s, beyond the longest window", "bounds of at most 86400s (Limits.max_window_ns)"),
        ("p and once[0, 86401s] q", 11, "'once[0, 86401s]' has the bound 86401s, beyond the longest window", "a past window may write inf"),
        ("once[90000s, inf] q", 5, "'once[90000s, inf]' has the bound 90000s", "at most 86400s"),
        ("p until[86400s, 86400.5s] q", 8, "'until[86400s, 86400.5s]' has the bound 86400500ms", "at most 86400s"),
        ("always[0, 50000s] (p or eventually[0, 40000s] q)", 1, "'always' here makes the formula look 90000s ahead", "at most 86400s ahead (Limits.max_window_ns)"),
    ],
)
def test_windows_are_bounded(text: str, column: int, what: str, expected: str) -> None:
    assert parse(text).text == text  # the language takes them; a manager's bounds do not
    with pytest.raises(FormulaError) as refused:
        check_formula(text)
    error = refused.value
    assert (error.where, error.column) == (f"formula column {column}", column)
    assert error.what.startswith(what), error.what
    assert expected in (error.expected or ""), error.expected


def test_the_bounds_are_the_operators_to_set() -> None:
    from dyknow.security import Limits

    text = "always[0, 2d] p".replace("2d", "172800s")
    with pytest.raises(FormulaError):
        check_formula(text)
    assert check_formula(text, Limits(max_window_ns=3 * 86_400 * S)).horizon_ns == 2 * 86_400 * S
    assert check_formula("once[0, 1s] p", Limits(max_formula_nodes=2)).operators == 1
    with pytest.raises(FormulaError) as nodes:
        check_formula("once[0, 1s] p and q", Limits(max_formula_nodes=2))
    assert nodes.value.column == 19  # at q, the third node read
    assert check_formula(parse("p or q")).text == "p or q"  # a parsed formula is checked by its text
    assert check_formula("historically[0, inf] p").horizon_ns == 0  # inf: no bound to exceed


def test_a_foreach_variable_in_a_term_s_args_is_its_object_s_value() -> None:
    """``Speed(t)`` in the body of ``foreach t in ...`` is a parameterized term: the member its
    object's value names (it was refused before parameterized terms)."""
    from dyknow.reasoning.syntax import Index, Var

    formula = parse("foreach t in T(x).id: Speed(t) > 1")
    body = formula.root.body  # type: ignore[attr-defined]
    assert isinstance(body.left, Index) and body.left.param == 0 and body.left.keys == (Var("t"),)
    assert [str(t) for t in formula.terms] == ["T(x)", "Speed(*)"]
    assert parse(str(formula)).root == formula.root
