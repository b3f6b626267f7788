"""Fuzzing the tag reader: generated terms round-trip, and any text is a term or a TagError.

Derandomized and bounded for CI; ``tools/fuzz.py --targets tags`` runs the same properties
randomized for longer.
"""

from __future__ import annotations

from hypothesis import example, given

from dyknow.tags import Term
from dyknow.testing.fuzzing import check_tag_text, check_term, derandomized, tag_texts, terms


@derandomized(1000)
@given(terms())
@example(Term("<http://x/y#a,b>", ("dk:X", ":y", "z.-")))
def test_a_term_written_out_parses_back_as_itself(term: Term) -> None:
    check_term(term)


@derandomized(1000)
@given(tag_texts())
@example("\u3000F\x85(\u2028a ,\tb)\xa0")  # Unicode whitespace, which the reader skips like ASCII
@example("F(G(x))")
@example("${Cam}")
def test_any_text_is_a_term_that_round_trips_or_a_tag_error(text: str) -> None:
    check_tag_text(text)

