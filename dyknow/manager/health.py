"""The manager's health as ``/diagnostics`` statuses: a registry of status sources (its requirements, monitored formulas, requests and managed nodes built in) and the publisher it runs when asked.

Each status is named as ROS 2's ``diagnostic_updater`` names them, after the manager's ROS 2 node
(``dyknow_robot``):

- ``dyknow_robot: requirement <formula>`` (``... of <transformation>`` for a requirement of a
  transformation's spec): OK while its latest verdict is true, ERROR when false (the request
  adapts), STALE before its first verdict; WARN when it cannot be watched (the stream is served
  unchecked) or its monitor warned about its data; ERROR when its monitor failed;
- ``dyknow_robot: monitor <formula>`` (``dyknow monitor``): the same, but WARN when false (a
  monitored formula watches; nothing adapts to it);
- ``dyknow_robot: request <tag>``: OK while active, WARN while degraded with a configuration
  running (a requirement false in place, one not watched), ERROR with none;
- ``dyknow_robot: node <ROS 2 node>`` for each managed node (:class:`~dyknow.ros2.managed.ManagedNode`):
  OK once brought up and while its unit runs (``active``), WARN while its topic is stalled, ERROR
  once it failed (at bring-up too), kept until it is chosen and active again; OK ``inactive`` once
  left healthy. Only nodes chosen since the manager started are said (at most 1,000, the oldest
  forgotten first);
- ``dyknow_robot: system <system>`` for each system in a mode (a spec's ``<system>``,
  :mod:`dyknow.manager.modes`): OK, its message the mode and why it was chosen, its values the
  system, the mode, the transformation, the cause and each constraint with its measure's value
  (a mode that fails is left at once: the request's and the node's statuses say so).

``values`` hold the formula and what decided the verdict: the latest verdict's fields as the
monitor publishes them (``verdict``, ``t``, ``decided_t``, ``t_ns``, ``decided_ns``, ``state``,
``robustness``, ``object``, ``gap``), the request's key and the verdicts' key; a request's tag,
key, state, transformations and reason; a node's unit and its error. ``hardware_id`` is the
request's key, the monitor's verdicts key, or the ROS 2 node's name.

More sources plug in with :meth:`Health.add_source` (``Manager.add_status_source``): a callable
returning :class:`~dyknow.ros2.diagnostics.DiagnosticStatus` objects, called once a second and on changes.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from typing import Any, Protocol

from dyknow.adaptation.knowledge import Knowledge
from dyknow.errors import DyKnowError
from dyknow.manager.modes import mode_infos
from dyknow.model import RequestInfo, UnitEvent, UnitInfo
from dyknow.reasoning.monitors import MonitorInfo
from dyknow.reasoning.unit import FormulaMonitor
from dyknow.ros2.diagnostics import ERROR, OK, STALE, WARN, DiagnosticsPublisher, DiagnosticStatus
from dyknow.ros2.managed import ManagedNode
from dyknow.unit import Unit

__all__ = ["DIAGNOSTICS_MIDDLEWARES", "Health", "StatusSource"]

log = logging.getLogger("dyknow.manager")

#: A source of statuses: called once a second (and on changes) on the publisher's thread; it must return at once.
StatusSource = Callable[[], Iterable[DiagnosticStatus]]
#: ``Manager(diagnostics=...)``: rmw_zenoh (the manager's ROS 2 node) or DDS (its participant).
DIAGNOSTICS_MIDDLEWARES = ("ros2", "ros2dds")
_MAX_NODES = 1000  # managed nodes remembered (a failed one is kept until it is active again)
_VERDICT_FIELDS = ("verdict", "t", "decided_t", "t_ns", "decided_ns", "state", "robustness", "object", "gap")


class Watched(Protocol):
    """What the built-in sources read of the manager: its model and its units' objects."""

    def requests(self) -> list[RequestInfo]:
        """The active requests."""
        ...

    def monitors(self) -> list[MonitorInfo]:
        """The monitored formulas."""
        ...

    def units(self) -> list[UnitInfo]:
        """Every unit."""
        ...

    def unit(self, name: str) -> Unit:
        """The object of unit ``name``; :class:`~dyknow.errors.DyKnowError` when there is none."""
        ...


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return value if isinstance(value, str) else json.dumps(value)


class Health:
    """The statuses of manager ``watched`` (its parts' and those of the sources added), named after
    ``node_name`` (its ROS 2 node's); ``knowledge`` is its adaptation loop's (the monitors of each
    request's requirements). Feed it the manager's unit events (:meth:`unit_event`)."""

    def __init__(self, node_name: str, watched: Watched, knowledge: Knowledge) -> None:
        self.node_name = node_name
        self._watched = watched
        self._knowledge = knowledge
        self._lock = threading.Lock()
        self._sources: list[StatusSource] = [self._requirements, self._monitors, self._requests, self._nodes, self._modes]
        self._failing: set[int] = set()  # sources whose failure was logged (once each)
        # managed nodes: unit -> the ROS 2 node it manages; the node -> its latest status
        self._node_of: dict[str, str] = {}
        self._node_status: OrderedDict[str, DiagnosticStatus] = OrderedDict()
        self._node_events = 0  # counts the nodes' events: a poll that read the units before one does not overwrite it
        self.publisher: DiagnosticsPublisher | None = None

    # -- the registry

    def add_source(self, source: StatusSource) -> Callable[[], None]:
        """Add ``source`` (its statuses join the array); returns a function that removes it."""
        with self._lock:
            self._sources.append(source)
        self.notify()

        def remove() -> None:
            with self._lock:
                if source in self._sources:
                    self._sources.remove(source)
            self.notify()

        return remove

    def statuses(self) -> list[DiagnosticStatus]:
        """Every source's statuses, in the order the sources were added; a source that raises is
        logged once and left out of this array. A name said twice (one requirement of two
        requests) is told apart by its ``hardware_id``: ``... (robot/request/...)``."""
        with self._lock:
            sources = list(self._sources)
        out: list[DiagnosticStatus] = []
        for source in sources:
            try:
                out.extend(source())
            except Exception:
                if id(source) not in self._failing:
                    self._failing.add(id(source))
                    log.exception("the /diagnostics status source %r failed; left out", source)
        names = Counter(status.name for status in out)
        if len(names) < len(out):
            out = [replace(s, name=f"{s.name} ({s.hardware_id})") if names[s.name] > 1 else s for s in out]
        return out

    def publish_on(self, node: Any, *, period_s: float = 1.0) -> DiagnosticsPublisher:
        """Start publishing on ``node`` (a ROS 2 node or DDS participant): see :class:`~dyknow.ros2.diagnostics.DiagnosticsPublisher`."""
        self.publisher = DiagnosticsPublisher(node, self.statuses, period_s=period_s)
        return self.publisher

    def notify(self) -> None:
        """Something changed: the publisher looks now."""
        if self.publisher is not None:
            self.publisher.notify()

    def close(self) -> None:
        """Stop publishing; safe twice."""
        publisher, self.publisher = self.publisher, None
        if publisher is not None:
            publisher.close()

    # -- the built-in sources

    def _name(self, what: str) -> str:
        return f"{self.node_name}: {what}"

    def _infos(self) -> dict[str, UnitInfo]:
        return {info.name: info for info in self._watched.units()}

    def _verdict_status(
        self, infos: dict[str, UnitInfo], name: str, formula: str, monitor: str, hardware_id: str, false_level: int, extra: Sequence[tuple[str, str]]
    ) -> DiagnosticStatus:
        values = [("formula", formula), *extra, ("unit", monitor)]
        info = infos.get(monitor)
        if info is not None and info.state == "failed":
            return DiagnosticStatus(name, ERROR, f"its monitor failed: {info.error}", hardware_id, tuple(values))
        try:
            unit = self._watched.unit(monitor)
        except DyKnowError:
            unit = None
        if info is None or not isinstance(unit, FormulaMonitor):
            return DiagnosticStatus(name, STALE, "its monitor is not running", hardware_id, tuple(values))
        latest = dict(unit.latest)
        verdict = latest.get(formula) or next(iter(latest.values()), None)
        warnings = list(unit.warnings)
        if verdict is None:
            return DiagnosticStatus(name, WARN if warnings else STALE, warnings[0] if warnings else "no verdict yet", hardware_id, tuple(values))
        values.extend((key, _text(verdict[key])) for key in _VERDICT_FIELDS if key in verdict)
        if verdict.get("verdict") is False:
            return DiagnosticStatus(name, false_level, f"false at t={verdict.get('t')}", hardware_id, tuple(values))
        if warnings:
            return DiagnosticStatus(name, WARN, warnings[0], hardware_id, tuple(values))
        return DiagnosticStatus(name, OK, "holds", hardware_id, tuple(values))

    def _requirements(self) -> list[DiagnosticStatus]:
        out = []
        infos = self._infos() if self._knowledge.requests else {}
        for request in list(self._knowledge.requests.values()):
            for formula, (monitor, _needs) in list(request.watches.items()):
                extra: tuple[tuple[str, str], ...] = (("request", request.key), ("verdicts", f"{request.key}/requirements/{monitor.rsplit('-', 1)[-1]}"))
                out.append(self._verdict_status(infos, self._name(f"requirement {formula}"), formula, monitor, request.key, ERROR, extra))
            for (unit, formula), watch in list(request.spec_watches.items()):
                extra = (("request", request.key), ("transformation", watch.label), ("served by", unit), ("verdicts", watch.key))
                out.append(self._verdict_status(infos, self._name(f"requirement {formula} of {watch.label}"), formula, watch.monitor, request.key, ERROR, extra))
            for (unit, formula), (label, why) in list(request.unwatched.items()):
                values = (("formula", formula), ("request", request.key), ("transformation", label), ("served by", unit), ("why", why))
                out.append(DiagnosticStatus(self._name(f"requirement {formula} of {label}"), WARN, f"not watched: {why}", request.key, values))
        return out

    def _monitors(self) -> list[DiagnosticStatus]:
        out = []
        monitors = self._watched.monitors()
        infos = self._infos() if monitors else {}
        for info in monitors:
            for individual, formula, unit, key in info.expansions:
                given = [("verdicts", key), *((("individual", individual),) if individual is not None else ())]
                out.append(self._verdict_status(infos, self._name(f"monitor {formula}"), formula, unit, key, WARN, given))
        return out

    def _requests(self) -> list[DiagnosticStatus]:
        out = []
        for info in self._watched.requests():
            values = [("tag", info.tag), ("key", info.key), ("state", info.state), ("transformations", ", ".join(info.labels)),
                      ("references", str(info.references))]  # fmt: skip
            if info.reason:
                values.append(("reason", info.reason))
            if info.state == "active":
                level, message = OK, f"active: {', '.join(info.labels) or 'no transformation'}"
            elif info.units:
                level, message = WARN, f"degraded: {info.reason or 'see the model'}"
            else:
                level, message = ERROR, f"no configuration: {info.reason or 'nothing provides it'}"
            out.append(DiagnosticStatus(self._name(f"request {info.tag}"), level, message, info.key, tuple(values)))
        return out

    def _modes(self) -> list[DiagnosticStatus]:
        out = []
        knowledge = self._knowledge
        for mode in mode_infos(self._watched.units(), self._watched.requests(), list(knowledge.history), dict(knowledge.measurements)):
            values = [("system", mode["system"]), ("mode", mode["mode"]), ("transformation", mode["transformation"]), ("why", mode["why"])]
            values += [(f"constraint {c['measure']} {c['op']} {c['value']}", _text(c["measured"])) for c in mode["constraints"]]
            message = f"in mode {mode['mode']}: {mode['why']}"
            out.append(DiagnosticStatus(self._name(f"system {mode['system']}"), OK, message[:1000], mode["system"], tuple(values)))
        return out

    def unit_event(self, event: UnitEvent) -> None:
        """A unit was spawned, failed or was destroyed: a managed node's status follows (on the thread where it happened)."""
        if event.kind == "destroyed":
            with self._lock:
                gone = self._node_of.pop(event.unit, None)
                last = self._node_status.get(gone) if gone is not None else None
                if gone is not None and (last is None or last.level != ERROR):  # (a failure is kept until it is active again)
                    self._set_node(gone, DiagnosticStatus(self._name(f"node {gone}"), OK, "inactive: not chosen now", gone, (("unit", event.unit),)))
        else:
            with self._lock:
                node = self._node_of.get(event.unit)
            if node is None:  # (a unit that fails in setup() is never said spawned)
                try:
                    unit = self._watched.unit(event.unit)
                except DyKnowError:
                    return
                if not isinstance(unit, ManagedNode):
                    return
                node = str(unit.params.get("node", "")) or event.unit
            values: tuple[tuple[str, str], ...] = (("unit", event.unit), ("transformation", event.label))
            if event.kind == "failed":
                status = DiagnosticStatus(self._name(f"node {node}"), ERROR, f"failed: {event.error}", node, (*values, ("error", str(event.error))))
            else:  # spawned: brought up (its setup() returned)
                status = DiagnosticStatus(self._name(f"node {node}"), OK, "active", node, values)
            with self._lock:
                self._node_of[event.unit] = node
                self._set_node(node, status)
        self.notify()

    def _set_node(self, node: str, status: DiagnosticStatus) -> None:  # (under the lock)
        self._node_events += 1
        self._node_status[node] = status
        self._node_status.move_to_end(node)
        while len(self._node_status) > _MAX_NODES:
            self._node_status.popitem(last=False)

    def _nodes(self) -> list[DiagnosticStatus]:
        with self._lock:
            units = dict(self._node_of)
            seen = self._node_events
        if units:
            stalled = set(self._knowledge.stalled)
            for info in self._watched.units():
                node = units.get(info.name)
                if node is None:
                    continue
                values: tuple[tuple[str, str], ...] = (("unit", info.name), ("transformation", info.label))
                if info.state == "failed":
                    status = DiagnosticStatus(self._name(f"node {node}"), ERROR, f"failed: {info.error}", node, (*values, ("error", str(info.error))))
                elif info.state == "running" and info.name in stalled:
                    status = DiagnosticStatus(self._name(f"node {node}"), WARN, "its topic is stalled (silent past its deadline)", node, values)
                elif info.state == "running":
                    status = DiagnosticStatus(self._name(f"node {node}"), OK, "active", node, values)
                else:
                    status = DiagnosticStatus(self._name(f"node {node}"), WARN, info.state, node, values)
                with self._lock:
                    if self._node_events == seen:  # (no event since the units were read)
                        self._set_node(node, status)
                        seen = self._node_events
        with self._lock:
            return sorted(self._node_status.values(), key=lambda s: s.name)
