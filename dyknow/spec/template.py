"""Templates: a ``<transformation>`` with ``<args>``, expanded into one spec per combination.

``${Name}`` is replaced by each value of the arg ``Name`` in the label, source, description, param
values, port names, tag texts, tag ``port`` attributes, constraint values, requirements and
bindings (a ``<binding>``'s ``term`` and source), and
``$$`` stands for a literal ``$``. Several args expand as their cartesian product, in document order.
:meth:`Template.expand` checks what depends on the substituted text (param values against their
type, port names, tag ports, constraint values, requirements against the formula language,
bindings against the requirements' terms and the sources :mod:`dyknow.reasoning.bindings` takes,
distinct labels) and reports every problem of the
template, located.
"""

from __future__ import annotations

import itertools
import math
import re
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

from dyknow.errors import DyKnowError, FormulaError, SpecError, SpecIssue, TagError, compose, did_you_mean
from dyknow.keys import label_problem
from dyknow.reasoning.bindings import check_source
from dyknow.reasoning.families import refuse_families
from dyknow.reasoning.syntax import check_formula, parse
from dyknow.security import Limits
from dyknow.spec.model import (
    DEFAULT_MAX_EXPANSIONS,
    DEFAULT_PRIORITY,
    NUMBER,
    Arg,
    Constraint,
    Individuals,
    Param,
    Port,
    Tag,
    TransformationSpec,
    convert_param,
    one_of,
    shorten,
)
from dyknow.tags import parse_term

__all__ = ["DOLLAR", "Template"]

# One match per '$': an escaped "$$", a "${Name}" reference, or (empty group) a stray '$'.
DOLLAR = re.compile(r"\$(?:(?P<escaped>\$)|\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)\}|(?P<stray>))")
_PORT_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*")
_Problem = tuple[int, str, str, str]  # line, element, what, expected: one problem of one expansion


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
    source_line: int = 0
    arg_lines: tuple[int, ...] = ()
    param_lines: tuple[int, ...] = ()
    port_lines: tuple[int, ...] = ()
    tag_lines: tuple[int, ...] = ()
    constraint_lines: tuple[int, ...] = ()
    requirements: tuple[str, ...] = ()
    requirement_lines: tuple[int, ...] = ()
    bindings: tuple[tuple[str, str], ...] = ()
    binding_lines: tuple[int, ...] = ()

    @property
    def is_template(self) -> bool:
        """Whether the transformation has args (and so expands to one spec per combination)."""
        return bool(self.args)

    def expand(
        self,
        individuals: Individuals | None = None,
        *,
        max_expansions: int = DEFAULT_MAX_EXPANSIONS,
        max_bytes: int | None = None,
        limits: Limits | None = None,
    ) -> list[TransformationSpec]:
        """One spec per combination of arg values (cartesian product, args in document order).

        ``individuals(class_ref)`` supplies the values of an ``<arg class="...">``. Raises
        :class:`SpecError` with every problem of this template; a problem that is the same in
        every expansion is reported once, otherwise it names the expansions it occurs in. A
        template with more than ``max_expansions`` combinations, or whose expansions would hold
        more than ``max_bytes`` bytes of text (:meth:`expansion_bytes`), is refused before any is
        built. With ``limits`` (a manager's bounds), each requirement is held to its formula bounds
        as the manager holds a formula it watches (:func:`~dyknow.reasoning.check_formula`: nodes,
        windows, future horizon), so a requirement that could not be watched is refused here;
        without, to the language's own bounds only.
        """
        issues: list[SpecIssue] = []
        value_sets: list[tuple[str, ...]] = []
        for arg, line in zip(self.args, self.arg_lines, strict=True):
            arg_values, arg_problem = _arg_values(arg, individuals)
            if arg_problem:
                issues.append(SpecIssue(self.path, line, arg_problem[0], f"<arg> {arg.label!r}", arg_problem[1]))
            value_sets.append(arg_values)
        if issues:
            raise SpecError(issues)
        total = math.prod(len(v) for v in value_sets)
        if total > max_expansions:
            counts = " x ".join(str(len(v)) for v in value_sets)
            what = f"expands to {total:,} transformations ({counts} arg values)"
            raise SpecError([SpecIssue(self.path, self.line, what, "<transformation>", f"at most {max_expansions:,}")])
        if max_bytes is not None:
            size = total * self.expansion_bytes(max((len(v.encode()) for vs in value_sets for v in vs), default=0))
            if size > max_bytes:
                what = f"expands to {total:,} transformations of up to {size:,} bytes of text in all"
                raise SpecError([SpecIssue(self.path, self.line, what, "<transformation>", f"at most {max_bytes:,} bytes (--max-expansion-bytes)")])

        specs: list[TransformationSpec] = []
        found: dict[_Problem, list[str]] = {}  # a problem -> the expansions it occurs in
        for combination in itertools.product(*value_sets):
            values = dict(zip((a.label for a in self.args), combination, strict=True))
            spec, problems = self._build(values, limits)
            specs.append(spec)
            expansion = ", ".join(f"{name}={value}" for name, value in values.items())
            for problem in dict.fromkeys(problems):
                found.setdefault(problem, []).append(expansion)
        for (line, element, what, expected), expansions in found.items():
            where = ""
            if len(expansions) == 1 and len(specs) > 1:
                where = f" (in expansion {expansions[0]})"
            elif len(expansions) < len(specs):
                where = f" (in expansions {'; '.join(expansions)})"
            if expected:  # the expansion closes the message, after what is expected
                expected += where
            else:
                what += where
            issues.append(SpecIssue(self.path, line, what, element, expected))
        issues.extend(self._label_collisions(specs))
        if issues:
            raise SpecError(sorted(issues, key=lambda i: i.line))
        return specs

    def expansion_bytes(self, longest_value: int) -> int:
        """An upper bound of the text one expansion holds, when no arg value is longer than
        ``longest_value`` bytes: the template's text with every ``${...}`` taken that long."""
        texts = [self.label, self.source, self.description]
        texts += [t for p in self.params for t in (p.name, str(p.value))]
        texts += [p.name for p in self.ports]
        texts += [t for tag in self.tags for t in (tag.port, tag.tag)]
        texts += [t for c in self.constraints for t in (c.measure, c.op, str(c.value))]
        texts += list(self.requirements)
        texts += [t for binding in self.bindings for t in binding]
        return sum(len(t.encode()) + t.count("${") * longest_value for t in texts) + 64 * (1 + len(texts))

    def _build(self, values: Mapping[str, str], limits: Limits | None = None) -> tuple[TransformationSpec, list[_Problem]]:
        """The spec for one substitution, and the problems found in it."""
        problems: list[_Problem] = []

        def sub(text: str) -> str:
            return _substitute(text, values)

        params = []
        for param, line in zip(self.params, self.param_lines, strict=True):
            text = sub(str(param.value))
            try:
                value = convert_param(param.type, text)
            except ValueError as exc:
                problems.append((line, f"<param> {param.name!r}", f"value {shorten(text)!r} is not a valid {param.type}", str(exc)))
                value = text
            params.append(Param(param.name, param.type, value, param.mode))

        ports = [replace(port, name=sub(port.name)) for port in self.ports]
        first_line: dict[str, int] = {}
        for port, line in zip(ports, self.port_lines, strict=True):
            if not _PORT_NAME.fullmatch(port.name):
                expected = "letters, digits, '_' and '-', starting with a letter or '_'"
                problems.append((line, "<port>", f"{port.name!r} is not a valid port name", expected))
            elif port.name in first_line:
                where = f"first at line {first_line[port.name]}"
                problems.append((line, "<port>", f"duplicate port {port.name!r} ({where})", "each port name once"))
            first_line.setdefault(port.name, line)

        tags = [Tag(sub(tag.port), sub(tag.tag)) for tag in self.tags]
        out_ports = {p.name for p in ports if p.direction == "out"}
        outputs: set[str] = set()  # the output ports' tags, as terms write themselves (requirements read them)
        for tag, line in zip(tags, self.tag_lines, strict=True):
            if tag.port not in first_line:
                names = list(first_line)
                hint = did_you_mean(tag.port, names)
                problems.append((line, "<tag> @port", f"no port named {tag.port!r}", f"{one_of(names)}{hint}"))
            if tag.tag:
                try:
                    term = parse_term(tag.tag)
                    if tag.port in out_ports:
                        outputs.add(str(term))
                except TagError as exc:
                    problems.append((line, "<tag>", compose(exc.what, exc.where), exc.expected or ""))

        constraints = []
        for constraint, line in zip(self.constraints, self.constraint_lines, strict=True):
            text = sub(str(constraint.value))
            if NUMBER.fullmatch(text):
                value = float(text)
                if not math.isfinite(value):  # 1e309: it would compare as infinity and write itself back as 'inf'
                    problems.append((line, "<constraint> @value", f"{shorten(text)!r} is out of range", "a finite number such as 0.25"))
                constraints.append(replace(constraint, value=value))
                continue
            if constraint.op not in ("==", "!="):
                problem = f"{shorten(text)!r} is not a number, so op {constraint.op!r} cannot compare it"
                problems.append((line, "<constraint> @value", problem, "a number, or op == or !="))
            constraints.append(replace(constraint, value=text))

        requirements = []
        read: set[str] = set()  # the terms the requirements read
        for text, line in zip(self.requirements, self.requirement_lines, strict=True):
            formula_text = sub(text)
            try:
                formula = parse(formula_text) if limits is None else check_formula(formula_text, limits)
            except FormulaError as exc:
                problems.append((line, "<requirement>", compose(exc.what, exc.where), exc.expected or ""))
                continue
            try:
                refuse_families(formula, "a transformation's requirement")
            except FormulaError as exc:
                problems.append((line, "<requirement>", exc.what, exc.expected or ""))
                continue
            if not {str(term) for term in formula.terms} & outputs:
                expected = f"a term that is one of its output tags ({', '.join(sorted(outputs)) or 'it has none'})"
                problems.append((line, "<requirement>", f"{shorten(formula_text)!r} reads none of this transformation's outputs", expected))
                continue
            requirements.append(str(formula))
            read.update(str(term) for term in formula.terms)

        bindings: list[tuple[str, str]] = []
        for (term_text, source_text), line in zip(self.bindings, self.binding_lines, strict=True):
            term_text, source_text = sub(term_text), sub(source_text)
            try:
                bound = str(parse_term(term_text))
            except TagError as exc:
                problems.append((line, "<binding> @term", compose(exc.what, exc.where), exc.expected or ""))
                continue
            if bound not in read:
                expected = f"a term of its requirements ({', '.join(sorted(read)) or 'it has none'}){did_you_mean(bound, sorted(read))}"
                problems.append((line, "<binding> @term", f"{bound!r} is no term of a requirement", expected))
                continue
            if bound in outputs:
                problems.append((line, "<binding> @term", f"{bound!r} is an output tag of this transformation", "a term its requirements read from elsewhere"))
                continue
            if bound in dict(bindings):
                problems.append((line, "<binding> @term", f"{bound!r} is bound twice", "one source for each term"))
                continue
            try:
                source = check_source(source_text, f"binding {bound}={shorten(source_text)}")
            except DyKnowError as exc:
                problems.append((line, "<binding>", compose(exc.what, exc.where), exc.expected or ""))
                continue
            bindings.append((bound, source))

        label = sub(self.label)
        label_issue = label_problem(label) if label else None  # an empty one is reported where it is read
        if label_issue is not None:
            problems.append((self.label_line, "<label>", *label_issue))
        spec = TransformationSpec(
            label=label,
            source=sub(self.source),
            params=tuple(params),
            ports=tuple(ports),
            tags=tuple(tags),
            priority=self.priority,
            constraints=tuple(constraints),
            requirements=tuple(requirements),
            bindings=tuple(bindings),
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
        used = {m["name"] for m in DOLLAR.finditer(self.label)}
        unused = [f"${{{a.label}}}" for a in self.args if a.label not in used]
        if unused:
            hint = f"put {' and '.join(unused)} in the label"
        else:
            hint = "make the arg values give distinct labels"
        what = f"{n} expansions get the same label {label!r}"
        return [SpecIssue(self.path, self.label_line, what, "<label>", f"one label per expansion ({hint})")]


def _substitute(text: str, values: Mapping[str, str]) -> str:
    def replacement(match: re.Match[str]) -> str:
        if match["name"] is not None:
            return values[match["name"]]
        return "$"  # "$$" (parse_templates refuses any stray '$')

    return DOLLAR.sub(replacement, text)


def _arg_values(arg: Arg, individuals: Individuals | None) -> tuple[tuple[str, ...], tuple[str, str] | None]:
    """The substitution values of an arg, or a problem as ``(what, expected)`` (for ontology classes)."""
    if arg.ontology_class is None:
        return arg.values, None
    cls = arg.ontology_class
    if individuals is None:
        problem = f"takes its values from ontology class {cls!r}, but no ontology is loaded"
        return (), (problem, "--ontology FILE")
    try:
        found = individuals(cls)
    except Exception as exc:  # the resolver is the caller's code: any failure becomes a located issue
        problem = f"cannot get the individuals of ontology class {cls!r} ({type(exc).__name__}: {exc})"
        return (), (problem, "a class of the loaded ontology")
    if isinstance(found, str):  # a str is a Sequence[str] too, of one-letter values
        problem = f"the individuals of ontology class {cls!r} came back as one string"
        return (), (problem, "a sequence of names")
    values = tuple(found)
    if not values:
        return (), (f"ontology class {cls!r} has no individuals", "at least one")
    for value in values:
        if not isinstance(value, str) or not value.strip():
            problem = f"ontology class {cls!r} gave the invalid individual name {value!r}"
            return (), (problem, "non-empty strings")
    # An ontology may list an individual twice (asserted under two classes); that is no error.
    return tuple(dict.fromkeys(v.strip() for v in values)), None

