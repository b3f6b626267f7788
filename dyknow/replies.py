"""What a client takes from a manager's replies: JSON within bounds, in the shape its readers expect.

A reply is another process's word: the manager's, a router's on the way or, without TLS, that of
anyone who answers on a manager's service key. So before anything reads it, :func:`decode_reply`
parses it no deeper than :data:`MAX_REPLY_DEPTH` levels (``NaN`` and ``Infinity``, which JSON does
not have, read as null, so that what ``--json`` prints stays JSON), and :func:`check_reply` checks
the fields that :class:`dyknow.Client` and the ``dyknow`` command read against the
service's shape in :data:`SHAPES`: their types, and names as the manager checks them
(``dyknow.keys.check_name``: a unit or manager name is a key chunk, so text that is not one,
a terminal escape say, names no unit of any manager). A reply that fails is refused whole, as a
:class:`dyknow.ServiceError` whose ``details["reason"]`` is ``"malformed"``, naming the
manager, the service, the field and what was expected. Fields nobody reads, and fields a newer
manager adds, pass as they came; free text (an error, a key, a host) is shown escaped by
whoever prints it (``dyknow.cli``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any

from dyknow import keys
from dyknow.errors import DyKnowError, ServiceError

__all__ = ["MALFORMED", "MAX_REPLY_DEPTH", "SHAPES", "Shape", "check_error", "check_reply", "decode_reply", "nesting"]

#: The deepest a reply's JSON may nest (a manager's replies nest a few levels: a model's specs, requests and clocks).
MAX_REPLY_DEPTH = 64
#: ``details["reason"]`` of a reply refused for its form.
MALFORMED = "malformed"


class _Wrong(Exception):
    """A field of a reply that is not as expected: where (``path``), what it is, what it should be."""

    def __init__(self, path: str, got: str, expected: str) -> None:
        super().__init__(path)
        self.path, self.got, self.expected = path, got, expected


#: A field's shape: checks ``value`` found at ``path``, raising :class:`_Wrong` when it does not fit.
Shape = Callable[[Any, str], None]


def _seen(value: Any) -> str:
    """A value as a message shows it: short text quoted (escaped by ``repr``), the rest described."""
    if isinstance(value, str):
        return repr(value) if len(value) <= 60 else f"text of {len(value)} characters"
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    if isinstance(value, int | float):
        return repr(value) if len(repr(value)) <= 40 else f"a number of {len(repr(value))} digits"
    return f"a JSON {'object' if isinstance(value, dict) else 'array'} of {len(value)} entries"


def _kind(test: Callable[[Any], bool], expected: str) -> Shape:
    def check(value: Any, path: str) -> None:
        if not test(value):
            raise _Wrong(path, _seen(value), expected)

    return check


def _whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and -(1 << 63) <= value < 1 << 63


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and abs(value) < 1e18  # (NaN and infinity are not)


TEXT = _kind(lambda v: isinstance(v, str), "text")
FLAG = _kind(lambda v: isinstance(v, bool), "true or false")
# (numbers are read into sums, rates and clock times: a bigger one would overflow them, or make
# what --json prints Infinity, which is not JSON)
WHOLE = _kind(_whole, "a whole number of at most 64 bits")
# (10**18: a latency in µs from a message stamped at time 0, 1.8 * 10**15 today, is a manager's honest figure)
NUMBER = _kind(_finite, "a number under 10**18")
TIME_NS = _kind(lambda v: _whole(v) and v >= 0, "a time in ns since 1970 (a whole number from 0 to 2**63)")
ANY: Shape = lambda value, path: None  # noqa: E731  (a field read as it is, or not at all)


def name(what: str) -> Shape:
    """A unit or manager name, as the manager checks it (:func:`~dyknow.keys.check_name`)."""

    def check(value: Any, path: str) -> None:
        try:
            keys.check_name(value, what)
        except DyKnowError as exc:
            raise _Wrong(path, f"{_seen(value)}, not a {what}", exc.expected or what) from None

    return check


def optional(shape: Shape) -> Shape:
    """``shape``, or null."""

    def check(value: Any, path: str) -> None:
        if value is not None:
            shape(value, path)

    return check


def listed(shape: Shape) -> Shape:
    """A JSON array whose entries each have ``shape``."""

    def check(value: Any, path: str) -> None:
        if not isinstance(value, list):
            raise _Wrong(path, _seen(value), "a JSON array")
        for i, entry in enumerate(value):
            shape(entry, f"{path}[{i}]")

    return check


def mapped(shape: Shape) -> Shape:
    """A JSON object whose values each have ``shape`` (its keys are any text)."""

    def check(value: Any, path: str) -> None:
        if not isinstance(value, dict):
            raise _Wrong(path, _seen(value), "a JSON object")
        for key, entry in value.items():
            shape(entry, f"{path}[{key[:60]!r}]")

    return check


def fields(required: Mapping[str, Shape], optional: Mapping[str, Shape] | None = None) -> Shape:
    """A JSON object with the ``required`` fields, and the ``optional`` ones when present, of
    their shapes (other fields pass unchecked)."""

    def check(value: Any, path: str) -> None:
        if not isinstance(value, dict):
            raise _Wrong(path, _seen(value), f"a JSON object with the fields {', '.join(required)}" if required else "a JSON object")
        for field, shape in required.items():
            if field not in value:
                raise _Wrong(f"{path}.{field}", "missing", f"the fields {', '.join(required)}")
            shape(value[field], f"{path}.{field}")
        for field, shape in (optional or {}).items():
            if field in value:
                shape(value[field], f"{path}.{field}")

    return check


_UNIT_NAME = name("unit name")
_MANAGER_NAME = name("manager name")
_PERCENTILES = fields({"count": WHOLE, "p50_us": NUMBER, "p99_us": NUMBER})
_PORT_FIGURES = fields(
    {"direction": TEXT, "key": TEXT, "messages": WHOLE, "bytes": WHOLE, "dropped": WHOLE},
    {"unsized": WHOLE, "queued": WHOLE, "lost": WHOLE, "shed": WHOLE},
)
_INPUT_FIGURES = fields({"latency": _PERCENTILES, "hop": _PERCENTILES})


def _port(value: Any, path: str) -> None:
    """A port's figures: an input's with its latency and hop percentiles."""
    _PORT_FIGURES(value, path)
    if value["direction"] == "in":
        _INPUT_FIGURES(value, path)


_UNIT = fields(
    {"name": _UNIT_NAME, "label": TEXT, "state": TEXT, "protected": FLAG, "bindings": mapped(TEXT)},
    {"error": optional(TEXT), "traceback": optional(TEXT)},
)
_LOST = listed(fields({"manager": _MANAGER_NAME, "since_ns": TIME_NS, "why": TEXT}))
_MODEL = fields(
    {"manager": _MANAGER_NAME, "units": listed(_UNIT), "specs": listed(fields({"label": TEXT}))},
    {
        "requests": listed(fields({"tag": TEXT, "key": TEXT, "state": TEXT})),
        "lost": _LOST,
        "clocks": mapped(ANY),
        "next": optional(fields({"units": WHOLE, "specs": WHOLE})),
    },
)
_METRICS = fields(
    {
        "manager": _MANAGER_NAME,
        "time_ns": TIME_NS,
        "cpu_s": NUMBER,
        "threads": WHOLE,
        "adaptations": mapped(WHOLE),
        "units": listed(
            fields(
                {"name": _UNIT_NAME, "label": TEXT, "state": TEXT, "callback_avg_us": NUMBER, "ports": mapped(_port)},
                {"error": optional(TEXT)},
            )
        ),
    },
    {"requests": listed(fields({"tag": TEXT, "key": TEXT, "state": TEXT}, {"reason": optional(TEXT)})), "lost": _LOST},
)
_STATISTICS = fields(
    {"name": _UNIT_NAME, "label": TEXT, "state": TEXT, "uptime_s": NUMBER, "reconfigurations": WHOLE, "executor": TEXT,
     "ports": mapped(_port)},
    {"error": optional(TEXT), "traceback": optional(TEXT)},
)  # fmt: skip
_LANE = fields(
    {"name": TEXT, "kind": TEXT, "units": WHOLE, "busy": NUMBER, "lag_ms": NUMBER, "queued": WHOLE, "stuck_ms": NUMBER, "names": listed(TEXT)}
)
_LOAD = fields(
    {
        "threads": WHOLE,
        "max_lanes": WHOLE,
        "lanes": listed(_LANE),
        "overload": fields(
            {"state": TEXT, "lag_ms": NUMBER, "lag_budget_ms": NUMBER, "units_shed": WHOLE,
             "shed": listed(fields({"priority": ANY, "rate": NUMBER}))}
        ),
    },
    {"nice": optional(WHOLE)},
)  # fmt: skip
_ADAPTATION = fields(
    {"id": ANY, "kind": TEXT, "request": TEXT, "cause": TEXT, "old": listed(TEXT), "new": listed(TEXT),
     "adaptation_ms": optional(NUMBER), "recovery_ms": optional(NUMBER)},
)  # fmt: skip
_KEY = fields({"key": TEXT})

#: The replies that name the manager that gives them (``"manager"``): it must be the one asked.
_SELF_NAMED = frozenset({"get_model", "get_metrics"})

SHAPES: Mapping[str, Shape] = {
    "get_model": _MODEL,
    "get_metrics": _METRICS,
    "get_statistics": _STATISTICS,
    "get_load": _LOAD,
    "get_adaptations": listed(_ADAPTATION),
    "spawn": _UNIT,
    "get_config": mapped(TEXT),
    "set_config": mapped(TEXT),
    "add_transformation": fields({"labels": listed(TEXT)}),
    "remove_transformation": fields({"removed": FLAG}),
    "request": _KEY,
    "monitor": _KEY,
    "release": fields({}, {"references": WHOLE}),
    "get_summary": fields({}, {"lost": _LOST, "degraded": listed(fields({"tag": TEXT, "key": TEXT}, {"reason": optional(TEXT)}))}),
}
"""The shape of each service's reply, as far as the client and the ``dyknow`` command read it."""


def nesting(value: Any, limit: int = MAX_REPLY_DEPTH) -> bool:
    """Whether ``value`` nests no deeper than ``limit`` levels (walked without recursion)."""
    todo = [(value, 1)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, dict | list):
            if depth > limit:
                return False
            todo.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return True


def _refused(manager: str, service: str, what: str, expected: str) -> ServiceError:
    return ServiceError(
        what,
        where=f"the reply of manager {manager!r} to {service}",
        expected=f"{expected} (a dyknow manager's reply: is another program answering on its service key? "
        "without TLS any peer can; dyknow doctor)",
        details={"reason": MALFORMED, "manager": manager, "call": service},
    )


def _null(constant: str) -> None:
    """``NaN``, ``Infinity`` and ``-Infinity``, which are not JSON, read as null."""
    return None


def decode_reply(data: bytes, manager: str, service: str) -> Any:
    """The JSON of ``manager``'s reply to ``service``, parsed within :data:`MAX_REPLY_DEPTH` levels;
    :class:`ServiceError` (reason ``"malformed"``) when it is not JSON or nests deeper."""
    try:
        reply = json.loads(data, parse_constant=_null)
    except RecursionError:
        reply, deep = None, True
    except (ValueError, UnicodeDecodeError) as exc:
        raise _refused(manager, service, f"it is not JSON ({len(data):,} bytes: {str(exc)[:80]})", "a JSON reply") from None
    else:
        deep = not nesting(reply)
    if deep:
        raise _refused(
            manager, service, f"it nests deeper than {MAX_REPLY_DEPTH} levels", f"at most {MAX_REPLY_DEPTH} levels (MAX_REPLY_DEPTH)"
        )
    return reply


def check_reply(reply: Any, manager: str, service: str) -> Any:
    """``reply`` when it has the shape :data:`SHAPES` gives ``service`` (any, for a service not
    there); else :class:`ServiceError` (reason ``"malformed"``) naming the first field that does not."""
    shape = SHAPES.get(service)
    if shape is None:
        return reply
    try:
        shape(reply, "reply")
    except _Wrong as wrong:
        raise _refused(manager, service, f"{wrong.path} is {wrong.got}", wrong.expected) from None
    said = reply.get("manager", manager) if service in _SELF_NAMED else manager
    if said != manager:  # (one that answers as another would show that one's units as its own)
        raise _refused(manager, service, f"reply.manager is {said!r}, another manager's name", f"its own name, {manager!r}")
    return reply


def check_error(details: Mapping[str, Any], manager: str, service: str) -> None:
    """Refuse an error reply (its JSON fields, ``details``) that nests deeper than
    :data:`MAX_REPLY_DEPTH` levels, as :func:`decode_reply` refuses a reply."""
    if not nesting(dict(details)):
        raise _refused(
            manager, service, f"its error nests deeper than {MAX_REPLY_DEPTH} levels", f"at most {MAX_REPLY_DEPTH} levels (MAX_REPLY_DEPTH)"
        )
