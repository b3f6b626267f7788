"""Ontologies: classes, their subclass hierarchy and individuals, loaded offline with rdflib.

An :class:`Ontology` gives tags their meaning. With ``dk:BallObject rdfs:subClassOf
dk:WorldObject`` loaded, a port tagged ``BallObject(rel)`` satisfies a request for
``WorldObject(rel)`` (and not the other way round); ``<arg class="dk:Camera"/>`` in a template
expands to the individuals of ``dk:Camera``. Without any ontology (:meth:`Ontology.empty`) every
functor matches only itself, so specs work without one.

**Loading** (:meth:`Ontology.load`) never touches the network. The format follows the extension
(``.ttl`` Turtle, ``.n3`` N3, ``.rdf``/``.owl``/``.xml`` RDF/XML, ``.nt`` N-Triples; otherwise
Turtle, then RDF/XML). Each ``owl:imports <IRI>`` is satisfied, in this order, by the ``imports``
mapping (IRI -> path); by a file already loaded that declares ``<IRI> a owl:Ontology`` (so giving
``sosa.ttl`` explicitly satisfies ``ssn.ttl``'s import of it); by a file in the importing file's
folder or in ``search_dirs`` named after the IRI's fragment or last path segment plus a known
extension (``<http://www.w3.org/ns/sosa/>`` -> ``sosa.ttl``); by a file in those folders that
declares ``<IRI> a owl:Ontology``. IRIs compare without a trailing ``/`` or ``#``. Imports are
followed recursively (the given files first, then their imports, breadth first) and each file is
loaded once, so cycles are harmless. A file that fails to parse fails the whole load: nothing is
partially loaded.

**Name resolution** (:meth:`Ontology.resolve`) turns a functor into an IRI:

1. ``<IRI>`` (or a bare ``scheme://...`` IRI) is that IRI;
2. ``p:Local``, when a loaded file declares the prefix ``p``, is the prefix's namespace plus
   ``Local``. Prefixes are the union of every file's own declarations; when two files bind the same
   prefix to different namespaces, the file loaded first (the given paths in order, then their
   imports) wins;
3. otherwise the local name (``Local`` of ``p:Local`` with an undeclared ``p``, or the plain
   name) is looked up among all classes: subjects and objects of ``rdfs:subClassOf`` and things
   typed ``owl:Class`` or ``rdfs:Class``. Two classes with that local name make the name
   ambiguous: :class:`~dyknow.errors.OntologyError` lists them.

An IRI from rules 1 and 2 counts only when it occurs in a loaded file; a name in no ontology
resolves to ``None``.

**Matching** (:meth:`Ontology.matches`): the args must have the same count and be pairwise equal
by local name (``dk:rel``, ``rel`` and ``<https://dyknow.dev/ontology#rel>`` are one arg). Two
resolved functors match when the provided class is a subclass of the required one (reflexive,
transitive ``rdfs:subClassOf``). An unresolved functor matches only another unresolved functor
with the same local name: a class of the ontology never matches a name outside it. The transitive
closure is computed once at load time, so matching is a few dictionary lookups.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax import SAXParseException

from rdflib import BNode, Graph, Literal, URIRef
from rdflib.namespace import OWL, RDF, RDFS

from dyknow.errors import OntologyError, did_you_mean
from dyknow.tags import Term, local_name, parse_term

__all__ = ["FORMATS", "Ontology"]

log = logging.getLogger(__name__)

FORMATS: Mapping[str, str] = {".ttl": "turtle", ".n3": "n3", ".rdf": "xml", ".owl": "xml", ".xml": "xml", ".nt": "nt"}
"""The rdflib parser for each known file extension."""

_FORMAT_NAMES = {"turtle": "Turtle", "n3": "N3", "xml": "RDF/XML", "nt": "N-Triples"}
_GUESSES = ("turtle", "xml")  # for files with an unknown extension
_MISSING_IMPORTS = ("error", "warn")
_IMPORT_HINT = "pass imports={IRI: PATH} (CLI: --ontology PATH) or add its folder to search_dirs"
_EXTENSIONS = "{" + ",".join(ext[1:] for ext in FORMATS) + "}"
_LOCAL = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]*")

PathLike = str | os.PathLike[str]


@dataclass(frozen=True, slots=True)
class _File:
    """One parsed ontology file."""

    path: Path
    graph: Graph
    prefixes: tuple[tuple[str, str], ...]
    declares: frozenset[str]  # the normalised IRIs it declares ``a owl:Ontology``
    imports: tuple[str, ...]


class Ontology:
    """Classes and individuals from RDF files (Turtle or RDF/XML), loaded offline with rdflib.

    Build one with :meth:`load` or :meth:`empty`; the constructor wraps an rdflib graph already
    in memory. An ontology does not change once built, so it is safe to share between threads.
    """

    def __init__(self, graph: Graph | None = None, *, prefixes: Mapping[str, str] | None = None, files: Sequence[str] = ()) -> None:
        graph = graph if graph is not None else Graph(bind_namespaces="none")
        self._prefixes = dict(prefixes or {})
        self._files = tuple(files)
        self._resolved: dict[str, str | None] = {}
        self._triples = len(graph)
        # Everything the queries need is indexed into plain dicts and sets of strings; the rdflib
        # graph (tens of thousands of small objects for SOSA/SSN) is not kept, so it costs the
        # garbage collector nothing while a robot runs.
        self._index(graph)

    @classmethod
    def load(
        cls,
        paths: PathLike | Iterable[PathLike],
        *,
        search_dirs: Iterable[PathLike] = (),
        imports: Mapping[str, PathLike] | None = None,
        missing_imports: str = "error",
    ) -> Ontology:
        """Load ontology files and, recursively, the local copies of what they ``owl:imports``.

        ``imports`` maps an imported IRI to the local file holding it; ``search_dirs`` are more
        folders to look for imports in (see the module docstring for the order). A missing import
        raises :class:`~dyknow.errors.OntologyError`, or only logs a warning with
        ``missing_imports="warn"`` (the classes of that module are then unknown).
        """
        if missing_imports not in _MISSING_IMPORTS:
            raise ValueError(f"missing_imports={missing_imports!r}; expected 'error' or 'warn'")
        loader = _Loader(search_dirs, imports or {}, warn=missing_imports == "warn")
        files = loader.load([paths] if isinstance(paths, str | os.PathLike) else list(paths))
        graph = Graph(bind_namespaces="none")
        prefixes: dict[str, str] = {}
        for file in files:
            graph += file.graph
            for prefix, namespace in file.prefixes:
                prefixes.setdefault(prefix, namespace)  # the first file to bind a prefix wins
        return cls(graph, prefixes=prefixes, files=[str(f.path) for f in files])

    @classmethod
    def empty(cls) -> Ontology:
        """An ontology without classes: every functor then matches only itself."""
        return cls()

    @property
    def files(self) -> tuple[str, ...]:
        """Every file loaded, imports included, in load order."""
        return self._files

    @property
    def classes(self) -> frozenset[str]:
        """The IRIs of every class."""
        return self._classes

    def __len__(self) -> int:
        """The number of triples."""
        return self._triples

    def __repr__(self) -> str:
        return f"Ontology(files={len(self._files)}, classes={len(self._classes)}, triples={len(self)})"

    def resolve(self, name: str) -> str | None:
        """The full IRI a functor or class name stands for, or ``None`` when it is in no ontology.

        Raises :class:`~dyknow.errors.OntologyError` when a local name belongs to several classes.
        """
        try:
            return self._resolved[name]
        except KeyError:
            pass
        iri = self._resolve(name.strip())
        self._resolved[name] = iri
        return iri

    def is_subclass(self, sub: str, sup: str) -> bool:
        """Whether class IRI ``sub`` is ``sup`` or a (transitive) ``rdfs:subClassOf`` it."""
        return sub == sup or sup in self._ancestors.get(sub, ())

    def descendants(self, iri: str) -> frozenset[str]:
        """The class ``iri`` and all its subclasses (just ``{iri}`` for an IRI that is no class)."""
        return self._descendants.get(iri) or frozenset((iri,))

    def matches(self, provided: Term | str, required: Term | str) -> bool:
        """Whether a stream tagged ``provided`` satisfies a request for ``required``.

        Args must be pairwise equal by local name; the provided functor must be a subclass of the
        required one, or both must be unresolved with equal local names.
        """
        have = provided if isinstance(provided, Term) else parse_term(provided)
        want = required if isinstance(required, Term) else parse_term(required)
        if len(have.args) != len(want.args):
            return False
        if have.args != want.args and any(local_name(a) != local_name(b) for a, b in zip(have.args, want.args, strict=True)):
            return False
        sub, sup = self.resolve(have.functor), self.resolve(want.functor)
        if sub is None or sup is None:
            return sub is None and sup is None and local_name(have.functor) == local_name(want.functor)
        return self.is_subclass(sub, sup)

    def individuals(self, class_ref: str) -> list[str]:
        """The names of the individuals of a class, for ``<arg class="dk:Camera"/>`` in templates.

        ``class_ref`` is resolved like a functor. Every individual typed (``rdf:type``) the class
        or one of its subclasses gives its ``rdfs:label`` (a label without language tag first, then
        English, then any; the smallest of several) or else its local name. The result is sorted
        and has no duplicates.
        """
        iri = self.resolve(class_ref)
        if iri is None or iri not in self._classes:
            raise self._unknown_class(class_ref, iri)
        members = {member for cls in self.descendants(iri) for member in self._members.get(cls, ())}
        return sorted({self._label(member) for member in members})

    # -- internals --------------------------------------------------------------------------------

    def _index(self, graph: Graph) -> None:
        """Precompute the classes, the transitive closure, the name indexes and the labels."""
        parents: dict[object, set[object]] = {}
        classes: set[str] = set()
        for sub, sup in graph.subject_objects(RDFS.subClassOf):
            if isinstance(sub, URIRef | BNode) and isinstance(sup, URIRef | BNode):
                parents.setdefault(_key(sub), set()).add(_key(sup))
                classes.update(str(n) for n in (sub, sup) if isinstance(n, URIRef))
        for kind in (OWL.Class, RDFS.Class):
            classes.update(str(s) for s in graph.subjects(RDF.type, kind) if isinstance(s, URIRef))
        members: dict[str, set[str]] = {}
        terms: set[str] = set()
        for s, p, o in graph:
            if isinstance(s, URIRef):
                terms.add(str(s))
            if isinstance(o, URIRef):
                terms.add(str(o))
                if p == RDF.type and isinstance(s, URIRef):
                    members.setdefault(str(o), set()).add(str(s))

        ancestors: dict[str, frozenset[str]] = {}
        descendants: dict[str, set[str]] = {c: set() for c in classes}
        for cls in classes:
            # Blank nodes (restrictions) stay on the path, so A ⊑ _:b ⊑ C gives A ⊑ C.
            seen: set[object] = {cls}
            todo: list[object] = [cls]
            while todo:
                for parent in parents.get(todo.pop(), ()):
                    if parent not in seen:
                        seen.add(parent)
                        todo.append(parent)
            ancestors[cls] = frozenset(n for n in seen if isinstance(n, str))
            for ancestor in ancestors[cls]:
                descendants[ancestor].add(cls)
        by_local: dict[str, list[str]] = {}
        for cls in sorted(classes):
            by_local.setdefault(local_name(cls), []).append(cls)

        self._classes = frozenset(classes)
        self._terms = frozenset(terms)
        self._members = members
        individuals = {member for group in members.values() for member in group}
        self._labels = {iri: self._best_label(graph, iri) for iri in individuals}
        self._ancestors = ancestors
        self._descendants = {c: frozenset(d) for c, d in descendants.items()}
        self._by_local = {name: tuple(iris) for name, iris in by_local.items()}

    def _resolve(self, name: str) -> str | None:
        if name.startswith("<") and name.endswith(">"):
            iri = name[1:-1]
            return iri if iri in self._terms else None
        if "://" in name:
            return name if name in self._terms else None
        prefix, colon, rest = name.partition(":")
        if colon and prefix in self._prefixes:
            iri = self._prefixes[prefix] + rest
            return iri if iri in self._terms else None
        found = self._by_local.get(local_name(name), ())
        if len(found) > 1:
            spelled = ", ".join(f"<{iri}>" + (f" ({short})" if (short := self._short(iri)) else "") for iri in found)
            raise OntologyError(
                f"class name {name!r} is ambiguous: {len(found)} classes have the local name {local_name(name)!r} ({spelled})",
                expected="one class: write a prefixed name or a full IRI in angle brackets instead",
            )
        return found[0] if found else None

    def _short(self, iri: str) -> str | None:
        """``p:Local`` for an IRI under a declared prefix, else None."""
        for prefix, namespace in sorted(self._prefixes.items()):
            if iri.startswith(namespace) and _LOCAL.fullmatch(iri[len(namespace) :]):
                return f"{prefix}:{iri[len(namespace) :]}"
        return None

    def _unknown_class(self, class_ref: str, iri: str | None) -> OntologyError:
        if not self._classes:
            return OntologyError("no ontology with classes is loaded", where=f"ontology class {class_ref!r}", expected="--ontology FILE")
        if iri is not None:
            return OntologyError(f"ontology class {class_ref!r} is <{iri}>, which is no class", expected="a class such as dk:Camera")
        names = {local_name(c) for c in self._classes}
        names.update(s for s in map(self._short, self._classes) if s)
        return OntologyError(
            f"unknown ontology class {class_ref!r}",
            expected=f"one of the {len(self._classes)} classes of the loaded ontology "
            f"({', '.join(self._files) or 'in memory'}){did_you_mean(class_ref, names)}",
        )

    def _label(self, iri: str) -> str:
        return self._labels.get(iri) or local_name(iri)

    @staticmethod
    def _best_label(graph: Graph, iri: str) -> str:
        best: tuple[int, str] | None = None
        for label in graph.objects(URIRef(iri), RDFS.label):
            if not isinstance(label, Literal) or not str(label).strip():
                continue
            lang = (label.language or "").lower()
            rank = 0 if not lang else 1 if lang == "en" or lang.startswith("en-") else 2
            if best is None or (rank, str(label).strip()) < best:
                best = (rank, str(label).strip())
        return best[1] if best else local_name(iri)


def _key(node: URIRef | BNode) -> object:
    """A dictionary key for a node: the IRI string, or a tuple for a blank node (never a str)."""
    return str(node) if isinstance(node, URIRef) else ("_:", str(node))


def _norm(iri: str) -> str:
    """An ontology IRI without angle brackets and trailing ``/`` or ``#``, for comparison."""
    iri = iri.strip()
    if iri.startswith("<") and iri.endswith(">"):
        iri = iri[1:-1]
    return iri.rstrip("/#")


class _Loader:
    """Parses the given files, then finds and parses their imports, breadth first."""

    def __init__(self, search_dirs: Iterable[PathLike], imports: Mapping[str, PathLike], *, warn: bool) -> None:
        self.search_dirs: list[Path] = []
        for folder in map(Path, search_dirs):
            if not folder.is_dir():
                raise OntologyError(f"{str(folder)!r} is not a folder", where="search_dirs", expected="folders holding ontology files")
            self.search_dirs.append(folder.resolve())
        self.imports = {_norm(iri): Path(path) for iri, path in imports.items()}
        self.warn = warn
        self.files: dict[Path, _File] = {}
        self.declared: dict[str, Path] = {}  # ontology IRI -> the loaded file holding it
        self.scanned: dict[Path, _File | None] = {}  # files parsed while looking for an ontology IRI
        self.missing: list[str] = []

    def load(self, paths: Sequence[PathLike]) -> list[_File]:
        for path in paths:
            self.add(_existing_file(Path(path), "ontology file"))
        queue = list(self.files.values())
        for file in queue:  # grows while it is walked: imports of imports
            for iri in file.imports:
                if _norm(iri) in self.declared and _norm(iri) not in self.imports:
                    continue
                found = self.locate(iri, file.path)
                if found is None:
                    continue
                self.declared[_norm(iri)] = found
                if found not in self.files:
                    try:
                        queue.append(self.add(found))
                    except OntologyError as exc:
                        raise OntologyError(f"{exc} (imported as <{iri}> by {file.path})") from exc
        if self.missing and not self.warn:
            hint = ", or load with missing_imports='warn' to go on without it"
            raise OntologyError("\n".join(message + hint for message in self.missing))
        for message in self.missing:
            log.warning("%s; going on without it (missing_imports='warn'): its classes are unknown", message)
        return list(self.files.values())

    def add(self, path: Path) -> _File:
        path = path.resolve()
        if path in self.files:
            return self.files[path]
        file = self.scanned.get(path) or _parse(path)
        self.files[path] = file
        for iri in file.declares:
            self.declared.setdefault(iri, path)
        return file

    def locate(self, iri: str, importer: Path) -> Path | None:
        """The local file for an imported IRI, or None (recorded as missing)."""
        key = _norm(iri)
        if key in self.imports:
            return _existing_file(self.imports[key], f"the local copy of <{iri}> in imports=").resolve()
        folders = list(dict.fromkeys([importer.parent, *self.search_dirs]))
        names, described = _import_file_names(iri)
        for folder in folders:
            for name in names:
                if (folder / name).is_file():
                    return (folder / name).resolve()
        for folder in folders:
            for candidate in sorted(p for p in folder.iterdir() if p.suffix.lower() in FORMATS and p.is_file()):
                parsed = self.scan(candidate.resolve())
                if parsed is not None and key in parsed.declares:
                    return candidate.resolve()
        self.missing.append(
            f"{importer}: owl:imports <{iri}> is not available offline; looked in "
            f"{', '.join(map(str, folders))} for {described + ' or ' if described else ''}a file declaring "
            f"<{iri}> a owl:Ontology; expected a local copy: {_IMPORT_HINT}"
        )
        return None

    def scan(self, path: Path) -> _File | None:
        if path in self.files:
            return self.files[path]
        if path not in self.scanned:
            try:
                self.scanned[path] = _parse(path)
            except OntologyError as exc:  # not the file we look for; reported if loaded for real
                log.debug("skipping %s while looking for an imported ontology: %s", path, exc)
                self.scanned[path] = None
        return self.scanned[path]


def _existing_file(path: Path, what: str) -> Path:
    if path.is_dir():
        raise OntologyError(f"{what} {str(path)!r} is a folder", expected=f"a file such as {path / 'ontology.ttl'}")
    if not path.is_file():
        raise OntologyError(f"{what} {str(path)!r} not found", expected="an existing Turtle (.ttl) or RDF/XML (.rdf, .owl) file")
    return path


def _import_file_names(iri: str) -> tuple[list[str], str]:
    """File names that may hold an imported IRI (its fragment or last path segment plus a known
    extension), and the same in words such as ``sosa.{ttl,n3,rdf,owl,xml,nt}``."""
    base, _, fragment = _norm(iri).partition("#")
    stems = [s for s in (fragment, base.rpartition("/")[2]) if s and s not in (".", "..") and "/" not in s]
    names: list[str] = []
    described: list[str] = []
    for stem in dict.fromkeys(stems):
        suffix = Path(stem).suffix.lower()
        if suffix in FORMATS:  # DUL.owl: the name as is, then DUL.ttl, ...
            names.append(stem)
            names.extend(stem[: -len(suffix)] + ext for ext in FORMATS)
            described += [stem, f"{stem[: -len(suffix)]}.{_EXTENSIONS}"]
        names.extend(stem + ext for ext in FORMATS)
        described.append(f"{stem}.{_EXTENSIONS}")
    return list(dict.fromkeys(names)), ", ".join(described)


def _parse(path: Path) -> _File:
    """Parse one file; a syntax error becomes an :class:`OntologyError` located ``path:line``."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OntologyError(f"cannot read the ontology file ({exc.strerror or exc})", where=str(path)) from exc
    known = FORMATS.get(path.suffix.lower())
    failures: list[tuple[str, Exception]] = []
    for fmt in (known,) if known else _guesses(data):
        graph = Graph(bind_namespaces="none")
        try:
            graph.parse(data=data, format=fmt, publicID=path.as_uri())
        except Exception as exc:  # rdflib's parsers raise many types: BadSyntax, SAXParseException, ...
            failures.append((fmt, exc))
            continue
        declares = frozenset(_norm(str(s)) for s in graph.subjects(RDF.type, OWL.Ontology) if isinstance(s, URIRef))
        imports = sorted({str(o) for o in graph.objects(None, OWL.imports) if isinstance(o, URIRef)})
        prefixes = tuple((prefix, str(namespace)) for prefix, namespace in graph.namespaces())
        return _File(path, graph, prefixes, declares, tuple(imports))
    if known:
        fmt, error = failures[0]
        raise OntologyError(_located(path, data, error), expected=f"valid {_FORMAT_NAMES[fmt]}") from error
    tried = "; ".join(f"as {_FORMAT_NAMES[fmt]}: {_located(path, data, error)}" for fmt, error in failures)
    raise OntologyError(
        f"neither Turtle nor RDF/XML ({tried})", where=str(path), expected=f"a file ending in {', '.join(FORMATS)}"
    ) from failures[-1][1]


def _guesses(data: bytes) -> tuple[str, ...]:
    """The formats to try for a file with an unknown extension, the likelier first."""
    head = data[:4096].lstrip(b"\xef\xbb\xbf \t\r\n")
    if head.startswith((b"<?xml", b"<!--", b"<rdf:RDF")):
        return tuple(reversed(_GUESSES))
    return _GUESSES


def _located(path: Path, data: bytes, exc: Exception) -> str:
    """``path:line: message`` from an rdflib parse error (``path: message`` without a line)."""
    if isinstance(exc, SAXParseException):
        return f"{path}:{exc.getLineNumber()}: {exc.getMessage()}"
    text = str(exc)
    found = re.search(r"\bat line (\d+)", text)
    why = re.search(r"Bad syntax \((.*?)\) at \^", text, re.DOTALL)
    message = why.group(1) if why else (text.strip().splitlines() or [type(exc).__name__])[0]
    if not found:
        return f"{path}: {message}"
    # rdflib's Turtle parser counts lines past the end when the file ends mid-statement.
    last = max(1, data.count(b"\n") + (0 if data.endswith(b"\n") else 1))
    return f"{path}:{min(int(found.group(1)), last)}: {message}"
