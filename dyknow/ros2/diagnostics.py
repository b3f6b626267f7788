"""ROS 2's ``/diagnostics`` both ways: statuses published as ``diagnostic_msgs/msg/DiagnosticArray``, and other nodes' statuses read as a dyknow stream.

**Publishing.** A :class:`DiagnosticStatus` is one ``diagnostic_msgs/msg/DiagnosticStatus``: its ``level``
(:data:`OK` 0, :data:`WARN` 1, :data:`ERROR` 2, :data:`STALE` 3), its ``name`` as ROS 2's
``diagnostic_updater`` names them (``<node name>: <what>``, so ``rqt_robot_monitor`` and
Foxglove group them under the node), ``hardware_id``, a short ``message`` and ``values``
(``diagnostic_msgs/msg/KeyValue``: strings). A :class:`DiagnosticsPublisher` publishes the
statuses a callable collects as one ``DiagnosticArray`` on ``/diagnostics`` (rmw_zenoh or DDS,
on the node or participant given), once a second as ``diagnostic_updater`` does, and at once
when a status's level or message changes (it looks every ``check_s``, and at once when told:
:meth:`DiagnosticsPublisher.notify`). A manager runs one when asked (``Manager(diagnostics="ros2")``,
``dyknow manager --diagnostics ros2``): see :mod:`dyknow.manager.health` for its statuses.

**Reading.** :class:`DiagnosticsSource` is a unit that reads ``/diagnostics`` (param
``binding``: ``ros2:/diagnostics``, the default, for rmw_zenoh, or ``ros2dds:/diagnostics`` for
DDS), keeps the statuses whose name matches the param ``status`` (the exact name, or a glob
such as ``thrusters: *``; default ``*``, every status) and publishes one message per status on
``out``::

    {"name": "thrusters: thruster_1", "level": 2, "level_name": "ERROR", "message": "no thrust",
     "hardware_id": "t1", "values": {"rpm": 0, "enabled": true, "mode": "auto"}}

its ``values`` read as numbers or booleans where they read so (``"12"``, ``"-0.5"``, ``"1e3"``,
``"true"``/``"False"``), else kept as text; its origin time is the array's ``header.stamp``
when set, else when the array was sent or arrived. A spec tags its output, so formulas read
it as any stream: ``always Health(thruster_1).level < 2``.

**Bounds.** Statuses come from the network: an array's first :data:`MAX_STATUSES` statuses are
read and the rest refused; a status whose name, message or hardware id is longer than
:data:`MAX_NAME_CHARS`, :data:`MAX_MESSAGE_CHARS` or :data:`MAX_NAME_CHARS`, with more than
:data:`MAX_VALUES` values, or a key or value longer than :data:`MAX_NAME_CHARS` or
:data:`MAX_MESSAGE_CHARS`, is refused whole. Each refusal is counted (``refused``), said in
``last_refusal`` and logged (the first three, then every hundredth), and the unit carries on.
What dyknow publishes stays within the same bounds (longer text is cut, ending ``...``).
"""

from __future__ import annotations

import fnmatch
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

from dyknow.errors import BindingError, ClosedError
from dyknow.ros2.binding import parse_binding
from dyknow.ros2.bridge import Ros2Source
from dyknow.ros2.convert import stamp_ns, to_message
from dyknow.ros2.dds import DdsNode, DdsPublisher
from dyknow.ros2.node import Received, Ros2Node, Ros2Publisher

__all__ = [
    "DIAGNOSTICS_TOPIC",
    "DIAGNOSTIC_ARRAY",
    "ERROR",
    "LEVEL_NAMES",
    "MAX_MESSAGE_CHARS",
    "MAX_NAME_CHARS",
    "MAX_STATUSES",
    "MAX_VALUES",
    "OK",
    "STALE",
    "WARN",
    "DiagnosticStatus",
    "DiagnosticsPublisher",
    "DiagnosticsSource",
    "read_status",
    "read_value",
]

log = logging.getLogger("dyknow.ros2")

#: The topic ROS 2's diagnostic tools read.
DIAGNOSTICS_TOPIC = "/diagnostics"
#: Its type.
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
#: ``diagnostic_msgs/msg/DiagnosticStatus`` levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3
#: Each level's name, as ``rqt_robot_monitor`` shows it.
LEVEL_NAMES: Mapping[int, str] = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}
#: The most statuses read of one array (and published in one).
MAX_STATUSES = 1000
#: The longest status name, hardware id and value key (characters).
MAX_NAME_CHARS = 1000
#: The longest status message and value (characters).
MAX_MESSAGE_CHARS = 4000
#: The most values of one status.
MAX_VALUES = 100

_INT = re.compile(r"[+-]?[0-9]{1,30}")
_FLOAT = re.compile(r"[+-]?(?:[0-9]{1,300}\.?[0-9]{0,300}|\.[0-9]{1,300})(?:[eE][+-]?[0-9]{1,4})?")


def _cut(text: str, most: int) -> str:
    return text if len(text) <= most else text[: most - 3] + "..."


@dataclass(frozen=True, slots=True)
class DiagnosticStatus:
    """One ``diagnostic_msgs/msg/DiagnosticStatus``: ``level`` (:data:`OK`, :data:`WARN`,
    :data:`ERROR` or :data:`STALE`), ``name`` (``<node name>: <what>``), ``message``,
    ``hardware_id`` and ``values`` (key, value) pairs, in order."""

    name: str
    level: int
    message: str
    hardware_id: str = ""
    values: tuple[tuple[str, str], ...] = ()

    @property
    def level_name(self) -> str:
        """``OK``, ``WARN``, ``ERROR``, ``STALE`` (``UNKNOWN`` for a level ROS 2 does not define)."""
        return LEVEL_NAMES.get(self.level, "UNKNOWN")

    def to_fields(self) -> dict[str, Any]:
        """The ``DiagnosticStatus`` fields, text cut to the bounds (:func:`~dyknow.ros2.convert.to_message` takes them)."""
        return {
            "level": int(self.level),
            "name": _cut(self.name, MAX_NAME_CHARS),
            "message": _cut(self.message, MAX_MESSAGE_CHARS),
            "hardware_id": _cut(self.hardware_id, MAX_NAME_CHARS),
            "values": [{"key": _cut(k, MAX_NAME_CHARS), "value": _cut(v, MAX_MESSAGE_CHARS)} for k, v in self.values[:MAX_VALUES]],
        }

    def to_dict(self) -> dict[str, Any]:
        """The JSON form: ``{"name", "level", "level_name", "message", "hardware_id", "values": {key: value}}``
        (the values as text; :class:`DiagnosticsSource` reads them as numbers and booleans)."""
        return {
            "name": self.name,
            "level": self.level,
            "level_name": self.level_name,
            "message": self.message,
            "hardware_id": self.hardware_id,
            "values": dict(self.values),
        }


def read_value(text: str) -> bool | int | float | str:
    """A ``KeyValue`` value as a formula reads it: ``true``/``false`` (any case) as a bool, an
    integer or a finite decimal number as a number, anything else as the text."""
    lowered = text.strip().lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    stripped = text.strip()
    if _INT.fullmatch(stripped):
        return int(stripped)
    if _FLOAT.fullmatch(stripped):
        number = float(stripped)
        if math.isfinite(number):
            return number
    return text


def _level(raw: Any) -> int:
    if isinstance(raw, (bytes, bytearray)):  # (a ``byte`` field: rclpy and rosbags give bytes)
        return raw[0] if raw else 0
    return int(raw)


def read_status(status: Any) -> DiagnosticStatus:
    """A ``DiagnosticStatus`` message object as a :class:`DiagnosticStatus`, held to the bounds (see the
    module's documentation): :class:`~dyknow.errors.BindingError` naming the field and the bound
    when it is over one."""
    name = str(status.name)
    shown = _cut(name, 100)

    def bounded(field: str, text: str, most: int) -> str:
        if len(text) > most:
            raise BindingError(
                f"status {shown!r}: its {field} is {len(text)} characters long",
                where=f"a {DIAGNOSTIC_ARRAY} on {DIAGNOSTICS_TOPIC}",
                expected=f"at most {most} characters (dyknow.ros2.diagnostics bounds what the network sends)",
            )
        return text

    bounded("name", name, MAX_NAME_CHARS)
    values = list(status.values)
    if len(values) > MAX_VALUES:
        raise BindingError(
            f"status {shown!r} has {len(values)} values",
            where=f"a {DIAGNOSTIC_ARRAY} on {DIAGNOSTICS_TOPIC}",
            expected=f"at most {MAX_VALUES} values per status",
        )
    pairs = tuple(
        (bounded("value key", str(kv.key), MAX_NAME_CHARS), bounded(f"value {str(kv.key)[:50]!r}", str(kv.value), MAX_MESSAGE_CHARS))
        for kv in values
    )
    return DiagnosticStatus(
        name,
        _level(status.level),
        bounded("message", str(status.message), MAX_MESSAGE_CHARS),
        bounded("hardware_id", str(status.hardware_id), MAX_NAME_CHARS),
        pairs,
    )


class DiagnosticsPublisher:
    """Publishes what ``collect()`` returns as one ``DiagnosticArray`` on ``/diagnostics`` of
    ``node`` (a :class:`~dyknow.ros2.node.Ros2Node` on rmw_zenoh or a
    :class:`~dyknow.ros2.dds.DdsNode`): every ``period_s`` (default 1 s, as ``diagnostic_updater``),
    and at once when a status's name, level or message changed since the last array (looked at
    every ``check_s``, and at once after :meth:`notify`). ``collect`` runs on the publisher's
    thread; what it raises is logged and the publisher carries on. ``published`` counts the arrays
    sent, ``last`` is the latest. A context manager; :meth:`close` is safe twice.
    """

    def __init__(
        self,
        node: Ros2Node | DdsNode,
        collect: Callable[[], Iterable[DiagnosticStatus]],
        *,
        period_s: float = 1.0,
        check_s: float = 0.1,
    ) -> None:
        if not 0 < check_s <= period_s <= 3600:
            raise BindingError(f"period_s {period_s}, check_s {check_s}", where="the /diagnostics publisher",
                               expected="0 < check_s <= period_s <= 3600 seconds")  # fmt: skip
        self._types = node.types
        self._pub: Ros2Publisher | DdsPublisher = node.create_publisher(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY)
        self._collect = collect
        self.period_s = period_s
        self.check_s = check_s
        self.published = 0
        self.last: tuple[DiagnosticStatus, ...] = ()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="dyknow-diagnostics", daemon=True)
        self._thread.start()

    def __enter__(self) -> DiagnosticsPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def notify(self) -> None:
        """Something may have changed: look now rather than at the next ``check_s``."""
        self._wake.set()

    def _gather(self) -> tuple[DiagnosticStatus, ...]:
        try:
            statuses = tuple(self._collect())
        except Exception:
            log.exception("collecting the /diagnostics statuses failed; the last ones stand")
            return self.last
        if len(statuses) > MAX_STATUSES:
            log.warning("%d /diagnostics statuses; only the first %d are published", len(statuses), MAX_STATUSES)
            statuses = statuses[:MAX_STATUSES]
        return statuses

    def _run(self) -> None:
        sent_at = -math.inf
        shown: tuple[tuple[str, int, str], ...] | None = None
        while not self._stop.is_set():
            statuses = self._gather()
            now = time.monotonic()
            seen = tuple((s.name, s.level, s.message) for s in statuses)
            if seen != shown or now - sent_at >= self.period_s:
                try:
                    self.publish(statuses)
                except ClosedError:
                    return
                except Exception:
                    log.exception("publishing /diagnostics failed")
                sent_at, shown = now, seen
            self._wake.wait(self.check_s)
            self._wake.clear()

    def publish(self, statuses: Sequence[DiagnosticStatus]) -> None:
        """Publish ``statuses`` as one array now (the thread does it by itself; tests and tools may too)."""
        message = to_message({"status": [s.to_fields() for s in statuses]}, DIAGNOSTIC_ARRAY, self._types, origin_ns=time.time_ns())
        self._pub.publish(message)
        self.last = tuple(statuses)
        self.published += 1

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the thread (bounded by ``timeout_s``) and undeclare the publisher; safe twice."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        self._pub.close()


class DiagnosticsSource(Ros2Source):
    """Reads ``/diagnostics`` and publishes on ``out`` one message per status whose name matches
    the param ``status`` (see the module's documentation; ``refused`` and ``last_refusal`` say
    what was refused and why). Params: ``binding`` (default ``ros2:/diagnostics``; its type, if
    given, must be ``diagnostic_msgs/msg/DiagnosticArray``) and ``status`` (default ``*``)."""

    _pattern = "*"
    _glob = True

    def setup(self) -> None:
        """Check the binding and the pattern, then subscribe as :class:`~dyknow.ros2.bridge.Ros2Source` does."""
        where = f"param 'binding' of unit {self.name!r}"
        binding = parse_binding(str(self.params.get("binding", "") or f"ros2:{DIAGNOSTICS_TOPIC}"), where=where)
        if binding.ros_type not in (None, DIAGNOSTIC_ARRAY):
            raise BindingError(f"{binding.uri()} names the type {binding.ros_type}", where=where, expected=f"{DIAGNOSTIC_ARRAY} (or no type)")
        if binding.ros_type is None:
            binding = replace(binding, ros_type=DIAGNOSTIC_ARRAY)
        pattern = str(self.params.get("status", "*") or "*")
        if len(pattern) > MAX_NAME_CHARS:
            raise BindingError(f"a pattern of {len(pattern)} characters", where=f"param 'status' of unit {self.name!r}",
                               expected=f"a status name or glob of at most {MAX_NAME_CHARS} characters")  # fmt: skip
        self._pattern = pattern
        self._glob = any(c in pattern for c in "*?[")
        self.params = {**self.params, "binding": binding.uri()}
        super().setup()

    def matches(self, name: str) -> bool:
        """Whether a status named ``name`` is one this unit keeps (the param ``status``)."""
        return fnmatch.fnmatchcase(name, self._pattern) if self._glob else name == self._pattern

    def _refuse(self, why: str) -> None:
        self.refused += 1
        self.last_refusal = why
        if self.refused <= 3 or self.refused % 100 == 0:
            self.log.warning("refused from %s: %s (%d refused so far)", self.binding.topic, why, self.refused)

    def _arrived(self, received: Received) -> None:  # on the unit's thread (call_soon)
        statuses = list(getattr(received.message, "status", ()))
        if len(statuses) > MAX_STATUSES:
            self._refuse(f"an array of {len(statuses)} statuses: the first {MAX_STATUSES} are read, the rest refused")
            statuses = statuses[:MAX_STATUSES]
        origin = stamp_ns(received.message) or received.attachment.source_timestamp_ns or received.arrival_ns
        for raw in statuses:
            name = str(raw.name)
            if not self.matches(name[: MAX_NAME_CHARS + 1]):
                continue
            try:
                status = read_status(raw)
            except BindingError as exc:
                self._refuse(str(exc))
                continue
            out = status.to_dict()
            out["values"] = {key: read_value(value) for key, value in status.values}
            self.publish("out", out, origin_ns=origin)
