"""The model: what a manager runs and knows, as plain data (the DyKnow paper's ``get_model``).

:class:`Model` is a snapshot: the running units (:class:`UnitInfo`), the stored specs and the
active requests (:class:`RequestInfo`). :class:`UnitEvent` tells listeners that a unit was
spawned, failed or was destroyed. Every type has ``to_dict()``, the JSON form the services send.
The manager builds them; the adaptation loop, the CLI and clients read them.

:data:`STANDBY_MODES` is the one home of a request's standby modes (``"none"``, ``"warm"``), and
:func:`standby_problem` the one check of them (:func:`check_standby` raises it for the Python
API, the services refuse with the same words).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from dyknow.errors import UnitError, did_you_mean

if TYPE_CHECKING:
    from dyknow.spec import TransformationSpec

__all__ = ["LOCAL", "STANDBY_MODES", "Model", "Owner", "RequestInfo", "UnitEvent", "UnitInfo", "check_standby", "standby_problem"]

#: How a request stands by for faults: ``"none"`` (re-plan and spawn when the configuration
#: breaks) or ``"warm"`` (the next-best configuration runs beside it, and a fault only moves the
#: request's anchor onto it).
STANDBY_MODES = ("none", "warm")


@dataclass(frozen=True, slots=True)
class Owner:
    """Who took a reference to a request, or asked for a monitor.

    ``caller``: the common name of the caller's certificate, on a manager with roles (None
    without); ``holder``: the id of the :class:`~dyknow.client.Client` that holds it (None: kept
    until released, :mod:`dyknow.holders`); ``local``: the manager's own Python API (the
    operator, trusted). Only the owner may give a reference back, or an admin who forces it.
    """

    caller: str | None = None
    holder: str | None = None
    local: bool = False

    def holds(self, other: Owner) -> bool:
        """Whether a release by this owner may give back ``other``'s reference: the local API
        any; a caller of a manager with roles those taken under its certificate's name (its own
        client's first); without roles, a client its own, and a caller without a holder the
        references kept over the services."""
        if self.local:
            return True
        if other.local or other.caller != self.caller:
            return False
        if self.holder is not None:
            return other.holder == self.holder
        return self.caller is not None or other.holder is None

    def same_caller(self, other: Owner) -> bool:
        """Whether ``other`` was taken by the caller that this owner is, for the references one
        caller may hold (:attr:`~dyknow.security.Limits.max_references_per_caller`): on a manager
        with roles the same certificate's name, whichever its client; without roles the same
        client, or, with no client id, any other reference kept over the services. The local API
        is nobody's caller."""
        if self.local or other.local:
            return False
        if self.caller is not None:
            return other.caller == self.caller
        return other.caller is None and other.holder == self.holder

    def who(self) -> str:
        """The owner as a message names a caller: ``'alice' (client 3f2a...)``, ``'alice'``."""
        if self.local:
            return "the manager's own API"
        if self.caller is None:
            return f"client {self.holder}" if self.holder is not None else "a caller without a client id"
        return f"{self.caller!r} (client {self.holder})" if self.holder is not None else repr(self.caller)

    def account(self) -> str | None:
        """Whose share of what a manager bounds per caller this owner draws on (the formula
        nodes of its monitors, :class:`~dyknow.reasoning.unit.MonitorBudget`): None for the
        manager's own API; else the caller's certificate name (its calls are signed), else its
        client, else the one account of every caller that names no client."""
        if self.local:
            return None
        if self.caller is not None:
            return f"caller {self.caller!r}"
        if self.holder is not None:
            return f"client {self.holder}"
        return "callers without a client id"

    def __str__(self) -> str:
        """The owner as a message names a reference: kept ones say so."""
        return self.who() if self.local or self.holder is not None else f"{self.who()} (kept)"


#: The owner of what the manager's Python API asks for.
LOCAL = Owner(local=True)


def standby_problem(value: object) -> tuple[str, str] | None:
    """Why ``value`` is no standby mode, as ``(got, expected)``; None when it is one."""
    if isinstance(value, str) and value in STANDBY_MODES:
        return None
    shown = repr(value) if len(repr(value)) <= 80 else f"a {type(value).__name__} of {len(repr(value))} characters"
    hint = did_you_mean(value, STANDBY_MODES) if isinstance(value, str) else ""
    return f"got {shown}", "one of " + ", ".join(repr(m) for m in STANDBY_MODES) + hint


def check_standby(value: object) -> str:
    """The standby mode ``value`` names (None is ``"none"``); :class:`UnitError` naming the field
    ``standby`` and the allowed values for anything else."""
    if value is None:
        return "none"
    problem = standby_problem(value)
    if problem is not None:
        raise UnitError(problem[0], where="field 'standby'", expected=problem[1])
    assert isinstance(value, str)
    return value


@dataclass(frozen=True, slots=True)
class UnitEvent:
    """Something happened to a unit: ``kind`` is "spawned", "failed" or "destroyed"."""

    kind: str
    unit: str
    label: str
    time_ns: int
    error: str | None = None


@dataclass(frozen=True, slots=True)
class UnitInfo:
    """One running unit as the model shows it.

    ``spec`` is the transformation it was spawned from (it may since have left the library);
    ``started_ns`` tells two units spawned under the same name apart. Neither is in ``to_dict()``.
    """

    name: str
    label: str
    state: str
    protected: bool
    bindings: Mapping[str, str]
    executor: str
    error: str | None = None
    traceback: str | None = None
    spec: TransformationSpec | None = field(default=None, compare=False, repr=False)
    started_ns: int = 0

    @property
    def alive(self) -> bool:
        """Whether the unit is starting or running (not failed, not stopped)."""
        return self.state in ("starting", "running")

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (``get_model``'s ``units`` entries)."""
        return {
            "name": self.name,
            "label": self.label,
            "state": self.state,
            "protected": self.protected,
            "bindings": dict(self.bindings),
            "executor": self.executor,
            "error": self.error,
            "traceback": self.traceback,
        }


@dataclass(frozen=True, slots=True)
class RequestInfo:
    """A request as the model shows it: its tag, stable key, state and the units serving it.

    ``standby_mode`` is one of :data:`STANDBY_MODES`; for a ``"warm"`` request, ``standby`` and
    ``standby_labels`` are the units (and their transformations) of the configuration kept running
    beside the active one, empty while there is none (``standby_reason`` says why).
    """

    tag: str
    key: str
    state: str  # "active" or "degraded" (no configuration, a requirement false, or one not watched)
    references: int
    units: tuple[str, ...]
    labels: tuple[str, ...]
    standby_mode: str = "none"
    standby: tuple[str, ...] = ()
    standby_labels: tuple[str, ...] = ()
    standby_reason: str | None = None
    requirements: tuple[str, ...] = ()  # formulas the stream must satisfy (see Manager.request)
    #: the requirements of the transformations serving it (their specs'), watched while they do:
    #: ``{"formula", "transformation", "unit", "key"}`` (``key``: where their verdicts go)
    spec_requirements: tuple[Mapping[str, str], ...] = ()
    #: the clients holding it (client id -> references; :mod:`dyknow.holders`); the other
    #: references (``references`` minus these) are kept until released
    holders: Mapping[str, int] = field(default_factory=dict)
    #: the holders whose client the manager does not see now (its token is not there): their
    #: references are released after the manager's grace unless the client comes back
    absent: tuple[str, ...] = ()
    #: transformations a requirement found false, avoided until a trial in the shadow shows the
    #: requirements hold on them: ``{"transformation", "formula", "since_ns", "trial" ("waiting",
    #: "running" or "in place"), "failed_trials", "backoff_s", "next_trial_ns"}``
    suspects: tuple[Mapping[str, Any], ...] = ()
    #: the requirements of the transformations serving it that could not be watched (the
    #: monitors' nodes were taken, say): ``{"formula", "transformation", "unit", "why"}``; while
    #: any is, the request shows "degraded" (its stream is served unchecked) and the manager
    #: tries again every second
    unwatched: tuple[Mapping[str, str], ...] = ()
    #: why it is degraded (None while active): no configuration (a provider lost, say), a
    #: requirement false, or one not watched
    reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (``get_model``'s ``requests`` entries)."""
        return {
            "tag": self.tag,
            "key": self.key,
            "state": self.state,
            "references": self.references,
            "units": list(self.units),
            "labels": list(self.labels),
            "standby_mode": self.standby_mode,
            "standby": list(self.standby),
            "standby_labels": list(self.standby_labels),
            "standby_reason": self.standby_reason,
            "requirements": list(self.requirements),
            "spec_requirements": [dict(r) for r in self.spec_requirements],
            "holders": dict(self.holders),
            "absent": list(self.absent),
            "kept": self.references - sum(self.holders.values()),
            "suspects": [dict(s) for s in self.suspects],
            "unwatched": [dict(u) for u in self.unwatched],
            "reason": self.reason,
        }

    def brief(self) -> dict[str, Any]:
        """What a tool shows of it beside the figures: ``{"tag", "key", "state", "reason"}``."""
        return {"tag": self.tag, "key": self.key, "state": self.state, "reason": self.reason}


@dataclass(frozen=True, slots=True)
class Model:
    """The manager's model: the running units, the stored specs, the active requests."""

    manager: str
    units: tuple[UnitInfo, ...]
    specs: tuple[TransformationSpec, ...] = field(default=())
    requests: tuple[RequestInfo, ...] = field(default=())
    #: The other managers' clocks as this one estimates them: name -> ``Estimate.to_dict()``
    #: (offset, uncertainty, drift; see :mod:`dyknow.clocks`), and its own under ``"clock"``.
    clocks: Mapping[str, Any] = field(default_factory=dict)
    #: The formulas it monitors (``MonitorInfo.to_dict()``, :mod:`dyknow.reasoning.monitors`).
    monitors: tuple[Mapping[str, Any], ...] = ()
    #: The managers this one knew and lost, and that have not come back:
    #: ``{"manager", "since_ns" (wall clock), "why"}`` each (see :meth:`dyknow.federation.Directory.lost`).
    lost: tuple[Mapping[str, Any], ...] = ()
    #: How it keeps up (:meth:`dyknow.manager.Manager.load`): ``max_lanes``, ``threads`` (of that
    #: bound, now), ``nice`` (the process's niceness: :mod:`dyknow.priority`), ``lanes`` (each
    #: lane's kind, units, busy fraction, lag, queue, stuck time) and ``overload`` (``state``:
    #: ``"ok"`` or ``"overloaded"``, and what is shed; :mod:`dyknow.overload`).
    executor: Mapping[str, Any] = field(default_factory=dict)
    #: The other managers this one reaches now (their liveliness token is up:
    #: :meth:`dyknow.federation.Directory.alive`, a liveliness query as the model is read, at most
    #: once a second), by name; it reads the summaries of those its plans need only
    #: (:meth:`dyknow.federation.Directory.peers`).
    peers: tuple[str, ...] = ()
    #: The systems in a mode (a spec's ``<system>``, :mod:`dyknow.ros2.modes`): ``{"system",
    #: "mode", "transformation", "unit", "request", "since_ns" (wall clock), "why",
    #: "constraints"}`` each (:func:`dyknow.manager.modes.mode_infos`).
    modes: tuple[Mapping[str, Any], ...] = ()

    def unit(self, name: str) -> UnitInfo:
        """The running unit ``name``; :class:`UnitError` when the model has none."""
        for info in self.units:
            if info.name == name:
                return info
        raise UnitError(f"no unit named {name!r} in the model", where=f"manager {self.manager!r}")

    def to_dict(self) -> dict[str, Any]:
        """The JSON form of the whole model (one ``get_model`` page when it fits)."""
        return {
            "manager": self.manager,
            "units": [u.to_dict() for u in self.units],
            "specs": [s.to_dict() for s in self.specs],
            "requests": [r.to_dict() for r in self.requests],
            "clocks": dict(self.clocks),
            "monitors": [dict(m) for m in self.monitors],
            "lost": [dict(m) for m in self.lost],
            "executor": dict(self.executor),
            "peers": list(self.peers),
            "modes": [dict(m) for m in self.modes],
        }

    def page(self, units_from: int = 0, specs_from: int = 0, max_bytes: int = 4 << 20) -> dict[str, Any]:
        """One page of the JSON form, as the ``get_model`` service serves it.

        The units from ``units_from`` on, then the specs from ``specs_from`` on, as many as fit in
        about ``max_bytes`` of JSON (at least one entry, so every page moves on), with every
        request. ``total`` counts the units and specs of the whole model; ``next`` holds the
        ``units`` and ``specs`` offsets of the next page, or None on the last.
        """
        out: dict[str, Any] = {
            "manager": self.manager,
            "units": [],
            "specs": [],
            "requests": [r.to_dict() for r in self.requests],
            "clocks": dict(self.clocks),
            "monitors": [dict(m) for m in self.monitors],
            "lost": [dict(m) for m in self.lost],
            "executor": dict(self.executor),
            "peers": list(self.peers),
            "modes": [dict(m) for m in self.modes],
            "total": {"units": len(self.units), "specs": len(self.specs)},
        }
        used = len(json.dumps(out))
        offsets = {"units": max(0, units_from), "specs": max(0, specs_from)}
        for kind, entries in (("units", self.units), ("specs", self.specs)):
            while offsets[kind] < len(entries):
                entry = entries[offsets[kind]].to_dict()
                size = len(json.dumps(entry)) + 2
                if used + size > max_bytes and (out["units"] or out["specs"]):
                    out["next"] = offsets
                    return out
                out[kind].append(entry)
                used += size
                offsets[kind] += 1
        out["next"] = None
        return out
