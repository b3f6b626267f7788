"""The ROS 2 graph as rmw_zenoh's liveliness tokens show it: nodes, topics, types, endpoints.

:class:`Graph` watches ``@ros2_lv/<domain>/**`` and keeps one :class:`~dyknow.ros2.names.Entity`
per token up; tokens that do not parse are counted in ``malformed`` and ignored. Tokens come from
the network, and anyone on it may declare them under any session id, so what is kept is bounded:
at most :data:`MAX_ENTITIES` in all and :data:`MAX_SESSION_ENTITIES` per session id the tokens
name (more are counted in ``overflow``). :func:`snapshot` asks once.

:class:`PublisherWatch` watches the publishers of one topic (of one type, when given) and nothing
else: tokens of other topics never reach it, so a flood of them cannot crowd out the topic's
publishers. It keeps at most :data:`MAX_TOPIC_PUBLISHERS`; the tokens it had to leave out are
not forgotten: when the last publisher it kept goes while some were left out, it asks the network
which are still up before it says the topic has none.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from dyknow.errors import BindingError, DyKnowError
from dyknow.ros2.names import ADMIN_SPACE, Entity, EntityKind, parse_token, publisher_pattern
from dyknow.transport import Session

__all__ = ["Graph", "GraphView", "PublisherWatch", "snapshot"]

log = logging.getLogger(__name__)

#: The most entities a graph keeps.
MAX_ENTITIES = 10_000
#: The most entities a graph keeps of one session id (as the tokens name it): an rmw_zenoh
#: process has one session, and a few hundred entities at most.
MAX_SESSION_ENTITIES = 1_000
#: The most publishers a :class:`PublisherWatch` keeps of its topic.
MAX_TOPIC_PUBLISHERS = 1_000
_RECOUNT_S = 2.0  # how long a recount of a topic's publishers waits for the answers


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

    def services(self) -> dict[str, dict[str, object]]:
        """Service -> ``{"types": [...], "servers": N, "clients": N}`` (their ``SS``/``SC`` tokens)."""
        found: dict[str, dict[str, object]] = {}
        for e in self.entities:
            if e.kind in (EntityKind.SERVICE, EntityKind.CLIENT) and e.topic is not None and e.ros_type is not None:
                entry = found.setdefault(e.topic, {"types": set(), "servers": 0, "clients": 0})
                entry["types"].add(e.ros_type)  # type: ignore[attr-defined]
                role = "servers" if e.kind is EntityKind.SERVICE else "clients"
                entry[role] = int(entry[role]) + 1  # type: ignore[call-overload]
        return {name: {**entry, "types": sorted(entry["types"])} for name, entry in sorted(found.items())}  # type: ignore[call-overload]

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
        return {"nodes": self.nodes(), "topics": self.topics(), "services": self.services(), "endpoints": endpoints}


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
        self.overflow = 0  # tokens left out: over MAX_ENTITIES, or over MAX_SESSION_ENTITIES of one session id
        self._entities: dict[str, Entity] = {}
        self._per_session: dict[str, int] = {}
        self._lock = threading.Lock()
        self._on_change = on_change
        self._sub = session.declare_liveliness_subscriber(f"{ADMIN_SPACE}/{self.domain}/**", self._changed)

    def _changed(self, key: str, alive: bool) -> None:
        with self._lock:
            entity = self._entities.pop(key, None) if not alive else None
            if entity is not None:
                left = self._per_session[entity.session_id] - 1
                if left:
                    self._per_session[entity.session_id] = left
                else:
                    del self._per_session[entity.session_id]
            if alive:
                if key in self._entities:
                    return
                if len(self._entities) >= MAX_ENTITIES:
                    self.overflow += 1
                    return
                try:
                    entity = parse_token(key)
                except BindingError as exc:
                    self.malformed += 1
                    log.debug("ignoring token %s: %s", key[:200], exc)
                    return
                held = self._per_session.get(entity.session_id, 0)
                if held >= MAX_SESSION_ENTITIES:
                    self.overflow += 1
                    return
                self._per_session[entity.session_id] = held + 1
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


class PublisherWatch:
    """The publishers of ``topic`` (of ``ros_type`` with ``type_hash`` when given) as their tokens
    come and go: ``on_change(entity, alive)`` for each change, those up now first (on a Zenoh
    thread). Bounded as the module documentation says: ``overflow`` counts the tokens left out,
    ``malformed`` those that did not parse. A context manager; ``close()`` is safe twice."""

    def __init__(
        self,
        session: Session,
        domain: int,
        topic: str,
        on_change: Callable[[Entity, bool], None],
        *,
        ros_type: str | None = None,
        type_hash: str | None = None,
    ) -> None:
        self.topic = topic
        self.key = publisher_pattern(domain, topic, ros_type, type_hash)
        self.malformed = 0
        self.overflow = 0
        self._entities: dict[str, Entity] = {}
        self._left_out = False  # tokens were left out since the last recount
        self._recounting = False
        self._gone_meanwhile: set[str] = set()  # tokens that went while a recount was asked (bounded)
        self._lock = threading.Lock()
        self._session = session
        self._on_change = on_change
        self._closed = False
        self._sub = session.declare_liveliness_subscriber(self.key, self._changed)

    def _parse(self, key: str) -> Entity | None:
        try:
            entity = parse_token(key)
        except BindingError as exc:
            self.malformed += 1
            log.debug("ignoring token %s: %s", key[:200], exc)
            return None
        # the key expression chose the topic and the kind; a token whose chunks only look so is not one
        return entity if entity.kind is EntityKind.PUBLISHER and entity.topic == self.topic else None

    def _changed(self, key: str, alive: bool) -> None:
        if alive:
            with self._lock:
                if self._closed or key in self._entities:
                    return
                if len(self._entities) >= MAX_TOPIC_PUBLISHERS:
                    self.overflow += 1
                    self._left_out = True
                    return
                entity = self._parse(key)
                if entity is None:
                    return
                self._entities[key] = entity
            self._on_change(entity, True)
            return
        with self._lock:
            gone = self._entities.pop(key, None)
            if gone is None:
                if self._recounting and len(self._gone_meanwhile) < MAX_TOPIC_PUBLISHERS:
                    self._gone_meanwhile.add(key)
                return
            recount = self._left_out and not self._entities and not self._closed and not self._recounting
            if recount:
                self._left_out = False
                self._recounting = True
        if not recount:
            self._on_change(gone, False)
            return
        # the last one kept went, but some were left out: ask which are up before saying none is
        log.info("the last publisher kept of %s went while %d were left out: asking which are up", self.topic, self.overflow)
        try:
            self._session.ask_alive(
                self.key, timeout_s=_RECOUNT_S, limit=MAX_TOPIC_PUBLISHERS, done=lambda keys, count: self._recounted(gone, keys, count)
            )
        except DyKnowError as exc:
            log.warning("cannot recount the publishers of %s: %s", self.topic, exc)
            self._recounted(gone, [], 0)

    def _recounted(self, gone: Entity, keys: list[str], count: int) -> None:
        added: list[Entity] = []
        with self._lock:
            self._recounting = False
            meanwhile, self._gone_meanwhile = self._gone_meanwhile, set()
            if self._closed:
                return
            for key in keys:
                if key in self._entities or key in meanwhile:
                    continue
                if len(self._entities) >= MAX_TOPIC_PUBLISHERS:
                    self._left_out = True
                    break
                entity = self._parse(key)
                if entity is not None and entity != gone:
                    self._entities[key] = entity
                    added.append(entity)
            if count > len(keys):
                self._left_out = True
        for entity in added:  # first the ones still up, then the one that went: never "none" between
            self._on_change(entity, True)
        self._on_change(gone, False)

    def view(self) -> list[Entity]:
        """The publishers kept now."""
        with self._lock:
            return list(self._entities.values())

    def close(self) -> None:
        """Stop watching; safe twice."""
        with self._lock:
            self._closed = True
        self._sub.undeclare()

    def __enter__(self) -> PublisherWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
