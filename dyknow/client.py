"""The client: calls a manager's services from another process over Zenoh.

Every method mirrors the manager's, takes JSON-friendly arguments and returns the manager's JSON
reply (plain dicts and lists). A refused request raises the same exception class the manager
raised (``UnitError``, ``BindingError``, ``SpecError``, ...); a manager that does not answer raises
:class:`~dyknow.errors.ServiceError`.

Usage::

    with Client("robot", connect=["tcp/127.0.0.1:7447"]) as client:
        client.spawn("relay", "relay1")
        print(client.get_model()["units"])
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dyknow import service
from dyknow.errors import ServiceError, SpecError, SpecIssue
from dyknow.message import Message
from dyknow.transport import DEFAULT_ENDPOINT, Session, Subscriber, check_key_expr, make_config

__all__ = ["Client"]


class Client:
    """A connection to one manager's services. A context manager; ``close()`` is safe twice."""

    def __init__(
        self,
        manager: str,
        *,
        connect: Sequence[str] = (DEFAULT_ENDPOINT,),
        zenoh_config: str | os.PathLike[str] | None = None,
        timeout: float = 5.0,
        session: Session | None = None,
    ) -> None:
        self.manager = manager
        self.timeout = timeout
        self._own_session = session is None
        self._connect = list(connect)
        self._session = session or Session(make_config(connect=self._connect, config_file=zenoh_config))

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._own_session:
            self._session.close()

    @property
    def session(self) -> Session:
        return self._session

    # ------------------------------------------------------------------ calls

    def _call(self, key: str, request: Mapping[str, Any], what: str) -> Any:
        where = f"manager {self.manager!r}" + (f" at {', '.join(self._connect)}" if self._connect else "")
        try:
            reply = self._session.call(key, json.dumps(request).encode(), timeout=self.timeout, what=f"{what} of {where}")
        except ServiceError as exc:
            if exc.kind is None and "nothing serves" in str(exc):
                raise ServiceError(
                    f"no answer from {where} within {self.timeout:g} s; is it running "
                    f"(dyknow manager --name {self.manager})?"
                ) from exc
            raise service.raise_remote(exc) from None
        return json.loads(reply)

    def add_transformation(self, xml_or_path: str | os.PathLike[str]) -> list[str]:
        """Send a spec (XML text, or a file's path) to the manager; returns the labels added."""
        text = str(xml_or_path)
        path = "<client>"
        if isinstance(xml_or_path, os.PathLike) or not text.lstrip().startswith("<"):
            file = Path(text)
            try:
                text = file.read_text(encoding="utf-8")
            except OSError as exc:
                raise SpecError([SpecIssue(str(file), 0, f"cannot read: {exc.strerror or exc}")]) from exc
            path = str(file)
        return list(self._call(service.manager_key(self.manager, "add_transformation"), {"xml": text, "path": path}, "add_transformation")["labels"])

    def remove_transformation(self, label: str) -> bool:
        return bool(self._call(service.manager_key(self.manager, "remove_transformation"), {"label": label}, "remove_transformation")["removed"])

    def spawn(
        self,
        label: str,
        name: str,
        *,
        protected: bool = False,
        params: Mapping[str, Any] | None = None,
        bindings: Mapping[str, str] | None = None,
    ) -> dict[str, Any]:
        request = {"label": label, "name": name, "protected": protected, "params": dict(params or {}), "bindings": dict(bindings or {})}
        return dict(self._call(service.manager_key(self.manager, "spawn"), request, "spawn"))

    def destroy(self, name: str) -> None:
        self._call(service.manager_key(self.manager, "destroy"), {"name": name}, "destroy")

    def get_model(self) -> dict[str, Any]:
        return dict(self._call(service.manager_key(self.manager, "get_model"), {}, "get_model"))

    def get_config(self, name: str) -> dict[str, str]:
        return dict(self._call(service.unit_key(self.manager, name, "get_config"), {}, "get_config"))

    def set_config(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        return dict(self._call(service.unit_key(self.manager, name, "set_config"), {"bindings": dict(bindings)}, "set_config"))

    def get_statistics(self, name: str) -> dict[str, Any]:
        return dict(self._call(service.unit_key(self.manager, name, "get_statistics"), {}, "get_statistics"))

    def request(self, tag: str) -> str:
        """Ask the manager for a stream of ``tag``; returns its key (PlanningError when nothing fits)."""
        return str(self._call(service.manager_key(self.manager, "request"), {"tag": tag}, "request")["key"])

    def release(self, key: str) -> None:
        self._call(service.manager_key(self.manager, "release"), {"key": key}, "release")

    def measure(self, name: str, value: float | str) -> None:
        """Record a measurement on the manager (constraints are checked against it)."""
        self._call(service.manager_key(self.manager, "measure"), {"name": name, "value": value}, "measure")

    def get_adaptations(self) -> list[dict[str, Any]]:
        return list(self._call(service.manager_key(self.manager, "get_adaptations"), {}, "get_adaptations"))

    # ------------------------------------------------------------------ streams

    def subscribe(self, key_expr: str, callback: Callable[[Message], None]) -> Subscriber:
        """Receive the messages published on ``key_expr`` (wildcards allowed) by other sessions."""
        check_key_expr(key_expr, what="subscription")
        return self._session.declare_subscriber(key_expr, callback)
