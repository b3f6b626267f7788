"""Whether the unit a spec's ``<source>`` names can be found, without running any of its code.

``dyknow validate`` checks what a spawn would need: the module found as the manager finds it
(an installed or importable package first, then the spec file's own folder and the ``--path``
folders), and the class defined in it. Nothing is imported: packages and modules are located
with :class:`importlib.machinery.PathFinder` (which reads folders, and runs no
``__init__.py``), and the class is looked for in the module's source with :mod:`ast`. A module
the operator has not allowed (``--allow-source``) must not run just because a spec was checked.

What cannot be told without running code is given the benefit of the doubt: a compiled module
(its names are not in a source), a module with a ``__getattr__`` or a ``from x import *``.
"""

from __future__ import annotations

import ast
import importlib.machinery
import importlib.util
import os
import sys
from collections.abc import Iterable, Sequence
from typing import NamedTuple

from dyknow.errors import SpecIssue, did_you_mean
from dyknow.spec.model import TransformationSpec

__all__ = ["SourceRef", "source_issues"]


def _locate(module_name: str, folders: Sequence[str]) -> importlib.machinery.ModuleSpec | None:
    """The module's spec as the import system would find it, found without importing anything."""
    top, *rest = module_name.split(".")
    if top in sys.builtin_module_names:
        return importlib.machinery.ModuleSpec(top, None, origin="built-in")
    found = importlib.machinery.PathFinder.find_spec(top, [*sys.path, *folders])
    if found is None:  # installed through a finder of its own (an editable install): a top-level name imports nothing
        try:
            found = importlib.util.find_spec(top)
        except (ImportError, ValueError):
            found = None
    for part in rest:
        if found is None or not found.submodule_search_locations:
            return None
        found = importlib.machinery.PathFinder.find_spec(f"{found.name}.{part}", list(found.submodule_search_locations))
    return found


def _defined_names(source: str) -> set[str] | None:
    """The names a module's source defines at top level, or None when its source cannot tell
    (a ``__getattr__`` or a star import)."""
    try:
        tree = ast.parse(source)
    except SyntaxError:
        return None  # spawn says so, with the line: not this check's business
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {t.id for t in targets if isinstance(t, ast.Name)}
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            if any(alias.name == "*" for alias in node.names):
                return None
            names |= {(alias.asname or alias.name).partition(".")[0] for alias in node.names}
        elif isinstance(node, (ast.If, ast.Try)):
            return None  # names defined conditionally: do not guess
    return None if "__getattr__" in names else names


def _unit_candidates(source: str, module_name: str) -> set[str]:
    """The names a module offers as its own classes (to suggest for a misspelt one): the classes
    it defines and those it imports from its own package, never what it imports from elsewhere
    (``Unit``, the base class every unit module imports, was suggested)."""
    package = module_name.rpartition(".")[0] if module_name.count(".") else module_name
    names: set[str] = set()
    for node in ast.parse(source).body:
        if isinstance(node, ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith(f"{package}.")):
            names |= {alias.asname or alias.name for alias in node.names}
    return names - {"Unit"}


class SourceRef(NamedTuple):
    """A ``<source>`` as written: its file, line and text (``package.module:Class``)."""

    path: str
    line: int
    source: str


def source_issues(specs: Iterable[TransformationSpec | SourceRef], folders: Iterable[str | os.PathLike[str]] = ()) -> list[SpecIssue]:
    """One issue per spec (or ``<source>`` as written: :class:`SourceRef`) whose source module
    cannot be found, or whose module's source does not define the class; ``folders`` are the
    ``--path`` folders (each spec's own folder is looked in too, as the manager does for the
    specs its operator gives it). Imports nothing."""
    issues: list[SpecIssue] = []
    extra = [os.path.abspath(f) for f in folders]
    for spec in specs:
        module_name, sep, class_name = spec.source.partition(":")
        if not sep:
            continue  # not a source at all: the reader refuses that with its own message
        own = [os.path.dirname(os.path.abspath(spec.path))] if os.path.isfile(spec.path) else []
        looked = [*own, *[f for f in extra if f not in own]]
        found = _locate(module_name, looked)
        if found is None:
            top = module_name.partition(".")[0]
            package = _locate(top, looked) if top != module_name else None
            if package is not None and package.submodule_search_locations:
                where = ", ".join(package.submodule_search_locations)
                what = f"no module {module_name!r}: package {top!r} ({where}) has no {module_name.partition('.')[2]!r}"
                expected = f"{module_name.rpartition('.')[2]}.py in {where}"
            else:
                what = f"no module {module_name!r} found (looked in the installed packages and in {', '.join(looked) or 'no folder'})"
                expected = (f"{top}.py or a package {top}/ beside the spec file, in a folder given with --path DIR (as the "
                            "manager's --path), installed, or on PYTHONPATH")  # fmt: skip
            issues.append(SpecIssue(spec.path, spec.line, what, element="<source>", expected=expected))
            continue
        origin = found.origin
        if origin is None or not origin.endswith(".py") or not os.path.isfile(origin):
            continue  # compiled or built in: its names are not in a source
        with open(origin, encoding="utf-8", errors="replace") as file:
            source_text = file.read()
        names = _defined_names(source_text)
        if names is not None and class_name not in names:
            classes = sorted(n for n in _unit_candidates(source_text, module_name) if n[:1].isupper() and not n.isupper())
            issues.append(SpecIssue(
                spec.path, spec.line, f"module {module_name!r} ({origin}) defines no {class_name!r}",
                element="<source>",
                expected="a Unit subclass of that name" + (f", such as {', '.join(classes[:8])}" if classes else "")
                + did_you_mean(class_name, classes),
            ))  # fmt: skip
    return issues
