"""Mode files of ROS 2's system_modes (dyknow.spec.modefile) and the spec's <system>: files as
SUAVE and system_modes write them load, with system_modes' meaning (a mode starts from the
default's parameters and parts); every mistake is located in the file."""

from __future__ import annotations

import json
import pathlib
from dataclasses import replace

import pytest

from dyknow.errors import SpecError
from dyknow.spec import load_specs, parse_specs
from dyknow.spec.modefile import MAX_BYTES, Target, load_mode_file, parse_mode_file
from dyknow.spec.model import Constraint

# The mode file of SUAVE (github.com/kas-lab/suave, suave/config/suave_modes.yaml, Apache-2.0),
# as that project writes it: parts as a plain multi-line scalar, nodes without the leading slash.
SUAVE = """---
f_generate_search_path:
  ros__parameters:
    type: system
    parts:
      f_generate_search_path_node
    modes:
      __DEFAULT__:
        f_generate_search_path_node: active.__DEFAULT__
      fd_spiral_high:
        f_generate_search_path_node: active.fd_spiral_high
      fd_spiral_low:
        f_generate_search_path_node: active.fd_spiral_low
      fd_spiral_medium:
        f_generate_search_path_node: active.fd_spiral_medium
      fd_unground:
        f_generate_search_path_node: inactive

f_generate_search_path_node:
  ros__parameters:
    type: node
    modes:
      __DEFAULT__:
        ros__parameters:
          spiral_altitude: 1.0
      fd_spiral_high:
        ros__parameters:
          spiral_altitude: 3.0
      fd_spiral_medium:
        ros__parameters:
          spiral_altitude: 2.0
      fd_spiral_low:
        ros__parameters:
          spiral_altitude: 1.0

f_maintain_motion:
  ros__parameters:
    type: system
    parts:
      f_maintain_motion_node
    modes:
      __DEFAULT__:
        f_maintain_motion_node: active.__DEFAULT__
      fd_all_thrusters:
        f_maintain_motion_node: inactive
      fd_recover_thrusters:
        f_maintain_motion_node: active.__DEFAULT__

f_maintain_motion_node:
  ros__parameters:
    type: node
    modes:
      __DEFAULT__:
        ros__parameters:
          system_mode_marker: __DEFAULT__
"""

# system_modes' own example (system_modes_examples/example_modes.yaml): a system of two nodes whose
# modes set only some parameters (the others come from __DEFAULT__), with a rule.
EXAMPLE = """actuation:
  ros__parameters:
    type: system
    parts:
      manipulator
      drive_base
    modes:
      __DEFAULT__:
        manipulator: inactive
        drive_base: active
      MODERATE:
        manipulator: active.WEAK
        drive_base: active.SLOW
      PERFORMANCE:
        manipulator: active.STRONG
        drive_base: active.FAST
    rules:
      degrade_from_PERFORMANCE:
        if_target: active.PERFORMANCE
        if_part: [manipulator, inactive]
        new_target: active.__DEFAULT__

manipulator:
  ros__parameters:
    type: node
    modes:
      __DEFAULT__:
        ros__parameters:
          max_torque: 0.1
      WEAK:
        ros__parameters:
          max_torque: 0.1
      STRONG:
        ros__parameters:
          max_torque: 0.2

drive_base:
  ros__parameters:
    type: node
    modes:
      __DEFAULT__:
        ros__parameters:
          max_speed: 0.1
          controller: PID
      SLOW:
        ros__parameters:
          max_speed: 0.2
      FAST:
        ros__parameters:
          max_speed: 0.9
          controller: MPC
"""


def test_suaves_mode_file_loads_with_each_mode_asking_what_the_file_says() -> None:
    modes = parse_mode_file(SUAVE, "suave_modes.yaml")
    assert modes.modes("f_generate_search_path") == ("__DEFAULT__", "fd_spiral_high", "fd_spiral_low", "fd_spiral_medium", "fd_unground")
    node = "/f_generate_search_path_node"
    for mode, altitude in (("fd_spiral_high", 3.0), ("fd_spiral_medium", 2.0), ("fd_spiral_low", 1.0), ("__DEFAULT__", 1.0)):
        assert modes.targets("f_generate_search_path", mode) == {node: Target(node, "active", mode, {"spiral_altitude": altitude})}
    assert modes.targets("f_generate_search_path", "fd_unground") == {node: Target(node, "inactive", None, {})}
    motion = "/f_maintain_motion_node"
    assert modes.targets("f_maintain_motion", "fd_all_thrusters") == {motion: Target(motion, "inactive", None, {})}
    assert modes.targets("f_maintain_motion", "fd_recover_thrusters") == {
        motion: Target(motion, "active", "__DEFAULT__", {"system_mode_marker": "__DEFAULT__"})
    }


def test_a_mode_starts_from_the_default_modes_parameters_and_parts() -> None:
    # system_modes' meaning, written out by hand: SLOW sets max_speed only, so controller stays PID
    modes = parse_mode_file(EXAMPLE, "example_modes.yaml")
    assert modes.targets("actuation", "MODERATE") == {
        "/manipulator": Target("/manipulator", "active", "WEAK", {"max_torque": 0.1}),
        "/drive_base": Target("/drive_base", "active", "SLOW", {"max_speed": 0.2, "controller": "PID"}),
    }
    assert modes.targets("actuation", "__DEFAULT__") == {
        "/manipulator": Target("/manipulator", "inactive", None, {}),
        "/drive_base": Target("/drive_base", "active", "__DEFAULT__", {"max_speed": 0.1, "controller": "PID"}),
    }


def test_nested_systems_flatten_to_their_nodes() -> None:
    text = EXAMPLE + """
robot:
  ros__parameters:
    type: system
    parts: [actuation]
    modes:
      __DEFAULT__:
        actuation: inactive
      FAST:
        actuation: active.PERFORMANCE
"""
    modes = parse_mode_file(text, "nested.yaml")
    assert modes.targets("robot", "__DEFAULT__") == {
        "/manipulator": Target("/manipulator", "inactive", None, {}),
        "/drive_base": Target("/drive_base", "inactive", None, {}),
    }
    assert modes.targets("robot", "FAST")["/drive_base"] == Target("/drive_base", "active", "FAST", {"max_speed": 0.9, "controller": "MPC"})


@pytest.mark.parametrize(
    ("change", "line", "fragment"),
    [
        (("drive_base: active.FAST", "drive_bse: active.FAST"), 16, "'drive_bse' is not a part of system 'actuation'"),
        (("drive_base: active.SLOW", "drive_base: active.SLUGGISH"), 13, "'drive_base' (declared) has no mode 'SLUGGISH'"),
        (("manipulator: active.WEAK", "manipulator: paused"), 12, "unknown state 'paused'"),
        (("manipulator: inactive", "manipulator: inactive.WEAK"), 9, "a mode for a part that is inactive"),
        (("max_speed: 0.9", "max_speed: {a: [1, x]}"), 0, "not a ROS 2 parameter value"),
        (("      __DEFAULT__:\n        ros__parameters:\n          max_torque", "      WEAKEST:\n        ros__parameters:\n          max_torque"), 0, "no __DEFAULT__ mode"),
        (("type: node\n    modes:\n      __DEFAULT__:\n        ros__parameters:\n          max_speed", "type: nod\n    modes:\n      __DEFAULT__:\n        ros__parameters:\n          max_speed"), 0, "'nod' is not a part type"),
        (("if_part: [manipulator, inactive]", "if_part: [gripper, inactive]"), 20, "is not [PART, STATE] of a part of 'actuation'"),
    ],
)
def test_a_mistake_in_a_mode_file_is_located(change: tuple[str, str], line: int, fragment: str) -> None:
    old, new = change
    assert old in EXAMPLE
    with pytest.raises(SpecError) as caught:
        parse_mode_file(EXAMPLE.replace(old, new, 1), "modes.yaml")
    issues = caught.value.issues
    assert any(fragment in str(i) for i in issues), [str(i) for i in issues]
    found = next(i for i in issues if fragment in str(i))
    assert found.path == "modes.yaml"
    if line:
        assert found.line == line, str(found)


def test_hostile_mode_files_are_refused_cheaply() -> None:
    # aliases multiply what a walk of the file reads: refused where the reader meets them
    bomb = "n:\n  ros__parameters:\n    type: node\n    modes:\n      __DEFAULT__:\n        ros__parameters: &p {a: 1, b: 2}\n      X:\n        ros__parameters: *p\n"
    with pytest.raises(SpecError, match="anchors and aliases are not allowed"):
        parse_mode_file(bomb, "bomb.yaml")
    with pytest.raises(SpecError, match="more than"):
        parse_mode_file("a: " + "x" * MAX_BYTES, "big.yaml")
    with pytest.raises(SpecError, match="not valid YAML"):
        parse_mode_file("a: [b\n", "broken.yaml")
    with pytest.raises(SpecError, match="the mode file is empty"):
        parse_mode_file("", "empty.yaml")
    with pytest.raises(SpecError, match="cannot read the mode file"):
        load_mode_file("/nonexistent/modes.yaml")


SYSTEM = """<transformations>
  <system name="actuation" modes="modes.yaml" middleware="dds" timeout-s="3">
    <label>act</label>
    <tags><tag>Mode(act)</tag></tags>
    <mode name="PERFORMANCE">
      <priority>1</priority>
      <constraints><constraint measure="battery" op="&gt;=" value="0.5" margin="0.1"/></constraints>
    </mode>
    <mode name="MODERATE"><priority>2</priority></mode>
  </system>
</transformations>
"""


def test_a_system_offers_one_transformation_per_mode_that_switches_to_it(tmp_path: pathlib.Path) -> None:
    (tmp_path / "modes.yaml").write_text(EXAMPLE)
    (tmp_path / "spec.xml").write_text(SYSTEM)
    performance, moderate = load_specs(tmp_path / "spec.xml")
    assert (performance.label, moderate.label) == ("act.PERFORMANCE", "act.MODERATE")
    assert performance.source == moderate.source == "dyknow.ros2.modes:ModeUnit"
    assert [t.tag for t in performance.tags] == ["Mode(act)"] and performance.tags[0].port == "mode"
    assert performance.priority == 1 and performance.constraints == (Constraint("battery", ">=", 0.5, 0.1),)
    params = {p.name: p.value for p in performance.params}
    assert (params["system"], params["mode"], params["middleware"], params["timeout_s"]) == ("actuation", "PERFORMANCE", "dds", 3.0)
    assert json.loads(str(params["targets"])) == {
        "/manipulator": {"state": "active", "mode": "STRONG", "parameters": {"max_torque": 0.2}},
        "/drive_base": {"state": "active", "mode": "FAST", "parameters": {"max_speed": 0.9, "controller": "MPC"}},
    }
    (again,) = parse_specs(performance.to_xml())  # as another manager reads it from the summary
    assert replace(again, path=performance.path, line=performance.line) == performance


def test_a_system_without_mode_children_offers_every_mode_of_the_file_its_default_preferred(tmp_path: pathlib.Path) -> None:
    (tmp_path / "modes.yaml").write_text(SUAVE)
    (tmp_path / "spec.xml").write_text(
        '<system name="f_generate_search_path" modes="modes.yaml"><label>search</label><tags><tag>Mode(search)</tag></tags></system>'
    )
    specs = {s.label: s.priority for s in load_specs(tmp_path / "spec.xml")}
    assert specs == {
        "search.__DEFAULT__": 99, "search.fd_spiral_high": 100, "search.fd_spiral_low": 100,
        "search.fd_spiral_medium": 100, "search.fd_unground": 100,
    }  # fmt: skip


def test_modes_written_in_the_spec_need_no_file() -> None:
    normal, degraded = parse_specs(
        """<system name="motion">
             <label>motion</label><tags><tag>Mode(motion)</tag></tags>
             <mode name="normal"><part node="/controller" state="active"><params><param name="degraded" type="bool">false</param></params></part>
               <part node="recover" state="inactive"/></mode>
             <mode name="degraded"><priority>200</priority>
               <part node="/controller" state="active"><params><param name="degraded" type="bool">true</param></params></part>
               <part node="/recover" state="active"/></mode>
           </system>"""
    )
    assert json.loads(str(next(p.value for p in normal.params if p.name == "targets"))) == {
        "/controller": {"state": "active", "mode": None, "parameters": {"degraded": False}},
        "/recover": {"state": "inactive", "mode": None, "parameters": {}},
    }
    assert degraded.priority == 200


@pytest.mark.parametrize(
    ("xml", "fragment"),
    [
        ('<system name="s" modes="modes.yaml"><label>s</label><tags><tag>Mode(s)</tag></tags></system>',
         "<system> @modes: a mode file is read only for a spec file the operator gave"),
        ('<system name="s"><label>s</label><tags><tag>Mode(s)</tag></tags><mode name="m"><part node="/a" state="running"/></mode></system>',
         "<part> @state: unknown state 'running'"),
        ('<system name="s"><label>s</label><tags><tag>Mode(s)</tag></tags><mode name="m"/></system>', "<mode>: no <part>"),
        ('<system name="s"><label>s</label><mode name="m"><part node="/a" state="active"/></mode></system>', "<system>: missing <tags>"),
        ('<system name="s"><label>s</label><tags><tag>Mode(s)</tag></tags><mode name="m"><part node="/a" state="inactive">'
         '<params><param name="x" type="int">1</param></params></part></mode></system>', "parameters for a node that is inactive"),
        ('<system name="s"><label>s</label><tags><tag>Mode(s)</tag></tags><mode name="m"><part node="/a" state="active">'
         '<params><param name="x" type="int">one</param></params></part></mode></system>', "<param> 'x': value 'one' is not a valid int"),
        ('<system name="s"><label>s</label><tags><tag>Mode(s)</tag></tags><mode name="m"><part node="/a" state="active"/></mode>'
         '<mode name="m"><part node="/a" state="active"/></mode></system>', "duplicate mode 'm'"),
        ('<system name="s"><label>s</label><tags><tag>Mode(s)</tag></tags><mode name="m"><part node="/a" state="active"/>'
         '<requirements><requirement>always Mode(s).mode == "m"</requirement></requirements></mode></system>',
         "<requirements>: requirements of a mode (trying a mode in the shadow would switch the system)"),
    ],
)  # fmt: skip
def test_a_mistake_in_a_system_is_located(xml: str, fragment: str) -> None:
    with pytest.raises(SpecError) as caught:
        parse_specs(xml, "spec.xml")
    assert any(fragment in str(i) for i in caught.value.issues), [str(i) for i in caught.value.issues]


def test_a_system_naming_what_its_mode_file_lacks_is_located_in_the_spec_and_the_file(tmp_path: pathlib.Path) -> None:
    (tmp_path / "modes.yaml").write_text(EXAMPLE)
    (tmp_path / "spec.xml").write_text(SYSTEM.replace('<mode name="MODERATE">', '<mode name="MODERAT">'))
    with pytest.raises(SpecError) as caught:
        load_specs(tmp_path / "spec.xml")
    assert [str(i) for i in caught.value.issues] == [
        f"{tmp_path / 'spec.xml'}:9: <mode> @name: system 'actuation' of modes.yaml has no mode 'MODERAT'; "
        "expected one of __DEFAULT__, MODERATE, PERFORMANCE (did you mean 'MODERATE'?)"
    ]
    (tmp_path / "spec.xml").write_text(SYSTEM.replace('name="actuation"', 'name="actuator"'))
    with pytest.raises(SpecError, match="no system 'actuator' in the mode file"):
        load_specs(tmp_path / "spec.xml")
    (tmp_path / "modes.yaml").write_text(EXAMPLE.replace("drive_base: active.FAST", "drive_bse: active.FAST"))
    (tmp_path / "spec.xml").write_text(SYSTEM)
    with pytest.raises(SpecError) as caught:
        load_specs(tmp_path / "spec.xml")
    assert any(i.path == str(tmp_path / "modes.yaml") and i.line == 16 for i in caught.value.issues), [str(i) for i in caught.value.issues]


def naive_holds(op: str, threshold: float, margin: float, value: float, held: bool) -> bool:
    """A Schmitt trigger written out: a running transformation's threshold moves by the margin in its favour."""
    if held:
        threshold = threshold - margin if op in (">", ">=") else threshold + margin
    return {"<": value < threshold, "<=": value <= threshold, ">": value > threshold, ">=": value >= threshold}[op]


@pytest.mark.parametrize("op", ["<", "<=", ">", ">="])
def test_a_constraints_margin_is_hysteresis(op: str) -> None:
    constraint = Constraint("visibility", op, 0.5, 0.125)
    for value in (0.0, 0.3, 0.375, 0.4, 0.5, 0.6, 0.625, 0.7, 1.0):
        for held in (False, True):
            assert constraint.holds(value, held=held) == naive_holds(op, 0.5, 0.125, value, held), (value, held)
