"""Errors carry fields (what, where, expected) beside their message, also across the services."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from dyknow import BindingError, Client, DyKnowError, LibraryError, Manager, SpecError, SpecIssue, TagError, UnitError, parse_term
from dyknow.errors import compose
from dyknow.keys import check_name
from dyknow.transport import check_key_expr


def test_the_message_is_composed_from_the_fields() -> None:
    assert compose("bad", "unit 'a'", "good") == "unit 'a': bad; expected good"
    assert compose("bad") == "bad"
    error = UnitError("no port 'ot'", where="unit 'r1'", expected="one of 'in', 'out'")
    assert str(error) == "unit 'r1': no port 'ot'; expected one of 'in', 'out'"
    assert error.to_dict() == {
        "error": "UnitError",
        "message": "unit 'r1': no port 'ot'; expected one of 'in', 'out'",
        "what": "no port 'ot'",
        "where": "unit 'r1'",
        "expected": "one of 'in', 'out'",
    }


def test_spec_issues_have_fields_and_round_trip() -> None:
    issue = SpecIssue("a.xml", 3, "unknown direction 'inn'", "<port> @type", "in or out")
    assert str(issue) == "a.xml:3: <port> @type: unknown direction 'inn'; expected in or out"
    assert issue.where == "a.xml:3" and SpecIssue.from_dict(issue.to_dict()) == issue
    error = SpecError([issue, SpecIssue("b.xml", 0, "cannot read: No such file")])
    assert str(error).splitlines() == [str(issue), "b.xml: cannot read: No such file"]
    assert error.where == "a.xml:3" and error.to_dict()["issues"][1]["path"] == "b.xml"


def _spawn_unknown(manager: Manager) -> None:
    manager.spawn("nope", "x")


CASES: list[tuple[str, Callable[[Manager], Any], type[DyKnowError], str, str | None, str | None]] = [
    ("unknown unit", lambda m: m.destroy("ghost"), UnitError, "no unit named 'ghost'", "manager '{m}'", "one of the running units: none"),
    ("unknown label", lambda m: m.spawn("rely", "r"), LibraryError, "no transformation labelled 'rely'", None, "one of the known labels"),
    ("unknown param", lambda m: m.spawn("relay", "r", params={"x": 1}), UnitError, "no param 'x'", "transformation 'relay'", "one of none"),
    ("bad param value", lambda m: m.spawn("periodic-source", "s", params={"rate_hz": "fast"}), UnitError, "got 'fast'", "param 'rate_hz' of 'periodic-source'", "a number (float)"),
    ("unknown port", lambda m: m.spawn("relay", "r", bindings={"ot": "a/b"}), BindingError, "no port 'ot'", "transformation 'relay'", "one of 'in', 'out' (did you mean 'out'?)"),
    ("bad key", lambda m: m.spawn("relay", "r", bindings={"out": "a/*"}), BindingError, "'a/*' has wildcards", "port 'out' of unit 'r'", "a concrete key to publish on, like 'robot/camera/image'"),
    ("bad unit name", lambda m: m.spawn("relay", "-r"), UnitError, "unit name '-r' is not a valid name", None, "letters, digits, '_', '-' or '.', not starting with '-' or '.' (it becomes part of Zenoh keys)"),
]


@pytest.mark.parametrize(("case", "call", "cls", "what", "where", "expected"), CASES, ids=[c[0] for c in CASES])
def test_errors_carry_their_fields_here_and_over_the_services(
    make_manager: Callable[..., Manager], case: str, call: Callable[[Manager], Any], cls: type[DyKnowError], what: str, where: str | None, expected: str | None
) -> None:
    manager = make_manager()
    where = where.format(m=manager.name) if where else None
    with pytest.raises(cls) as local:
        call(manager)
    assert local.value.what == what and local.value.where == where
    assert (local.value.expected or "").startswith(expected or "")
    with Client(manager.name, connect=manager.endpoints) as client:  # the same error, rebuilt on the caller's side
        with pytest.raises(cls) as remote:
            call(client)  # type: ignore[arg-type]  # the client mirrors these manager methods
    assert (remote.value.what, remote.value.where, remote.value.expected, str(remote.value)) == (
        local.value.what,
        local.value.where,
        local.value.expected,
        str(local.value),
    )


def test_errors_of_keys_and_tags_have_fields() -> None:
    with pytest.raises(UnitError) as name:
        check_name("a/b", "manager name")
    assert name.value.what == "manager name 'a/b' is not a valid name"
    with pytest.raises(BindingError) as key:
        check_key_expr("a//b", what="subscription")
    assert key.value.where == "subscription" and key.value.expected == "chunks separated by '/', like 'robot/camera/image'"
    with pytest.raises(TagError) as tag:
        parse_term("Ball(")
    assert tag.value.where == "tag 'Ball('" and (tag.value.expected or "").startswith("Functor or Functor(arg, ...)")
