"""What the tests of live monitors recorded, then checked, share: driving the publishers until
everything is judged and recorded, and the verdicts the semantics gives over the recording with
the freshness a live monitor derived.

A live monitor derives each term's freshness from its rate (``FormulaMonitor.ages``); a
publisher starved by a loaded machine for longer than that makes its states unknown live, which a
check of the recording (no freshness asked) decides. So a live run is compared with the semantics
over the recorded samples *with the live ages*, and the check of the recording must agree with
each verdict that comparison gives."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from dyknow.recording import Recorder
from tests.conftest import wait_until


def publish_recorded(
    recorder: Recorder,
    publish: Callable[[int], None],
    ready: Callable[[], bool],
    judged: Callable[[int], bool],
    monitors: Callable[[], Iterable[Any]],
    *,
    topics: int,
    count: int,
    limit: int = 1500,
) -> int:
    """Call ``publish(i)`` every 20 ms until ``ready()``, each of the ``monitors()`` (their
    units) has derived the freshness of each of its terms (the ages hold from then on: the
    verdicts before may have taken none), and the recorder holds at least 5 messages on each of
    its ``topics``; then ``count`` times 10 ms apart; then on until
    ``judged(t_ns)`` (the last verdicts are at ``t_ns`` or later: later samples close a reorder
    window over the last ones), and the recorder holds every message published meanwhile
    (``publish`` puts one on each topic). Returns when the ``count`` publications started."""
    i = 0
    while not (
        ready() and all(set(unit.terms) <= set(unit.ages) for unit in monitors()) and len(recorder.topics) == topics and min(recorder.topics.values()) >= 5
    ):
        publish(i)
        i += 1
        time.sleep(0.02)
        assert i < limit, "the monitors and the recorder to receive every key"
    start_ns, recorded = time.time_ns(), recorder.count
    for _ in range(count):
        publish(i)
        i += 1
        time.sleep(0.01)
    end_ns = time.time_ns()
    while not judged(end_ns - 100_000_000):
        publish(i)
        i += 1
        time.sleep(0.01)
        assert time.time_ns() - end_ns < 30e9, "the last samples judged"
    wait_until(lambda: recorder.count >= recorded + topics * count, "the last samples recorded")
    return start_ns


def from_start(recording: Path, start_ns: int, out: Path) -> Path:
    """The messages of ``recording`` from ``start_ns`` on, as recorded, in ``out``."""
    from dyknow.recording import Player

    with Player(recording, rate=float("inf")) as player, Recorder((), out) as writer:
        player.play(lambda message, record: writer.write(message) if message.origin_ns >= start_ns else None)
    return out


def fresh_verdicts(
    formula: str, recording: Path, topics: Mapping[str, str], ages: Mapping[str, int], *, idle_ns: int | None = None
) -> dict[tuple[str, int], Any]:
    """The verdicts of ``formula`` over ``recording`` by the semantics, each term (``topics``:
    term -> recorded topic) read with the freshness ``ages`` (a live monitor's): ``{(object, t_ns):
    verdict}``, the object ``""`` unless ``idle_ns`` is given (a ``foreach`` formula's lives)."""
    from dyknow.reasoning import evaluate_ns, evaluate_objects_ns
    from dyknow.reasoning.offline import read_topics

    read, _ = read_topics(recording, set(topics.values()))
    streams = {term: read.get(topic, []) for term, topic in topics.items()}
    if idle_ns is None:
        return {("", t): v for t, v in evaluate_ns(formula, streams, max_age_ns=ages)}
    objects = evaluate_objects_ns(formula, streams, idle_ns=idle_ns, max_age_ns=ages)
    return {(obj, t): v for obj, lives in objects.items() for life in lives for t, v in life}
