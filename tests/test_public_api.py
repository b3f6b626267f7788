"""The public surface: one sorted __all__, locked here so changes are deliberate."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys

import pytest

import dyknow

EXPECTED = [
    "DEFAULT_ENDPOINT", "AccessControl", "AccessError", "AdaptationEvent", "BindingError", "ChannelInfo", "Client", "ClosedError",
    "Constraint", "DyKnowError", "FormulaError", "LatencySummary", "Library", "LibraryError", "Limits", "Manager", "Message",
    "Model", "Ontology", "OntologyError", "Param", "PayloadError", "Plan", "Planner",
    "PlanningError", "Player", "Port", "PortStatistics", "RecordedMessage", "Recorder", "Recording",
    "RecordingError", "RecordingInfo", "RequestInfo", "RunningUnit", "ServiceError", "SpecError",
    "SpecIssue", "Tag", "TagError", "Template", "Term", "Timer", "TlsFiles", "TransformationSpec",
    "TransportError", "Unit", "UnitError", "UnitEvent", "UnitInfo", "UnitState", "UnitStatistics",
    "__version__", "default_key", "load_specs", "parse_specs", "parse_term", "plan",
]  # fmt: skip


def test_all_is_sorted_and_locked() -> None:
    def kind(name: str) -> int:  # constants, then classes, then functions (isort's order)
        return 0 if name.isupper() else 1 if name[0].isupper() else 2

    assert dyknow.__all__ == sorted(dyknow.__all__, key=lambda n: (kind(n), n))
    assert dyknow.__all__ == EXPECTED
    for name in dyknow.__all__:
        assert getattr(dyknow, name) is not None


def test_every_error_derives_from_the_root() -> None:
    for name in dyknow.__all__:
        obj = getattr(dyknow, name)
        if isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, dyknow.DyKnowError), name


@pytest.mark.process
def test_import_does_not_pull_opencv() -> None:
    code = "import sys, dyknow; print('cv2' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _public_members(cls: type) -> list[tuple[str, object]]:
    """Public methods and properties a class of dyknow defines (itself or through dyknow bases)."""
    found: dict[str, object] = {}
    for klass in reversed(cls.__mro__):
        if not klass.__module__.startswith("dyknow"):
            continue
        for name, value in vars(klass).items():
            if name.startswith("_"):
                continue
            if isinstance(value, (staticmethod, classmethod)):
                value = value.__func__
            if inspect.isfunction(value) or isinstance(value, property):
                found[name] = value
    return sorted(found.items())


def test_every_public_name_and_method_is_documented() -> None:
    missing = []
    for name in dyknow.__all__:
        obj = getattr(dyknow, name)
        if not (inspect.isclass(obj) or inspect.isfunction(obj)):
            continue  # constants and the version string
        if not inspect.getdoc(obj):
            missing.append(name)
        if inspect.isclass(obj):
            missing += [f"{name}.{member}" for member, value in _public_members(obj) if not (value.__doc__ or "").strip()]
    assert missing == []


# the public names of dyknow and of each family's package, as the API reference documents them
FAMILIES = ["dyknow", "dyknow.spec", "dyknow.reasoning", "dyknow.recording", "dyknow.testing", "dyknow.ui", "dyknow.demo"]


def _public_names() -> list[str]:
    import importlib

    return [f"{family}.{name}" for family in FAMILIES for name in importlib.import_module(family).__all__]


def test_help_renders_every_public_name() -> None:
    """``help(dyknow.Unit)`` crashed: pydoc (and Sphinx's autodoc) probe attributes such as ``__objclass__``."""
    import importlib
    import pydoc

    failed = []
    for dotted in FAMILIES + _public_names():
        family, _, name = dotted.rpartition(".")
        obj = importlib.import_module(dotted) if dotted in FAMILIES else getattr(importlib.import_module(family), name)
        if not (inspect.ismodule(obj) or inspect.isclass(obj) or callable(obj)):
            continue  # constants: pydoc would look a string up as a name; their module's page shows them
        try:
            text = pydoc.render_doc(obj, renderer=pydoc.plaintext)
        except Exception as exc:  # every failure is listed, not only the first
            failed.append(f"{dotted}: {type(exc).__name__}: {exc}")
            continue
        assert text.startswith("Python Library Documentation"), dotted
    assert failed == []
    assert "Base class of computation units" in pydoc.render_doc(dyknow.Unit, renderer=pydoc.plaintext)


def test_every_public_class_of_every_family_has_its_docstring() -> None:
    """Compiling with mypyc takes class docstrings away; each family's package gives them back."""
    import importlib

    missing = []
    for dotted in _public_names():
        family, _, name = dotted.rpartition(".")
        obj = getattr(importlib.import_module(family), name)
        if inspect.isclass(obj) and (obj.__doc__ or "").strip() in ("", "mypyc filler docstring"):
            missing.append(dotted)
    assert missing == []


@pytest.mark.process
def test_help_runs_in_a_fresh_interpreter() -> None:
    """As a user types it: ``help(dyknow.Unit)`` with no pager."""
    code = "import dyknow; help(dyknow.Unit); help(dyknow.Manager); help(dyknow)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=dict(os.environ, PAGER="cat"))
    assert out.returncode == 0, out.stderr[-2000:]
    assert "class Unit" in out.stdout and "class Manager" in out.stdout
