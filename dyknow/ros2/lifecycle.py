"""The lifecycle and parameters of a ROS 2 node dyknow did not spawn, driven through the node's services.

A ROS 2 lifecycle node (``rclcpp_lifecycle``, ``rclpy.lifecycle``) serves ``<node>/get_state``
(``lifecycle_msgs/srv/GetState``) and ``<node>/change_state`` (``lifecycle_msgs/srv/ChangeState``);
every node serves ``<node>/set_parameters`` (``rcl_interfaces/srv/SetParameters``). A
:class:`NodeLifecycle` calls them, over rmw_zenoh (a :class:`~dyknow.ros2.node.Ros2Node`) or DDS
(a :class:`~dyknow.ros2.dds.DdsNode`), the way ``ros2 lifecycle set`` and ``ros2 param set`` do:

- :meth:`NodeLifecycle.bring_up` sets the parameters, then configures the node if it is
  unconfigured and activates it if it is inactive. What it cannot do raises
  :class:`~dyknow.errors.ServiceError` saying why: a node whose services never answer (naming the
  node and the time waited), a transition the node refuses (naming the state it is in), a
  parameter the node refuses (with the node's reason, such as a wrong type). A node it configured
  and could not activate is cleaned up again (back to unconfigured), so nothing is left
  half-done but the parameters it set, which the error lists.
- :meth:`NodeLifecycle.bring_down` deactivates an active node; it never cleans it up or shuts it
  down (the node stays inactive, ready to be activated again).
- :meth:`NodeLifecycle.state` reads the node's state (its id and label).

The primary states are ``unconfigured`` (1), ``inactive`` (2), ``active`` (3) and ``finalized``
(4); a node in transition is in ``configuring`` (10) ... ``errorprocessing`` (15): see
:data:`STATES`. A node that is not a lifecycle node (``lifecycle=False``) only gets its parameters.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from typing import Any, Protocol

from dyknow.errors import BindingError, ClosedError, DyKnowError, ServiceError
from dyknow.ros2.dds import DdsClient, DdsNode
from dyknow.ros2.names import check_topic
from dyknow.ros2.node import Ros2Node
from dyknow.ros2.services import READ_ONLY_SERVICES, RESEND_S
from dyknow.spec.modefile import ParameterValue

__all__ = ["ACTIVATE", "CLEANUP", "CONFIGURE", "DEACTIVATE", "STATES", "NodeLifecycle", "ParameterValue", "parameter", "parameter_value"]

log = logging.getLogger(__name__)

GET_STATE = "lifecycle_msgs/srv/GetState"
CHANGE_STATE = "lifecycle_msgs/srv/ChangeState"
SET_PARAMETERS = "rcl_interfaces/srv/SetParameters"
GET_PARAMETERS = "rcl_interfaces/srv/GetParameters"

#: The transitions dyknow asks for (``lifecycle_msgs/msg/Transition``'s ids).
CONFIGURE, CLEANUP, ACTIVATE, DEACTIVATE = 1, 2, 3, 4
_TRANSITIONS = {CONFIGURE: "configure", CLEANUP: "cleanup", ACTIVATE: "activate", DEACTIVATE: "deactivate"}

STATES: Mapping[int, str] = {
    0: "unknown",
    1: "unconfigured",
    2: "inactive",
    3: "active",
    4: "finalized",
    10: "configuring",
    11: "cleaningup",
    12: "shuttingdown",
    13: "activating",
    14: "deactivating",
    15: "errorprocessing",
}
"""``lifecycle_msgs/msg/State``'s ids and labels."""


class _Client(Protocol):
    """A service client: :class:`~dyknow.ros2.services.Ros2Client` or :class:`~dyknow.ros2.dds.DdsClient`."""

    def call(self, request: Any, timeout_s: float = 5.0) -> Any:
        """Send ``request`` and return the response."""
        ...

    def close(self) -> None:
        """Close the client."""
        ...


# rcl_interfaces/msg/ParameterType: the type id and ParameterValue field of each kind of value
_SCALARS = ((bool, 1, "bool_value"), (int, 2, "integer_value"), (float, 3, "double_value"), (str, 4, "string_value"))
_ARRAYS = ((bool, 6, "bool_array_value"), (int, 7, "integer_array_value"), (float, 8, "double_array_value"), (str, 9, "string_array_value"))


def parameter(name: str, value: ParameterValue) -> dict[str, Any]:
    """``rcl_interfaces/msg/Parameter``'s fields for ``name = value`` (a bool, integer, double or
    string, or a tuple or list of one of them)."""
    for kind, type_id, value_field in _SCALARS:
        if type(value) is kind:
            return {"name": name, "value": {"type": type_id, value_field: value}}
    if isinstance(value, (tuple, list)) and value:
        for kind, type_id, value_field in _ARRAYS:
            if all(type(v) is kind for v in value):
                return {"name": name, "value": {"type": type_id, value_field: list(value)}}
    raise BindingError(f"a {type(value).__name__} for parameter {name!r}", where="ROS 2 parameter", expected="a bool, int, float or str, or a list of one of them")


def parameter_value(value: Any) -> ParameterValue | None:
    """The Python value of a ``rcl_interfaces/msg/ParameterValue`` (None when it is not set or a byte array)."""
    type_id = int(getattr(value, "type", 0))
    for _, kind_id, value_field in _SCALARS:
        if type_id == kind_id:
            return getattr(value, value_field)  # type: ignore[no-any-return]
    for kind, kind_id, value_field in _ARRAYS:
        if type_id == kind_id:
            return tuple(kind(v) for v in getattr(value, value_field))  # type: ignore[return-value]
    return None


class NodeLifecycle:
    """Drives the ROS 2 node ``name`` (``/camera_top``, ``/robot/camera``) through its services on
    ``node`` (the manager's rmw_zenoh node or DDS participant); each call waits up to
    ``timeout_s``. ``lifecycle``: whether it is a lifecycle node. A context manager; ``close()``
    closes the clients (safe twice), never the node."""

    def __init__(self, node: Ros2Node | DdsNode, name: str, *, lifecycle: bool = True, timeout_s: float = 5.0) -> None:
        self.name = check_topic(name, "ROS 2 node name")
        if not 0 < timeout_s <= 3600:
            raise BindingError(f"timeout {timeout_s} s", where=f"ROS 2 node {self.name}", expected="from 0 to 3600 s")
        self.lifecycle = lifecycle
        self.timeout_s = timeout_s
        self.where = f"ROS 2 node {self.name}" + (" over DDS" if isinstance(node, DdsNode) else "")
        self._node = node
        self._clients: dict[str, _Client] = {}
        self._lock = threading.Lock()
        self._closed = False

    def _client(self, suffix: str, srv_type: str) -> _Client:
        with self._lock:
            if self._closed:
                raise ClosedError("the lifecycle client is closed", where=self.where, expected="a new NodeLifecycle")
            client = self._clients.get(suffix)
            if client is None:
                service = f"{self.name}/{suffix}"
                made: _Client = self._node.create_client(service, srv_type)
                client = self._clients[suffix] = made
            return client

    def _call(self, suffix: str, srv_type: str, request: dict[str, Any], timeout_s: float | None) -> Any:
        try:
            client = self._client(suffix, srv_type)
            if isinstance(client, DdsClient) and srv_type in READ_ONLY_SERVICES:  # (a lost answer asked again)
                return client.call(request, timeout_s=timeout_s or self.timeout_s, resend_s=RESEND_S)
            return client.call(request, timeout_s=timeout_s or self.timeout_s)
        except ServiceError as exc:
            silent = "no answer" in exc.what
            raise ServiceError(
                f"{self.name}/{suffix}: {exc.what}" + (": the node does not answer, or does not exist" if silent else ""),
                where=self.where,
                expected=f"a running node {self.name} serving {self.name}/{suffix}" if silent else exc.expected,
            ) from exc

    def prepare(self) -> None:
        """Make every service client now (each finds its server in the background), so the first
        transition or parameter set later does not wait for discovery (a DDS client's is tens to
        hundreds of milliseconds)."""
        self._client("get_state", GET_STATE)
        if self.lifecycle:
            self._client("change_state", CHANGE_STATE)
        self._client("set_parameters", SET_PARAMETERS)
        self._client("get_parameters", GET_PARAMETERS)

    def state(self, timeout_s: float | None = None) -> tuple[int, str]:
        """The node's state: its id and label (``(3, "active")``)."""
        state = self._call("get_state", GET_STATE, {}, timeout_s).current_state
        return int(state.id), str(state.label) or STATES.get(int(state.id), "unknown")

    def change(self, transition: int) -> None:
        """Ask for ``transition`` (:data:`CONFIGURE`, :data:`ACTIVATE`, ...); a refusal raises
        :class:`~dyknow.errors.ServiceError` naming the state the node is in afterwards."""
        name = _TRANSITIONS.get(transition, str(transition))
        answer = self._call("change_state", CHANGE_STATE, {"transition": {"id": transition}}, None)
        if not answer.success:
            try:
                _, label = self.state()
            except ServiceError:
                label = "unknown (get_state does not answer)"
            raise ServiceError(f"the node refused the transition {name!r}; it is {label}", where=self.where, expected=_expected(label, name))

    def get_parameters(self, names: list[str]) -> dict[str, ParameterValue | None]:
        """The values of parameters ``names`` (None for one that is not set)."""
        if not names:
            return {}
        answer = self._call("get_parameters", GET_PARAMETERS, {"names": list(names)}, None)
        values = list(answer.values)
        if len(values) != len(names):
            raise ServiceError(f"the node answered {len(values)} values for {len(names)} parameters", where=self.where)
        return {name: parameter_value(value) for name, value in zip(names, values, strict=True)}

    def set_parameters(self, values: Mapping[str, ParameterValue]) -> None:
        """Set ``values`` (name -> value), each on its own as ``ros2 param set`` does; a parameter
        the node refuses raises :class:`~dyknow.errors.ServiceError` with the node's reason,
        naming those that were set."""
        if not values:
            return
        params = [parameter(name, value) for name, value in values.items()]
        answer = self._call("set_parameters", SET_PARAMETERS, {"parameters": params}, None)
        results = list(zip(values, answer.results, strict=False))
        done = [name for name, result in results if result.successful]
        for name, result in results:
            if not result.successful:
                raise ServiceError(
                    f"the node refused the parameter {name}={values[name]!r}: {str(result.reason)[:300] or 'no reason given'}",
                    where=self.where,
                    expected="a parameter the node declares, of its type" + (f" (these were set: {', '.join(done)})" if done else ""),
                )
        if len(results) < len(values):
            raise ServiceError(f"the node answered {len(results)} results for {len(values)} parameters", where=self.where)

    def bring_up(self, parameters: Mapping[str, ParameterValue] | None = None) -> list[str]:
        """Set ``parameters``, then configure (if unconfigured) and activate (if inactive) the
        node; returns what was done (``["set 2 parameter(s)", "configure", "activate"]``). On a
        failure after configuring, the node is cleaned up again (see the module's docs)."""
        done: list[str] = []
        if parameters:
            self.set_parameters(parameters)
            done.append(f"set {len(parameters)} parameter(s)")
        if not self.lifecycle:
            return done
        state, label = self.state()
        if state == 3:
            return done
        if state not in (1, 2):
            raise ServiceError(f"the node is {label}", where=self.where, expected=_expected(label, "activate"))
        configured = False
        if state == 1:
            self.change(CONFIGURE)
            configured = True
            done.append("configure")
        try:
            self.change(ACTIVATE)
        except DyKnowError as exc:
            if not configured:
                raise
            try:
                self.change(CLEANUP)
            except DyKnowError as undo:
                raise ServiceError(
                    f"{exc.what}; configured it, and the cleanup back to unconfigured failed too: {undo.what}",
                    where=self.where,
                    expected=exc.expected,
                ) from exc
            raise ServiceError(f"{exc.what}; the configure before it was undone (cleaned up: unconfigured again)", where=self.where, expected=exc.expected) from exc
        done.append("activate")
        return done

    def bring_down(self) -> bool:
        """Deactivate the node if it is active (never clean it up nor shut it down); whether it was."""
        if not self.lifecycle:
            return False
        state, _ = self.state()
        if state != 3:
            return False
        self.change(DEACTIVATE)
        return True

    def close(self) -> None:
        """Close the service clients; safe twice."""
        with self._lock:
            self._closed = True
            clients, self._clients = list(self._clients.values()), {}
        for client in clients:
            client.close()

    def __enter__(self) -> NodeLifecycle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _expected(label: str, transition: str) -> str:
    if transition == "activate":
        return {
            "unconfigured": "configure before activate (ROS 2 activates only an inactive node)",
            "finalized": "a node that is not finalized (a finalized node must be restarted)",
            "errorprocessing": "a node that recovered from its error (it is in ErrorProcessing)",
            "inactive": "a node whose activation succeeds (its on_activate failed: its log says why)",
        }.get(label, "a node that is unconfigured, inactive or active")
    return f"a node in a state from which {transition!r} is allowed"
