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
    └── RecordingError     an MCAP recording cannot be written or read (file, offset, what is wrong)

Messages say what came in, what was expected, and what to do about it.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

__all__ = [
    "BindingError",
    "ClosedError",
    "DyKnowError",
    "LibraryError",
    "OntologyError",
    "PlanningError",
    "RecordingError",
    "ServiceError",
    "SpecError",
    "SpecIssue",
    "TagError",
    "TransportError",
    "UnitError",
    "did_you_mean",
]


class DyKnowError(Exception):
    """Root of every error dyknow raises on purpose."""


@dataclass(frozen=True, slots=True)
class SpecIssue:
    """One problem found in a specification file, with its location."""

    path: str
    line: int
    message: str

    def __str__(self) -> str:
        if self.line <= 0:  # a problem with the file as a whole (missing, unreadable)
            return f"{self.path}: {self.message}"
        return f"{self.path}:{self.line}: {self.message}"


class SpecError(DyKnowError):
    """A transformation specification is malformed.

    ``issues`` holds every problem found in the input (not only the first); ``str(error)`` is one
    ``PATH:LINE: message`` line per issue.
    """

    def __init__(self, issues: Iterable[SpecIssue]) -> None:
        self.issues: tuple[SpecIssue, ...] = tuple(issues)
        super().__init__("\n".join(str(i) for i in self.issues))


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

    def __init__(self, message: str, kind: str | None = None, details: dict[str, object] | None = None) -> None:
        self.kind = kind
        self.details = details or {}
        super().__init__(message)


class ClosedError(DyKnowError):
    """An object was used after ``close()``."""


def did_you_mean(name: str, candidates: Iterable[str]) -> str:
    """A hint naming the closest candidates to ``name``, or an empty string.

    >>> did_you_mean("rawcamera", ["raw-camera", "undist"])
    " (did you mean 'raw-camera'?)"
    """
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
        return {"request": self.request, "message": str(self), "rejection": self.rejection.to_dict() if self.rejection is not None else None}


class RecordingError(DyKnowError):
    """An MCAP recording cannot be written (unwritable path, full disk) or read (not MCAP,
    truncated, corrupt). The message names the file and, for a damaged file, the offset."""
