"""Tag terms: what a port carries, written ``Functor`` or ``Functor(arg, ...)``.

A tag such as ``BallPosition(field)`` names a kind of stream (the functor) and the things it is
about (the args). Functor and args are *names*, written in one of three ways:

* a local name: ``BallPosition``, ``cam_1`` (``[A-Za-z_][A-Za-z0-9_.-]*``);
* a prefixed name: ``dk:BallPosition``, ``sosa:Sensor``, ``:Camera`` (a prefix a loaded ontology
  declares, then a local name);
* a full IRI in angle brackets: ``<http://www.w3.org/ns/sosa/Sensor>``.

Whitespace around names and commas is ignored, so ``BallPosition( field )`` is
``BallPosition(field)``. Args are plain names: nested terms such as ``F(G(x))`` are refused in this
version. What a functor means (and which tags satisfy which) is the business of
:mod:`dyknow.ontology`; this module only reads and writes the text.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

from dyknow.errors import TagError

__all__ = ["NAME", "Term", "local_name", "parse_term"]

_EXPECTED = "Functor or Functor(arg, ...)"
_LOCAL = r"[A-Za-z_][A-Za-z0-9_.\-]*"
_NAME = re.compile(rf"<[^<>\"{{}}|^`\\\s]+>|(?:{_LOCAL})?:{_LOCAL}|{_LOCAL}")
NAME: re.Pattern[str] = _NAME
"""A functor's or an arg's name, as a tag writes it (a local name, a prefixed name or an IRI in angle brackets)."""
_SPACE = re.compile(r"\s*")
_HINTS = {
    "$": " (a template variable ${...} left unexpanded?)",
    "<": " (an IRI in angle brackets must be non-empty, without spaces, quotes or braces)",
}


@dataclass(frozen=True, slots=True)
class Term:
    """A parsed tag: ``functor`` and ``args`` as written (whitespace stripped)."""

    functor: str
    args: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in (self.functor, *self.args):
            if not isinstance(name, str) or not _NAME.fullmatch(name):
                raise TagError(
                    f"term name {name!r} is not a name",
                    expected="a local name such as BallPosition, a prefixed name such as dk:BallPosition or a full IRI in angle brackets",
                )

    def __str__(self) -> str:
        if not self.args:
            return self.functor
        return f"{self.functor}({', '.join(self.args)})"


@functools.lru_cache(maxsize=65536)
def parse_term(text: str) -> Term:
    """Parse a tag such as ``BallPosition(field)``; raises :class:`TagError` saying what is wrong.

    Results are cached (terms are immutable), so matching the same tags again is cheap.
    """
    return _Reader(text).term()


@functools.lru_cache(maxsize=65536)
def local_name(name: str) -> str:
    """The local part of a name: ``Camera`` for ``<http://x/y#Camera>``, ``ex:Camera`` and ``Camera``.

    An IRI (in angle brackets, or bare with ``://``) gives its fragment, else its last non-empty
    path segment; a prefixed name gives what follows the prefix; a local name is returned as is.
    """
    name = name.strip()
    if name.startswith("<") and name.endswith(">"):
        return _iri_local_name(name[1:-1])
    if "://" in name:
        return _iri_local_name(name)
    return name.rpartition(":")[2] if ":" in name else name


def _iri_local_name(iri: str) -> str:
    base, _, fragment = iri.partition("#")
    if fragment:
        return fragment
    last = base.rstrip("/").rpartition("/")[2]
    return last.rpartition(":")[2] or last  # urn:x:Name has no '/'


class _Reader:
    """A one-pass reader over a tag's text that says where and why it is malformed."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.pos = 0

    def fail(self, problem: str, hint: str = "") -> TagError:
        return TagError(problem, where=f"tag {self.text!r}", expected=f"{_EXPECTED}{hint}")

    def skip_space(self) -> None:
        self.pos = _SPACE.match(self.text, self.pos).end()  # type: ignore[union-attr]  # \s* always matches

    def at_end(self) -> bool:
        return self.pos >= len(self.text)

    def name(self, what: str) -> str:
        match = _NAME.match(self.text, self.pos)
        if match is None:
            if self.at_end():
                raise self.fail(f"missing {what} at the end")
            char = self.text[self.pos]
            hint = _HINTS.get(char, "")
            raise self.fail(f"unexpected character {char!r} at column {self.pos + 1} where {what} should start", hint)
        self.pos = match.end()
        return match.group()

    def term(self) -> Term:
        if not self.text.strip():
            raise self.fail("empty tag")
        self.skip_space()
        functor = self.name("the functor")
        self.skip_space()
        if self.at_end():
            return Term(functor)
        if self.text[self.pos] != "(":
            raise self._trailing()
        self.pos += 1
        self.skip_space()
        if not self.at_end() and self.text[self.pos] == ")":
            raise self.fail("empty parentheses", f" (write {functor} for a tag without args)")
        args: list[str] = []
        while True:
            self.skip_space()
            if self.at_end():
                raise self.fail("unbalanced parenthesis", " ('(' is never closed)")
            if self.text[self.pos] in ",)":
                raise self.fail("empty arg", f" (arg {len(args) + 1} at column {self.pos + 1})")
            args.append(self.name(f"arg {len(args) + 1}"))
            self.skip_space()
            if self.at_end():
                raise self.fail("unbalanced parenthesis", " ('(' is never closed)")
            char = self.text[self.pos]
            self.pos += 1
            if char == ")":
                break
            if char == "(":
                raise self.fail("nested terms are not allowed", f" (arg {len(args)} is {args[-1]}(...))")
            if char != ",":
                raise self.fail(f"unexpected character {char!r} at column {self.pos} after arg {len(args)}")
        self.skip_space()
        if not self.at_end():
            raise self._trailing()
        return Term(functor, tuple(args))

    def _trailing(self) -> TagError:
        rest = self.text[self.pos :].strip()
        if rest.startswith(")"):
            return self.fail("unbalanced parenthesis", f" (')' at column {self.pos + 1} closes nothing)")
        return self.fail(f"unexpected text {rest!r} after the term at column {self.pos + 1}")
