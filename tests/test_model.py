"""The model: plain data of what a manager runs, and its JSON form."""

from __future__ import annotations

import json

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
