"""The exceptions dyknow raises.

Every error dyknow raises on purpose derives from :class:`DyKnowError`, with one base per family::

    DyKnowError
    ├── SpecError          a transformation specification is malformed (located issues)
    ├── LibraryError       a label is unknown to the library, or a library operation is refused
    ├── UnitError          a unit cannot be spawned, destroyed or found
    ├── BindingError       a port binding (port -> key expression) is invalid
    ├── TransportError     Zenoh failed (session, endpoint, publish); wraps the Zenoh error
    ├── ServiceError       a remote service call failed (no manager, timeout, refused request)
    ├── ClosedError        an object was used after close()
    ├── OntologyError      an ontology cannot be loaded, or a class name is unknown or ambiguous
    ├── TagError           a tag is not a well-formed term such as ``BallPosition(field)``
    ├── PlanningError      no configuration provides a requested tag (with the explanation)
    ├── RecordingError     an MCAP recording cannot be written or read (file, offset, what is wrong)
    ├── AccessError        refused by the manager's security policy: a source that is not allowed,
    │                      a file outside the data roots, a request over a limit
    └── FormulaError       a temporal formula does not parse (its column), or it is used with
                           streams or times it cannot take (a term without samples, time going back)

Every error carries fields as well as its message, so that the CLI, the services and a user
interface can show them without parsing prose: ``what`` (the problem), ``where`` (what it
concerns: a file and line, a manager, a unit, a port, a key; None when nothing in particular) and
``expected`` (what would have been accepted, with a hint such as close matches; None when there is
nothing to say). ``str(error)`` is ``"WHERE: WHAT; expected EXPECTED"`` with the missing parts left
out, and :meth:`DyKnowError.to_dict` gives the fields as JSON (the services send it, and the client
raises the same class with the same fields). :class:`SpecIssue` has the same fields for one problem
of a spec file.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

__all__ = [
    "AccessError",
    "BindingError",
    "ClosedError",
    "DyKnowError",
    "FormulaError",
    "LibraryError",
    "OntologyError",
    "PayloadError",
    "PlanningError",
    "RecordingError",
    "ServiceError",
    "SpecError",
    "SpecIssue",
    "TagError",
    "TransportError",
    "UnitError",
    "compose",
    "did_you_mean",
]


def compose(what: str, where: str | None = None, expected: str | None = None) -> str:
    """The one-line message of an error: ``"WHERE: WHAT; expected EXPECTED"``, parts left out when None.

    >>> compose("unknown port 'ot'", "unit 'r1'", "one of 'in', 'out' (did you mean 'out'?)")
    "unit 'r1': unknown port 'ot'; expected one of 'in', 'out' (did you mean 'out'?)"
    """
    text = f"{where}: {what}" if where else what
    return f"{text}; expected {expected}" if expected else text


class DyKnowError(Exception):
    """Root of every error dyknow raises on purpose.

    ``what`` is the problem, ``where`` what it concerns and ``expected`` what would have been
    accepted (see the module documentation); the message is built from them.
    """

    def __init__(self, what: str, *, where: str | None = None, expected: str | None = None) -> None:
        self.what = what
        self.where = where
        self.expected = expected
        super().__init__(compose(what, where, expected))

    def to_dict(self) -> dict[str, Any]:
        """The error as JSON: its class name, message and fields (what the services reply)."""
        return {"error": type(self).__name__, "message": str(self), "what": self.what, "where": self.where, "expected": self.expected}


@dataclass(frozen=True, slots=True)
class SpecIssue:
    """One problem found in a specification file, located.

    ``element`` names the part of the spec it concerns, such as ``<port> @type`` (empty for the
    file as a whole); ``what`` is the problem and ``expected`` what would be accepted (may be
    empty). ``str(issue)`` is ``PATH:LINE: ELEMENT: WHAT; expected EXPECTED``.
    """

    path: str
    line: int
    what: str
    element: str = ""
    expected: str = ""

    @property
    def where(self) -> str:
        """``path:line``, or the path alone for a problem with the file as a whole (line 0)."""
        return f"{self.path}:{self.line}" if self.line > 0 else self.path

    @property
    def message(self) -> str:
        """The problem without its location: ``ELEMENT: WHAT; expected EXPECTED``."""
        return compose(self.what, self.element or None, self.expected or None)

    def __str__(self) -> str:
        return f"{self.where}: {self.message}"

    def to_dict(self) -> dict[str, Any]:
        """The issue as JSON (what the services send for a refused spec)."""
        return {
            "path": self.path,
            "line": self.line,
            "element": self.element,
            "what": self.what,
            "expected": self.expected,
            "message": self.message,
        }

    @classmethod
    def from_dict(cls, data: Any) -> SpecIssue:
        """The issue back from :meth:`to_dict` (``KeyError``, ``TypeError`` or ``ValueError`` when malformed)."""
        return cls(str(data["path"]), int(data["line"]), str(data["what"]), str(data.get("element", "")), str(data.get("expected", "")))


class SpecError(DyKnowError):
    """A transformation specification is malformed.

    ``issues`` holds every problem found in the input (not only the first); ``str(error)`` is one
    ``PATH:LINE: message`` line per issue.
    """

    def __init__(self, issues: Iterable[SpecIssue]) -> None:
        self.issues: tuple[SpecIssue, ...] = tuple(issues)
        first = self.issues[0] if self.issues else SpecIssue("<spec>", 0, "invalid spec")
        more = f" (and {len(self.issues) - 1} more problems)" if len(self.issues) > 1 else ""
        # the fields summarise the first issue; the message lists them all, one per line
        self.what, self.where, self.expected = first.message + more, first.where, None
        Exception.__init__(self, "\n".join(str(i) for i in self.issues))

    def to_dict(self) -> dict[str, Any]:
        """The JSON form, with every issue."""
        return {**DyKnowError.to_dict(self), "issues": [i.to_dict() for i in self.issues]}


class LibraryError(DyKnowError):
    """A transformation label is unknown, or a library operation is refused."""


class UnitError(DyKnowError):
    """A unit cannot be spawned, destroyed or found, or its source is not a unit."""


class BindingError(DyKnowError):
    """A port binding is invalid: unknown port, or a key expression Zenoh does not accept."""


class TransportError(DyKnowError):
    """Zenoh failed: a session could not open, an endpoint is in use, a publish failed."""


class ServiceError(DyKnowError):
    """A remote service call failed: no manager answered, it timed out, or it was refused.

    ``kind`` is the name of the error class raised on the manager's side when the manager refused
    the request (for example ``"UnitError"``), or ``None`` when no manager answered; ``details``
    is the manager's whole error reply.
    """

    def __init__(
        self,
        what: str,
        kind: str | None = None,
        details: dict[str, object] | None = None,
        *,
        where: str | None = None,
        expected: str | None = None,
    ) -> None:
        self.kind = kind
        self.details = details or {}
        super().__init__(what, where=where, expected=expected)


class ClosedError(DyKnowError):
    """An object was used after ``close()``."""


def did_you_mean(name: str, candidates: Iterable[str]) -> str:
    """A hint naming the closest candidates to ``name``, or an empty string.

    >>> did_you_mean("rawcamera", ["raw-camera", "undist"])
    " (did you mean 'raw-camera'?)"
    """
    import difflib

    close = difflib.get_close_matches(name, list(candidates), n=3, cutoff=0.6)
    if not close:
        return ""
    return " (did you mean " + " or ".join(repr(c) for c in close) + "?)"


class OntologyError(DyKnowError):
    """An ontology cannot be loaded (missing file or import, syntax error), or a class name is
    unknown or ambiguous."""


class TagError(DyKnowError):
    """A tag is not a well-formed term: ``Functor`` or ``Functor(arg, ...)``."""


class PlanningError(DyKnowError):
    """No configuration provides the requested tag.

    ``rejection`` (a :class:`dyknow.planner.Rejection`, or None when the request itself is bad)
    names the unmet tag and, for each alternative tried, why it was rejected.
    """

    def __init__(self, request: str, rejection: Any = None, message: str | None = None) -> None:
        self.request = request
        self.rejection = rejection
        if message is None:
            message = f"cannot plan {request}:\n" + "\n".join(rejection.lines(1)) if rejection is not None else f"cannot plan {request}"
        super().__init__(message)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form, with the request and the explanation of each rejected alternative."""
        return {
            **super().to_dict(),
            "request": self.request,
            "rejection": self.rejection.to_dict() if self.rejection is not None else None,
        }


class RecordingError(DyKnowError):
    """An MCAP recording cannot be written (unwritable path, full disk) or read (not MCAP,
    truncated, corrupt). The message names the file and, for a damaged file, the offset."""


class AccessError(DyKnowError):
    """Refused by the manager's security policy: a unit source outside the allow-list, a file
    outside the data roots, or a request over a limit. ``where`` names the field or param."""


class PayloadError(DyKnowError, TypeError):
    """A payload cannot be published or decoded."""


class FormulaError(DyKnowError):
    """A temporal formula (:mod:`dyknow.reasoning`) is malformed, or is used with data it cannot take.

    For a parse error ``where`` is ``formula column N`` (1-based) and ``column`` is N; ``formula``
    is the text. For misuse (streams missing a term, samples out of time order) ``where`` names
    the term or argument and ``column`` is None.
    """

    def __init__(
        self, what: str, *, where: str | None = None, expected: str | None = None, formula: str | None = None, column: int | None = None
    ) -> None:
        self.formula = formula
        self.column = column
        super().__init__(what, where=where, expected=expected)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form, with the formula and the column."""
        return {**super().to_dict(), "formula": self.formula, "column": self.column}
