"""The language of temporal formulas: its syntax tree and its parser.

A formula is text::

    historically[0, 2s] Battery(robot) > 0.2
    Speed(robot) < SpeedLimit(zone)
    abs(Pose(robot).x - Goal(robot).x) < 0.1
    rise(Door(hall).open) implies eventually[0, 2s] Alarm(hall)
    avg[0, 5s] Speed(robot) < 0.5 and count[0, 60s] rise(Bump(robot)) <= 3
    Mode(robot) == "manual" or Battery(robot) >= 0.2
    forall c in Camera: always[0, 1s] Fresh(c)
    foreach t in Track(field).id: always[0, 2s] Track(field).speed < 3

Grammar (keywords are lowercase; whitespace is free)::

    formula    := quantifier | implies
    quantifier := ('forall' | 'exists') VAR 'in' CLASS ':' formula       over an ontology class
                | 'foreach' VAR 'in' stream ':' formula                  over the objects a stream names
    implies    := or ['implies' formula]                                 right-associative
    or         := and {'or' and}
    and        := binary {'and' binary}
    binary     := unary [('until' | 'since') interval unary]             not chained: parenthesise
    unary      := 'not' unary
                | ('always' | 'eventually' | 'historically' | 'once') interval unary
                | comparison
    comparison := sum [CMP sum]                                          CMP: < <= > >= == !=  (not chained)
    sum        := product {('+' | '-') product}
    product    := prefix {('*' | '/') prefix}
    prefix     := '-' prefix
                | AGGREGATE interval prefix                              count sum avg min max integral rate
                | primary
    primary    := NUMBER | STRING | 'true' | 'false'
                | ('abs' | 'prev' | 'rise' | 'fall' | 'robustness') '(' formula ')'
                | ('min' | 'max') '(' formula ',' formula ')'
                | '(' formula ')'
                | VAR                                                    a quantifier's variable, in its body
                | stream
    stream     := TERM {'.' FIELD}                                       Battery(robot), BallTrack(field).speed
    interval   := '[' duration ',' duration ']'                          a <= b
    duration   := NUMBER ('s' | 'ms') | '0' | 'inf'                      inf: upper bound of past windows only

So ``always[0, 1s] p and q`` is ``(always[0, 1s] p) and q``, ``not x > 3`` is ``not (x > 3)``,
``avg[0, 5s] Speed(robot) + 1`` is ``(avg[0, 5s] Speed(robot)) + 1`` and a quantifier's body
reaches as far right as it can (``forall c in C: p and q`` quantifies both).

- **Terms** are semantic tags as specs write them (:mod:`dyknow.tags` reads them: ``parse_term``),
  so ``Battery(robot)``, ``dk:Battery(robot)`` and ``<http://x/Battery>(robot)`` all work. A ``.``
  after a term starts a field path into a JSON object payload: ``BallTrack(field).speed``,
  ``Pose(robot).position.x``; for a term without args the name ends at the first ``.``
  (``Ticks.count`` is the field ``count`` of ``Ticks``). A tag whose name itself holds a dot, or is
  spelled like a keyword, is written in backquotes: ```cam.left`.exposure > 3``. The words of
  functions and aggregates (``abs``, ``count``, ...) are keywords only before ``(`` or ``[``.
- **Values** are numbers, strings (``"manual"`` or ``'manual'``, with ``\\"``, ``\\'`` and
  ``\\\\`` escapes), ``true`` and ``false``, and what streams carry. **Expressions** compute
  with them: ``+ - * /``, unary ``-``, ``abs``, ``min`` and ``max`` of two, ``prev`` (the value at
  the previous state), ``robustness(F)`` (a condition's robustness: how far from changing) and the
  aggregates of a past window. **Conditions** (what ``and``, ``or``,
  ``not``, the temporal operators, ``rise``, ``fall`` and ``count`` take) are comparisons, ``true``
  and ``false``, ``rise(F)``/``fall(F)``, and bare expressions of boolean value (``Stalled(robot)``,
  ``Door(hall).open``, ``prev(p)``). A mistake of kinds that can be seen in the text is refused at
  its column (``Speed(robot) + "fast"``, ``avg[0, 1s] (p and q)``, ``"a" < 1``, ``3 and p``);
  what a value of the wrong kind *in the data* gives is stated in :mod:`dyknow.reasoning.semantics`
  (unknown, never false).
- **Aggregates** (``count``, ``sum``, ``avg``, ``min``, ``max``, ``integral``, ``rate``) look at a
  past window, as ``once`` does, and so do ``prev``, ``rise`` and ``fall``: their operand may not
  look into the future (a verdict decided later cannot be aggregated now).
- **Quantifiers**: ``forall``/``exists`` range over the individuals of an ontology class (their
  variable stands in terms' args, ``Fresh(c)``, and as a string value); a monitor expands them
  (:mod:`dyknow.reasoning.quantify`). ``foreach VAR in STREAM:`` makes one monitor per object: per
  distinct value of the stream's field; in the body the stream reads the object's own samples and
  the variable is the object's value. ``foreach`` comes first (after ``forall`` prefixes, if
  any), never inside an operator.
- **Durations** are integer nanoseconds once parsed (``1.5s`` is 1_500_000_000; a duration finer
  than a nanosecond is refused). Future operators (``always``, ``eventually``, ``until``) need a
  finite upper bound; past ones (``historically``, ``once``, ``since``, the aggregates) may write
  ``inf``.

A formula's text is bounded (:data:`MAX_FORMULA_CHARS` characters, :data:`MAX_DEPTH` levels of
nesting), because formulas reach a manager over the network as unit params; a chain ``p or q or
...`` (or ``and``, ``+``, ``*``) is read in a loop and counts as one level however long it is.
Nothing that walks a formula (writing it, comparing, hashing, evaluating, monitoring) recurses in
Python, so no depth that parses can exhaust the stack. :func:`check_formula` holds a formula to a
manager's :class:`~dyknow.security.Limits` as well: at most ``max_formula_nodes`` nodes (500),
interval bounds and a future horizon of at most ``max_window_ns`` (one day); a manager checks
every formula so before it requests or spawns anything for it.

Parse errors are :class:`~dyknow.errors.FormulaError` with ``where`` = ``formula column N``
(1-based), saying what came and what was expected there. ``str(formula)`` writes a formula back
with only the parentheses it needs; parsing that text gives the same tree.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, fields
from decimal import Decimal, InvalidOperation
from typing import TypeVar

from dyknow.errors import FormulaError, TagError, did_you_mean
from dyknow.security import Limits
from dyknow.tags import Term, parse_term

__all__ = [
    "AGGREGATES",
    "ARITHMETIC",
    "COMPARISONS",
    "MAX_DEPTH",
    "MAX_FORMULA_CHARS",
    "Aggregate",
    "Always",
    "And",
    "Arith",
    "Atom",
    "Call",
    "Const",
    "Eventually",
    "Fall",
    "Formula",
    "Historically",
    "Implies",
    "Interval",
    "Neg",
    "Node",
    "Not",
    "Num",
    "Once",
    "Or",
    "Prev",
    "Quantifier",
    "Rise",
    "Since",
    "Str",
    "Stream",
    "Until",
    "Var",
    "check_formula",
    "children",
    "kind_of",
    "parse",
    "parse_value",
    "walk",
]

COMPARISONS: tuple[str, ...] = ("<", "<=", ">", ">=", "==", "!=")
"""The comparison operators."""

ARITHMETIC: tuple[str, ...] = ("+", "-", "*", "/")
"""The arithmetic operators."""

AGGREGATES: tuple[str, ...] = ("count", "sum", "avg", "min", "max", "integral", "rate")
"""The aggregates of a past window."""

FUNCTIONS: tuple[str, ...] = ("abs", "min", "max", "prev", "rise", "fall", "robustness")
"""The functions written with their operands in parentheses."""

MAX_FORMULA_CHARS: int = 10_000
"""The longest formula text :func:`parse` reads."""

MAX_DEPTH: int = 64
"""The deepest nesting of operators and parentheses :func:`parse` reads (a chain of one operator
counts once)."""

_NS_PER_S = 1_000_000_000


def _duration_text(ns: int) -> str:
    if ns == 0:
        return "0"
    if ns % 1_000_000 == 0 and ns % _NS_PER_S != 0:
        return f"{ns // 1_000_000}ms"
    text = format(Decimal(ns) / _NS_PER_S, "f")
    return (text.rstrip("0").rstrip(".") if "." in text else text) + "s"


def _number_text(number: int | float) -> str:
    if isinstance(number, int):
        return str(number)
    return str(int(number)) if number.is_integer() and abs(number) < 1e15 else repr(number)


def _string_text(value: str) -> str:
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'


@dataclass(frozen=True, slots=True)
class Interval:
    """A metric interval ``[a, b]`` in integer nanoseconds; ``hi_ns`` None is ``inf``."""

    lo_ns: int
    hi_ns: int | None

    def __str__(self) -> str:
        hi = "inf" if self.hi_ns is None else _duration_text(self.hi_ns)
        return f"[{_duration_text(self.lo_ns)}, {hi}]"


# ---------------------------------------------------------------------------- the leaves


@dataclass(frozen=True, slots=True)
class Num:
    """A number as written: an ``int`` for whole literals (``3``), a ``float`` otherwise (``0.5``)."""

    value: int | float

    def __str__(self) -> str:
        return _number_text(self.value)


@dataclass(frozen=True, slots=True)
class Str:
    """A string constant: ``"manual"``."""

    value: str

    def __str__(self) -> str:
        return _string_text(self.value)


@dataclass(frozen=True, slots=True)
class Const:
    """``true`` or ``false``: a condition, and a boolean value."""

    value: bool

    def __str__(self) -> str:
        return "true" if self.value else "false"


@dataclass(frozen=True, slots=True)
class Stream:
    """A stream's value: the term's latest sample, down the field path when there is one.

    ``term`` is the stream's tag; ``fields`` the path into a JSON object payload (empty: the
    payload itself).
    """

    term: Term
    fields: tuple[str, ...] = ()

    def __str__(self) -> str:
        name = str(self.term)
        functor = self.term.functor
        if not functor.startswith("<") and ("." in functor or functor in _RESERVED):
            name = f"`{name}`"
        return name + "".join(f".{f}" for f in self.fields)


@dataclass(frozen=True, slots=True)
class Var:
    """A quantifier's variable used as a value in its body."""

    name: str

    def __str__(self) -> str:
        return self.name


# ---------------------------------------------------------------------------- the operators


class _Operator:
    """What the operators share: writing, comparing, hashing and ``repr`` walk the tree with a
    stack of their own, not Python's, so a tree as deep as a long ``p or q or ...`` chain (which
    nests to the left, one level per ``or``) costs no recursion. The operators' dataclasses keep
    these (``eq=False, repr=False``)."""

    __slots__ = ()

    def __str__(self) -> str:
        return _text(self)  # type: ignore[arg-type]  # every subclass is a Node

    def __repr__(self) -> str:
        return _repr(self)  # type: ignore[arg-type]

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return _same(self, other)  # type: ignore[arg-type]

    def __hash__(self) -> int:
        return hash((type(self).__name__, _text(self)))  # type: ignore[arg-type]  # the text determines the tree


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Atom(_Operator):
    """A condition on values: ``left OP right`` (``op`` one of :data:`COMPARISONS`), or, when
    ``op`` is None, the bare value ``left`` read as a condition (``Stalled(robot)``)."""

    left: Node
    op: str | None = None
    right: Node | None = None


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Neg(_Operator):
    """``-arg``."""

    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Arith(_Operator):
    """``left OP right``, ``op`` one of :data:`ARITHMETIC`."""

    op: str
    left: Node
    right: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Call(_Operator):
    """``abs(x)``, ``min(x, y)``, ``max(x, y)``."""

    fn: str
    args: tuple[Node, ...]


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Prev(_Operator):
    """``prev(arg)``: ``arg``'s value (or verdict) at the previous state."""

    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Rise(_Operator):
    """``rise(arg)``: ``arg`` false at the previous state and true at this one."""

    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Fall(_Operator):
    """``fall(arg)``: ``arg`` true at the previous state and false at this one."""

    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Aggregate(_Operator):
    """``KIND[a, b] arg`` over the past window ``[a, b]``, ``kind`` one of :data:`AGGREGATES`
    (``count`` counts the states where a condition is true; the others take numbers)."""

    kind: str
    interval: Interval
    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Not(_Operator):
    """``not arg``."""

    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class And(_Operator):
    """``left and right``."""

    left: Node
    right: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Or(_Operator):
    """``left or right``."""

    left: Node
    right: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Implies(_Operator):
    """``left implies right``: ``(not left) or right``."""

    left: Node
    right: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Always(_Operator):
    """``always[a, b] arg`` (future): ``arg`` at every state between ``a`` and ``b`` from now."""

    interval: Interval
    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Eventually(_Operator):
    """``eventually[a, b] arg`` (future): ``arg`` at some state between ``a`` and ``b`` from now."""

    interval: Interval
    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Historically(_Operator):
    """``historically[a, b] arg`` (past): ``arg`` at every state between ``b`` and ``a`` ago."""

    interval: Interval
    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Once(_Operator):
    """``once[a, b] arg`` (past): ``arg`` at some state between ``b`` and ``a`` ago."""

    interval: Interval
    arg: Node


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Until(_Operator):
    """``left until[a, b] right`` (future)."""

    left: Node
    right: Node
    interval: Interval


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Since(_Operator):
    """``left since[a, b] right`` (past)."""

    left: Node
    right: Node
    interval: Interval


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Quantifier(_Operator):
    """``forall VAR in CLASS: body``, ``exists VAR in CLASS: body`` (``domain`` a class reference
    as specs write it) or ``foreach VAR in STREAM: body`` (``domain`` a :class:`Stream`)."""

    kind: str
    var: str
    domain: str | Stream
    body: Node


Node = (
    Num | Str | Const | Stream | Var
    | Atom | Neg | Arith | Call | Prev | Rise | Fall | Aggregate
    | Not | And | Or | Implies | Always | Eventually | Historically | Once | Until | Since | Quantifier
)  # fmt: skip
"""A node of a formula's syntax tree: a value (constants, streams, variables, expressions) or a
condition (atoms, connectives, temporal operators, rise/fall, quantifiers)."""

_N = TypeVar("_N", bound=Node)

_LEAVES = (Num, Str, Const, Stream, Var)
_FUTURE = (Always, Eventually, Until)
_PAST_WINDOW = (Historically, Once, Since, Aggregate, Prev, Rise, Fall)

# binding strength, loosest first: what a child must reach to be written without parentheses
_QUANT, _IMPLIES, _OR, _AND, _BINARY, _UNARY, _COMPARE, _SUM, _PRODUCT, _PREFIX, _PRIMARY = range(11)


def _level(node: Node) -> int:
    if isinstance(node, Quantifier):
        return _QUANT
    if isinstance(node, Implies):
        return _IMPLIES
    if isinstance(node, Or):
        return _OR
    if isinstance(node, And):
        return _AND
    if isinstance(node, Until | Since):
        return _BINARY
    if isinstance(node, Not | Always | Eventually | Historically | Once):
        return _UNARY
    if isinstance(node, Atom):
        return _COMPARE if node.op is not None else _level(node.left)
    if isinstance(node, Arith):
        return _SUM if node.op in ("+", "-") else _PRODUCT
    if isinstance(node, Neg | Aggregate):
        return _PREFIX
    if isinstance(node, Num) and node.value < 0:
        return _PREFIX  # written with its sign
    return _PRIMARY


_Piece = str | tuple[Node, int]  # text as is, or a node written at least at a binding strength


def _pieces(node: Node) -> list[_Piece]:
    """How ``node`` is written: its own text around its operands, each with the binding strength
    it must reach to go without parentheses."""
    if isinstance(node, _LEAVES):
        return [str(node)]
    if isinstance(node, Atom):
        if node.op is None:
            return [(node.left, _UNARY)]
        assert node.right is not None
        return [(node.left, _SUM), f" {node.op} ", (node.right, _SUM)]
    if isinstance(node, Neg):
        if isinstance(node.arg, Num):  # -(3), not the literal -3
            return ["-(", (node.arg, _QUANT), ")"]
        return ["-", (node.arg, _PREFIX)]
    if isinstance(node, Arith):
        own = _SUM if node.op in ("+", "-") else _PRODUCT
        return [(node.left, own), f" {node.op} ", (node.right, own + 1)]
    if isinstance(node, Call):
        pieces: list[_Piece] = [f"{node.fn}("]
        for k, arg in enumerate(node.args):
            if k:
                pieces.append(", ")
            pieces.append((arg, _QUANT))
        return [*pieces, ")"]
    if isinstance(node, Prev | Rise | Fall):
        return [f"{type(node).__name__.lower()}(", (node.arg, _QUANT), ")"]
    if isinstance(node, Aggregate):
        return [f"{node.kind}{node.interval} ", (node.arg, _PREFIX)]
    if isinstance(node, Not):
        return ["not ", (node.arg, _UNARY)]
    if isinstance(node, And):
        return [(node.left, _AND), " and ", (node.right, _BINARY)]
    if isinstance(node, Or):
        return [(node.left, _OR), " or ", (node.right, _AND)]
    if isinstance(node, Implies):
        return [(node.left, _OR), " implies ", (node.right, _IMPLIES)]
    if isinstance(node, Until | Since):
        op = "until" if isinstance(node, Until) else "since"
        return [(node.left, _UNARY), f" {op}{node.interval} ", (node.right, _UNARY)]
    if isinstance(node, Quantifier):
        return [f"{node.kind} {node.var} in {node.domain}: ", (node.body, _QUANT)]
    return [f"{type(node).__name__.lower()}{node.interval} ", (node.arg, _UNARY)]


def _text(root: Node) -> str:
    """The formula's text with only the parentheses it needs (iteratively: trees may be deep)."""
    out: list[str] = []
    stack: list[_Piece] = [(root, 0)]
    while stack:
        piece = stack.pop()
        if isinstance(piece, str):
            out.append(piece)
            continue
        node, least = piece
        pieces = _pieces(node)
        if _level(node) < least:
            pieces = ["(", *pieces, ")"]
        stack.extend(reversed(pieces))
    return "".join(out)


def _own(node: Node) -> object:
    """What a node holds besides its operands (compared by value)."""
    if isinstance(node, _LEAVES):
        return node
    if isinstance(node, Atom):
        return node.op
    if isinstance(node, Arith):
        return node.op
    if isinstance(node, Call):
        return (node.fn, len(node.args))
    if isinstance(node, Aggregate):
        return (node.kind, node.interval)
    if isinstance(node, Quantifier):
        return (node.kind, node.var, node.domain)
    if isinstance(node, Always | Eventually | Historically | Once | Until | Since):
        return node.interval
    return None


def _same(a: Node, b: Node) -> bool:
    """Whether two trees are equal, node by node (iteratively)."""
    stack = [(a, b)]
    while stack:
        x, y = stack.pop()
        if x is y:
            continue
        if type(x) is not type(y) or _own(x) != _own(y):
            return False
        xs, ys = children(x), children(y)
        if len(xs) != len(ys):
            return False
        stack.extend(zip(xs, ys, strict=True))
    return True


def _repr(root: Node) -> str:
    """``repr`` as a dataclass writes it, ``And(left=Atom(...), right=...)`` (iteratively)."""
    out: list[str] = []
    stack: list[str | Node] = [root]
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            out.append(item)
            continue
        if isinstance(item, _LEAVES):
            out.append(repr(item))
            continue
        names = [f.name for f in fields(item)]
        pieces: list[str | Node] = [f"{type(item).__name__}("]
        for k, name in enumerate(names):
            value = getattr(item, name)
            pieces.append(("" if k == 0 else ", ") + f"{name}=")
            if isinstance(value, tuple):
                pieces.append("(")
                for j, v in enumerate(value):
                    pieces.extend([", " if j else "", v])
                pieces.append(",)" if len(value) == 1 else ")")
            elif isinstance(value, _OPERATOR_TYPES):
                pieces.append(value)
            else:
                pieces.append(repr(value))
        pieces.append(")")
        stack.extend(reversed(pieces))
    return "".join(out)


def children(node: Node) -> tuple[Node, ...]:
    """A node's operands, left to right (none for the leaves)."""
    if isinstance(node, _LEAVES):
        return ()
    if isinstance(node, Atom):
        return (node.left,) if node.right is None else (node.left, node.right)
    if isinstance(node, And | Or | Implies | Until | Since | Arith):
        return (node.left, node.right)
    if isinstance(node, Call):
        return node.args
    if isinstance(node, Quantifier):
        return (node.body,)
    return (node.arg,)


def walk(root: Node) -> list[Node]:
    """Every node, parents before children, left to right (iteratively: formulas may be deep)."""
    out: list[Node] = []
    stack = [root]
    while stack:
        node = stack.pop()
        out.append(node)
        stack.extend(reversed(children(node)))
    return out


_OPERATOR_TYPES = (Atom, Neg, Arith, Call, Prev, Rise, Fall, Aggregate, Not, And, Or, Implies, Always, Eventually, Historically, Once, Until, Since, Quantifier, *_LEAVES)


# ---------------------------------------------------------------------------- kinds of values

#: What a node gives: a condition (a verdict), a number, a string, or any value (what a stream
#: or a variable holds: its kind is the data's).
BOOL, NUM, STR, ANY = "condition", "number", "string", "value"


def kind_of(node: Node) -> str:
    """What ``node`` gives, as far as the text tells: :data:`BOOL`, :data:`NUM`, :data:`STR` or :data:`ANY`."""
    if isinstance(node, Num | Neg | Arith | Call):
        return NUM
    if isinstance(node, Aggregate):
        return NUM
    if isinstance(node, Str):
        return STR
    if isinstance(node, Stream | Var):
        return ANY
    if isinstance(node, Prev):
        return kind_of(node.arg)
    return BOOL


# ---------------------------------------------------------------------------- the formula


@dataclass(frozen=True, slots=True)
class Formula:
    """A parsed formula: the text as written, its syntax tree and the terms it mentions.

    ``terms`` are the distinct streams' tags in order of first appearance (several fields of one
    term share it); :func:`parse` and :meth:`Formula.of` fill them in, so build a formula with one
    of those. ``str(formula)`` is the canonical text.
    """

    text: str
    root: Node
    terms: tuple[Term, ...] = field(default=())

    def __str__(self) -> str:
        return str(self.root)

    @property
    def past_only(self) -> bool:
        """Whether no future operator occurs: every state's verdict is decided at that state."""
        return not any(isinstance(node, _FUTURE) for node in walk(self.root))

    @property
    def horizon_ns(self) -> int:
        """How far into the future a verdict may need to look: the largest sum of future upper
        bounds along a path from the root (0 for a past-only formula)."""
        return _future_horizon(self.root)

    @property
    def reach_ns(self) -> int | None:
        """How far into the past a verdict may read: the largest sum of past upper bounds (past
        windows, aggregates, and a state for prev, rise and fall) along a path from the root;
        None when a past window is unbounded (it reads back to the first state)."""
        return _past_reach(self.root)

    @property
    def nodes(self) -> int:
        """How many atoms and operators the syntax tree has (the leaves, streams and constants,
        are not counted: they cost a monitor nothing per state): what the bounds count."""
        return sum(1 for node in walk(self.root) if not isinstance(node, _LEAVES))

    @property
    def operators(self) -> int:
        """How many operators (connectives, temporal operators, arithmetic, aggregates; not
        leaves nor atoms) the formula has."""
        return sum(1 for node in walk(self.root) if not isinstance(node, (*_LEAVES, Atom)))

    @property
    def quantifiers(self) -> tuple[Quantifier, ...]:
        """The quantifiers the formula starts with, outermost first (its body follows the last)."""
        found: list[Quantifier] = []
        node = self.root
        while isinstance(node, Quantifier):
            found.append(node)
            node = node.body
        return tuple(found)

    @classmethod
    def of(cls, root: Node, text: str | None = None) -> Formula:
        """A formula from a syntax tree built in code (its terms collected, its text written)."""
        terms: dict[Term, None] = {}
        for node in walk(root):
            if isinstance(node, Quantifier) and isinstance(node.domain, Stream):
                terms.setdefault(node.domain.term, None)  # foreach reads its stream
            if isinstance(node, Stream):
                terms.setdefault(node.term, None)
        return cls(str(root) if text is None else text, root, tuple(terms))


def _past_reach(root: Node) -> int | None:
    memo: dict[int, int | None] = {}
    for node in reversed(walk(root)):  # children before parents
        below: int | None = 0
        for child in children(node):
            value = memo[id(child)]
            below = None if below is None or value is None else max(below, value)
        if isinstance(node, Historically | Once | Since | Aggregate):
            hi = node.interval.hi_ns
            memo[id(node)] = None if below is None or hi is None else below + hi
        else:
            memo[id(node)] = below
    return memo[id(root)]


def _future_horizon(root: Node) -> int:
    memo: dict[int, int] = {}
    for node in reversed(walk(root)):  # children before parents
        below = max((memo[id(child)] for child in children(node)), default=0)
        own = 0
        if isinstance(node, _FUTURE):
            own = node.interval.hi_ns or 0
        memo[id(node)] = below + own
    return memo[id(root)]


# ---------------------------------------------------------------------------- the parser

_KEYWORDS = frozenset(
    {
        "not", "and", "or", "implies", "always", "eventually", "historically", "once", "until", "since",
        "true", "false", "inf", "forall", "exists", "foreach", "in",
    }
)  # fmt: skip
_RESERVED = _KEYWORDS | frozenset(AGGREGATES) | frozenset(FUNCTIONS)  # spelled like these, a tag is backquoted
_UNARY_TEMPORAL: dict[str, type[Always | Eventually | Historically | Once]] = {
    "always": Always,
    "eventually": Eventually,
    "historically": Historically,
    "once": Once,
}
_DELIMITERS = frozenset(" \t\r\n\f\v()[],<>=!.`+-*/\"'")
_SPACE = re.compile(r"\s*")
_NUMBER = re.compile(r"(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_DURATION = re.compile(r"([0-9]+(?:\.[0-9]+)?)(ms|s)?(?![A-Za-z0-9_.])")
_FIELD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_VARIABLE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_CLASS = re.compile(r"<[^>\s]+>|[A-Za-z_][\w.-]*(?::[\w.-]+)?")
_OPERATOR = re.compile(r"<=|>=|==|!=|<|>")
_HINT_OPERATORS = {"=": "== (equality is written ==)", "!": "!= (inequality is written !=)"}
_FORMULA_START = (
    "a condition: a comparison such as Battery(robot) > 0.2, a stream of boolean value, 'not', a temporal operator, "
    "rise(...), '(' or true/false"
)
_VALUE_START = "a value: a number, a string in quotes, a stream such as Speed(robot), '(' or a function such as abs(...)"


def parse(text: str) -> Formula:
    """Parse a formula; raises :class:`~dyknow.errors.FormulaError` naming the column and what was expected.

    Only the language's own bounds apply (:data:`MAX_FORMULA_CHARS`, :data:`MAX_DEPTH`); a
    formula from a caller the process does not trust goes through :func:`check_formula`.

    >>> str(parse("historically[0,2s](Battery(robot)>0.2)"))
    'historically[0, 2s] Battery(robot) > 0.2'
    >>> str(parse("abs(Pose(robot).x-Goal(robot).x)<0.1"))
    'abs(Pose(robot).x - Goal(robot).x) < 0.1'
    """
    return _parse(text, None, None)


def check_formula(formula: str | Formula, limits: Limits | None = None) -> Formula:
    """Parse ``formula`` and hold it to ``limits`` (:class:`~dyknow.security.Limits`; its
    defaults when None): what a manager does with every formula before it requests or spawns
    anything for it. A :class:`Formula` is checked by its text.

    Besides the language's bounds (:func:`parse`), the formula may have at most
    ``limits.max_formula_nodes`` nodes (atoms and operators), no interval bound beyond
    ``limits.max_window_ns`` (a past window may still write ``inf``), and may look at most that
    far ahead (its future horizon: the upper bounds of nested future operators add up). Raises
    :class:`~dyknow.errors.FormulaError` located at the column where the formula crosses a bound,
    naming the bound; nothing else (a deep formula is refused, never a ``RecursionError``).

    >>> check_formula("p implies eventually[0, 2s] q").horizon_ns
    2000000000
    >>> check_formula("always[0, 100000000000000000000000000000s] p")
    Traceback (most recent call last):
    ...
    dyknow.errors.FormulaError: formula column 7: 'always[0, 100000000000000000000000000000s]' has the bound ..., beyond the longest window ...; expected bounds of at most 86400s (Limits.max_window_ns)
    """
    limits = limits if limits is not None else Limits()
    text = formula.text if isinstance(formula, Formula) else formula
    return _parse(text, limits.max_formula_nodes, limits.max_window_ns)


def parse_value(text: str) -> Formula:
    """Parse an expression (a value, or a condition) rather than a formula: ``avg[0, 1s] Speed(robot)``;
    :func:`~dyknow.reasoning.semantics.evaluate_values` computes it at every state."""
    return _parse(text, None, None, value=True)


def _parse(text: str, max_nodes: int | None, max_window_ns: int | None, *, value: bool = False) -> Formula:
    if not isinstance(text, str):
        raise FormulaError(f"a formula is text, got {type(text).__name__}", where="formula", expected="a str such as 'once[0, 1s] p'")
    if len(text) > MAX_FORMULA_CHARS:
        raise FormulaError(
            f"the formula has {len(text)} characters", where="formula", expected=f"at most {MAX_FORMULA_CHARS}", formula=text[:80] + "..."
        )
    parser = _Parser(text, max_nodes, max_window_ns)
    try:
        root = parser.formula(0, top=True)
        parser.skip()
        if not parser.at_end():
            hint = did_you_mean(parser.word(), ["and", "or", "implies", "until", "since"])
            raise parser.unexpected("the end of the formula, 'and', 'or', 'implies', 'until', 'since' or an operator" + hint)
        if not value:
            root = parser.condition(root, 0)
    except RecursionError:  # a caller already deep in its stack: MAX_DEPTH levels did not fit
        raise parser.fail(
            "the formula nests deeper than this thread's stack allows", f"fewer levels of operators and parentheses (at most {MAX_DEPTH})"
        ) from None
    return Formula.of(root, text)


class _Parser:
    """A recursive-descent reader over the text that says where and why it is malformed, and
    checks the kinds of the values it reads as it builds (a condition where a number must be)."""

    def __init__(self, text: str, max_nodes: int | None = None, max_window_ns: int | None = None) -> None:
        self.text = text
        self.pos = 0
        self.max_nodes = max_nodes
        self.max_window_ns = max_window_ns
        self.nodes = 0
        self.ahead: dict[int, int] = {}  # id(node) -> its future horizon, where not 0 (bounded windows only)
        self.future: set[int] = set()  # id(node) of the nodes with a future operator at or below them
        self.columns: dict[int, int] = {}  # id(node) -> where its text starts (for errors about it)
        self.variables: dict[str, str] = {}  # the quantifiers' variables in scope -> their kind

    def made(self, node: _N, column: int) -> _N:
        """Count a node built from the text at ``column`` (its leaves: streams, constants and
        variables, cost nothing); refuse it past the bounds."""
        self.columns.setdefault(id(node), column)
        if not isinstance(node, _LEAVES):
            self.nodes += 1
        if self.max_nodes is not None and self.nodes > self.max_nodes:
            raise self.fail(
                f"the formula has more than {self.max_nodes} nodes",
                f"at most {self.max_nodes} atoms and operators (Limits.max_formula_nodes)",
                column=column,
            )
        kids = children(node)
        if isinstance(node, _FUTURE) or any(id(kid) in self.future for kid in kids):
            self.future.add(id(node))
        if self.max_window_ns is not None:
            below = max((self.ahead.get(id(kid), 0) for kid in kids), default=0)
            ahead = below + ((node.interval.hi_ns or 0) if isinstance(node, _FUTURE) else 0)
            if ahead > self.max_window_ns:
                op = type(node).__name__.lower()
                raise self.fail(
                    f"'{op}' here makes the formula look {_duration_text(ahead)} ahead (the upper bounds of nested future operators add up)",
                    f"at most {_duration_text(self.max_window_ns)} ahead (Limits.max_window_ns)",
                    column=column,
                )
            if ahead:
                self.ahead[id(node)] = ahead
        return node

    def column_of(self, node: Node) -> int:
        """Where the text of ``node`` starts (its leftmost part's column)."""
        found = [self.columns[id(n)] for n in walk(node) if id(n) in self.columns]
        return min(found) if found else self.pos

    # -- reading

    def skip(self) -> None:
        self.pos = _SPACE.match(self.text, self.pos).end()  # type: ignore[union-attr]  # \s* always matches

    def at_end(self) -> bool:
        return self.pos >= len(self.text)

    def word(self) -> str:
        """The name-like chunk at the position (not consumed); empty when none starts here."""
        end = self.pos
        while end < len(self.text) and self.text[end] not in _DELIMITERS:
            end += 1
        return self.text[self.pos : end]

    def keyword(self, *words: str) -> str | None:
        """Consume one of ``words`` when it is the next chunk."""
        self.skip()
        chunk = self.word()
        if chunk in words:
            self.pos += len(chunk)
            return chunk
        return None

    def char(self, char: str) -> bool:
        """Consume ``char`` when it is next."""
        self.skip()
        if self.text.startswith(char, self.pos):
            self.pos += len(char)
            return True
        return False

    def after_word(self, chunk: str) -> str:
        """The character after ``chunk`` (at the position) and any space: '' at the end."""
        at = _SPACE.match(self.text, self.pos + len(chunk)).end()  # type: ignore[union-attr]
        return self.text[at] if at < len(self.text) else ""

    # -- errors

    def fail(self, what: str, expected: str, column: int | None = None) -> FormulaError:
        col = (self.pos if column is None else column) + 1
        return FormulaError(
            f"{what} in {_quote(self.text)}", where=f"formula column {col}", expected=expected, formula=self.text, column=col
        )

    def unexpected(self, expected: str) -> FormulaError:
        self.skip()
        if self.at_end():
            return self.fail("unexpected end of formula", expected)
        chunk = self.word() or self.text[self.pos]
        number = _NUMBER.match(self.text, self.pos)
        if number is not None and len(number.group()) > len(chunk):
            chunk = number.group()
        return self.fail(f"unexpected {_quote(chunk)}", expected)

    def deep(self, depth: int) -> None:
        if depth > MAX_DEPTH:
            raise self.fail(f"the formula nests deeper than {MAX_DEPTH} levels", f"at most {MAX_DEPTH} levels of operators and parentheses")

    # -- kinds

    def condition(self, node: Node, column: int | None = None, where: str = "") -> Node:
        """``node`` as a condition: a bare value becomes an :class:`Atom`; a number or a string is refused."""
        kind = self.kind(node)
        if kind == BOOL:
            return node
        at = self.column_of(node) if column is None else column
        if kind == ANY:
            return self.made(Atom(node), at)
        raise self.fail(
            f"{_quote(str(node))} is a {kind}, not a condition{where}",
            "a comparison (such as x > 0.5), true/false, or a stream of boolean value",
            column=at,
        )

    def value(self, node: Node, want: str, what: str) -> Node:
        """``node`` as an operand that must give a ``want`` (NUM): a condition or a string is refused."""
        kind = self.kind(node)
        if kind == ANY or kind == want:
            return node
        raise self.fail(
            f"{_quote(str(node))} is a {kind}, and {what} takes {'numbers' if want == NUM else want + 's'}",
            "a number: a stream's numeric field, a constant, or an expression of them",
            column=self.column_of(node),
        )

    def kind(self, node: Node) -> str:
        if isinstance(node, Var):
            return self.variables.get(node.name, ANY)
        if isinstance(node, Prev):
            return self.kind(node.arg)
        return kind_of(node)

    def past(self, node: Node, what: str) -> None:
        """Refuse an operand of a past window (or of a comparison) that looks into the future."""
        if id(node) in self.future:
            raise self.fail(
                f"{what} reads values decided by its state, and {_quote(str(node))} looks into the future",
                f"an operand without always, eventually or until; or put {what} outside the future operator",
                column=self.column_of(node),
            )

    # -- the grammar: conditions

    def formula(self, depth: int, top: bool = False) -> Node:
        self.deep(depth)
        self.skip()
        at = self.pos
        chunk = self.word()
        if chunk in ("forall", "exists", "foreach"):
            return self.quantifier(chunk, depth, top, at)
        left = self.disjunction(depth)
        self.skip()
        at = self.pos
        if self.keyword("implies"):
            left = self.condition(left)
            right = self.condition(self.formula(depth + 1))
            return self.made(Implies(left, right), at)
        return left

    def quantifier(self, kind: str, depth: int, top: bool, at: int) -> Node:
        if kind == "foreach" and not top:
            raise self.fail(
                "'foreach' inside the formula",
                "foreach first (it makes one monitor per object): foreach t in Track(field).id: ...; forall and exists may nest",
                column=at,
            )
        self.pos += len(kind)
        self.skip()
        match = _VARIABLE.match(self.text, self.pos)
        if match is None or match.group() in _RESERVED:
            raise self.unexpected(f"a variable after '{kind}': {kind} c in Camera: ...")
        var = match.group()
        if var in self.variables:
            raise self.fail(f"the variable {var!r} is bound already", "another name for the inner quantifier's variable")
        self.pos = match.end()
        if not self.keyword("in"):
            raise self.unexpected(f"'in' after the variable: {kind} {var} in ...")
        self.skip()
        domain: str | Stream
        if kind == "foreach":
            column = self.pos
            domain = self.stream()
            if not domain.fields:
                raise self.fail(
                    f"foreach over the stream {domain} itself",
                    f"a field that names the object in each sample: foreach {var} in {domain}.id: ...",
                    column=column,
                )
            kind_of_var = ANY
        else:
            found = _CLASS.match(self.text, self.pos)
            if found is None:
                raise self.unexpected(f"an ontology class after 'in': {kind} {var} in Camera: ...")
            domain = found.group()
            self.pos = found.end()
            kind_of_var = STR
        if not self.char(":"):
            raise self.unexpected(f"':' before the quantifier's formula: {kind} {var} in {domain}: ...")
        self.variables[var] = kind_of_var
        try:
            body = self.condition(self.formula(depth + 1, top=top and kind == "forall"))
        finally:
            del self.variables[var]
        if kind == "foreach":
            for node in walk(body):
                if isinstance(node, Stream) and var in node.term.args:
                    raise self.fail(
                        f"foreach's variable {var!r} stands in the args of {node.term}",
                        "foreach's variable names an object of its stream, as a value (t == \"bob\"); forall's stand in terms' args",
                        column=self.column_of(node),
                    )
        elif not any(isinstance(node, Var) and node.name == var or isinstance(node, Stream) and var in node.term.args for node in walk(body)):
            raise self.fail(
                f"the variable {var!r} is not used in the formula",
                f"a term such as Fresh({var}) that it stands in, or {var} as a value",
                column=at,
            )
        return self.made(Quantifier(kind, var, domain, body), at)

    def disjunction(self, depth: int) -> Node:
        node = self.conjunction(depth)
        self.skip()
        at = self.pos
        while self.keyword("or"):
            node = self.made(Or(self.condition(node), self.condition(self.conjunction(depth + 1))), at)
            self.skip()
            at = self.pos
        return node

    def conjunction(self, depth: int) -> Node:
        node = self.binary(depth)
        self.skip()
        at = self.pos
        while self.keyword("and"):
            node = self.made(And(self.condition(node), self.condition(self.binary(depth + 1))), at)
            self.skip()
            at = self.pos
        return node

    def binary(self, depth: int) -> Node:
        left = self.unary(depth)
        self.skip()
        at = self.pos
        op = self.keyword("until", "since")
        if op is None:
            return left
        interval = self.interval(op, future=op == "until")
        right = self.unary(depth + 1)
        self.skip()
        if self.word() in ("until", "since"):
            raise self.fail(
                f"'{self.word()}' right after '{op}'", "parentheses around one of them: (p until[..] q) until[..] r", column=self.pos
            )
        left, right = self.condition(left), self.condition(right)
        return self.made(Until(left, right, interval) if op == "until" else Since(left, right, interval), at)

    def unary(self, depth: int) -> Node:
        self.deep(depth)
        self.skip()
        if self.at_end():
            raise self.fail("unexpected end of formula", _FORMULA_START)
        chunk = self.word()
        at = self.pos
        if chunk == "not":
            self.pos += 3
            return self.made(Not(self.condition(self.unary(depth + 1))), at)
        if chunk in _UNARY_TEMPORAL:
            self.pos += len(chunk)
            interval = self.interval(chunk, future=chunk in ("always", "eventually"))
            return self.made(_UNARY_TEMPORAL[chunk](interval, self.condition(self.unary(depth + 1))), at)
        if chunk in ("forall", "exists", "foreach"):
            raise self.fail(f"'{chunk}' inside an operator", f"parentheses around the quantified formula: ({chunk} ... : ...)")
        if chunk and self.after_word(chunk) == "[" and chunk not in AGGREGATES and chunk not in _KEYWORDS:
            operators = [*_UNARY_TEMPORAL, "until", "since", *AGGREGATES]
            raise self.fail(f"'{chunk}' is not a temporal operator", "one of " + ", ".join(operators) + did_you_mean(chunk, operators))
        return self.comparison(depth)

    # -- the grammar: values

    def comparison(self, depth: int) -> Node:
        left = self.sum(depth)
        self.skip()
        at = self.pos
        match = _OPERATOR.match(self.text, self.pos)
        if match is None:
            if self.pos < len(self.text) and self.text[self.pos] in _HINT_OPERATORS:
                raise self.fail(f"unexpected {_quote(self.text[self.pos])}", _HINT_OPERATORS[self.text[self.pos]])
            return left
        op = match.group()
        self.pos = match.end()
        right = self.sum(depth + 1)
        self.skip()
        if _OPERATOR.match(self.text, self.pos):
            raise self.fail(
                f"a second comparison right after '{op}'", "one comparison per atom: (a < b) and (b < c)", column=self.pos
            )
        self.past(left, f"'{op}'")
        self.past(right, f"'{op}'")
        lk, rk = self.kind(left), self.kind(right)
        if op in ("==", "!="):
            if ANY not in (lk, rk) and lk != rk:
                raise self.fail(
                    f"{_quote(str(left))} is a {lk} and {_quote(str(right))} a {rk}: they are never equal",
                    "two values of one kind: numbers, strings, or conditions (true/false)",
                    column=at,
                )
        else:
            left = self.value(left, NUM, f"'{op}'")
            right = self.value(right, NUM, f"'{op}'")
        return self.made(Atom(left, op, right), at)

    def sum(self, depth: int) -> Node:
        node = self.product(depth)
        while True:
            self.skip()
            at = self.pos
            if self.text.startswith("+", at) or self.text.startswith("-", at):
                op = self.text[at]
                self.pos += 1
                right = self.product(depth + 1)
                node = self.made(Arith(op, self.value(node, NUM, f"'{op}'"), self.value(right, NUM, f"'{op}'")), at)
            else:
                return node

    def product(self, depth: int) -> Node:
        node = self.prefix(depth)
        while True:
            self.skip()
            at = self.pos
            if self.text.startswith("*", at) or self.text.startswith("/", at):
                op = self.text[at]
                self.pos += 1
                right = self.prefix(depth + 1)
                node = self.made(Arith(op, self.value(node, NUM, f"'{op}'"), self.value(right, NUM, f"'{op}'")), at)
            else:
                return node

    def prefix(self, depth: int) -> Node:
        self.deep(depth)
        self.skip()
        at = self.pos
        if self.text.startswith("-", at):
            self.pos += 1
            self.skip()
            number = _NUMBER.match(self.text, self.pos)
            if number is not None and (number.end() == len(self.text) or self.text[number.end()] in _DELIMITERS):
                self.pos = number.end()
                return self.made(Num(-_number(number.group())), at)  # a negative literal, as written
            arg = self.prefix(depth + 1)
            return self.made(Neg(self.value(arg, NUM, "'-'")), at)
        chunk = self.word()
        if chunk in AGGREGATES and self.after_word(chunk) == "[":
            self.pos += len(chunk)
            interval = self.interval(chunk, future=False)
            arg = self.prefix(depth + 1)
            if chunk == "count":
                arg = self.condition(arg, where=", and count counts the states where a condition is true")
            else:
                arg = self.value(arg, NUM, chunk)
            self.past(arg, chunk)
            return self.made(Aggregate(chunk, interval, arg), at)
        return self.primary(depth)

    def primary(self, depth: int) -> Node:
        self.skip()
        at = self.pos
        if self.at_end():
            raise self.fail("unexpected end of formula", _VALUE_START)
        text = self.text
        if self.char("("):
            inner = self.formula(depth + 1)
            if not self.char(")"):
                raise self.unexpected("')' closing the '(' before")
            return inner
        if text[at] in "\"'":
            return self.made(Str(self.string()), at)
        number = _NUMBER.match(text, at)
        if number is not None:
            end = number.end()
            if end < len(text) and text[end] not in _DELIMITERS:
                raise self.fail(f"{_quote(text[at:end + 1])} is neither a number nor a stream", _VALUE_START)
            self.pos = end
            return self.made(Num(_number(number.group())), at)
        chunk = self.word()
        if chunk in ("true", "false"):
            self.pos += len(chunk)
            return self.made(Const(chunk == "true"), at)
        if chunk in FUNCTIONS and self.after_word(chunk) == "(":
            return self.function(chunk, depth, at)
        if chunk in self.variables and not text.startswith("(", self.pos + len(chunk)):
            self.pos += len(chunk)
            if self.text.startswith(".", self.pos):
                raise self.fail(f"a field of the variable {chunk!r}", f"the variable alone: {chunk} is a value", column=self.pos)
            return self.made(Var(chunk), at)
        if chunk in _KEYWORDS:
            raise self.fail(f"unexpected keyword '{chunk}'", _VALUE_START if chunk not in ("not", "always") else _FORMULA_START)
        return self.made(self.stream(), at)

    def function(self, fn: str, depth: int, at: int) -> Node:
        self.pos += len(fn)
        self.char("(")
        args = [self.formula(depth + 1)]
        while self.char(","):
            args.append(self.formula(depth + 1))
        if not self.char(")"):
            raise self.unexpected(f"')' closing {fn}(...)" + (" or ',' before its second operand" if fn in ("min", "max") else ""))
        arity = 2 if fn in ("min", "max") else 1
        if len(args) != arity:
            raise self.fail(f"{fn} of {len(args)} operand{'s' if len(args) != 1 else ''}", f"{fn} of {arity}: {fn}(x{', y' if arity == 2 else ''})", column=at)
        if fn in ("rise", "fall"):
            arg = self.condition(args[0])
            self.past(arg, fn)
            return self.made(Rise(arg) if fn == "rise" else Fall(arg), at)
        if fn == "prev":
            arg = args[0]
            if self.kind(arg) == BOOL:
                arg = self.condition(arg)
            self.past(arg, fn)
            return self.made(Prev(arg), at)
        if fn == "robustness":
            arg = self.condition(args[0])
            self.past(arg, fn)
            return self.made(Call(fn, (arg,)), at)
        checked = tuple(self.value(arg, NUM, fn) for arg in args)
        return self.made(Call(fn, checked), at)

    def string(self) -> str:
        quote = self.text[self.pos]
        at = self.pos
        self.pos += 1
        out: list[str] = []
        while self.pos < len(self.text):
            char = self.text[self.pos]
            if char == "\\" and self.pos + 1 < len(self.text) and self.text[self.pos + 1] in "\\\"'":
                out.append(self.text[self.pos + 1])
                self.pos += 2
                continue
            if char == quote:
                self.pos += 1
                return "".join(out)
            out.append(char)
            self.pos += 1
        raise self.fail(f"the string opened by {quote} is never closed", f"a closing {quote}", column=at)

    def interval(self, op: str, *, future: bool) -> Interval:
        if not self.char("["):
            raise self.unexpected(f"'[' after '{op}': an interval such as {op}[0, 2s]")
        self.skip()
        lo_at = self.pos
        lo = self.duration(op, allow_inf=False)
        if not self.char(","):
            raise self.unexpected("',' between the two bounds of the interval, as in [0, 2s]")
        hi = self.duration(op, allow_inf=not future)
        if not self.char("]"):
            raise self.unexpected("']' closing the interval, as in [0, 2s]")
        assert lo is not None  # allow_inf=False
        if hi is not None and hi < lo:
            raise self.fail(
                f"the interval's lower bound {_duration_text(lo)} is above its upper bound {_duration_text(hi)}",
                "[a, b] with a <= b",
                column=lo_at,
            )
        longest = self.max_window_ns
        if longest is not None and max(lo, hi or 0) > longest:
            opened = self.text.rfind("[", 0, lo_at)
            raise self.fail(
                f"{_quote(op + self.text[opened : self.pos])} has the bound {_duration_text(max(lo, hi or 0))}, beyond the longest window",
                f"bounds of at most {_duration_text(longest)} (Limits.max_window_ns)"
                + ("" if future else "; a past window may write inf for no upper bound"),
                column=opened,
            )
        return Interval(lo, hi)

    def duration(self, op: str, *, allow_inf: bool) -> int | None:
        self.skip()
        at = self.pos
        if self.word() == "inf":
            if not allow_inf:
                if self.text.startswith(",", _SPACE.match(self.text, at + 3).end()):  # type: ignore[union-attr]
                    raise self.fail("'inf' as a lower bound", "a finite lower bound such as 0 or 500ms")
                raise self.fail(
                    f"'inf' as the upper bound of the future operator '{op}'",
                    "a finite upper bound such as 2s (only past windows, historically, once, since and the aggregates, take inf)",
                )
            self.pos += 3
            return None
        match = _DURATION.match(self.text, at)
        if match is None:
            raise self.unexpected("a duration: a number with s or ms such as 500ms or 2s, or 0" + (", or inf" if allow_inf else ""))
        digits, unit = match.group(1), match.group(2)
        if unit is None:
            try:
                zero = Decimal(digits) == 0
            except InvalidOperation:  # pragma: no cover - the pattern only matches decimals
                zero = False
            if not zero:
                raise self.fail(
                    f"the duration {digits} has no unit", f"{digits}s or {digits}ms (only 0 may be written without a unit)", column=at
                )
        scale = 1_000_000 if unit == "ms" else _NS_PER_S
        ns = Decimal(digits) * scale
        if ns != ns.to_integral_value():
            raise self.fail(f"the duration {match.group()} is finer than a nanosecond", "a whole number of nanoseconds", column=at)
        self.pos = match.end()
        return int(ns)

    def stream(self) -> Stream:
        self.skip()
        term = self.term()
        fields: list[str] = []
        while self.text.startswith(".", self.pos):
            self.pos += 1
            match = _FIELD.match(self.text, self.pos)
            if match is None:
                raise self.unexpected(f"a field name after '.' (letters, digits and '_', as in {term}.speed)")
            fields.append(match.group())
            self.pos = match.end()
        return Stream(term, tuple(fields))

    def term(self) -> Term:
        start = self.pos
        text = self.text
        if text.startswith("`", start):
            end = text.find("`", start + 1)
            if end < 0:
                raise self.fail("'`' is never closed", "a term in backquotes: `cam.left`")
            self.pos = end + 1
            return self.tag(text[start + 1 : end], start + 1)
        if text.startswith("<", start):  # a full IRI as the functor
            end = text.find(">", start)
            if end < 0:
                raise self.fail("'<' opens an IRI that is never closed", "a term such as <http://example.org/Battery>(robot)")
            end += 1
        else:
            end = start
            while end < len(text) and text[end] not in _DELIMITERS:
                end += 1
            if end > start + 1 and text[end - 1] == ":" and (end == len(text) or text[end].isspace()):
                end -= 1  # a quantifier's colon, not a prefix's (dk:Battery)
            if end == start:
                raise self.unexpected(_VALUE_START)
        after = _SPACE.match(text, end).end()  # type: ignore[union-attr]
        if text.startswith("(", after):
            close = text.find(")", after)
            if close < 0:
                raise self.fail("unbalanced parenthesis: '(' is never closed", "')' closing the term's args", column=after)
            end = close + 1
        self.pos = end
        return self.tag(text[start:end], start)

    def tag(self, tag: str, column: int) -> Term:
        try:
            return parse_term(tag)
        except TagError as exc:
            hint = did_you_mean(tag, _KEYWORDS)
            raise self.fail(
                f"term {_quote(tag)} is not a tag: {exc.what}", (exc.expected or "a tag such as Battery(robot)") + hint, column=column
            ) from exc


def _number(text: str) -> int | float:
    """A literal's value: an ``int`` when it is written whole (no point, no exponent)."""
    if "." in text or "e" in text or "E" in text:
        value = float(text)
        if value != value or value in (float("inf"), float("-inf")):
            raise FormulaError(f"the number {text} is not finite", where="formula", expected="a finite number")
        return value
    return int(text)


def _quote(text: str) -> str:
    return "'" + text.replace("'", "\\'") + "'" if len(text) <= 60 else "'" + text[:57].replace("'", "\\'") + "...'"
