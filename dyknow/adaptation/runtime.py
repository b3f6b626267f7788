"""What the adaptation loop needs of the manager that runs it: a :class:`Runtime` (a test can hand the
loop a small stand-in), and the :class:`DeadlinePort` s it watches.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from dyknow.federation import Summary
from dyknow.library import Library
from dyknow.model import LOCAL, Owner, UnitInfo
from dyknow.ontology import Ontology
from dyknow.reasoning.syntax import Formula
from dyknow.spec import TransformationSpec
from dyknow.unit import Unit

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs


# ---------------------------------------------------------------------------- what the loop needs


@dataclass(frozen=True, slots=True)
class DeadlinePort:
    """An output port with a ``deadline-ms`` of a live unit, and how many messages it sent so far.

    ``started_ns`` tells two units spawned under the same name apart.
    """

    unit: str
    label: str
    port: str
    deadline_ns: int
    messages: int
    started_ns: int


class Runtime(Protocol):
    """What the adaptation loop needs of the manager whose requests it keeps flowing.

    :class:`~dyknow.manager.Manager` provides all of it publicly.
    """

    @property
    def name(self) -> str:
        """The manager's name (it appears in keys)."""
        ...

    @property
    def library(self) -> Library:
        """The specs the planner may use."""
        ...

    @property
    def ontology(self) -> Ontology | None:
        """The ontology tags are matched against."""
        ...

    def units(self) -> list[UnitInfo]:
        """A snapshot of every running unit."""
        ...

    def has_unit(self, name: str) -> bool:
        """Whether a unit called ``name`` runs."""
        ...

    def unit_info(self, name: str) -> UnitInfo | None:
        """Running unit ``name`` as :meth:`units` shows it (None when there is none)."""
        ...

    def unit_changes(self, since: int) -> tuple[int, list[str] | None]:
        """The version of the units now, and the names of the units spawned, destroyed, rebound
        or failed after version ``since`` (None: the log does not reach back that far, so read
        :meth:`units` again)."""
        ...

    def unit(self, name: str) -> Unit:
        """The Python object of running unit ``name``."""
        ...

    def spawn(
        self, label: str | TransformationSpec, name: str, *, bindings: Mapping[str, str] | None = None, owner: Owner = LOCAL
    ) -> UnitInfo:
        """Start a unit of a library label, or of a spec given directly; ``owner``: whom a
        requirement's monitor watches for (its formula's nodes count against that caller's
        share; the loop passes it for the requirements a request's reference adds, and only then)."""
        ...

    def destroy(self, name: str) -> None:
        """Stop unit ``name``."""
        ...

    def get_config(self, name: str) -> dict[str, str]:
        """Port -> key bindings of unit ``name``."""
        ...

    def set_config(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """Rebind ports of unit ``name``."""
        ...

    def deadline_ports(self) -> list[DeadlinePort]:
        """The output ports with a deadline, of every live unit."""
        ...

    def publish_event(self, kind: str, event: Mapping[str, Any]) -> None:
        """Publish an event of ``kind`` (JSON) on the manager's event key."""
        ...

    def peers(self) -> Mapping[str, Summary]:
        """The other managers this one follows (reachable, and candidates of its plans or in use),
        with their last summary (empty when alone)."""
        ...

    def discover(self, wanted: Collection[tuple[str, tuple[str, ...]]], *, need: str | None = None) -> bool:
        """Find the managers that offer the tags ``wanted`` (``(functor, args)`` by local names)
        and follow them (:meth:`peers` then has them); True when one was added. ``need``: the tag
        of the request that asks: what it found is let go once no open request has that tag."""
        ...

    def spawn_on(self, manager: str, label: str, name: str, *, bindings: Mapping[str, str]) -> None:
        """Spawn a unit of ``manager``'s library on ``manager``, for a request of this one."""
        ...

    def destroy_on(self, manager: str, name: str) -> None:
        """Destroy a unit this manager spawned on ``manager``."""
        ...

    def set_config_on(self, manager: str, name: str, bindings: Mapping[str, str]) -> None:
        """Rebind ports of a unit on ``manager``."""
        ...

    def check_formula(self, formula: str) -> Formula:
        """``formula`` parsed and held to the manager's bounds, and to what its monitors may
        still take (:class:`~dyknow.errors.FormulaError` otherwise), before anything is requested."""
        ...

    def changed(self) -> None:
        """Something the other managers see changed (a unit stalled or resumed)."""
        ...
