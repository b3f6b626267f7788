"""specs/transformation.xsd agrees with the loader: same elements, attributes and values."""

from __future__ import annotations

import pathlib

import pytest
import xmlschema
from xmlschema.validators import XsdAtomicRestriction

from dyknow import spec
from dyknow.errors import SpecError
from dyknow.spec import (
    load_specs,
)
from dyknow.spec.modefile import STATES as MODE_STATES
from tests.spec.support import BROKEN, GOOD, REPO_SPECS, SPECS, XSD


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
    assert set(schema.elements) == {"transformations", "transformation", "node", "system"}  # the possible roots


@pytest.mark.parametrize(
    ("type_name", "values"),
    [
        ("paramType", spec.PARAM_TYPES),
        ("constraintOp", spec.CONSTRAINT_OPS),
        ("portDirection", spec.PORT_DIRECTIONS),
        ("transformationType", spec.TRANSFORMATION_TYPES),
        ("pathMode", spec.PATH_MODES),
        ("nodeMiddleware", spec.NODE_MIDDLEWARES),
        ("partState", MODE_STATES),
    ],
)
def test_xsd_enumerations_match_the_loader(schema: xmlschema.XMLSchema, type_name: str, values: tuple[str, ...]) -> None:
    simple_type = schema.types[type_name]
    assert isinstance(simple_type, XsdAtomicRestriction)
    assert tuple(simple_type.enumeration or ()) == values
