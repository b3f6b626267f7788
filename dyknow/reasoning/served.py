"""The formulas a monitor unit serves, and a sample pushed to those that read it.

A monitor unit (:class:`dyknow.reasoning.unit.FormulaMonitor`) serves one formula or several;
each is a :class:`Served`: its monitor and what it published last. :func:`push_sample` hands one
sample to every formula that reads its term and returns the verdicts to publish. It runs once per
sample and formula (ten ``foreach`` formulas over one tracker stream of 1,000 objects at 20 Hz:
200,000 times a second), so it is compiled with the monitors (``setup.py``): interpreted, this
loop cost about as much as the ten monitors' own steps.
"""

from __future__ import annotations

from typing import Any

from dyknow.reasoning.objects import ObjectMonitor
from dyknow.reasoning.progression import Monitor, Verdict
from dyknow.reasoning.values import object_key, read

__all__ = ["EXPLAIN_BURST", "Served", "push_sample"]

#: The explanations a formula gives at once (then one per EXPLAIN_GAP_NS of sample time).
EXPLAIN_BURST = 8


class Served:
    """One formula a monitor unit serves: its monitor, which of the unit's terms it reads, what it
    published last (per object)."""

    def __init__(self, name: str | None, monitor: Monitor | ObjectMonitor) -> None:
        self.name = name
        self.monitor = monitor
        self.reach: int | None = monitor.formula.reach_ns
        self.horizon: int = monitor.formula.horizon_ns
        self.given_up_logged = 0
        self.last_published: dict[str | None, bool | None] = {}
        self.last_verdict: bool | None = None  # the last verdict published (a formula without foreach): its changes are explained
        self.object_verdicts: dict[str, bool | None] = {}  # a foreach formula's: each live object's
        self.explained_ns = 0  # the state whose change was last explained (sample time), and the
        self.explain_tokens = float(EXPLAIN_BURST)  # explanations it may give at once (refilled with sample time)


def push_sample(
    readers: list[tuple[Served, int]], t_ns: int, value: Any, quiet: bool
) -> tuple[list[tuple[Served, Verdict, str | None]], Monitor | ObjectMonitor | None]:
    """Push one sample (at ``t_ns``) to every formula of ``readers`` (each with the position of
    the sample's term among its monitor's terms); the verdicts to publish, in order, and the
    last monitor that dropped the sample as late (None when none did).

    The object a sample of a ``foreach`` formula's quantified stream names is read once for
    every formula that reads it down the same fields.

    ``quiet`` (only changes are published, and nobody listens to every verdict): an object's
    verdict equal to the one it last published is left out here, as publishing would leave it
    out (an object's repeated verdict: 10,000s a second); the others are all returned."""
    out: list[tuple[Served, Verdict, str | None]] = []
    late: Monitor | ObjectMonitor | None = None
    fields: tuple[str, ...] | None = None  # the fields the sample's object was read down, once
    key: str | None = None
    for served, local in readers:
        monitor = served.monitor
        if isinstance(monitor, ObjectMonitor):
            before = monitor.late
            if local == monitor.domain_index and type(value) is not list:  # (a frame: its elements' objects, in push_index)
                domain = monitor.domain.fields
                if domain != fields:
                    fields, key = domain, object_key(read(value, domain))
                pairs = monitor.push_object(t_ns, value, key)
            else:
                pairs = monitor.push_index(local, t_ns, value)
            if pairs:
                if quiet:
                    _changes(served, pairs, out)
                else:
                    for key, verdict in pairs:
                        out.append((served, verdict, key))
        else:
            before = monitor.late
            for verdict in monitor.push_index(local, t_ns, value):
                out.append((served, verdict, None))
        if monitor.late != before:
            late = monitor
    return out, late


def _changes(served: Served, pairs: list[tuple[str, Verdict]], out: list[tuple[Served, Verdict, str | None]]) -> None:
    """The pairs whose verdict is not the object's last published one, to ``out``: compared with
    the verdicts before them in ``pairs`` too, as publishing them one by one would."""
    last = served.last_published
    if len(pairs) == 1:
        key, verdict = pairs[0]
        if last.get(key) is not verdict.verdict:
            out.append((served, verdict, key))
        return
    now: dict[str, bool | None] = {}
    for key, verdict in pairs:
        previous = now[key] if key in now else last.get(key)
        if previous is not verdict.verdict:
            out.append((served, verdict, key))
            now[key] = verdict.verdict
