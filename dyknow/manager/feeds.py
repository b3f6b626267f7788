"""Measures fed from streams: a measurement taken from a ROS 2 topic or a Zenoh key as it arrives.

``Manager.measure_from("visibility", "ros2dds:/water_visibility?type=std_msgs/msg/Float64#data")``
(``dyknow manager --measure-from NAME=SOURCE[#FIELD]``) makes every sample of SOURCE the latest
value of measure NAME, which the specs' constraints read (:mod:`dyknow.manager.measurements`).
SOURCE is a ``ros2:`` or ``ros2dds:`` topic (:mod:`dyknow.ros2.binding`) or a Zenoh key: a dyknow
stream's (a unit's output, of this manager or another, such as a
:class:`~dyknow.ros2.diagnostics.DiagnosticsSource`'s status of one node) or one whose samples are
JSON (:func:`~dyknow.reasoning.bindings.sample_value`). The manager reads it as any input: a unit
``feed.NAME`` (:class:`FeedUnit`) whose port ``in`` is bound to SOURCE, bounded as every input is
(the ROS 2 companion's ``max_bytes``, the manager's message limit); ``#FIELD`` is a dotted path
into each sample (``#pose.position.z``, ``#value``), the whole sample without it. A number or
text is the measurement; a bool is 1 or 0; anything else is refused (logged once per feed, counted).

A sample is recorded at once when it changes whether a constraint on the measure holds (with or
without its margin), else at most once per :data:`REFRESH_S`: a topic at 1 kHz costs the
adaptation loop nothing between crossings, and a crossing is taken as soon as it arrives.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from dyknow import keys
from dyknow.errors import BindingError, DyKnowError
from dyknow.message import Message
from dyknow.reasoning.bindings import check_source, is_ros2_source, sample_value
from dyknow.spec.model import Constraint, Port, TransformationSpec
from dyknow.unit import Unit

__all__ = ["FEED_SPEC", "REFRESH_S", "FeedUnit", "MeasureFeeds", "parse_feed"]

log = logging.getLogger("dyknow.manager")

#: How often a sample that changes no constraint's verdict is recorded anyway.
REFRESH_S = 1.0
_MAX_FIELD = 300


class FeedUnit(Unit):
    """The unit of a measure's feed: hands each message of its input ``in`` to ``feed``."""

    feed: Callable[[Any], None] | None = None

    def on_message(self, port: str, msg: Message) -> None:
        """Hand the message's payload on."""
        feed = self.feed
        if feed is not None:
            feed(msg.payload)


FEED_SPEC = TransformationSpec("measure-feed", "dyknow.manager.feeds:FeedUnit", (), (Port("in", "in"),), description="feeds a measure from a stream")
"""The spec of a :class:`FeedUnit` (spawned by the manager, not in its library)."""


def parse_feed(name: str, text: str) -> tuple[str, tuple[str, ...]]:
    """``SOURCE[#FIELD]`` of measure ``name``: the checked source and the field path."""
    keys.check_name(name, "measurement name")
    where = f"measure {name!r} from {text[:300]!r}"
    source, _, field = text.partition("#")
    path = tuple(field.split(".")) if field else ()
    if len(field) > _MAX_FIELD or any(not part.isidentifier() for part in path):
        raise BindingError(f"the field {field[:100]!r}", where=where, expected="a dotted path of field names, such as #data or #pose.position.z")
    if not is_ros2_source(source) and ("*" in source or "$" in source):
        raise BindingError(f"the key expression {source[:200]!r} has wildcards", where=where, expected="one key: a measure has one value at a time")
    return check_source(source, where), path


@dataclass
class _Feed:
    name: str
    source: str
    path: tuple[str, ...]
    close: Callable[[], None]
    last: tuple[bool, ...] | None = None
    last_ns: int = 0
    refused: int = 0


class MeasureFeeds:
    """The measures a manager takes from streams. ``record(name, value)`` records a measurement;
    ``constraints(name)`` are the library's constraints on a measure; a Zenoh key is read on
    ``session``, a ROS 2 topic on ``ros2``'s node or participant. A context manager."""

    def __init__(
        self,
        *,
        record: Callable[[str, float | str], None],
        constraints: Callable[[str], Iterable[Constraint]],
        spawn: Callable[[TransformationSpec, str, Mapping[str, str]], object],
        unit: Callable[[str], object],
        destroy: Callable[[str], None],
    ) -> None:
        self._record = record
        self._constraints = constraints
        self._spawn = spawn
        self._unit = unit
        self._destroy = destroy
        self._feeds: dict[str, _Feed] = {}
        self._lock = threading.Lock()

    def add(self, name: str, text: str) -> None:
        """Feed measure ``name`` from ``SOURCE[#FIELD]`` (replacing an earlier feed of it)."""
        source, path = parse_feed(name, text)
        feed = _Feed(name, source, path, lambda: None)
        with self._lock:
            old = self._feeds.pop(name, None)
        if old is not None:  # (its unit's name is the new one's)
            old.close()
        feed.close = self._subscribe(name, source, lambda sample: self._sample(feed, sample))
        with self._lock:
            self._feeds[name] = feed
        log.info("measure %s from %s%s", name, source, "#" + ".".join(path) if path else "")

    def _subscribe(self, name: str, source: str, on_sample: Callable[[Any], None]) -> Callable[[], None]:
        """A :class:`FeedUnit` named ``feed.NAME`` whose input is bound to ``source`` (the manager
        wires a ROS 2 topic through its companion, a key through its bus and Zenoh, so a unit of the
        same manager feeds it too); returns what destroys it."""
        unit_name = f"feed.{name}"
        self._spawn(FEED_SPEC, unit_name, {"in": source})
        unit = self._unit(unit_name)
        if isinstance(unit, FeedUnit):
            unit.feed = on_sample
        return lambda: self._destroy(unit_name)

    def feeds(self) -> dict[str, str]:
        """Each fed measure and its source."""
        with self._lock:
            return {f.name: f.source + ("#" + ".".join(f.path) if f.path else "") for f in self._feeds.values()}

    def remove(self, name: str) -> bool:
        """Stop feeding measure ``name``; whether it was fed."""
        with self._lock:
            feed = self._feeds.pop(name, None)
        if feed is not None:
            feed.close()
        return feed is not None

    def _sample(self, feed: _Feed, sample: Any) -> None:
        value = _value(sample_value(sample), feed.path)
        if value is None:
            feed.refused += 1
            if feed.refused == 1:
                log.warning("measure %s: a sample of %s gave no number or text at %s; such samples are ignored", feed.name, feed.source, ".".join(feed.path) or "the sample")
            return
        verdicts = tuple(v for c in self._constraints(feed.name) for v in (c.holds(value), c.holds(value, held=True)))
        now = time.monotonic_ns()
        if verdicts == feed.last and now - feed.last_ns < REFRESH_S * 1e9:
            return
        try:
            self._record(feed.name, value)
        except DyKnowError as exc:
            feed.refused += 1
            if feed.refused == 1:
                log.warning("measure %s from %s: %s", feed.name, feed.source, exc)
            return
        feed.last, feed.last_ns = verdicts, now

    def close(self) -> None:
        """Stop every feed (a unit the manager already destroyed is left as it is)."""
        with self._lock:
            feeds, self._feeds = list(self._feeds.values()), {}
        for feed in feeds:
            try:
                feed.close()
            except DyKnowError as exc:
                log.debug("feed of %s: %s", feed.name, exc)

    def __enter__(self) -> MeasureFeeds:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _value(sample: Any, path: tuple[str, ...]) -> float | int | str | None:
    for part in path:
        sample = sample.get(part) if isinstance(sample, dict) else getattr(sample, part, None)
        if sample is None:
            return None
    if isinstance(sample, bool):
        return int(sample)
    if isinstance(sample, (int, float, str)):
        return sample
    return None
