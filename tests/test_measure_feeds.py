"""Measures taken from streams (dyknow.manager.feeds): a Zenoh key's JSON samples or a dyknow unit's
messages become a measure's latest value, at once when a constraint's verdict changes; bad
sources and fields are refused naming them; hostile samples are ignored, never recorded."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest
import zenoh  # a plain Zenoh publisher stands in for a robot's existing key

from dyknow import Manager
from dyknow.errors import BindingError, UnitError
from dyknow.manager.feeds import REFRESH_S
from dyknow.spec import TransformationSpec
from dyknow.spec.model import Constraint, Param, Port, Tag
from dyknow.testing import Source
from dyknow.transport import make_config
from tests.conftest import free_port, wait_until

# a provider whose constraint reads the measure (so a crossing is recorded at once)
CONSTRAINED = TransformationSpec(
    "fast", "transformations.generic:PeriodicSource", (Param("rate_hz", "float", 5.0),), (Port("out", "out"),), (Tag("out", "Beat(x)"),),
    constraints=(Constraint("visibility", ">=", 0.5, 0.1),),
)  # fmt: skip
SOURCE = TransformationSpec("health", "dyknow.testing:Source", (), (Port("out", "out"),))


def wait_for(condition: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "not within the time"
        time.sleep(0.01)


def test_a_zenoh_keys_json_samples_feed_a_measure(make_manager: Callable[..., Manager]) -> None:
    """A plain Zenoh publisher (another session: a robot's existing key) puts JSON objects."""
    manager = make_manager(specs=[CONSTRAINED], listen=[f"tcp/127.0.0.1:{free_port()}"])
    manager.measure_from("visibility", "sensors/visibility#value")
    with zenoh.open(make_config(connect=manager.endpoints)) as plain:
        publisher = plain.declare_publisher("sensors/visibility", congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: publisher.matching_status.matching, "the feed to subscribe")
        while manager.measurements.get("visibility") != 0.9:  # until the path is up (a put right after matching may not arrive yet)
            publisher.put(b'{"value": 0.9}')
            time.sleep(0.05)
        publisher.put(b'{"value": 0.3}')  # crosses the threshold: at once
        wait_for(lambda: manager.measurements.get("visibility") == 0.3)
        publisher.put(b'{"value": 0.31}')  # no verdict changes: not before REFRESH_S
        time.sleep(0.2)
        assert manager.measurements.get("visibility") == 0.3
        for hostile in (b'{"value": "x" ', b'{"value": NaN}', b'{"other": 1}', b"[1, 2]", b'{"value": {"deep": 1}}'):
            publisher.put(hostile)
        time.sleep(REFRESH_S + 0.2)
        assert manager.measurements.get("visibility") == 0.3  # none of them recorded
        publisher.put(b'{"value": 0.32}')  # past REFRESH_S: recorded though no verdict changed
        wait_for(lambda: manager.measurements.get("visibility") == 0.32)
        assert manager.remove_measure_feed("visibility") and not manager.remove_measure_feed("visibility")
        assert "feed.visibility" not in {u.name for u in manager.units()}
        publisher.put(b'{"value": 0.9}')
        time.sleep(0.3)
        assert manager.measurements.get("visibility") == 0.32 and manager.measure_feeds == {}
        publisher.undeclare()


def test_a_dyknow_units_messages_feed_a_measure(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager(specs=[CONSTRAINED, SOURCE])
    manager.spawn("health", "health", bindings={"out": "robot/thruster_1"})
    source = manager.unit("health")
    assert isinstance(source, Source)
    manager.measure_from("thruster_1", "robot/thruster_1#level")
    assert manager.measure_feeds == {"thruster_1": "robot/thruster_1#level"}
    source.emit({"name": "thruster_monitor: thruster_1", "level": 2, "ok": False})
    wait_for(lambda: manager.measurements.get("thruster_1") == 2)
    manager.measure_from("thruster_ok", "robot/thruster_1#ok")  # a bool is 1 or 0
    source.emit({"name": "thruster_monitor: thruster_1", "level": 0, "ok": True})
    wait_for(lambda: manager.measurements.get("thruster_ok") == 1)


@pytest.mark.parametrize(
    ("name", "source", "error", "fragment"),
    [
        ("visibility", "sensors/visibility#not a path", BindingError, "the field 'not a path'"),
        ("visibility", "ros:/water_visibility", BindingError, "the scheme 'ros:'"),
        ("visibility", "ros2dds:/water visibility", BindingError, "/water visibility"),
        ("visibility", "sensors/**/x#value", BindingError, None),
        ("bad name", "sensors/visibility", UnitError, "measurement name 'bad name' is not a valid name"),
    ],
)
def test_a_bad_feed_is_refused_naming_it(make_manager: Callable[..., Manager], name: str, source: str, error: type, fragment: str | None) -> None:
    manager = make_manager(specs=[CONSTRAINED])
    with pytest.raises(error) as caught:
        manager.measure_from(name, source)
    if fragment is not None:
        assert fragment in str(caught.value), caught.value
    assert manager.measure_feeds == {}
