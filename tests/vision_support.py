"""Helpers for the vision tests: a manager with the vision specs, a stamped publisher, waits.

Each test module declares its ``vision`` fixture as ``vision_manager(make_manager)``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dyknow import Manager, PortStatistics, Unit, UnitEvent, default_key, parse_specs
from dyknow.testing import Sink
from tests.conftest import GENERIC_SPECS, REPO, UNIT_SPECS

VISION_SPECS = REPO / "specs" / "vision.xml"
SOURCE_SPECS = REPO / "specs" / "sources.xml"

SUPPORT_SPECS = parse_specs(
    """<transformations>
      <transformation><label>stamped-publisher</label><source>tests.vision_support:StampedPublisher</source>
        <ports><port type="out">out</port></ports></transformation>
      <transformation><label>deep-sink</label><source>dyknow.testing:Sink</source>
        <ports><port type="in" queue="4096">in</port></ports></transformation>
    </transformations>""",
    "vision_support.py",
)


class StampedPublisher(Unit):
    """Publishes on demand from the test, with an origin time of the test's choosing."""

    def emit(self, payload: Any, origin_ns: int | None = None) -> None:
        self.publish("out", payload, origin_ns=origin_ns)


def vision_manager(make_manager: Callable[..., Manager]) -> Manager:
    """A manager with the generic, test and vision specs, plus ``stamped-publisher`` and ``deep-sink``."""
    return make_manager(specs=[GENERIC_SPECS, UNIT_SPECS, VISION_SPECS, SOURCE_SPECS, *SUPPORT_SPECS])


def publisher(manager: Manager, name: str = "src") -> StampedPublisher:
    """Spawn a ``stamped-publisher`` named ``name``; the test publishes with its ``emit``."""
    manager.spawn("stamped-publisher", name)
    unit = manager.unit(name)
    assert isinstance(unit, StampedPublisher)
    return unit


def key(manager: Manager, unit: str, port: str) -> str:
    """The default key of ``unit``'s ``port`` on ``manager``."""
    return default_key(manager.name, unit, port)


def spawn_chain(
    manager: Manager,
    label: str,
    name: str,
    *,
    inputs: Mapping[str, str] | None = None,
    params: Mapping[str, Any] | None = None,
    sink_port: str = "out",
    deep: bool = False,
) -> tuple[Unit, Sink]:
    """Spawn ``label`` as ``name`` with its inputs bound to the outputs of other units
    (``{port: "unit/port"}``) and a sink on its ``sink_port`` (spawned first, so that it misses
    nothing a source publishes as it starts; ``deep`` gives it a queue that never drops);
    returns both units."""
    sink_name = f"{name}-sink"
    manager.spawn("deep-sink" if deep else "sink", sink_name, bindings={"in": key(manager, name, sink_port)})
    sink = manager.unit(sink_name)
    assert isinstance(sink, Sink)
    bindings = {port: key(manager, *source.split("/")) for port, source in (inputs or {}).items()}
    info = manager.spawn(label, name, params=dict(params or {}), bindings=bindings)
    assert info.state == "running", info.error
    return manager.unit(name), sink


def failure_of(manager: Manager, label: str, name: str, params: Mapping[str, Any]) -> str:
    """Spawn a unit expected to fail in setup; its error message."""
    info = manager.spawn(label, name, params=dict(params))
    assert info.state == "failed", f"{label} started with {params}"
    assert info.error is not None
    return info.error


class FailureWatch:
    """Waits for a unit to fail at runtime (from ``run`` or a callback), via the manager's events."""

    def __init__(self, manager: Manager, name: str) -> None:
        self.name = name
        self.event = threading.Event()
        self.error: str | None = None
        self._remove = manager.on_unit_event(self._on_event)

    def _on_event(self, event: UnitEvent) -> None:
        if event.kind == "failed" and event.unit == self.name:
            self.error = event.error
            self.event.set()

    def wait(self, timeout: float = 10.0) -> str:
        assert self.event.wait(timeout), f"unit {self.name!r} did not fail within {timeout} s"
        self._remove()
        assert self.error is not None
        return self.error


def port_stats(manager: Manager, name: str, port: str) -> PortStatistics:
    """The statistics of one port of unit ``name``."""
    (stats,) = [p for p in manager.get_statistics(name).ports if p.port == port]
    return stats


def read_image(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    """An image of the shared data (asserting that it decodes)."""
    image = cv2.imread(str(path), flags)
    assert image is not None, f"cannot read test image {path}"
    return image


def solid(height: int = 48, width: int = 64, bgr: tuple[int, int, int] = (120, 120, 120)) -> np.ndarray:
    """A plain BGR frame."""
    frame = np.empty((height, width, 3), np.uint8)
    frame[:] = bgr
    return frame
