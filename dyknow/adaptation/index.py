"""Part of the K of MAPE-K: :class:`RunningIndex`, what runs on the manager, indexed so that planning
a request costs the same with 100 units running as with 10,000.

Planning needs, of the running units, only those whose outputs could serve the request (their
tags' functor and arguments), the producers and readers of a few keys, and whether a name is
taken. Building that from a snapshot of every unit for each request made the 10,000th spawn of a
monitor cost 50 times the 100th (every request walked every unit several times). The index is
kept up to date from the runtime's log of changed units (:meth:`Runtime.unit_changes
<dyknow.adaptation.runtime.Runtime.unit_changes>`): each refresh reads only the units that changed
since the last one (all of them, once, when the log no longer reaches back that far).
"""

from __future__ import annotations

from collections.abc import Collection, Iterator, Mapping
from typing import TypeVar

from dyknow.adaptation.runtime import Runtime
from dyknow.errors import DyKnowError
from dyknow.model import UnitInfo
from dyknow.tags import local_name, parse_term

__all__ = ["RunningIndex", "TagKey", "tag_key"]

K = TypeVar("K")

TagKey = tuple[str, tuple[str, ...]]
"""A tag as the index files it: the local names of its functor and of its arguments."""


def tag_key(tag: str) -> TagKey | None:
    """The :data:`TagKey` of ``tag`` (None when it does not parse: it then matches nothing)."""
    try:
        term = parse_term(tag)
    except DyKnowError:
        return None
    return local_name(term.functor), tuple(local_name(a) for a in term.args)


class RunningIndex:
    """The runtime's units by name, by the tags of their outputs, and by the keys they read and write."""

    def __init__(self, runtime: Runtime) -> None:
        self._runtime = runtime
        self._version = -1
        self._units: dict[str, UnitInfo] = {}
        self._by_tag: dict[TagKey, set[str]] = {}
        self._producers: dict[str, set[str]] = {}  # output key -> units
        self._readers: dict[str, set[str]] = {}  # input key -> units

    def refresh(self) -> None:
        """Read the units that changed since the last refresh (every unit, the first time)."""
        version, changed = self._runtime.unit_changes(self._version)
        if changed is None:
            for name in list(self._units):
                self._forget(name)
            for info in self._runtime.units():
                self._file(info)
        else:
            for name in changed:
                self._forget(name)
                found = self._runtime.unit_info(name)
                if found is not None:
                    self._file(found)
        self._version = version

    def _file(self, info: UnitInfo) -> None:
        self._units[info.name] = info
        spec = info.spec
        if spec is None:
            return
        for port in spec.outputs:
            self._producers.setdefault(info.bindings.get(port.name, ""), set()).add(info.name)
            for tag in spec.tags_for(port.name):
                key = tag_key(tag)
                if key is not None:
                    self._by_tag.setdefault(key, set()).add(info.name)
        for port in spec.inputs:
            self._readers.setdefault(info.bindings.get(port.name, ""), set()).add(info.name)

    def _forget(self, name: str) -> None:
        info = self._units.pop(name, None)
        if info is None or info.spec is None:
            return
        for port in info.spec.outputs:
            _discard(self._producers, info.bindings.get(port.name, ""), name)
            for tag in info.spec.tags_for(port.name):
                key = tag_key(tag)
                if key is not None:
                    _discard(self._by_tag, key, name)
        for port in info.spec.inputs:
            _discard(self._readers, info.bindings.get(port.name, ""), name)

    @property
    def units(self) -> Mapping[str, UnitInfo]:
        """Every unit by name (as of the last refresh)."""
        return self._units

    def __len__(self) -> int:
        return len(self._units)

    def serving(self, keys: Collection[TagKey]) -> list[UnitInfo]:
        """The units with an output tag of one of ``keys``, by name."""
        names: set[str] = set()
        for key in keys:
            names |= self._by_tag.get(key, set())
        return [self._units[name] for name in sorted(names)]

    def producers(self, key: str) -> Iterator[UnitInfo]:
        """The units with an output bound to ``key``."""
        for name in sorted(self._producers.get(key, ())):
            yield self._units[name]

    def readers(self, key: str) -> Iterator[UnitInfo]:
        """The units with an input bound to ``key``."""
        for name in sorted(self._readers.get(key, ())):
            yield self._units[name]


def _discard(index: dict[K, set[str]], key: K, name: str) -> None:
    found = index.get(key)
    if found is not None:
        found.discard(name)
        if not found:
            del index[key]
