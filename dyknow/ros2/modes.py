"""System modes: a mode of a system is a provider the planner chooses; choosing it switches the nodes.

A spec's ``<system>`` (:mod:`dyknow.spec`) offers one transformation per mode of a system (read
from a ``system_modes`` mode file, :mod:`dyknow.ros2.modefile`, or written in the spec), each with
its priority, constraints and requirements, all providing the system's tag (``Mode(search)``). A
request for that tag is a request that the system be in its best mode: the planner takes the
preferred mode whose constraints hold, the adaptation loop leaves a mode whose requirement turns
false or whose node fails, and a constraint's ``margin`` keeps a mode chosen until its measure
is clearly past the threshold (hysteresis). Each mode is a :class:`ModeUnit`:

- ``setup()`` switches the system to the mode (:func:`switch`): it reads every node's state
  first (a node that does not answer stops the switch before anything changed), then deactivates
  the nodes the mode wants inactive (and cleans up those it wants unconfigured), sets the
  parameters of the nodes it wants active, configures and activates them, and confirms every
  node's state with ``get_state``. A switch that fails half-way is rolled back in reverse order
  (parameters set back to the values read before, transitions undone), and its error says
  which step failed and which state each node is in afterwards (:class:`SwitchError`). The loop
  then takes the next-best mode, as for any unit that fails at start.
- while it runs, it publishes the system's mode on its port ``mode`` (at the switch, then every
  ``poll_s``), and fails when a node it wants active is not any more (a ``transition_event``, a
  poll of ``get_state``, a node that stops answering, a ``/diagnostics`` ERROR of the node);
- ``teardown()`` leaves the nodes as they are while another mode of the system holds them (the
  loop starts the new mode before it stops the old one); the last mode to leave deactivates the
  nodes it made active (never cleans up or destroys them).

The mode units of one system on one manager share a :class:`_System` (the node clients, the
current mode, a lock): switches and polls of one system never overlap, so a mode being left never
mistakes the new mode's transitions for a failure.

Its params: ``system``, ``mode``, ``targets`` (JSON: node -> ``{"state", "mode", "parameters"}``,
as :meth:`~dyknow.ros2.modefile.ModeFile.targets` gives), ``middleware`` (``zenoh`` or ``dds``),
``timeout_s`` (each service call, default 5), ``poll_s`` (default 0.5) and ``diagnostics``
(default true: read ``/diagnostics``).
"""

from __future__ import annotations

import functools
import json
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from dyknow.errors import BindingError, DyKnowError, ServiceError
from dyknow.ros2.bridge import Ros2Provider
from dyknow.ros2.dds import DdsNode, DdsSubscription
from dyknow.ros2.lifecycle import ACTIVATE, CLEANUP, CONFIGURE, DEACTIVATE, STATES, NodeLifecycle
from dyknow.ros2.names import check_topic
from dyknow.ros2.node import Received, Ros2Node, Ros2Subscription
from dyknow.spec.modefile import STATES as TARGET_STATES
from dyknow.spec.modefile import ParameterValue, Target
from dyknow.spec.model import MODE_PORT
from dyknow.unit import Unit

__all__ = ["MAX_NODES", "ModeUnit", "Switch", "SwitchError", "switch", "targets_from_json"]

_TEARDOWN_TIMEOUT_S = 1.5  # the manager waits 2 s for a teardown
#: The most nodes one mode may name (its ``targets``).
MAX_NODES = 256
_MAX_PARAMETERS = 1024  # per node
_MAX_TEXT = 4096  # a parameter's string, or an array's items, at most
_DIAGNOSTICS = ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
_TRANSITION_EVENT = "lifecycle_msgs/msg/TransitionEvent"
_STATE_IDS = {"unconfigured": 1, "inactive": 2, "active": 3}


def targets_from_json(text: str, where: str) -> dict[str, Target]:
    """Check and read a ``targets`` param (it may come from a spec sent over the network)."""
    try:
        data = json.loads(text)
    except (TypeError, ValueError) as exc:
        raise BindingError(f"targets are not JSON: {exc}", where=where, expected='{"/node": {"state": "active", "parameters": {...}}}') from exc
    if not isinstance(data, dict) or not data:
        raise BindingError("targets name no node", where=where, expected='{"/node": {"state": "active", "parameters": {...}}}')
    if len(data) > MAX_NODES:
        raise BindingError(f"targets name {len(data)} nodes", where=where, expected=f"at most {MAX_NODES}")
    out: dict[str, Target] = {}
    for node, target in data.items():
        name = check_topic(node if str(node).startswith("/") else f"/{node}", f"node name in {where}")
        if not isinstance(target, dict) or target.get("state") not in TARGET_STATES:
            raise BindingError(f"the target of {name} is {str(target)[:100]!r}", where=where, expected=f"a state, one of {', '.join(TARGET_STATES)}")
        parameters = target.get("parameters") or {}
        mode = target.get("mode")
        if not isinstance(parameters, dict) or len(parameters) > _MAX_PARAMETERS or not (mode is None or isinstance(mode, str)):
            raise BindingError(f"the parameters or mode of {name} are not valid", where=where, expected=f"at most {_MAX_PARAMETERS} parameters by name, a mode name")
        checked: dict[str, ParameterValue] = {}
        for key, value in parameters.items():
            checked[str(key)] = _parameter(value, f"parameter {key!r} of {name} in {where}")
        out[name] = Target(name, str(target["state"]), mode, checked)
    return out


def _parameter(value: Any, where: str) -> ParameterValue:
    if isinstance(value, list):
        value = tuple(value)
    ok = isinstance(value, (bool, int, str)) or (isinstance(value, float) and math.isfinite(value))
    if isinstance(value, tuple) and 0 < len(value) <= _MAX_TEXT:
        ok = any(all(type(v) is kind for v in value) for kind in (bool, int, float, str))
    if not ok or len(str(value)) > 64 * _MAX_TEXT:
        raise BindingError(f"{str(value)[:100]!r} is not a ROS 2 parameter value", where=where, expected="a bool, integer, double, string, or a list of one of them")
    return value  # type: ignore[no-any-return]


class SwitchError(ServiceError):
    """A mode switch failed: ``what`` says at which step and why, whether the rollback brought
    every node back, and ``states`` the state of each node afterwards (node -> label)."""

    def __init__(self, what: str, *, where: str, states: Mapping[str, str], expected: str | None = None) -> None:
        now = ", ".join(f"{node} {label}" for node, label in states.items())
        super().__init__(f"{what}; now: {now}" if states else what, where=where, expected=expected)
        self.states = dict(states)


@dataclass
class Switch:
    """What a switch did: the steps (``"/search: set 1 parameter(s)"``, ``"/follow: activate"``)
    and the time it took, from the first call to the last state confirmed."""

    steps: list[str] = field(default_factory=list)
    seconds: float = 0.0


def switch(lifecycles: Mapping[str, NodeLifecycle], targets: Mapping[str, Target], *, where: str) -> Switch:
    """Bring every node of ``targets`` to its target (see the module's documentation): the
    lifecycles by node name. Raises :class:`SwitchError`, after rolling back what it did."""
    start = time.perf_counter()
    done = Switch()
    undo: list[tuple[str, Callable[[], None]]] = []
    step = "reading the states"
    try:
        states = {node: lifecycles[node].state()[0] for node in targets}  # a silent node stops it here, before any change
        wanted = {node: _STATE_IDS[t.state] for node, t in targets.items()}
        for node, state in states.items():
            if state not in (1, 2, 3) and not (wanted[node] != 3 and state == 4):
                raise ServiceError(f"{node} is {STATES.get(state, state)}", where=where, expected="nodes that are unconfigured, inactive or active (none in transition or error)")
        old = {
            node: lifecycles[node].get_parameters(list(t.parameters))
            for node, t in targets.items()
            if t.parameters and wanted[node] == 3
        }
        for node in targets:  # down first: nothing the new mode leaves runs beside it
            lifecycle = lifecycles[node]
            if states[node] == 3 and wanted[node] < 3:
                step = f"deactivating {node}"
                lifecycle.change(DEACTIVATE)
                undo.append((f"activate {node}", functools.partial(lifecycle.change, ACTIVATE)))
                done.steps.append(f"{node}: deactivate")
                states[node] = 2
            if states[node] == 2 and wanted[node] == 1:
                step = f"cleaning up {node}"
                lifecycle.change(CLEANUP)
                undo.append((f"configure {node}", functools.partial(lifecycle.change, CONFIGURE)))
                done.steps.append(f"{node}: cleanup")
                states[node] = 1
        for node, target in targets.items():
            lifecycle = lifecycles[node]
            if wanted[node] != 3:
                continue
            if target.parameters:
                step = f"setting the parameters of {node}"
                lifecycle.set_parameters(target.parameters)
                before = {k: v for k, v in old[node].items() if v is not None}
                undo.append((f"set the parameters of {node} back", functools.partial(lifecycle.set_parameters, before)))
                done.steps.append(f"{node}: set {len(target.parameters)} parameter(s)")
            if states[node] == 1:
                step = f"configuring {node}"
                lifecycle.change(CONFIGURE)
                undo.append((f"clean up {node}", functools.partial(lifecycle.change, CLEANUP)))
                done.steps.append(f"{node}: configure")
                states[node] = 2
            if states[node] == 2:
                step = f"activating {node}"
                lifecycle.change(ACTIVATE)
                undo.append((f"deactivate {node}", functools.partial(lifecycle.change, DEACTIVATE)))
                done.steps.append(f"{node}: activate")
                states[node] = 3
        step = "confirming the states"
        for node in targets:
            state, label = lifecycles[node].state()
            if state != wanted[node] and not (wanted[node] == 2 and state == 1):
                raise ServiceError(f"{node} is {label} after the switch, not {targets[node].state}", where=where)
    except DyKnowError as exc:
        failed = [what for what, action in reversed(undo) if not _tried(action)]
        after = _states(lifecycles, targets)
        rolled = "nothing had changed" if not undo else "rolled back" if not failed else f"the rollback could not {', '.join(failed)}"
        raise SwitchError(f"{step} failed: {exc.what}; {rolled}", where=where, states=after, expected=exc.expected) from exc
    done.seconds = time.perf_counter() - start
    return done


def _tried(action: Callable[[], None]) -> bool:
    try:
        action()
    except DyKnowError:
        return False
    return True


def _states(lifecycles: Mapping[str, NodeLifecycle], targets: Mapping[str, Target]) -> dict[str, str]:
    out = {}
    for node in targets:
        try:
            out[node] = lifecycles[node].state(timeout_s=min(lifecycles[node].timeout_s, 1.0))[1]
        except DyKnowError:
            out[node] = "unknown (get_state does not answer)"
    return out


class _System:
    """One system's shared state on one manager: its node clients, its mode, its mode units."""

    def __init__(self, ros_node: Ros2Node | DdsNode, timeout_s: float) -> None:
        self.ros_node = ros_node
        self.timeout_s = timeout_s
        self.lifecycles: dict[str, NodeLifecycle] = {}
        self.mode: str | None = None
        self.active: set[str] = set()  # the nodes a mode of this system made or found active
        self.holders: set[str] = set()
        self.lock = threading.RLock()

    def lifecycles_of(self, targets: Mapping[str, Target]) -> dict[str, NodeLifecycle]:
        """The clients of the nodes of ``targets`` (made on first use, shared by the system's modes,
        every service's at once: a node a mode leaves inactive is ready when another activates it)."""
        for node in targets:
            if node not in self.lifecycles:
                lifecycle = self.lifecycles[node] = NodeLifecycle(self.ros_node, node, timeout_s=self.timeout_s)
                lifecycle.prepare()
        return {node: self.lifecycles[node] for node in targets}

    def close(self) -> None:
        """Close the node clients."""
        for lifecycle in self.lifecycles.values():
            lifecycle.close()
        self.lifecycles.clear()


_SYSTEMS: dict[tuple[int, str], _System] = {}
_SYSTEMS_LOCK = threading.Lock()


class ModeUnit(Unit):
    """The provider unit of one mode of a system (see the module's documentation).

    ``switched`` is what its switch did (:class:`Switch`), None before it.
    """

    switched: Switch | None = None
    _provider: Ros2Provider | None = None
    _system: _System | None = None
    _key: tuple[int, str] = (0, "")
    _subscriptions: list[Ros2Subscription | DdsSubscription] = []  # each unit its own list from setup() on

    def use_ros2(self, provider: Ros2Provider) -> None:
        """Take the manager's ROS 2 middleware (called by the manager before ``setup()``)."""
        self._provider = provider

    @property
    def mode(self) -> str:
        """The mode this unit stands for (``system.mode``)."""
        return f"{self.params.get('system', '')}.{self.params.get('mode', '')}"

    def setup(self) -> None:
        """Switch the system to this mode, then watch its nodes."""
        where = f"mode {self.mode} (unit {self.name!r})"
        self.targets = targets_from_json(str(self.params.get("targets", "")), where)
        provider = self._provider
        if provider is None:
            raise BindingError("no ROS 2 middleware to manage nodes on", where=where, expected="a unit spawned by a manager")
        dds = str(self.params.get("middleware", "zenoh")) == "dds"
        ros_node: Ros2Node | DdsNode = provider.dds_node() if dds else provider.ros2_node()
        timeout_s = float(self.params.get("timeout_s", 5.0))
        self._key = (id(ros_node), str(self.params.get("system", "")))
        with _SYSTEMS_LOCK:
            system = _SYSTEMS.get(self._key)
            if system is None:
                system = _SYSTEMS[self._key] = _System(ros_node, timeout_s)
            system.holders.add(self.name)
        self._system = system
        self._subscriptions = []
        try:
            with system.lock:
                previous, system.mode = system.mode, None  # the mode being left stops judging its nodes
                try:
                    self.switched = switch(system.lifecycles_of(self.targets), self.targets, where=where)
                except BaseException:
                    system.mode = previous  # (rolled back: the nodes are as that mode left them)
                    raise
                system.mode = self.mode
                system.active = {node for node, target in self.targets.items() if target.state == "active"}
            self.log.info("%s: %s in %.1f ms", self.mode, ", ".join(self.switched.steps) or "already in it", self.switched.seconds * 1e3)
            for node in sorted(system.active):
                topic = f"{node}/transition_event"
                self._subscriptions.append(
                    ros_node.create_subscription(topic, _TRANSITION_EVENT, functools.partial(self._transitioned, node), call_soon=self.call_soon)
                )
            if self.params.get("diagnostics", True) in (True, "true", "1"):
                self._subscriptions.append(ros_node.create_subscription(*_DIAGNOSTICS, self._diagnosed, call_soon=self.call_soon))
            self._announce()
        except BaseException:
            self._unsubscribe()
            self._leave(bring_down=False)
            raise

    def _mine(self) -> bool:
        system = self._system
        return system is not None and system.mode == self.mode

    def _announce(self, states: Mapping[str, str] | None = None) -> None:
        nodes = states or {node: target.state for node, target in self.targets.items()}
        self.publish(MODE_PORT, {"system": self.params.get("system", ""), "mode": self.params.get("mode", ""), "nodes": dict(nodes)})

    def _transitioned(self, node: str, received: Received) -> None:  # on the unit's thread
        """A transition event is a hint, the node's state the truth: a late event of a switch
        (one rolled back, say) must not fail the mode."""
        goal = getattr(received.message, "goal_state", None)
        system = self._system
        if goal is None or int(goal.id) == 3 or system is None:
            return
        with system.lock:
            if not self._mine() or node not in system.lifecycles:
                return
            try:
                state, label = system.lifecycles[node].state()
            except DyKnowError as exc:
                self.fail(f"{node} vanished: {exc.what} (mode {self.mode})")
                return
        if state != 3:
            self.fail(f"{node} went to {label}, not active (its transition_event); mode {self.mode} needs it active")

    def _diagnosed(self, received: Received) -> None:  # on the unit's thread
        system = self._system
        if system is None or not self._mine():
            return
        for status in getattr(received.message, "status", ())[:1000]:
            level = status.level[0] if isinstance(status.level, bytes) else int(status.level)
            head = str(status.name).split(":", 1)[0].strip()
            if level == 2 and any(head in (node, node.lstrip("/"), node.rsplit("/", 1)[-1]) for node in system.active):
                self.fail(f"/diagnostics: {str(status.name)[:200]} is ERROR: {str(status.message)[:300]} (mode {self.mode})")
                return

    def run(self, stop: threading.Event) -> None:
        """Every ``poll_s``: ask each node the mode wants active for its state; fail when one is
        not active or does not answer, and publish the system's mode."""
        system = self._system
        if system is None:
            return
        poll_s = float(self.params.get("poll_s", 0.5))
        while not stop.wait(poll_s):
            with system.lock:
                if not self._mine():
                    return  # another mode of the system took over: it watches the nodes now
                states: dict[str, str] = {}
                for node, lifecycle in system.lifecycles_of(self.targets).items():
                    try:
                        state, label = lifecycle.state()
                    except DyKnowError as exc:
                        if not stop.is_set():
                            self.fail(f"{node} vanished: {exc.what} (mode {self.mode})")
                        return
                    states[node] = label
                    if self.targets[node].state == "active" and state != 3 and not stop.is_set():
                        self.fail(f"{node} is {label}, not active; mode {self.mode} needs it active")
                        return
            self._announce(states)

    def teardown(self) -> None:
        """Unsubscribe; the last mode of the system to leave deactivates the nodes it made active."""
        self._unsubscribe()
        self._leave(bring_down=True)

    def _unsubscribe(self) -> None:
        subscriptions, self._subscriptions = self._subscriptions, []
        for subscription in subscriptions:
            subscription.close()

    def _leave(self, *, bring_down: bool) -> None:
        system, self._system = self._system, None
        if system is None:
            return
        with _SYSTEMS_LOCK:
            system.holders.discard(self.name)
            last = not system.holders
            if last:
                _SYSTEMS.pop(self._key, None)
        if not last:
            return
        try:
            with system.lock:
                if bring_down and system.mode == self.mode:
                    for node in sorted(system.active):
                        lifecycle = system.lifecycles[node]
                        lifecycle.timeout_s = min(lifecycle.timeout_s, _TEARDOWN_TIMEOUT_S)
                        try:
                            if lifecycle.bring_down():
                                self.log.info("%s deactivated (mode %s left)", node, self.mode)
                        except DyKnowError as exc:
                            self.log.warning("could not deactivate %s: %s", node, exc)
                system.mode = None
        finally:
            system.close()
