"""Tests for dyknow.spec: the XML format, its validation, template expansion and the XSD."""

from __future__ import annotations

import json
import pathlib
from collections.abc import Sequence

import pytest
import xmlschema
from xmlschema.validators import XsdAtomicRestriction

from dyknow import spec
from dyknow.errors import SpecError, SpecIssue
from dyknow.spec import (
    Constraint,
    Param,
    Port,
    Tag,
    TransformationSpec,
    load_specs,
    parse_specs,
    parse_templates,
    spec_files,
)

HERE = pathlib.Path(__file__).parent
SPECS = HERE / "specs"
BROKEN = SPECS / "broken"
GOOD = SPECS / "good"
REPO_SPECS = HERE.parent / "specs"
XSD = REPO_SPECS / "transformation.xsd"

ROBOTS = {"ex:Robot": ["r1", "r2"], "ex:Camera": ["front", "rear"]}


def robots(class_ref: str) -> Sequence[str]:
    return ROBOTS[class_ref]


def issues_of(paths: spec.PathsLike, individuals: spec.Individuals | None = None) -> tuple[SpecIssue, ...]:
    with pytest.raises(SpecError) as info:
        load_specs(paths, individuals)
    return info.value.issues


def listing(issues: Sequence[SpecIssue]) -> str:
    return "\n".join(map(str, issues))


# --- the paper's Listing 1 ----------------------------------------------------------------------


def test_listing1_as_printed_reports_its_tag_bug_once() -> None:
    path = SPECS / "listing1.xml"
    issues = issues_of(path)
    assert len(issues) == 1, listing(issues)
    (issue,) = issues
    assert issue.path == str(path)
    assert issue.line == 18  # <tag port="raw-camera">
    assert issue.message == (
        "<tag> @port: no port named 'raw-camera'; expected one of 'undist', 'rawcamera' "
        "(did you mean 'rawcamera'?)"
    )
    assert str(issue) == f"{path}:18: {issue.message}"


def test_listing1_fixed_expands_to_three_cameras() -> None:
    specs = load_specs(SPECS / "listing1_fixed.xml")
    assert [s.label for s in specs] == ["undistort(cam1)", "undistort(cam2)", "undistort(cam3)"]
    for cam, s in zip(("cam1", "cam2", "cam3"), specs, strict=True):
        assert s.source == "package/Undistort"
        assert s.params == (Param("config-path", "string", f"/path/to/configuration/{cam}/"),)
        assert s.ports == (Port("undist", "out"), Port("rawcamera", "in"))
        assert s.tags == (Tag("undist", f"Undistorted({cam})"), Tag("rawcamera", f"RawRGB({cam})"))
        assert s.args == (("Cam", cam),)
        assert s.priority == spec.DEFAULT_PRIORITY
        assert s.location == f"{SPECS / 'listing1_fixed.xml'}:1"


def test_listing1_template_is_structurally_valid() -> None:
    (template,) = parse_templates((SPECS / "listing1.xml").read_bytes(), "listing1.xml")
    assert template.is_template
    assert template.label == "undistort(${Cam})"
    assert [a.label for a in template.args] == ["Cam"]
    assert template.args[0].values == ("cam1", "cam2", "cam3")
    assert (template.path, template.line) == ("listing1.xml", 1)


# --- one broken file per validation case ------------------------------------------------------

# (file, line, fragment of the message, number of issues in the file)
BROKEN_CASES = [
    ("missing_source.xml", 2, "<transformation>: missing <source>; expected <source>package.module:Class</source>", 1),
    ("param_bad_int.xml", 5, "<param> 'rate': value 'fast' is not a valid int; expected a whole number such as 10", 1),
    ("param_unknown_type.xml", 5, "<param> @type: unknown type 'integer'; expected one of string, int, float, bool (did you mean 'int'?)", 1),
    ("param_expansion.xml", 6, "<param> 'rate': value 'two' is not a valid int; expected a whole number such as 10 (in expansion N=two)", 1),
    ("unknown_element.xml", 2, "<lable>: unknown element in <transformation>; expected one of label, source, description, args, params, ports, tags, priority, constraints (did you mean 'label'?)", 2),
    ("unknown_element.xml", 1, "<transformation>: missing <label>", 2),
    ("unknown_attribute.xml", 5, "<port> @kind: unknown attribute; expected type, deadline-ms", 1),
    ("missing_attribute.xml", 6, "<tag>: missing @port", 1),
    ("undefined_variable.xml", 2, "<label>: undefined template variable ${Camx}; expected one of the declared args: Cam (did you mean 'Cam'?)", 1),
    ("undefined_variable_no_args.xml", 6, '<tag>: undefined template variable ${Camx}; expected it declared as <args><arg label="Camx">{...}</arg></args>', 1),
    ("stray_dollar.xml", 4, "<description>: stray '$' in 'costs $5'; expected ${Name} to use an arg, or $$ for a literal '$'", 1),
    ("duplicate_label.xml", 9, "<label>: duplicate label 'a', first defined at {path}:3", 1),
    ("duplicate_port.xml", 6, "<port>: duplicate port 'x' (first at line 5)", 1),
    ("duplicate_param.xml", 6, "<param> @name: duplicate param 'rate' (first at line 5)", 1),
    ("duplicate_arg.xml", 6, "<arg> @label: duplicate arg 'Cam' (first at line 5)", 1),
    ("duplicate_child.xml", 5, "<source>: duplicate <source> in <transformation> (the first is at line 3); expected at most one", 1),
    ("same_label.xml", 2, "<label>: 3 expansions get the same label 'undistort'; expected one label per expansion (put ${Cam} in the label)", 1),
    ("malformed.xml", 4, "malformed XML: mismatched tag at column 30; expected well-formed XML", 1),
    ("text_in_container.xml", 4, "<ports>: unexpected text 'stray words'; expected only <port> elements", 1),
    ("text_in_constraint.xml", 6, "<constraint>: unexpected text 'high'; expected an empty element", 1),
    ("element_in_text.xml", 2, "<b>: unexpected element in <label>; expected text only", 1),
    ("port_direction.xml", 5, "<port> @type: unknown direction 'output'; expected in or out (did you mean 'out'?)", 1),
    ("port_name.xml", 5, "<port>: 'raw camera' is not a valid port name", 1),
    ("no_ports.xml", 4, "<ports>: no <port> elements; expected at least one", 1),
    ("deadline_on_input.xml", 6, "<port> @deadline-ms: only allowed on out ports", 1),
    ("queue_on_output.xml", 5, "<port> @queue: only allowed on in ports", 1),
    ("queue_not_positive.xml", 5, "<port> @queue: '0' is not a positive whole number; expected a queue size such as 1 or 8", 1),
    ("queue_policy.xml", 5, "<port> @policy: unknown queue policy 'keep-latest'; expected keep-last or drop-new (did you mean 'keep-last'?)", 1),
    ("deadline_not_positive.xml", 5, "<port> @deadline-ms: '0' is not a positive number; expected milliseconds such as 500", 1),
    ("tag_templated_port.xml", 7, "<tag> @port: no port named 'image_rear'; expected 'image_front' (did you mean 'image_front'?) (in expansion Cam=rear)", 1),
    ("empty_tag.xml", 6, "<tag>: empty tag", 1),
    ("tag_syntax.xml", 6, "<tag>: tag 'Ball(Position(field))': nested terms are not allowed; expected Functor or Functor(arg, ...)", 1),
    ("constraint_op.xml", 6, "<constraint> @op: unknown operator '=>'; expected one of <, <=, >, >=, ==, !=", 1),
    ("constraint_not_number.xml", 6, "<constraint> @value: 'docked' is not a number, so op '>=' cannot compare it; expected a number, or op == or !=", 1),
    ("priority.xml", 5, "<priority>: 'high' is not an integer; expected a whole number such as 1", 1),
    ("arg_empty_value.xml", 5, "<arg> 'Cam': empty value in '{cam1;; cam2}'", 1),
    ("arg_empty_set.xml", 5, "<arg> 'Cam': empty set", 1),
    ("arg_duplicate_value.xml", 5, "<arg> 'Cam': duplicate value 'cam1'", 1),
    ("arg_class_and_values.xml", 5, "<arg> 'Cam': has both @class and the values '{cam1}'", 1),
    ("arg_without_ontology.xml", 5, "<arg> 'Cam': takes its values from ontology class 'ex:Camera', but no ontology is loaded; expected --ontology FILE", 1),
    ("empty_label.xml", 2, "<label>: empty; expected a unique name", 1),
    ("transformation_type.xml", 1, "<transformation> @type: unknown type 'node'; expected unit or nodelet (did you mean 'nodelet'?)", 1),
    ("root.xml", 2, "<transformation-list>: unknown root element; expected <transformations> or <transformation>", 1),
    ("empty_root.xml", 2, "<transformations>: no <transformation> inside", 1),
    ("namespace.xml", 1, "<transformation> @xmlns: namespace 'https://example.org/dyknow' is not used", 1),
]  # fmt: skip


@pytest.mark.parametrize(("name", "line", "fragment", "count"), BROKEN_CASES, ids=[f"{c[0]}:{c[1]}" for c in BROKEN_CASES])
def test_broken_spec_is_reported_at_its_line(name: str, line: int, fragment: str, count: int) -> None:
    path = BROKEN / name
    issues = issues_of(path)
    assert len(issues) == count, listing(issues)
    assert {i.path for i in issues} == {str(path)}
    fragment = fragment.replace("{path}", str(path))
    assert any(i.line == line and fragment in i.message for i in issues), listing(issues)


def test_every_broken_fixture_is_tested() -> None:
    tested = {case[0] for case in BROKEN_CASES} | {"billion_laughs.xml", "external_entity.xml", "several_errors.xml"}
    assert {p.name for p in BROKEN.glob("*.xml")} == tested


def test_all_errors_of_a_file_are_reported() -> None:
    path = BROKEN / "several_errors.xml"
    issues = issues_of(path)
    assert [(i.line, i.message) for i in issues] == [
        (2, "<transformation>: missing <source>; expected <source>package.module:Class</source>"),
        (7, "<param> @type: unknown type 'double'; expected one of string, int, float, bool"),
        (10, "<port> @speed: unknown attribute; expected type, deadline-ms, queue, policy"),
        # The second transformation is structurally fine, so its expansion errors are found too.
        (17, "<tag> @port: no port named 'item'; expected 'items' (did you mean 'items'?)"),
    ]
    assert str(SpecError(issues)).splitlines()[0] == f"{path}:2: {issues[0].message}"


def test_parse_templates_reports_structure_without_expanding() -> None:
    with pytest.raises(SpecError) as info:
        parse_templates((BROKEN / "several_errors.xml").read_bytes(), "several.xml")
    assert [i.line for i in info.value.issues] == [2, 7, 10]


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


def test_unreadable_file_is_reported_without_a_line(monkeypatch: pytest.MonkeyPatch, tmp_path: pathlib.Path) -> None:
    path = tmp_path / "locked.xml"
    path.write_text("<transformation/>")
    real_read_bytes = pathlib.Path.read_bytes

    def read_bytes(self: pathlib.Path) -> bytes:
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return real_read_bytes(self)

    monkeypatch.setattr(pathlib.Path, "read_bytes", read_bytes)
    issues = issues_of([path, SPECS / "listing1.xml"])
    assert [str(i) for i in issues][0] == f"{path}: cannot read: Permission denied"
    assert issues[1].path == str(SPECS / "listing1.xml")  # the other file is still checked


# --- hardened parsing -------------------------------------------------------------------------

DTD_MESSAGE = "<!DOCTYPE>: DTDs and entity declarations are not allowed in transformation specs"


@pytest.mark.timeout(5)
def test_billion_laughs_is_refused_before_expansion() -> None:
    path = BROKEN / "billion_laughs.xml"
    (issue,) = issues_of(path)
    assert (issue.path, issue.line) == (str(path), 2)
    assert issue.message.startswith(DTD_MESSAGE)
    assert "remove the <!DOCTYPE ...> block" in issue.message
    assert "lollol" not in issue.message


def test_external_entity_is_never_read() -> None:
    path = BROKEN / "external_entity.xml"
    (issue,) = issues_of(path)
    assert (issue.path, issue.line) == (str(path), 2)
    assert issue.message.startswith(DTD_MESSAGE)
    passwd = pathlib.Path("/etc/passwd")
    if passwd.exists():
        first_entry = passwd.read_text().splitlines()[0]
        assert first_entry not in str(SpecError([issue]))
    assert "root:" not in issue.message


def test_doctype_without_entities_is_refused_too() -> None:
    with pytest.raises(SpecError) as info:
        parse_specs('<?xml version="1.0"?>\n\n<!DOCTYPE transformation>\n<transformation/>', "d.xml")
    (issue,) = info.value.issues
    assert issue.line == 3
    assert issue.message.startswith(DTD_MESSAGE)


def test_bytes_are_decoded_by_their_xml_declaration() -> None:
    text = """<?xml version="1.0" encoding="ISO-8859-1"?>
<transformation><label>caf\xe9</label><source>m:C</source><ports><port type="out">o</port></ports></transformation>"""
    (s,) = parse_specs(text.encode("latin-1"))
    assert s.label == "caf\xe9"
    (s,) = parse_specs(text.replace("ISO-8859-1", "UTF-8"))  # a str is already decoded
    assert s.label == "caf\xe9"


def test_comments_processing_instructions_and_schema_attributes_are_accepted() -> None:
    data = """<?xml version="1.0"?>
<!-- a comment -->
<?editor hint?>
<transformation xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
    xsi:noNamespaceSchemaLocation="transformation.xsd">
  <!-- inside -->
  <label>a<!-- split -->b</label><source>m:C</source><ports><port type="out">o</port></ports>
</transformation>"""
    (s,) = parse_specs(data)
    assert s.label == "ab"


# --- templates --------------------------------------------------------------------------------


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


def test_nodelet_is_the_same_as_unit() -> None:
    unit, nodelet = (
        parse_specs(f'<transformation type="{t}"><label>a</label><source>m:C</source>'
                    '<ports><port type="out">o</port></ports></transformation>', "x.xml")[0]
        for t in ("unit", "nodelet")
    )  # fmt: skip
    assert unit == nodelet


# --- the model --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("op", "value", "measured", "expected"),
    [
        (">=", 0.25, 0.3, True),
        (">=", 0.25, 0.25, True),
        (">=", 0.25, 0.2, False),
        (">", 0.25, 0.25, False),
        ("<", 10.0, 3, True),
        ("<=", 10.0, 10, True),
        ("<=", 10.0, 11, False),
        ("==", 1.0, 1, True),
        ("!=", 1.0, 2.0, True),
        ("==", "docked", "docked", True),
        ("==", "docked", "flying", False),
        ("!=", "docked", "flying", True),
        ("==", 1.0, "1", False),  # a number never equals a string
        ("!=", 1.0, "1", True),
        (">=", 0.25, "full", False),  # ordering a string is never true
        ("<", "docked", 3.0, False),
    ],
)
def test_constraint_holds(op: str, value: float | str, measured: float | str, expected: bool) -> None:
    assert Constraint("m", op, value).holds(measured) is expected


def test_port_lookup_names_the_ports_there_are() -> None:
    s = load_specs(SPECS / "listing1_fixed.xml")[0]
    assert s.port("undist").direction == "out"
    with pytest.raises(KeyError) as info:
        s.port("raw-camera")
    assert "expected one of 'undist', 'rawcamera' (did you mean 'rawcamera'?)" in str(info.value)


def test_to_dict_is_json_ready() -> None:
    s = load_specs(GOOD / "vision.xml")[2]
    d = json.loads(json.dumps(s.to_dict()))
    assert d == {
        "label": "detect(rear, yolo)",
        "source": "transformations.vision:Detector",
        "params": {"camera": "rear", "rate": 10, "threshold": 0.5, "gpu": True},
        "ports": [
            {"name": "image", "direction": "in", "queue": 1, "policy": "keep-last"},
            {"name": "objects_rear", "direction": "out", "deadline_ms": 250.5},
        ],
        "tags": [{"port": "objects_rear", "tag": "Objects(rear)"}, {"port": "image", "tag": "RawRGB(rear)"}],
        "priority": 1,
        "constraints": [
            {"measure": "battery", "op": ">=", "value": 0.25},
            {"measure": "mode", "op": "!=", "value": "docked"},
        ],
        "description": "Finds objects in the images of rear with yolo (costs $0).",
        "args": {"Cam": "rear", "Model": "yolo"},
        "location": f"{GOOD / 'vision.xml'}:5",
    }


def without_location(s: TransformationSpec) -> TransformationSpec:
    return TransformationSpec(**{**{f: getattr(s, f) for f in s.__dataclass_fields__}, "path": "", "line": 0})


@pytest.mark.parametrize("s", [*load_specs(GOOD, robots), *load_specs(SPECS / "listing1_fixed.xml")], ids=lambda s: s.label)
def test_to_xml_round_trips(s: TransformationSpec) -> None:
    (back,) = parse_specs(s.to_xml(), "round.xml", robots)
    assert without_location(back) == without_location(s)


def test_to_xml_escapes_xml_and_dollar() -> None:
    s = TransformationSpec(
        label='odd <label> & "quotes" $x',
        source="m:C",
        params=(
            Param("text", "string", 'a<b & "c" ${Cam} $$'),
            Param("n", "int", -3),
            Param("x", "float", 1e-7),
            Param("on", "bool", False),
        ),
        ports=(Port("o", "out", 0.00001), Port("i", "in")),
        tags=(Tag("o", "<http://ex.org/a?b=1&c=$2#T>(x)"),),  # & < > need escaping, $ doubling
        priority=-2,
        constraints=(Constraint("mode", "!=", 'a "b" <c>'), Constraint("battery", "<", 0.5)),
        description="line one\nline & two",
        args=(("Cam", "a<b"),),
    )
    (back,) = parse_specs(s.to_xml(), "round.xml")
    assert without_location(back) == without_location(s)
    assert xmlschema.XMLSchema(XSD).is_valid(s.to_xml())


# --- files --------------------------------------------------------------------------------------


def test_spec_files_lists_a_directory_sorted_and_not_recursively(tmp_path: pathlib.Path) -> None:
    (tmp_path / "b.xml").write_text("x")
    (tmp_path / "a.xml").write_text("x")
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "c.xml").write_text("x")
    assert spec_files(tmp_path) == [tmp_path / "a.xml", tmp_path / "b.xml"]
    assert spec_files(str(tmp_path / "notes.txt")) == [tmp_path / "notes.txt"]
    # A file named twice (directly and through its directory) counts once.
    assert spec_files([tmp_path / "a.xml", tmp_path]) == [tmp_path / "a.xml", tmp_path / "b.xml"]
    assert spec_files(GOOD) == [GOOD / "ontology.xml", GOOD / "vision.xml"]


def test_spec_files_reports_every_missing_path(tmp_path: pathlib.Path) -> None:
    with pytest.raises(SpecError) as info:
        spec_files([tmp_path / "nope.xml", GOOD, tmp_path / "gone"])
    assert [str(i) for i in info.value.issues] == [
        f"{tmp_path / 'nope.xml'}: no such file or directory; expected a spec file or a directory of *.xml files",
        f"{tmp_path / 'gone'}: no such file or directory; expected a spec file or a directory of *.xml files",
    ]


def test_load_specs_loads_a_directory() -> None:
    specs = load_specs(GOOD, robots)
    assert [s.label for s in specs] == [
        "track(r1)",
        "track(r2)",
        "detect(front, yolo)",
        "detect(front, ssd)",
        "detect(rear, yolo)",
        "detect(rear, ssd)",
        "count",
    ]


def test_duplicate_labels_across_files_name_both_locations() -> None:
    a, b = SPECS / "dup" / "a.xml", SPECS / "dup" / "b.xml"
    issues = issues_of(SPECS / "dup")
    assert [str(i) for i in issues] == [
        f"{b}:4: <label>: duplicate label 'shared', first defined at {a}:2; expected each label once"
    ]


def test_load_specs_collects_the_issues_of_every_file() -> None:
    issues = issues_of([BROKEN / "missing_source.xml", SPECS / "listing1.xml", BROKEN / "priority.xml"])
    assert [(pathlib.Path(i.path).name, i.line) for i in issues] == [
        ("missing_source.xml", 2),
        ("listing1.xml", 18),
        ("priority.xml", 5),
    ]


# --- the XSD ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def schema() -> xmlschema.XMLSchema:
    return xmlschema.XMLSchema(XSD)


GOOD_FIXTURES = [SPECS / "listing1_fixed.xml", *sorted(GOOD.glob("*.xml")), *sorted((SPECS / "dup").glob("*.xml"))]


@pytest.mark.parametrize("path", [*sorted(REPO_SPECS.glob("*.xml")), *GOOD_FIXTURES], ids=lambda p: p.name)
def test_good_specs_validate_against_the_xsd(schema: xmlschema.XMLSchema, path: pathlib.Path) -> None:
    schema.validate(path)


def test_the_repo_specs_load() -> None:
    files = sorted(REPO_SPECS.glob("*.xml"))
    # The shipped specs may use ontology classes; any class resolves to two names here.
    specs = load_specs(files, lambda class_ref: ["a", "b"])
    assert len(specs) >= len(files)


# Broken files whose problem the XSD can see (the others depend on template substitution).
XSD_DETECTABLE = [
    "listing1.xml", "missing_source.xml", "param_unknown_type.xml", "unknown_element.xml",
    "unknown_attribute.xml", "missing_attribute.xml", "duplicate_port.xml", "duplicate_param.xml",
    "duplicate_arg.xml", "duplicate_child.xml", "text_in_container.xml", "text_in_constraint.xml",
    "element_in_text.xml", "port_direction.xml", "port_name.xml", "no_ports.xml",
    "deadline_not_positive.xml", "tag_templated_port.xml", "empty_tag.xml", "constraint_op.xml",
    "priority.xml", "empty_label.xml", "transformation_type.xml", "root.xml", "empty_root.xml",
    "namespace.xml", "several_errors.xml",
]  # fmt: skip


@pytest.mark.parametrize("name", XSD_DETECTABLE)
def test_xsd_rejects_what_the_loader_rejects(schema: xmlschema.XMLSchema, name: str) -> None:
    path = SPECS / name if name.startswith("listing1") else BROKEN / name
    assert not schema.is_valid(path)
    with pytest.raises(SpecError):
        load_specs(path)


def xsd_elements(schema: xmlschema.XMLSchema) -> dict[str, frozenset[str]]:
    """Every element the XSD declares (globally or inside another) and its attribute names."""
    found: dict[str, frozenset[str]] = {}

    def visit(element: xmlschema.XsdElement) -> None:
        if element.name in found:
            return
        assert element.name is not None
        assert None not in element.attributes  # no attribute wildcards: the format is closed
        found[element.name] = frozenset(name for name in element.attributes if name is not None)
        for child in element.iterchildren():
            assert isinstance(child, xmlschema.XsdElement)  # no element wildcards either
            visit(child)

    for element in schema.elements.values():
        visit(element)
    return found


def test_xsd_elements_and_attributes_match_the_loader(schema: xmlschema.XMLSchema) -> None:
    assert xsd_elements(schema) == dict(spec.ELEMENTS)
    assert set(schema.elements) == {"transformations", "transformation"}  # the two possible roots


@pytest.mark.parametrize(
    ("type_name", "values"),
    [
        ("paramType", spec.PARAM_TYPES),
        ("constraintOp", spec.CONSTRAINT_OPS),
        ("portDirection", spec.PORT_DIRECTIONS),
        ("transformationType", spec.TRANSFORMATION_TYPES),
    ],
)
def test_xsd_enumerations_match_the_loader(schema: xmlschema.XMLSchema, type_name: str, values: tuple[str, ...]) -> None:
    simple_type = schema.types[type_name]
    assert isinstance(simple_type, XsdAtomicRestriction)
    assert tuple(simple_type.enumeration or ()) == values
