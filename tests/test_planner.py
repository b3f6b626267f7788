"""The planner: subclass matching, ontology template args, priorities, reuse, cycles, explanations."""

from __future__ import annotations

import random

import pytest

from dyknow.errors import PlanningError
from dyknow.ontology import Ontology
from dyknow.planner import Planner, RunningUnit, plan, unit_name_for
from dyknow.spec import TransformationSpec, load_specs, parse_specs
from dyknow.testing import SCENARIO_SPECS as SCENARIO
from tests.conftest import REPO

ONTOLOGY = REPO / "specs" / "dyknow.ttl"


@pytest.fixture(scope="module")
def ontology() -> Ontology:
    return Ontology.load([ONTOLOGY])


@pytest.fixture(scope="module")
def scenario(ontology: Ontology) -> list[TransformationSpec]:
    return load_specs([SCENARIO], individuals=ontology.individuals)


def labels(p: object) -> list[str]:
    return [u.label for u in p.units]  # type: ignore[attr-defined]


def specs(xml: str) -> list[TransformationSpec]:
    return parse_specs(f"<transformations>{xml}</transformations>", "test.xml")


def t(label: str, ins: dict[str, str], outs: dict[str, str], priority: int = 100, extra: str = "") -> str:
    ports = "".join(f'<port type="in">{p}</port>' for p in ins) + "".join(f'<port type="out">{p}</port>' for p in outs)
    tags = "".join(f'<tag port="{p}">{tag}</tag>' for p, tag in {**ins, **outs}.items())
    return (
        f"<transformation><label>{label}</label><source>m:C</source><ports>{ports}</ports>"
        f"<tags>{tags}</tags><priority>{priority}</priority>{extra}</transformation>"
    )


def test_the_papers_example_chain(scenario: list[TransformationSpec], ontology: Ontology) -> None:
    result = plan("BallPosition(field)", scenario, ontology, manager="robot")
    assert labels(result) == ["robot-camera", "subsampler(bottom)", "ball-detector(bottom)", "localization(bottom)", "tracker"]
    assert result.to_dict() == {
        "request": "BallPosition(field)",
        "output": {"unit": "tracker", "port": "out", "key": "dyknow/robot/tracker/out"},
        "units": [
            {"name": "robot-camera", "label": "robot-camera", "new": True, "manager": "robot"},
            {"name": "subsampler-bottom", "label": "subsampler(bottom)", "new": True, "manager": "robot"},
            {"name": "ball-detector-bottom", "label": "ball-detector(bottom)", "new": True, "manager": "robot"},
            {"name": "localization-bottom", "label": "localization(bottom)", "new": True, "manager": "robot"},
            {"name": "tracker", "label": "tracker", "new": True, "manager": "robot"},
        ],
        "connections": [
            {"from": "robot-camera.out", "to": "subsampler-bottom.in", "key": "dyknow/robot/robot-camera/out"},
            {"from": "subsampler-bottom.hsv", "to": "ball-detector-bottom.in", "key": "dyknow/robot/subsampler-bottom/hsv"},
            {"from": "ball-detector-bottom.out", "to": "localization-bottom.in", "key": "dyknow/robot/ball-detector-bottom/out"},
            {"from": "localization-bottom.out", "to": "tracker.in", "key": "dyknow/robot/localization-bottom/out"},
        ],
    }
    tracker = result.units[-1]
    assert tracker.bindings == {"in": "dyknow/robot/localization-bottom/out", "out": "dyknow/robot/tracker/out"}


def test_subclass_matching_is_one_way(ontology: Ontology) -> None:
    library = specs(
        t("detector", {}, {"out": "BallObject(rel)"})
        + t("localization", {"in": "WorldObject(rel)"}, {"out": "Located(field)"})
        + t("needs-ball", {"in": "BallObject(rel)"}, {"out": "Kicked(field)"})
        + t("generic-source", {}, {"out": "WorldObject(other)"})
    )
    assert labels(plan("Located(field)", library, ontology)) == ["detector", "localization"]
    with pytest.raises(PlanningError):
        plan("BallObject(other)", library, ontology)  # a WorldObject is not a BallObject
    with pytest.raises(PlanningError, match="nothing provides BallObject"):
        plan("Kicked(field)", specs(t("needs-ball", {"in": "BallObject(rel)"}, {"out": "Kicked(field)"}) + t("g", {}, {"out": "WorldObject(rel)"})), ontology)


def test_args_compare_by_local_name(ontology: Ontology) -> None:
    library = specs(t("src", {}, {"out": "BallObject(dk:rel)"}))
    assert labels(plan("WorldObject(rel)", library, ontology)) == ["src"]
    assert labels(plan("<https://dyknow.dev/ontology#WorldObject>(<https://dyknow.dev/ontology#rel>)", library, ontology)) == ["src"]
    with pytest.raises(PlanningError):
        plan("WorldObject(field)", library, ontology)


def test_functors_in_no_ontology_match_only_themselves() -> None:
    library = specs(t("a", {}, {"out": "Foo(x)"}) + t("b", {}, {"out": "Bar(x)"}))
    assert labels(plan("Foo(x)", library)) == ["a"]
    with pytest.raises(PlanningError, match="nothing provides Baz"):
        plan("Baz(x)", library)


def test_a_tag_nothing_has_is_told_the_close_ones_there_are() -> None:
    """A misspelled request (or input tag) gets the closest tags of the library and of what runs."""
    library = specs(t("sensor", {}, {"out": "OverheatAlert(engine)"}) + t("b", {}, {"out": "Temperature(engine)"}))
    with pytest.raises(PlanningError) as caught:
        plan("OverheatAlrt(engine)", library)
    assert "nothing provides OverheatAlrt(engine) (no transformation or running unit has an output port with a matching tag; " \
        "did you mean 'OverheatAlert(engine)'?)" in str(caught.value)  # fmt: skip
    assert caught.value.to_dict()["rejection"]["suggestions"] == ["OverheatAlert(engine)"]
    running = [RunningUnit("probe", "probe", {"out": "k/probe"}, {"out": ("Pressure(engine)",)})]
    with pytest.raises(PlanningError, match=r"did you mean 'Pressure\(engine\)'\?"):
        Planner(library).plan("Presure(engine)", running)
    with pytest.raises(PlanningError) as far:
        plan("Nothing(alike)", library)
    assert "did you mean" not in str(far.value) and "suggestions" not in far.value.to_dict()["rejection"]


def test_ontology_template_args_expand_over_individuals(scenario: list[TransformationSpec]) -> None:
    detectors = sorted(s.label for s in scenario if s.label.startswith("ball-detector"))
    assert detectors == ["ball-detector(bottom)", "ball-detector(ceiling)", "ball-detector(top)"]


def test_priority_ranks_alternatives_with_equal_cost() -> None:
    library = specs(t("cam-b", {}, {"out": "Image"}, priority=5) + t("cam-a", {}, {"out": "Image"}, priority=7))
    assert labels(plan("Image", library)) == ["cam-b"]
    library = specs(t("cam-b", {}, {"out": "Image"}) + t("cam-a", {}, {"out": "Image"}))
    assert labels(plan("Image", library)) == ["cam-a"]  # then by label


def test_fewest_new_units_beats_priority() -> None:
    library = specs(
        t("long-src", {}, {"out": "Raw"}, priority=1)
        + t("long-proc", {"in": "Raw"}, {"out": "Image"}, priority=1)
        + t("direct", {}, {"out": "Image"}, priority=50)
    )
    assert labels(plan("Image", library)) == ["direct"]


def test_reuses_running_units(scenario: list[TransformationSpec], ontology: Ontology) -> None:
    running = [
        RunningUnit("cam", "robot-camera", {"out": "robot/cam"}, {"out": ("RawImage(bottom)",)}),
        RunningUnit("sub", "subsampler(bottom)", {"hsv": "robot/hsv"}, {"hsv": ("HSVImage(bottom)",)}),
    ]
    result = plan("BallPosition(field)", scenario, ontology, running)
    assert [(u.name, u.new) for u in result.units] == [
        ("sub", False),
        ("ball-detector-bottom", True),
        ("localization-bottom", True),
        ("tracker", True),
    ]
    assert result.units[1].bindings["in"] == "robot/hsv"
    assert result.cost[0] == 3


def test_failed_running_units_are_not_reused(scenario: list[TransformationSpec], ontology: Ontology) -> None:
    running = [RunningUnit("sub", "subsampler(bottom)", {"hsv": "robot/hsv"}, {"hsv": ("HSVImage(bottom)",)}, healthy=False)]
    result = plan("BallPosition(field)", scenario, ontology, running)
    assert "sub" not in [u.name for u in result.units]
    assert ("subsampler(bottom)", True) in [(u.label, u.new) for u in result.units]


def test_unavailable_and_constraints_switch_to_the_alternative(scenario: list[TransformationSpec], ontology: Ontology) -> None:
    assert "ceiling-camera" in labels(plan("BallPosition(field)", scenario, ontology, unavailable={"robot-camera"}))
    assert "ceiling-camera" in labels(plan("BallPosition(field)", scenario, ontology, measurements={"battery": 0.2}))
    assert "robot-camera" in labels(plan("BallPosition(field)", scenario, ontology, measurements={"battery": 0.25}))


def test_explanation_names_the_unmet_tag_and_every_reason(scenario: list[TransformationSpec], ontology: Ontology) -> None:
    with pytest.raises(PlanningError) as info:
        plan("BallPosition(field)", scenario, ontology, unavailable={"ceiling-camera"}, measurements={"battery": 0.1})
    text = str(info.value)
    assert text.startswith("cannot plan BallPosition(field):")
    assert "robot-camera (port out): constraint violated: battery = 0.1, needs >= 0.25" in text
    assert "ceiling-camera (port out): unavailable" in text
    assert "nothing provides RawImage(top)" in text
    tree = info.value.to_dict()["rejection"]
    assert tree["tag"] == "BallPosition(field)"
    assert tree["alternatives"][0]["provider"] == "tracker"


def test_cycles_are_detected_and_escaped() -> None:
    looping = specs(t("a", {"in": "Y"}, {"out": "X"}) + t("b", {"in": "X"}, {"out": "Y"}))
    with pytest.raises(PlanningError, match="cycle: a -> b -> a"):
        plan("X", looping)
    escapable = specs(t("a", {"in": "Y"}, {"out": "X"}) + t("b", {"in": "X"}, {"out": "Y"}) + t("seed", {}, {"out": "Y"}))
    assert labels(plan("X", escapable)) == ["seed", "a"]


def test_depth_limit() -> None:
    chain = "".join(t(f"s{i:02d}", {"in": f"T{i + 1}"}, {"out": f"T{i}"}) for i in range(10)) + t("root", {}, {"out": "T10"})
    assert len(plan("T0", specs(chain)).units) == 11
    with pytest.raises(PlanningError, match=r"depth limit \(5 transformations deep\)"):
        plan("T0", specs(chain), max_depth=5)


def test_shared_inputs_spawn_one_unit() -> None:
    library = specs(t("cam", {}, {"out": "Image"}) + t("fuse", {"a": "Image", "b": "Image"}, {"out": "Fused"}))
    result = plan("Fused", library)
    assert labels(result) == ["cam", "fuse"]
    assert sorted(c.target for c in result.connections) == ["fuse.a", "fuse.b"]


def test_untagged_inputs_are_not_wired() -> None:
    library = specs(t("src", {}, {"out": "X"}) + '<transformation><label>user</label><source>m:C</source>'
                    '<ports><port type="in">cfg</port><port type="out">out</port></ports>'
                    '<tags><tag port="out">Y</tag></tags></transformation>')  # fmt: skip
    result = plan("Y", library, manager="m")
    assert labels(result) == ["user"] and result.units[0].bindings["cfg"] == "dyknow/m/user/cfg"


def test_names_avoid_collisions_and_are_valid() -> None:
    library = specs(t("cam(left)", {}, {"out": "Image"}))
    planner = Planner(library)
    assert planner.plan("Image").units[0].name == "cam-left"
    assert planner.plan("Image", reserved_names={"cam-left"}).units[0].name == "cam-left-2"
    assert unit_name_for("<http://x>(a b)") == "http-x-a-b"


def test_deterministic_whatever_the_library_order(scenario: list[TransformationSpec], ontology: Ontology) -> None:
    first = plan("BallPosition(field)", scenario, ontology, measurements={"battery": 0.1})
    for seed in range(5):
        shuffled = list(scenario)
        random.Random(seed).shuffle(shuffled)
        assert plan("BallPosition(field)", shuffled, ontology, measurements={"battery": 0.1}) == first


def test_bad_request_is_a_clear_error() -> None:
    with pytest.raises(PlanningError, match="cannot plan 'Foo\\(': "):
        plan("Foo(", [])


# ---------------------------------------------------------------------- several managers

CAMERA = t("camera", {}, {"out": "Raw(cam)"}, priority=1, extra='<constraints><constraint measure="battery" op="&gt;=" value="0.25"/></constraints>')
DETECT = t("detect", {"in": "Raw(cam)"}, {"out": "Ball(cam)"})
TRACK = t("track", {"in": "Ball(cam)"}, {"out": "Track(cam)"})


def where(p: object) -> dict[str, str]:
    return {u.label: u.manager for u in p.units}  # type: ignore[attr-defined]


def test_a_transformation_runs_where_its_library_holds_it() -> None:
    result = plan("Track(cam)", specs(DETECT + TRACK), manager="ground", peers={"robot": specs(CAMERA)})
    assert where(result) == {"camera": "robot", "detect": "ground", "track": "ground"}
    camera = next(u for u in result.units if u.label == "camera")
    assert camera.remote and camera.ref == "camera@robot" and camera.bindings == {"out": "dyknow/robot/camera/out"}
    detect = next(u for u in result.units if u.label == "detect")
    assert not detect.remote and detect.bindings["in"] == "dyknow/robot/camera/out"  # wired across managers by key
    assert result.to_dict()["units"][0] == {"name": "camera", "label": "camera", "new": True, "manager": "robot"}
    assert result.connections[0].source == "camera@robot.out"


def test_the_requesting_manager_is_preferred_then_the_one_with_the_inputs_then_the_least_loaded() -> None:
    # detect is in every library: the requester's copy wins
    assert where(plan("Ball(cam)", specs(DETECT), manager="ground", peers={"robot": specs(CAMERA + DETECT)}))["detect"] == "ground"
    # not in the requester's library: the manager that runs its input wins over an idle one
    peers = {"robot": specs(CAMERA + DETECT), "spare": specs(DETECT)}
    assert where(plan("Ball(cam)", [], manager="ground", peers=peers, load={"robot": 50, "spare": 0}))["detect"] == "robot"
    # neither runs the input: the least loaded one
    peers = {"robot": specs(CAMERA), "a": specs(DETECT), "b": specs(DETECT)}
    assert where(plan("Ball(cam)", [], manager="ground", peers=peers, load={"a": 7, "b": 3}))["detect"] == "b"
    assert where(plan("Ball(cam)", [], manager="ground", peers=peers, load={"a": 3, "b": 7}))["detect"] == "a"


def test_constraints_are_checked_with_the_measurements_of_the_manager_that_runs_the_unit() -> None:
    local_low = plan("Raw(cam)", [], manager="ground", peers={"robot": specs(CAMERA)}, measurements={"battery": 0.1})
    assert where(local_low) == {"camera": "robot"}  # the ground station's battery is not the robot's
    with pytest.raises(PlanningError, match=r"camera@robot \(port out\): constraint violated: battery = 0.1"):
        plan("Raw(cam)", [], manager="ground", peers={"robot": specs(CAMERA)}, peer_measurements={"robot": {"battery": 0.1}})


def test_units_running_on_other_managers_are_reused_by_key() -> None:
    running = [RunningUnit("cam1", "camera", {"out": "dyknow/robot/cam1/out"}, {"out": ("Raw(cam)",)}, manager="robot")]
    result = plan("Ball(cam)", specs(DETECT), running_model=running, manager="ground", peers={"robot": specs(CAMERA)})
    reused = next(u for u in result.units if not u.new)
    assert (reused.name, reused.manager, reused.remote, reused.ref) == ("cam1", "robot", True, "cam1@robot")
    assert next(u for u in result.units if u.new).bindings["in"] == "dyknow/robot/cam1/out"
    with pytest.raises(PlanningError, match="unavailable"):
        plan("Raw(cam)", [], unavailable={"camera@robot"}, manager="ground", peers={"robot": specs(CAMERA)})


def test_names_are_unique_per_manager() -> None:
    running = [RunningUnit("detect", "other", {}, {}, manager="robot")]
    result = plan("Ball(cam)", [], running_model=running, manager="ground", peers={"robot": specs(CAMERA + DETECT)})
    assert {(u.name, u.manager) for u in result.units} == {("camera", "robot"), ("detect-2", "robot")}
