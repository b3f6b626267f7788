"""The service protocol: how other processes call a manager and its units' proxies over Zenoh.

Services are Zenoh queryables; requests and replies are JSON objects.

Keys (built by :mod:`dyknow.keys`; ``@dyknow`` is a verbatim chunk, so data subscriptions like
``**`` never match services):

- ``@dyknow/<manager>/<service>`` for the manager's services: ``add_transformation``
  ``{"xml": "...", "path": "name used in errors"}``, ``remove_transformation`` ``{"label"}``,
  ``spawn`` ``{"label", "name", "protected", "params", "bindings"}``, ``destroy`` ``{"name"}``,
  ``get_model`` ``{}``; ``request`` ``{"tag", "standby", "require", "holder"}`` -> ``{"key", "kept"}``
  (``standby``: optional, one of :data:`~dyknow.model.STANDBY_MODES`; ``holder``: the client
  that holds it, see :mod:`dyknow.holders`); ``release`` ``{"key", "holder", "force"}`` ->
  ``{"released", "references"}`` (the references that remain; a caller gives back only what it
  took, and ``force``, an admin's on a manager with roles, every reference); ``monitor``
  ``{"formula", "reorder_ms", "holder", "bindings", "robustness"}`` -> ``{"key", "kept"}``;
  ``measure`` ``{"name", "value"}``; ``get_adaptations`` ``{}``; ``get_load`` ``{}`` (its lanes and
  overload state: :meth:`~dyknow.manager.Manager.load`); ``get_summary`` ``{}`` (for
  the other managers: see :mod:`dyknow.federation`; ``{"brief": true}`` counts only, for a
  listing; ``{"health": true}`` those and the managers it lost and its degraded requests:
  :mod:`dyknow.presence`); ``get_metrics`` ``{}`` (every unit's
  figures at once: :mod:`dyknow.metrics`, ``dyknow top``); a ``spawn`` may name the ``owner``, the
  manager whose request it serves (its units go when that manager does);
- ``@dyknow/<manager>/unit/<unit>/<service>`` for a unit's proxy: ``get_config`` ``{}``,
  ``set_config`` ``{"bindings": {port: key}}``, ``get_statistics`` ``{}``.

Every request is checked before a handler sees it (:func:`check_request`): its size and JSON
depth, then each field against :data:`SCHEMAS` (unknown fields, wrong types, over-long names and
keys are refused, naming the field). A refused request is answered with a Zenoh error reply ``{"error": "<DyKnowError subclass>",
"message": "...", "issues": [...]}``; :func:`raise_remote` turns it back into the same exception
class on the caller's side.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from dyknow import errors, keys
from dyknow.access import AccessControl
from dyknow.errors import AccessError, DyKnowError, PlanningError, ServiceError, SpecError, SpecIssue
from dyknow.holders import HOLDER
from dyknow.model import standby_problem
from dyknow.reasoning.syntax import MAX_FORMULA_CHARS
from dyknow.security import Limits
from dyknow.transport import ServiceChannel, ServiceRequest

if TYPE_CHECKING:  # (cryptography's x509 is imported only where calls are signed or checked)
    from dyknow.identity import Caller, Verifier

__all__ = [
    "MANAGER_SERVICES",
    "READ_ONLY_SERVICES",
    "SCHEMAS",
    "UNIT_SERVICES",
    "Handler",
    "Workers",
    "check_request",
    "decode_request",
    "dispatcher",
    "raise_remote",
]

log = logging.getLogger(__name__)

MANAGER_SERVICES = (
    "add_transformation",
    "remove_transformation",
    "spawn",
    "destroy",
    "get_model",
    "request",
    "release",
    "measure",
    "monitor",
    "get_adaptations",
    "get_summary",
    "get_load",
    "get_metrics",
)
UNIT_SERVICES = ("get_config", "set_config", "get_statistics")
#: Services that change nothing: they have threads of their own, so they never wait behind a spawn.
_STUCK_S = 0.05  # writers all inside their calls this long while a change waits: add one
READ_ONLY_SERVICES = frozenset({"get_model", "get_adaptations", "get_summary", "get_load", "get_metrics", "get_config", "get_statistics"})

Handler = Callable[[dict[str, Any], "Caller | None"], Any]
"""A service's handler: the checked request and its caller (None when the manager has no roles)."""


def _error_reply(exc: DyKnowError) -> bytes:
    return json.dumps(exc.to_dict()).encode()


# ---------------------------------------------------------------------- what a request may hold
#
# Every field of every service, its type and its bounds: a request is checked against this before
# any handler sees it, and refused naming the field. Names and keys are bounded well below what a
# Zenoh batch holds (a key declared over about 65 kB made Zenoh's transport panic).

Check = Callable[[Any, str, Limits], Any]


def _refuse(field: str, got: Any, expected: str) -> ServiceError:
    shown = repr(got) if len(repr(got)) <= 80 else f"a {type(got).__name__} of {len(repr(got))} characters"
    return ServiceError(f"got {shown}", where=f"field {field!r}", expected=expected)


def _text(max_bytes: int | None = None) -> Check:
    def check(value: Any, field: str, limits: Limits) -> str:
        bound = max_bytes or limits.max_request_bytes
        if not isinstance(value, str):
            raise _refuse(field, value, "text")
        if len(value.encode()) > bound:
            raise _refuse(field, value, f"at most {bound} bytes of text")
        return value

    return check


def _name(what: str) -> Check:
    """A unit or manager name: the same UnitError the manager raises locally (the client
    rebuilds it), so a caller sees one error for one mistake, here or over Zenoh."""

    def check(value: Any, field: str, limits: Limits) -> str:
        if not isinstance(value, str) or len(value.encode()) > limits.max_name_bytes:
            raise _refuse(field, value, f"a name of at most {limits.max_name_bytes} bytes")
        return keys.check_name(value, what)

    return check


def _label(value: Any, field: str, limits: Limits) -> str:
    """A transformation label (:func:`~dyknow.keys.label_problem`)."""
    problem = keys.label_problem(value)
    if problem is not None:
        raise ServiceError(problem[0], where=f"field {field!r}", expected=problem[1])
    return str(value)


def _key(value: Any, field: str, limits: Limits) -> str:
    if not isinstance(value, str) or not value or len(value.encode()) > limits.max_key_bytes:
        raise _refuse(field, value, f"a key expression of at most {limits.max_key_bytes} bytes")
    return value


def _flag(value: Any, field: str, limits: Limits) -> bool:
    if not isinstance(value, bool):
        raise _refuse(field, value, "true or false")
    return value


def _scalar(value: Any, field: str, limits: Limits) -> Any:
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, int | float):
        if isinstance(value, float) and not math.isfinite(value):
            raise _refuse(field, value, "a finite number, text or true/false")
        return value
    return _text(4096)(value, field, limits)


def _number_or_text(value: Any, field: str, limits: Limits) -> Any:
    if isinstance(value, int | float) and not isinstance(value, bool) and value == value and abs(value) != float("inf"):
        return value
    if isinstance(value, str) and len(value.encode()) <= 256:
        return value
    raise _refuse(field, value, "a finite number, or text of at most 256 bytes")


def _holder(value: Any, field: str, limits: Limits) -> str:
    """The id of the client that holds a request (:mod:`dyknow.holders`)."""
    if not isinstance(value, str) or not HOLDER.fullmatch(value):
        raise _refuse(field, value, "a client id: 8 to 32 hexadecimal digits")
    return value


def _standby(value: Any, field: str, limits: Limits) -> str:
    """A request's standby mode (in the same words as :func:`~dyknow.model.check_standby`)."""
    problem = standby_problem(value)
    if problem is not None:
        got, expected = problem
        raise ServiceError(got, where=f"field {field!r}", expected=expected)
    return str(value)


def _page(value: Any, field: str, limits: Limits) -> dict[str, int]:
    """Where a ``get_model`` page starts: ``{"units": i, "specs": j}`` (either may be left out)."""
    if not isinstance(value, dict) or not set(value) <= {"units", "specs"}:
        raise _refuse(field, value, 'an object such as {"units": 0, "specs": 120}, the "next" of the previous page')
    for kind, offset in value.items():
        if isinstance(offset, bool) or not isinstance(offset, int) or not 0 <= offset <= 1 << 31:
            raise _refuse(f"{field}.{kind}", offset, "a whole number from 0")
    return {str(k): int(v) for k, v in value.items()}


def _milliseconds(value: Any, field: str, limits: Limits) -> float:
    """A delay in milliseconds: a number from 0 to an hour."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value <= 3_600_000:
        raise _refuse(field, value, "a number of milliseconds from 0 to 3,600,000")
    return float(value)


def _formulas(value: Any, field: str, limits: Limits) -> list[str]:
    """A request's requirements: at most 16 formulas."""
    if not isinstance(value, list) or len(value) > 16:
        raise _refuse(field, value, "a list of at most 16 formulas")
    for v in value:
        if not isinstance(v, str) or len(v.encode()) > _FORMULA_BYTES:
            raise _refuse(field, v, f"formulas, each text of at most {_FORMULA_BYTES} bytes")
    return list(value)


def _mapping(key_check: Check, value_check: Check, max_items: int = 256) -> Check:
    def check(value: Any, field: str, limits: Limits) -> dict[str, Any]:
        if not isinstance(value, dict) or len(value) > max_items:
            raise _refuse(field, value, f"an object of at most {max_items} entries")
        return {key_check(k, f"{field}.{k}", limits): value_check(v, f"{field}.{k}", limits) for k, v in value.items()}

    return check


_PORT = _text(128)
_FORMULA_BYTES = 4 * MAX_FORMULA_CHARS  # UTF-8 bytes of the longest formula the parser takes
SCHEMAS: Mapping[str, Mapping[str, tuple[bool, Check]]] = {
    "add_transformation": {"xml": (True, _text()), "path": (False, _text(256))},
    "remove_transformation": {"label": (True, _label)},
    "spawn": {
        "label": (True, _label),
        "name": (True, _name("unit name")),
        "protected": (False, _flag),
        "params": (False, _mapping(_text(128), _scalar)),
        "bindings": (False, _mapping(_PORT, _key)),
        "owner": (False, _name("manager name")),
    },
    "destroy": {"name": (True, _name("unit name")), "force": (False, _flag)},
    "get_model": {"page": (False, _page)},
    "request": {"tag": (True, _text(512)), "standby": (False, _standby), "require": (False, _formulas), "holder": (False, _holder)},
    "monitor": {
        "formula": (True, _text(_FORMULA_BYTES)),
        "reorder_ms": (False, _milliseconds),
        "holder": (False, _holder),
        "bindings": (False, _mapping(_text(512), _key, max_items=64)),
        "robustness": (False, _flag),
    },
    "release": {"key": (True, _key), "holder": (False, _holder), "force": (False, _flag)},
    "measure": {"name": (True, _name("measurement name")), "value": (True, _number_or_text)},
    "get_adaptations": {},
    "get_summary": {"brief": (False, _flag), "health": (False, _flag)},
    "get_load": {},
    "get_metrics": {},
    "get_config": {},
    "set_config": {"bindings": (True, _mapping(_PORT, _key))},
    "get_statistics": {},
}
"""Every service's fields: ``{field: (required, check)}``. Unknown fields are refused."""


def check_request(service: str, request: Any, limits: Limits) -> dict[str, Any]:
    """``request`` with every field checked against the service's schema; :class:`ServiceError`
    naming the first field that is missing, unknown, of the wrong type or too large."""
    if not isinstance(request, dict):
        raise ServiceError(f"the request is a JSON {type(request).__name__}", expected="a JSON object")
    schema = SCHEMAS[service]
    unknown = [name for name in request if name not in schema]
    if unknown:
        fields = ", ".join(schema) or "none"
        raise ServiceError(f"unknown field {str(unknown[0])[:80]!r}", where=f"service {service!r}", expected=f"the fields {fields}")
    checked: dict[str, Any] = {}
    for name, (required, check) in schema.items():
        if name in request:
            checked[name] = check(request[name], name, limits)
        elif required:
            raise ServiceError(f"missing field {name!r}", where=f"service {service!r}", expected=f"the fields {', '.join(schema)}")
    return checked


def _depth(value: Any, limit: int) -> bool:
    """Whether ``value`` nests no deeper than ``limit`` (walked without recursion)."""
    todo = [(value, 1)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, dict | list):
            if depth > limit:
                return False
            todo.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return True


def decode_request(payload: bytes, limits: Limits) -> Any:
    """The JSON of a request, bounded in size and depth before and while it is parsed."""
    if len(payload) > limits.max_request_bytes:
        raise ServiceError(
            f"the request has {len(payload):,} bytes",
            where="request",
            expected=f"at most {limits.max_request_bytes:,} (--max-request-bytes)",
        )
    try:
        request = json.loads(payload) if payload else {}
    except RecursionError:
        raise ServiceError(
            "the request's JSON nests too deep", where="request", expected=f"at most {limits.max_json_depth} levels"
        ) from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ServiceError(f"the request is not JSON: {str(exc)[:120]}", where="request", expected="a JSON object") from None
    if not _depth(request, limits.max_json_depth):
        raise ServiceError("the request's JSON nests too deep", where="request", expected=f"at most {limits.max_json_depth} levels")
    return request


def dispatcher(
    manager: str,
    manager_handlers: Mapping[str, Handler],
    unit_handler: Callable[[str, str, dict[str, Any], Caller | None], Any],
    limits: Limits | None = None,
    *,
    verifier: Verifier | None = None,
    access: AccessControl | None = None,
) -> Callable[[str, bytes, bytes | None], tuple[bool, bytes]]:
    """A queryable handler for ``@dyknow/<manager>/**`` that checks each request, then routes it.

    With a ``verifier`` and the ``access`` roles, every call must be signed by its caller
    (:mod:`dyknow.identity`) and the caller's role must allow the service, or it is refused
    before its request is even read; handlers get the :class:`~dyknow.identity.Caller`.
    """
    known = ", ".join([*manager_handlers, *(f"unit/<name>/{s}" for s in UNIT_SERVICES)])
    bounds = limits or Limits()

    def handle(key: str, payload: bytes, attachment: bytes | None = None) -> tuple[bool, bytes]:
        try:
            if len(key.encode()) > bounds.max_key_bytes:
                raise ServiceError(f"a key of {len(key.encode())} bytes", where="key", expected=f"at most {bounds.max_key_bytes}")
            if len(payload) > bounds.max_request_bytes:
                decode_request(payload, bounds)  # refuses it, naming the bound
            address = keys.parse_service_key(manager, key)
            caller: Caller | None = None
            if verifier is not None and access is not None:
                if address is None:
                    raise ServiceError(f"no service at {key[:200]!r} on manager {manager!r}", expected=f"one of {known}")
                service, unit = address.service, address.unit is not None
                # the role is checked before anything of the call is remembered (dyknow.identity)
                caller = verifier.verify(key, payload, attachment, allowed=lambda c: _authorize(manager, access, c, service, unit))
            if address is not None and address.unit is None and address.service in manager_handlers:
                result = manager_handlers[address.service](check_request(address.service, decode_request(payload, bounds), bounds), caller)
            elif address is not None and address.unit is not None and address.service in UNIT_SERVICES:
                request = check_request(address.service, decode_request(payload, bounds), bounds)
                result = unit_handler(address.unit, address.service, request, caller)
            else:
                raise ServiceError(f"no service at {key[:200]!r} on manager {manager!r}", expected=f"one of {known}")
            return True, json.dumps(result).encode()
        except DyKnowError as exc:
            return False, _error_reply(exc)
        except (KeyError, TypeError, ValueError) as exc:  # a handler's own check of a field
            return False, _error_reply(ServiceError(f"bad request: {type(exc).__name__}: {exc}", where=key[:200]))

    return handle


def _authorize(manager: str, access: AccessControl, caller: Caller, service: str, unit: bool) -> None:
    if access.may_call(caller.common_name, service, unit=unit):
        return
    who = f"{caller.common_name!r} ({caller.role})" if caller.role else f"{caller.common_name!r}, which has no role here,"
    roles = access.roles_for_call(service, unit=unit)
    raise AccessError(
        f"{who} may not call {service}",
        where=f"manager {manager!r}",
        expected=f"a caller whose certificate has the role {' or '.join(roles) or 'none'} in this manager's --acl",
    )


class Workers:
    """The threads that answer a manager's service calls, so that calls do not wait on each other.

    ``readers`` threads take calls straight from the :class:`~dyknow.transport.ServiceChannel`:
    read-only services (:data:`READ_ONLY_SERVICES`) are answered there and then, everything else
    goes to ``writers`` threads. So a model query never queues behind a spawn whose unit takes a
    second to set up, and spawns of different units set up side by side (the manager keeps the
    calls on one unit in order): when every writer has been inside one call for 50 ms while a
    change waits, another writer starts, up to ``max_writers``. At most ``max_backlog`` changes wait for a writer; beyond that
    the readers wait too, and the channel's queue holds the calls back on their links.
    A context manager; :meth:`close` undeclares the channel and stops the threads.
    """

    def __init__(
        self,
        manager: str,
        channel: ServiceChannel,
        handler: Callable[[str, bytes, bytes | None], tuple[bool, bytes]],
        *,
        readers: int = 2,
        writers: int = 2,
        max_writers: int = 8,
        max_backlog: int = 1024,
    ) -> None:
        self.manager = manager
        self._channel = channel
        self._handler = handler
        self._changes: queue.Queue[ServiceRequest | None] = queue.Queue(max_backlog)
        self._readers = [threading.Thread(target=self._read, name=f"dyknow-{manager}-reader-{i}", daemon=True) for i in range(readers)]
        self._writers: list[threading.Thread] = []
        self._busy_since: list[float] = []  # per writer: when its current call began (0: idle)
        self._max_writers = max(writers, max_writers)
        self._lock = threading.Lock()
        self._checking = False  # a check of the writers is scheduled
        self._closed = False
        for thread in self._readers:
            thread.start()
        for _ in range(writers):
            self._add_writer()

    def _add_writer(self) -> None:
        with self._lock:
            index = len(self._writers)
            self._busy_since.append(0.0)
            thread = threading.Thread(target=self._write, args=(index,), name=f"dyknow-{self.manager}-writer-{index}", daemon=True)
            self._writers.append(thread)
        thread.start()

    def _check_writers(self) -> None:
        """A change waits and every writer is busy: in 50 ms, if they all are still inside their
        calls (a unit's slow setup(), say) and a change still waits, add a writer (up to
        ``max_writers``). Calls that merely take CPU end sooner and add none."""
        with self._lock:
            if self._checking or len(self._writers) >= self._max_writers or not all(self._busy_since):
                return
            self._checking = True

        def check() -> None:
            now = time.monotonic()
            stuck = all(b and now - b >= _STUCK_S for b in self._busy_since)
            with self._lock:
                self._checking = False
            if stuck and not self._changes.empty() and not self._closed:
                self._add_writer()
                self._check_writers()  # the next change may be waiting too

        timer = threading.Timer(_STUCK_S, check)
        timer.daemon = True
        timer.start()

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _answer(self, request: ServiceRequest) -> None:
        try:
            ok, reply = self._handler(request.key, request.payload, request.attachment)
        except Exception as exc:  # a bug in a handler must still answer the caller
            log.exception("service handler for %s failed", request.key[:200])
            ok, reply = False, json.dumps({"error": type(exc).__name__, "message": str(exc)}).encode()
        request.reply(ok, reply)

    def _read(self) -> None:
        while (request := self._channel.receive()) is not None:
            address = keys.parse_service_key(self.manager, request.key)
            if address is not None and address.service in READ_ONLY_SERVICES:
                self._answer(request)
            else:
                self._changes.put(request)
                self._check_writers()

    def _write(self, index: int) -> None:
        while (request := self._changes.get()) is not None:
            self._busy_since[index] = time.monotonic()
            try:
                self._answer(request)
            finally:
                self._busy_since[index] = 0.0

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop receiving, let the threads finish the calls in hand (waits up to ``timeout_s``); safe twice."""
        if self._closed:
            return
        self._closed = True
        self._channel.undeclare()
        for _ in self._writers:
            with contextlib.suppress(queue.Full):
                self._changes.put(None, timeout=timeout_s / 4)
        threads = [*self._readers, *self._writers]
        for thread in threads:
            if thread is not threading.current_thread():
                thread.join(timeout_s / len(threads))


def raise_remote(exc: ServiceError) -> DyKnowError:
    """The exception a manager raised, rebuilt on the caller's side (same class, message and fields)."""
    kind = exc.kind
    cls = getattr(errors, kind, None) if kind else None
    details = exc.details
    if cls is SpecError:
        issues = []
        with contextlib.suppress(KeyError, TypeError, ValueError):
            raw = details.get("issues", [])
            issues = [SpecIssue.from_dict(i) for i in (raw if isinstance(raw, list) else [])]
        return SpecError(issues or [SpecIssue("<remote>", 0, str(exc))])
    if kind == "PlanningError":
        return PlanningError(str(details.get("request", "")), None, str(exc))
    if isinstance(cls, type) and issubclass(cls, DyKnowError) and cls not in (DyKnowError, SpecError, ServiceError, PlanningError):
        what, where, expected = details.get("what"), details.get("where"), details.get("expected")
        if isinstance(what, str):
            return cls(what, where=where if isinstance(where, str) else None, expected=expected if isinstance(expected, str) else None)
        return cls(str(exc))
    return exc
