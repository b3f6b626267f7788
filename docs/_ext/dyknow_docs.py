"""Sphinx extension of dyknow's site: the CLI reference from argparse, and the API reference.

- ``{dyknow-cli}`` renders ``dyknow --help`` and each command's ``--help``, as the installed
  command prints them (``dyknow.cli.main``), so the reference cannot fall behind the parser.
- ``{dyknow-api} FAMILY`` documents the public names (``__all__``) of ``dyknow`` or of one
  family's package with autodoc; a family's names that ``dyknow`` re-exports are documented once,
  under ``dyknow``.
- References to where a public class is defined (``dyknow.spec.model.TransformationSpec``, as
  signatures name it) resolve to where it is documented (``dyknow.TransformationSpec``).
"""

from __future__ import annotations

import ast
import contextlib
import functools
import importlib
import inspect
import io
import os
import pkgutil
import re
import sys
from pathlib import Path
from typing import Any

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.application import Sphinx
from sphinx.pycode import ModuleAnalyzer
from sphinx.util.docutils import SphinxDirective

#: The packages whose ``__all__`` the API reference documents, in the order of its pages.
FAMILIES = ("dyknow", "dyknow.spec", "dyknow.reasoning", "dyknow.recording", "dyknow.testing", "dyknow.ui", "dyknow.demo")


def cli_help(*argv: str) -> str:
    """What ``dyknow ARGV --help`` prints, at a fixed width."""
    from dyknow.cli import main

    out = io.StringIO()
    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "80"  # what a page of the theme shows without scrolling
    try:
        with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
            main([*argv, "--help"])
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns
    return out.getvalue()


def cli_commands(*argv: str) -> list[str]:
    """The subcommands ``dyknow ARGV --help`` lists under its COMMAND argument."""
    text = cli_help(*argv)
    block = text.split("  COMMAND\n", 1)[1].split("\n\n", 1)[0] if "  COMMAND\n" in text else ""
    return re.findall(r"^    ([a-z][\w-]*)", block, re.MULTILINE)


class CliDirective(SphinxDirective):
    """``{dyknow-cli}``: a section per command with its ``--help``."""

    has_content = False

    def run(self) -> list[nodes.Node]:
        result: list[nodes.Node] = [nodes.literal_block(text=cli_help().rstrip(), language="text")]
        for command in cli_commands():
            argvs = [(command,)] + [(command, sub) for sub in cli_commands(command)]
            for argv in argvs:
                title = "dyknow " + " ".join(argv)
                section = nodes.section(ids=[nodes.make_id(title)], names=[nodes.fully_normalize_name(title)])
                section += nodes.title(text=title)
                section += nodes.literal_block(text=cli_help(*argv).rstrip(), language="text")
                self.state.document.note_implicit_target(section, section)
                result.append(section)
        return result


class ServicesDirective(SphinxDirective):
    """``{dyknow-services}``: a table of every service and its fields, from ``dyknow.service.SCHEMAS``."""

    has_content = False

    def run(self) -> list[nodes.Node]:
        from dyknow import service

        lines = ["| service | of | fields (required in bold) | read-only |", "|---|---|---|---|"]
        for name, schema in service.SCHEMAS.items():
            scope = "a unit" if name in service.UNIT_SERVICES else "a manager"
            fields = ", ".join(f"**`{field}`**" if required else f"`{field}`" for field, (required, _) in schema.items()) or "(none)"
            lines.append(f"| `{name}` | {scope} | {fields} | {'yes' if name in service.READ_ONLY_SERVICES else ''} |")
        container = nodes.container()
        self.state.nested_parse(StringList(lines, source="<dyknow-services>"), self.content_offset, container)
        return container.children


#: The reference's order for ``dyknow``'s names: what a user meets first comes first (a manager,
#: a unit, its messages, a client), then specs, what the manager reports, recording, planning,
#: security, and the errors last; a name not listed follows in ``__all__`` order.
READING_ORDER = [
    "Manager", "Unit", "Message", "Client", "DEFAULT_ENDPOINT", "Timer",
    "load_specs", "parse_specs", "TransformationSpec", "Port", "Param", "Tag", "Constraint", "Template", "Library",
    "Model", "UnitInfo", "UnitState", "UnitStatistics", "PortStatistics", "LatencySummary", "RequestInfo", "UnitEvent",
    "AdaptationEvent", "default_key",
    "Recorder", "Player", "Recording", "RecordingInfo", "ChannelInfo", "RecordedMessage",
    "plan", "Plan", "Planner", "RunningUnit", "Ontology", "Term", "parse_term",
    "TlsFiles", "AccessControl", "Limits",
    "DyKnowError",
]  # fmt: skip


def public_names(family: str) -> list[str]:
    """The names ``family`` documents: its ``__all__``, less what ``dyknow`` re-exports; for
    ``dyknow``, in :data:`READING_ORDER`, then the rest (errors last)."""
    module = importlib.import_module(family)
    names = list(module.__all__)
    if family != "dyknow":
        top = importlib.import_module("dyknow")
        return [n for n in names if not (n in top.__all__ and getattr(top, n) is getattr(module, n))]
    first = [n for n in READING_ORDER if n in names]
    rest = [n for n in names if n not in first]
    errors = [n for n in rest if isinstance(getattr(module, n), type) and issubclass(getattr(module, n), BaseException)]
    return first + [n for n in rest if n not in errors] + errors


class ApiDirective(SphinxDirective):
    """``{dyknow-api} FAMILY``: autodoc of the family's public names."""

    required_arguments = 1
    has_content = False

    def run(self) -> list[nodes.Node]:
        family = self.arguments[0]
        module = importlib.import_module(family)
        # the pages are MyST Markdown, and autodoc writes reStructuredText: hand it to eval-rst
        lines = ["```{eval-rst}", f".. automodule:: {family}", "   :no-members:", ""]  # its docstring, then its names
        for name in public_names(family):
            obj = getattr(module, name)
            if inspect.isclass(obj):
                kind = "exception" if issubclass(obj, BaseException) else "class"
            elif inspect.isroutine(obj):
                kind = "function"
            else:
                kind = "data"
            if kind == "data":
                lines += data_directive(family, name, obj)
            else:
                lines += [f".. auto{kind}:: {family}.{name}"]
                if inspect.isclass(obj) and obj.__bases__ != (object,):
                    lines += ["   :show-inheritance:"]  # Bases: DyKnowError, Unit; never Bases: object
                lines += [""]
        lines += ["```"]
        container = nodes.container()
        self.state.nested_parse(StringList(lines, source=f"<dyknow-api {family}>"), self.content_offset, container)
        return container.children


def data_directive(family: str, name: str, obj: object) -> list[str]:
    """A constant, with the ``#:`` comment or docstring of the module that defines it.

    ``autodata`` would show the docstring of the value's type (``str``, ``dict``) instead, since the
    comment sits in the defining module, not in the family's ``__init__`` that re-exports it.
    """
    doc: list[str] = []
    package = importlib.import_module(family)
    candidates = [family] + [f"{family}.{m.name}" for m in pkgutil.iter_modules(getattr(package, "__path__", []))]
    candidates += [f"dyknow.{m.name}" for m in pkgutil.iter_modules(importlib.import_module("dyknow").__path__)]
    for candidate in candidates:  # (it grows: a package that re-exports the name adds its modules)
        try:
            module = importlib.import_module(candidate)
            if getattr(module, name, None) is not obj:
                continue
            doc = ModuleAnalyzer.for_module(candidate).find_attr_docs().get(("", name), [])
            if not doc and candidate != family and hasattr(module, "__path__"):  # defined in one of its modules
                candidates += [f"{candidate}.{m.name}" for m in pkgutil.iter_modules(module.__path__)]
        except Exception:  # a module without source (compiled) or one that needs an extra
            continue
        if doc:
            break
    value = repr(obj)
    lines = [f".. py:data:: {name}"]  # in the current module, set by py:module
    if len(value) <= 120:
        lines += [f"   :value: {value}"]
    lines += [""] + [f"   {line}" for line in doc] + [""]
    return lines


def _documented() -> dict[int, str]:
    """id(object) -> the name it is documented under, for every public class and function."""
    found: dict[int, str] = {}
    for family in FAMILIES:
        module = importlib.import_module(family)
        for name in public_names(family):
            obj = getattr(module, name)
            if inspect.isclass(obj) or inspect.isroutine(obj):
                found.setdefault(id(obj), f"{family}.{name}")
    return found


def _lookup(target: str) -> tuple[object, str, list[str]] | None:
    """The object ``target`` names, the module part of the name and the attributes after it."""
    parts = target.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return None
            obj = getattr(obj, attr)
        return obj, ".".join(parts[:i]), parts[i:]
    return None


def _module_exists(name: str) -> bool:
    """Whether ``name`` is a module of dyknow, found without running it: the site is built with
    the ``docs`` extra alone (``make docs``), where a module that needs another extra
    (``dyknow.testing.fuzzing``: Hypothesis) cannot be imported but is no broken reference."""
    import importlib.util

    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def resolve_public_alias(app: Sphinx, env: Any, node: Any, contnode: nodes.Element) -> nodes.Element | None:
    """A Python reference to where a public object is defined resolves to where it is documented.

    ``dyknow.spec.model.TransformationSpec`` (as signatures name it) resolves to
    ``dyknow.TransformationSpec``, and ``dyknow.manager.Manager.request`` to
    ``dyknow.Manager.request``. In the reference pages, a name that exists but is internal (not in
    any ``__all__``: ``dyknow.clocks``, ``dyknow.planner.Rejection``, as docstrings name them) is shown as text; a name
    that does not exist stays a broken reference, which fails the build.
    """
    if node.get("refdomain") != "py":
        return None
    target = str(node.get("reftarget", ""))
    if not target.startswith("dyknow."):
        return None
    found = _lookup(target)
    if found is None:
        if node["refdoc"].startswith("reference/") and _module_exists(target):
            return contnode  # a module that needs an extra the docs do not install (dyknow.testing.fuzzing): text
        return None
    obj, module_name, attrs = found
    documented = _documented()
    public = documented.get(id(obj))
    if public is None:  # a method or attribute of a public class: map the class
        holder: object = importlib.import_module(module_name)
        for i, attr in enumerate(attrs[:-1]):
            holder = getattr(holder, attr)
            if id(holder) in documented:
                public = ".".join([documented[id(holder)], *attrs[i + 1 :]])
                break
    if public is not None and public != target:
        ref = env.get_domain("py").resolve_xref(env, node["refdoc"], app.builder, node["reftype"], public, node, contnode)
        if ref is not None:
            return ref
    if node["refdoc"].startswith("reference/"):
        return contnode  # internal (in a docstring the reference shows): text, not a link
    return None


@functools.cache
def _source_docstrings(module_name: str) -> dict[str, str]:
    """Qualified name -> docstring of every class, function and method in a module's source."""
    module = sys.modules.get(module_name) or importlib.import_module(module_name)
    source = Path(str(module.__file__)).with_name(module_name.rsplit(".", 1)[-1] + ".py")
    if not source.is_file():
        return {}
    found: dict[str, str] = {}

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                found[prefix + child.name] = ast.get_docstring(child) or ""
                if isinstance(child, ast.ClassDef):
                    walk(child, f"{prefix}{child.name}.")

    tree = ast.parse(source.read_text(encoding="utf-8"))
    found[""] = ast.get_docstring(tree) or ""  # the module's own
    walk(tree, "")
    return found


def _compiled_docstring(obj: Any) -> str:
    """The source's docstring of a module, function, class or method of dyknow, or ""."""
    if inspect.ismodule(obj):
        return _source_docstrings(obj.__name__).get("", "") if obj.__name__.startswith("dyknow") else ""
    module_name = getattr(obj, "__module__", None) or getattr(getattr(obj, "__objclass__", None), "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if not (isinstance(module_name, str) and module_name.startswith("dyknow") and isinstance(qualname, str)):
        return ""
    return _source_docstrings(module_name).get(qualname, "")


def restore_compiled_docstring(app: Sphinx, what: str, name: str, obj: Any, options: Any, lines: list[str]) -> None:
    """Modules compiled by mypyc (setup.py) lose their docstrings and those of their functions and
    methods (``dyknow.reasoning.evaluate``, ``Monitor.push``); take them from the source beside
    the compiled module."""
    if "".join(lines).strip() in ("", "mypyc filler docstring") and (doc := _compiled_docstring(obj)):
        lines[:] = inspect.cleandoc(doc).splitlines() + [""]


def keep_compiled_members(app: Sphinx, what: str, name: str, obj: Any, skip: bool, options: Any) -> bool | None:
    """A public method of a compiled class has no ``__doc__``, so autodoc would leave it out."""
    if skip and not name.startswith("_") and _compiled_docstring(obj):
        return False
    return None


def setup(app: Sphinx) -> dict[str, Any]:
    """Register the directives and the reference resolver."""
    app.add_directive("dyknow-cli", CliDirective)
    app.add_directive("dyknow-api", ApiDirective)
    app.add_directive("dyknow-services", ServicesDirective)
    app.connect("missing-reference", resolve_public_alias)
    app.connect("autodoc-process-docstring", restore_compiled_docstring)
    app.connect("autodoc-skip-member", keep_compiled_members)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
