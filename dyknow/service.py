"""The service protocol: how other processes call a manager and its units' proxies over Zenoh.

Services are Zenoh queryables; requests and replies are JSON objects.

Keys (``@dyknow`` is a verbatim chunk, so data subscriptions like ``**`` never match services):

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

from dyknow import errors
from dyknow.errors import DyKnowError, PlanningError, ServiceError, SpecError, SpecIssue

__all__ = [
    "MANAGER_SERVICES",
    "ROOT",
    "UNIT_SERVICES",
    "Handler",
    "dispatcher",
    "manager_key",
    "raise_remote",
    "unit_key",
]

log = logging.getLogger(__name__)

ROOT = "@dyknow"
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


def manager_key(manager: str, service: str) -> str:
    return f"{ROOT}/{manager}/{service}"


def unit_key(manager: str, unit: str, service: str) -> str:
    return f"{ROOT}/{manager}/unit/{unit}/{service}"


def _error_reply(exc: DyKnowError) -> bytes:
    return json.dumps(exc.to_dict()).encode()


def dispatcher(
    manager: str,
    manager_handlers: Mapping[str, Handler],
    unit_handler: Callable[[str, str, dict[str, Any]], Any],
) -> Callable[[str, bytes], tuple[bool, bytes]]:
    """A queryable handler for ``@dyknow/<manager>/**`` that routes to the given handlers."""
    prefix = f"{ROOT}/{manager}/"

    def handle(key: str, payload: bytes) -> tuple[bool, bytes]:
        try:
            if not key.startswith(prefix):
                raise ServiceError(f"no service at {key!r}")
            path = key[len(prefix) :].split("/")
            try:
                request = json.loads(payload) if payload else {}
            except ValueError as exc:
                raise ServiceError(f"request to {key!r} is not JSON: {exc}; expected a JSON object") from exc
            if not isinstance(request, dict):
                raise ServiceError(f"request to {key!r}: got {type(request).__name__}; expected a JSON object")
            if len(path) == 1 and path[0] in manager_handlers:
                result = manager_handlers[path[0]](request)
            elif len(path) == 3 and path[0] == "unit" and path[2] in UNIT_SERVICES:
                result = unit_handler(path[1], path[2], request)
            else:
                known = ", ".join([*manager_handlers, *(f"unit/<name>/{s}" for s in UNIT_SERVICES)])
                raise ServiceError(f"no service {'/'.join(path)!r} on manager {manager!r}; expected one of {known}")
            return True, json.dumps(result).encode()
        except DyKnowError as exc:
            return False, _error_reply(exc)
        except (KeyError, TypeError, ValueError) as exc:
            # a request with missing or mistyped fields
            return False, _error_reply(ServiceError(f"bad request to {key!r}: {type(exc).__name__}: {exc}"))

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
