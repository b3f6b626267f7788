"""The manager: library services, spawn/destroy/protect, failures, the model."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import pytest

from dyknow import (
    BindingError,
    ClosedError,
    LibraryError,
    Manager,
    SpecError,
    UnitError,
    UnitEvent,
    default_key,
)
from dyknow.testing import Sink, Source
from tests.units import Counter, Looping, TornDown


def test_spawn_and_destroy(manager: Manager) -> None:
    info = manager.spawn("sink", "s1")
    assert info.name == "s1" and info.label == "sink" and info.state == "running" and not info.protected
    assert info.bindings == {"in": default_key(manager.name, "s1", "in")}
    assert [u.name for u in manager.get_model().units] == ["s1"]
    manager.destroy("s1")
    assert manager.get_model().units == ()
    with pytest.raises(UnitError, match="no unit named 's1'"):
        manager.destroy("s1")


def test_protected_unit_refuses_destroy(manager: Manager) -> None:
    manager.spawn("sink", "guard", protected=True)
    with pytest.raises(UnitError, match="protected"):
        manager.destroy("guard")
    info = manager.get_model().unit("guard")
    assert info.protected and info.state == "running"


def test_unknown_label_names_close_matches(manager: Manager) -> None:
    with pytest.raises(LibraryError, match=r"no transformation labelled 'sinc'.*did you mean 'sink'"):
        manager.spawn("sinc", "x")
    assert manager.get_model().units == ()


def test_duplicate_and_invalid_names(manager: Manager) -> None:
    manager.spawn("sink", "s1")
    with pytest.raises(UnitError, match="already exists"):
        manager.spawn("sink", "s1")
    with pytest.raises(UnitError, match="not a valid name"):
        manager.spawn("sink", "bad/name")
    assert [u.name for u in manager.get_model().units] == ["s1"]


@pytest.mark.parametrize(
    ("label", "fragment"),
    [
        ("missing-module", "cannot import module 'tests.no_such_module'"),
        ("missing-class", "has no 'Sinc'.*did you mean 'Sink'"),
        ("not-a-unit", "not a unit; expected a subclass of dyknow.Unit"),
        ("not-a-class", "is a int, not a unit"),
        ("bad-source", "'package/Undistort' is not importable; expected 'package.module:Class'"),
        ("constructor-fails", "constructor exploded"),
    ],
)
def test_bad_source_is_a_clear_error_and_changes_nothing(manager: Manager, label: str, fragment: str) -> None:
    manager.spawn("sink", "keeper")
    before = manager.get_model()
    with pytest.raises(UnitError, match=fragment):
        manager.spawn(label, "victim")
    after = manager.get_model()
    assert after.units == before.units
    assert after.unit("keeper").state == "running"


def test_setup_failure_marks_unit_failed_with_traceback(manager: Manager) -> None:
    info = manager.spawn("setup-fails", "cam")
    assert info.state == "failed"
    assert "ValueError: cannot open the device" in (info.error or "")
    assert "Traceback" in (info.traceback or "") and "setup" in (info.traceback or "")
    stats = manager.get_statistics("cam")
    assert stats.state == "failed" and "cannot open the device" in (stats.error or "")
    manager.destroy("cam")  # a failed unit can be cleaned up


def test_failing_unit_is_isolated_and_others_keep_flowing(manager: Manager) -> None:
    manager.spawn("publisher", "src")
    src_key = default_key(manager.name, "src", "out")
    manager.spawn("failing", "bad", params={"fail_at": 3}, bindings={"in": src_key})
    manager.spawn("sink", "good", bindings={"in": src_key})
    failures: list[tuple[str, str | None]] = []
    manager.on_unit_event(lambda e: failures.append((e.unit, e.error)) if e.kind == "failed" else None)
    src = manager.unit("src")
    assert isinstance(src, Source)
    for i in range(6):  # fewer than the queue depth (8): a burst from another thread is not dropped
        src.emit({"i": i})
    good = manager.unit("good")
    assert isinstance(good, Sink)
    assert [m.payload["i"] for m in good.wait_for(6)] == list(range(6))
    info = manager.get_model().unit("bad")
    assert info.state == "failed"
    assert "RuntimeError: boom at message 3" in (info.error or "")
    assert "on_message('in')" in (info.error or "")
    assert failures == [("bad", info.error)]
    # the failed unit receives nothing more, the manager still serves
    stats = manager.get_statistics("bad")
    assert stats.ports[0].messages == 3
    manager.spawn("sink", "late", bindings={"in": src_key})
    src.emit({"i": 6})
    late = manager.unit("late")
    assert isinstance(late, Sink)
    assert late.wait_for(1)[0].payload == {"i": 6}


def _wait_event(manager: Manager, kind: str, unit: str) -> UnitEvent:
    seen: list[UnitEvent] = []
    happened = threading.Event()

    def listener(event: UnitEvent) -> None:
        if event.kind == kind and event.unit == unit:
            seen.append(event)
            happened.set()

    manager.on_unit_event(listener)
    return happened, seen  # type: ignore[return-value]


def test_unit_destroys_itself(manager: Manager) -> None:
    manager.spawn("publisher", "src")
    manager.spawn("self-destroying", "once", bindings={"in": default_key(manager.name, "src", "out")})
    happened, seen = _wait_event(manager, "destroyed", "once")
    src = manager.unit("src")
    assert isinstance(src, Source)
    src.emit(b"bye")
    assert happened.wait(5), "the unit did not destroy itself"
    assert all(u.name != "once" for u in manager.get_model().units)


def test_protected_unit_cannot_destroy_itself(manager: Manager) -> None:
    manager.spawn("publisher", "src")
    manager.spawn("self-destroying", "once", protected=True, bindings={"in": default_key(manager.name, "src", "out")})
    happened, seen = _wait_event(manager, "failed", "once")
    src = manager.unit("src")
    assert isinstance(src, Source)
    src.emit(b"bye")
    assert happened.wait(5)
    info = manager.get_model().unit("once")
    assert info.state == "failed" and "protected" in (info.error or "")


def test_params_are_typed_and_overridable(manager: Manager) -> None:
    manager.spawn("failing", "f1")
    assert manager.unit("f1").params == {"fail_at": 1}
    manager.spawn("failing", "f2", params={"fail_at": "7"})
    assert manager.unit("f2").params == {"fail_at": 7}
    with pytest.raises(UnitError, match=r"param 'fail_at'.*got 'seven'; expected a whole number"):
        manager.spawn("failing", "f3", params={"fail_at": "seven"})
    with pytest.raises(UnitError, match=r"no param 'fail_a'.*did you mean 'fail_at'"):
        manager.spawn("failing", "f4", params={"fail_a": 1})


def test_bindings_override_and_validation(manager: Manager) -> None:
    info = manager.spawn("counter", "c", bindings={"in": "robot/numbers/**", "out": "robot/count"})
    assert info.bindings == {"in": "robot/numbers/**", "out": "robot/count"}
    with pytest.raises(BindingError, match=r"has wildcards; expected a concrete key"):
        manager.spawn("counter", "c2", bindings={"out": "robot/*"})
    with pytest.raises(BindingError, match="not a valid Zenoh key expression"):
        manager.spawn("counter", "c3", bindings={"in": "robot//x"})
    with pytest.raises(BindingError, match=r"no port 'inn'.*did you mean 'in'"):
        manager.spawn("counter", "c4", bindings={"inn": "robot/x"})


def test_model_lists_units_and_specs(manager: Manager) -> None:
    manager.spawn("counter", "c", protected=True)
    model = manager.get_model()
    data = model.to_dict()
    assert data["manager"] == manager.name
    assert data["units"] == [
        {
            "name": "c",
            "label": "counter",
            "state": "running",
            "protected": True,
            "bindings": {"in": default_key(manager.name, "c", "in"), "out": default_key(manager.name, "c", "out")},
            "executor": "shared thread",
            "error": None,
            "traceback": None,
        }
    ]
    labels = [s["label"] for s in data["specs"]]
    assert "periodic-source" in labels and "relay" in labels and "counter" in labels


TEMPLATE = """<transformation>
  <label>cam(${Cam})</label>
  <source>dyknow.testing:Sink</source>
  <args><arg label="Cam">{left; right}</arg></args>
  <ports><port type="in">in</port></ports>
  <tags><tag port="in">Image(${Cam})</tag></tags>
</transformation>"""


def test_add_template_override_and_remove(manager: Manager) -> None:
    assert manager.add_transformation(TEMPLATE) == ["cam(left)", "cam(right)"]
    manager.spawn("cam(left)", "left")
    override = TEMPLATE.replace("dyknow.testing:Sink", "tests.units:Counter").replace(
        '<port type="in">in</port>', '<port type="in">in</port><port type="out">out</port>'
    )
    manager.add_transformation(override)
    assert manager.library.get("cam(right)").source == "tests.units:Counter"
    assert manager.remove_transformation("cam(right)") is True
    assert manager.remove_transformation("cam(right)") is False
    assert "cam(right)" not in manager.library
    # running units are not affected by library changes
    assert manager.get_model().unit("left").state == "running"


def test_add_transformation_reports_all_errors(manager: Manager) -> None:
    bad = """<transformation><label>x</label><source>a.b:C</source>
      <ports><port type="in">in</port><port type="in">in</port></ports>
      <tags><tag port="nope">T</tag></tags></transformation>"""
    with pytest.raises(SpecError) as info:
        manager.add_transformation(bad, path="remote.xml")
    assert len(info.value.issues) == 2
    assert all(i.path == "remote.xml" for i in info.value.issues)
    assert "x" not in manager.library


def test_teardown_runs_on_destroy_and_close(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager()
    manager.spawn("torn-down", "t1")
    manager.spawn("torn-down", "t2", protected=True)
    manager.destroy("t1")
    assert "t1" in TornDown.torn_down
    manager.close()
    assert "t2" in TornDown.torn_down  # close stops protected units too


def test_run_loop_unit_publishes_and_stops(manager: Manager) -> None:
    # the sink first: a loop spawned before it may publish its first message before anyone listens
    manager.spawn("sink", "s", bindings={"in": default_key(manager.name, "loop", "out")})
    manager.spawn("looping", "loop")
    sink = manager.unit("s")
    assert isinstance(sink, Sink)
    got = sink.wait_for(5)
    assert [m.payload["n"] for m in got[:5]] == [1, 2, 3, 4, 5]
    loop = manager.unit("loop")
    assert isinstance(loop, Looping)
    manager.destroy("loop")
    assert loop.stopped_cleanly


def test_use_after_close_is_a_clear_error(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager()
    manager.close()
    manager.close()  # safe twice
    with pytest.raises(ClosedError, match="closed"):
        manager.spawn("sink", "s")
    with pytest.raises(ClosedError):
        manager.get_config("s")


def test_bad_spec_paths_fail_before_starting(tmp_path: object) -> None:
    with pytest.raises(SpecError, match="no such file"):
        Manager("never", specs=["/nonexistent/specs.xml"])


def test_counter_keeps_state_between_messages(manager: Manager) -> None:
    manager.spawn("publisher", "src")
    manager.spawn("counter", "c", bindings={"in": default_key(manager.name, "src", "out")})
    manager.spawn("sink", "s", bindings={"in": default_key(manager.name, "c", "out")})
    src = manager.unit("src")
    assert isinstance(src, Source)
    for _ in range(3):
        src.emit(np.zeros(3))
    sink = manager.unit("s")
    assert isinstance(sink, Sink)
    assert [m.payload["count"] for m in sink.wait_for(3)] == [1, 2, 3]
    counter = manager.unit("c")
    assert isinstance(counter, Counter) and counter.count == 3


TYPED = """<transformation><label>typed</label><source>dyknow.testing:Sink</source>
  <params><param name="on" type="bool">false</param><param name="n" type="int">1</param><param name="x" type="float">0.5</param></params>
  <ports><port type="in">in</port></ports></transformation>"""


@pytest.mark.parametrize(
    ("param", "given", "value"),
    [("on", "TRUE", True), ("on", " 0 ", False), ("on", True, True), ("n", "-12", -12), ("n", 7.0, 7), ("x", "1e3", 1000.0), ("x", 2, 2.0)],
)
def test_spawn_time_params_read_as_the_spec_format_reads_them(manager: Manager, param: str, given: object, value: object) -> None:
    manager.add_transformation(TYPED)
    manager.spawn("typed", "t", params={param: given})
    got = manager.unit("t").params[param]
    assert got == value and type(got) is type(value)


@pytest.mark.parametrize(
    ("param", "given", "expected"),
    [("on", "yes", "true or false (bool)"), ("on", 1, "true or false (bool)"), ("n", "1_000", "a whole number (int)"),
     ("n", 1.5, "a whole number (int)"), ("x", "inf", "a number (float)"), ("x", float("nan"), "a number (float)"), ("x", True, "a number (float)")],
)  # fmt: skip
def test_spawn_time_params_the_spec_format_would_refuse_are_refused(manager: Manager, param: str, given: object, expected: str) -> None:
    manager.add_transformation(TYPED)
    with pytest.raises(UnitError) as refused:
        manager.spawn("typed", "t", params={param: given})
    assert refused.value.where == f"param {param!r} of 'typed'" and refused.value.expected == expected
    assert not manager.has_unit("t")
