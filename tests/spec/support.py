"""What the spec tests share: the fixture folders and helpers to collect issues."""

from __future__ import annotations

import pathlib
from collections.abc import Sequence

import pytest

from dyknow import spec
from dyknow.errors import SpecError, SpecIssue
from dyknow.spec import load_specs

TESTS = pathlib.Path(__file__).parent.parent
SPECS = TESTS / "specs"
BROKEN = SPECS / "broken"
GOOD = SPECS / "good"
REPO_SPECS = TESTS.parent / "specs"
XSD = REPO_SPECS / "transformation.xsd"

ROBOTS = {"ex:Robot": ["r1", "r2"], "ex:Camera": ["front", "rear"]}


def robots(class_ref: str) -> Sequence[str]:
    """A stand-in ontology: the individuals of two classes."""
    return ROBOTS[class_ref]


def issues_of(paths: spec.PathsLike, individuals: spec.Individuals | None = None) -> tuple[SpecIssue, ...]:
    """The issues loading ``paths`` raises (fails if it loads)."""
    with pytest.raises(SpecError) as info:
        load_specs(paths, individuals)
    return info.value.issues


def listing(issues: Sequence[SpecIssue]) -> str:
    """The issues as the CLI prints them."""
    return "\n".join(map(str, issues))
