"""Reading spec files: the hardened XML parser and the structural checks of the format.

:func:`parse_templates` checks the structure of a document (elements, attributes, required parts,
template variables) and returns :class:`~dyknow.spec.Template` objects; :func:`parse_specs` and
:func:`load_specs` also expand them, and report every problem of every file in one
:class:`~dyknow.errors.SpecError`, each issue located and with its fields (element, what,
expected).

The XML is parsed with :mod:`xml.parsers.expat` directly and any DTD is refused before it is read,
so external entities and entity-expansion bombs cannot work.
"""

from __future__ import annotations

import os
import pathlib
import re
from collections.abc import Iterable, Mapping, Sequence
from decimal import Decimal
from types import MappingProxyType

from dyknow.errors import SpecError, SpecIssue, did_you_mean
from dyknow.security import Limits
from dyknow.spec.modefile import DEFAULT_MODE, Target, load_mode_file, targets_to_json
from dyknow.spec.modefile import STATES as MODE_STATES
from dyknow.spec.model import (
    BOOL_WORDS,
    CONSTRAINT_OPS,
    DECIMAL,
    DEFAULT_MAX_EXPANSIONS,
    DEFAULT_PRIORITY,
    INT_RANGE,
    INTEGER,
    MANAGED_NODE_SOURCE,
    MAX_DEADLINE_MS,
    MAX_QUEUE,
    MODE_PORT,
    MODE_UNIT_SOURCE,
    NODE_MIDDLEWARES,
    NODE_PORT,
    PARAM_TYPES,
    PARAMETER_PREFIX,
    PATH_MODES,
    PORT_DIRECTIONS,
    QUEUE_POLICIES,
    TRANSFORMATION_TYPES,
    Arg,
    Constraint,
    Individuals,
    Param,
    PathsLike,
    Port,
    Tag,
    TransformationSpec,
    convert_param,
    shorten,
)
from dyknow.spec.template import DOLLAR, Template
from dyknow.spec.xmltree import Element as _Node
from dyknow.spec.xmltree import parse_xml as _parse_xml

__all__ = ["ELEMENTS", "load_specs", "parse_specs", "parse_templates", "spec_files", "template_sources"]

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
    "param": ("name", "type", "mode"),
    "ports": (),
    "port": ("type", "deadline-ms", "queue", "policy"),
    "tags": (),
    "tag": ("port",),
    "priority": (),
    "constraints": (),
    "constraint": ("measure", "op", "value", "margin"),
    "requirements": (),
    "requirement": (),
    "node": ("name", "middleware", "lifecycle", "timeout-s"),
    "topic": ("type", "deadline-ms"),
    "bindings": (),
    "binding": ("term",),
    "system": ("name", "modes", "middleware", "timeout-s"),
    "mode": ("name",),
    "part": ("node", "state"),
}

ELEMENTS: Mapping[str, frozenset[str]] = MappingProxyType({name: frozenset(attributes) for name, attributes in _ATTRIBUTES.items()})
"""Every element of the format and the attributes it allows (``specs/transformation.xsd`` agrees)."""

_TRANSFORMATION_CHILDREN = (
    "label", "source", "description", "args", "params", "ports", "tags", "priority", "constraints", "requirements", "bindings",
)  # fmt: skip
_NODE_CHILDREN = ("label", "description", "args", "params", "topic", "tags", "priority", "constraints", "requirements")
_SYSTEM_CHILDREN = ("label", "description", "tags", "mode")
_MODE_CHILDREN = ("priority", "constraints", "requirements", "part")
_DEFINITIONS = ("transformation", "node", "system")  # what a <transformations> holds, or a document is
# the required children of a <node>, with their examples
_NODE_REQUIRED = {
    "label": "<label>camera-top</label>",
    "topic": '<topic type="sensor_msgs/msg/Image">/camera_top/image_raw</topic>',
}
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
    "node": {"name": 'name="/camera_top"'},
    "topic": {"type": 'type="sensor_msgs/msg/Image"'},
    "binding": {"term": 'term="Odom(r1)" naming a term of the requirements'},
    "system": {"name": 'name="f_generate_search_path" (a system of the mode file, or a name of your own)'},
    "mode": {"name": 'name="fd_spiral_high"'},
    "part": {"node": 'node="/spiral_search"', "state": 'state="active" (or inactive, unconfigured)'},
}
# the required children of a <system>, with their examples
_SYSTEM_REQUIRED = {
    "label": "<label>search</label> (each mode becomes the transformation search.MODE)",
    "tags": "<tags><tag>Mode(search)</tag></tags>",
}
# Each container holds any number of one kind of child.
_CONTAINERS = {
    "transformations": "transformation",
    "args": "arg",
    "params": "param",
    "ports": "port",
    "tags": "tag",
    "constraints": "constraint",
    "requirements": "requirement",
    "bindings": "binding",
}
_EMPTY_ELEMENTS = frozenset({"constraint"})  # attributes only, no text
# Root-only attributes: namespace declarations and the ones editors use to attach the XSD.
_SCHEMA_LOCATIONS = frozenset({"xsi:noNamespaceSchemaLocation", "xsi:schemaLocation"})


_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")



def parse_templates(data: str | bytes, path: str = "<string>") -> list[Template]:
    """Parse a spec document into templates, checking its structure.

    Raises :class:`SpecError` with every structural problem of the document.
    """
    templates, issues = _parse(data, path)
    if issues:
        raise SpecError(issues)
    return [template for template, _ in templates]


def template_sources(paths: PathsLike) -> list[tuple[str, int, str]]:
    """``(path, line, source)`` of the ``<source>`` of every ``<transformation>`` in ``paths``,
    read even where the rest of the file has mistakes (``dyknow validate`` checks them all in one
    run), those with a ``${...}`` left out; files that cannot be read or parsed are skipped."""
    files, _ = _spec_files(paths)
    found = []
    for file in files:
        try:
            templates, _ = _parse(file.read_bytes(), str(file))
        except OSError:
            continue
        found += [(t.path, t.source_line or t.line, t.source) for t, _ in templates if t.source_line and "${" not in t.source]
    return found


def parse_specs(
    data: str | bytes,
    path: str = "<string>",
    individuals: Individuals | None = None,
    *,
    max_expansions: int = DEFAULT_MAX_EXPANSIONS,
    max_bytes: int | None = None,
    limits: Limits | None = None,
) -> list[TransformationSpec]:
    """Parse and expand a spec document.

    Every problem of the document (structure, expansion, labels defined twice) is reported in
    one :class:`SpecError`. ``max_expansions`` and ``max_bytes`` bound each template's
    expansions; ``limits`` (a manager's bounds) holds its requirements to the formula bounds
    (see :meth:`Template.expand`).
    """
    located, issues = _load(data, path, individuals, max_expansions, max_bytes, limits)
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


def load_specs(
    paths: PathsLike,
    individuals: Individuals | None = None,
    *,
    max_expansions: int = DEFAULT_MAX_EXPANSIONS,
    max_bytes: int | None = None,
    limits: Limits | None = None,
) -> list[TransformationSpec]:
    """Load and expand every spec in ``paths`` (see :func:`spec_files`; the bounds as
    :func:`parse_specs` takes them).

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
        file_located, file_issues = _load(data, str(file), individuals, max_expansions, max_bytes, limits, files=True)
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
            issues.append(SpecIssue(str(path), 0, "no such file or directory", expected="a spec file or a directory of *.xml files"))
    # A file named both directly and through its directory must not clash with itself.
    unique: list[pathlib.Path] = []
    seen: set[pathlib.Path] = set()
    for file in files:
        if file.resolve() not in seen:
            seen.add(file.resolve())
            unique.append(file)
    return unique, issues


def _load(
    data: str | bytes,
    path: str,
    individuals: Individuals | None,
    max_expansions: int,
    max_bytes: int | None = None,
    limits: Limits | None = None,
    *,
    files: bool = False,
) -> tuple[list[tuple[TransformationSpec, int]], list[SpecIssue]]:
    """Parse and expand; (spec, line of its label) pairs and every issue but duplicate labels
    (``files``: whether the document may read files beside it, see :func:`_parse`)."""
    templates, issues = _parse(data, path, files=files)
    flagged = {issue.line for issue in issues}
    located: list[tuple[TransformationSpec, int]] = []
    for template, valid in templates:
        # (a template with structural issues is expanded too, for the issues its expansion finds:
        # every mistake in one run; not those on a line already flagged, which follow from them)
        try:
            expanded = template.expand(individuals, max_expansions=max_expansions, max_bytes=max_bytes, limits=limits)
            if valid:
                located.extend((spec, template.label_line) for spec in expanded)
        except SpecError as exc:
            issues.extend(i for i in exc.issues if valid or i.line not in flagged)
        except Exception:  # noqa: BLE001 - an invalid template's expansion may fail in any way: its issues stand
            if valid:
                raise
    return located, _once(issues)


def _once(issues: list[SpecIssue]) -> list[SpecIssue]:
    """Each mistake once per file: issues saying the same thing of the same element (an unknown
    class in the args of several transformations) as one, at its first line, naming the others."""
    lines: dict[tuple[str, str, str, str], list[int]] = {}
    for issue in sorted(issues, key=lambda i: i.line):
        lines.setdefault((issue.path, issue.element, issue.what, issue.expected), []).append(issue.line)
    out = []
    for (path, element, what, expected), at in lines.items():
        also = sorted(set(at[1:]) - {at[0]})
        more = f" (also at line{'s' if len(also) > 1 else ''} {', '.join(map(str, also))})" if also else ""
        out.append(SpecIssue(path, at[0], what + more, element, expected))
    return out


def _duplicate_labels(located: Iterable[tuple[TransformationSpec, int]]) -> list[SpecIssue]:
    issues = []
    first: dict[str, str] = {}
    for spec, line in located:
        if spec.label not in first:
            first[spec.label] = f"{spec.path}:{line}"
            continue
        what = f"duplicate label {spec.label!r}, first defined at {first[spec.label]}"
        issues.append(SpecIssue(spec.path, line, what, "<label>", "each label once"))
    return issues


# --- structure --------------------------------------------------------------------------------


class _Issues:
    """Collects the issues of one file."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.items: list[SpecIssue] = []

    def add(self, line: int, element: str, what: str, expected: str = "") -> None:
        self.items.append(SpecIssue(self.path, line, what, element, expected))


def _parse(data: str | bytes, path: str, *, files: bool = False) -> tuple[list[tuple[Template, bool]], list[SpecIssue]]:
    """The templates of a document, each with whether it is structurally valid, and every
    structural issue. ``files``:
    whether the document may read other files (a ``<system>``'s mode file, beside it): only a spec
    file the operator gave, never a document that came over the network."""
    try:
        root = _parse_xml(data, path)
    except SpecError as exc:
        return [], list(exc.issues)
    issues = _Issues(path)
    if root.name == "transformations":
        _check_element(root, issues, is_root=True)
        nodes = [c for c in root.children if c.name in _DEFINITIONS]
        if not root.children:
            issues.add(root.line, "<transformations>", "no <transformation> inside", "at least one")
    elif root.name in _DEFINITIONS:
        nodes = [root]
    else:
        hint = did_you_mean(root.name, ["transformations", *_DEFINITIONS])
        expected = "<transformations>, <transformation>, <node> or <system>"
        issues.add(root.line, f"<{root.name}>", "unknown root element", f"{expected}{hint}")
        nodes = []
    templates: list[tuple[Template, bool]] = []
    for node in nodes:
        before = len(issues.items)
        if node.name in ("node", "system"):
            _untagged_ports(node, NODE_PORT if node.name == "node" else MODE_PORT)
        _check_tree(node, issues, is_root=node is root)
        if node.name == "system":
            read = _read_system(node, issues, pathlib.Path(path).parent if files else None)
        else:
            read = [_read_node(node, issues) if node.name == "node" else _read_template(node, issues)]
        templates.extend((template, len(issues.items) == before) for template in read)  # (valid: expanded for its specs)
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
    if name == "node":
        return _NODE_CHILDREN
    if name == "system":
        return _SYSTEM_CHILDREN
    if name == "mode":
        return _MODE_CHILDREN
    if name == "part":
        return ("params",)
    if name == "transformations":
        return _DEFINITIONS
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
                issues.add(node.line, f"<{name}> @xmlns", problem, "no default namespace")
            continue
        expected = ", ".join(_ATTRIBUTES[name]) or "no attributes"
        hint = did_you_mean(attr, _ATTRIBUTES[name])
        issues.add(node.line, f"<{name}> @{attr}", "unknown attribute", f"{expected}{hint}")
    for attr, example in _REQUIRED_ATTRIBUTES.get(name, {}).items():
        if attr not in node.attrs:
            issues.add(node.line, f"<{name}>", f"missing @{attr}", example)

    allowed = _allowed_children(name)
    first_line: dict[str, int] = {}
    for child in node.children:
        if not allowed:
            expected = "no content" if name in _EMPTY_ELEMENTS else "text only"
            issues.add(child.line, f"<{child.name}>", f"unexpected element in <{name}>", expected)
        elif child.name not in allowed:
            expected = f"one of {', '.join(allowed)}" if len(allowed) > 1 else f"<{allowed[0]}>"
            hint = did_you_mean(child.name, allowed)
            issues.add(child.line, f"<{child.name}>", f"unknown element in <{name}>", f"{expected}{hint}")
        elif name in ("transformation", "node", "system", "mode", "part") and child.name in first_line and child.name not in ("mode", "part"):
            where = f"the first is at line {first_line[child.name]}"
            issues.add(child.line, f"<{child.name}>", f"duplicate <{child.name}> in <{name}> ({where})", "at most one")
        first_line.setdefault(child.name, child.line)

    if name in ("transformation", "node", "system"):
        required = {"transformation": _REQUIRED_CHILDREN, "node": _NODE_REQUIRED, "system": _SYSTEM_REQUIRED}[name]
        for child_name, example in required.items():
            if child_name not in first_line:
                issues.add(node.line, f"<{name}>", f"missing <{child_name}>", example)
    if node.text and (allowed or name in _EMPTY_ELEMENTS):
        if name in _EMPTY_ELEMENTS:
            expected = "an empty element"
        elif name in ("transformation", "node", "system", "mode", "part"):
            expected = "elements only"
        else:
            expected = f"only <{allowed[0]}> elements"
        issues.add(node.line, f"<{name}>", f"unexpected text {shorten(node.text)!r}", expected)


def _read_template(node: _Node, issues: _Issues) -> Template:
    """Read the values of a structurally checked ``<transformation>``, adding the issues found."""
    first: dict[str, _Node] = {}
    for child in node.children:
        first.setdefault(child.name, child)

    kind = node.attrs.get("type", "unit").strip()
    if kind not in TRANSFORMATION_TYPES:
        hint = did_you_mean(kind, TRANSFORMATION_TYPES)
        issues.add(node.line, "<transformation> @type", f"unknown type {kind!r}", f"unit or nodelet{hint}")

    args, arg_lines = _read_args(first.get("args"), issues)
    declared = [a.label for a in args]

    def text_of(name: str, example: str | None) -> tuple[str, int]:
        return _child_text(first, name, example, declared, issues)

    label, label_line = text_of("label", "a unique name such as undistort(${Cam})")
    source, source_line = text_of("source", "<source>package.module:Class</source>")
    description, _ = text_of("description", None)

    priority = _read_priority(first.get("priority"), issues)
    params, param_lines = _read_params(first.get("params"), declared, issues)
    ports, port_lines = _read_ports(first.get("ports"), declared, issues)
    tags, tag_lines = _read_tags(first.get("tags"), declared, issues)
    constraints, constraint_lines = _read_constraints(first.get("constraints"), declared, issues)
    requirements, requirement_lines = _read_requirements(first.get("requirements"), declared, issues)
    bindings, binding_lines = _read_bindings(first.get("bindings"), declared, issues)
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
        source_line=source_line,
        arg_lines=arg_lines,
        param_lines=param_lines,
        port_lines=port_lines,
        tag_lines=tag_lines,
        constraint_lines=constraint_lines,
        requirements=requirements,
        requirement_lines=requirement_lines,
        bindings=bindings,
        binding_lines=binding_lines,
    )


def _read_priority(element: _Node | None, issues: _Issues) -> int:
    if element is None:
        return DEFAULT_PRIORITY
    text = element.text
    # the length bounds int() (which refuses over 4,300 digits) before the range does
    if INTEGER.fullmatch(text) and len(text) <= 20 and INT_RANGE[0] <= int(text) <= INT_RANGE[1]:
        return int(text)
    if INTEGER.fullmatch(text):
        expected = "a whole number from -2**63 to 2**63-1 (lower is preferred)"
        issues.add(element.line, "<priority>", f"{shorten(text)!r} is out of range", expected)
    else:
        expected = "a whole number such as 1 (lower is preferred)"
        issues.add(element.line, "<priority>", f"{shorten(text)!r} is not an integer", expected)
    return DEFAULT_PRIORITY


def _untagged_ports(node: _Node, port: str) -> None:
    """A ``<tag>`` of a ``<node>`` or ``<system>`` without @port tags its one output ``port``
    (a node's topic, a system's mode)."""
    for tags in node.children:
        if tags.name == "tags":
            for tag in tags.children:
                if tag.name == "tag":
                    tag.attrs.setdefault("port", port)


def _read_node(node: _Node, issues: _Issues) -> Template:
    """Read a structurally checked ``<node>``: a managed ROS 2 node, as the transformation whose
    unit is :class:`~dyknow.ros2.managed.ManagedNode` (its params: the node's name, its topic's
    binding, whether it is a lifecycle node, the call timeout, and ``ros.NAME`` per parameter)."""
    first: dict[str, _Node] = {}
    for child in node.children:
        first.setdefault(child.name, child)
    args, arg_lines = _read_args(first.get("args"), issues)
    declared = [a.label for a in args]
    name = node.attrs.get("name", "").strip()
    _check_template("<node> @name", name, node.line, declared, issues)
    if "name" in node.attrs and not name:
        issues.add(node.line, "<node> @name", "empty", 'the ROS 2 node\'s name, such as name="/camera_top"')
    middleware = node.attrs.get("middleware", "zenoh").strip()
    if middleware not in NODE_MIDDLEWARES:
        hint = did_you_mean(middleware, NODE_MIDDLEWARES)
        issues.add(node.line, "<node> @middleware", f"unknown middleware {middleware!r}", f"zenoh (rmw_zenoh) or dds{hint}")
    lifecycle = node.attrs.get("lifecycle", "true").strip().lower()
    if lifecycle not in BOOL_WORDS:
        issues.add(node.line, "<node> @lifecycle", f"{shorten(lifecycle)!r} is not a boolean", "true or false")
    params = [Param("node", "string", name), Param("lifecycle", "bool", lifecycle)]
    if "timeout-s" in node.attrs:
        text = node.attrs["timeout-s"].strip()
        if not DECIMAL.fullmatch(text) or not 0 < Decimal(text) <= 3600:
            issues.add(node.line, "<node> @timeout-s", f"{shorten(text)!r} is not a number of seconds from 0 to 3600", "seconds such as 5")
        params.append(Param("timeout_s", "float", text))

    def text_of(child: str, example: str | None) -> tuple[str, int]:
        return _child_text(first, child, example, declared, issues)

    label, label_line = text_of("label", "a unique name such as camera-top")
    description, _ = text_of("description", None)
    topic, topic_line = text_of("topic", "the node's topic, such as /camera_top/image_raw")
    deadline_ms = None
    element = first.get("topic")
    if element is not None:
        ros_type = element.attrs.get("type", "").strip()
        _check_template("<topic> @type", ros_type, element.line, declared, issues)
        if "type" in element.attrs and not ros_type:
            issues.add(element.line, "<topic> @type", "empty", "a message type such as sensor_msgs/msg/Image")
        scheme = "ros2dds" if middleware == "dds" else "ros2"
        params.append(Param("binding", "string", f"{scheme}:{topic}?type={ros_type}"))
        if "deadline-ms" in element.attrs:
            text = element.attrs["deadline-ms"].strip()
            if not DECIMAL.fullmatch(text) or not 0 < Decimal(text) <= MAX_DEADLINE_MS:
                expected = f"milliseconds such as 500 (at most {MAX_DEADLINE_MS:,})"
                issues.add(element.line, "<topic> @deadline-ms", f"{text!r} is not a positive number", expected)
            else:
                deadline_ms = float(text)
    ros_params, ros_param_lines = _read_params(first.get("params"), declared, issues)
    for param in ros_params:
        if param.type == "path":
            issues.add(node.line, f"<param> {param.name!r}", "a path parameter of a ROS 2 node", "string, int, float or bool")
    params.extend(Param(PARAMETER_PREFIX + p.name, p.type, p.value) for p in ros_params)
    own_lines = (node.line,) * (len(params) - len(ros_params))
    tags, tag_lines = _read_tags(first.get("tags"), declared, issues)
    constraints, constraint_lines = _read_constraints(first.get("constraints"), declared, issues)
    requirements, requirement_lines = _read_requirements(first.get("requirements"), declared, issues)
    return Template(
        label=label,
        source=MANAGED_NODE_SOURCE,
        args=args,
        path=issues.path,
        line=node.line,
        description=description,
        params=tuple(params),
        ports=(Port(NODE_PORT, "out", deadline_ms),),
        tags=tags,
        priority=_read_priority(first.get("priority"), issues),
        constraints=constraints,
        label_line=label_line,
        arg_lines=arg_lines,
        param_lines=own_lines + ros_param_lines,
        port_lines=(topic_line,),
        tag_lines=tag_lines,
        constraint_lines=constraint_lines,
        requirements=requirements,
        requirement_lines=requirement_lines,
    )


def _read_system(system: _Node, issues: _Issues, base: pathlib.Path | None) -> list[Template]:
    """Read a structurally checked ``<system>``: one transformation per mode offered, whose unit
    is :class:`~dyknow.ros2.modes.ModeUnit` (its params: the system, the mode, what the mode asks
    of each node as JSON, the middleware and the call timeout). ``base``: the folder a mode file
    is read from (None: the document may read no file)."""
    first: dict[str, _Node] = {}
    for child in system.children:
        first.setdefault(child.name, child)
    name = system.attrs.get("name", "").strip()
    _check_template("<system> @name", name, system.line, (), issues)
    if "name" in system.attrs and not name:
        issues.add(system.line, "<system> @name", "empty", _REQUIRED_ATTRIBUTES["system"]["name"])
    middleware = system.attrs.get("middleware", "zenoh").strip()
    if middleware not in NODE_MIDDLEWARES:
        hint = did_you_mean(middleware, NODE_MIDDLEWARES)
        issues.add(system.line, "<system> @middleware", f"unknown middleware {middleware!r}", f"zenoh (rmw_zenoh) or dds{hint}")
    params = [Param("system", "string", name), Param("middleware", "string", middleware)]
    if "timeout-s" in system.attrs:
        text = system.attrs["timeout-s"].strip()
        if not DECIMAL.fullmatch(text) or not 0 < Decimal(text) <= 3600:
            issues.add(system.line, "<system> @timeout-s", f"{shorten(text)!r} is not a number of seconds from 0 to 3600", "seconds such as 5")
        params.append(Param("timeout_s", "float", text))
    label, label_line = _child_text(first, "label", "a name such as search", (), issues)
    description, _ = _child_text(first, "description", None, (), issues)
    tags, tag_lines = _read_tags(first.get("tags"), (), issues)
    modes = [m for m in system.children if m.name == "mode" and "name" in m.attrs]
    seen: dict[str, int] = {}
    for mode in modes:
        mode_name = mode.attrs["name"].strip()
        if mode_name in seen:
            issues.add(mode.line, "<mode> @name", f"duplicate mode {mode_name!r} (first at line {seen[mode_name]})", "each mode once")
        seen.setdefault(mode_name, mode.line)
    targets = _system_targets(system, name, modes, issues, base)
    if targets is None:
        return []
    offered: list[tuple[str, _Node | None, int]]
    if not modes:  # every mode of the file, its default preferred
        offered = [(mode, None, DEFAULT_PRIORITY - 1 if mode == DEFAULT_MODE else DEFAULT_PRIORITY) for mode in targets]
    else:
        offered = [(m.attrs["name"].strip(), m, 0) for m in modes]
    out = []
    for mode_name, element, priority in offered:
        children: dict[str, _Node] = {c.name: c for c in reversed(element.children)} if element is not None else {}
        constraints, constraint_lines = _read_constraints(children.get("constraints"), (), issues)
        requirements, requirement_lines = _read_requirements(children.get("requirements"), (), issues)
        if requirements:  # a suspect is tried in the shadow, beside the active configuration: a mode cannot be
            expected = "constraints on measures (a measure can be taken from any stream: --measure-from), with a margin"
            issues.add(requirement_lines[0], "<requirements>", "requirements of a mode (trying a mode in the shadow would switch the system)", expected)
        line = element.line if element is not None else system.line
        text = targets_to_json(targets.get(mode_name, {})).replace("$", "$$")
        mode_params = [*params, Param("mode", "string", mode_name.replace("$", "$$")), Param("targets", "string", text)]
        out.append(
            Template(
                label=f"{label}.{mode_name}",
                source=MODE_UNIT_SOURCE,
                path=issues.path,
                line=line,
                description=description,
                params=tuple(mode_params),
                ports=(Port(MODE_PORT, "out"),),
                tags=tags,
                priority=_read_priority(children.get("priority"), issues) if element is not None else priority,
                constraints=constraints,
                label_line=label_line,
                param_lines=(line,) * len(mode_params),
                port_lines=(line,),
                tag_lines=tag_lines,
                constraint_lines=constraint_lines,
                requirements=requirements,
                requirement_lines=requirement_lines,
            )
        )
    return out


def _system_targets(system: _Node, name: str, modes: list[_Node], issues: _Issues, base: pathlib.Path | None) -> dict[str, dict[str, Target]] | None:
    """What each mode asks of each node: from the mode file, or from the modes' ``<part>``s."""
    file = system.attrs.get("modes", "").strip()
    if "modes" in system.attrs:
        for mode in modes:
            for part in (c for c in mode.children if c.name == "part"):
                issues.add(part.line, "<part>", "a <part> in a mode of a system read from a mode file", "the parts in the mode file, or no @modes")
        if not file:
            issues.add(system.line, "<system> @modes", "empty", "a system_modes YAML file beside the spec, such as modes.yaml")
            return None
        if base is None:
            expected = "a spec file on disk (dyknow manager --specs, load_specs), or the modes written in the spec with <part>s"
            issues.add(system.line, "<system> @modes", "a mode file is read only for a spec file the operator gave", expected)
            return None
        try:
            model = load_mode_file(base / file)
            available = model.modes(name)
            for mode in modes:
                mode_name = mode.attrs["name"].strip()
                if mode_name not in available:
                    hint = did_you_mean(mode_name, available)
                    issues.add(mode.line, "<mode> @name", f"system {name!r} of {file} has no mode {mode_name!r}", f"one of {', '.join(available)}{hint}")
            return {mode: model.targets(name, mode) for mode in available}
        except SpecError as exc:
            for issue in exc.issues:
                if issue.line == 0 and issue.path == str(base / file):  # (a system not in the file: located at the <system>)
                    issues.add(system.line, "<system> @name", f"{issue.what} ({file})", issue.expected)
                else:
                    issues.items.append(issue)
            return None
    targets: dict[str, dict[str, Target]] = {}
    if not modes:
        issues.add(system.line, "<system>", "no <mode>", '<mode name="normal"><part node="/controller" state="active"/></mode>, or @modes naming a mode file')
    for mode in modes:
        parts = [c for c in mode.children if c.name == "part" and "node" in c.attrs and "state" in c.attrs]
        if not parts:
            issues.add(mode.line, "<mode>", "no <part>", '<part node="/controller" state="active"/> for each node the mode sets')
        mode_targets: dict[str, Target] = {}
        for part in parts:
            node, state = part.attrs["node"].strip(), part.attrs["state"].strip()
            node = node if node.startswith("/") else f"/{node}"
            if state not in MODE_STATES:
                issues.add(part.line, "<part> @state", f"unknown state {state!r}", f"one of {', '.join(MODE_STATES)}{did_you_mean(state, MODE_STATES)}")
            if node in mode_targets:
                issues.add(part.line, "<part> @node", f"{node} twice in mode {mode.attrs['name']!r}", "each node once per mode")
            values, _ = _read_params(next((c for c in part.children if c.name == "params"), None), (), issues)
            for param in values:
                if param.type == "path":
                    issues.add(part.line, f"<param> {param.name!r}", "a path parameter of a ROS 2 node", "string, int, float or bool")
            parameters = {}
            for param in values:
                try:
                    parameters[param.name] = convert_param(param.type, str(param.value))
                except ValueError as exc:
                    issues.add(part.line, f"<param> {param.name!r}", f"value {shorten(str(param.value))!r} is not a valid {param.type}", str(exc))
            if parameters and state != "active":
                issues.add(part.line, "<part>", f"parameters for a node that is {state}", "parameters only for an active node")
            mode_targets[node] = Target(node, state, None, parameters)
        targets[mode.attrs["name"].strip()] = mode_targets
    return targets


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
            issues.add(node.line, "<arg> @label", f"{label!r} is not a valid name", expected)
            continue
        if label in first_line:
            where = f"first at line {first_line[label]}"
            issues.add(node.line, "<arg> @label", f"duplicate arg {label!r} ({where})", "each arg once")
            continue
        first_line[label] = node.line
        ontology_class = node.attrs.get("class")
        if ontology_class is None:
            values, problem = _parse_set(node.text)
            if problem:
                issues.add(node.line, f"<arg> {label!r}", *problem)
            args.append(Arg(label, values))
        else:
            if not ontology_class.strip():
                issues.add(node.line, "<arg> @class", "empty", "an ontology class such as ex:Camera")
            if node.text:
                issues.add(node.line, f"<arg> {label!r}", f"has both @class and the values {shorten(node.text)!r}", "one or the other")
            args.append(Arg(label, (), ontology_class.strip()))
        lines.append(node.line)
    return tuple(args), tuple(lines)


def _parse_set(text: str) -> tuple[tuple[str, ...], tuple[str, str] | None]:
    """The values of ``{a; b; c}`` (braces optional), or a problem as ``(what, expected)``."""
    inner = text
    if inner.startswith("{") and inner.endswith("}"):
        inner = inner[1:-1]
    elif inner.startswith("{") or inner.endswith("}"):
        return (), (f"unbalanced braces in {shorten(text)!r}", "a set such as {cam1; cam2}")
    if not inner.strip():
        return (), ("empty set", 'values such as {cam1; cam2}, or class="ex:Class"')
    values = tuple(v.strip() for v in inner.split(";"))
    if "" in values:
        return (), (f"empty value in {shorten(text)!r}", "non-empty values separated by ';'")
    for i, value in enumerate(values):
        if value in values[:i]:
            return (), (f"duplicate value {value!r}", "each value once")
    return values, None


def _read_params(container: _Node | None, declared: Sequence[str], issues: _Issues) -> tuple[tuple[Param, ...], tuple[int, ...]]:
    params: list[Param] = []
    first_line: dict[str, int] = {}
    nodes = _children(container)
    for node in nodes:
        name = node.attrs["name"].strip()
        type_ = node.attrs.get("type", "string").strip()
        if not name:
            issues.add(node.line, "<param> @name", "empty", "a name such as config-path")
        elif name in first_line:
            where = f"first at line {first_line[name]}"
            issues.add(node.line, "<param> @name", f"duplicate param {name!r} ({where})", "each name once")
        first_line.setdefault(name, node.line)
        if type_ not in PARAM_TYPES:
            hint = did_you_mean(type_, PARAM_TYPES)
            expected = f"one of {', '.join(PARAM_TYPES)}{hint}"
            issues.add(node.line, "<param> @type", f"unknown type {type_!r}", expected)
        mode = node.attrs.get("mode")
        if mode is not None:
            mode = mode.strip()
            if type_ != "path":
                issues.add(node.line, "<param> @mode", "only allowed on path params", 'it on a <param type="path">')
            elif mode not in PATH_MODES:
                issues.add(node.line, "<param> @mode", f"unknown mode {mode!r}", f"read or write{did_you_mean(mode, PATH_MODES)}")
        elif type_ == "path":
            mode = "read"
        _check_template(f"<param> {name!r}", node.text, node.line, declared, issues)
        params.append(Param(name, type_, node.text, mode))
    return tuple(params), tuple(n.line for n in nodes)


def _read_ports(container: _Node | None, declared: Sequence[str], issues: _Issues) -> tuple[tuple[Port, ...], tuple[int, ...]]:
    ports: list[Port] = []
    nodes = _children(container)
    if container is not None and not container.children:
        expected = 'at least one <port type="out">name</port>'
        issues.add(container.line, "<ports>", "no <port> elements", expected)
    for node in nodes:
        direction = node.attrs["type"].strip()
        if direction not in PORT_DIRECTIONS:
            hint = did_you_mean(direction, PORT_DIRECTIONS)
            issues.add(node.line, "<port> @type", f"unknown direction {direction!r}", f"in or out{hint}")
        deadline_ms = None
        if "deadline-ms" in node.attrs:
            text = node.attrs["deadline-ms"].strip()
            if direction == "in":
                expected = 'it on a <port type="out">'
                issues.add(node.line, "<port> @deadline-ms", "only allowed on out ports", expected)
            elif not DECIMAL.fullmatch(text) or not 0 < Decimal(text) <= MAX_DEADLINE_MS:
                expected = f"milliseconds such as 500 (at most {MAX_DEADLINE_MS:,})"
                issues.add(node.line, "<port> @deadline-ms", f"{text!r} is not a positive number", expected)
            else:
                deadline_ms = float(text)
        queue = None
        if "queue" in node.attrs:
            text = node.attrs["queue"].strip()
            if direction == "out":
                issues.add(node.line, "<port> @queue", "only allowed on in ports", 'it on a <port type="in">')
            elif not INTEGER.fullmatch(text) or (len(text) <= 12 and int(text) < 1):
                issues.add(node.line, "<port> @queue", f"{text[:40]!r} is not a positive whole number", "a queue size such as 1 or 8")
            elif len(text) > 12 or int(text) > MAX_QUEUE:
                issues.add(node.line, "<port> @queue", f"{text[:40]!r} is too large", f"a queue size of at most {MAX_QUEUE:,}")
            else:
                queue = int(text)
        policy = None
        if "policy" in node.attrs:
            text = node.attrs["policy"].strip()
            if direction == "out":
                issues.add(node.line, "<port> @policy", "only allowed on in ports", 'it on a <port type="in">')
            elif text not in QUEUE_POLICIES:
                hint = did_you_mean(text, QUEUE_POLICIES)
                issues.add(node.line, "<port> @policy", f"unknown queue policy {text!r}", f"keep-last or drop-new{hint}")
            else:
                policy = text
        if not node.text:
            issues.add(node.line, "<port>", "empty port name", "a name such as undist")
        _check_template("<port>", node.text, node.line, declared, issues)
        ports.append(Port(node.text, direction, deadline_ms, queue, policy))
    return tuple(ports), tuple(n.line for n in nodes)


def _read_tags(container: _Node | None, declared: Sequence[str], issues: _Issues) -> tuple[tuple[Tag, ...], tuple[int, ...]]:
    tags: list[Tag] = []
    nodes = _children(container)
    for node in nodes:
        port = node.attrs["port"].strip()
        if not port:
            issues.add(node.line, "<tag> @port", "empty", "the name of one of the <ports>")
        if not node.text:
            issues.add(node.line, "<tag>", "empty tag", "a tag such as Undistorted(${Cam})")
        _check_template("<tag> @port", port, node.line, declared, issues)
        _check_template("<tag>", node.text, node.line, declared, issues)
        tags.append(Tag(port, node.text))
    return tuple(tags), tuple(n.line for n in nodes)


def _read_constraints(container: _Node | None, declared: Sequence[str], issues: _Issues) -> tuple[tuple[Constraint, ...], tuple[int, ...]]:
    constraints: list[Constraint] = []
    nodes = _children(container)
    for node in nodes:
        measure, op, value = (node.attrs[a].strip() for a in ("measure", "op", "value"))
        if not measure:
            issues.add(node.line, "<constraint> @measure", "empty", "a measure such as battery")
        if op not in CONSTRAINT_OPS:
            hint = did_you_mean(op, CONSTRAINT_OPS)
            expected = f"one of {', '.join(CONSTRAINT_OPS)}{hint}"
            issues.add(node.line, "<constraint> @op", f"unknown operator {op!r}", expected)
        if not value:
            expected = "a number such as 0.25 or a word such as docked"
            issues.add(node.line, "<constraint> @value", "empty", expected)
        _check_template("<constraint> @value", value, node.line, declared, issues)
        margin = 0.0
        if "margin" in node.attrs:
            text = node.attrs["margin"].strip()
            if not DECIMAL.fullmatch(text) or not 0 <= Decimal(text) <= Decimal("1e12"):
                issues.add(node.line, "<constraint> @margin", f"{shorten(text)!r} is not a number from 0", "the hysteresis, such as 0.05")
            elif op in ("==", "!="):
                issues.add(node.line, "<constraint> @margin", f"a margin for op {op!r}", "a margin with <, <=, > or >= only")
            else:
                margin = float(text)
        constraints.append(Constraint(measure, op, value, margin))
    return tuple(constraints), tuple(n.line for n in nodes)


def _read_requirements(container: _Node | None, declared: Sequence[str], issues: _Issues) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """The formulas' text as written (checked against the language when expanded)."""
    formulas: list[str] = []
    nodes = _children(container)
    for node in nodes:
        if not node.text:
            issues.add(
                node.line, "<requirement>", "empty", "a temporal formula over the outputs, such as eventually[0, 2s] Track(${Cam}).seen"
            )
        _check_template("<requirement>", node.text, node.line, declared, issues)
        formulas.append(node.text)
    return tuple(formulas), tuple(n.line for n in nodes)


def _read_bindings(container: _Node | None, declared: Sequence[str], issues: _Issues) -> tuple[tuple[tuple[str, str], ...], tuple[int, ...]]:
    """The requirements' terms bound to what exists: ``(term, source)`` as written (checked when expanded)."""
    bindings: list[tuple[str, str]] = []
    nodes = _children(container)
    for node in nodes:
        term = node.attrs["term"]
        if not node.text:
            issues.add(node.line, "<binding>", "empty", "the source of the term: ros2:/TOPIC, ros2dds:/TOPIC?type=pkg/msg/Type or a Zenoh key")
        _check_template("<binding> @term", term, node.line, declared, issues)
        _check_template("<binding>", node.text, node.line, declared, issues)
        bindings.append((term, node.text))
    return tuple(bindings), tuple(n.line for n in nodes)


def _child_text(first: Mapping[str, _Node], name: str, example: str | None, declared: Sequence[str], issues: _Issues) -> tuple[str, int]:
    """The text and line of the child ``name`` of ``first`` (("", 0) when absent); an empty one is
    an issue when ``example`` says what to write, and a template in it is checked against ``declared``."""
    element = first.get(name)
    if element is None:
        return "", 0
    if not element.text and example is not None:
        issues.add(element.line, f"<{name}>", "empty", example)
    _check_template(f"<{name}>", element.text, element.line, declared, issues)
    return element.text, element.line


def _check_template(where: str, text: str, line: int, declared: Sequence[str], issues: _Issues) -> None:
    """Report each stray '$' and each ``${Name}`` that names no declared arg."""
    for match in DOLLAR.finditer(text):
        name = match["name"]
        if match["stray"] is not None:
            expected = "${Name} to use an arg, or $$ for a literal '$'"
            issues.add(line, where, f"stray '$' in {shorten(text)!r}", expected)
        elif name is not None and name not in declared:
            if declared:
                expected = f"one of the declared args: {', '.join(declared)}{did_you_mean(name, declared)}"
            else:
                expected = f'it declared as <args><arg label="{name}">{{...}}</arg></args>'
            issues.add(line, where, f"undefined template variable ${{{name}}}", expected)
