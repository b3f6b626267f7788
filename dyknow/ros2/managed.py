"""A managed ROS 2 node: a node dyknow did not spawn, offered to the planner as a provider of its topic.

A spec's ``<node>`` element (:mod:`dyknow.spec`) becomes a transformation whose unit is a
:class:`ManagedNode`: the planner plans with it as with any unit (its output port carries the
tags of the node's topic), and the adaptation loop recovers its failures on the same key, with
the same back-off, probation and anti-flapping. Being chosen spawns the unit, which

- in ``setup()`` sets the node's parameters and brings it up (configure if unconfigured, then
  activate: :class:`~dyknow.ros2.lifecycle.NodeLifecycle`), then reads its topic into ``out`` as
  a :class:`~dyknow.ros2.bridge.Ros2Source` that requires a publisher does;
- while it runs, reads the node's ``<node>/transition_event`` and asks for its state every
  ``poll_s``, and fails when the node is not active any more (it went to ErrorProcessing, was
  finalized or deactivated by someone else) or does not answer (it vanished); it also fails when the topic's publishers vanish, and when
  ``/diagnostics`` has an ERROR status of the node (:func:`is_status_of`; param ``diagnostics``
  false: not read), and the loop marks it stalled when its topic is silent past the port's
  ``deadline-ms``;
- in ``teardown()`` (the request left it, or it failed) deactivates the node if it is active and
  no other unit of the manager uses it (two ``<node>``s of one node, one per topic, share it),
  never cleans it up or destroys it.

Its params: ``node`` (the node's name, ``/camera_top``), ``binding`` (its topic, ``ros2:`` for
rmw_zenoh or ``ros2dds:`` for DDS, with the type), ``lifecycle`` (default true), ``timeout_s``
(each service call, default 5), ``poll_s`` (default 0.5), ``wait_s`` (for the topic's publisher
after activation, default ``timeout_s``), and one ``ros.NAME`` param per ROS 2 parameter to set
(:data:`~dyknow.spec.model.PARAMETER_PREFIX`).
"""

from __future__ import annotations

import threading
from typing import Any

from dyknow.errors import DyKnowError
from dyknow.ros2.bridge import Ros2Source
from dyknow.ros2.dds import DdsNode, DdsSubscription
from dyknow.ros2.lifecycle import STATES, NodeLifecycle
from dyknow.ros2.node import Received, Ros2Subscription
from dyknow.spec.model import PARAMETER_PREFIX

__all__ = ["ManagedNode", "is_status_of", "node_parameters"]

_TEARDOWN_TIMEOUT_S = 1.5  # the manager waits 2 s for a teardown
DIAGNOSTICS_TOPIC = "/diagnostics"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
TRANSITION_EVENT = "lifecycle_msgs/msg/TransitionEvent"
ERROR = 2  # diagnostic_msgs/msg/DiagnosticStatus.ERROR
# each node's NodeLifecycle and the units that use it (by the manager's node or participant, and the
# node's name): they share its clients (a DDS client makes one call at a time, and could take another
# client's answer), and the last to leave deactivates it, so two <node>s of one node (one per topic)
# never pull it from under each other
_HOLDERS: dict[tuple[int, str], tuple[NodeLifecycle, set[str]]] = {}
_HOLDERS_LOCK = threading.Lock()


def is_status_of(status_name: str, node: str) -> bool:
    """Whether a ``/diagnostics`` status named ``status_name`` is node ``node``'s: named after its
    name as ROS 2's ``diagnostic_updater`` names them (``camera_top: Frame rate``), with or without
    its namespace, or the node's name alone."""
    head = status_name.split(":", 1)[0].strip()
    return head in (node, node.lstrip("/"), node.rsplit("/", 1)[-1])


def node_parameters(params: dict[str, Any] | Any) -> dict[str, bool | int | float | str]:
    """The ROS 2 parameters among a managed node's unit params (``ros.NAME`` -> ``NAME``)."""
    return {name[len(PARAMETER_PREFIX) :]: value for name, value in dict(params).items() if name.startswith(PARAMETER_PREFIX)}


class ManagedNode(Ros2Source):
    """The provider unit of a managed ROS 2 node (see the module's documentation).

    ``node_lifecycle`` is its :class:`~dyknow.ros2.lifecycle.NodeLifecycle` (shared by the units of
    one node on one manager); ``brought_up`` says
    what choosing it did (``["set 1 parameter(s)", "configure", "activate"]``).
    """

    node_lifecycle: NodeLifecycle | None = None
    brought_up: tuple[str, ...] = ()
    _held: tuple[int, str] = (0, "")
    _subscriptions: list[Ros2Subscription | DdsSubscription] = []  # each unit its own list from setup() on; this one stays empty

    def setup(self) -> None:
        """Set the parameters, configure and activate the node, then subscribe to its topic."""
        ros_node, binding = self._binding()
        self._subscriptions = []
        timeout_s = float(self.params.get("timeout_s", 5.0))
        self.params = {"wait_s": timeout_s, **self.params, "require_publisher": True}
        lifecycle = NodeLifecycle(
            ros_node,
            str(self.params.get("node", "")),
            lifecycle=self.params.get("lifecycle", True) in (True, "true", "1"),
            timeout_s=timeout_s,
        )
        self._held = (id(ros_node), lifecycle.name)
        with _HOLDERS_LOCK:  # before it is brought up: a unit of the node leaving meanwhile leaves it active
            shared, holders = _HOLDERS.setdefault(self._held, (lifecycle, set()))
            holders.add(self.name)
        self.node_lifecycle = shared
        if shared is not lifecycle:
            lifecycle.close()  # (it made no client yet)
        try:
            self.brought_up = tuple(shared.bring_up(node_parameters(self.params)))
        except BaseException:
            self._leave()
            raise
        self.log.info("%s%s: %s", shared.name, " (DDS)" if isinstance(ros_node, DdsNode) else "", ", ".join(self.brought_up) or "already active")
        try:
            super().setup()
            if shared.lifecycle:  # told at once of a transition, beside the polls
                topic = f"{shared.name}/transition_event"
                self._subscriptions.append(ros_node.create_subscription(topic, TRANSITION_EVENT, self._transitioned, call_soon=self.call_soon))
            if self.params.get("diagnostics", True) in (True, "true", "1"):
                self._subscriptions.append(
                    ros_node.create_subscription(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY, self._diagnosed, call_soon=self.call_soon)
                )
        except BaseException:
            self._unsubscribe()
            super().teardown()
            self._leave()
            raise

    def _transitioned(self, received: Received) -> None:  # on the unit's thread
        lifecycle = self.node_lifecycle
        goal = getattr(received.message, "goal_state", None)
        if lifecycle is None or goal is None or int(goal.id) == 3:
            return
        start = received.message.start_state
        went = [str(state.label)[:100] or STATES.get(int(state.id), "unknown") for state in (start, goal)]
        self.fail(f"{lifecycle.name} went from {went[0]} to {went[1]}, not active (its transition_event)")

    def _diagnosed(self, received: Received) -> None:  # on the unit's thread
        lifecycle = self.node_lifecycle
        if lifecycle is None:
            return
        for status in getattr(received.message, "status", ())[:1000]:
            level = status.level[0] if isinstance(status.level, bytes) else int(status.level)
            if level == ERROR and is_status_of(str(status.name), lifecycle.name):
                self.fail(f"/diagnostics: {str(status.name)[:200]} is ERROR: {str(status.message)[:300]}")
                return

    def run(self, stop: threading.Event) -> None:
        """Ask for the node's state every ``poll_s``; fail when it is not active or does not answer."""
        lifecycle = self.node_lifecycle
        if lifecycle is None or not lifecycle.lifecycle:
            return
        poll_s = float(self.params.get("poll_s", 0.5))
        while not stop.wait(poll_s):
            try:
                state, label = lifecycle.state()
            except Exception as exc:  # (a call cut short by teardown closing the clients, too)
                if not stop.is_set():
                    self.fail(f"{lifecycle.name} vanished: {exc}" if isinstance(exc, DyKnowError) else f"{lifecycle.name}: {exc!r}")
                return
            if state != 3 and not stop.is_set():
                self.fail(f"{lifecycle.name} is {label}, not active")
                return

    def teardown(self) -> None:
        """Unsubscribe, then deactivate the node if it is active (never destroy it)."""
        self._unsubscribe()
        super().teardown()
        self._leave()

    def _unsubscribe(self) -> None:
        subscriptions, self._subscriptions = self._subscriptions, []
        for subscription in subscriptions:
            subscription.close()

    def _leave(self) -> None:
        lifecycle, self.node_lifecycle = self.node_lifecycle, None
        if lifecycle is None:
            return
        with _HOLDERS_LOCK:
            holders = _HOLDERS.get(self._held, (lifecycle, set()))[1]
            holders.discard(self.name)
            others = sorted(holders)
            if not holders:
                _HOLDERS.pop(self._held, None)
        if others:
            self.log.info("%s stays as it is: units %s still use it", lifecycle.name, ", ".join(others[:10]))
            return
        try:
            lifecycle.timeout_s = min(lifecycle.timeout_s, _TEARDOWN_TIMEOUT_S)
            if lifecycle.bring_down():
                self.log.info("%s deactivated", lifecycle.name)
        except DyKnowError as exc:
            self.log.warning("could not deactivate %s: %s", lifecycle.name, exc)
        finally:
            lifecycle.close()

