"""dyknow.spec.model: the dataclasses, constraints, JSON and writing XML back."""

from __future__ import annotations

import json

import pytest
import xmlschema

from dyknow.spec import (
    Constraint,
    Param,
    Port,
    Tag,
    TransformationSpec,
    load_specs,
    parse_specs,
)
from tests.spec.support import GOOD, SPECS, XSD, robots


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
        "param_types": {"camera": "string", "rate": "int", "threshold": "float", "gpu": "bool"},
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
        "requirements": ["not historically[0, 2s] Objects(rear).count < 1"],
        "bindings": {},
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


def test_to_xml_keeps_a_carriage_return() -> None:
    """Found by fuzzing: a '\r' (from '&#13;' in a spec) was written as such, and XML reads a
    written carriage return as a newline, so the spec came back changed."""
    s = TransformationSpec(
        label="ab",  # a label may hold no control character at all
        source="m:C",
        params=(Param("text", "string", "x\ry"),),
        ports=(Port("o", "out"),),
        tags=(Tag("o", "F(\ra)"),),
        constraints=(Constraint("mode", "==", "p\rq"),),
        description="one\rtwo\r\nthree",
        args=(("Cam", "c\rd"),),
    )
    (back,) = parse_specs(s.to_xml(), "round.xml")
    assert without_location(back) == without_location(s)


