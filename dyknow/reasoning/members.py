"""Parameterized terms, live: a monitor plans a member the first time its argument is seen.

A monitor of ``Speed(r1) < SpeedLimit(State(r1).zone)`` has one input port for the family
``SpeedLimit(*)`` (:mod:`dyknow.reasoning.families`). Its unit (:class:`LiveFamilies`) computes
the argument, ``State(r1).zone``, from each new sample of the streams it reads; a value not seen
before that names a member (a string that is a name: ``z2``) is handed to its manager's
:class:`~dyknow.reasoning.monitors.Monitors`, which requests the member ``SpeedLimit(z2)`` as any
term is requested (planned by meaning, kept flowing by the adaptation loop) and spawns a
:class:`MemberRelay` from the member's key to the family's: it hands each sample on as
``{"arg": "z2", "value": ...}`` at its own sample time, and the monitor's unit makes the family's
value of it. A member bound to what exists (``--bind 'SpeedLimit(z1)=limits/z1'``) is relayed
from the start, never requested.

So a member's samples count from when it is planned: the state at which the robot first enters
a zone reads that zone's limit as unknown until its first sample comes (a limit published once
and held, as a latched topic is, comes at once). Recorded, the members' keys give the same
verdicts offline (:func:`~dyknow.reasoning.semantics.evaluate` assembles the family from them).
At most :data:`~dyknow.reasoning.families.MAX_MEMBERS` members a family: past that, and for a
member that cannot be planned, the monitor warns once (``{"warning": ...}`` on ``verdicts``, in
its model) and the term is unknown there.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from dyknow.clocks import CLOCKS
from dyknow.message import CLOCK_ID
from dyknow.reasoning.bindings import sample_value
from dyknow.reasoning.families import MAX_MEMBERS, Family
from dyknow.reasoning.quantify import replace_var
from dyknow.reasoning.semantics import evaluate_values_ns
from dyknow.reasoning.syntax import Formula, Index, Quantifier, Stream, walk
from dyknow.reasoning.tree import is_family
from dyknow.spec import Param, Port, TransformationSpec
from dyknow.tags import NAME
from dyknow.unit import Unit

if TYPE_CHECKING:
    from dyknow.message import Message

__all__ = ["RELAY_SPEC", "LiveFamilies", "MemberRelay"]


class MemberRelay(Unit):
    """Hands a member's samples (input ``in``) on to its monitor's family port (output ``out``):
    ``{"arg": ARG, "value": payload}`` at the sample's own time, on this host's clock. Params:
    ``arg`` (the member's argument), ``textual`` (a bound member's text samples are read as
    JSON values, as a bound term's are)."""

    def setup(self) -> None:
        """Read the params."""
        self._arg = str(self.params["arg"])
        self._textual = bool(self.params.get("textual", False))

    def on_message(self, port: str, msg: Message) -> None:
        """Wrap the sample and publish it at its time (another host's clock's offset taken off)."""
        t_ns = msg.origin_ns
        if msg.origin_clock != CLOCK_ID:
            offset = CLOCKS.current.get(msg.origin_clock)
            if offset is not None:
                t_ns -= offset
        value = sample_value(msg.payload) if self._textual else msg.payload
        self.publish("out", {"arg": self._arg, "value": value}, origin_ns=t_ns)


RELAY_SPEC = TransformationSpec(
    "member-relay",
    "dyknow.reasoning.members:MemberRelay",
    (Param("arg", "string", ""), Param("textual", "bool", False)),
    (Port("in", "in", queue=256), Port("out", "out")),
    description="hands a parameterized term's member on to its monitor",
)
"""The spec of :class:`MemberRelay`."""


class LiveFamilies:
    """What a monitor unit does for the parameterized terms of its ``formulas`` (its ports are
    ``terms``, in order): the family ports' values (:meth:`value`) and the arguments seen
    (:meth:`observe`), each new one handed to the watcher (:meth:`watch`)."""

    def __init__(self, formulas: Sequence[Formula], terms: Sequence[str]) -> None:
        #: the family ports: position -> its value, assembled
        self.ports: dict[int, Family] = {}
        self._arguments: list[tuple[str, Formula, list[int]]] = []  # (family, its argument, the ports it reads)
        #: the ports an argument reads -> which arguments
        self.reads: dict[int, list[int]] = {}
        for formula in formulas:
            for term in formula.terms:
                if is_family(term):
                    self.ports.setdefault(terms.index(str(term)), Family(term))
            root = formula.root
            for node in walk(root):
                if isinstance(node, Index) and node.param >= 0:
                    argument = Formula.of(node.keys[0])
                    if isinstance(root, Quantifier) and root.kind == "foreach" and isinstance(root.domain, Stream):
                        # the object's value: its stream's field, read from each of its samples
                        argument = Formula.of(replace_var(node.keys[0], root.var, root.domain))
                    if any(text == str(node.stream.term) and str(a) == str(argument) for text, a, _ in self._arguments):
                        continue
                    ports = [terms.index(str(t)) for t in argument.terms]
                    for k in ports:
                        self.reads.setdefault(k, []).append(len(self._arguments))
                    self._arguments.append((str(node.stream.term), argument, ports))
        self._latest: dict[int, Any] = {}
        #: each family's arguments seen (their members planned, or being planned), by family
        self.seen: dict[str, set[str]] = {str(f.family): set() for f in self.ports.values()}
        self._lock = threading.Lock()  # (the watcher is set from the manager's thread)
        self._watcher: Callable[[str, str], None] | None = None
        self._waiting: list[tuple[str, str]] = []
        #: the families that reached :data:`~dyknow.reasoning.families.MAX_MEMBERS` (warned once)
        self.full: list[str] = []

    def value(self, k: int, t_ns: int, payload: Any) -> Any:
        """The value of the family on port ``k`` at ``t_ns``, given a relay's sample; None when
        the sample is no relay's (``{"arg": NAME, "value": ...}``)."""
        if type(payload) is not dict or type(payload.get("arg")) is not str:
            return None
        return self.ports[k].push(payload["arg"], t_ns, payload.get("value"))

    def observe(self, k: int, payload: Any) -> None:
        """A sample on port ``k``, which an argument reads: compute the arguments it may change
        and hand on each new value that names a member."""
        items = payload if type(payload) is list else [payload]  # (a foreach stream's frame: each element)
        for item in items:
            self._latest[k] = item
            for a in self.reads[k]:
                family, argument, ports = self._arguments[a]
                if any(p not in self._latest for p in ports):
                    continue
                found = evaluate_values_ns(argument, {str(t): [(0, self._latest[p])] for t, p in zip(argument.terms, ports, strict=True)})
                arg = found[0][1] if found else None
                seen = self.seen[family]
                if type(arg) is not str or arg in seen or not NAME.fullmatch(arg):
                    continue
                if len(seen) >= MAX_MEMBERS:
                    if family not in self.full:
                        self.full.append(family)
                    continue
                seen.add(arg)
                with self._lock:
                    watcher = self._watcher
                    if watcher is None:
                        self._waiting.append((family, arg))
                if watcher is not None:
                    watcher(family, arg)

    def watch(self, watcher: Callable[[str, str], None]) -> None:
        """Call ``watcher(family, arg)`` for each new argument (those seen before it, at once), on
        the unit's thread (it must return at once)."""
        with self._lock:
            self._watcher = watcher
            waiting, self._waiting = self._waiting, []
        for family, arg in waiting:
            watcher(family, arg)
