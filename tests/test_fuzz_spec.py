"""Fuzzing the spec reader: any document parses or is a SpecError located in it; specs round-trip.

Derandomized (the same examples every run) and bounded for CI; ``tools/fuzz.py --targets spec``
runs the same properties randomized for longer.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from dyknow.testing.fuzzing import Mutated, check_spec_document, derandomized, mutated_documents, spec_documents
from tests.conftest import REPO

SEEDS = {path.name: path.read_bytes() for path in [*sorted((REPO / "specs").glob("*.xml")), REPO / "tests" / "units.xml"]}


def _check_generated(document: bytes, parsed: list[int]) -> None:
    parsed.append(len(check_spec_document(document)))


def test_a_generated_document_parses_and_round_trips_or_is_a_located_spec_error() -> None:
    parsed: list[int] = []
    derandomized(300)(given(spec_documents(), st.just(parsed))(_check_generated))()
    # the round trip is exercised only if many documents parse, several specs to a document too
    assert sum(1 for n in parsed if n) > len(parsed) // 3 and max(parsed) >= 3, parsed


@derandomized(1000)
@given(mutated_documents(sorted(SEEDS)))
@example(Mutated("generic.xml", (("encoding", 0, "utf-32"),)))
@example(Mutated("generic.xml", (("nest", 200, 100_000),)))
@example(Mutated("vision.xml", (("attribute", 3, b"1e309"), ("text", 7, b"9" * 5000))))
@example(Mutated("generic.xml", (("encoding", 0, "unicode_escape"),)))
def test_a_mutated_real_spec_parses_or_is_a_located_spec_error(mutated: Mutated) -> None:
    check_spec_document(mutated.apply(SEEDS[mutated.seed]), mutated.seed)


FOUND = [
    # a ValueError from int() (over 4,300 digits), not a SpecError
    b"<transformation><label>p</label><source>m:C</source><ports><port type='out'>o</port></ports><priority>" + b"9" * 5000 + b"</priority></transformation>",
    # loaded as infinity; to_xml() wrote 'inf', which does not read back
    b'<transformation><label>c</label><source>m:C</source><ports><port type="out">o</port></ports><constraints><constraint measure="m" op="&lt;" value="1e309"/></constraints></transformation>',
    # to_xml() wrote the carriage return as such, and it read back as a newline
    b'<transformation><label>a&#13;b</label><source>m:C</source><ports><port type="out">o</port></ports></transformation>',
    # the codec's DeprecationWarning escaped where warnings are errors
    b'<?xml version="1.0" encoding="unicode_escape"?><transformation/>',
]


@pytest.mark.parametrize("document", FOUND, ids=["huge-priority", "infinite-constraint", "carriage-return", "unicode-escape"])
def test_what_fuzzing_found_stays_fixed(document: bytes) -> None:
    check_spec_document(document)


def test_the_seeds_are_the_real_specs_and_parse() -> None:
    assert {"generic.xml", "vision.xml", "units.xml"} <= set(SEEDS)
    for name, data in SEEDS.items():
        assert check_spec_document(data, name), name  # the round trip is checked on every real spec


def test_a_mutation_names_its_seed_and_changes(tmp_path: Path) -> None:
    mutated = Mutated("generic.xml", (("truncate", 10, None), ("insert", 0, b"<")))
    assert mutated.apply(b"<transformations/>") == b"<<transform"
    assert "generic.xml" in repr(mutated) and "truncate" in repr(mutated)
