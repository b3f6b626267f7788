"""The XML tree a spec is read from: each element with the line of its start tag; DTDs refused.

:func:`parse_xml` parses with expat and refuses any ``<!DOCTYPE>`` before anything in it is
expanded or fetched (external entities and entity-expansion bombs cannot be written in a spec);
malformed XML is a :class:`~dyknow.errors.SpecError` located at the element still open.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NoReturn
from xml.parsers import expat

from dyknow.errors import SpecError, SpecIssue

__all__ = ["DTD_PROBLEM", "Element", "parse_xml"]

#: What a spec with a DTD is told.
DTD_PROBLEM = (
    "DTDs and entity declarations are not allowed in transformation specs (they enable "
    "external entities and entity-expansion bombs); remove the <!DOCTYPE ...> block"
)


@dataclass(slots=True)
class Element:
    """An element of the parsed document, with the line of its start tag."""

    name: str
    attrs: dict[str, str]
    line: int
    children: list[Element] = field(default_factory=list)
    chunks: list[str] = field(default_factory=list)

    @property
    def text(self) -> str:
        """The text directly inside the element, stripped."""
        return "".join(self.chunks).strip()


class _Refused(Exception):
    """Stops expat at a DTD, before anything in it is expanded."""

    def __init__(self, line: int) -> None:
        super().__init__(line)
        self.line = line


def parse_xml(data: str | bytes, path: str) -> Element:
    """The root element of the document; :class:`SpecError` when malformed or when it has a DTD."""
    parser = expat.ParserCreate()  # no namespace processing: names stay as written ("xsi:...")
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    stack: list[Element] = []
    roots: list[Element] = []

    def start(name: str, attrs: dict[str, str]) -> None:
        node = Element(name, attrs, parser.CurrentLineNumber)
        (stack[-1].children if stack else roots).append(node)
        stack.append(node)

    def end(name: str) -> None:
        stack.pop()

    def characters(text: str) -> None:
        if stack:
            stack[-1].chunks.append(text)

    def refuse(*_: object) -> NoReturn:
        raise _Refused(parser.CurrentLineNumber)

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = characters
    # "<!DOCTYPE" fires before any declaration inside it is processed, so nothing is ever
    # expanded or fetched; the other handlers are a second line of defence.
    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.UnparsedEntityDeclHandler = refuse
    parser.ExternalEntityRefHandler = refuse
    try:
        parser.Parse(data, True)  # pyexpat parses a str as UTF-8, bytes by their XML declaration
    except _Refused as exc:
        raise SpecError([SpecIssue(path, exc.line, DTD_PROBLEM, "<!DOCTYPE>")]) from None
    except expat.ExpatError as exc:
        what = f"malformed XML: {expat.ErrorString(exc.code)} at column {exc.offset + 1}"
        expected = "well-formed XML"
        if stack:  # the mistake is usually in the element still open, not where the parser stopped
            open_ = stack[-1]
            what += f", inside <{open_.name}> opened at line {open_.line}"
            expected = f"</{open_.name}> closing it, complete"
            if exc.code == expat.errors.codes[expat.errors.XML_ERROR_TAG_MISMATCH]:
                what = f"malformed XML: a closing tag that does not match at column {exc.offset + 1}"
                expected = f"</{open_.name}> closing the <{open_.name}> opened at line {open_.line}"
        raise SpecError([SpecIssue(path, exc.lineno, what, expected=expected)]) from None
    except (LookupError, ValueError, Warning) as exc:
        # An XML declaration naming an encoding Python lacks (LookupError), cannot use for XML
        # (ValueError), or warns about while decoding: unicode_escape's DeprecationWarning, an
        # exception where warnings are errors (python -W error, pytest's filterwarnings).
        what = f"the XML declaration names an encoding that cannot be read: {exc}"
        raise SpecError([SpecIssue(path, 1, what, "<?xml?>", expected='encoding="UTF-8" (or ISO-8859-1, or none)')]) from None
    return roots[0]
