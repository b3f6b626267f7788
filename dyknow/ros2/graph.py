"""The ROS 2 graph as rmw_zenoh's liveliness tokens show it: nodes, topics, types, endpoints.

:class:`Graph` watches ``@ros2_lv/<domain>/**`` and keeps one :class:`~dyknow.ros2.names.Entity`
per token up; tokens that do not parse are counted in ``malformed`` and ignored. At most
``max_entities`` are kept (tokens come from the network). :func:`snapshot` asks once.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from dyknow.errors import BindingError
from dyknow.ros2.names import ADMIN_SPACE, Entity, EntityKind, parse_token
from dyknow.transport import Session

__all__ = ["Graph", "GraphView", "snapshot"]

log = logging.getLogger(__name__)

#: The most entities a graph keeps.
MAX_ENTITIES = 10_000


@dataclass(frozen=True, slots=True)
class GraphView:
    """What the graph holds at one moment."""

    entities: tuple[Entity, ...]

    def nodes(self) -> list[str]:
        """Fully qualified node names, sorted."""
        return sorted({e.node for e in self.entities if e.kind is EntityKind.NODE})

    def topics(self) -> dict[str, list[str]]:
        """Topic -> its types (sorted), for the topics with a publisher or subscription."""
        found: dict[str, set[str]] = {}
        for e in self.entities:
            if e.kind in (EntityKind.PUBLISHER, EntityKind.SUBSCRIPTION) and e.topic is not None and e.ros_type is not None:
                found.setdefault(e.topic, set()).add(e.ros_type)
        return {topic: sorted(types) for topic, types in sorted(found.items())}

    def publishers(self, topic: str) -> list[Entity]:
        """The publishers of ``topic``."""
        return [e for e in self.entities if e.kind is EntityKind.PUBLISHER and e.topic == topic]

    def to_dict(self) -> dict[str, object]:
        """The JSON form (``dyknow ros2 list --json``)."""
        endpoints = [
            {"kind": e.kind.name.lower(), "node": e.node, "topic": e.topic, "type": e.ros_type, "type_hash": e.type_hash}
            for e in self.entities
            if e.kind is not EntityKind.NODE
        ]
        return {"nodes": self.nodes(), "topics": self.topics(), "endpoints": endpoints}


def _parse(keys: Iterable[str], on_bad: Callable[[str, str], None]) -> dict[str, Entity]:
    found: dict[str, Entity] = {}
    for key in keys:
        try:
            found[key] = parse_token(key)
        except BindingError as exc:
            on_bad(key, str(exc))
    return found


def snapshot(session: Session, domain: int, *, timeout_s: float = 1.0) -> GraphView:
    """The graph of ``domain`` as the tokens up now show it."""
    keys = session.alive(f"{ADMIN_SPACE}/{int(domain)}/**", timeout_s=timeout_s)[:MAX_ENTITIES]
    found = _parse(keys, lambda key, why: log.debug("ignoring token %s: %s", key[:200], why))
    return GraphView(tuple(found.values()))


class Graph:
    """Watches the ROS 2 graph of ``domain``; ``on_change(entity, alive)`` for each change (on a
    Zenoh thread). A context manager; ``close()`` is safe twice."""

    def __init__(self, session: Session, domain: int, on_change: Callable[[Entity, bool], None] | None = None) -> None:
        self.domain = int(domain)
        self.malformed = 0
        self._entities: dict[str, Entity] = {}
        self._lock = threading.Lock()
        self._on_change = on_change
        self._sub = session.declare_liveliness_subscriber(f"{ADMIN_SPACE}/{self.domain}/**", self._changed)

    def _changed(self, key: str, alive: bool) -> None:
        with self._lock:
            entity = self._entities.pop(key, None) if not alive else None
            if alive:
                if len(self._entities) >= MAX_ENTITIES:
                    self.malformed += 1
                    return
                try:
                    entity = parse_token(key)
                except BindingError as exc:
                    self.malformed += 1
                    log.debug("ignoring token %s: %s", key[:200], exc)
                    return
                self._entities[key] = entity
        if entity is not None and self._on_change is not None:
            self._on_change(entity, alive)

    def view(self) -> GraphView:
        """The graph now."""
        with self._lock:
            return GraphView(tuple(self._entities.values()))

    def close(self) -> None:
        """Stop watching; safe twice."""
        self._sub.undeclare()

    def __enter__(self) -> Graph:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
