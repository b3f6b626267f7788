"""Mode files of ROS 2's ``system_modes`` package: systems, their modes, and what each asks of each node.

A mode file (system_modes' "SMH" file, YAML, as SUAVE's ``suave_modes.yaml`` is written) names
systems and nodes, each under ``ros__parameters``::

    actuation:                       # a system
      ros__parameters:
        type: system
        parts:                       # its parts: nodes or other systems (names by spaces or a list)
          drive_base
          manipulator
        modes:
          __DEFAULT__:               # every system and node has a default mode
            drive_base: active       # a part's state, and for an active part its mode
            manipulator: inactive
          PERFORMANCE:
            drive_base: active.FAST
            manipulator: active.STRONG
    drive_base:                      # a node
      ros__parameters:
        type: node
        modes:
          __DEFAULT__:
            ros__parameters:         # a node's mode is a set of parameter values
              max_speed: 0.1
          FAST:
            ros__parameters:
              max_speed: 0.9

The meaning is system_modes' own: a mode other than ``__DEFAULT__`` starts from the default
mode's parameters and parts and changes those it names; ``active`` alone is ``active.__DEFAULT__``;
a part's state is ``active``, ``inactive`` or ``unconfigured``. A part that the file does not
declare is a node without modes (only its state is set). A system's ``rules`` are read and checked
but not applied: dyknow leaves a mode whose part fails and takes the best other one
(:mod:`dyknow.ros2.modes`).

:func:`load_mode_file` reads a file; :meth:`ModeFile.targets` flattens a system's mode to what it
asks of each node (its state and parameters), through nested systems. Every mistake is a
:class:`~dyknow.errors.SpecError` located in the file (``modes.yaml:12: actuation: ...``): a
system mode naming a part not among the system's parts, a mode a part does not have, an unknown
state, a node mode without ``ros__parameters``, a parameter of a type ROS 2 parameters do not
have. The file is bounded (:data:`MAX_BYTES`, :data:`MAX_ENTRIES`) and YAML anchors and aliases
are refused, so a hostile file cannot make reading it expensive.
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import yaml

from dyknow.errors import SpecError, SpecIssue

__all__ = [
    "DEFAULT_MODE",
    "MAX_BYTES",
    "MAX_ENTRIES",
    "STATES",
    "ModeFile",
    "ParameterValue",
    "Target",
    "load_mode_file",
    "parse_mode_file",
    "targets_to_json",
]

#: The mode every system and node has (system_modes' name for it).
DEFAULT_MODE = "__DEFAULT__"
#: The states a mode can ask of a part.
STATES: tuple[str, ...] = ("active", "inactive", "unconfigured")
#: The largest mode file read.
MAX_BYTES = 1 << 20
#: The most entries (mappings' keys and lists' items, all together) a mode file may have.
MAX_ENTRIES = 100_000
_MAX_DEPTH = 32  # nesting of systems in systems

ParameterValue = bool | int | float | str | tuple[bool, ...] | tuple[int, ...] | tuple[float, ...] | tuple[str, ...]
"""A value a ROS 2 parameter holds: a bool, integer, double or string, or a list of one of them."""


@dataclass(frozen=True, slots=True)
class Target:
    """What a mode asks of one node: its ``state`` (one of :data:`STATES`), the node's own
    ``mode`` (for an active node with modes, else None) and the ``parameters`` that mode sets."""

    node: str
    state: str
    mode: str | None = None
    parameters: Mapping[str, ParameterValue] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class _System:
    name: str
    line: int
    parts: tuple[str, ...]
    modes: Mapping[str, Mapping[str, tuple[str, str | None, int]]]  # mode -> part -> (state, mode, line)
    mode_lines: Mapping[str, int]


@dataclass(frozen=True, slots=True)
class _Node:
    name: str
    line: int
    modes: Mapping[str, Mapping[str, ParameterValue]]  # mode -> parameters (the default's included)


@dataclass(frozen=True, slots=True)
class ModeFile:
    """A checked mode file: its ``path``, its systems and its nodes with modes."""

    path: str
    systems: Mapping[str, _System]
    nodes: Mapping[str, _Node]

    def modes(self, system: str) -> tuple[str, ...]:
        """The modes of ``system``, in the file's order (``__DEFAULT__`` first)."""
        found = self.systems.get(system)
        if found is None:
            raise self._unknown(system)
        return tuple(found.modes)

    def targets(self, system: str, mode: str) -> dict[str, Target]:
        """What mode ``mode`` of ``system`` asks of each node (its full name, ``/drive_base`` ->
        :class:`Target`), nested systems flattened: a system part ``inactive`` makes every node
        below it inactive."""
        if system not in self.systems:
            raise self._unknown(system)
        if mode not in self.systems[system].modes:
            raise SpecError([SpecIssue(self.path, self.systems[system].line, f"system {system!r} has no mode {mode!r}", system, _one_of(self.systems[system].modes))])
        out: dict[str, Target] = {}
        self._flatten(system, "active", mode, out, 0)
        return out

    def _flatten(self, part: str, state: str, mode: str | None, out: dict[str, Target], depth: int) -> None:
        system = self.systems.get(part)
        if system is None:
            node = self.nodes.get(part)
            parameters = node.modes[mode or DEFAULT_MODE] if node is not None and state == "active" else {}
            name = part if part.startswith("/") else f"/{part}"  # the node's full name (the file writes it without the root)
            out[name] = Target(name, state, (mode or DEFAULT_MODE) if node is not None and state == "active" else None, dict(parameters))
            return
        if depth > _MAX_DEPTH:
            raise SpecError([SpecIssue(self.path, system.line, f"systems nested more than {_MAX_DEPTH} deep", part, "a shallower hierarchy")])
        if state != "active":  # the parts of a system that is not active are all in that state
            for child in system.parts:
                self._flatten(child, state, None, out, depth + 1)
            return
        for child, (child_state, child_mode, _) in system.modes[mode or DEFAULT_MODE].items():
            self._flatten(child, child_state, child_mode, out, depth + 1)

    def _unknown(self, system: str) -> SpecError:
        return SpecError([SpecIssue(self.path, 0, f"no system {system!r} in the mode file", "", _one_of(self.systems))])


def _one_of(names: Mapping[str, Any] | tuple[str, ...]) -> str:
    listed = sorted(names)
    return ("one of " + ", ".join(listed[:20]) + (" ..." if len(listed) > 20 else "")) if listed else "a file that declares it"


def load_mode_file(path: str | pathlib.Path) -> ModeFile:
    """Read and check the mode file at ``path`` (see the module's documentation)."""
    where = str(path)
    try:
        with open(path, "rb") as file:
            data = file.read(MAX_BYTES + 1)
    except OSError as exc:
        raise SpecError([SpecIssue(where, 0, f"cannot read the mode file: {exc.strerror or exc}", "", "a system_modes YAML file")]) from exc
    return parse_mode_file(data, where)


def parse_mode_file(data: str | bytes, path: str = "<modes>") -> ModeFile:
    """Check a mode file's text (``path`` names it in errors); see :func:`load_mode_file`."""
    size = len(data.encode() if isinstance(data, str) else data)
    if size > MAX_BYTES:
        raise SpecError([SpecIssue(path, 0, f"the mode file has more than {MAX_BYTES:,} bytes", "", "a smaller file")])
    try:
        root = yaml.compose(data, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else 0
        problem = getattr(exc, "problem", None) or str(exc)
        raise SpecError([SpecIssue(path, line, f"not valid YAML: {str(problem)[:200]}", "", "a system_modes YAML file")]) from exc
    reader = _Reader(path)
    systems, nodes = reader.read(root)
    if reader.issues:
        raise SpecError(reader.issues)
    found = ModeFile(path, systems, nodes)
    reader.check_references(found)
    if reader.issues:
        raise SpecError(reader.issues)
    return found


def _line(node: yaml.Node) -> int:
    return int(node.start_mark.line) + 1


class _Reader:
    """Walks the composed YAML, collecting every issue."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.issues: list[SpecIssue] = []
        self._entries = 0
        self._seen: set[int] = set()
        self._constructor = yaml.constructor.SafeConstructor()

    def add(self, node: yaml.Node | int, element: str, what: str, expected: str = "") -> None:
        line = node if isinstance(node, int) else _line(node)
        if len(self.issues) < 100:
            self.issues.append(SpecIssue(self.path, line, what, element, expected))

    def _visit(self, node: yaml.Node) -> bool:
        if id(node) in self._seen:  # an alias: the same node reached twice
            self.add(node, "", "YAML anchors and aliases are not allowed in a mode file", "each value written out")
            return False
        self._seen.add(id(node))
        self._entries += 1
        if self._entries > MAX_ENTRIES:
            if self._entries == MAX_ENTRIES + 1:
                self.add(node, "", f"more than {MAX_ENTRIES:,} entries", "a smaller mode file")
            return False
        return True

    def mapping(self, node: yaml.Node, element: str, expected: str) -> list[tuple[str, yaml.Node, int]]:
        """The (key, value, line) of a mapping with text keys; an issue when it is not one."""
        if not self._visit(node):
            return []
        if not isinstance(node, yaml.MappingNode):
            self.add(node, element, "not a mapping", expected)
            return []
        out = []
        for key, value in node.value:
            if not self._visit(key) or not isinstance(key, yaml.ScalarNode):
                self.add(key, element, "a key that is not text", expected)
                continue
            out.append((str(key.value), value, _line(key)))
        return out

    def scalar(self, node: yaml.Node, element: str, expected: str) -> Any:
        if not self._visit(node):
            return None
        if isinstance(node, yaml.SequenceNode) and all(isinstance(item, yaml.ScalarNode) for item in node.value):
            return tuple(self._constructor.construct_object(item) for item in node.value if self._visit(item))
        if not isinstance(node, yaml.ScalarNode):
            self.add(node, element, "not a value", expected)
            return None
        return self._constructor.construct_object(node)

    def read(self, root: yaml.Node | None) -> tuple[dict[str, _System], dict[str, _Node]]:
        systems: dict[str, _System] = {}
        nodes: dict[str, _Node] = {}
        if root is None:
            self.add(1, "", "the mode file is empty", "systems and nodes, each with ros__parameters")
            return systems, nodes
        for name, body, line in self.mapping(root, "", "systems and nodes by name, each with ros__parameters"):
            if name in systems or name in nodes:
                self.add(line, name, "declared twice", "each system or node once")
                continue
            params = dict((k, (v, ln)) for k, v, ln in self.mapping(body, name, "ros__parameters: {type: system or node, ...}"))
            if "ros__parameters" not in params:
                self.add(line, name, "no ros__parameters", "ros__parameters: {type: system or node, modes: ...}")
                continue
            fields = {k: (v, ln) for k, v, ln in self.mapping(params["ros__parameters"][0], name, "type, parts and modes")}
            kind = self.scalar(fields["type"][0], f"{name}: type", "system or node") if "type" in fields else None
            if kind == "system":
                found = self._system(name, line, fields)
                if found is not None:
                    systems[name] = found
            elif kind == "node":
                nodes[name] = self._node(name, line, fields)
            else:
                self.add(fields["type"][1] if "type" in fields else line, f"{name}: type", f"{kind!r} is not a part type" if kind is not None else "missing", "type: system or type: node")
        return systems, nodes

    def _system(self, name: str, line: int, fields: dict[str, tuple[yaml.Node, int]]) -> _System | None:
        for extra in sorted(set(fields) - {"type", "parts", "modes", "rules"}):
            self.add(fields[extra][1], f"{name}: {extra}", "unknown field of a system", "type, parts, modes or rules")
        if "modes" not in fields:
            self.add(line, name, "a system without modes", "modes: {__DEFAULT__: {PART: active}, ...}")
            return None
        modes: dict[str, dict[str, tuple[str, str | None, int]]] = {}
        mode_lines: dict[str, int] = {}
        for mode, body, mode_line in self.mapping(fields["modes"][0], f"{name}: modes", "modes by name"):
            mode_lines[mode] = mode_line
            parts: dict[str, tuple[str, str | None, int]] = {}
            for part, value, part_line in self.mapping(body, f"{name}: modes.{mode}", "PART: STATE[.MODE] for each part"):
                text = self.scalar(value, f"{name}: modes.{mode}.{part}", "a state such as active.FAST")
                if not isinstance(text, str):
                    self.add(part_line, f"{name}: modes.{mode}.{part}", f"{text!r} is not a state", "active, active.MODE, inactive or unconfigured")
                    continue
                state, _, part_mode = text.strip().partition(".")
                if state not in STATES:
                    self.add(part_line, f"{name}: modes.{mode}.{part}", f"unknown state {state!r}", "active, active.MODE, inactive or unconfigured")
                    continue
                if part_mode and state != "active":
                    self.add(part_line, f"{name}: modes.{mode}.{part}", f"a mode for a part that is {state}", f"{state} alone, or active.{part_mode}")
                    continue
                parts[part] = (state, (part_mode or DEFAULT_MODE) if state == "active" else None, part_line)
            modes[mode] = parts
        if DEFAULT_MODE not in modes:
            self.add(fields["modes"][1], f"{name}: modes", f"no {DEFAULT_MODE} mode", f"a {DEFAULT_MODE} mode, which the others start from")
            return None
        default = modes[DEFAULT_MODE]
        modes = {mode: {**default, **parts} if mode != DEFAULT_MODE else parts for mode, parts in modes.items()}
        if "parts" in fields:
            listed = self.scalar(fields["parts"][0], f"{name}: parts", "the part names, one per line or a list")
            names = listed.split() if isinstance(listed, str) else [str(p) for p in listed] if isinstance(listed, tuple) else []
            if not names:
                self.add(fields["parts"][1], f"{name}: parts", "no parts", "the part names, one per line or a list")
        else:
            names = list(default)
        for mode, parts in modes.items():
            for part, (_, _, part_line) in parts.items():
                if part not in names:
                    self.add(part_line, f"{name}: modes.{mode}.{part}", f"{part!r} is not a part of system {name!r}", f"one of its parts: {', '.join(names[:20])}")
        if "rules" in fields:
            self._rules(name, fields["rules"][0], modes, names)
        return _System(name, line, tuple(names), {m: dict(p) for m, p in modes.items()}, mode_lines)

    def _rules(self, name: str, body: yaml.Node, modes: Mapping[str, Any], parts: list[str]) -> None:
        for rule, spec, line in self.mapping(body, f"{name}: rules", "rules by name"):
            fields = {k: (v, ln) for k, v, ln in self.mapping(spec, f"{name}: rules.{rule}", "if_target, if_part and new_target")}
            for required in ("if_target", "if_part", "new_target"):
                if required not in fields:
                    self.add(line, f"{name}: rules.{rule}", f"missing {required}", "if_target: active.MODE, if_part: [PART, STATE], new_target: active.MODE")
            for key in ("if_target", "new_target"):
                if key in fields:
                    text = self.scalar(fields[key][0], f"{name}: rules.{rule}.{key}", "active.MODE")
                    state, _, mode = str(text).partition(".")
                    if state not in STATES or (mode and mode not in modes):
                        self.add(fields[key][1], f"{name}: rules.{rule}.{key}", f"{text!r} is no state or mode of {name!r}", "active.MODE naming one of its modes, or inactive")
            if "if_part" in fields:
                part = self.scalar(fields["if_part"][0], f"{name}: rules.{rule}.if_part", "[PART, STATE]")
                if not isinstance(part, tuple) or len(part) != 2 or str(part[0]) not in parts:
                    self.add(fields["if_part"][1], f"{name}: rules.{rule}.if_part", f"{part!r} is not [PART, STATE] of a part of {name!r}", "[PART, STATE] such as [manipulator, inactive]")

    def _node(self, name: str, line: int, fields: dict[str, tuple[yaml.Node, int]]) -> _Node:
        for extra in sorted(set(fields) - {"type", "modes"}):
            self.add(fields[extra][1], f"{name}: {extra}", "unknown field of a node", "type or modes")
        modes: dict[str, dict[str, ParameterValue]] = {}
        if "modes" not in fields:
            self.add(line, name, "a node without modes", "modes: {__DEFAULT__: {ros__parameters: {...}}, ...}")
            return _Node(name, line, {})
        for mode, body, mode_line in self.mapping(fields["modes"][0], f"{name}: modes", "modes by name"):
            wrapper = {k: (v, ln) for k, v, ln in self.mapping(body, f"{name}: modes.{mode}", "ros__parameters: {PARAMETER: VALUE}")}
            if "ros__parameters" not in wrapper or len(wrapper) != 1:
                self.add(mode_line, f"{name}: modes.{mode}", f"has {', '.join(sorted(wrapper)) or 'nothing'} instead of ros__parameters", "ros__parameters: {PARAMETER: VALUE} alone")
                continue
            parameters: dict[str, ParameterValue] = {}
            self._parameters(f"{name}: modes.{mode}", "", wrapper["ros__parameters"][0], parameters)
            modes[mode] = parameters
        if DEFAULT_MODE not in modes:
            self.add(fields["modes"][1], f"{name}: modes", f"no {DEFAULT_MODE} mode", f"a {DEFAULT_MODE} mode, which the others start from")
            return _Node(name, line, {})
        default = modes[DEFAULT_MODE]
        return _Node(name, line, {mode: {**default, **values} for mode, values in modes.items()})

    def _parameters(self, element: str, prefix: str, body: yaml.Node, out: dict[str, ParameterValue]) -> None:
        """Parameters, nested mappings joined by dots as ROS 2 parameter files do (``a: {b: 1}`` is ``a.b``)."""
        for key, value, line in self.mapping(body, element, "PARAMETER: VALUE"):
            name = f"{prefix}{key}"
            if isinstance(value, yaml.MappingNode):
                self._parameters(element, f"{name}.", value, out)
                continue
            found = self.scalar(value, f"{element}.{name}", "a bool, integer, double, string or a list of one of them")
            checked = _parameter_value(found)
            if checked is None:
                self.add(line, f"{element}.{name}", f"{found!r} is not a ROS 2 parameter value", "a bool, integer, double, string or a list of one of them")
                continue
            out[name] = checked

    def check_references(self, found: ModeFile) -> None:
        """A part named ``active.MODE`` must have that mode."""
        for system in found.systems.values():
            for mode, parts in system.modes.items():
                for part, (state, part_mode, line) in parts.items():
                    if state != "active" or part_mode is None:
                        continue
                    owner = found.systems.get(part) or found.nodes.get(part)
                    modes = owner.modes if owner is not None else {DEFAULT_MODE: {}}
                    if part_mode not in modes:
                        declared = "declared" if owner is not None else "not declared in the file, so it has only __DEFAULT__"
                        self.add(line, f"{system.name}: modes.{mode}.{part}", f"{part!r} ({declared}) has no mode {part_mode!r}", _one_of(modes))


def _parameter_value(value: Any) -> ParameterValue | None:
    """``value`` if ROS 2 parameters can hold it (a bool, integer, double, string, or a list of
    one of them), else None."""
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, tuple) and value:
        for kind in (bool, int, float, str):
            if all(type(v) is kind for v in value):
                return value
    return None


def targets_to_json(targets: Mapping[str, Target]) -> str:
    """The ``targets`` param of a mode unit (see the module's documentation)."""
    return json.dumps(
        {t.node: {"state": t.state, "mode": t.mode, "parameters": {k: list(v) if isinstance(v, tuple) else v for k, v in t.parameters.items()}} for t in targets.values()},
        separators=(",", ":"),
    )
