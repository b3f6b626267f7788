"""The model of the spec format: frozen dataclasses for transformations and their parts.

A :class:`TransformationSpec` is one concrete transformation (after template expansion): the
unit's source, params, ports, tags, priority and constraints, and where it was written. It can
write itself back as XML (:meth:`TransformationSpec.to_xml`). The constants name what the format
allows; :func:`convert_param` reads a param's text as its declared type (the one place that
defines, for instance, which words a ``bool`` accepts).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from decimal import Decimal
from xml.sax.saxutils import escape, quoteattr

from dyknow.errors import did_you_mean

__all__ = [
    "BOOL_WORDS",
    "CONSTRAINT_OPS",
    "DEFAULT_MAX_EXPANSIONS",
    "DEFAULT_PRIORITY",
    "MANAGED_NODE_SOURCE",
    "MODE_PORT",
    "MODE_UNIT_SOURCE",
    "NODE_MIDDLEWARES",
    "NODE_PORT",
    "PARAMETER_PREFIX",
    "PARAM_TYPES",
    "PATH_MODES",
    "PORT_DIRECTIONS",
    "QUEUE_POLICIES",
    "TRANSFORMATION_TYPES",
    "Arg",
    "Constraint",
    "Individuals",
    "Param",
    "PathsLike",
    "Port",
    "Tag",
    "TransformationSpec",
    "convert_param",
    "one_of",
    "shorten",
]

DEFAULT_PRIORITY: int = 100
"""The priority of a transformation without ``<priority>``; lower numbers are preferred."""

PARAM_TYPES: tuple[str, ...] = ("string", "int", "float", "bool", "path")
MAX_QUEUE = 1_000_000  # the largest input queue a port may ask for
MAX_DEADLINE_MS = 86_400_000  # a day: the longest output deadline
INT_RANGE = (-(2**63), 2**63 - 1)  # int params are 64-bit (they reach C libraries such as OpenCV)
"""The values allowed in ``<param type="...">``. A ``path`` is text naming a file or folder:
for remote callers the manager confines it to its data roots (see :mod:`dyknow.security`)."""

PATH_MODES: tuple[str, ...] = ("read", "write")

DEFAULT_MAX_EXPANSIONS: int = 10_000
"""How many specs one template may expand to unless told otherwise (a bigger product is refused)."""
"""What a ``path`` param is for (``<param type="path" mode="...">``; ``read`` when absent)."""

CONSTRAINT_OPS: tuple[str, ...] = ("<", "<=", ">", ">=", "==", "!=")
"""The operators allowed in ``<constraint op="...">``."""

TRANSFORMATION_TYPES: tuple[str, ...] = ("unit", "nodelet")
"""The values allowed in ``<transformation type="...">``; "nodelet" is the paper's word for a unit."""

PORT_DIRECTIONS: tuple[str, ...] = ("in", "out")
"""The values allowed in ``<port type="...">``."""

MANAGED_NODE_SOURCE = "dyknow.ros2.managed:ManagedNode"
"""The ``<source>`` a ``<node>`` (a managed ROS 2 node) reads as: its unit drives the node."""

MODE_UNIT_SOURCE = "dyknow.ros2.modes:ModeUnit"
"""The ``<source>`` each mode of a ``<system>`` reads as: its unit switches the system's nodes to the mode."""

MODE_PORT = "mode"
"""The output port of a mode's transformation: the system's mode (a ``<tag>`` of a ``<system>`` tags it)."""

NODE_MIDDLEWARES: tuple[str, ...] = ("zenoh", "dds")
"""The values allowed in ``<node middleware="...">``: rmw_zenoh (``ros2:`` topics) or DDS (``ros2dds:``)."""

NODE_PORT = "out"
"""The output port of a managed node's transformation: its topic (a ``<tag>`` without @port tags it)."""

PARAMETER_PREFIX = "ros."
"""A managed node's unit param ``ros.NAME`` is its ROS 2 parameter ``NAME``, set when it is chosen."""

QUEUE_POLICIES: tuple[str, ...] = ("keep-last", "drop-new")
"""What a full input queue does with a new message (``<port type="in" policy="...">``): keep-last
drops the oldest queued message (like a Zenoh ring channel), drop-new refuses the new one."""


INTEGER = re.compile(r"[+-]?[0-9]+")  # the lexical space of xs:integer
NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)")  # the lexical space of xs:decimal

BOOL_WORDS: dict[str, bool] = {"true": True, "1": True, "false": False, "0": False}
"""The words a ``bool`` param accepts (xs:boolean's, compared case-insensitively)."""

_VALUE_HINTS = {"int": "a whole number such as 10", "float": "a number such as 0.5", "bool": "true or false"}

Individuals = Callable[[str], Sequence[str]]
"""Returns the substitution values for an ontology class reference such as ``ex:Camera``."""

PathsLike = str | os.PathLike[str] | Iterable[str | os.PathLike[str]]
"""One path or several: what :func:`~dyknow.spec.spec_files` and :func:`~dyknow.spec.load_specs` accept."""


@dataclass(frozen=True, slots=True)
class Param:
    """A parameter passed to the unit when it is spawned; ``value`` has the Python type of ``type``.

    ``mode`` ("read" or "write") is set for ``path`` params only.
    """

    name: str
    type: str
    value: str | int | float | bool
    mode: str | None = None


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
    """A condition on a measure (``battery >= 0.25``) that must hold for the transformation to run.

    ``margin`` (a number, ordering operators only) is its hysteresis: a transformation that runs
    keeps running until the measure is past the threshold by the margin (``battery >= 0.25``
    with margin 0.05 holds for a running one down to 0.20), while one that does not run needs the
    threshold itself, so a measure hovering at the threshold switches once per crossing.
    """

    measure: str
    op: str
    value: float | str
    margin: float = 0.0

    def holds(self, measured: float | str, *, held: bool = False) -> bool:
        """Whether ``measured op value`` holds; ``held``: for a transformation that runs (the
        threshold moved by ``margin`` in its favour).

        Numbers compare as numbers. A string only supports ``==`` and ``!=`` (a number never
        equals a string); the ordering operators are false for it.
        """
        if self.op == "==":
            return measured == self.value
        if self.op == "!=":
            return measured != self.value
        if isinstance(measured, str) or isinstance(self.value, str):
            return False
        slack = self.margin if held else 0.0
        if self.op == "<":
            return measured < self.value + slack
        if self.op == "<=":
            return measured <= self.value + slack
        if self.op == ">":
            return measured > self.value - slack
        if self.op == ">=":
            return measured >= self.value - slack
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
    requirements: tuple[str, ...] = ()  # temporal formulas its outputs must satisfy (dyknow.reasoning)
    #: the requirements' terms read from what exists, not requested: (term, source), a source being
    #: ros2:/TOPIC, ros2dds:/TOPIC or a Zenoh key (dyknow.reasoning.bindings)
    bindings: tuple[tuple[str, str], ...] = ()
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
        raise KeyError(f"{self.label!r} has no port named {name!r}; expected {one_of(names)}{did_you_mean(name, names)}")

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
            "param_types": {p.name: p.type for p in self.params},
            "ports": ports,
            "tags": [{"port": t.port, "tag": t.tag} for t in self.tags],
            "priority": self.priority,
            "constraints": [{"measure": c.measure, "op": c.op, "value": c.value} for c in self.constraints],
            "requirements": list(self.requirements),
            "bindings": dict(self.bindings),
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
            out.extend(f"    <arg label={quoteattr(name)}>{{{escape(value, _CARRIAGE_RETURN)}}}</arg>" for name, value in args)
            out.append("  </args>")
        if self.params:
            out.append("  <params>")
            for p in self.params:
                value = _xml_text(_value_text(p.value))
                mode = f" mode={quoteattr(p.mode)}" if p.mode else ""
                out.append(f"    <param name={quoteattr(p.name)} type={quoteattr(p.type)}{mode}>{value}</param>")
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
                if c.margin:
                    attributes += f' margin="{c.margin!r}"'
                out.append(f"    <constraint {attributes}/>")
            out.append("  </constraints>")
        if self.requirements:
            out.append("  <requirements>")
            out.extend(f"    <requirement>{_xml_text(r)}</requirement>" for r in self.requirements)
            out.append("  </requirements>")
        if self.bindings:
            out.append("  <bindings>")
            out.extend(f"    <binding term={_xml_attr(term)}>{_xml_text(source)}</binding>" for term, source in self.bindings)
            out.append("  </bindings>")
        out.append("</transformation>")
        return "\n".join(out) + "\n"


def convert_param(type_: str, text: str) -> str | int | float | bool:
    """``text`` as a value of the param type; the :class:`ValueError` names the expected form."""
    if type_ in ("string", "path"):
        return text
    if type_ == "int" and INTEGER.fullmatch(text):
        if len(text) <= 20 and INT_RANGE[0] <= int(text) <= INT_RANGE[1]:
            return int(text)
        raise ValueError("a whole number from -2**63 to 2**63-1")
    if type_ == "float" and NUMBER.fullmatch(text):
        if math.isfinite(float(text)):
            return float(text)
        raise ValueError("a finite number such as 0.5")
    if type_ == "bool" and text.lower() in BOOL_WORDS:
        return BOOL_WORDS[text.lower()]
    raise ValueError(_VALUE_HINTS[type_])


def one_of(names: Sequence[str]) -> str:
    """How a message lists port names: ``'a'``, or ``one of 'a', 'b'``."""
    if not names:
        return "the name of a declared <port>"
    quoted = ", ".join(map(repr, names))
    return f"one of {quoted}" if len(names) > 1 else quoted


def shorten(text: str, limit: int = 30) -> str:
    """``text`` cut to ``limit`` characters (with ``...``), for quoting input in a message."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


# A parser turns a carriage return written as such into a newline (XML's line-end rule); only a
# character reference keeps it.
_CARRIAGE_RETURN = {"\r": "&#13;"}


def _xml_text(text: str) -> str:
    """A templated field as element text: '$' doubled, then XML-escaped."""
    return escape(text.replace("$", "$$"), _CARRIAGE_RETURN)


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
