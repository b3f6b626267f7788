"""dyknow.spec.template: expanding templates over their args, and locating what goes wrong."""

from __future__ import annotations

from collections.abc import Sequence

import pytest

from dyknow import spec
from dyknow.errors import SpecError
from dyknow.spec import (
    Constraint,
    Port,
    Tag,
    load_specs,
    parse_specs,
    parse_templates,
)
from tests.spec.support import BROKEN, GOOD, ROBOTS, SPECS


def test_expansion_issue_identical_in_every_expansion_is_reported_once() -> None:
    data = (BROKEN / "param_bad_int.xml").read_text().replace("<label>a</label>", "<label>a(${N})</label>")
    data = data.replace("<source>", '<args><arg label="N">{1; 2; 3}</arg></args><source>')
    with pytest.raises(SpecError) as info:
        parse_specs(data, "p.xml")
    (issue,) = info.value.issues
    assert issue.message.endswith("expected a whole number such as 10")  # no "(in expansion ...)"


def test_expansion_issue_in_some_expansions_names_them() -> None:
    data = """<transformation>
      <label>a(${N})</label><source>m:C</source>
      <args><arg label="N">{1; x; y}</arg></args>
      <params><param name="n" type="float">0${N}</param></params>
      <ports><port type="out">o</port></ports>
    </transformation>"""
    with pytest.raises(SpecError) as info:
        parse_specs(data, "p.xml")
    assert [str(i) for i in info.value.issues] == [
        "p.xml:4: <param> 'n': value '0x' is not a valid float; expected a number such as 0.5 (in expansion N=x)",
        "p.xml:4: <param> 'n': value '0y' is not a valid float; expected a number such as 0.5 (in expansion N=y)",
    ]


def test_expansion_issue_shared_by_several_expansions_lists_them() -> None:
    data = """<transformation>
      <label>a(${A}, ${B})</label><source>m:C</source>
      <args><arg label="A">{a; b}</arg><arg label="B">{x; 1}</arg></args>
      <params><param name="n" type="int">${B}</param></params>
      <ports><port type="out">o</port></ports>
    </transformation>"""
    with pytest.raises(SpecError) as info:
        parse_specs(data, "p.xml")
    assert [str(i) for i in info.value.issues] == [
        "p.xml:4: <param> 'n': value 'x' is not a valid int; expected a whole number such as 10 "
        "(in expansions A=a, B=x; A=b, B=x)"
    ]


def test_expanded_label_clashing_with_another_transformation_is_a_duplicate() -> None:
    fixed = (SPECS / "listing1_fixed.xml").read_text()
    data = f"""<transformations>
{fixed}
<transformation><label>undistort(cam2)</label><source>m:C</source><ports><port type="out">o</port></ports></transformation>
</transformations>"""
    with pytest.raises(SpecError) as info:
        parse_specs(data, "p.xml")
    assert [str(i) for i in info.value.issues] == [
        "p.xml:23: <label>: duplicate label 'undistort(cam2)', first defined at p.xml:3; expected each label once"
    ]


def test_two_args_expand_as_a_cartesian_product_in_document_order() -> None:
    specs = [s for s in load_specs(GOOD / "vision.xml") if s.label.startswith("detect")]
    assert [s.label for s in specs] == [
        "detect(front, yolo)",
        "detect(front, ssd)",
        "detect(rear, yolo)",
        "detect(rear, ssd)",
    ]
    assert specs[2].args == (("Cam", "rear"), ("Model", "yolo"))
    rear = specs[2]
    assert rear.port("objects_rear") == Port("objects_rear", "out", 250.5)
    assert rear.tags_for("objects_rear") == ("Objects(rear)",)
    assert rear.tags_for("image") == ("RawRGB(rear)",)
    assert rear.param_values() == {"camera": "rear", "rate": 10, "threshold": 0.5, "gpu": True}
    assert rear.priority == 1
    assert rear.constraints == (Constraint("battery", ">=", 0.25), Constraint("mode", "!=", "docked"))
    assert rear.inputs == (Port("image", "in", queue=1, policy="keep-last"),)
    assert [p.name for p in rear.outputs] == ["objects_rear"]


def test_double_dollar_is_a_literal_dollar() -> None:
    (s,) = parse_specs(
        """<transformation><label>price$$</label><source>m:C</source>
        <params><param name="p">$${HOME}</param></params>
        <ports><port type="out">o</port></ports></transformation>"""
    )
    assert s.label == "price$"
    assert s.param_values() == {"p": "${HOME}"}  # "$$" then "{HOME}": not a reference


def test_ontology_args_take_the_individuals_of_their_class() -> None:
    calls: list[str] = []

    def individuals(class_ref: str) -> Sequence[str]:
        calls.append(class_ref)
        return ["r1", "r2"]

    specs = load_specs(GOOD / "ontology.xml", individuals)
    assert calls == ["ex:Robot"]
    assert [s.label for s in specs] == ["track(r1)", "track(r2)"]
    assert [s.tags for s in specs] == [(Tag("pose_r1", "Pose(r1)"),), (Tag("pose_r2", "Pose(r2)"),)]


def test_ontology_arg_without_ontology_is_located() -> None:
    (template,) = parse_templates((GOOD / "ontology.xml").read_bytes(), "o.xml")
    with pytest.raises(SpecError) as info:
        template.expand()
    assert [str(i) for i in info.value.issues] == [
        "o.xml:6: <arg> 'Robot': takes its values from ontology class 'ex:Robot', but no ontology "
        "is loaded; expected --ontology FILE"
    ]


@pytest.mark.parametrize(
    ("individuals", "fragment"),
    [
        (lambda c: ROBOTS["ex:Nothing"], "cannot get the individuals of ontology class 'ex:Robot' (KeyError: 'ex:Nothing')"),
        (lambda c: [], "ontology class 'ex:Robot' has no individuals"),
        (lambda c: ["r1", ""], "ontology class 'ex:Robot' gave the invalid individual name ''"),
        (lambda c: "r1", "came back as one string"),
    ],
)  # fmt: skip
def test_failing_ontology_lookup_names_the_class(individuals: spec.Individuals, fragment: str) -> None:
    (template,) = parse_templates((GOOD / "ontology.xml").read_bytes(), "o.xml")
    with pytest.raises(SpecError) as info:
        template.expand(individuals)
    (issue,) = info.value.issues
    assert issue.line == 6
    assert fragment in issue.message


def test_template_without_args_expands_to_one_spec() -> None:
    (template,) = parse_templates("<transformation><label>a</label><source>m:C</source><ports><port type='in'>i</port></ports></transformation>")
    assert not template.is_template
    (s,) = template.expand()
    assert (s.label, s.args, s.ports) == ("a", (), (Port("i", "in"),))


