"""The local bus: routes messages between the ports of one manager without going through Zenoh.

Each output port keeps ``targets``, the tuple of local input ports whose key expression intersects
its key. Publishing walks that tuple, so the hot path takes no lock; the bus recomputes the tuples
under its lock whenever a port appears, disappears or is rebound, and swaps them in one assignment
each. Zenoh still carries the same streams to and from other sessions (see ``proxy``), with
locality options that keep it out of the local path, so no message arrives twice.

Ports are indexed by key: attaching, detaching or rebinding a port with a concrete key costs the
same with ten units or ten thousand (only wildcard keys are compared with every port of the other
direction, and they are rare).

Forwarding units (``forward_to``) pass every message on, so forwarding units bound into a cycle
(``a.in = x/b, a.out = x/a, b.in = x/a, b.out = x/b``, or one relay reading ``dyknow/**``,
which holds its own output) would circle one message forever. The bus refuses any attach or
rebind that closes such a cycle, naming its ports (:meth:`LocalBus.forwarding_cycle` tells
beforehand). A cycle through units that run Python is left alone: a feedback loop may be meant,
and such a unit decides itself whether to publish.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Protocol

from dyknow.errors import BindingError
from dyknow.transport import is_wild, key_exprs_intersect

__all__ = ["LocalBus", "cycle_error", "describe_cycle"]


class _In(Protocol):
    key: str
    name: str
    job: Any  # the unit's job (dyknow.proxy.job: its name names the unit in errors)
    forward: Any  # the output it forwards to (forward_to), or None


class _Out(Protocol):
    key: str
    name: str
    targets: tuple[Any, ...]  # the input ports it delivers to


class _Index:
    """Ports of one direction by key: a dict per concrete key, and the wildcard ones apart."""

    def __init__(self) -> None:
        self.all: dict[int, Any] = {}  # id(port) -> port, in attach order
        self.exact: dict[str, dict[int, Any]] = {}
        self.wild: dict[int, Any] = {}

    def add(self, port: Any) -> None:
        self.all[id(port)] = port
        if is_wild(port.key):
            self.wild[id(port)] = port
        else:
            self.exact.setdefault(port.key, {})[id(port)] = port

    def remove(self, port: Any) -> None:
        if self.all.pop(id(port), None) is None:
            return
        if self.wild.pop(id(port), None) is None:
            same = self.exact.get(port.key)
            if same is not None:
                same.pop(id(port), None)
                if not same:
                    del self.exact[port.key]

    def reaching(self, key: str) -> list[Any]:
        """The ports whose key intersects ``key``."""
        if is_wild(key):
            return [p for p in self.all.values() if key_exprs_intersect(p.key, key)]
        found = list(self.exact.get(key, {}).values())
        found += [p for p in self.wild.values() if key_exprs_intersect(p.key, key)]
        return found


class LocalBus:
    """The input and output ports of one manager, and who delivers to whom."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._inputs = _Index()
        self._outputs = _Index()
        self._order: dict[int, int] = {}  # id(input) -> when it was attached (targets keep that order)
        self._next = itertools.count()

    def attach(self, inputs: Iterable[_In], outputs: Iterable[_Out]) -> None:
        """Add a unit's ports and route them; :class:`BindingError` (and nothing added) when its
        inputs would close a cycle of forwarding units."""
        inputs, outputs = tuple(inputs), tuple(outputs)
        with self._lock:
            cycle = self._cycle(inputs, {}, inputs)
            if cycle:
                raise cycle_error(cycle)
            for inp in inputs:
                self._order[id(inp)] = next(self._next)
                self._inputs.add(inp)
                for out in self._outputs.reaching(inp.key):
                    out.targets = out.targets + (inp,)  # one assignment: publishers see old or new
            for out in outputs:
                self._outputs.add(out)
                out.targets = self._targets_of(out)

    def detach(self, inputs: Iterable[_In], outputs: Iterable[_Out]) -> None:
        """Remove a unit's ports; nothing is delivered to them afterwards."""
        with self._lock:
            for inp in inputs:
                if id(inp) not in self._inputs.all:
                    continue
                self._inputs.remove(inp)
                del self._order[id(inp)]
                for out in self._outputs.reaching(inp.key):
                    if any(t is inp for t in out.targets):
                        out.targets = tuple(t for t in out.targets if t is not inp)
            for out in outputs:
                self._outputs.remove(out)
                out.targets = ()

    def rebind(self, changes: Sequence[tuple[_In | _Out, str]]) -> None:
        """Give ports new keys, all at once: no message sees a half-applied change.
        :class:`BindingError` (and nothing changed) when the new keys would close a cycle of
        forwarding units."""
        with self._lock:
            cycle = self._rebind_cycle(changes)
            if cycle:
                raise cycle_error(cycle, {id(port): key for port, key in changes})
            moved_in = [p for p, _ in changes if id(p) in self._inputs.all]
            moved_out: list[Any] = [p for p, _ in changes if id(p) in self._outputs.all]
            affected: dict[int, Any] = {}  # outputs whose targets may change
            for inp in moved_in:
                affected.update((id(o), o) for o in self._outputs.reaching(inp.key))
            for port, key in changes:
                index = self._inputs if id(port) in self._inputs.all else self._outputs if id(port) in self._outputs.all else None
                if index is not None:
                    index.remove(port)
                port.key = key
                if index is not None:
                    index.add(port)
            for inp in moved_in:
                affected.update((id(o), o) for o in self._outputs.reaching(inp.key))
            moved_ids = {id(p) for p in moved_in}
            for out in moved_out:
                affected.pop(id(out), None)
                out.targets = self._targets_of(out)
            for out in affected.values():
                kept = tuple(t for t in out.targets if id(t) not in moved_ids)
                extra = tuple(p for p in moved_in if key_exprs_intersect(p.key, out.key))
                if kept + extra != out.targets:
                    out.targets = kept + extra  # one assignment: publishers see old or new

    def forwarding_cycle(
        self, *, inputs: Iterable[_In] = (), changes: Sequence[tuple[_In | _Out, str]] = ()
    ) -> list[tuple[_In, _Out]] | None:
        """The cycle of forwarding units that attaching ``inputs`` (a new unit's, its outputs
        already attached or given as the inputs' ``forward``) or applying ``changes`` (as
        :meth:`rebind` takes them) would close, as (input, the output it forwards to) pairs in
        the order a message would go round; None when there is none. Nothing changes."""
        with self._lock:
            if changes:
                return self._rebind_cycle(changes)
            new = tuple(inputs)
            return self._cycle(new, {}, new)

    def _rebind_cycle(self, changes: Sequence[tuple[_In | _Out, str]]) -> list[tuple[_In, _Out]] | None:
        keys = {id(port): key for port, key in changes}
        moved_in: list[Any] = [p for p, _ in changes if id(p) in self._inputs.all]
        moved_out = {id(p) for p, _ in changes if id(p) in self._outputs.all}
        # a new cycle goes through a moved input, or through an input forwarding to a moved output
        starts: list[Any] = [p for p in moved_in if p.forward is not None]
        if moved_out:
            starts += [p for p in self._inputs.all.values() if p.forward is not None and id(p.forward) in moved_out and id(p) not in keys]
        return self._cycle(starts, keys, moved_in)

    def _cycle(self, starts: Sequence[_In], keys: dict[int, str], extra: Sequence[_In]) -> list[tuple[_In, _Out]] | None:
        """Depth-first from each forwarding input of ``starts`` along forward -> its readers,
        with ``keys`` overriding ports' keys and the ``extra`` inputs (not indexed yet, or
        indexed under their old key) read at their key in ``keys`` or their own."""
        skip = {id(p) for p in extra}

        def readers(out: Any) -> list[Any]:
            key = keys.get(id(out), out.key)
            found = [p for p in self._inputs.reaching(key) if id(p) not in skip]
            found += [p for p in extra if key_exprs_intersect(keys.get(id(p), p.key), key)]
            return [p for p in found if p.forward is not None]

        for start in starts:
            if start.forward is None:
                continue
            # iterative: a chain of forwarding units may be longer than Python's recursion limit
            path: list[tuple[Any, Any]] = [(start, start.forward)]
            pending: list[list[Any]] = [readers(start.forward)]
            seen = {id(start)}
            while pending:
                if not pending[-1]:
                    pending.pop()
                    path.pop()
                    continue
                nxt = pending[-1].pop()
                if nxt is start:
                    return path
                if id(nxt) in seen:
                    continue
                seen.add(id(nxt))
                path.append((nxt, nxt.forward))
                pending.append(readers(nxt.forward))
        return None

    def _targets_of(self, out: _Out) -> tuple[Any, ...]:
        order = self._order
        return tuple(sorted(self._inputs.reaching(out.key), key=lambda p: order[id(p)]))

    def __len__(self) -> int:
        """How many ports are attached (inputs and outputs)."""
        return len(self._inputs.all) + len(self._outputs.all)


def describe_cycle(cycle: Sequence[tuple[Any, Any]], keys: Mapping[int, str] | None = None) -> str:
    """``a.in (x/b) -> a.out (x/a) -> b.in (x/a) -> b.out (x/b) -> a.in``: who forwards to whom."""
    keys = keys or {}

    def shown(port: Any) -> str:
        return f"{getattr(port.job, 'name', '?')}.{port.name}"

    steps = []
    for inp, out in cycle:
        unit = getattr(inp.job, "name", "?")
        steps.append(f"{unit}.{inp.name} ({keys.get(id(inp), inp.key)}) -> {unit}.{out.name} ({keys.get(id(out), out.key)})")
    return " -> ".join(steps) + f" -> {shown(cycle[0][0])}"


def cycle_error(cycle: Sequence[tuple[Any, Any]], keys: Mapping[int, str] | None = None) -> BindingError:
    """The error refusing bindings that close ``cycle`` (``keys``: ports' new keys, by id)."""
    return BindingError(
        f"these bindings close a cycle of forwarding units, which would pass one message round forever: {describe_cycle(cycle, keys)}",
        where=f"unit {getattr(cycle[0][0].job, 'name', '?')!r}",
        expected="bindings under which no forwarding unit reads, directly or through others, what it forwards itself",
    )
