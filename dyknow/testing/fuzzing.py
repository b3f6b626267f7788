"""Fuzzing: Hypothesis strategies for what callers and spec authors hand dyknow, and the properties
dyknow must keep whatever they hand it.

Every failure a caller or a spec author can cause is a :class:`~dyknow.errors.DyKnowError`
subclass that says where; nothing else escapes, nothing hangs, nothing dies. Each
:class:`Property` states that for one kind of input:

==========  ======================================================================================
target      property
==========  ======================================================================================
spec        a spec document, generated (:func:`spec_documents`) or a real one mutated
            (:func:`mutated_documents`), parses, or raises :class:`~dyknow.errors.SpecError` whose
            issues name the file and a line of it; a spec that parses writes itself back
            (:meth:`~dyknow.spec.TransformationSpec.to_xml`) as the same spec, and its JSON form
            is strict JSON
tags        a generated tag parses, and ``parse_term(str(parse_term(t))) == parse_term(t)``; any
            text parses or raises :class:`~dyknow.errors.TagError`
request     any payload to any service (JSON or not) is decoded and checked
            (:func:`~dyknow.service.decode_request`, :func:`~dyknow.service.check_request`) into
            the service's fields, or refused with a DyKnowError
service     the same over Zenoh to a real :class:`~dyknow.Manager`: a reply, or an error reply
            naming a DyKnowError class, and the manager answers ``get_model`` after it
mcap        an MCAP file (our writer's or another's) truncated, bit-flipped or with bad length
            fields is read (summary, messages, records, replay) or raises
            :class:`~dyknow.errors.RecordingError`, within a time bound
==========  ======================================================================================

The test suite runs them derandomized and bounded (``tests/test_fuzz_*.py``, with
:func:`derandomized`), so CI is repeatable; ``tools/fuzz.py`` runs them randomized for minutes
before a release (:func:`run_for`). Examples are small records whose ``repr`` is the minimal
failing input Hypothesis reports (a mutation says which seed, where and what).

Hypothesis is a test and development dependency (``pip install 'dyknow[test]'``), not one of
dyknow's: importing this module without it raises :class:`ImportError` saying so, and nothing
else in dyknow imports this module.
"""

from __future__ import annotations

import ast
import json
import math
import os
import re
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

try:
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise ImportError(
        "dyknow.testing.fuzzing needs Hypothesis, a test dependency of dyknow: pip install 'dyknow[test]' (or pip install hypothesis)"
    ) from exc

from dyknow import errors, keys
from dyknow.errors import DyKnowError, RecordingError, ServiceError, SpecError, TagError
from dyknow.message import Message
from dyknow.model import STANDBY_MODES
from dyknow.recording import Player, Recorder, Recording
from dyknow.security import Limits
from dyknow.service import SCHEMAS, UNIT_SERVICES, check_request, decode_request, raise_remote
from dyknow.spec import CONSTRAINT_OPS, PARAM_TYPES, TransformationSpec, parse_specs
from dyknow.tags import Term, parse_term

__all__ = [
    "JSON_PROBES",
    "TARGETS",
    "TEST_PROFILE",
    "Caller",
    "Mutated",
    "MutatedRecording",
    "Outcome",
    "Property",
    "ServiceCall",
    "check_recording",
    "check_request_payload",
    "check_service_call",
    "check_spec_document",
    "check_tag_text",
    "check_term",
    "derandomized",
    "json_values",
    "mcap_property",
    "mutated_documents",
    "mutated_recordings",
    "read_recording",
    "request_payloads",
    "request_property",
    "run_for",
    "service_calls",
    "service_property",
    "spec_documents",
    "spec_property",
    "tag_property",
    "tag_texts",
    "terms",
    "write_seed_recordings",
]

TARGETS: tuple[str, ...] = ("spec", "tags", "request", "service", "mcap")
"""The names of the targets, in the order ``tools/fuzz.py`` runs them."""

TEST_PROFILE = "dyknow-tests"
"""The Hypothesis settings profile of the test suite: derandomized (the same examples every run,
so CI is repeatable), no deadline (a loaded CI machine is slow, not wrong), no example database."""

settings.register_profile(
    TEST_PROFILE,
    derandomize=True,
    deadline=None,
    database=None,
    print_blob=False,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)

JSON_PROBES: Mapping[str, Any] = {
    "null": None,
    "true": True,
    "0": 0,
    "1.5": 1.5,
    "10**30": 10**30,
    '"text"': "text",
    "[]": [],
    "{}": {},
}
"""One JSON value of each type (and a huge integer), to try in every field of every service."""


def derandomized(max_examples: int) -> settings:
    """The test suite's settings (:data:`TEST_PROFILE`) with ``max_examples``, to decorate a test."""
    return settings(settings.get_profile(TEST_PROFILE), max_examples=max_examples)


# --------------------------------------------------------------------------- properties, runs


@dataclass(frozen=True, slots=True)
class Property:
    """A property to fuzz: examples drawn from ``strategy`` are given to ``check``, which raises
    :class:`AssertionError` (or lets an unexpected exception through) when the property fails."""

    name: str
    strategy: st.SearchStrategy[Any]
    check: Callable[[Any], None]

    def hypothesis_test(self, test_settings: settings) -> Callable[[], None]:
        """A Hypothesis test of the property with ``test_settings``; call it to run it."""

        def run(example: Any) -> None:
            self.check(example)

        run.__name__ = run.__qualname__ = self.name  # what Hypothesis's report of a failure calls it
        test: Callable[[], None] = test_settings(given(self.strategy)(run))
        return test


@dataclass(frozen=True, slots=True)
class Outcome:
    """What a run of a property found: how many examples were tried (shrinking included) in how
    long, and the failure (the minimal example, then the error), or None."""

    name: str
    examples: int
    elapsed_s: float
    failure: str | None = None

    @property
    def ok(self) -> bool:
        """Whether no example failed."""
        return self.failure is None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form ``tools/fuzz.py --json`` prints."""
        return {"target": self.name, "examples": self.examples, "elapsed_s": round(self.elapsed_s, 3), "ok": self.ok, "failure": self.failure}


def run_for(prop: Property, duration_s: float, *, derandomize: bool = False) -> Outcome:
    """Run ``prop`` for about ``duration_s`` (at least one round), randomized unless ``derandomize``.

    Rounds of growing size, each a Hypothesis run of its own, go on while the time left allows
    another; the first failure ends the run, after Hypothesis has shrunk it to a minimal example.
    """
    tried = 0

    def counted(example: Any) -> None:
        nonlocal tried
        tried += 1
        prop.check(example)

    counting = Property(prop.name, prop.strategy, counted)
    started = time.monotonic()
    batch = 10
    while True:
        round_started = time.monotonic()
        round_settings = settings(
            max_examples=batch,
            derandomize=derandomize,
            deadline=None,
            database=None,
            print_blob=False,
            suppress_health_check=list(HealthCheck),
        )
        try:
            counting.hypothesis_test(round_settings)()
        except Exception as exc:  # a failure of the property: report it, with Hypothesis's minimal example
            notes = "\n".join(getattr(exc, "__notes__", ()))
            message = f"{type(exc).__name__}: {exc}"
            return Outcome(prop.name, tried, time.monotonic() - started, f"{notes}\n{message}".strip())
        now = time.monotonic()
        per_example_s = (now - round_started) / max(1, batch)
        left_s = duration_s - (now - started)
        if derandomize or left_s < per_example_s * 10:
            return Outcome(prop.name, tried, now - started)
        batch = int(min(batch * 4, 5000, left_s / per_example_s))


# --------------------------------------------------------------------------- tags


_LOCAL = r"[A-Za-z_][A-Za-z0-9_.\-]{0,8}"
_local_names = st.from_regex(_LOCAL, fullmatch=True)
_prefixed_names = st.builds(lambda p, n: f"{p}:{n}", st.sampled_from(["", "dk", "sosa", "ex_1"]) | _local_names, _local_names)
_iris = st.from_regex(r"<[a-z]{1,5}://[A-Za-z0-9_.~/#%:?=&;,()\-]{1,20}>", fullmatch=True)
_names = st.one_of(_local_names, _prefixed_names, _iris)
# What the tag reader skips around names: \s in Python's re, ASCII and not.
_space = st.text(st.sampled_from(" \t\n\r\x0b\x0c\x1c\x85\xa0\u2003\u2028\u3000"), max_size=2)


def terms() -> st.SearchStrategy[Term]:
    """Well-formed tag terms: a functor (local, prefixed or IRI name) and up to four args."""
    return st.builds(Term, _names, st.lists(_names, max_size=4).map(tuple))


@st.composite
def _term_texts(draw: st.DrawFn) -> str:
    """A term written with arbitrary whitespace around its names, parentheses and commas."""
    term = draw(terms())
    text = draw(_space) + term.functor + draw(_space)
    if term.args:
        parts = [draw(_space) + arg + draw(_space) for arg in term.args]
        text += "(" + ",".join(parts) + ")" + draw(_space)
    return text


_TAG_CHARS = "aZ_09:<>(), \t\n.-$/#{}|\"`^\\é\xa0"


def tag_texts() -> st.SearchStrategy[str]:
    """Tag text: well-formed terms written loosely, near-misses from the tag alphabet, anything."""
    return st.one_of(_term_texts(), st.text(st.sampled_from(_TAG_CHARS), max_size=24), st.text(max_size=24))


def check_term(term: Term) -> None:
    """A term written out parses back as itself, and writes out the same again."""
    text = str(term)
    again = parse_term(text)
    assert again == term, f"{text!r} parses as {again!r}, not {term!r}"
    assert str(again) == text


def check_tag_text(text: str) -> None:
    """``text`` parses (and then its written form parses to the same term) or raises TagError."""
    try:
        term = parse_term(text)
    except TagError as exc:
        assert exc.where == f"tag {text!r}", f"the error names {exc.where!r}, not the tag"
        return
    again = parse_term(str(term))
    assert again == term, f"{text!r} parses as {term!r}, but {str(term)!r} parses as {again!r}"


def tag_property() -> Property:
    """The ``tags`` target: well-formed terms round-trip and any text is a term or a TagError."""

    def check(example: str | Term) -> None:
        if isinstance(example, Term):
            check_term(example)
        else:
            check_tag_text(example)

    return Property("tags", st.one_of(terms(), tag_texts()), check)


# --------------------------------------------------------------------------- spec documents


# Characters XML 1.0 allows (no C0 controls but tab, newline and carriage return).
_xml_chars = st.characters(codec="utf-8", exclude_categories=("Cs", "Cc", "Cn")) | st.sampled_from("\t\n\r <>&\"'$;{}")
_free_text = st.text(_xml_chars, max_size=12)
_identifiers = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,7}", fullmatch=True)
_ODD_NUMBERS = ["1e309", "-1e309", "nan", "NaN", "inf", "-inf", "1e-400", "-0", "+5", "0x10", "1_000", ".5", "1.", "", " "]
_ODD_NUMBERS += ["9" * 30, "9" * 5000, "1" + "0" * 400 + ".5", "\u0663"]  # 5000 digits: past int()'s default limit


def _mostly(usual: st.SearchStrategy[Any], odd: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    """``usual`` 31 times in 32, else ``odd``: a document draws a few dozen values, so most stay
    valid enough to parse (and the round trip is exercised) while every part is sometimes wrong."""
    return st.integers(0, 31).flatmap(lambda i: odd if i == 31 else usual)  # 0, the simplest draw, is usual


def _numbers(values: st.SearchStrategy[Any]) -> st.SearchStrategy[str]:
    return _mostly(values.map(str), st.sampled_from(_ODD_NUMBERS))


def _render(parts: Sequence[tuple[str, str]]) -> str:
    """Template source from literal pieces (their '$' doubled) and ``${Name}`` references."""
    return "".join(value.replace("$", "$$") if kind == "literal" else f"${{{value}}}" for kind, value in parts)


def _template_text(args: Sequence[str], literal: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    """Text made of literal pieces and references to the declared ``args``."""
    piece = literal.map(lambda v: ("literal", v))
    if args:
        piece = piece | st.sampled_from(list(args)).map(lambda a: ("ref", a))
    return st.lists(piece, min_size=1, max_size=3).map(_render)


def _escape(text: str, refs: bool, attribute: bool = False) -> str:
    """``text`` as XML character data; with ``refs``, whitespace and non-ASCII as character references."""
    out = []
    for char in text:
        if char == "&":
            out.append("&amp;")
        elif char == "<":
            out.append("&lt;")
        elif char == ">":
            out.append("&gt;")
        elif char == '"' and attribute:
            out.append("&quot;")
        elif refs and (char in "\t\n\r" or ord(char) > 126):
            out.append(f"&#{ord(char)};")
        else:
            out.append(char)
    return "".join(out)


_SOURCES = ["dyknow.testing:Sink", "transformations.generic:Relay", "pkg.mod:Class"]
_PARAM_VALUES: dict[str, st.SearchStrategy[str]] = {
    "int": _numbers(st.integers()),
    "float": _numbers(st.floats(allow_nan=False, allow_infinity=False)),
    "bool": _mostly(st.sampled_from(["true", "false", "1", "0", "TRUE", " False "]), st.sampled_from(["yes", "", "2"])),
}


@st.composite
def _transformation(draw: st.DrawFn, refs: bool, index: int) -> str:
    """One ``<transformation>`` element: mostly valid values (so that most parse), sometimes odd ones."""
    arg_names = draw(st.lists(_identifiers, max_size=2, unique=True))
    children: list[str] = []
    args = []
    for name in arg_names:
        if draw(st.integers(0, 31)) == 31:
            args.append(f'<arg label="{name}" class="ex:Thing"/>')  # no ontology is loaded: refused, located
        else:
            values = draw(st.lists(st.from_regex(r"[a-z0-9]{1,4}", fullmatch=True), min_size=1, max_size=3, unique=True))
            args.append(f'<arg label="{name}">{{{"; ".join(values)}}}</arg>')
    if args:
        children.append(f"<args>{''.join(args)}</args>")

    def text(element: str, literal: st.SearchStrategy[str]) -> str:
        return f"<{element}>{_escape(draw(_template_text(arg_names, literal)), refs)}</{element}>"

    # every arg in the label, so that the expansions get distinct labels (mostly)
    label = draw(_mostly(_identifiers.map(lambda n: f"{n}.{index}"), _free_text)) + "".join(f"-${{{name}}}" for name in arg_names)
    children.append(f"<label>{_escape(label, refs)}</label>")
    children.append(text("source", _mostly(st.sampled_from(_SOURCES), _free_text)))
    if draw(st.booleans()):
        children.append(text("description", _free_text))

    params = []
    for name in draw(st.lists(_mostly(_identifiers, _free_text), max_size=3, unique=True)):
        kind = draw(_mostly(st.sampled_from(PARAM_TYPES), st.just("double")))
        if kind in _PARAM_VALUES:  # typed: a number or a word alone (a substituted value is rarely one)
            value = draw(_mostly(_PARAM_VALUES[kind], _template_text(arg_names, _PARAM_VALUES[kind])))
        else:
            value = draw(_template_text(arg_names, _free_text))
        mode = f' mode="{draw(_mostly(st.sampled_from(["read", "write"]), st.just("exec")))}"' if kind == "path" and draw(st.booleans()) else ""
        params.append(f'<param name="{_escape(name, refs, True)}" type="{kind}"{mode}>{_escape(value, refs)}</param>')
    if params:
        children.append(f"<params>{''.join(params)}</params>")

    ports = []
    port_names = draw(st.lists(_identifiers, min_size=1, max_size=4, unique=True))
    for name in port_names:
        direction = draw(_mostly(st.sampled_from(["in", "out"]), st.just("both")))
        attributes = f'type="{direction}"'
        if direction == "out" and draw(st.booleans()):
            deadline = draw(_numbers(st.decimals(min_value="0.001", max_value=86_400_000, places=3)))
            attributes += f' deadline-ms="{deadline}"'
        if direction == "in" and draw(st.booleans()):
            attributes += f' queue="{draw(_numbers(st.integers(1, 1_000_000)))}"'
        if direction == "in" and draw(st.booleans()):
            attributes += f' policy="{draw(_mostly(st.sampled_from(["keep-last", "drop-new"]), st.just("drop-old")))}"'
        ports.append(f"<port {attributes}>{name}</port>")
    children.append(f"<ports>{''.join(ports)}</ports>")

    tags = []
    for _ in range(draw(st.integers(0, 3))):
        port = draw(_mostly(st.sampled_from(port_names), _identifiers))
        tag = draw(_mostly(terms().map(str), tag_texts()))
        tags.append(f'<tag port="{_escape(port, refs, True)}">{_escape(tag.replace("$", "$$"), refs)}</tag>')
    if tags:
        children.append(f"<tags>{''.join(tags)}</tags>")

    if draw(st.booleans()):
        children.append(f"<priority>{draw(_numbers(st.integers(-(2**63), 2**63 - 1)))}</priority>")

    constraints = []
    for _ in range(draw(st.integers(0, 2))):
        op, value = draw(
            st.one_of(
                st.tuples(st.sampled_from(CONSTRAINT_OPS), _numbers(st.floats(allow_nan=False, allow_infinity=False))),
                st.tuples(_mostly(st.sampled_from(["==", "!="]), st.sampled_from(CONSTRAINT_OPS)), _identifiers),
            )
        )
        measure = draw(_identifiers)
        constraints.append(f'<constraint measure="{measure}" op="{_escape(op, refs, True)}" value="{_escape(value, refs, True)}"/>')
    if constraints:
        children.append(f"<constraints>{''.join(constraints)}</constraints>")

    order = draw(st.permutations(children))
    separator = draw(st.sampled_from(["", "\n  ", "\r\n  "]))
    kind = draw(_mostly(st.sampled_from(["", ' type="unit"', ' type="nodelet"']), st.just(' type="node"')))
    return f"<transformation{kind}>{separator}{separator.join(order)}{separator}</transformation>"


@st.composite
def _document(draw: st.DrawFn) -> bytes:
    refs = draw(st.booleans())
    transformations = [draw(_transformation(refs, i)) for i in range(draw(st.integers(1, 3)))]
    if len(transformations) == 1 and draw(st.booleans()):
        body = transformations[0]
    else:
        body = "<transformations>\n" + "\n".join(transformations) + "\n</transformations>"
    encoding = draw(st.sampled_from([None, "UTF-8", "utf-8", "ISO-8859-1", "US-ASCII", "UTF-16"]))
    if encoding is None:
        return body.encode("utf-8")
    document = f'<?xml version="1.0" encoding="{encoding}"?>\n{body}\n'
    return document.encode(encoding, "xmlcharrefreplace")  # a character the encoding lacks as a reference


def spec_documents() -> st.SearchStrategy[bytes]:
    """Spec documents built from strategies: one or several transformations with args, params of
    every type, ports, tags, priority and constraints in any order, their values mostly valid and
    sometimes odd (huge numbers, ``1e309``, ``nan``, stray ``$``), text sometimes written as
    character references, in several encodings."""
    return _document()


# -- mutations of real documents


_ODD_TOKENS = [
    b"1e309", b"nan", b"-inf", b"9" * 5000, b"", b"\x00", b"\xff", b"${X}", b"$", b"&amp;", b"&#0;", b"&#x110000;",
    b"&undefined;", b"\xef\xbb\xbf", b"<a>", b"</label>", b"<!DOCTYPE x>", b"<![CDATA[$]]>", b"<?pi x?>", b"<!-- -->",
    b'<?xml version="1.0" encoding="utf-16"?>', b"\r", b"\xe2\x80\xa8",
]  # fmt: skip
_ENCODINGS = ["bogus", "utf-32", "utf-16", "UTF-16LE", "rot13", "latin-1", "ascii", "cp1252", "utf-7", "idna", "punycode",
              "hex", "base64", "zlib", "undefined", "utf_8_sig", "unicode_escape", "shift_jis", "big5", "x" * 300]  # fmt: skip
_ATTRIBUTE_VALUE = re.compile(rb'="([^"]*)"')
_ELEMENT_TEXT = re.compile(rb">([^<]+)<")


@dataclass(frozen=True, slots=True)
class Mutated:
    """A seed document (by name) changed by ``mutations``, each ``(kind, position, argument)``.

    Positions are taken modulo the length of what they index, so any integer is valid and
    Hypothesis shrinks towards the start of the document.
    """

    seed: str
    mutations: tuple[tuple[str, int, Any], ...]

    def apply(self, data: bytes) -> bytes:
        """The seed's bytes with the mutations applied in turn."""
        out = bytearray(data)
        for kind, position, argument in self.mutations:
            out = _mutate_document(out, kind, position, argument)
        return bytes(out)


def _mutate_document(data: bytearray, kind: str, position: int, argument: Any) -> bytearray:
    at = position % (len(data) + 1)
    if kind == "flip" and data:
        data[at % len(data)] ^= 1 << (argument % 8)
    elif kind == "truncate":
        del data[at:]
    elif kind == "insert":
        data[at:at] = argument
    elif kind == "delete":
        del data[at : at + argument]
    elif kind in ("attribute", "text"):
        pattern = _ATTRIBUTE_VALUE if kind == "attribute" else _ELEMENT_TEXT
        found = list(pattern.finditer(data))
        if found:
            match = found[position % len(found)]
            data[match.start(1) : match.end(1)] = argument
    elif kind == "encoding":
        _, closed, rest = bytes(data).partition(b"?>")
        body = rest if data.startswith(b"<?xml") and closed else bytes(data)
        data = bytearray(f'<?xml version="1.0" encoding="{argument}"?>'.encode() + body)
    elif kind == "nest":
        data[at:at] = b"<a>" * argument + b"</a>" * argument
    elif kind == "repeat":
        data[at:at] = data[at : at + 200] * argument
    return data


_mutations = st.one_of(
    st.tuples(st.just("flip"), st.integers(0, 2**20), st.integers(0, 7)),
    st.tuples(st.just("truncate"), st.integers(0, 2**20), st.none()),
    st.tuples(st.just("insert"), st.integers(0, 2**20), st.sampled_from(_ODD_TOKENS)),
    st.tuples(st.just("delete"), st.integers(0, 2**20), st.integers(1, 64)),
    st.tuples(st.just("attribute"), st.integers(0, 2**10), st.sampled_from(_ODD_TOKENS)),
    st.tuples(st.just("text"), st.integers(0, 2**10), st.sampled_from(_ODD_TOKENS)),
    st.tuples(st.just("encoding"), st.just(0), st.sampled_from(_ENCODINGS)),
    st.tuples(st.just("nest"), st.integers(0, 2**20), st.sampled_from([10, 1000, 100_000])),
    st.tuples(st.just("repeat"), st.integers(0, 2**20), st.integers(2, 50)),
)


def mutated_documents(seeds: Sequence[str]) -> st.SearchStrategy[Mutated]:
    """Mutations of the documents named ``seeds``: bit flips, truncation, insertion of odd tokens,
    attribute values and element text replaced by odd values (huge numbers, ``1e309``, ``nan``,
    character references, markup), unknown encodings in the XML declaration, deep nesting."""
    return st.builds(Mutated, st.sampled_from(list(seeds)), st.lists(_mutations, min_size=1, max_size=3).map(tuple))


def _line_breaks(data: str | bytes) -> int:
    """An upper bound of the lines of a document in any encoding (expat counts \\r, \\n and \\r\\n)."""
    if isinstance(data, str):
        return data.count("\n") + data.count("\r") + 1
    return data.count(b"\n") + data.count(b"\r") + 1


def check_spec_document(data: str | bytes, path: str = "fuzz.xml") -> list[TransformationSpec]:
    """``data`` parses into specs that round-trip, or raises SpecError whose issues name ``path``
    and a line of it; returns the specs (none when refused)."""
    try:
        specs = parse_specs(data, path)
    except SpecError as exc:
        assert exc.issues, "a SpecError without issues"
        last = _line_breaks(data)
        for issue in exc.issues:
            assert issue.path == path, f"{issue} names {issue.path!r}, not the file"
            assert 1 <= issue.line <= last, f"{issue} names line {issue.line}; the document has at most {last}"
            assert str(issue).startswith(f"{path}:{issue.line}: ")
        return []
    for spec in specs:
        assert spec.path == path and 1 <= spec.line <= _line_breaks(data), spec.location
        json.dumps(spec.to_dict(), allow_nan=False)  # what get_model sends: strict JSON
        written = spec.to_xml()
        try:
            again = parse_specs(written, path)
        except SpecError as exc:
            raise AssertionError(f"{spec.label!r} does not read back from its to_xml():\n{written}\n{exc}") from None
        assert [replace(s, line=spec.line) for s in again] == [spec], f"{spec} reads back as {again}"
    return specs


def spec_property(seeds: Mapping[str, bytes]) -> Property:
    """The ``spec`` target: generated documents, and the ``seeds`` (name -> bytes) mutated."""

    def check(example: bytes | Mutated) -> None:
        if isinstance(example, Mutated):
            check_spec_document(example.apply(seeds[example.seed]), example.seed)
        else:
            check_spec_document(example)

    return Property("spec", st.one_of(spec_documents(), mutated_documents(sorted(seeds))), check)


# --------------------------------------------------------------------------- service requests


def json_values(max_leaves: int = 20) -> st.SearchStrategy[Any]:
    """Any JSON value (``NaN`` and ``Infinity`` included, as Python's json writes them)."""
    scalars = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20)
    return st.recursive(scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4), max_leaves=max_leaves)


_RAW_PAYLOADS = [
    b"", b"{}", b"null", b"[]", b'"x"', b"{", b"\xff\xfe\x00", b"NaN", b"Infinity", b"-Infinity", b"1" * 5000, b"[" * 10_000,
    b'{"a": 1, "a": 2}', b"\xef\xbb\xbf{}", '{"label": "sink"}'.encode("utf-16"), '{"name": "x"}'.encode("utf-32"),
    b'{"\\ud800": 1}', b'{"name": "\\u0000"}', b"{" + b" " * 2_000_000 + b"}",
]  # fmt: skip
_WORDS = ["sink", "relay", "publisher", "failing", "slow", "x", "", "-x", ".", "a" * 129, "**", "$*", "a/b", "é", "\x00"]


def _field_values(field: str) -> st.SearchStrategy[Any]:
    """Values near what ``field`` takes (names, keys, flags, params), else any JSON."""
    words = st.sampled_from(_WORDS) | st.text(max_size=12)
    by_field: dict[str, st.SearchStrategy[Any]] = {
        "xml": spec_documents().map(lambda d: d.decode("utf-8", "replace")) | st.sampled_from(["/etc/passwd", "specs/generic.xml"]),
        "protected": st.booleans(),
        "params": st.dictionaries(words, st.one_of(st.integers(), st.floats(), st.booleans(), words, st.none()), max_size=4),
        "bindings": st.dictionaries(st.sampled_from(["in", "out", "a"]) | words, words, max_size=3),
        "tag": tag_texts(),
        "value": st.one_of(st.floats(), st.integers(), words),
        # the valid modes (and None, the default) as often as a near miss
        "standby": st.sampled_from([*STANDBY_MODES, None]) | st.sampled_from(["Warm", "hot", " warm", ""]),
    }
    return by_field.get(field, words) | json_values(6)


@st.composite
def _objects(draw: st.DrawFn, service: str) -> dict[str, Any]:
    """A request object for ``service``: each of its fields likely there, sometimes a stranger."""
    request = {field: draw(_field_values(field)) for field in SCHEMAS[service] if draw(st.integers(0, 4))}
    if draw(st.integers(0, 9)) == 0:
        request[draw(st.text(max_size=8))] = draw(json_values(4))
    return request


def request_payloads(service: str) -> st.SearchStrategy[bytes]:
    """Payloads for ``service``: objects of its fields (mostly), any JSON, any bytes, known nasties."""
    return st.one_of(
        _objects(service).map(lambda r: json.dumps(r).encode()),
        _objects(service).map(lambda r: json.dumps(r).encode()),
        json_values().map(lambda v: json.dumps(v).encode()),
        st.binary(max_size=64),
        st.sampled_from(_RAW_PAYLOADS),
    )


@dataclass(frozen=True, slots=True)
class ServiceCall:
    """A request to a manager's service, or to a unit's when ``unit`` is set."""

    service: str
    payload: bytes
    unit: str | None = None

    def __repr__(self) -> str:
        shown = self.payload if len(self.payload) <= 200 else self.payload[:200] + b"... (%d bytes)" % len(self.payload)
        unit = f", unit={self.unit!r}" if self.unit is not None else ""
        return f"ServiceCall({self.service!r}, {shown!r}{unit})"


def service_calls(units: Sequence[str] = ("sink",)) -> st.SearchStrategy[ServiceCall]:
    """Calls of every service in :data:`~dyknow.service.SCHEMAS`; unit services go to one of
    ``units`` or to a unit that does not exist."""

    def one(service: str) -> st.SearchStrategy[ServiceCall]:
        if service in UNIT_SERVICES:
            unit = st.sampled_from([*units, "ghost"])
            return st.builds(ServiceCall, st.just(service), request_payloads(service), unit)
        return st.builds(ServiceCall, st.just(service), request_payloads(service))

    return st.one_of([one(service) for service in SCHEMAS])


def check_request_payload(call: ServiceCall, limits: Limits | None = None) -> dict[str, Any] | None:
    """The payload decodes and checks into the service's fields, or is refused with a DyKnowError
    (a ServiceError naming the field it refuses); returns the checked request, or None."""
    bounds = limits or Limits()
    try:
        request = decode_request(call.payload, bounds)
        checked = check_request(call.service, request, bounds)
    except ServiceError as exc:
        if exc.where is not None and exc.where.startswith("field "):
            field = str(ast.literal_eval(exc.where.removeprefix("field "))).split(".")[0]
            assert field in SCHEMAS[call.service], f"{exc} names a field {call.service!r} does not have"
        return None
    except DyKnowError:
        return None  # a name check of keys.check_name: a UnitError
    assert isinstance(request, dict) and checked == request, f"{request!r} was checked into {checked!r}"
    required = {name for name, (needed, _) in SCHEMAS[call.service].items() if needed}
    assert required <= set(checked) <= set(SCHEMAS[call.service])
    return checked


def request_property(limits: Limits | None = None) -> Property:
    """The ``request`` target: :func:`check_request_payload` for calls of every service."""

    def check(call: ServiceCall) -> None:
        check_request_payload(call, limits)

    return Property("request", service_calls(), check)


class Caller(Protocol):
    """What the ``service`` target calls through: :class:`dyknow.transport.Session` does."""

    def call(self, key: str, payload: bytes, *, timeout_s: float, what: str) -> bytes:
        """Send ``payload`` to the service on ``key`` and return its reply."""
        ...


def check_service_call(caller: Caller, manager: str, call: ServiceCall, timeout_s: float = 10.0) -> None:
    """The manager replies to ``call`` (strict JSON), or refuses it with an error reply naming a
    DyKnowError class that the client rebuilds; then it still answers ``get_model``."""
    if call.unit is None:
        key = keys.manager_service_key(manager, call.service)
    else:
        key = keys.unit_service_key(manager, call.unit, call.service)
    try:
        reply = caller.call(key, call.payload, timeout_s=timeout_s, what=call.service)
    except ServiceError as exc:
        assert exc.kind is not None, f"no error reply: {exc}"
        cls = getattr(errors, exc.kind, None)
        assert isinstance(cls, type) and issubclass(cls, DyKnowError), f"the error reply names {exc.kind!r}, not a DyKnowError"
        assert isinstance(raise_remote(exc), cls)
    else:
        _strict_json(reply)
    model = _strict_json(caller.call(keys.manager_service_key(manager, "get_model"), b"{}", timeout_s=timeout_s, what="get_model"))
    assert model["manager"] == manager


def _refuse_constant(name: str) -> Any:
    raise AssertionError(f"the reply holds {name}, which JSON does not have (only Python's json reads it)")


def _strict_json(data: bytes) -> Any:
    """``data`` as JSON that any client reads: no NaN or Infinity."""
    return json.loads(data, parse_constant=_refuse_constant)


def service_property(caller: Caller, manager: str, units: Sequence[str] = ("sink",), timeout_s: float = 10.0) -> Property:
    """The ``service`` target: :func:`check_service_call` against ``manager`` through ``caller``."""
    return Property("service", service_calls(units), lambda call: check_service_call(caller, manager, call, timeout_s))


# --------------------------------------------------------------------------- MCAP recordings


def write_seed_recordings(folder: str | os.PathLike[str]) -> list[Path]:
    """Small recordings from our own writer, one per chunk compression, in ``folder``: JSON,
    bytes, text, arrays and an image on three topics, several chunks each."""
    import numpy as np  # a dependency of dyknow; imported here so the module stays light

    paths = []
    for compression in ("none", "zstd", "lz4"):
        path = Path(folder) / f"ours-{compression}.mcap"
        with Recorder(path=path, compression=compression, chunk_size=256, metadata={"fuzz": "seed"}) as recorder:
            for i in range(12):
                payload = [
                    {"x": i, "y": [1.5, None, "a"]},
                    bytes(range(i)),
                    f"text {i}",
                    np.arange(i + 1, dtype=np.float32),
                    np.full((4, 5, 3), i, np.uint8),
                ][i % 5]
                recorder.write(Message(payload, i, 1_000_000 + i, 1_000_000 + i, f"fuzz/{i % 3}"))
        paths.append(path)
    return paths


def _length_fields(data: bytes) -> list[int]:
    """The offsets of the 8-byte length field of each top-level record, and of each record in
    an uncompressed chunk: where a bad length does the most harm."""
    offsets = []
    pos = 8
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        offsets.append(pos + 1)
        if opcode == 0x06:  # a Chunk: its records follow its header when uncompressed
            try:
                name_length = struct.unpack_from("<I", data, pos + 9 + 32)[0]
                if name_length == 0:
                    inner = pos + 9 + 36 + 8
                    end = inner + struct.unpack_from("<Q", data, pos + 9 + 36)[0]
                    while inner + 9 <= min(end, len(data)):
                        offsets.append(inner + 1)
                        inner += 9 + struct.unpack_from("<Q", data, inner + 1)[0]
            except struct.error:
                pass
        pos += 9 + length
    return offsets


@dataclass(frozen=True, slots=True)
class MutatedRecording:
    """A seed recording (by name) changed by ``mutations``, each ``(kind, position, argument)``.

    Positions are taken modulo the file's size (for ``length``: modulo the number of length
    fields), so any integer is valid.
    """

    seed: str
    mutations: tuple[tuple[str, int, int], ...]

    def apply(self, data: bytes) -> bytes:
        """The seed's bytes with the mutations applied in turn."""
        out = bytearray(data)
        for kind, position, argument in self.mutations:
            if kind == "length":
                fields = _length_fields(bytes(out))
                if fields:
                    at = fields[position % len(fields)]
                    out[at : at + 8] = struct.pack("<Q", argument % 2**64)
                continue
            at = position % max(1, len(out))
            if kind == "truncate":
                del out[at:]
            elif kind == "flip" and out:
                out[at] ^= 1 << (argument % 8)
            elif kind == "u32" and len(out) >= 4:
                at = min(at, len(out) - 4)
                out[at : at + 4] = struct.pack("<I", argument % 2**32)
            elif kind == "insert":
                out[at:at] = bytes([argument % 256]) * (1 + argument % 7)
            elif kind == "delete":
                del out[at : at + 1 + argument % 64]
        return bytes(out)


_ODD_LENGTHS = [0, 1, 8, 9, 2**31, 2**32 - 1, 2**32, 2**63 - 1, 2**63, 2**64 - 1]
_recording_mutations = st.one_of(
    st.tuples(st.just("truncate"), st.integers(0, 2**24), st.just(0)),
    st.tuples(st.just("flip"), st.integers(0, 2**24), st.integers(0, 7)),
    st.tuples(st.just("length"), st.integers(0, 2**10), st.sampled_from(_ODD_LENGTHS) | st.integers(0, 2**64 - 1)),
    st.tuples(st.just("u32"), st.integers(0, 2**24), st.sampled_from([0, 1, 2**31, 2**32 - 1]) | st.integers(0, 2**32 - 1)),
    st.tuples(st.just("insert"), st.integers(0, 2**24), st.integers(0, 255)),
    st.tuples(st.just("delete"), st.integers(0, 2**24), st.integers(0, 63)),
)


def mutated_recordings(seeds: Sequence[str]) -> st.SearchStrategy[MutatedRecording]:
    """Mutations of the recordings named ``seeds``: truncation, bit flips, record lengths replaced
    by odd values (0, 2**63, one past the data, ...), other fields overwritten, bytes inserted or
    deleted; one to three of them."""
    return st.builds(MutatedRecording, st.sampled_from(list(seeds)), st.lists(_recording_mutations, min_size=1, max_size=3).map(tuple))


def read_recording(path: str | os.PathLike[str]) -> int:
    """Read all of a recording as a user would: its summary (as JSON), its messages, its records,
    then replay it (payloads decoded), each strictly and with ``recover``; returns the messages
    read. Raises :class:`RecordingError` (and only that) for a file it cannot read."""
    count = 0
    for recover in (False, True):
        try:
            with Recording(path, recover=recover) as recording:
                json.dumps(recording.info.to_dict(), allow_nan=False)
                count += sum(1 for _ in recording.messages())
                count += sum(1 for _ in recording.records())
        except RecordingError:
            pass
        try:
            with Player(path, rate=math.inf, recover=recover) as player:
                count += player.play(lambda msg, record: None)
        except RecordingError:
            pass
    return count


def check_recording(path: str | os.PathLike[str], timeout_s: float = 60.0) -> None:
    """:func:`read_recording` of ``path`` raises nothing but RecordingError, and ends within
    ``timeout_s`` (it runs on a thread of its own, left behind if it hangs)."""
    outcome: list[BaseException | None] = []

    def read() -> None:
        try:
            read_recording(path)
        except BaseException as exc:  # handed to the caller's thread, which re-raises it
            outcome.append(exc)
        else:
            outcome.append(None)

    thread = threading.Thread(target=read, name="dyknow-fuzz-read", daemon=True)
    thread.start()
    thread.join(timeout_s)
    assert not thread.is_alive(), f"reading {os.fspath(path)} did not end within {timeout_s} s"
    if outcome[0] is not None:
        raise outcome[0]


def mcap_property(seeds: Mapping[str, Path], workdir: str | os.PathLike[str] | None = None, timeout_s: float = 60.0) -> Property:
    """The ``mcap`` target: the ``seeds`` (name -> path) mutated, written to ``workdir`` (a
    temporary folder by default) and read with :func:`check_recording`."""
    contents = {name: Path(path).read_bytes() for name, path in seeds.items()}
    folder = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="dyknow-fuzz-"))

    def check(example: MutatedRecording) -> None:
        path = folder / f"mutated-{threading.get_ident()}.mcap"
        path.write_bytes(example.apply(contents[example.seed]))
        try:
            check_recording(path, timeout_s)
        finally:
            path.unlink(missing_ok=True)

    return Property("mcap", mutated_recordings(sorted(contents)), check)
