"""The manager's ROS 2 side: its node, its DDS participant, and the companions of ports bound to ROS 2.

A binding ``ros2:/TOPIC?...`` (:mod:`dyknow.ros2.binding`) wires a unit's port to a ROS 2 topic
through a companion unit ``<name>.<port>.ros2`` (a :class:`~dyknow.ros2.bridge.Ros2Source` or
:class:`~dyknow.ros2.bridge.Ros2Sink`), spawned after the unit and destroyed with it.
"""

from __future__ import annotations

import contextlib
import os
import re
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import replace
from typing import Any

from dyknow import keys
from dyknow.errors import BindingError, DyKnowError, did_you_mean
from dyknow.library import Library
from dyknow.manager.spawning import Spawner
from dyknow.model import UnitInfo
from dyknow.ros2.binding import is_ros2, parse_binding
from dyknow.ros2.dds import DdsNode
from dyknow.ros2.node import Ros2Node
from dyknow.security import Limits
from dyknow.spec import TransformationSpec
from dyknow.spec.model import Param, Port
from dyknow.transport import Session

__all__ = ["Ros2Wiring", "ros2_bindings"]

#: A port's companion: its name, its spec, the key the port binds to, and the ``ros2:`` binding.
Companion = tuple[str, TransformationSpec, str, str]


def ros2_bindings(bindings: Mapping[str, str]) -> dict[str, str]:
    """The bindings of ``bindings`` to ROS 2 topics (port -> ``ros2:`` binding)."""
    return {port: key for port, key in bindings.items() if is_ros2(key)}


class Ros2Wiring:
    """The ROS 2 node and DDS participant of manager ``manager`` (each made on first use), and the
    companion units it spawns and destroys through ``spawner`` (of specs of ``library``).

    ``options``: the ROS domain (None: ``ROS_DOMAIN_ID``, else 0), the node's name (None: the
    manager's) and its namespace; ``dds_config``: the participant's Cyclone XML. It shares the
    manager's ``lock``; ``check_open`` raises when the manager is closed.
    """

    def __init__(
        self,
        manager: str,
        *,
        session: Session,
        limits: Limits,
        lock: threading.RLock,
        check_open: Callable[[], None],
        spawner: Spawner,
        library: Library,
        options: tuple[int | None, str | None, str],
        dds_config: str | None,
    ) -> None:
        self._manager = manager
        self._session = session
        self._limits = limits
        self._lock = lock
        self._check_open = check_open
        self._spawner = spawner
        self._library = library
        self._options = options
        self._dds_config = dds_config
        self._ros2: Ros2Node | None = None
        self._dds: DdsNode | None = None
        # ports bound to ros2: topics are wired through a companion unit each: (unit, port) -> (companion, binding)
        self._ports: dict[tuple[str, str], tuple[str, str]] = {}

    def _domain(self) -> int:
        domain = self._options[0]
        if domain is None:
            text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
            if not text.isdigit():
                raise BindingError(f"ROS_DOMAIN_ID={text!r}", where=f"manager {self._manager!r}", expected="a number from 0 to 232")
            domain = int(text)
        return domain

    def node_name(self) -> str:
        """The name of the manager's ROS 2 node: the one given, else the manager's with every
        character a ROS 2 name may not hold as ``_`` (and ``_`` before a leading digit)."""
        name = self._options[1] or re.sub(r"[^A-Za-z0-9_]", "_", self._manager)
        return "_" + name if name[0].isdigit() else name

    def ros2_node(self) -> Ros2Node:
        """The manager's ROS 2 node (see :meth:`dyknow.manager.Manager.ros2_node`)."""
        with self._lock:
            self._check_open()
            if self._ros2 is None:
                self._ros2 = Ros2Node(
                    self._session, self.node_name(), namespace=self._options[2], domain=self._domain(), max_message_bytes=self._limits.max_ros2_message_bytes
                )
            return self._ros2

    def dds_node(self) -> DdsNode:
        """The manager's DDS participant (see :meth:`dyknow.manager.Manager.dds_node`)."""
        with self._lock:
            self._check_open()
            if self._dds is None:
                self._dds = DdsNode(
                    domain=self._domain(),
                    config=self._dds_config,
                    types=self.ros2_node().types if self._ros2 else None,
                    max_message_bytes=self._limits.max_ros2_message_bytes,
                )
            return self._dds

    def close(self) -> None:
        """Close the node and the participant that were made."""
        if self._ros2 is not None:
            self._ros2.close()
        if self._dds is not None:
            self._dds.close()

    # ------------------------------------------------------------------ companions

    def spawn(
        self,
        label: str | TransformationSpec,
        name: str,
        *,
        protected: bool,
        params: Mapping[str, Any] | None,
        bindings: Mapping[str, str],
        ros2: Mapping[str, str],
        remote: bool,
        account: str | None = None,
    ) -> UnitInfo:
        """Spawn a unit with its ports ``ros2`` (port -> ``ros2:`` binding, among ``bindings``)
        wired through companions, spawned after it; if one cannot start, the unit is destroyed
        again and the error raised. ``account``: as :meth:`dyknow.manager.spawning.Spawner.spawn` takes it."""
        spec = label if isinstance(label, TransformationSpec) else self._library.get(label)
        plan = self.plan(spec, name, ros2)
        plain = {port: key for port, key in bindings.items() if port not in ros2}
        plain.update((port, key) for port, (_, _, key, _) in plan.items())
        info = self._spawner.spawn(label, name, protected=protected, params=params, bindings=plain, remote=remote, account=account)
        try:
            self.start(name, plan)
        except BaseException:
            with contextlib.suppress(DyKnowError):
                self._spawner.destroy(name, force=True)
            raise
        return replace(info, bindings=self.shown(name, info.bindings))

    def rewire(self, name: str, spec: TransformationSpec, bindings: Mapping[str, str], ros2: Mapping[str, str], wired: Iterable[str]) -> dict[str, str]:
        """Swap the companions of unit ``name`` for a rebinding to ``bindings``: those of its
        ``wired`` ports go, those of its ports bound to ROS 2 (``ros2``) start; returns the
        bindings its proxy takes (a port rewired to or from ROS 2 is not switched atomically)."""
        plan = self.plan(spec, name, ros2)
        self.drop(name, wired)
        self.start(name, plan)
        plain = {port: key for port, key in bindings.items() if port not in ros2}
        plain.update((port, key) for port, (_, _, key, _) in plan.items())
        return plain

    def plan(self, spec: TransformationSpec, name: str, ros2: Mapping[str, str]) -> dict[str, Companion]:
        """Port -> (companion name, companion spec, the key the port binds to, the binding), checked."""
        ports = {p.name: p for p in spec.ports}
        plan = {}
        for port, text in ros2.items():
            where = f"port {port!r} of unit {name!r}"
            if port not in ports:
                raise BindingError(
                    f"no port {port!r}",
                    where=f"transformation {spec.label!r}",
                    expected=f"one of {', '.join(ports)}{did_you_mean(port, ports)}",
                )
            binding = parse_binding(text, where=where)
            output = ports[port].direction == "out"
            if binding.ros_type is None and output:
                raise BindingError(f"{text!r} names no type", where=where, expected=f"ros2:{binding.topic}?type=pkg/msg/Type for an output")
            if binding.ros_type is not None:
                (self.dds_node() if binding.dds else self.ros2_node()).types.check(binding.ros_type, where=where)
            companion = keys.check_name(f"{name}.{port}.ros2", "companion unit name")
            cspec = _ROS2_SINK if output else _ROS2_SOURCE
            key = keys.default_key(self._manager, companion, "in" if output else "out")
            plan[port] = (companion, cspec, key, binding.uri())
        return plan

    def start(self, name: str, plan: Mapping[str, Companion]) -> None:
        """Spawn the companions of ``plan`` for unit ``name``."""
        for port, (companion, cspec, _key, uri) in plan.items():
            info = self._spawner.spawn(cspec, companion, params={"binding": uri})
            if info.state == "failed":
                with contextlib.suppress(DyKnowError):
                    self._spawner.destroy(companion, force=True)
                raise BindingError(f"{uri}: {info.error}", where=f"port {port!r} of unit {name!r}")
            with self._lock:
                self._ports[(name, port)] = (companion, uri)

    def drop(self, name: str, ports: Iterable[str] | None = None) -> None:
        """Destroy the companions of unit ``name`` (of its ``ports``; None: all of them)."""
        with self._lock:
            gone = [(k, v[0]) for k, v in self._ports.items() if k[0] == name and (ports is None or k[1] in ports)]
            for k, _ in gone:
                del self._ports[k]
        for _, companion in gone:
            with contextlib.suppress(DyKnowError):
                self._spawner.destroy(companion, force=True)

    def wired(self, name: str, bindings: Mapping[str, str]) -> list[str]:
        """The ports among ``bindings`` that unit ``name`` has wired to ROS 2 now."""
        with self._lock:
            return [port for port in bindings if (name, port) in self._ports]

    def any(self) -> bool:
        """Whether a port of some unit is wired to ROS 2."""
        return bool(self._ports)

    def shown(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """``bindings`` with each port wired to ROS 2 shown as its ``ros2:`` binding."""
        with self._lock:
            return {port: self._ports.get((name, port), (None, key))[1] for port, key in bindings.items()}


_ROS2_BINDING = (Param("binding", "string", ""),)
_ROS2_SOURCE = TransformationSpec(
    "ros2-source", "dyknow.ros2.bridge:Ros2Source", _ROS2_BINDING, (Port("out", "out"),), description="a ROS 2 topic as a dyknow stream"
)
_ROS2_SINK = TransformationSpec(
    "ros2-sink", "dyknow.ros2.bridge:Ros2Sink", _ROS2_BINDING, (Port("in", "in"),), description="a dyknow stream as a ROS 2 topic"
)
