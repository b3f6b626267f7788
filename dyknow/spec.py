"""Transformation specifications: the XML format, its hardened loader and the template expander.

A transformation is a blueprint for a unit (the DyKnow paper's *nodelet*): the Python class to
instantiate, its parameters, its ports and the semantic tags that describe what the ports carry::

    <transformations>                          <!-- or a single <transformation> as the root -->
      <transformation type="unit">             <!-- "unit" (default) or "nodelet" -->
        <label>undistort(${Cam})</label>
        <source>transformations.vision:Undistort</source>
        <description>free text</description>
        <args>
          <arg label="Cam">{cam1; cam2; cam3}</arg>    <!-- an explicit set of values -->
          <arg label="Robot" class="ex:Robot"/>        <!-- the individuals of an ontology class -->
        </args>
        <params>
          <param name="config-path" type="string">/path/${Cam}/</param>  <!-- string|int|float|bool -->
        </params>
        <ports>
          <port type="out" deadline-ms="500">undist</port>
          <port type="in" queue="1" policy="keep-last">rawcamera</port>
        </ports>
        <tags>
          <tag port="undist">Undistorted(${Cam})</tag>
        </tags>
        <priority>1</priority>                 <!-- lower is preferred; DEFAULT_PRIORITY when absent -->
        <constraints>
          <constraint measure="battery" op="&gt;=" value="0.25"/>
        </constraints>
      </transformation>
    </transformations>

The children of ``<transformation>`` come in any order, each at most once; ``label``, ``source``
and ``ports`` are required. ``specs/transformation.xsd`` describes the same format for editors.

A ``<transformation>`` with ``<args>`` is a *template*: ``${Name}`` is replaced by each value of
the arg ``Name`` in the label, source, description, param values, port names, tag texts, tag
``port`` attributes and constraint values, and ``$$`` stands for a literal ``$``. Several args
expand as their cartesian product, in document order.

Loading happens in two steps. :func:`parse_templates` checks the structure (elements, attributes,
required parts, template variables) and returns :class:`Template` objects; :meth:`Template.expand`
substitutes the args and checks what depends on the substituted text (param values against their
type, port names, tag ports, constraint values, distinct labels), giving
:class:`TransformationSpec` objects. :func:`parse_specs` and :func:`load_specs` do both and report
every problem of every file in one :class:`~dyknow.errors.SpecError`.

The XML is parsed with :mod:`xml.parsers.expat` directly and any DTD is refused before it is read,
so external entities and entity-expansion bombs cannot work.
"""


from __future__ import annotations

import itertools
import os
import pathlib
import re
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from decimal import Decimal
from types import MappingProxyType
from typing import NoReturn
from xml.parsers import expat
from xml.sax.saxutils import escape, quoteattr

from dyknow.errors import SpecError, SpecIssue, TagError, did_you_mean
from dyknow.tags import parse_term

__all__ = [
    "CONSTRAINT_OPS",
    "DEFAULT_PRIORITY",
    "ELEMENTS",
    "PARAM_TYPES",
    "PORT_DIRECTIONS",
    "PathsLike",
    "QUEUE_POLICIES",
    "TRANSFORMATION_TYPES",
    "Arg",
    "Constraint",
    "Individuals",
    "Param",
    "Port",
    "Tag",
    "Template",
    "TransformationSpec",
    "load_specs",
    "parse_specs",
    "parse_templates",
    "spec_files",
]

DEFAULT_PRIORITY: int = 100
"""The priority of a transformation without ``<priority>``; lower numbers are preferred."""

PARAM_TYPES: tuple[str, ...] = ("string", "int", "float", "bool")
"""The values allowed in ``<param type="...">``."""

CONSTRAINT_OPS: tuple[str, ...] = ("<", "<=", ">", ">=", "==", "!=")
"""The operators allowed in ``<constraint op="...">``."""

TRANSFORMATION_TYPES: tuple[str, ...] = ("unit", "nodelet")
"""The values allowed in ``<transformation type="...">``; "nodelet" is the paper's word for a unit."""

PORT_DIRECTIONS: tuple[str, ...] = ("in", "out")
"""The values allowed in ``<port type="...">``."""

QUEUE_POLICIES: tuple[str, ...] = ("keep-last", "drop-new")
"""What a full input queue does with a new message (``<port type="in" policy="...">``): keep-last
drops the oldest queued message (like a Zenoh ring channel), drop-new refuses the new one."""

# Every element and its attributes, in the order messages list them.
_ATTRIBUTES: dict[str, tuple[str, ...]] = {
    "transformations": (),
    "transformation": ("type",),
    "label": (),
    "source": (),
    "description": (),
    "args": (),
    "arg": ("label", "class"),
    "params": (),
    "param": ("name", "type"),
    "ports": (),
    "port": ("type", "deadline-ms", "queue", "policy"),
    "tags": (),
    "tag": ("port",),
    "priority": (),
    "constraints": (),
    "constraint": ("measure", "op", "value"),
}

ELEMENTS: Mapping[str, frozenset[str]] = MappingProxyType(
    {name: frozenset(attributes) for name, attributes in _ATTRIBUTES.items()}
)
"""Every element of the format and the attributes it allows (``specs/transformation.xsd`` agrees)."""

_TRANSFORMATION_CHILDREN = (
    "label", "source", "description", "args", "params", "ports", "tags", "priority", "constraints",
)  # fmt: skip
# Required children and attributes, with the example their "missing" message shows.
_REQUIRED_CHILDREN = {
    "label": "<label>a-unique-name</label>",
    "source": "<source>package.module:Class</source>",
    "ports": '<ports><port type="out">name</port></ports>',
}
_REQUIRED_ATTRIBUTES = {
    "arg": {"label": 'label="Cam"'},
    "param": {"name": 'name="config-path"'},
    "port": {"type": 'type="in" or type="out"'},
    "tag": {"port": 'port="NAME" naming one of the <ports>'},
    "constraint": {"measure": 'measure="battery"', "op": 'op="&gt;="', "value": 'value="0.25"'},
}
# Each container holds any number of one kind of child.
_CONTAINERS = {
    "transformations": "transformation",
    "args": "arg",
    "params": "param",
    "ports": "port",
    "tags": "tag",
    "constraints": "constraint",
}
_EMPTY_ELEMENTS = frozenset({"constraint"})  # attributes only, no text
# Root-only attributes: namespace declarations and the ones editors use to attach the XSD.
_SCHEMA_LOCATIONS = frozenset({"xsi:noNamespaceSchemaLocation", "xsi:schemaLocation"})

_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_PORT_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*")
_INTEGER = re.compile(r"[+-]?[0-9]+")  # the lexical space of xs:integer
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)")  # the lexical space of xs:decimal
# One match per '$': an escaped "$$", a "${Name}" reference, or (empty group) a stray '$'.
_DOLLAR = re.compile(r"\$(?:(?P<escaped>\$)|\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)\}|(?P<stray>))")
_BOOLS = {"true": True, "1": True, "false": False, "0": False}
_VALUE_HINTS = {"int": "a whole number such as 10", "float": "a number such as 0.5", "bool": "true or false"}

_DTD_MESSAGE = (
    "<!DOCTYPE>: DTDs and entity declarations are not allowed in transformation specs (they enable "
    "external entities and entity-expansion bombs); remove the <!DOCTYPE ...> block"
)

Individuals = Callable[[str], Sequence[str]]
"""Returns the substitution values for an ontology class reference such as ``ex:Camera``."""

PathsLike = str | os.PathLike[str] | Iterable[str | os.PathLike[str]]
"""One path or several: what :func:`spec_files` and :func:`load_specs` accept."""


@dataclass(frozen=True, slots=True)
class Param:
    """A parameter passed to the unit when it is spawned; ``value`` has the Python type of ``type``."""

    name: str
    type: str
    value: str | int | float | bool


@dataclass(frozen=True, slots=True)
class Port:
    """A named input or output of a unit.

    ``deadline_ms`` (out ports) bounds the time between two outputs; ``queue`` and ``policy`` (in
    ports) size the input queue and say what a full queue does; None means the manager's default.
    """

    name: str
    direction: str
    deadline_ms: float | None = None
    queue: int | None = None
    policy: str | None = None


@dataclass(frozen=True, slots=True)
class Tag:
    """A semantic description of what a port carries, such as ``Undistorted(cam1)``."""

    port: str
    tag: str


@dataclass(frozen=True, slots=True)
class Constraint:
    """A condition on a measure (``battery >= 0.25``) that must hold for the transformation to run."""

    measure: str
    op: str
    value: float | str

    def holds(self, measured: float | str) -> bool:
        """Whether ``measured op value`` holds.

        Numbers compare as numbers. A string only supports ``==`` and ``!=`` (a number never
        equals a string); the ordering operators are false for it.
        """
        if self.op == "==":
            return measured == self.value
        if self.op == "!=":
            return measured != self.value
        if isinstance(measured, str) or isinstance(self.value, str):
            return False
        if self.op == "<":
            return measured < self.value
        if self.op == "<=":
            return measured <= self.value
        if self.op == ">":
            return measured > self.value
        if self.op == ">=":
            return measured >= self.value
        raise ValueError(f"unknown operator {self.op!r}; expected one of {', '.join(CONSTRAINT_OPS)}")


@dataclass(frozen=True, slots=True)
class Arg:
    """A template argument: explicit ``values``, or the individuals of ``ontology_class``."""

    label: str
    values: tuple[str, ...] = ()
    ontology_class: str | None = None


@dataclass(frozen=True, slots=True)
class TransformationSpec:
    """One concrete transformation: everything needed to spawn a unit and wire its ports.

    ``args`` is the substitution that produced it from its template, such as
    ``(("Cam", "cam1"),)``; ``path`` and ``line`` locate its ``<transformation>``.
    """

    label: str
    source: str
    params: tuple[Param, ...] = ()
    ports: tuple[Port, ...] = ()
    tags: tuple[Tag, ...] = ()
    priority: int = DEFAULT_PRIORITY
    constraints: tuple[Constraint, ...] = ()
    description: str = ""
    args: tuple[tuple[str, str], ...] = ()
    path: str = "<memory>"
    line: int = 0

    @property
    def inputs(self) -> tuple[Port, ...]:
        """The ``in`` ports, in document order."""
        return tuple(p for p in self.ports if p.direction == "in")

    @property
    def outputs(self) -> tuple[Port, ...]:
        """The ``out`` ports, in document order."""
        return tuple(p for p in self.ports if p.direction == "out")

    @property
    def location(self) -> str:
        """Where the spec was written, as ``path:line``."""
        return f"{self.path}:{self.line}"

    def port(self, name: str) -> Port:
        """The port called ``name``; raises :class:`KeyError` naming the ports there are."""
        for port in self.ports:
            if port.name == name:
                return port
        names = [p.name for p in self.ports]
        raise KeyError(
            f"{self.label!r} has no port named {name!r}; expected {_one_of(names)}{did_you_mean(name, names)}"
        )

    def param_values(self) -> dict[str, str | int | float | bool]:
        """The parameters as a ``name -> value`` dict."""
        return {p.name: p.value for p in self.params}

    def tags_for(self, port: str) -> tuple[str, ...]:
        """The tags describing ``port``, in document order."""
        return tuple(t.tag for t in self.tags if t.port == port)

    def to_dict(self) -> dict[str, object]:
        """A JSON-ready description of the spec."""
        ports: list[dict[str, object]] = []
        for port in self.ports:
            entry: dict[str, object] = {"name": port.name, "direction": port.direction}
            if port.deadline_ms is not None:
                entry["deadline_ms"] = port.deadline_ms
            if port.queue is not None:
                entry["queue"] = port.queue
            if port.policy is not None:
                entry["policy"] = port.policy
            ports.append(entry)
        return {
            "label": self.label,
            "source": self.source,
            "params": self.param_values(),
            "ports": ports,
            "tags": [{"port": t.port, "tag": t.tag} for t in self.tags],
            "priority": self.priority,
            "constraints": [{"measure": c.measure, "op": c.op, "value": c.value} for c in self.constraints],
            "description": self.description,
            "args": dict(self.args),
            "location": self.location,
        }

    def to_xml(self) -> str:
        """A standalone ``<transformation>`` document that :func:`parse_specs` reads back as this spec.

        Args are written as one-value sets so that ``args`` survives the round trip; a value the
        set syntax cannot hold (an ontology individual containing ``;``) is left out.
        """
        out = ['<?xml version="1.0" encoding="UTF-8"?>', "<transformation>"]
        out.append(f"  <label>{_xml_text(self.label)}</label>")
        out.append(f"  <source>{_xml_text(self.source)}</source>")
        if self.description:
            out.append(f"  <description>{_xml_text(self.description)}</description>")
        args = [(name, value) for name, value in self.args if _is_set_value(value)]
        if args:
            out.append("  <args>")
            # Arg values are not templates: they need XML escaping but no "$$".
            out.extend(f"    <arg label={quoteattr(name)}>{{{escape(value)}}}</arg>" for name, value in args)
            out.append("  </args>")
        if self.params:
            out.append("  <params>")
            for p in self.params:
                value = _xml_text(_value_text(p.value))
                out.append(f"    <param name={quoteattr(p.name)} type={quoteattr(p.type)}>{value}</param>")
            out.append("  </params>")
        out.append("  <ports>")
        for port in self.ports:
            extra = ""
            if port.deadline_ms is not None:
                extra += f' deadline-ms="{_decimal_text(port.deadline_ms)}"'
            if port.queue is not None:
                extra += f' queue="{port.queue}"'
            if port.policy is not None:
                extra += f' policy="{port.policy}"'
            out.append(f'    <port type="{port.direction}"{extra}>{_xml_text(port.name)}</port>')
        out.append("  </ports>")
        if self.tags:
            out.append("  <tags>")
            out.extend(f"    <tag port={_xml_attr(t.port)}>{_xml_text(t.tag)}</tag>" for t in self.tags)
            out.append("  </tags>")
        if self.priority != DEFAULT_PRIORITY:
            out.append(f"  <priority>{self.priority}</priority>")
        if self.constraints:
            out.append("  <constraints>")
            for c in self.constraints:
                value = _xml_attr(_value_text(c.value))
                attributes = f"measure={quoteattr(c.measure)} op={quoteattr(c.op)} value={value}"
                out.append(f"    <constraint {attributes}/>")
            out.append("  </constraints>")
        out.append("</transformation>")
        return "\n".join(out) + "\n"


@dataclass(frozen=True, slots=True)
class Template:
    """One parsed ``<transformation>`` before expansion.

    Text fields are kept as written and may contain ``${Name}``: ``params`` hold their raw text as
    value, ``constraints`` their raw value text. The ``*_lines`` fields hold the line of each
    element, parallel to the tuple they describe, so that expansion errors can be located.
    """

    label: str
    source: str
    args: tuple[Arg, ...] = ()
    path: str = "<memory>"
    line: int = 0
    description: str = ""
    params: tuple[Param, ...] = ()
    ports: tuple[Port, ...] = ()
    tags: tuple[Tag, ...] = ()
    priority: int = DEFAULT_PRIORITY
    constraints: tuple[Constraint, ...] = ()
    label_line: int = 0
    arg_lines: tuple[int, ...] = ()
    param_lines: tuple[int, ...] = ()
    port_lines: tuple[int, ...] = ()
    tag_lines: tuple[int, ...] = ()
    constraint_lines: tuple[int, ...] = ()

    @property
    def is_template(self) -> bool:
        """Whether the transformation has args (and so expands to one spec per combination)."""
        return bool(self.args)

    def expand(self, individuals: Individuals | None = None) -> list[TransformationSpec]:
        """One spec per combination of arg values (cartesian product, args in document order).

        ``individuals(class_ref)`` supplies the values of an ``<arg class="...">``. Raises
        :class:`SpecError` with every problem of this template; a problem that is the same in
        every expansion is reported once, otherwise it names the expansions it occurs in.
        """
        issues: list[SpecIssue] = []
        value_sets: list[tuple[str, ...]] = []
        for arg, line in zip(self.args, self.arg_lines, strict=True):
            arg_values, arg_problem = _arg_values(arg, individuals)
            if arg_problem:
                issues.append(SpecIssue(self.path, line, f"<arg> {arg.label!r}: {arg_problem}"))
            value_sets.append(arg_values)
        if issues:
            raise SpecError(issues)

        specs: list[TransformationSpec] = []
        found: dict[tuple[int, str], list[str]] = {}  # (line, message) -> the expansions it occurs in
        for combination in itertools.product(*value_sets):
            values = dict(zip((a.label for a in self.args), combination, strict=True))
            spec, problems = self._build(values)
            specs.append(spec)
            expansion = ", ".join(f"{name}={value}" for name, value in values.items())
            for problem in dict.fromkeys(problems):
                found.setdefault(problem, []).append(expansion)
        for (line, message), expansions in found.items():
            if len(expansions) == 1 and len(specs) > 1:
                message += f" (in expansion {expansions[0]})"
            elif len(expansions) < len(specs):
                message += f" (in expansions {'; '.join(expansions)})"
            issues.append(SpecIssue(self.path, line, message))
        issues.extend(self._label_collisions(specs))
        if issues:
            raise SpecError(sorted(issues, key=lambda i: i.line))
        return specs

    def _build(self, values: Mapping[str, str]) -> tuple[TransformationSpec, list[tuple[int, str]]]:
        """The spec for one substitution, and the (line, message) problems found in it."""
        problems: list[tuple[int, str]] = []

        def sub(text: str) -> str:
            return _substitute(text, values)

        params = []
        for param, line in zip(self.params, self.param_lines, strict=True):
            text = sub(str(param.value))
            try:
                value = _convert(param.type, text)
            except ValueError as exc:
                message = f"<param> {param.name!r}: value {text!r} is not a valid {param.type}; expected {exc}"
                problems.append((line, message))
                value = text
            params.append(Param(param.name, param.type, value))

        ports = [replace(port, name=sub(port.name)) for port in self.ports]
        first_line: dict[str, int] = {}
        for port, line in zip(ports, self.port_lines, strict=True):
            if not _PORT_NAME.fullmatch(port.name):
                expected = "letters, digits, '_' and '-', starting with a letter or '_'"
                problems.append((line, f"<port>: {port.name!r} is not a valid port name; expected {expected}"))
            elif port.name in first_line:
                where = f"first at line {first_line[port.name]}"
                problems.append((line, f"<port>: duplicate port {port.name!r} ({where}); expected each port name once"))
            first_line.setdefault(port.name, line)

        tags = [Tag(sub(tag.port), sub(tag.tag)) for tag in self.tags]
        for tag, line in zip(tags, self.tag_lines, strict=True):
            if tag.port not in first_line:
                names = list(first_line)
                hint = did_you_mean(tag.port, names)
                problems.append((line, f"<tag> @port: no port named {tag.port!r}; expected {_one_of(names)}{hint}"))
            if tag.tag:
                try:
                    parse_term(tag.tag)
                except TagError as exc:
                    problems.append((line, f"<tag>: {exc}"))

        constraints = []
        for constraint, line in zip(self.constraints, self.constraint_lines, strict=True):
            text = sub(str(constraint.value))
            if _NUMBER.fullmatch(text):
                constraints.append(replace(constraint, value=float(text)))
                continue
            if constraint.op not in ("==", "!="):
                problem = f"{text!r} is not a number, so op {constraint.op!r} cannot compare it"
                problems.append((line, f"<constraint> @value: {problem}; expected a number, or op == or !="))
            constraints.append(replace(constraint, value=text))

        spec = TransformationSpec(
            label=sub(self.label),
            source=sub(self.source),
            params=tuple(params),
            ports=tuple(ports),
            tags=tuple(tags),
            priority=self.priority,
            constraints=tuple(constraints),
            description=sub(self.description),
            args=tuple(values.items()),
            path=self.path,
            line=self.line,
        )
        return spec, problems

    def _label_collisions(self, specs: Sequence[TransformationSpec]) -> list[SpecIssue]:
        """An issue when several expansions get the same label (usually an arg missing from it)."""
        shared = [(label, n) for label, n in Counter(s.label for s in specs).items() if n > 1]
        if not shared:
            return []
        label, n = shared[0]
        used = {m["name"] for m in _DOLLAR.finditer(self.label)}
        unused = [f"${{{a.label}}}" for a in self.args if a.label not in used]
        if unused:
            hint = f"put {' and '.join(unused)} in the label"
        else:
            hint = "make the arg values give distinct labels"
        message = f"<label>: {n} expansions get the same label {label!r}; expected one label per expansion ({hint})"
        return [SpecIssue(self.path, self.label_line, message)]


def parse_templates(data: str | bytes, path: str = "<string>") -> list[Template]:
    """Parse a spec document into templates, checking its structure.

    Raises :class:`SpecError` with every structural problem of the document.
    """
    templates, issues = _parse(data, path)
    if issues:
        raise SpecError(issues)
    return templates


def parse_specs(
    data: str | bytes, path: str = "<string>", individuals: Individuals | None = None
) -> list[TransformationSpec]:
    """Parse and expand a spec document.

    Every problem of the document (structure, expansion, labels defined twice) is reported in
    one :class:`SpecError`.
    """
    located, issues = _load(data, path, individuals)
    issues.extend(_duplicate_labels(located))
    if issues:
        raise SpecError(sorted(issues, key=lambda i: i.line))
    return [spec for spec, _ in located]


def spec_files(paths: PathsLike) -> list[pathlib.Path]:
    """The spec files named by ``paths``.

    A directory gives its ``*.xml`` files (sorted, not recursive) and a file gives itself; a file
    named twice counts once. Raises :class:`SpecError` naming every missing path.
    """
    files, issues = _spec_files(paths)
    if issues:
        raise SpecError(issues)
    return files


def load_specs(paths: PathsLike, individuals: Individuals | None = None) -> list[TransformationSpec]:
    """Load and expand every spec in ``paths`` (see :func:`spec_files`).

    Raises one :class:`SpecError` with the problems of every file, including labels defined in
    more than one place.
    """
    files, issues = _spec_files(paths)
    located: list[tuple[TransformationSpec, int]] = []
    for file in files:
        try:
            data = file.read_bytes()
        except OSError as exc:
            issues.append(SpecIssue(str(file), 0, f"cannot read: {exc.strerror or exc}"))
            continue
        file_located, file_issues = _load(data, str(file), individuals)
        issues.extend(sorted(file_issues, key=lambda i: i.line))
        located.extend(file_located)
    issues.extend(_duplicate_labels(located))
    if issues:
        raise SpecError(issues)
    return [spec for spec, _ in located]


# --- loading ----------------------------------------------------------------------------------


def _spec_files(paths: PathsLike) -> tuple[list[pathlib.Path], list[SpecIssue]]:
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    files: list[pathlib.Path] = []
    issues: list[SpecIssue] = []
    for name in paths:
        path = pathlib.Path(name)
        if path.is_dir():
            files.extend(sorted(p for p in path.glob("*.xml") if p.is_file()))
        elif path.exists():
            files.append(path)
        else:
            message = "no such file or directory; expected a spec file or a directory of *.xml files"
            issues.append(SpecIssue(str(path), 0, message))
    # A file named both directly and through its directory must not clash with itself.
    unique: list[pathlib.Path] = []
    seen: set[pathlib.Path] = set()
    for file in files:
        if file.resolve() not in seen:
            seen.add(file.resolve())
            unique.append(file)
    return unique, issues


def _load(
    data: str | bytes, path: str, individuals: Individuals | None
) -> tuple[list[tuple[TransformationSpec, int]], list[SpecIssue]]:
    """Parse and expand; (spec, line of its label) pairs and every issue but duplicate labels."""
    templates, issues = _parse(data, path)
    located: list[tuple[TransformationSpec, int]] = []
    for template in templates:
        try:
            located.extend((spec, template.label_line) for spec in template.expand(individuals))
        except SpecError as exc:
            issues.extend(exc.issues)
    return located, issues


def _duplicate_labels(located: Iterable[tuple[TransformationSpec, int]]) -> list[SpecIssue]:
    issues = []
    first: dict[str, str] = {}
    for spec, line in located:
        if spec.label not in first:
            first[spec.label] = f"{spec.path}:{line}"
            continue
        message = (
            f"<label>: duplicate label {spec.label!r}, first defined at {first[spec.label]}; "
            "expected each label once"
        )
        issues.append(SpecIssue(spec.path, line, message))
    return issues


# --- XML --------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Node:
    """An element of the parsed document, with the line of its start tag."""

    name: str
    attrs: dict[str, str]
    line: int
    children: list[_Node] = field(default_factory=list)
    chunks: list[str] = field(default_factory=list)

    @property
    def text(self) -> str:
        """The text directly inside the element, stripped."""
        return "".join(self.chunks).strip()


class _Refused(Exception):
    """Stops expat at a DTD, before anything in it is expanded."""

    def __init__(self, line: int) -> None:
        super().__init__(line)
        self.line = line


def _parse_xml(data: str | bytes, path: str) -> _Node:
    """The root element of the document; :class:`SpecError` when malformed or when it has a DTD."""
    parser = expat.ParserCreate()  # no namespace processing: names stay as written ("xsi:...")
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    stack: list[_Node] = []
    roots: list[_Node] = []

    def start(name: str, attrs: dict[str, str]) -> None:
        node = _Node(name, attrs, parser.CurrentLineNumber)
        (stack[-1].children if stack else roots).append(node)
        stack.append(node)

    def end(name: str) -> None:
        stack.pop()

    def characters(text: str) -> None:
        if stack:
            stack[-1].chunks.append(text)

    def refuse(*_: object) -> NoReturn:
        raise _Refused(parser.CurrentLineNumber)

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = characters
    # "<!DOCTYPE" fires before any declaration inside it is processed, so nothing is ever
    # expanded or fetched; the other handlers are a second line of defence.
    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.UnparsedEntityDeclHandler = refuse
    parser.ExternalEntityRefHandler = refuse
    try:
        parser.Parse(data, True)  # pyexpat parses a str as UTF-8, bytes by their XML declaration
    except _Refused as exc:
        raise SpecError([SpecIssue(path, exc.line, _DTD_MESSAGE)]) from None
    except expat.ExpatError as exc:
        problem = f"{expat.ErrorString(exc.code)} at column {exc.offset + 1}"
        message = f"malformed XML: {problem}; expected well-formed XML"
        raise SpecError([SpecIssue(path, exc.lineno, message)]) from None
    return roots[0]


# --- structure --------------------------------------------------------------------------------


class _Issues:
    """Collects the issues of one file."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.items: list[SpecIssue] = []

    def add(self, line: int, message: str) -> None:
        self.items.append(SpecIssue(self.path, line, message))


def _parse(data: str | bytes, path: str) -> tuple[list[Template], list[SpecIssue]]:
    """The structurally valid templates of a document, and every structural issue."""
    try:
        root = _parse_xml(data, path)
    except SpecError as exc:
        return [], list(exc.issues)
    issues = _Issues(path)
    if root.name == "transformations":
        _check_element(root, issues, is_root=True)
        nodes = [c for c in root.children if c.name == "transformation"]
        if not root.children:
            issues.add(root.line, "<transformations>: no <transformation> inside; expected at least one")
    elif root.name == "transformation":
        nodes = [root]
    else:
        hint = did_you_mean(root.name, ["transformations", "transformation"])
        expected = "<transformations> or <transformation>"
        issues.add(root.line, f"<{root.name}>: unknown root element; expected {expected}{hint}")
        nodes = []
    templates = []
    for node in nodes:
        before = len(issues.items)
        _check_tree(node, issues, is_root=node is root)
        template = _read_template(node, issues)
        if len(issues.items) == before:  # only structurally valid templates are expanded
            templates.append(template)
    return templates, sorted(issues.items, key=lambda i: i.line)


def _check_tree(node: _Node, issues: _Issues, is_root: bool = False) -> None:
    _check_element(node, issues, is_root)
    allowed = _allowed_children(node.name)
    for child in node.children:
        if child.name in allowed:
            _check_tree(child, issues)


def _allowed_children(name: str) -> tuple[str, ...]:
    if name == "transformation":
        return _TRANSFORMATION_CHILDREN
    if name in _CONTAINERS:
        return (_CONTAINERS[name],)
    return ()


def _check_element(node: _Node, issues: _Issues, is_root: bool = False) -> None:
    """Check the attributes, children and text of one element (whose name is known)."""
    name = node.name
    for attr, value in node.attrs.items():
        if attr in _ATTRIBUTES[name]:
            continue
        if is_root and (attr == "xmlns" or attr.startswith("xmlns:") or attr in _SCHEMA_LOCATIONS):
            # A default namespace would put every element in it, and the format has none.
            if attr == "xmlns" and value:
                problem = f"namespace {value!r} is not used by transformation specs"
                issues.add(node.line, f"<{name}> @xmlns: {problem}; expected no default namespace")
            continue
        expected = ", ".join(_ATTRIBUTES[name]) or "no attributes"
        hint = did_you_mean(attr, _ATTRIBUTES[name])
        issues.add(node.line, f"<{name}> @{attr}: unknown attribute; expected {expected}{hint}")
    for attr, example in _REQUIRED_ATTRIBUTES.get(name, {}).items():
        if attr not in node.attrs:
            issues.add(node.line, f"<{name}>: missing @{attr}; expected {example}")

    allowed = _allowed_children(name)
    first_line: dict[str, int] = {}
    for child in node.children:
        if not allowed:
            expected = "no content" if name in _EMPTY_ELEMENTS else "text only"
            issues.add(child.line, f"<{child.name}>: unexpected element in <{name}>; expected {expected}")
        elif child.name not in allowed:
            expected = f"one of {', '.join(allowed)}" if len(allowed) > 1 else f"<{allowed[0]}>"
            hint = did_you_mean(child.name, allowed)
            issues.add(child.line, f"<{child.name}>: unknown element in <{name}>; expected {expected}{hint}")
        elif name == "transformation" and child.name in first_line:
            where = f"the first is at line {first_line[child.name]}"
            message = f"duplicate <{child.name}> in <transformation> ({where}); expected at most one"
            issues.add(child.line, f"<{child.name}>: {message}")
        first_line.setdefault(child.name, child.line)

    if name == "transformation":
        for child_name, example in _REQUIRED_CHILDREN.items():
            if child_name not in first_line:
                issues.add(node.line, f"<transformation>: missing <{child_name}>; expected {example}")
    if node.text and (allowed or name in _EMPTY_ELEMENTS):
        if name in _EMPTY_ELEMENTS:
            expected = "an empty element"
        elif name == "transformation":
            expected = "elements only"
        else:
            expected = f"only <{allowed[0]}> elements"
        issues.add(node.line, f"<{name}>: unexpected text {_shorten(node.text)!r}; expected {expected}")


def _read_template(node: _Node, issues: _Issues) -> Template:
    """Read the values of a structurally checked ``<transformation>``, adding the issues found."""
    first: dict[str, _Node] = {}
    for child in node.children:
        first.setdefault(child.name, child)

    kind = node.attrs.get("type", "unit").strip()
    if kind not in TRANSFORMATION_TYPES:
        hint = did_you_mean(kind, TRANSFORMATION_TYPES)
        issues.add(node.line, f"<transformation> @type: unknown type {kind!r}; expected unit or nodelet{hint}")

    args, arg_lines = _read_args(first.get("args"), issues)
    declared = [a.label for a in args]

    def text_of(name: str, example: str | None) -> tuple[str, int]:
        element = first.get(name)
        if element is None:
            return "", 0
        if not element.text and example is not None:
            issues.add(element.line, f"<{name}>: empty; expected {example}")
        _check_template(f"<{name}>", element.text, element.line, declared, issues)
        return element.text, element.line

    label, label_line = text_of("label", "a unique name such as undistort(${Cam})")
    source, _ = text_of("source", "<source>package.module:Class</source>")
    description, _ = text_of("description", None)

    priority = DEFAULT_PRIORITY
    if "priority" in first:
        element = first["priority"]
        if _INTEGER.fullmatch(element.text):
            priority = int(element.text)
        else:
            expected = "a whole number such as 1 (lower is preferred)"
            issues.add(element.line, f"<priority>: {element.text!r} is not an integer; expected {expected}")

    params, param_lines = _read_params(first.get("params"), declared, issues)
    ports, port_lines = _read_ports(first.get("ports"), declared, issues)
    tags, tag_lines = _read_tags(first.get("tags"), declared, issues)
    constraints, constraint_lines = _read_constraints(first.get("constraints"), declared, issues)
    return Template(
        label=label,
        source=source,
        args=args,
        path=issues.path,
        line=node.line,
        description=description,
        params=params,
        ports=ports,
        tags=tags,
        priority=priority,
        constraints=constraints,
        label_line=label_line,
        arg_lines=arg_lines,
        param_lines=param_lines,
        port_lines=port_lines,
        tag_lines=tag_lines,
        constraint_lines=constraint_lines,
    )


def _children(container: _Node | None) -> list[_Node]:
    """The known children of a container that have their required attributes (the others have
    been reported by _check_element)."""
    if container is None:
        return []
    kind = _CONTAINERS[container.name]
    required = _REQUIRED_ATTRIBUTES.get(kind, {})
    return [c for c in container.children if c.name == kind and all(a in c.attrs for a in required)]


def _read_args(container: _Node | None, issues: _Issues) -> tuple[tuple[Arg, ...], tuple[int, ...]]:
    args: list[Arg] = []
    lines: list[int] = []
    first_line: dict[str, int] = {}
    for node in _children(container):
        label = node.attrs["label"].strip()
        if not _IDENTIFIER.fullmatch(label):
            expected = "letters, digits and '_', starting with a letter or '_' (such as Cam)"
            issues.add(node.line, f"<arg> @label: {label!r} is not a valid name; expected {expected}")
            continue
        if label in first_line:
            where = f"first at line {first_line[label]}"
            issues.add(node.line, f"<arg> @label: duplicate arg {label!r} ({where}); expected each arg once")
            continue
        first_line[label] = node.line
        ontology_class = node.attrs.get("class")
        if ontology_class is None:
            values, problem = _parse_set(node.text)
            if problem:
                issues.add(node.line, f"<arg> {label!r}: {problem}")
            args.append(Arg(label, values))
        else:
            if not ontology_class.strip():
                issues.add(node.line, "<arg> @class: empty; expected an ontology class such as ex:Camera")
            if node.text:
                problem = f"has both @class and the values {_shorten(node.text)!r}"
                issues.add(node.line, f"<arg> {label!r}: {problem}; expected one or the other")
            args.append(Arg(label, (), ontology_class.strip()))
        lines.append(node.line)
    return tuple(args), tuple(lines)


def _parse_set(text: str) -> tuple[tuple[str, ...], str | None]:
    """The values of ``{a; b; c}`` (braces optional), or a problem."""
    inner = text
    if inner.startswith("{") and inner.endswith("}"):
        inner = inner[1:-1]
    elif inner.startswith("{") or inner.endswith("}"):
        return (), f"unbalanced braces in {_shorten(text)!r}; expected a set such as {{cam1; cam2}}"
    if not inner.strip():
        return (), 'empty set; expected values such as {cam1; cam2}, or class="ex:Class"'
    values = tuple(v.strip() for v in inner.split(";"))
    if "" in values:
        return (), f"empty value in {_shorten(text)!r}; expected non-empty values separated by ';'"
    for i, value in enumerate(values):
        if value in values[:i]:
            return (), f"duplicate value {value!r}; expected each value once"
    return values, None


def _read_params(
    container: _Node | None, declared: Sequence[str], issues: _Issues
) -> tuple[tuple[Param, ...], tuple[int, ...]]:
    params: list[Param] = []
    first_line: dict[str, int] = {}
    nodes = _children(container)
    for node in nodes:
        name = node.attrs["name"].strip()
        type_ = node.attrs.get("type", "string").strip()
        if not name:
            issues.add(node.line, "<param> @name: empty; expected a name such as config-path")
        elif name in first_line:
            where = f"first at line {first_line[name]}"
            issues.add(node.line, f"<param> @name: duplicate param {name!r} ({where}); expected each name once")
        first_line.setdefault(name, node.line)
        if type_ not in PARAM_TYPES:
            hint = did_you_mean(type_, PARAM_TYPES)
            expected = f"one of {', '.join(PARAM_TYPES)}{hint}"
            issues.add(node.line, f"<param> @type: unknown type {type_!r}; expected {expected}")
        _check_template(f"<param> {name!r}", node.text, node.line, declared, issues)
        params.append(Param(name, type_, node.text))
    return tuple(params), tuple(n.line for n in nodes)


def _read_ports(
    container: _Node | None, declared: Sequence[str], issues: _Issues
) -> tuple[tuple[Port, ...], tuple[int, ...]]:
    ports: list[Port] = []
    nodes = _children(container)
    if container is not None and not container.children:
        expected = 'at least one <port type="out">name</port>'
        issues.add(container.line, f"<ports>: no <port> elements; expected {expected}")
    for node in nodes:
        direction = node.attrs["type"].strip()
        if direction not in PORT_DIRECTIONS:
            hint = did_you_mean(direction, PORT_DIRECTIONS)
            issues.add(node.line, f"<port> @type: unknown direction {direction!r}; expected in or out{hint}")
        deadline_ms = None
        if "deadline-ms" in node.attrs:
            text = node.attrs["deadline-ms"].strip()
            if direction == "in":
                expected = 'it on a <port type="out">'
                issues.add(node.line, f"<port> @deadline-ms: only allowed on out ports; expected {expected}")
            elif not _DECIMAL.fullmatch(text) or Decimal(text) <= 0:
                expected = "milliseconds such as 500"
                issues.add(node.line, f"<port> @deadline-ms: {text!r} is not a positive number; expected {expected}")
            else:
                deadline_ms = float(text)
        queue = None
        if "queue" in node.attrs:
            text = node.attrs["queue"].strip()
            if direction == "out":
                issues.add(node.line, '<port> @queue: only allowed on in ports; expected it on a <port type="in">')
            elif not _INTEGER.fullmatch(text) or int(text) < 1:
                issues.add(node.line, f"<port> @queue: {text!r} is not a positive whole number; expected a queue size such as 1 or 8")
            else:
                queue = int(text)
        policy = None
        if "policy" in node.attrs:
            text = node.attrs["policy"].strip()
            if direction == "out":
                issues.add(node.line, '<port> @policy: only allowed on in ports; expected it on a <port type="in">')
            elif text not in QUEUE_POLICIES:
                hint = did_you_mean(text, QUEUE_POLICIES)
                issues.add(node.line, f"<port> @policy: unknown queue policy {text!r}; expected keep-last or drop-new{hint}")
            else:
                policy = text
        if not node.text:
            issues.add(node.line, "<port>: empty port name; expected a name such as undist")
        _check_template("<port>", node.text, node.line, declared, issues)
        ports.append(Port(node.text, direction, deadline_ms, queue, policy))
    return tuple(ports), tuple(n.line for n in nodes)


def _read_tags(
    container: _Node | None, declared: Sequence[str], issues: _Issues
) -> tuple[tuple[Tag, ...], tuple[int, ...]]:
    tags: list[Tag] = []
    nodes = _children(container)
    for node in nodes:
        port = node.attrs["port"].strip()
        if not port:
            issues.add(node.line, "<tag> @port: empty; expected the name of one of the <ports>")
        if not node.text:
            issues.add(node.line, "<tag>: empty tag; expected a tag such as Undistorted(${Cam})")
        _check_template("<tag> @port", port, node.line, declared, issues)
        _check_template("<tag>", node.text, node.line, declared, issues)
        tags.append(Tag(port, node.text))
    return tuple(tags), tuple(n.line for n in nodes)


def _read_constraints(
    container: _Node | None, declared: Sequence[str], issues: _Issues
) -> tuple[tuple[Constraint, ...], tuple[int, ...]]:
    constraints: list[Constraint] = []
    nodes = _children(container)
    for node in nodes:
        measure, op, value = (node.attrs[a].strip() for a in ("measure", "op", "value"))
        if not measure:
            issues.add(node.line, "<constraint> @measure: empty; expected a measure such as battery")
        if op not in CONSTRAINT_OPS:
            hint = did_you_mean(op, CONSTRAINT_OPS)
            expected = f"one of {', '.join(CONSTRAINT_OPS)}{hint}"
            issues.add(node.line, f"<constraint> @op: unknown operator {op!r}; expected {expected}")
        if not value:
            expected = "a number such as 0.25 or a word such as docked"
            issues.add(node.line, f"<constraint> @value: empty; expected {expected}")
        _check_template("<constraint> @value", value, node.line, declared, issues)
        constraints.append(Constraint(measure, op, value))
    return tuple(constraints), tuple(n.line for n in nodes)


# --- templates --------------------------------------------------------------------------------


def _check_template(where: str, text: str, line: int, declared: Sequence[str], issues: _Issues) -> None:
    """Report each stray '$' and each ``${Name}`` that names no declared arg."""
    for match in _DOLLAR.finditer(text):
        name = match["name"]
        if match["stray"] is not None:
            expected = "${Name} to use an arg, or $$ for a literal '$'"
            issues.add(line, f"{where}: stray '$' in {_shorten(text)!r}; expected {expected}")
        elif name is not None and name not in declared:
            if declared:
                expected = f"one of the declared args: {', '.join(declared)}{did_you_mean(name, declared)}"
            else:
                expected = f'it declared as <args><arg label="{name}">{{...}}</arg></args>'
            issues.add(line, f"{where}: undefined template variable ${{{name}}}; expected {expected}")


def _substitute(text: str, values: Mapping[str, str]) -> str:
    def replacement(match: re.Match[str]) -> str:
        if match["name"] is not None:
            return values[match["name"]]
        return "$"  # "$$" (parse_templates refuses any stray '$')

    return _DOLLAR.sub(replacement, text)


def _arg_values(arg: Arg, individuals: Individuals | None) -> tuple[tuple[str, ...], str | None]:
    """The substitution values of an arg, or a problem (for ontology classes)."""
    if arg.ontology_class is None:
        return arg.values, None
    cls = arg.ontology_class
    if individuals is None:
        problem = f"takes its values from ontology class {cls!r}, but no ontology is loaded"
        return (), f"{problem}; expected --ontology FILE"
    try:
        found = individuals(cls)
    except Exception as exc:  # the resolver is the caller's code: any failure becomes a located issue
        problem = f"cannot get the individuals of ontology class {cls!r} ({type(exc).__name__}: {exc})"
        return (), f"{problem}; expected a class of the loaded ontology"
    if isinstance(found, str):  # a str is a Sequence[str] too, of one-letter values
        problem = f"the individuals of ontology class {cls!r} came back as one string"
        return (), f"{problem}; expected a sequence of names"
    values = tuple(found)
    if not values:
        return (), f"ontology class {cls!r} has no individuals; expected at least one"
    for value in values:
        if not isinstance(value, str) or not value.strip():
            problem = f"ontology class {cls!r} gave the invalid individual name {value!r}"
            return (), f"{problem}; expected non-empty strings"
    # An ontology may list an individual twice (asserted under two classes); that is no error.
    return tuple(dict.fromkeys(v.strip() for v in values)), None


def _convert(type_: str, text: str) -> str | int | float | bool:
    """``text`` as a value of the param type; the :class:`ValueError` names the expected form."""
    if type_ == "string":
        return text
    if type_ == "int" and _INTEGER.fullmatch(text):
        return int(text)
    if type_ == "float" and _NUMBER.fullmatch(text):
        return float(text)
    if type_ == "bool" and text.lower() in _BOOLS:
        return _BOOLS[text.lower()]
    raise ValueError(_VALUE_HINTS[type_])


# --- messages and writing ---------------------------------------------------------------------


def _one_of(names: Sequence[str]) -> str:
    if not names:
        return "the name of a declared <port>"
    quoted = ", ".join(map(repr, names))
    return f"one of {quoted}" if len(names) > 1 else quoted


def _shorten(text: str, limit: int = 30) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _xml_text(text: str) -> str:
    """A templated field as element text: '$' doubled, then XML-escaped."""
    return escape(text.replace("$", "$$"))


def _xml_attr(text: str) -> str:
    """A templated field as a quoted attribute value."""
    return quoteattr(text.replace("$", "$$"))


def _value_text(value: str | int | float | bool) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # repr() round-trips exactly
    return str(value)


def _decimal_text(value: float) -> str:
    # repr() may use exponent notation (1e-05), which xs:decimal does not allow.
    return format(Decimal(repr(value)), "f")


def _is_set_value(value: str) -> bool:
    return bool(value) and value == value.strip() and ";" not in value
