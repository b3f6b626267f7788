"""The local bus: routes messages between the ports of one manager without going through Zenoh.

Each output port keeps ``targets``, the tuple of local input ports whose key expression intersects
its key. Publishing walks that tuple, so the hot path takes no lock; the bus recomputes the tuples
under its lock whenever a port appears, disappears or is rebound, and swaps them in one assignment
each. Zenoh still carries the same streams to and from other sessions (see ``proxy``), with
locality options that keep it out of the local path, so no message arrives twice.

Ports are indexed by key: attaching, detaching or rebinding a port with a concrete key costs the
same with ten units or ten thousand (only wildcard keys are compared with every port of the other
direction, and they are rare).
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterable, Sequence
from typing import Any, Protocol

from dyknow.transport import is_wild, key_exprs_intersect

__all__ = ["LocalBus"]


class _In(Protocol):
    key: str


class _Out(Protocol):
    key: str
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
        """Add a unit's ports and route them."""
        with self._lock:
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
        """Give ports new keys, all at once: no message sees a half-applied change."""
        with self._lock:
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

    def _targets_of(self, out: _Out) -> tuple[Any, ...]:
        order = self._order
        return tuple(sorted(self._inputs.reaching(out.key), key=lambda p: order[id(p)]))

    def __len__(self) -> int:
        """How many ports are attached (inputs and outputs)."""
        return len(self._inputs.all) + len(self._outputs.all)
