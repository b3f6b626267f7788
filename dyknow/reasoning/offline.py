"""A formula over a recording: yesterday's data, the same semantics (``dyknow monitor FORMULA --mcap FILE``).

:func:`evaluate_recording` replays an MCAP file as fast as it reads (:class:`~dyknow.recording.Player`:
payloads decoded as live units get them, each message's origin time its sample time), takes the
samples of the topic each term is bound to (``ros2:/TOPIC`` and ``ros2dds:/TOPIC`` name the topic
``/TOPIC``, so the bindings of a live monitor serve here as they are; every sample read as a
bound term's is, :func:`~dyknow.reasoning.bindings.sample_value`), and evaluates the formula over them with
:func:`~dyknow.reasoning.evaluate`: every state's verdict, unknown ones included (None). A
``foreach`` formula's verdicts are per object and life (:func:`evaluate_recording_objects`, as
:func:`~dyknow.reasoning.semantics.evaluate_objects_ns` gives them). :func:`changes` keeps the
verdicts that differ from the one before; :func:`explainer` says, at a state, each comparison
of a formula with its sides' values then (``State(r2).speed <= 0.5: 0.9 <= 0.5``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Collection, Mapping

from dyknow.errors import FormulaError, TagError, did_you_mean
from dyknow.reasoning.bindings import sample_value, topic_of
from dyknow.reasoning.explain import MAX_ATOMS, explainer
from dyknow.reasoning.families import family_samples, members
from dyknow.reasoning.semantics import evaluate_ns, evaluate_objects_ns
from dyknow.reasoning.syntax import Formula, parse
from dyknow.reasoning.tree import is_family
from dyknow.recording import Player, ReadLimits
from dyknow.tags import parse_term

__all__ = ["MAX_ATOMS", "changes", "evaluate_recording", "evaluate_recording_objects", "explainer", "read_topics", "recording_samples"]


def evaluate_recording(
    formula: str, path: str | os.PathLike[str], bindings: Mapping[str, str], limits: ReadLimits | None = None
) -> list[tuple[int, bool | None]]:
    """Every state's ``(t_ns, verdict)`` of ``formula`` over the recording at ``path``, each term
    read from the topic ``bindings[term]`` names (the topic as written in the file, or its key).
    ``limits`` bound what reading the file holds in memory (:class:`~dyknow.recording.ReadLimits`).

    :class:`~dyknow.errors.FormulaError` when the formula does not read, a term has no binding, a
    binding names no term or a topic the file does not hold (with the topics it does);
    :class:`~dyknow.errors.RecordingError` when the file cannot be read.
    """
    parsed = parse(formula)
    return evaluate_ns(parsed, _samples(parsed, path, bindings, limits))


def evaluate_recording_objects(
    formula: str, path: str | os.PathLike[str], bindings: Mapping[str, str], limits: ReadLimits | None = None, *, idle_ns: int
) -> dict[str, list[list[tuple[int, bool | None]]]]:
    """A ``foreach`` formula's ``{object: [[(t_ns, verdict), ...] per life]}`` over the recording at
    ``path`` (``idle_ns`` ends a life), its terms read as :func:`evaluate_recording` reads them;
    its errors too."""
    parsed = parse(formula)
    return evaluate_objects_ns(parsed, _samples(parsed, path, bindings, limits), idle_ns=idle_ns)


def recording_samples(
    formula: str, path: str | os.PathLike[str], bindings: Mapping[str, str], limits: ReadLimits | None = None
) -> tuple[Formula, dict[str, list[tuple[int, object]]]]:
    """The formula parsed, and each of its terms' samples from the recording (as
    :func:`evaluate_recording` reads them; its errors too)."""
    parsed = parse(formula)
    return parsed, _samples(parsed, path, bindings, limits)


def changes(series: list[tuple[int, bool | None]]) -> list[tuple[int, bool | None]]:
    """The verdicts of ``series`` that differ from the one before (the first one included)."""
    out: list[tuple[int, bool | None]] = []
    for t, v in series:
        if not out or out[-1][1] is not v:
            out.append((t, v))
    return out


def read_topics(
    path: str | os.PathLike[str], wanted: Collection[str], limits: ReadLimits | None = None, *, also: Callable[[str], bool] | None = None
) -> tuple[dict[str, list[tuple[int, object]]], list[str]]:
    """The samples ``(origin_ns, value)`` of each topic in ``wanted`` the recording holds (a topic
    as written in the file, or its key), in one pass over the file; and every topic it holds,
    sorted (to name the close ones when a topic is missing). A topic the file lacks is left out.
    ``also(topic)``: read the topics (as written in the file) it says yes to as well (the members
    of a parameterized term a template binds)."""
    with Player(path, rate=math.inf, limits=limits) as player:
        names = {c.topic: c.topic for c in player.channels} | {key: topic for topic, key in player.keys.items()}
        if also is not None:
            wanted = [*wanted, *(c.topic for c in player.channels if c.topic not in wanted and also(c.topic))]
        found = {names[t]: t for t in wanted if t in names}
        samples: dict[str, list[tuple[int, object]]] = {t: [] for t in found.values()}
        by_topic = {topic: samples[asked] for topic, asked in found.items()}
        # (a topic asked by its name and by its key: one list, given under the name asked first)

        def take(message: object, record: object) -> None:
            into = by_topic.get(getattr(record, "topic", ""))
            if into is not None:
                into.append((message.origin_ns, sample_value(message.payload)))  # type: ignore[attr-defined]

        player.play(take)
        held = sorted(names)
    return {t: samples[found[names[t]]] for t in wanted if t in names}, held


def _samples(
    parsed: Formula, path: str | os.PathLike[str], bindings: Mapping[str, str], limits: ReadLimits | None
) -> dict[str, list[tuple[int, object]]]:
    """Each term's samples from the topic it is bound to."""
    families = [t for t in parsed.terms if is_family(t)]
    terms = [str(t) for t in parsed.terms if not is_family(t)]
    try:
        bindings = {str(parse_term(term)): topic_of(topic) for term, topic in bindings.items()}
    except TagError as exc:
        raise FormulaError(f"a binding's term does not read: {exc.what}", where="--bind", expected="TERM=TOPIC, such as Battery(robot)=robot/battery") from exc
    unbound = [t for t in terms if t not in bindings] + [f"a member of {f}" for f in families if not members(f, list(bindings))]
    if unbound:
        raise FormulaError(f"no topic for {', '.join(unbound)}", where="--bind", expected="TERM=TOPIC for every term of the formula, and each member "
                           "of a parameterized term read (SpeedLimit(z1)=limits/z1 for SpeedLimit(State(r).zone))")  # fmt: skip
    extra = [t for t in bindings if t not in terms and not any(members(f, [t]) for f in families)]
    if extra:
        raise FormulaError(f"{extra[0]!r} is no term of the formula", where="--bind", expected=f"one of {', '.join(terms)}{did_you_mean(extra[0], terms)}")
    read, held = read_topics(path, set(bindings.values()), limits)
    for term, topic in bindings.items():
        if topic not in read:
            raise FormulaError(
                f"the recording has no topic {topic!r} (for {term})", where=f"--bind {term}={topic}",
                expected=f"one of {', '.join(held)}{did_you_mean(topic, held)}",
            )  # fmt: skip
    out = {term: list(read[topic]) for term, topic in bindings.items()}
    for family in families:  # a parameterized term's: its members' samples as one stream
        out[str(family)] = family_samples(family, out)  # type: ignore[assignment]  # (its values: objects of the members')
    return out
