"""Requirements checked over a recording, for CI: ``dyknow check REQUIREMENTS.toml --mcap RUN.mcap``.

A requirements file is TOML: bindings shared by its requirements (a term, the topic or key that
carries it in the recording), then one ``[[requirement]]`` table per requirement, each with a
``name``, a ``formula`` and, if need be, ``bindings`` of its own (over the shared ones) and
``idle_ms`` (a ``foreach`` formula: an object's life ends after this long without a sample)::

    [bindings]
    "State(r1)" = "floor/r1/state"
    "State(r)" = "floor/{r}/state"          # a template: State(r2) is read from floor/r2/state
    "Limits(floor)" = "floor/limits"

    [[requirement]]
    name = "speed under the zone's limit"
    formula = "forall r in Robot: historically[0, 1s] State(r).speed <= Limits(floor)[State(r).zone]"

A binding whose topic names an argument in braces (``{r}``) is a template: it binds every term
of its functor whose other arguments match, the braces replaced by that term's argument (the
exact binding of a term first, then the template with the fewest braces). A parameterized
term's members (``SpeedLimit(z1)``, ... of ``SpeedLimit(State(r).zone)``) are bound one by one,
or by a template of its functor: ``"SpeedLimit(z)" = "floor/limits/{z}"`` makes every recorded
topic it matches a member (``floor/limits/z7`` is ``SpeedLimit(z7)``).

Each requirement is evaluated over the recording as :mod:`dyknow.reasoning.semantics` states
it, as a live monitor evaluates it over the same samples: a ``forall`` the formula starts with
gives one verdict series per individual of the ontology (per tuple), keyed as a live monitor's
(``r1``, ``r1/r2``); a ``foreach`` one per object; any other formula one. A requirement holds
when no verdict is false; unknown verdicts (a window reaching before the first sample, a stale
stream) are counted, not failed. A requirement that cannot be checked (its formula does not
read, a term has no binding, the recording lacks a topic) is an error, said with its file and
line, and the others are still checked. :func:`junit_xml` reports the results as a JUnit XML
test suite, byte for byte the same for the same inputs (no run times in it).
"""

from __future__ import annotations

import functools
import math
import os
import re
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape, quoteattr

from dyknow.errors import DyKnowError, FormulaError, did_you_mean
from dyknow.message import Message
from dyknow.reasoning.bindings import topic_of
from dyknow.reasoning.explain import object_explainer
from dyknow.reasoning.families import family_samples, members
from dyknow.reasoning.objects import DEFAULT_IDLE_NS
from dyknow.reasoning.offline import changes, explainer, read_topics
from dyknow.reasoning.quantify import expand
from dyknow.reasoning.semantics import evaluate_ns, evaluate_objects_ns
from dyknow.reasoning.syntax import Formula, Quantifier
from dyknow.reasoning.tree import FAMILY_ARG, is_family, member_term
from dyknow.recording import ReadLimits, Recorder
from dyknow.security import Limits
from dyknow.tags import Term, parse_term

__all__ = ["MAX_REQUIREMENTS", "Requirement", "Result", "check_recording", "junit_xml", "load_requirements", "write_verdicts"]

#: The most requirements a file may hold.
MAX_REQUIREMENTS = 1_000
#: Runs of false verdicts explained per instance.
MAX_EXPLAINED = 10
#: Changes of a verdict explained per instance (:attr:`Result.changes`).
MAX_CHANGES_EXPLAINED = 50
#: Objects of a ``foreach`` requirement whose verdicts are explained.
MAX_OBJECTS_EXPLAINED = 100
_FIELDS = {"name", "formula", "bindings", "idle_ms"}
_HEADER = re.compile(r"^[ \t]*\[\[[ \t]*requirement[ \t]*\]\]", re.MULTILINE)
_BRACED = re.compile(r"\{([^{}]*)\}")


@dataclass(frozen=True)
class Requirement:
    """One requirement of a file: its ``name``, ``formula``, every binding it reads (the file's,
    then its own over them: term text -> topic), ``idle_ns`` (a ``foreach`` object's end) and
    ``where`` (``PATH:LINE`` of its table)."""

    name: str
    formula: str
    bindings: Mapping[str, str]
    idle_ns: int = DEFAULT_IDLE_NS
    where: str = ""


@dataclass
class Result:
    """What a requirement gave over a recording: its verdict series by instance (``""`` for a
    formula without quantifiers; ``r1`` or ``r1/r2`` for a leading ``forall``; the object for a
    ``foreach``), each ``[(t_ns, verdict), ...]`` in time order, or the ``error`` that kept it
    from being checked."""

    requirement: Requirement
    verdicts: dict[str, list[tuple[int, bool | None]]] = field(default_factory=dict)
    error: DyKnowError | None = None
    #: (instance, t_ns) -> each atom of the formula as written and with its sides' values at the
    #: first state of each run of false verdicts (a ``foreach`` object's: its body's atoms over
    #: its own samples, for the first :data:`MAX_OBJECTS_EXPLAINED` objects)
    why: dict[tuple[str, int], list[str]] = field(default_factory=dict)
    #: by instance, each change of its verdict ``(t_ns, verdict, atoms)``, the first verdict
    #: included; the atoms' values as :attr:`why` gives them, for the first
    #: :data:`MAX_CHANGES_EXPLAINED` changes of an instance
    changes: dict[str, list[tuple[int, bool | None, list[str]]]] = field(default_factory=dict)

    @property
    def held(self) -> bool:
        """Checked, with a verdict, and no verdict false (one never evaluated does not hold: a
        check that saw nothing says nothing)."""
        verdicts = [v for series in self.verdicts.values() for _, v in series]
        return self.error is None and bool(verdicts) and False not in verdicts

    def counts(self) -> dict[str, int]:
        """How many verdicts were true, false and unknown, over every instance."""
        out = {"true": 0, "false": 0, "unknown": 0}
        for series in self.verdicts.values():
            for _, v in series:
                out["unknown" if v is None else "true" if v else "false"] += 1
        return out

    def false_spans(self) -> dict[str, list[tuple[int, int]]]:
        """By instance, each run of false verdicts as ``(first t_ns, last t_ns)``."""
        out: dict[str, list[tuple[int, int]]] = {}
        for key, series in self.verdicts.items():
            spans: list[tuple[int, int]] = []
            start = last = -1
            for t, v in series:
                if v is False:
                    start, last = (t if start < 0 else start), t
                elif start >= 0:
                    spans.append((start, last))
                    start = -1
            if start >= 0:
                spans.append((start, last))
            if spans:
                out[key] = spans
        return out

    def to_dict(self) -> dict[str, Any]:
        """The result as JSON: name, formula, where, held, counts, false spans (ns), error."""
        return {
            "name": self.requirement.name,
            "formula": self.requirement.formula,
            "where": self.requirement.where,
            "held": self.held,
            "counts": self.counts(),
            "instances": sorted(self.verdicts),
            "false": {k: [list(s) for s in spans] for k, spans in sorted(self.false_spans().items())},
            "why": [{"instance": k, "t_ns": t, "atoms": atoms} for (k, t), atoms in sorted(self.why.items())],
            "error": None if self.error is None else str(self.error),
        }


def load_requirements(path: str | os.PathLike[str]) -> list[Requirement]:
    """The requirements of the TOML file at ``path`` (see the module documentation).

    :class:`~dyknow.errors.FormulaError` naming the file and line when it cannot be read, is no
    TOML, or a table or field is not as expected (the formulas are read when checked)."""
    where = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FormulaError(f"cannot read the requirements file: {exc}", where=where, expected="a readable UTF-8 TOML file") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise FormulaError(f"not TOML: {exc}", where=where, expected="a TOML file with [bindings] and [[requirement]] tables") from exc
    lines = [text.count("\n", 0, m.start()) + 1 for m in _HEADER.finditer(text)]
    unknown = sorted(set(data) - {"bindings", "requirement"})
    if unknown:
        raise FormulaError(f"unknown table or key {unknown[0]!r}", where=where,
                           expected=f"[bindings] and [[requirement]] tables{did_you_mean(unknown[0], ['bindings', 'requirement'])}")  # fmt: skip
    shared = _bindings(data.get("bindings", {}), where, "[bindings]")
    tables = data.get("requirement", [])
    if not isinstance(tables, list) or not tables:
        raise FormulaError("no requirement", where=where, expected="at least one [[requirement]] table with a name and a formula")
    if len(tables) > MAX_REQUIREMENTS:
        raise FormulaError(f"{len(tables):,} requirements", where=where, expected=f"at most {MAX_REQUIREMENTS:,} (MAX_REQUIREMENTS)")
    out: list[Requirement] = []
    names: set[str] = set()
    for i, table in enumerate(tables):
        at = f"{where}:{lines[i]}" if i < len(lines) else where
        what = f"requirement {i + 1}"
        extra = sorted(set(table) - _FIELDS)
        if extra:
            raise FormulaError(f"unknown field {extra[0]!r}", where=f"{at}: {what}",
                               expected=f"one of {', '.join(sorted(_FIELDS))}{did_you_mean(extra[0], sorted(_FIELDS))}")  # fmt: skip
        for key in ("name", "formula"):
            if not isinstance(table.get(key), str) or not table[key].strip():
                raise FormulaError(f"no {key}", where=f"{at}: {what}", expected=f"{key} = \"...\" (a non-empty string)")
        name = table["name"].strip()
        if name in names:
            raise FormulaError(f"a second requirement named {name!r}", where=f"{at}: {what}", expected="a name of its own")
        names.add(name)
        idle_ms = table.get("idle_ms", DEFAULT_IDLE_NS / 1e6)
        if isinstance(idle_ms, bool) or not isinstance(idle_ms, int | float) or not 0 < idle_ms < math.inf:
            raise FormulaError(f"idle_ms = {idle_ms!r}", where=f"{at}: requirement {name!r}", expected="a positive number of milliseconds")
        own = _bindings(table.get("bindings", {}), at, f"requirement {name!r}: bindings")
        out.append(Requirement(name, table["formula"], {**shared, **own}, round(idle_ms * 1e6), at))
    return out


def _bindings(table: object, where: str, what: str) -> dict[str, str]:
    """A bindings table, its terms in their canonical text (a template's braces checked)."""
    if not isinstance(table, dict):
        raise FormulaError(f"{what} is no table", where=where, expected='"TERM" = "TOPIC" pairs')
    out: dict[str, str] = {}
    for term, topic in table.items():
        if not isinstance(topic, str) or not topic:
            raise FormulaError(f"{what}: {term!r} = {topic!r}", where=where, expected="a topic or key, as text")
        try:
            parsed = parse_term(term)
        except DyKnowError as exc:
            raise FormulaError(f"{what}: {term!r} is no term: {exc.what}", where=where, expected="a term such as State(r1)") from exc
        for name in _BRACED.findall(topic):
            if name not in parsed.args:
                raise FormulaError(f"{what}: {topic!r} names {{{name}}}, no argument of {term}", where=where,
                                   expected=f"braces around one of its arguments: {', '.join(parsed.args) or 'it has none'}")  # fmt: skip
        out[str(parsed)] = topic_of(topic)
    return out


def topic_for(term: Term, bindings: Mapping[str, str]) -> str | None:
    """The topic ``term`` is read from: its exact binding, else the template of its functor
    whose other arguments match with the fewest braces (see the module documentation)."""
    exact = bindings.get(str(term))
    if exact is not None:
        return exact
    best: tuple[int, str] | None = None
    for text, topic in bindings.items():
        if "{" not in topic:
            continue
        template = parse_term(text)
        if template.functor != term.functor or len(template.args) != len(term.args):
            continue
        braced = set(_BRACED.findall(topic))
        if all(a == b or a in braced for a, b in zip(template.args, term.args, strict=True)):
            values = dict(zip(template.args, term.args, strict=True))
            filled = _BRACED.sub(lambda m, values=values: values.get(m.group(1), m.group(0)), topic)  # type: ignore[misc]
            if best is None or len(braced) < best[0]:
                best = (len(braced), filled)
    return None if best is None else best[1]


def _members_bound(family: Term, bindings: Mapping[str, str]) -> tuple[dict[str, str], re.Pattern[str] | None] | None:
    """A parameterized term's members bound one by one (member -> topic), and the topics a
    template of its functor binds (a pattern whose group is the argument); None when neither."""
    exact = {name: bindings[name] for name in members(family, list(bindings)) if "{" not in bindings[name]}  # (not a template)
    pattern: re.Pattern[str] | None = None
    for text, topic in bindings.items():
        try:
            template = parse_term(text)
        except DyKnowError:
            continue
        braced = set(_BRACED.findall(topic))
        if "{" not in topic or template.functor != family.functor or len(template.args) != len(family.args):
            continue
        position = family.args.index(FAMILY_ARG)
        if template.args[position] not in braced or not all(a == b or a in braced for a, b in zip(template.args, family.args, strict=True) if b != FAMILY_ARG):
            continue
        values = {a: b for a, b in zip(template.args, family.args, strict=True) if b != FAMILY_ARG}
        argument, regex, seen = template.args[position], "", False
        for piece in re.split(r"(\{[^{}]*\})", topic):
            name = piece[1:-1] if piece.startswith("{") and piece.endswith("}") else None
            if name == argument:
                regex += "(?P=arg)" if seen else "(?P<arg>[^/]+)"
                seen = True
            else:
                regex += re.escape(values[name] if name is not None and name in values else piece)
        pattern = re.compile(regex)
        break
    if not exact and pattern is None:
        return None
    return exact, pattern


def check_recording(
    requirements: Sequence[Requirement],
    path: str | os.PathLike[str],
    *,
    individuals: Callable[[str], Sequence[str]] | None = None,
    limits: ReadLimits | None = None,
    formula_limits: Limits | None = None,
) -> list[Result]:
    """Each requirement's :class:`Result` over the recording at ``path`` (read once), in order.

    ``individuals`` (an ontology's, :meth:`dyknow.ontology.Ontology.individuals`) expands
    ``forall``; ``limits`` bound what reading the file holds; ``formula_limits`` bound each
    formula as a manager's would (:class:`~dyknow.security.Limits`). A requirement that cannot
    be checked has its ``error``; :class:`~dyknow.errors.RecordingError` when the file cannot be read.
    """
    formula_limits = formula_limits if formula_limits is not None else Limits()
    plans: list[tuple[Result, list[tuple[str, Formula]], dict[str, str]]] = []
    families: list[tuple[Term, re.Pattern[str]]] = []  # parameterized terms bound by a template: its members are the topics it matches
    for requirement in requirements:
        result = Result(requirement)
        try:
            expanded = expand(requirement.formula, individuals, max_expansions=formula_limits.max_expansions, limits=formula_limits)
            terms: dict[str, str] = {}
            for _, formula in expanded:
                for term in formula.terms:
                    if is_family(term):  # a parameterized term: its members bound one by one, or by a template
                        bound = _members_bound(term, requirement.bindings)
                        if bound is None:
                            raise FormulaError(f"no topic for the members of {term}", where=f"{requirement.where}: requirement {requirement.name!r}",
                                               expected=f"a binding of each member (\"{member_term(term, 'z1')}\" = \"TOPIC\") or a template "
                                                        f"(\"{member_term(term, 'x')}\" = \"a/{{x}}/b\")")  # fmt: skip
                        terms.update(bound[0])
                        if bound[1] is not None:
                            families.append((term, bound[1]))
                        continue
                    topic = topic_for(term, requirement.bindings)
                    if topic is None:
                        known = sorted(requirement.bindings)
                        raise FormulaError(f"no topic for {term}", where=f"{requirement.where}: requirement {requirement.name!r}",
                                           expected=f"a binding \"{term}\" = \"TOPIC\" (or a template such as "
                                                    f"\"{term.functor}(x)\" = \"a/{{x}}/b\"){did_you_mean(str(term), known)}")  # fmt: skip
                    terms[str(term)] = topic
            plans.append((result, [(key or "", formula) for key, formula in expanded], terms))
        except DyKnowError as exc:
            result.error = _located(exc, requirement)
            plans.append((result, [], {}))
    wanted = {topic for _, _, terms in plans for topic in terms.values()}
    read, held = read_topics(path, wanted, limits, also=lambda topic: any(p.fullmatch(topic) for _, p in families))
    for result, cases, terms in plans:
        if result.error is not None:
            continue
        for family, pattern in families:  # the members its template binds: the topics recorded
            if any(family in formula.terms for _, formula in cases):
                for topic in read:
                    match = pattern.fullmatch(topic)
                    try:
                        member = str(member_term(family, match.group("arg"))) if match else None
                    except DyKnowError:
                        member = None  # (no name: no member)
                    if member is not None:
                        terms.setdefault(member, topic)
        missing = sorted({(t, topic) for t, topic in terms.items() if topic not in read})
        if missing:
            absent, topic = missing[0]
            result.error = FormulaError(
                f"the recording has no topic {topic!r} (for {absent})", where=f"{result.requirement.where}: requirement {result.requirement.name!r}",
                expected=f"one of {', '.join(held)}{did_you_mean(topic, held)}",
            )  # fmt: skip
            continue
        samples = {t: read[topic] for t, topic in terms.items()}
        for _, formula in cases:
            for term in formula.terms:
                if is_family(term):
                    samples[str(term)] = family_samples(term, samples)  # type: ignore[assignment]  # (objects of the members' values)
        try:
            result.verdicts = _evaluate(cases, samples, result.requirement.idle_ns)
        except DyKnowError as exc:
            result.error = _located(exc, result.requirement)
            continue
        explainers = _explainers(cases, samples, result.verdicts)
        for key, spans in result.false_spans().items():
            if key in explainers:
                for first, _ in spans[:MAX_EXPLAINED]:
                    result.why[(key, first)] = explainers[key](first)
        for key, series in result.verdicts.items():
            explain = explainers.get(key)
            result.changes[key] = [
                (t, v, explain(t) if explain is not None and i < MAX_CHANGES_EXPLAINED else []) for i, (t, v) in enumerate(changes(series))
            ]
    return [result for result, _, _ in plans]


def _explainers(
    cases: list[tuple[str, Formula]], samples: Mapping[str, list[tuple[int, object]]], verdicts: Mapping[str, object]
) -> dict[str, Callable[[int], list[str]]]:
    """By instance, what explains its verdicts at a time: the formula's atoms over the samples;
    for a ``foreach`` object (the first :data:`MAX_OBJECTS_EXPLAINED` of each formula), its body's
    atoms over the object's own samples, the variable bound to it."""
    out: dict[str, Callable[[int], list[str]]] = {}
    for key, formula in cases:
        if not _foreach(formula):
            out[key] = explainer(formula, samples)
            continue
        per_object = object_explainer(formula, samples)
        prefix = f"{key}/" if key else ""
        objects = [k.removeprefix(prefix) for k in verdicts if k.startswith(prefix)][:MAX_OBJECTS_EXPLAINED]
        for obj in objects:
            out[prefix + obj] = functools.partial(per_object, obj)
    return out


def write_verdicts(results: Sequence[Result], path: str | os.PathLike[str]) -> int:
    """Write every verdict of ``results`` to the MCAP file ``path``, for Foxglove's panels (its
    State Transitions panel plots ``.state`` or ``.verdict``): one topic per requirement and
    instance, ``verdicts/<name>`` (``verdicts/<name>/<instance>`` for a ``forall`` individual or a
    ``foreach`` object), each verdict a JSON message at its state's time, ``{"requirement",
    "formula", "instance", "verdict", "state"}`` (``state``: "true", "false" or "unknown"), and
    ``"why"`` (the atoms' values) at each change that has it. Returns how many were written;
    :class:`~dyknow.errors.RecordingError` when the file cannot be written."""
    written = 0
    with Recorder(path=path, metadata={"written_by": "dyknow check --verdicts"}) as recorder:
        for result in results:
            name = result.requirement.name
            for instance, series in result.verdicts.items():
                key = f"verdicts/{_key_chunk(name)}" + (f"/{'/'.join(_key_chunk(c) for c in instance.split('/'))}" if instance else "")
                why = {t: atoms for t, _, atoms in result.changes.get(instance, []) if atoms}
                for seq, (t, v) in enumerate(series):
                    payload: dict[str, Any] = {"requirement": name, "formula": result.requirement.formula, "instance": instance,
                                               "verdict": v, "state": "unknown" if v is None else "true" if v else "false"}  # fmt: skip
                    if t in why:
                        payload["why"] = why[t]
                    recorder.write(Message(payload, seq, t, t, key))
                    written += 1
    if recorder.error is not None:
        raise recorder.error
    return written


def _key_chunk(text: str) -> str:
    """``text`` as one chunk of a key: the characters a Zenoh key may not hold replaced by ``_``."""
    return re.sub(r"[/*$?#\s]", "_", text) or "_"


def _located(exc: DyKnowError, requirement: Requirement) -> DyKnowError:
    """``exc`` said of ``requirement``: its file, line and name first (once)."""
    here = f"{requirement.where}: requirement {requirement.name!r}"
    if exc.where is not None and exc.where.startswith(here):
        return exc
    located = FormulaError(exc.what, where=f"{here}: {exc.where}" if exc.where else here, expected=exc.expected)
    located.__cause__ = exc
    return located


def _foreach(formula: Formula) -> bool:
    return isinstance(formula.root, Quantifier) and formula.root.kind == "foreach"


def _evaluate(
    instances: list[tuple[str, Formula]], samples: Mapping[str, list[tuple[int, object]]], idle_ns: int
) -> dict[str, list[tuple[int, bool | None]]]:
    """Each instance's verdicts; a ``foreach`` one's by object (``KEY/OBJECT`` under a ``forall``)."""
    out: dict[str, list[tuple[int, bool | None]]] = {}
    for key, formula in instances:
        streams = {str(t): samples[str(t)] for t in formula.terms}
        if isinstance(formula.root, Quantifier) and formula.root.kind == "foreach":
            for obj, lives in evaluate_objects_ns(formula, streams, idle_ns=idle_ns).items():
                out[f"{key}/{obj}" if key else obj] = sorted((t, v) for life in lives for t, v in life)
        else:
            out[key] = [(t, v) for t, v in evaluate_ns(formula, streams)]
    return dict(sorted(out.items()))


_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ufffe\uffff\ud800-\udfff]")


def _xml_text(text: str) -> str:
    """``text`` without the characters XML 1.0 cannot hold (control characters: U+FFFD instead)."""
    return _NOT_XML.sub("\ufffd", text)


def junit_xml(results: Sequence[Result], *, suite: str = "dyknow requirements", recording: str = "") -> str:
    """``results`` as a JUnit XML report: a test suite of one test case per requirement, a
    ``<failure>`` for one that was false (where and when, by instance), an ``<error>`` for one
    that could not be checked. The same results give the same bytes (no times of the run)."""
    failures = sum(1 for r in results if r.error is None and not r.held)
    errors = sum(1 for r in results if r.error is not None)
    out = ['<?xml version="1.0" encoding="UTF-8"?>']
    out.append(f"<testsuites tests=\"{len(results)}\" failures=\"{failures}\" errors=\"{errors}\">")
    out.append(f"  <testsuite name={quoteattr(suite)} tests=\"{len(results)}\" failures=\"{failures}\" errors=\"{errors}\" skipped=\"0\">")
    if recording:
        out.append(f"    <properties><property name=\"recording\" value={quoteattr(recording)}/></properties>")
    for r in results:
        classname = quoteattr(r.requirement.where.rpartition(":")[0] or r.requirement.where or "requirements")
        head = f"    <testcase classname={classname} name={quoteattr(r.requirement.name)}"
        if r.error is not None:
            out.append(f"{head}>")
            out.append(f"      <error message={quoteattr(str(r.error))} type={quoteattr(type(r.error).__name__)}/>")
            out.append("    </testcase>")
        elif not r.held:
            out.append(f"{head}>")
            out.append(f"      <failure message={quoteattr(summary(r))} type=\"false\">{escape(details(r))}</failure>")
            out.append("    </testcase>")
        else:
            out.append(f"{head}>")
            out.append(f"      <system-out>{escape(summary(r))}</system-out>")
            out.append("    </testcase>")
    out.append("  </testsuite>")
    out.append("</testsuites>")
    return _xml_text("\n".join(out) + "\n")


def summary(result: Result) -> str:
    """One line: the counts, and where and when it was first false."""
    if result.error is not None:
        return f"not checked: {result.error}"
    c = result.counts()
    total = sum(c.values())
    states = f"{total:,} verdict{'' if total == 1 else 's'}: {c['true']:,} true, {c['false']:,} false, {c['unknown']:,} unknown"
    spans = result.false_spans()
    if not spans:
        return states if sum(c.values()) else "no verdict: no state of the recording had every term's samples"
    first = min((s[0][0], key) for key, s in spans.items())
    who = f" for {first[1]}" if first[1] else ""
    return f"false{who} at t={first[0] / 1e9:.3f} s ({states}; false for {len(spans)} of {len(result.verdicts)} instances)"


def details(result: Result) -> str:
    """The requirement, then every run of false verdicts, by instance: ``r2: false from t=12.300 s
    to t=14.100 s`` (``at t=...`` for one state), each followed by its atoms' values at its start
    (:attr:`Result.why`)."""
    lines = [f"{result.requirement.name}: {result.requirement.formula}"]
    for key, spans in sorted(result.false_spans().items()):
        for first, last in spans:
            when = f"at t={first / 1e9:.3f} s" if first == last else f"from t={first / 1e9:.3f} s to t={last / 1e9:.3f} s"
            lines.append(f"{key}: false {when}" if key else f"false {when}")
            lines.extend(f"  {atom}" for atom in result.why.get((key, first), ()))
    return "\n".join(lines)
