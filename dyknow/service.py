"""The service protocol: how other processes call a manager and its units' proxies over Zenoh.

Services are Zenoh queryables; requests and replies are JSON objects.

Keys (built by :mod:`dyknow.keys`; ``@dyknow`` is a verbatim chunk, so data subscriptions like
``**`` never match services):

- ``@dyknow/<manager>/<service>`` for the manager's services: ``add_transformation``
  ``{"xml": "...", "path": "name used in errors"}``, ``remove_transformation`` ``{"label"}``,
  ``spawn`` ``{"label", "name", "protected", "params", "bindings"}``, ``destroy`` ``{"name"}``,
  ``get_model`` ``{}``; ``request`` ``{"tag"}`` -> ``{"key"}``; ``release`` ``{"key"}``;
  ``measure`` ``{"name", "value"}``; ``get_adaptations`` ``{}``;
- ``@dyknow/<manager>/unit/<unit>/<service>`` for a unit's proxy: ``get_config`` ``{}``,
  ``set_config`` ``{"bindings": {port: key}}``, ``get_statistics`` ``{}``.

A refused request is answered with a Zenoh error reply ``{"error": "<DyKnowError subclass>",
"message": "...", "issues": [...]}``; :func:`raise_remote` turns it back into the same exception
class on the caller's side.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable, Mapping
from typing import Any

from dyknow import errors, keys
from dyknow.errors import DyKnowError, PlanningError, ServiceError, SpecError, SpecIssue

__all__ = [
    "MANAGER_SERVICES",
    "UNIT_SERVICES",
    "Handler",
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
    "get_adaptations",
)
UNIT_SERVICES = ("get_config", "set_config", "get_statistics")

Handler = Callable[[dict[str, Any]], Any]


def _error_reply(exc: DyKnowError) -> bytes:
    return json.dumps(exc.to_dict()).encode()


def dispatcher(
    manager: str,
    manager_handlers: Mapping[str, Handler],
    unit_handler: Callable[[str, str, dict[str, Any]], Any],
) -> Callable[[str, bytes], tuple[bool, bytes]]:
    """A queryable handler for ``@dyknow/<manager>/**`` that routes to the given handlers."""
    known = ", ".join([*manager_handlers, *(f"unit/<name>/{s}" for s in UNIT_SERVICES)])

    def handle(key: str, payload: bytes) -> tuple[bool, bytes]:
        try:
            try:
                request = json.loads(payload) if payload else {}
            except ValueError as exc:
                raise ServiceError(f"the request is not JSON: {exc}", where=key, expected="a JSON object") from exc
            if not isinstance(request, dict):
                raise ServiceError(f"the request is a JSON {type(request).__name__}", where=key, expected="a JSON object")
            address = keys.parse_service_key(manager, key)
            if address is not None and address.unit is None and address.service in manager_handlers:
                result = manager_handlers[address.service](request)
            elif address is not None and address.unit is not None and address.service in UNIT_SERVICES:
                result = unit_handler(address.unit, address.service, request)
            else:
                raise ServiceError(f"no service at {key!r} on manager {manager!r}", expected=f"one of {known}")
            return True, json.dumps(result).encode()
        except DyKnowError as exc:
            return False, _error_reply(exc)
        except (KeyError, TypeError, ValueError) as exc:
            # a request with missing or mistyped fields
            return False, _error_reply(ServiceError(f"bad request: {type(exc).__name__}: {exc}", where=key))

    return handle


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
