"""The local bus: routes messages between the ports of one manager without going through Zenoh.

Each output port keeps ``targets``, the tuple of local input ports whose key expression intersects
its key. Publishing walks that tuple, so the hot path takes no lock; the bus recomputes the tuples
under its lock whenever a port appears, disappears or is rebound, and swaps them in one assignment
each. Zenoh still carries the same streams to and from other sessions (see ``proxy``), with
locality options that keep it out of the local path, so no message arrives twice.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Sequence
from typing import Any, Protocol

from dyknow.transport import key_exprs_intersect

__all__ = ["LocalBus"]


class _In(Protocol):
    key: str


class _Out(Protocol):
    key: str
    targets: tuple[Any, ...]  # the input ports it delivers to


class LocalBus:
    """The input and output ports of one manager, and who delivers to whom."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._inputs: list[_In] = []
        self._outputs: list[_Out] = []

    def attach(self, inputs: Iterable[_In], outputs: Iterable[_Out]) -> None:
        """Add a unit's ports and route them."""
        new_in, new_out = list(inputs), list(outputs)
        with self._lock:
            for out in self._outputs:
                self._add_targets(out, new_in)
            self._inputs.extend(new_in)
            self._outputs.extend(new_out)
            for out in new_out:
                out.targets = ()
                self._add_targets(out, self._inputs)

    def detach(self, inputs: Iterable[_In], outputs: Iterable[_Out]) -> None:
        """Remove a unit's ports; nothing is delivered to them afterwards."""
        gone_in = {id(p) for p in inputs}
        gone_out = list(outputs)
        with self._lock:
            self._inputs = [p for p in self._inputs if id(p) not in gone_in]
            self._outputs = [p for p in self._outputs if all(p is not o for o in gone_out)]
            for out in self._outputs:
                self._drop_targets(out, gone_in)
            for out in gone_out:
                out.targets = ()

    def rebind(self, changes: Sequence[tuple[_In | _Out, str]]) -> None:
        """Give ports new keys, all at once: no message sees a half-applied change."""
        with self._lock:
            input_ids = {id(p) for p in self._inputs}
            moved_in = [p for p, _ in changes if id(p) in input_ids]
            moved_out = [p for p, _ in changes if id(p) not in input_ids]
            for port, key in changes:
                port.key = key
            moved_ids = {id(p) for p in moved_in}
            for out in self._outputs:
                if any(out is o for o in moved_out):
                    out.targets = ()
                    self._add_targets(out, self._inputs)
                elif moved_ids:
                    kept = tuple(t for t in out.targets if id(t) not in moved_ids)
                    extra = tuple(p for p in moved_in if key_exprs_intersect(p.key, out.key))
                    if kept + extra != out.targets:
                        out.targets = kept + extra  # one assignment: publishers see old or new

    @staticmethod
    def _add_targets(out: _Out, inputs: Iterable[_In]) -> None:
        extra = tuple(p for p in inputs if key_exprs_intersect(p.key, out.key))
        if extra:
            out.targets = out.targets + extra  # one assignment: publishers see old or new

    @staticmethod
    def _drop_targets(out: _Out, ids: set[int]) -> None:
        if any(id(t) in ids for t in out.targets):
            out.targets = tuple(t for t in out.targets if id(t) not in ids)
