"""The model: plain data of what a manager runs, and its JSON form."""

from __future__ import annotations

import json
from collections.abc import Callable

import pytest

from dyknow import Manager, Model, UnitError, UnitInfo


def test_the_model_is_json_and_finds_units(manager: Manager) -> None:
    manager.spawn("sink", "s", protected=True)
    model = manager.get_model()
    assert isinstance(model, Model) and model.unit("s").protected and model.unit("s").alive
    assert model.unit("s").spec is not None and model.unit("s").spec.label == "sink"
    data = json.loads(json.dumps(model.to_dict()))
    assert data["units"] == [
        {"name": "s", "label": "sink", "state": "running", "protected": True, "bindings": {"in": f"dyknow/{manager.name}/s/in"},
         "executor": "shared thread", "error": None, "traceback": None}
    ]  # fmt: skip
    assert "spec" not in data["units"][0] and {s["label"] for s in data["specs"]} >= {"sink", "relay"}
    with pytest.raises(UnitError) as missing:
        model.unit("ghost")
    assert missing.value.where == f"manager {manager.name!r}"


def test_a_failed_unit_is_not_alive() -> None:
    info = UnitInfo("u", "l", "failed", False, {}, "shared thread", error="boom")
    assert not info.alive and info.to_dict()["error"] == "boom"


def test_a_silent_unit_shows_as_stalled_in_the_model(make_manager: Callable[..., Manager]) -> None:
    """An output silent past its deadline-ms: the model says "stalled" (the tool colours it), then "running" again."""
    from dyknow.testing import SCENARIO_SPECS, Camera
    from tests.conftest import REPO, wait_until

    manager = make_manager(specs=[SCENARIO_SPECS], ontology=[REPO / "specs" / "dyknow.ttl"])
    manager.spawn("ceiling-camera", "cam")
    camera = manager.unit("cam")
    assert isinstance(camera, Camera)
    state = lambda: manager.get_model().unit("cam").state  # noqa: E731
    wait_until(lambda: camera.frames > 3, "frames")
    assert state() == "running"
    camera.freeze()
    wait_until(lambda: state() == "stalled", "the stall in the model")
    camera.resume()
    wait_until(lambda: state() == "running", "running again")
    spec = manager.get_model().to_dict()["specs"][0]
    assert spec["param_types"] == {"camera": "string", "rate_hz": "float"}
