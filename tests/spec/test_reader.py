"""dyknow.spec.reader: the hardened XML parser, the structure checks, loading files."""

from __future__ import annotations

import json
import pathlib
from dataclasses import replace

import pytest

from dyknow import spec
from dyknow.errors import SpecError, SpecIssue
from dyknow.spec import (
    Param,
    Port,
    Tag,
    load_specs,
    parse_specs,
    parse_templates,
    spec_files,
)
from tests.spec.support import BROKEN, GOOD, SPECS, issues_of, listing, robots


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


BROKEN_CASES = [
    ("missing_source.xml", 2, "<transformation>: missing <source>; expected <source>package.module:Class</source>", 1),
    ("param_bad_int.xml", 5, "<param> 'rate': value 'fast' is not a valid int; expected a whole number such as 10", 1),
    ("param_unknown_type.xml", 5, "<param> @type: unknown type 'integer'; expected one of string, int, float, bool, path (did you mean 'int'?)", 1),
    ("param_mode.xml", 5, "<param> @mode: only allowed on path params; expected it on a <param type=\"path\">", 2),
    ("param_mode.xml", 6, "<param> @mode: unknown mode 'append'; expected read or write", 2),
    ("param_expansion.xml", 6, "<param> 'rate': value 'two' is not a valid int; expected a whole number such as 10 (in expansion N=two)", 1),
    ("unknown_element.xml", 2, "<lable>: unknown element in <transformation>; expected one of label, source, description, args, params, ports, tags, priority, constraints, requirements, bindings (did you mean 'label'?)", 2),
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
    ("malformed.xml", 4, "malformed XML: a closing tag that does not match at column 30; expected </port> closing the <port> opened at line 4", 1),
    ("truncated.xml", 4, "malformed XML: not well-formed (invalid token) at column 3, inside <label> opened at line 3; expected </label> closing it, complete", 1),
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
    ("root.xml", 2, "<transformation-list>: unknown root element; expected <transformations>, <transformation>, <node> or <system>", 1),
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
        (7, "<param> @type: unknown type 'double'; expected one of string, int, float, bool, path"),
        (10, "<port> @speed: unknown attribute; expected type, deadline-ms, queue, policy"),
        # The second transformation is structurally fine, so its expansion errors are found too.
        (17, "<tag> @port: no port named 'item'; expected 'items' (did you mean 'items'?)"),
    ]
    assert str(SpecError(issues)).splitlines()[0] == f"{path}:2: {issues[0].message}"


def test_parse_templates_reports_structure_without_expanding() -> None:
    with pytest.raises(SpecError) as info:
        parse_templates((BROKEN / "several_errors.xml").read_bytes(), "several.xml")
    assert [i.line for i in info.value.issues] == [2, 7, 10]


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


def test_nodelet_is_the_same_as_unit() -> None:
    unit, nodelet = (
        parse_specs(f'<transformation type="{t}"><label>a</label><source>m:C</source>'
                    '<ports><port type="out">o</port></ports></transformation>', "x.xml")[0]
        for t in ("unit", "nodelet")
    )  # fmt: skip
    assert unit == nodelet


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




FIELDS = [
    ("port_direction", 5, "<port> @type", "unknown direction 'output'", "in or out (did you mean 'out'?)"),
    ("unknown_attribute", 5, "<port> @kind", "unknown attribute", "type, deadline-ms, queue, policy"),
    ("unknown_element", 2, "<lable>", "unknown element in <transformation>",
     "one of label, source, description, args, params, ports, tags, priority, constraints, requirements, bindings (did you mean 'label'?)"),
    ("missing_source", 2, "<transformation>", "missing <source>", "<source>package.module:Class</source>"),
    ("param_expansion", 6, "<param> 'rate'", "value 'two' is not a valid int", "a whole number such as 10 (in expansion N=two)"),
    ("malformed", 4, "", "malformed XML: a closing tag that does not match at column 30", "</port> closing the <port> opened at line 4"),
    ("arg_empty_set", 5, "<arg> 'Cam'", "empty set", 'values such as {cam1; cam2}, or class="ex:Class"'),
    ("stray_dollar", 4, "<description>", "stray '$' in 'costs $5'", "${Name} to use an arg, or $$ for a literal '$'"),
]  # fmt: skip


@pytest.mark.parametrize(("name", "line", "element", "what", "expected"), FIELDS, ids=[f[0] for f in FIELDS])
def test_issues_carry_their_fields(name: str, line: int, element: str, what: str, expected: str) -> None:
    """What the CLI prints is built from fields a program can read without parsing the text."""
    issue = next(i for i in issues_of(BROKEN / f"{name}.xml") if i.line == line)
    assert (issue.element, issue.what, issue.expected) == (element, what, expected)
    assert str(issue) == f"{BROKEN / name}.xml:{line}: " + (f"{element}: " if element else "") + f"{what}; expected {expected}"
    assert SpecIssue.from_dict(json.loads(json.dumps(issue.to_dict()))) == issue


def test_a_duplicate_label_across_files_names_the_first_place() -> None:
    issue = issues_of(SPECS / "dup")[0]
    assert issue.element == "<label>" and issue.expected == "each label once"
    assert issue.what.startswith("duplicate label ") and ", first defined at " in issue.what


def test_path_params_read_by_default_and_round_trip() -> None:
    specs = parse_specs(
        '<transformation><label>r</label><source>transformations.recording:RecorderUnit</source>'
        '<params><param name="out" type="path" mode="write">x.mcap</param><param name="in" type="path">y</param></params>'
        '<ports><port type="in">in</port></ports></transformation>'
    )
    assert [(p.name, p.type, p.mode) for p in specs[0].params] == [("out", "path", "write"), ("in", "path", "read")]
    assert parse_specs(specs[0].to_xml())[0].params == specs[0].params


RELAY_PORTS = '<ports><port type="in"{queue}>in</port><port type="out"{deadline}>out</port></ports>'


@pytest.mark.parametrize(
    ("declaration", "says"),
    [
        ("bogus", "unknown encoding: bogus"),
        ("rot13", "'rot13' is not a text encoding"),
        ("utf-32", "multi-byte encodings are not supported"),
        # found by fuzzing: the codec warns while pyexpat maps its bytes, and where warnings are
        # errors (as in this suite) the DeprecationWarning escaped the loader
        ("unicode_escape", "invalid escape sequence"),
    ],
)
def test_an_unknown_xml_encoding_is_a_located_error(tmp_path: pathlib.Path, declaration: str, says: str) -> None:
    path = tmp_path / "odd.xml"
    path.write_bytes(f'<?xml version="1.0" encoding="{declaration}"?>\n<transformation><label>x</label><source>m:C</source></transformation>'.encode())
    with pytest.raises(SpecError) as info:
        spec.load_specs([path])
    (issue,) = info.value.issues
    assert (issue.path, issue.line, issue.element) == (str(path), 1, "<?xml?>") and says in issue.what


@pytest.mark.parametrize(
    ("fragment", "says"),
    [
        (RELAY_PORTS.format(queue=' queue="100000000000000000000"', deadline=""), "'100000000000000000000' is too large; expected a queue size of at most 1,000,000"),
        (RELAY_PORTS.format(queue="", deadline=' deadline-ms="1e309"'), "'1e309' is not a positive number; expected milliseconds such as 500 (at most 86,400,000)"),
        ('<params><param name="v" type="float">1e309</param></params>', "value '1e309' is not a valid float; expected a finite number such as 0.5"),
        ('<params><param name="v" type="float">nan</param></params>', "is not a valid float"),
        ('<params><param name="n" type="int">99999999999999999999999</param></params>', "expected a whole number from -2**63 to 2**63-1"),
        # found by fuzzing: int() refuses over 4,300 digits with a ValueError, which escaped the loader
        ("<priority>" + "9" * 5000 + "</priority>", "<priority>: '999999999999999999999999999...' is out of range"),
        ("<priority>9223372036854775808</priority>", "expected a whole number from -2**63 to 2**63-1 (lower is preferred)"),
        ('<params><param name="n" type="int">' + "9" * 5000 + "</param></params>", "value '999999999999999999999999999...' is not a valid int"),
        # found by fuzzing: a constraint value of 1e309 compared as infinity and wrote itself back as 'inf'
        ('<constraints><constraint measure="battery" op="&lt;" value="1e309"/></constraints>', "'1e309' is out of range; expected a finite number"),
        ('<constraints><constraint measure="battery" op="==" value="' + "9" * 400 + '"/></constraints>', "<constraint> @value: '99999"),
    ],
)
def test_out_of_range_numbers_are_refused_where_they_are_written(tmp_path: pathlib.Path, fragment: str, says: str) -> None:
    path = tmp_path / "numbers.xml"
    ports = "" if "<ports>" in fragment else RELAY_PORTS.format(queue="", deadline="")
    path.write_text(f"<transformation>\n<label>x</label><source>m:C</source>\n{fragment}{ports}\n</transformation>\n")
    with pytest.raises(SpecError) as info:
        spec.load_specs([path])
    assert [(i.line, says in str(i)) for i in info.value.issues] == [(3, True)], [str(i) for i in info.value.issues]


NODE = """<transformations>
  <node name="/camera_${Cam}" middleware="dds" timeout-s="15">
    <label>camera-${Cam}</label>
    <args><arg label="Cam">{top; side}</arg></args>
    <params><param name="exposure" type="float">0.5</param></params>
    <topic type="std_msgs/msg/String" deadline-ms="1000">/camera_${Cam}/frames</topic>
    <tags><tag>Frames(${Cam})</tag></tags>
    <priority>0</priority>
  </node>
  <node name="/lidar" lifecycle="false">
    <label>lidar</label>
    <topic type="sensor_msgs/msg/PointCloud2">/points</topic>
    <tags><tag port="out">Points(front)</tag></tags>
  </node>
</transformations>
"""


def test_a_node_reads_as_the_transformation_of_its_managed_node() -> None:
    top, side, lidar = parse_specs(NODE)
    assert (top.label, top.source, top.priority) == ("camera-top", spec.model.MANAGED_NODE_SOURCE, 0)
    assert top.params == (
        Param("node", "string", "/camera_top"),
        Param("lifecycle", "bool", True),
        Param("timeout_s", "float", 15.0),
        Param("binding", "string", "ros2dds:/camera_top/frames?type=std_msgs/msg/String"),
        Param("ros.exposure", "float", 0.5),
    )
    assert top.ports == (Port("out", "out", 1000.0),) and top.tags == (Tag("out", "Frames(top)"),)
    assert side.param_values()["node"] == "/camera_side"
    assert lidar.param_values() == {"node": "/lidar", "lifecycle": False, "binding": "ros2:/points?type=sensor_msgs/msg/PointCloud2"}
    assert parse_specs(top.to_xml()) == [replace(top, path="<string>", line=2)]  # written back as its transformation


@pytest.mark.parametrize(
    ("fragment", "says"),
    [
        ('<node middleware="dds"><label>a</label><topic type="t/msg/T">/a</topic></node>', "<node>: missing @name; expected name=\"/camera_top\""),
        ('<node name="/a" middleware="fastdds"><label>a</label><topic type="t/msg/T">/a</topic></node>', "unknown middleware 'fastdds'; expected zenoh (rmw_zenoh) or dds (did you mean 'dds'?)"),
        ('<node name="/a" lifecycle="maybe"><label>a</label><topic type="t/msg/T">/a</topic></node>', "<node> @lifecycle: 'maybe' is not a boolean"),
        ('<node name="/a"><label>a</label></node>', "<node>: missing <topic>"),
        ('<node name="/a"><label>a</label><topic>/a</topic></node>', "<topic>: missing @type"),
        ('<node name="/a"><label>a</label><source>x:Y</source><topic type="t/msg/T">/a</topic></node>', "<source>: unknown element in <node>"),
        ('<node name="/a"><label>a</label><topic type="t/msg/T">/a</topic><tags><tag port="img">A</tag></tags></node>', "no port named 'img'; expected 'out'"),
    ],
)
def test_a_node_with_a_mistake_is_reported_where_it_is(fragment: str, says: str) -> None:
    with pytest.raises(SpecError) as caught:
        parse_specs(f"<transformations>\n  {fragment}\n</transformations>")
    assert any(says in issue.message and issue.line == 2 for issue in caught.value.issues), listing(caught.value.issues)
