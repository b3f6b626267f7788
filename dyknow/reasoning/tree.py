"""A formula's syntax tree: its nodes, and how a tree is walked, written back and compared.

The nodes are frozen dataclasses: the leaves (:class:`Num`, :class:`Str`, :class:`Const`,
:class:`Stream`, :class:`Var`) and the operators, which are written (``str``), compared, hashed
and shown (``repr``) without recursing in Python, so no tree that parses can exhaust the stack.
``str(node)`` writes the formula with only the parentheses it needs. The language these trees
are read from is stated in :mod:`dyknow.reasoning.syntax`; :mod:`dyknow.reasoning.parser` builds
them from text.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, fields
from decimal import Decimal

from dyknow.tags import Term

__all__ = [
    "AGGREGATES",
    "ANY",
    "ARITHMETIC",
    "BOOL",
    "FAMILY_ARG",
    "COMPARISONS",
    "FUNCTIONS",
    "FUTURE",
    "KEYWORDS",
    "LEAVES",
    "NUM",
    "RESERVED",
    "STR",
    "Aggregate",
    "Always",
    "And",
    "Arith",
    "Atom",
    "Call",
    "Index",
    "Const",
    "Eventually",
    "Fall",
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
    "children",
    "duration_text",
    "family_term",
    "is_family",
    "member_arg",
    "member_term",
    "kind_of",
    "raw_reads",
    "walk",
]

COMPARISONS: tuple[str, ...] = ("<", "<=", ">", ">=", "==", "!=")
"""The comparison operators."""

ARITHMETIC: tuple[str, ...] = ("+", "-", "*", "/")
"""The arithmetic operators."""

AGGREGATES: tuple[str, ...] = ("count", "sum", "avg", "min", "max", "integral", "rate")
"""The aggregates of a past window."""

FUNCTIONS: tuple[str, ...] = ("abs", "min", "max", "sqrt", "hypot", "pow", "dist", "prev", "rise", "fall", "robustness")
"""The functions written with their operands in parentheses."""

ARITY: dict[str, int] = {"abs": 1, "min": 2, "max": 2, "sqrt": 1, "hypot": 2, "pow": 2, "dist": 2, "prev": 1, "rise": 1, "fall": 1, "robustness": 1}
"""How many operands each function takes."""

KEYWORDS: frozenset[str] = frozenset(
    {
        "not", "and", "or", "implies", "always", "eventually", "historically", "once", "until", "since",
        "true", "false", "inf", "forall", "exists", "foreach", "in",
    }
)  # fmt: skip
"""The keywords of the language."""

RESERVED = KEYWORDS | frozenset(AGGREGATES) | frozenset(FUNCTIONS)  # spelled like these, a tag is backquoted
"""The words a tag spelled like is written in backquotes (```in`.x``): the keywords, and the
words of aggregates and functions."""

_NS_PER_S = 1_000_000_000
_FIELD_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")  # a key written as a field: .speed


def duration_text(ns: int) -> str:
    """A duration in nanoseconds as a formula writes it: ``0``, ``500ms``, ``1500ms``, ``2s``."""
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
        hi = "inf" if self.hi_ns is None else duration_text(self.hi_ns)
        return f"[{duration_text(self.lo_ns)}, {hi}]"


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
        if not functor.startswith("<") and ("." in functor or functor in RESERVED):
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
    """``abs(x)``, ``min(x, y)``, ``max(x, y)``, ``sqrt(x)``, ``hypot(x, y)``, ``pow(x, y)``,
    ``dist(p, q)`` and ``robustness(F)``."""

    fn: str
    args: tuple[Node, ...]


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class Index(_Operator):
    """A lookup: ``stream[key]``, a value of the stream's JSON object (or array) by a key computed
    at each state, ``Limits(floor)[State(r).zone]``. ``keys`` go down one level each; a field
    written after a key (``Limits(floor)[State(r).zone].speed``) is the key ``Str("speed")``."""

    stream: Stream
    keys: tuple[Node, ...]
    #: a **parameterized term** when 0 or more (``SpeedLimit(State(r).zone)``): the position of
    #: the argument computed at each state, ``keys[0]``; ``stream`` is then the term's family
    #: (:func:`family_term`: ``SpeedLimit(*)``), whose value is an object of each member's latest
    #: value by its argument, so the term is a lookup into it (:mod:`dyknow.reasoning.semantics`)
    param: int = -1


FAMILY_ARG = "*"
"""The argument a family term has in place of a parameterized term's computed one: ``SpeedLimit(*)``."""


def family_term(functor: str, args: tuple[str, ...]) -> Term:
    """The family of a parameterized term: ``functor`` with ``args``, one of them :data:`FAMILY_ARG`
    (no tag can be written so: only a formula's parser makes one). Its members are the terms with
    a name in that place (``SpeedLimit(z1)``, :func:`member_arg`)."""
    term = object.__new__(Term)
    object.__setattr__(term, "functor", functor)
    object.__setattr__(term, "args", args)
    return term


def is_family(term: Term) -> bool:
    """Whether ``term`` is a parameterized term's family (:func:`family_term`)."""
    return FAMILY_ARG in term.args


def member_arg(family: Term, term: Term) -> str | None:
    """The argument that makes ``term`` a member of ``family`` (``z1`` for ``SpeedLimit(z1)`` of
    ``SpeedLimit(*)``); None when it is none of its members."""
    if term.functor != family.functor or len(term.args) != len(family.args):
        return None
    found = None
    for mine, theirs in zip(family.args, term.args, strict=True):
        if mine == FAMILY_ARG:
            found = theirs
        elif mine != theirs:
            return None
    return found


def member_term(family: Term, arg: str) -> Term:
    """The member of ``family`` whose argument is ``arg`` (a name: :class:`~dyknow.errors.TagError` otherwise)."""
    return Term(family.functor, tuple(arg if a == FAMILY_ARG else a for a in family.args))


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
    | Atom | Neg | Arith | Call | Index | Prev | Rise | Fall | Aggregate
    | Not | And | Or | Implies | Always | Eventually | Historically | Once | Until | Since | Quantifier
)  # fmt: skip
"""A node of a formula's syntax tree: a value (constants, streams, variables, expressions) or a
condition (atoms, connectives, temporal operators, rise/fall, quantifiers)."""

LEAVES = (Num, Str, Const, Stream, Var)
"""The nodes without operands: constants, streams and variables."""

FUTURE = (Always, Eventually, Until)
"""The future temporal operators: their verdicts wait for later states."""

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
    if isinstance(node, LEAVES):
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
    if isinstance(node, Index):
        looked: list[_Piece] = [(node.stream, _PRIMARY)]
        if node.param >= 0:  # SpeedLimit(State(r).zone): the family's args, the computed one in its place
            looked = [f"{node.stream.term.functor}("]
            for k, name in enumerate(node.stream.term.args):
                looked.append(", " if k else "")
                looked.append((node.keys[0], _QUANT) if name == FAMILY_ARG else name)
            looked.append(")")
        for k, key in enumerate(node.keys):
            if node.param >= 0 and k == 0:
                continue
            if k and isinstance(key, Str) and _FIELD_NAME.fullmatch(key.value):
                looked.append("." + key.value)
            else:
                looked.extend(["[", (key, _QUANT), "]"])
        return looked
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
    if isinstance(node, LEAVES):
        return node
    if isinstance(node, Atom):
        return node.op
    if isinstance(node, Arith):
        return node.op
    if isinstance(node, Call):
        return (node.fn, len(node.args))
    if isinstance(node, Index):
        return (len(node.keys), node.param)
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
        if isinstance(item, LEAVES):
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
    if isinstance(node, LEAVES):
        return ()
    if isinstance(node, Atom):
        return (node.left,) if node.right is None else (node.left, node.right)
    if isinstance(node, And | Or | Implies | Until | Since | Arith):
        return (node.left, node.right)
    if isinstance(node, Call):
        return node.args
    if isinstance(node, Index):
        return (node.stream, *node.keys)
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


_OPERATOR_TYPES = (Atom, Neg, Arith, Call, Index, Prev, Rise, Fall, Aggregate, Not, And, Or, Implies, Always, Eventually, Historically, Once, Until, Since, Quantifier, *LEAVES)


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
    if isinstance(node, Stream | Var | Index):
        return ANY
    if isinstance(node, Prev):
        return kind_of(node.arg)
    return BOOL


def raw_reads(root: Node) -> set[int]:
    """The ids of the nodes below ``root`` read as they are, objects and arrays too (not only
    numbers, strings and booleans): the stream a lookup looks into, the lookups a lookup goes on
    from, and the points of ``dist``."""
    found: set[int] = set()
    for node in walk(root):
        if isinstance(node, Index):
            found.add(id(node.stream))
        elif isinstance(node, Call) and node.fn == "dist":
            found.update(id(arg) for arg in node.args if isinstance(arg, Stream | Index))
    return found
