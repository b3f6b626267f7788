"""The manager's library: the specs loaded at start and added at runtime, and who gave each.

A :class:`Librarian` keeps the manager's :class:`~dyknow.library.Library` and decides what comes
in: a spec from the operator (files at start, the Python API) is trusted, so the module it names
may be loaded and is looked for beside the spec file too; a spec from a remote caller (the
``add_transformation`` service) must be XML text naming allowed sources only, and the file params
of its units are confined to the data roots when they are spawned (:mod:`dyknow.manager.spawning`).
From anyone, a spec whose ``<requirement>`` is over the manager's formula bounds
(:func:`~dyknow.reasoning.check_formula`) is refused when it is added, naming the requirement and the
bound: the manager could not watch it, and a request it served would run unwatched.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterable

from dyknow.errors import AccessError, FormulaError, LibraryError, SpecError, SpecIssue, compose
from dyknow.library import Library
from dyknow.ontology import Ontology
from dyknow.reasoning.syntax import check_formula
from dyknow.security import DEFAULT_SOURCES, Limits, SourcePolicy, module_of
from dyknow.spec import Template, TransformationSpec, load_specs, parse_specs
from dyknow.spec.model import shorten

__all__ = ["SOURCE_SYNTAX", "Librarian"]

SOURCE_SYNTAX = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*")
"""What a unit's source looks like: ``package.module:Class``."""


class Librarian:
    """The manager's library, where its specs came from, and where their units' code may be loaded from.

    ``specs``: spec files, directories of ``*.xml`` files, or specs, loaded now (bad specs fail
    before anything starts). ``allow_sources``: unit sources allowed beyond ``dyknow``,
    ``transformations`` and the modules the operator's specs name; ``code_paths``: folders unit
    modules are looked for in (``--path``).
    """

    def __init__(
        self,
        *,
        specs: Iterable[str | os.PathLike[str] | TransformationSpec],
        ontology: Ontology | None,
        limits: Limits,
        allow_sources: Iterable[str],
        code_paths: Iterable[str | os.PathLike[str]],
    ) -> None:
        self._ontology = ontology
        self._limits = limits
        self.library = Library(max_specs=limits.max_library_specs, max_bytes=limits.max_library_bytes)
        #: the unit sources the manager may import
        self.sources = SourcePolicy([*DEFAULT_SOURCES, *allow_sources])
        #: folders unit modules are looked for in (--path, the trusted specs' own)
        self.code_paths: list[str] = []
        for folder in code_paths:
            if not os.path.isdir(folder):
                raise LibraryError(f"code path {os.fspath(folder)!r} is not a folder", expected="a folder holding unit modules (--path DIR)")
            self.code_paths.append(os.path.abspath(folder))
        self._remote_labels: set[str] = set()  # added through the service: their params are checked
        spec_objs = [s for s in specs if isinstance(s, TransformationSpec)]
        paths = [s for s in specs if not isinstance(s, TransformationSpec)]
        if paths:
            # bad specs fail before anything starts
            loaded = load_specs(paths, individuals=self.individuals_or_none(), max_expansions=limits.max_expansions, limits=limits)
            self.trust(loaded)
            self.library.add(loaded)
        self._check_requirements(spec_objs)
        self.trust(spec_objs)
        self.library.add(spec_objs)
        #: the folders of the spec files given at start (file params may read there)
        self.spec_dirs = [p if os.path.isdir(p) else os.path.dirname(os.path.abspath(p)) for p in (os.fspath(q) for q in paths)]

    def add(self, spec: TransformationSpec | Template | str | os.PathLike[str], *, path: str | None = None, remote: bool = False) -> list[str]:
        """Store a spec, or every expansion of a template; returns the labels added (see
        :meth:`dyknow.manager.Manager.add_transformation`)."""
        individuals = self.individuals_or_none()
        limit = self._limits.max_expansions
        if remote:
            if not isinstance(spec, str) or not spec.lstrip().startswith("<"):
                raise AccessError(
                    "a remote caller may only send XML text",
                    where="field 'xml'",
                    expected="the spec's XML (the client reads files on its side)",
                )
            specs = parse_specs(
                spec,
                path or "<remote>",
                individuals=individuals,
                max_expansions=limit,
                max_bytes=self._limits.max_expansion_bytes,
                limits=self._limits,
            )
            for one in specs:
                self.sources.check(one.source, where=f"transformation {one.label!r} ({one.location})")
        elif isinstance(spec, TransformationSpec):
            specs = [spec]
            self._check_requirements(specs)
        elif isinstance(spec, Template):
            specs = spec.expand(individuals, max_expansions=limit, limits=self._limits)
        elif isinstance(spec, os.PathLike) or (isinstance(spec, str) and not spec.lstrip().startswith("<")):
            specs = load_specs([spec], individuals=individuals, max_expansions=limit, limits=self._limits)
        elif isinstance(spec, str):
            specs = parse_specs(spec, path or "<add_transformation>", individuals=individuals, max_expansions=limit, limits=self._limits)
        else:
            raise LibraryError(f"add_transformation got a {type(spec).__name__}", expected="a spec, a template, XML text or a path")
        added = {s.label for s in specs}
        was_remote = added & self._remote_labels
        if remote:
            self._remote_labels.update(added)
        else:
            self.trust(specs)
            self._remote_labels.difference_update(added)
        try:
            return self.library.add(specs)
        except LibraryError:  # past the library's bounds: nothing added, the labels as they were
            self._remote_labels.difference_update(added - was_remote)
            self._remote_labels.update(was_remote)
            raise

    def remove(self, label: str) -> bool:
        """Forget the spec with ``label``; returns whether there was one."""
        removed = self.library.remove(label)
        self._remote_labels.discard(label)
        return removed

    def added_remotely(self, label: str) -> bool:
        """Whether the spec ``label`` came from a remote caller (its units' file params are confined)."""
        return label in self._remote_labels

    def trust(self, specs: Iterable[TransformationSpec]) -> None:
        """Specs from the operator (files at start, the Python API): their modules may be loaded,
        and are looked for beside the spec file too."""
        for spec in specs:
            folder = os.path.dirname(os.path.abspath(spec.path)) if os.path.isfile(spec.path) else None
            if folder is not None and folder not in self.code_paths:
                self.code_paths.append(folder)
            if self.sources.allows(spec.source) or not SOURCE_SYNTAX.fullmatch(spec.source):
                continue  # allowed already, or not a source at all (refused with its own message at spawn)
            self.sources.allow(module_of(spec.source))

    def _check_requirements(self, specs: Iterable[TransformationSpec]) -> None:
        """:class:`SpecError` at each spec built in Python (not read from XML, where the reader
        holds them to the bounds at the requirement's line) whose requirements are over this
        manager's formula bounds."""
        issues: list[SpecIssue] = []
        for spec in specs:
            for text in spec.requirements:
                try:
                    check_formula(text, self._limits)
                except FormulaError as exc:
                    element = f"<requirement> {shorten(text, 80)!r}"
                    issues.append(SpecIssue(spec.path, spec.line, compose(exc.what, exc.where), element, exc.expected or ""))
        if issues:
            raise SpecError(issues)

    def individuals(self, class_ref: str) -> list[str]:
        """The individuals of an ontology class, for a template's ``arg class``."""
        if self._ontology is None:
            raise LibraryError(f"template arg class {class_ref!r} needs an ontology", expected="ontology=[...] (--ontology FILE)")
        return self._ontology.individuals(class_ref)

    def individuals_or_none(self) -> Callable[[str], list[str]] | None:
        """:meth:`individuals` when the manager has an ontology (templates expand over its classes)."""
        return self.individuals if self._ontology is not None else None
