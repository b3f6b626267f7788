"""The monitor's node kinds decided at their state: values, atoms and the boolean connectives.

A formula becomes a tree of nodes, stepped bottom-up at each state (see
:mod:`dyknow.reasoning.progression`). Here are their bases (:class:`Step`, :class:`Condition`,
:class:`Value`), the values (streams, constants, arithmetic, calls), the atoms, ``prev``,
``rise``, ``fall``, ``not``, ``and``, ``or`` and ``implies``; the aggregates
(:mod:`~dyknow.reasoning.aggregates`) and the temporal operators
(:mod:`~dyknow.reasoning.past`, :mod:`~dyknow.reasoning.future`) are nodes on these bases.
"""

from __future__ import annotations

from typing import Any, Final

from dyknow.reasoning.robustness import RobustnessTree
from dyknow.reasoning.timeline import NEVER, Clock, Held
from dyknow.reasoning.values import (
    FALSE,
    TRUE,
    UNKNOWN,
    UNKNOWN_VALUE,
    arith,
    as_value,
    call,
    compare,
    lookup,
    read,
    read_raw,
    scalar,
    truth,
)

__all__ = [
    "AND",
    "IMPLIES",
    "OR",
    "ArithValue",
    "AtomNode",
    "BinaryNode",
    "CallValue",
    "Condition",
    "ConstNode",
    "ConstValue",
    "EdgeNode",
    "IndexValue",
    "NotNode",
    "PrevNode",
    "PrevValue",
    "RawStreamValue",
    "RobustnessValue",
    "Step",
    "StreamValue",
    "Value",
    "VerdictValue",
]

# (Final: compiled, a plain module global is a dictionary lookup at every use)
AND: Final = 0  # the kinds of a BinaryNode
OR: Final = 1
IMPLIES: Final = 2
_OPS: Final = ("<", ">", "<=", ">=", "==", "!=")  # an atom's comparison, by its code


class Step:
    """What a state steps through: a condition's node or a value's (one base, so the monitor's
    loop over them dispatches with one type check, compiled)."""

    max_states: int  # how many states' entries it may keep (the monitor sets it)
    # the next in the order a state steps through (the monitor links them): compiled, walking
    # these costs nothing per node, where taking each from a list[Step] checks its type
    # (a walk of the class's bases, its class being a subclass)
    next_step: Step | None = None

    def step(self, n: int, t: int, held: list[Any]) -> None:
        """Evaluate the new state ``n`` at ``t`` (operands have stepped already)."""
        raise NotImplementedError


class Condition(Step):
    """A condition's node of the monitored formula: its verdict at the newest state (``cur``), at every
    retained state when the formula has asynchronous nodes (``vals``: ``history``), and for an
    asynchronous node the states it decided during the current step (``events``)."""

    def __init__(self, clock: Clock, sync: bool, need_ns: int) -> None:
        self.clock = clock
        self.cur = UNKNOWN
        self.vals: list[int] = []
        self.history = not sync  # a synchronous node keeps its verdicts only if some node reads them later
        # the states decided during the current step are the first ``nev`` of ``events`` (boxed:
        # the clock's ``idx`` objects); the list is kept from step to step, its entries written
        # over (compiled, a new list per step cost an allocation and a reallocation on its first append)
        self.events: list[Any] = []
        self.nev = 0
        self.sync = sync
        self.need_ns = need_ns  # how far back from the newest state this node reads
        self.max_states = 1 << 62  # how many states' entries it may keep (the monitor sets it)
        self.held: Held | None = None  # a window's: the staleness of the terms below it
        self.below: list[int] = []
        self.first_t = NEVER  # the first state's time (where an unbounded past window starts)

    def step(self, n: int, t: int, held: list[Any]) -> None:
        """Evaluate the new state ``n`` at ``t`` (children have stepped already)."""
        raise NotImplementedError

    def event(self, i: Any) -> None:
        """State ``i`` (an int: its ``clock.idx`` object) was decided during this step."""
        c = self.nev
        events = self.events
        if c < len(events):
            events[c] = i
        else:
            events.append(i)
        self.nev = c + 1

    def prune(self, base: int) -> None:
        """States before ``base`` were dropped from ``vals``' front; drop what refers to them."""


class Value(Step):
    """A node that gives a value at each state (a stream's, a constant, an expression, an
    aggregate): always decided at its state, so it keeps no history."""

    def __init__(self) -> None:
        self.val: Any = UNKNOWN_VALUE
        self.max_states = 1 << 62
        self.given_up = 0

    def step(self, n: int, t: int, held: list[Any]) -> None:
        """Compute the value at the new state ``n`` at ``t`` (operands have stepped already)."""
        raise NotImplementedError


def _finite_float(x: Any) -> bool:
    """Whether ``x`` is a finite float (a function of its own: compiled, a caller that tested it
    inline would hold ``x`` as a C double and box a new float to store it)."""
    return type(x) is float and x - x == 0.0


class StreamValue(Value):
    """A term's value (or a field of it) at the state: unknown while the term is stale."""

    def __init__(self, k: int, fields: tuple[str, ...], held: Held) -> None:
        super().__init__()
        self.k = k
        self.fields = fields
        self.held = held

    def stale(self, t: int) -> bool:
        """Whether the term is stale at ``t`` (more than its maximum age after its latest sample)."""
        age = self.held.max_age[self.k]
        return age >= 0 and t - self.held.times[self.k] > age

    def step(self, n: int, t: int, held: list[Any]) -> None:
        if self.held.aged and self.stale(t):
            self.val = UNKNOWN_VALUE
            return
        value = held[self.k]
        if not self.fields and _finite_float(value):
            self.val = value  # the common case, without a call (nor, compiled, a new float object)
        else:
            self.val = read(value, self.fields)


class RawStreamValue(StreamValue):
    """A term's payload (or a field of it) as it is, objects and arrays too: what a lookup looks
    into and what ``dist`` measures; unknown while the term is stale."""

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.val = UNKNOWN_VALUE if self.held.aged and self.stale(t) else read_raw(held[self.k], self.fields)


class IndexValue(Value):
    """A lookup, ``stream[key]...``: down ``keys`` from the raw value of ``base``; a value of the
    semantics (a number, string or boolean, else unknown), or as it is when ``raw`` (the point of
    a ``dist``)."""

    def __init__(self, base: Value, keys: list[Value], raw: bool) -> None:
        super().__init__()
        self.base = base
        self.keys = keys
        self.raw = raw

    def step(self, n: int, t: int, held: list[Any]) -> None:
        value = self.base.val
        for key in self.keys:
            value = lookup(value, key.val)
        self.val = value if self.raw else scalar(value)


class ConstValue(Value):
    """A constant: a number or a string written in the formula, or a variable's value."""

    def __init__(self, value: Any) -> None:
        super().__init__()
        self.val = value

    def step(self, n: int, t: int, held: list[Any]) -> None:
        pass


class VerdictValue(Value):
    """A condition used as a value: True, False or unknown."""

    def __init__(self, arg: Condition) -> None:
        super().__init__()
        self.arg = arg

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.val = as_value(self.arg.cur)


class ArithValue(Value):
    """``left OP right`` of two values, ``OP`` one of ``+ - * /``."""

    def __init__(self, op: str, left: Value, right: Value) -> None:
        super().__init__()
        self.op = op
        self.left = left
        self.right = right

    def step(self, n: int, t: int, held: list[Any]) -> None:
        x = self.left.val
        y = self.right.val
        op = self.op
        if type(x) is float and type(y) is float:  # the common case, without a call
            if op == "+":
                result = x + y
            elif op == "-":
                result = x - y
            elif op == "*":
                result = x * y
            elif y != 0.0:
                result = x / y
            else:
                self.val = UNKNOWN_VALUE
                return
            self.val = result if result - result == 0.0 else UNKNOWN_VALUE
        else:
            self.val = arith(op, x, y)


class CallValue(Value):
    """A function of values: ``abs(x)``, ``min(x, y)``, ``max(x, y)`` or ``-x``."""

    def __init__(self, fn: str, args: list[Value]) -> None:
        super().__init__()
        self.fn = fn
        self.args = args

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.val = call(self.fn, [a.val for a in self.args])


class PrevValue(Value):
    """``prev(x)`` of a value: its value at the previous state."""

    def __init__(self, arg: Value) -> None:
        super().__init__()
        self.arg = arg
        self.before: Any = UNKNOWN_VALUE

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.val = self.before
        self.before = self.arg.val


class RobustnessValue(Value):
    """``robustness(F)`` of a condition decided by its state: its own robustness tree, stepped
    after F's verdict nodes (they are its operands), read at the state."""

    def __init__(self, tree: RobustnessTree) -> None:
        super().__init__()
        self.tree = tree

    def step(self, n: int, t: int, held: list[Any]) -> None:
        tree = self.tree
        tree.step(n, t)
        known, rob = tree.get(n)
        self.val = rob if known and rob is not None else UNKNOWN_VALUE
        tree.trim(t)


def _compare_floats(code: int, x: float, y: float) -> int:
    """``x OP y`` of two floats, the operator by its code in ``_OPS``, as TRUE or FALSE."""
    if code == 0:
        return TRUE if x < y else FALSE
    if code == 1:
        return TRUE if x > y else FALSE
    if code == 2:
        return TRUE if x <= y else FALSE
    if code == 3:
        return TRUE if x >= y else FALSE
    if code == 4:
        return TRUE if x == y else FALSE
    return TRUE if x != y else FALSE


class AtomNode(Condition):
    """``left OP right`` (or a bare value, ``op`` None): a condition decided at its state."""

    def __init__(self, clock: Clock, op: str | None, left: Value, right: Value | None) -> None:
        super().__init__(clock, True, 0)
        self.op = op
        self.code = _OPS.index(op) if op in _OPS else -1  # (an int: compiled, comparing strs costs calls)
        self.left = left
        self.right = right
        # a number written in the formula (``Speed(r) < 0.5``, the common atom), unboxed once:
        # compiled, reading the constant's float object at every state cost a type check and an unboxing
        self.const = isinstance(right, ConstValue) and _finite_float(right.val) and self.code >= 0
        self.number = float(right.val) if self.const and right is not None else 0.0

    def step(self, n: int, t: int, held: list[Any]) -> None:
        x = self.left.val
        if self.const and type(x) is float:
            self.cur = value = _compare_floats(self.code, x, self.number)
            if self.history:
                self.vals.append(value)
            return
        op = self.op
        right = self.right
        if right is None:
            value = truth(x)
        else:
            y = right.val
            code = self.code
            if type(x) is float and type(y) is float and code >= 0:  # the common case, without a generic call
                value = _compare_floats(code, x, y)
            else:
                value = compare(op or "", x, y)
        self.cur = value
        if self.history:
            self.vals.append(value)


class PrevNode(Condition):
    """``prev(F)`` of a condition decided at its state: F's verdict at the previous state."""

    def __init__(self, clock: Clock, arg: Condition) -> None:
        super().__init__(clock, True, 0)
        self.arg = arg
        self.before = UNKNOWN

    def step(self, n: int, t: int, held: list[Any]) -> None:
        value = self.before
        self.before = self.arg.cur
        self.cur = value
        if self.history:
            self.vals.append(value)


class EdgeNode(Condition):
    """``rise(F)``: F and not prev(F); ``fall(F)``: not F and prev(F)."""

    def __init__(self, clock: Clock, rise: bool, arg: Condition) -> None:
        super().__init__(clock, True, 0)
        self.rise = rise
        self.arg = arg
        self.before = UNKNOWN

    def step(self, n: int, t: int, held: list[Any]) -> None:
        now = self.arg.cur
        before = self.before
        self.before = now
        if self.rise:
            value = now if now < 2 - before else 2 - before
        else:
            value = 2 - now if 2 - now < before else before
        self.cur = value
        if self.history:
            self.vals.append(value)


class ConstNode(Condition):
    """``true`` or ``false``."""

    def __init__(self, clock: Clock, value: int) -> None:
        super().__init__(clock, True, 0)
        self.value = value

    def step(self, n: int, t: int, held: list[Any]) -> None:
        self.cur = self.value
        if self.history:
            self.vals.append(self.value)


class NotNode(Condition):
    """``not F``: Kleene's 2 - F, at every state F decides."""

    def __init__(self, clock: Clock, arg: Condition) -> None:
        super().__init__(clock, arg.sync, arg.need_ns)
        self.arg = arg

    def step(self, n: int, t: int, held: list[Any]) -> None:
        arg = self.arg
        value = 2 - arg.cur
        self.cur = value
        if self.history:
            vals = self.vals
            vals.append(value)
            if not self.sync:
                base = self.clock.base
                arg_vals = arg.vals
                arg_events = arg.events
                count = arg.nev
                for e in range(count):
                    j: int = arg_events[e]
                    vals[j - base] = 2 - arg_vals[j - base]
                self.events = arg_events
                self.nev = count


def _combine(kind: int, x: int, y: int) -> int:
    if kind == AND:
        return x if x < y else y
    if kind == OR:
        return x if x > y else y
    x = 2 - x
    return x if x > y else y


class BinaryNode(Condition):
    """``and``, ``or``, ``implies``: Kleene's min, max and max(not x, y)."""

    def __init__(self, clock: Clock, kind: int, left: Condition, right: Condition, horizon_ns: int) -> None:
        sync = left.sync and right.sync
        super().__init__(clock, sync, 0 if sync else horizon_ns)
        self.kind = kind
        self.left = left
        self.right = right

    def step(self, n: int, t: int, held: list[Any]) -> None:
        left_node = self.left
        right_node = self.right
        kind = self.kind
        value = _combine(kind, left_node.cur, right_node.cur)
        self.cur = value
        if not self.history:
            return
        vals = self.vals
        vals.append(value)
        if self.sync:
            return
        self.nev = 0  # (a parent reads the events during this state only)
        if value != UNKNOWN:
            self.event(self.clock.idx[-1])
        left_count = left_node.nev
        right_count = right_node.nev
        if not left_count and not right_count:  # (a synchronous operand has none)
            return
        left = left_node.vals
        right = right_node.vals
        base = self.clock.base
        left_events = left_node.events
        for e in range(left_count):
            jb = left_events[e]  # (kept boxed: it goes into events as it is)
            j: int = jb
            if vals[j - base] == UNKNOWN:
                value = _combine(kind, left[j - base], right[j - base])
                if value != UNKNOWN:
                    vals[j - base] = value
                    self.event(jb)
        right_events = right_node.events
        for e in range(right_count):
            jb = right_events[e]
            j = jb
            if vals[j - base] == UNKNOWN:
                value = _combine(kind, left[j - base], right[j - base])
                if value != UNKNOWN:
                    vals[j - base] = value
                    self.event(jb)
