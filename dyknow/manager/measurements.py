"""Measurements: the latest values of measures (battery, say), which the specs' constraints read.

A measurement is given through the Python API, or put on the measurement keys by anyone
(:func:`dyknow.keys.measurement_patterns`: for every manager, or for this one): a JSON number or
text, or ``{"value": x, "host": h}``, which on the keys for every manager is only for the managers
of host ``h``. A value the constraints could not use (text where they compare numbers, a number
that is not finite) is refused: raised to the Python API, logged and ignored from Zenoh.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from typing import Any

from dyknow import keys
from dyknow.adaptation import AdaptationLoop
from dyknow.errors import LibraryError, UnitError
from dyknow.library import Library
from dyknow.transport import Session

__all__ = ["Measurements"]

log = logging.getLogger("dyknow.manager")  # one name for the manager, whichever part logs


class Measurements:
    """The measurements of manager ``manager`` on ``host``: checked against the constraints of
    the specs of ``library``, handed to ``adaptation`` (its knowledge keeps them), and then
    ``changed()`` (the other managers hear of them). :meth:`declare` subscribes to the
    measurement keys on ``session``.
    """

    def __init__(
        self, manager: str, host: str, *, session: Session, library: Library, adaptation: AdaptationLoop, changed: Callable[[], None]
    ) -> None:
        self._manager = manager
        self._host = host
        self._session = session
        self._library = library
        self._adaptation = adaptation
        self._changed = changed
        self._subs: list[Any] = []

    def declare(self) -> None:
        """Subscribe to the measurement keys (what was declared stays, for :meth:`undeclare`, when one fails)."""
        for pattern in keys.measurement_patterns(self._manager):
            self._subs.append(self._session.declare_raw_subscriber(pattern, self._sample))

    def undeclare(self) -> None:
        """Undeclare the subscriptions."""
        for sub in self._subs:
            sub.undeclare()

    def record(self, name: str, value: float | str) -> None:
        """Record the latest value of measure ``name`` (see :meth:`dyknow.manager.Manager.measure`)."""
        keys.check_name(name, "measurement name")
        self._check(name, value)
        self._adaptation.measure(name, value)
        self._changed()

    def _check(self, name: str, value: object) -> None:
        """:class:`LibraryError` naming the measurement when constraints could not use ``value``."""
        where = f"measurement {name!r}"
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise LibraryError(f"got {value!r}", where=where, expected="a finite number, or text")
        if isinstance(value, float) and not math.isfinite(value):
            raise LibraryError(f"got {value!r}", where=where, expected="a finite number")
        if isinstance(value, str):
            numeric = sorted({s.label for s in self._library.specs() for c in s.constraints if c.measure == name and not isinstance(c.value, str)})
            if numeric:
                raise LibraryError(
                    f"got the text {value[:40]!r}", where=where, expected=f"a number: the constraints of {', '.join(numeric[:3])} compare it with numbers"
                )

    def _sample(self, key: str, payload: bytes) -> None:
        name = key.rsplit("/", 1)[-1]
        try:
            # a put on a wildcard key ('dyknow/**/in') reaches this subscription too: only a
            # concrete key names a measurement
            keys.check_name(name, "measurement name")
            if "*" in key or "$" in key:
                raise UnitError(f"{key[:200]!r} is a key expression with wildcards", expected="a concrete key such as dyknow/measurements/battery")
        except UnitError as exc:
            log.warning("measurement on %s ignored: %s", key[:200], exc)
            return
        try:
            value = json.loads(payload)
            if isinstance(value, dict):
                host = value.get("host")
                if host is not None and key.startswith(keys.measurement_key("")) and host != self._host:
                    return  # a measurement of another machine: its managers take it
                value = value["value"]
            if not isinstance(value, (int, float, str)) or isinstance(value, bool):
                raise ValueError(f"got {value!r}")
        except (ValueError, KeyError, TypeError) as exc:
            log.warning('measurement on %s ignored: %s; expected a JSON number or {"value": x}', key, exc)
            return
        try:
            self._check(name, value)
        except LibraryError as exc:
            log.warning("measurement on %s ignored: %s", key, exc)
            return
        self._adaptation.measure(name, value)
        self._changed()
