"""Tag terms: parsing, canonical text, local names."""

from __future__ import annotations

import pytest

from dyknow.errors import DyKnowError, TagError
from dyknow.tags import Term, local_name, parse_term

EXPECTED = "expected Functor or Functor(arg, ...)"


@pytest.mark.parametrize(
    ("text", "functor", "args", "canonical"),
    [
        ("BallPosition", "BallPosition", (), "BallPosition"),
        ("  BallPosition  ", "BallPosition", (), "BallPosition"),
        ("BallPosition(field)", "BallPosition", ("field",), "BallPosition(field)"),
        ("BallPosition( field )", "BallPosition", ("field",), "BallPosition(field)"),
        ("BallPosition (field)", "BallPosition", ("field",), "BallPosition(field)"),
        ("Undistorted(cam1,rel)", "Undistorted", ("cam1", "rel"), "Undistorted(cam1, rel)"),
        ("F(\ta ,\n b )", "F", ("a", "b"), "F(a, b)"),
        ("ex:Camera", "ex:Camera", (), "ex:Camera"),
        ("sosa:Sensor(dk:bottom)", "sosa:Sensor", ("dk:bottom",), "sosa:Sensor(dk:bottom)"),
        (":Camera", ":Camera", (), ":Camera"),
        ("_private.v2-x", "_private.v2-x", (), "_private.v2-x"),
        ("<http://www.w3.org/ns/sosa/Sensor>", "<http://www.w3.org/ns/sosa/Sensor>", (),
         "<http://www.w3.org/ns/sosa/Sensor>"),
        ("<https://dyknow.dev/ontology#BallPosition>(<https://dyknow.dev/ontology#field>, rel)",
         "<https://dyknow.dev/ontology#BallPosition>", ("<https://dyknow.dev/ontology#field>", "rel"),
         "<https://dyknow.dev/ontology#BallPosition>(<https://dyknow.dev/ontology#field>, rel)"),
    ],
)  # fmt: skip
def test_parse_term_accepts(text: str, functor: str, args: tuple[str, ...], canonical: str) -> None:
    term = parse_term(text)
    assert term == Term(functor, args)
    assert str(term) == canonical
    assert parse_term(str(term)) == term  # the canonical text reads back as the same term


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("Foo(", ["tag 'Foo(': unbalanced parenthesis; " + EXPECTED]),
        ("Foo(a", ["unbalanced parenthesis", "'(' is never closed"]),
        ("Foo(a))", ["unbalanced parenthesis", "')' at column 7 closes nothing"]),
        ("Foo)", ["unbalanced parenthesis", "')' at column 4"]),
        ("", ["tag '': empty tag; " + EXPECTED]),
        ("   ", ["empty tag"]),
        ("Foo()", ["empty parentheses", "write Foo for a tag without args"]),
        ("Foo( )", ["empty parentheses"]),
        ("Foo(a,)", ["empty arg", "arg 2"]),
        ("Foo(,a)", ["empty arg", "arg 1"]),
        ("Foo(a,,b)", ["empty arg", "arg 2"]),
        ("Foo(Bar(x))", ["nested terms are not allowed", "arg 1 is Bar(...)"]),
        ("Foo(a) b", ["unexpected text 'b' after the term at column 8"]),
        ("Foo bar", ["unexpected text 'bar'"]),
        ("9Foo", ["unexpected character '9' at column 1 where the functor should start"]),
        ("Foo(a b)", ["unexpected character 'b' at column 7 after arg 1"]),
        ("Foo(a;b)", ["unexpected character ';'"]),
        ("Foo(9)", ["unexpected character '9' at column 5 where arg 1 should start"]),
        ("Undistorted(${Cam})", ["unexpected character '$'", "template variable ${...} left unexpanded"]),
        ("<>", ["unexpected character '<' at column 1", "IRI in angle brackets"]),
        ("<http://a b>", ["IRI in angle brackets must be non-empty, without spaces"]),
        ("ex:", ["unexpected text ':'"]),
    ],
)
def test_parse_term_refuses(text: str, fragments: list[str]) -> None:
    with pytest.raises(TagError) as caught:
        parse_term(text)
    message = str(caught.value)
    assert message.startswith(f"tag {text!r}: ")
    assert EXPECTED in message
    for fragment in fragments:
        assert fragment in message


def test_tag_error_is_a_dyknow_error() -> None:
    assert issubclass(TagError, DyKnowError)


def test_terms_are_cached_and_immutable() -> None:
    first = parse_term("BallPosition(field)")
    assert parse_term("BallPosition(field)") is first
    with pytest.raises(AttributeError):
        first.functor = "Other"  # type: ignore[misc]


def test_term_checks_names_when_built_directly() -> None:
    assert str(Term("F", ("a", "dk:b"))) == "F(a, dk:b)"
    with pytest.raises(TagError, match="term name 'Foo bar' is not a name"):
        Term("Foo bar")
    with pytest.raises(TagError, match="term name 'x,y' is not a name"):
        Term("F", ("x,y",))


@pytest.mark.parametrize(
    ("name", "local"),
    [
        ("<http://x/y#Camera>", "Camera"),
        ("<http://w3.org/ns/sosa/Sensor>", "Sensor"),
        ("<http://www.w3.org/ns/sosa/>", "sosa"),
        ("<urn:dyknow:Camera>", "Camera"),
        ("http://x/y#Camera", "Camera"),
        ("https://dyknow.dev/ontology#rel", "rel"),
        ("ex:Camera", "Camera"),
        (":Camera", "Camera"),
        ("Camera", "Camera"),
        (" dk:rel ", "rel"),
    ],
)
def test_local_name(name: str, local: str) -> None:
    assert local_name(name) == local
