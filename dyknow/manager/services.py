"""The manager's Zenoh services: each call decoded, its caller's role checked, the manager called.

:class:`Services` declares the queryables of :mod:`dyknow.service` for one manager and answers
them through the manager's public interface (:class:`Served`). What a request may hold is checked
before a handler sees it (:func:`dyknow.service.check_request`); what only some roles may do (force
a destroy or a release: admins) is checked here, with the references a caller takes held for its
client (:mod:`dyknow.holders`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from dyknow import clocks, keys, service
from dyknow.access import AccessControl
from dyknow.adaptation import AdaptationEvent
from dyknow.errors import AccessError, BindingError, DyKnowError
from dyknow.federation import Summary
from dyknow.holders import Holders, check_holder
from dyknow.identity import Caller, Verifier
from dyknow.manager.peers import Peers
from dyknow.metrics import Metrics
from dyknow.model import LOCAL, Model, Owner, UnitInfo
from dyknow.proxy import UnitStatistics
from dyknow.security import Limits
from dyknow.transport import Session

__all__ = ["Served", "Services"]

log = logging.getLogger("dyknow.manager")  # one name for the manager, whichever part logs


class Served(Protocol):
    """What the services call of the manager: its public interface (:class:`~dyknow.manager.Manager` provides it)."""

    @property
    def name(self) -> str:
        """The manager's name."""
        ...

    @property
    def limits(self) -> Limits:
        """What one request may cost."""
        ...

    @property
    def metrics(self) -> Metrics:
        """The manager's figures for operators."""
        ...

    def add_transformation(self, spec: str, *, path: str | None = None, remote: bool = False) -> list[str]:
        """Store a spec (XML text, from a remote caller); returns the labels added."""
        ...

    def remove_transformation(self, label: str) -> bool:
        """Forget a spec; returns whether there was one."""
        ...

    def spawn(
        self,
        label: str,
        name: str,
        *,
        protected: bool = False,
        params: Mapping[str, Any] | None = None,
        bindings: Mapping[str, str] | None = None,
        remote: bool = False,
        owner: Owner = LOCAL,
    ) -> UnitInfo:
        """Start a unit (a formula monitor's nodes count against ``owner``'s share)."""
        ...

    def destroy(self, name: str, *, force: bool = False) -> None:
        """Stop a unit."""
        ...

    def unit_info(self, name: str) -> UnitInfo | None:
        """A running unit (None when it does not run)."""
        ...

    def get_model(self) -> Model:
        """The running units and the stored specs."""
        ...

    def request(self, tag: str, *, standby: str | None = None, require: Sequence[str] = (), owner: Owner = LOCAL) -> str:
        """Provide a stream of ``tag``; returns its key."""
        ...

    def release(self, key: str, *, owner: Owner = LOCAL, force: bool = False) -> int:
        """Give back a request or a monitor; returns the references that remain."""
        ...

    def monitor(
        self, formula: str, *, reorder_ms: float = 0.0, owner: Owner = LOCAL, bindings: Mapping[str, str] | None = None, robustness: bool = False
    ) -> str:
        """Monitor a temporal formula; returns the key of its verdicts."""
        ...

    def measure(self, name: str, value: float | str) -> None:
        """Record the latest value of a measure."""
        ...

    def get_adaptations(self) -> list[AdaptationEvent]:
        """Every adaptation so far."""
        ...

    def summary(self) -> Summary:
        """What the manager offers the others."""
        ...

    def load(self) -> dict[str, Any]:
        """How the manager keeps up."""
        ...

    def get_config(self, name: str) -> dict[str, str]:
        """Port -> key bindings of a unit."""
        ...

    def set_config(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """Rebind ports of a unit."""
        ...

    def get_statistics(self, name: str) -> UnitStatistics:
        """A unit's statistics."""
        ...

    def changed(self) -> None:
        """The manager's model changed (the other managers hear of it)."""
        ...


class Services:
    """The Zenoh services of ``manager``, declared on ``session`` (closed by :meth:`close`).

    ``peers``: the manager among the others (the units a ``spawn`` runs for another manager's
    request, a listing's brief summary); ``holders``: the clients holding references (None: the
    manager keeps none for them); ``verifier`` and ``access``: the caller's certificate and roles,
    when the manager has roles.
    """

    def __init__(
        self,
        manager: Served,
        *,
        session: Session,
        peers: Peers,
        holders: Holders | None,
        verifier: Verifier | None,
        access: AccessControl | None,
    ) -> None:
        self._manager = manager
        self._peers = peers
        self._holders = holders
        name = manager.name
        self._workers = service.Workers(
            name,
            # clock exchanges are answered on Zenoh's thread, where their times are taken
            session.declare_service_channel(keys.services_pattern(name), at_once={keys.clock_key(name): clocks.answer}),
            service.dispatcher(name, self._handlers(), self._unit_service, manager.limits, verifier=verifier, access=access),
        )

    def close(self, timeout_s: float) -> None:
        """Undeclare the services and stop their threads."""
        self._workers.close(timeout_s)

    def _handlers(self) -> dict[str, service.Handler]:
        manager = self._manager
        return {
            "add_transformation": lambda r, c: {"labels": manager.add_transformation(r["xml"], path=r.get("path") or "<remote>", remote=True)},
            "remove_transformation": lambda r, c: {"removed": manager.remove_transformation(str(r["label"]))},
            "spawn": self._serve_spawn,
            "destroy": self._serve_destroy,
            "get_model": self._serve_model,
            "request": self._serve_request,
            "release": self._serve_release,
            "monitor": self._serve_monitor,
            "measure": self._serve_measure,
            "get_adaptations": lambda r, c: [e.to_dict() for e in manager.get_adaptations()],
            "get_summary": lambda r, c: self._peers.brief(bool(r.get("health"))) if r.get("brief") or r.get("health") else manager.summary().to_dict(),
            "get_load": lambda r, c: manager.load(),
            "get_metrics": lambda r, c: manager.metrics.snapshot(),
        }

    def _serve_model(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        page = request.get("page", {})
        return self._manager.get_model().page(page.get("units", 0), page.get("specs", 0), max_bytes=self._manager.limits.max_reply_bytes)

    def _serve_spawn(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        owner = request.get("owner")
        log.info("spawn %s for %s", request.get("name"), owner)
        if owner:
            self._peers.follow(str(owner))  # its loss (or goodbye) is this one's concern now
        info = self._manager.spawn(
            request["label"],
            request["name"],
            protected=bool(request.get("protected", False)),
            params=request.get("params") or {},
            bindings=request.get("bindings") or {},
            remote=True,
            owner=_owner(caller, None),
        )
        if owner:
            self._peers.serves(info.name, owner)
            self._manager.changed()
        return info.to_dict()

    def _serve_destroy(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        force = bool(request.get("force", False))
        unit = self._manager.unit_info(str(request["name"]))
        if force and caller is not None and caller.role != "admin" and unit is not None and unit.protected:
            role = f"the role {caller.role}" if caller.role else "no role"
            raise AccessError(
                f"{caller.common_name!r}, with {role}, may not destroy a protected unit",
                where=f"unit {request['name']!r} on manager {self._manager.name!r}",
                expected="an admin (force: true is for admins), or destroy without force",
            )
        self._manager.destroy(str(request["name"]), force=force)
        return {"destroyed": request["name"]}

    def _serve_release(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        key = str(request["key"])
        holder = request.get("holder")  # (checked with the request: dyknow.service)
        force = bool(request.get("force", False))
        if force and caller is not None and caller.role != "admin":
            role = f"the role {caller.role}" if caller.role else "no role"
            raise AccessError(
                f"{caller.common_name!r}, with {role}, may not force a release",
                where=f"{key!r} on manager {self._manager.name!r}",
                expected="an admin (force: true is for admins), or a release of what the caller requested",
            )
        remaining = self._manager.release(key, owner=_owner(caller, holder), force=force)
        if holder is not None and self._holders is not None and remaining > 0:
            self._holders.gave_back(key, holder)
        return {"released": key, "references": remaining}

    def _serve_request(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        holder = self._holder(request, caller)
        owner = _owner(caller, holder)
        key = self._manager.request(str(request["tag"]), standby=request.get("standby"), require=request.get("require", ()), owner=owner)
        self._held(key, holder, owner)
        return {"key": key, "kept": holder is None}

    def _serve_monitor(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        holder = self._holder(request, caller)
        owner = _owner(caller, holder)
        key = self._manager.monitor(
            str(request["formula"]), reorder_ms=float(request.get("reorder_ms", 0.0)), owner=owner, bindings=request.get("bindings") or None,
            robustness=request.get("robustness") is True,
        )  # fmt: skip
        self._held(key, holder, owner)
        return {"key": key, "kept": holder is None}

    def _holder(self, request: dict[str, Any], caller: Caller | None) -> str | None:
        """The client a reference is taken for (checked with the request: dyknow.service), once it
        is known to be the caller's own (a signed caller's ids start with its scope:
        :func:`dyknow.holders.check_holder`), before anything is taken."""
        holder = request.get("holder")
        if holder is not None and caller is not None:
            check_holder(str(holder), caller.common_name, f"field 'holder' on manager {self._manager.name!r}")
        return None if holder is None else str(holder)

    def _held(self, key: str, holder: str | None, owner: Owner) -> None:
        """The reference ``owner`` took on ``key`` is held for its client ``holder``; if it cannot
        be, it is given back and the error raised."""
        if holder is not None and self._holders is not None:
            try:
                self._holders.took(key, holder, owner.caller)
            except DyKnowError:
                self._manager.release(key, owner=owner)
                raise

    def _serve_measure(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        self._manager.measure(str(request["name"]), request["value"])
        return {"measured": request["name"]}

    def _unit_service(self, name: str, what: str, request: dict[str, Any], caller: Caller | None) -> Any:
        if what == "get_config":
            return self._manager.get_config(name)
        if what == "set_config":
            bindings = request.get("bindings")
            if not isinstance(bindings, dict):
                raise BindingError(f"set_config got {bindings!r}", where=f"unit {name!r}", expected='{"bindings": {port: key}}')
            return self._manager.set_config(name, bindings)
        return self._manager.get_statistics(name).to_dict()


def _owner(caller: Caller | None, holder: str | None) -> Owner:
    """Who a service call takes a reference for: its caller's name (with roles) and its client."""
    return Owner(caller.common_name if caller is not None else None, holder)
