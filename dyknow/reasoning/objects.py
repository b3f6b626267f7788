"""One monitor per object: :class:`ObjectMonitor` runs a ``foreach`` formula
(``foreach t in Track(field).id: always[0, 2s] Track(field).speed < 3``) as one
:class:`~dyknow.reasoning.Monitor` of its body per object, as the semantics defines it
(:mod:`dyknow.reasoning.semantics`: each object's lives, evaluated apart).

**Instances.** A sample of the quantified stream whose field names an object (a string, or a
number) goes to that object's instance, which is made at the object's first sample (seeded with
the other terms' latest samples, so its states hold them from the start, and with their outages
within the body's reach, at most :data:`MAX_OUTAGES` each, so that its first windows count
them as the semantics' span rule says) and ends
``idle_ns`` (sample time) after the object's last sample: the first sample of any term later
than that (less the reorder delay) retires it (its buffered states are closed, its verdicts
given), and a sample of the object after that starts a new instance. The other terms' samples go
to every live instance. A sample whose field names no object is counted in :attr:`unassigned`.
A sample of the quantified stream whose value is a list is a *frame* (a tracker's tracks): one
sample per element, all at its time, so one message can carry every object's sample.

**Bounds.** At most ``max_objects`` instances live at once, and no more than ``max_cells``
can hold at their least (:data:`~dyknow.reasoning.progression.MIN_STATES` states of the body's
nodes each: :attr:`capacity`): a sample of a new object past that is refused, and counted in
:attr:`refused` (the objects already tracked go on). Each instance keeps at most its share of
``max_cells`` (the cells over the instances alive, their number rounded up to a power of two, so
that shares are dealt again only when it doubles or falls to a quarter: 10,000 objects appearing
cost 10,000 deals, not 50 million), so the monitor's memory is bounded by ``max_cells`` cells
plus the instances' constant part, however many objects a stream names over time, and however
many monitors share a manager's cells (each instance's least states count against them: 4,000
monitors of 1,000 objects each could otherwise keep 16 states of 64 million instances).
:meth:`discard` lets go of every instance at once, deciding nothing (a unit going).
"""

from __future__ import annotations

import heapq
from collections.abc import Mapping
from typing import Any

from dyknow.errors import FormulaError, TagError, did_you_mean
from dyknow.reasoning.families import Members
from dyknow.reasoning.progression import DEFAULT_MAX_CELLS, MIN_STATES, Monitor, Verdict
from dyknow.reasoning.syntax import Formula, Quantifier, Stream, parse
from dyknow.reasoning.values import object_key, read
from dyknow.tags import parse_term

__all__ = ["DEFAULT_IDLE_NS", "DEFAULT_MAX_OBJECTS", "MAX_OUTAGES", "ObjectMonitor"]

#: How long an object lives without a sample (sample time): 10 s.
DEFAULT_IDLE_NS = 10_000_000_000
#: How many objects a monitor tracks at once.
DEFAULT_MAX_OBJECTS = 1000
#: The most outages of one term a foreach monitor keeps for its new instances (the newest; each
#: is a gap of more than the term's maximum age between two samples, within the body's reach)
MAX_OUTAGES = 1024


class ObjectMonitor:
    """Monitors a ``foreach`` formula, one instance of its body per object (see the module
    documentation). ``push`` a sample, get the ``(object, verdict)`` pairs it decided;
    :meth:`flush` at the end of the input. Not thread-safe: one caller at a time."""

    def __init__(
        self,
        formula: str | Formula,
        *,
        reorder_ns: int = 0,
        max_cells: int = DEFAULT_MAX_CELLS,
        idle_ns: int = DEFAULT_IDLE_NS,
        max_objects: int = DEFAULT_MAX_OBJECTS,
        max_age_ns: Mapping[str, int] | None = None,
    ) -> None:
        self.formula = parse(formula) if isinstance(formula, str) else formula
        root = self.formula.root
        if not isinstance(root, Quantifier) or root.kind != "foreach":
            raise FormulaError("an ObjectMonitor monitors a foreach formula", where=f"monitor of {str(self.formula)!r}",
                               expected="foreach t in Track(field).id: ...")  # fmt: skip
        if idle_ns <= 0 or max_objects < 1:
            raise FormulaError(f"idle_ns {idle_ns}, max_objects {max_objects}", where="ObjectMonitor", expected="both positive")
        domain = root.domain
        assert isinstance(domain, Stream)
        self.var = root.var
        self.domain = domain
        inner = Formula.of(root.body)  # its states are the object's samples' too, whether the body reads them or not
        self.body = Formula(inner.text, inner.root, (domain.term, *(t for t in inner.terms if t != domain.term)))
        self.reorder_ns = int(reorder_ns)
        self.idle_ns = int(idle_ns)
        self.max_objects = int(max_objects)
        self._max_cells = int(max_cells)
        self._least_cells = MIN_STATES * max(1, self.body.nodes)  # what an instance keeps at its least
        self._slots = 0  # the instances the cells are shared among: a power of two, at least those alive
        self._max_age = dict(max_age_ns or {})
        #: the terms as the formula writes them (the quantified stream's first)
        self.terms: tuple[str, ...] = tuple(str(term) for term in self.formula.terms)
        self._index = {term: k for k, term in enumerate(self.terms)}
        self._members: Members | None = None  # a parameterized term's families, once a member is pushed by name
        self._domain_k = self._index[str(domain.term)]
        #: the position of the quantified stream in :attr:`terms`
        self.domain_index = self._domain_k
        self._latest: dict[int, tuple[int, Any]] = {}  # term -> its latest sample, to seed new instances
        # term -> its outages (open spans, as Held keeps them) that a new instance's first windows
        # may reach back into: at most MAX_OUTAGES each, none older than the body's reach
        self._outages: dict[int, list[tuple[int, int]]] = {}
        self._reach = Monitor(self.body, variables={self.var: ""}).reach_ns  # (a probe: the variable's value does not matter)
        self._live: dict[str, _Life] = {}  # object -> its instance and its latest sample's time (one lookup a sample)
        self._deadlines: list[tuple[int, str]] = []  # (last + idle, object): looked at as time goes on
        self._newest = -(2**62)
        #: samples of the quantified stream whose field names no object
        self.unassigned = 0
        #: samples of new objects refused because max_objects were alive
        self.refused = 0
        #: instances made so far (objects and their later lives)
        self.made = 0
        # samples late for their instance (see Monitor.late), over every instance so far: counted
        # as they come (summing the instances' counts costs a pass over them, per sample)
        self._late = 0
        #: states given up by the memory bound, summed over instances retired too
        self._given_up_retired = 0

    # -- input

    def push(self, term: str, t_ns: int, value: Any) -> list[tuple[str, Verdict]]:
        """Hand over one sample of ``term`` at ``t_ns``; the ``(object, verdict)`` pairs it decided."""
        k = self._index.get(term)
        if k is None:
            if self._members is None:
                self._members = Members(self.formula.terms)
            member = self._members.find(term)
            if member is not None:  # SpeedLimit(z1) of SpeedLimit(State(r).zone): its family's value then
                return self.push_index(member[0], t_ns, self._members.value(member[0], member[1], t_ns, value))
            k = self._term_index(term)
        return self.push_index(k, t_ns, value)

    def push_index(self, k: int, t_ns: int, value: Any) -> list[tuple[str, Verdict]]:
        """:meth:`push` with the term given by its position in :attr:`terms`."""
        out: list[tuple[str, Verdict]] = []
        if t_ns > self._newest:
            self._newest = t_ns
            self._retire(out)
        if k == self._domain_k:
            if type(value) is list:  # a frame (a tracker's tracks): a sample per element, all at its time
                for item in value:
                    if type(item) is list:
                        self.unassigned += 1  # (one level: a list in a frame names no object)
                    else:
                        out.extend(self.push_index(k, t_ns, item))
                return out
            self._object_sample(t_ns, value, object_key(read(value, self.domain.fields)), out)
            return out
        name = self.terms[k]
        before = self._latest.get(k)
        if before is None or t_ns >= before[0]:
            age = self._max_age.get(name)
            if age is not None and before is not None and t_ns - before[0] > age + 1:
                self._outage(k, before[0] + age, t_ns)
            self._latest[k] = (t_ns, value)
        self._others(k, name, t_ns, value, out)
        return out

    def push_object(self, t_ns: int, value: Any, key: str | None) -> list[tuple[str, Verdict]]:
        """:meth:`push_index` of one sample of the quantified stream (not a frame) whose object
        the caller read already: ``key`` is ``object_key(read(value, self.domain.fields))`` (a
        unit serving several formulas over one stream reads it once for all of them)."""
        out: list[tuple[str, Verdict]] = []
        if t_ns > self._newest:
            self._newest = t_ns
            self._retire(out)
        self._object_sample(t_ns, value, key, out)
        return out

    def _object_sample(self, t_ns: int, value: Any, key: str | None, out: list[tuple[str, Verdict]]) -> None:
        """A sample of the quantified stream, of the object ``key`` (None: it names none), to its instance."""
        k = self._domain_k
        self._latest[k] = (t_ns, value)
        if key is None:
            self.unassigned += 1  # (no instance takes it: those of the objects read the quantified stream's samples of their own)
            return
        life = self._live.get(key)
        if life is not None and t_ns - life.last_ns > self.idle_ns:
            self._end(key, out)
            life = None
        if life is None:
            if len(self._live) >= self.max_objects or len(self._live) >= self.capacity:
                self.refused += 1
                return
            monitor = self._start(key, read(value, self.domain.fields), t_ns)
            heapq.heappush(self._deadlines, (t_ns + self.idle_ns, key))  # (moved on when it comes up: _retire)
        else:
            monitor = life.monitor
            if t_ns > life.last_ns:
                life.last_ns = t_ns
        late = monitor.late
        for verdict in monitor.push_index(0, t_ns, value):  # (the body's terms start with the quantified stream)
            out.append((key, verdict))
        if monitor.late != late:
            self._late += monitor.late - late

    def _outage(self, k: int, start: int, end: int) -> None:
        """Note that term ``k`` was stale in ``(start, end)``; forget what no new instance can reach."""
        periods = self._outages.setdefault(k, [])
        periods.append((start, end))
        edge = end - self._reach - max(self._max_age.get(self.terms[k], 0), 0)
        drop = 0
        while drop < len(periods) and (periods[drop][1] < edge or len(periods) - drop > MAX_OUTAGES):
            drop += 1
        if drop:
            del periods[:drop]

    def _others(self, k: int, name: str, t_ns: int, value: Any, out: list[tuple[str, Verdict]]) -> None:
        if k == self._domain_k:
            return
        for key, life in self._live.items():
            monitor = life.monitor
            if name in monitor.terms:
                late = monitor.late
                out.extend((key, v) for v in monitor.push(name, t_ns, value))
                self._late += monitor.late - late

    def flush(self) -> list[tuple[str, Verdict]]:
        """Close every instance's buffered states (the input ended); the pairs that decided."""
        out: list[tuple[str, Verdict]] = []
        for key, life in self._live.items():
            out.extend((key, v) for v in life.monitor.flush())
        return out

    def close(self) -> list[tuple[str, Verdict]]:
        """:meth:`flush`, then retire every instance; safe twice."""
        out = self.flush()
        for key in list(self._live):
            self._end(key, out)
        return out

    def widen(self, reorder_ns: int) -> None:
        """Raise the reorder delay of every instance, and of those to come, to ``reorder_ns``
        (:meth:`~dyknow.reasoning.Monitor.widen`)."""
        if reorder_ns > self.reorder_ns:
            self.reorder_ns = int(reorder_ns)
            for life in self._live.values():
                life.monitor.widen(self.reorder_ns)

    def discard(self) -> None:
        """Let go of every instance and what it keeps (states, object ids, the latest samples)
        at once, deciding nothing: the monitor is going, and its memory is free from now on
        whoever still holds the monitor. It starts anew if pushed to again."""
        self._given_up_retired += sum(life.monitor.given_up for life in self._live.values())
        self._live = {}
        self._deadlines = []
        self._latest = {}
        self._outages = {}
        self._slots = 0

    # -- instances

    def _start(self, key: str, value: Any, t_ns: int) -> Monitor:
        cells = max(1, self._max_cells // self._slots_for(len(self._live) + 1))
        monitor = Monitor(self.body, reorder_ns=self.reorder_ns, max_cells=cells, variables={self.var: value})
        for term, age in self._max_age.items():
            if term in monitor.terms:
                monitor.set_max_age(term, age)
        for k, periods in self._outages.items():  # before the seeded samples: the outages they ended
            name = self.terms[k]
            if name in monitor.terms:
                for start, end in periods:
                    monitor.outage(name, start, end)
        if len(self._latest) > 1:  # (the quantified stream's own is always there, and not pushed)
            for k, (t, held) in sorted(self._latest.items(), key=lambda item: item[1][0]):
                name = self.terms[k]
                if k != self._domain_k and name in monitor.terms:
                    monitor.push(name, t, held)  # (before the object's first sample: no state yet)
        self._live[key] = _Life(monitor, t_ns)
        self.made += 1
        self._reshare()
        return monitor

    def _end(self, key: str, out: list[tuple[str, Verdict]]) -> None:
        monitor = self._live.pop(key).monitor
        out.extend((key, v) for v in monitor.close())
        self._given_up_retired += monitor.given_up
        self._reshare()

    def _retire(self, out: list[tuple[str, Verdict]]) -> None:
        """End the instances whose object has been silent longer than ``idle_ns`` (less the reorder delay)."""
        now = self._newest - self.reorder_ns
        deadlines = self._deadlines
        while deadlines and deadlines[0][0] < now:
            _deadline, key = heapq.heappop(deadlines)
            life = self._live.get(key)
            if life is None:
                continue  # (that life ended)
            due = life.last_ns + self.idle_ns
            if due < now:
                self._end(key, out)
            else:  # a later sample moved it on: one entry per object, not one per sample
                heapq.heappush(deadlines, (due, key))

    def _slots_for(self, live: int) -> int:
        slots = self._slots or 1
        while live > slots:
            slots *= 2
        while slots > 1 and live <= slots // 4:
            slots //= 2
        return slots

    def _reshare(self, again: bool = False) -> None:
        if not self._live:
            return
        slots = self._slots_for(len(self._live))
        if slots == self._slots and not again:
            return  # (every instance's share is still max_cells // slots)
        self._slots = slots
        cells = max(1, self._max_cells // slots)
        for life in self._live.values():
            life.monitor.set_max_cells(cells)

    def set_max_age(self, term: str, max_age_ns: int | None) -> None:
        """Every instance's (and every later one's) maximum age of ``term`` (see :meth:`Monitor.set_max_age`)."""
        k = self._index.get(term)
        if k is None:
            k = self._term_index(term)
        name = self.terms[k]
        if max_age_ns is None:
            self._max_age.pop(name, None)
        else:
            self._max_age[name] = int(max_age_ns)
        for life in self._live.values():
            if name in life.monitor.terms:
                life.monitor.set_max_age(name, max_age_ns)

    def set_max_cells(self, max_cells: int) -> None:
        """Keep at most ``max_cells`` cells in all from now on, shared among the instances
        (fewer cells take no instance away: they bound the new ones, :attr:`capacity`)."""
        self._max_cells = max(1, int(max_cells))
        self._reshare(again=True)

    @property
    def capacity(self) -> int:
        """The most instances ``max_cells`` can hold at their least (each keeps at least
        :data:`~dyknow.reasoning.progression.MIN_STATES` states of the body's nodes), at least 1:
        no new object is taken past it (nor past ``max_objects``)."""
        return max(1, self._max_cells // self._least_cells)

    def _term_index(self, term: str) -> int:
        try:
            k = self._index.get(str(parse_term(term)))
        except TagError:
            k = None
        if k is None:
            raise FormulaError(
                f"the formula does not mention the term {term!r}",
                where=f"monitor of {str(self.formula)!r}",
                expected="one of " + ", ".join(repr(t) for t in self.terms) + did_you_mean(term, self.terms),
            )
        self._index[term] = k
        return k

    # -- introspection

    @property
    def objects(self) -> list[str]:
        """The objects alive now."""
        return list(self._live)

    def instance(self, key: str) -> Monitor:
        """The monitor of object ``key`` (one of :attr:`objects`); KeyError when it has none alive."""
        return self._live[key].monitor

    @property
    def late(self) -> int:
        """Samples late for their instance (see :attr:`Monitor.late`), over every instance so far."""
        return self._late

    @property
    def given_up(self) -> int:
        """States the memory bound gave up, over every instance so far."""
        return self._given_up_retired + sum(life.monitor.given_up for life in self._live.values())

    @property
    def states(self) -> int:
        """States closed by the instances alive."""
        return sum(life.monitor.states for life in self._live.values())

    def retained(self) -> int:
        """States (and buffered samples) the instances alive keep."""
        return sum(life.monitor.retained() for life in self._live.values())


class _Life:
    """An object's instance and the time of its latest sample (of the quantified stream)."""

    def __init__(self, monitor: Monitor, last_ns: int) -> None:
        self.monitor = monitor
        self.last_ns = last_ns
