"""The language of temporal formulas: its syntax tree and its parser.

A formula is text::

    historically[0, 2s] (Battery(robot) > 0.2)
    BallTrack(field).speed < 3 since[0, inf] not Stalled(robot)
    Obstacle(front) implies eventually[0, 500ms] Braking(robot)

Grammar (keywords are lowercase and reserved; whitespace is free)::

    formula   := or ['implies' formula]                 right-associative
    or        := and {'or' and}
    and       := binary {'and' binary}
    binary    := unary [('until' | 'since') interval unary]   not chained: parenthesise
    unary     := 'not' unary
               | ('always' | 'eventually' | 'historically' | 'once') interval unary
               | '(' formula ')' | 'true' | 'false' | atom
    atom      := stream [OP NUMBER]                     OP: < <= > >= == !=
    stream    := TERM {'.' FIELD}                       Battery(robot), BallTrack(field).speed
    interval  := '[' duration ',' duration ']'          a <= b
    duration  := NUMBER ('s' | 'ms') | '0' | 'inf'      inf: upper bound of past operators only

So unary operators bind tightest, then ``until``/``since``, ``and``, ``or`` and ``implies``:
``always[0, 1s] p and q`` is ``(always[0, 1s] p) and q``.

- **Terms** are semantic tags as specs write them (:mod:`dyknow.tags` reads them: ``parse_term``),
  so ``Battery(robot)``, ``dk:Battery(robot)`` and ``<http://x/Battery>(robot)`` all work. A ``.``
  after a term starts a field path into a JSON object payload: ``BallTrack(field).speed``,
  ``Pose(robot).position.x``; for a term without args the name ends at the first ``.``
  (``Ticks.count`` is the field ``count`` of ``Ticks``). A tag whose name itself holds a dot is
  written in backquotes: ```cam.left`.exposure > 3``.
- **Atoms** compare a stream with a number (``TERM OP NUMBER``), or are a bare stream of boolean
  value (``Stalled(robot)``, ``Door(hall).open``). What an atom is on a value that is not a number
  (or not a boolean) is stated in :mod:`dyknow.reasoning.semantics`.
- **Durations** are integer nanoseconds once parsed (``1.5s`` is 1_500_000_000; a duration finer
  than a nanosecond is refused). Future operators (``always``, ``eventually``, ``until``) need a
  finite upper bound; past ones (``historically``, ``once``, ``since``) may write ``inf``.

A formula's text is bounded (:data:`MAX_FORMULA_CHARS` characters, :data:`MAX_DEPTH` levels of
nesting), because formulas reach a manager over the network as unit params; a chain ``p or q or
...`` (or ``and``) is read in a loop and counts as one level however long it is. Nothing that
walks a formula (writing it, comparing, hashing, evaluating, monitoring) recurses in Python, so
no depth that parses can exhaust the stack. :func:`check_formula` holds a formula to a manager's
:class:`~dyknow.security.Limits` as well: at most ``max_formula_nodes`` nodes (500), interval
bounds and a future horizon of at most ``max_window_ns`` (one day); a manager checks every
formula so before it requests or spawns anything for it.

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
    "COMPARISONS",
    "MAX_DEPTH",
    "MAX_FORMULA_CHARS",
    "Always",
    "And",
    "Atom",
    "Const",
    "Eventually",
    "Formula",
    "Historically",
    "Implies",
    "Interval",
    "Node",
    "Not",
    "Once",
    "Or",
    "Since",
    "Until",
    "check_formula",
    "children",
    "parse",
]

COMPARISONS: tuple[str, ...] = ("<", "<=", ">", ">=", "==", "!=")
"""The comparison operators of atoms."""

MAX_FORMULA_CHARS: int = 10_000
"""The longest formula text :func:`parse` reads."""

MAX_DEPTH: int = 64
"""The deepest nesting of operators and parentheses :func:`parse` reads (``not``, temporal
operators, ``implies``, which groups to the right, and parentheses; a chain ``p or q or ...``
is one level however long: it is read in a loop)."""

_NS_PER_S = 1_000_000_000


def _duration_text(ns: int) -> str:
    if ns == 0:
        return "0"
    if ns % 1_000_000 == 0 and ns % _NS_PER_S != 0:
        return f"{ns // 1_000_000}ms"
    text = format(Decimal(ns) / _NS_PER_S, "f")
    return (text.rstrip("0").rstrip(".") if "." in text else text) + "s"


@dataclass(frozen=True, slots=True)
class Interval:
    """A metric interval ``[a, b]`` in integer nanoseconds; ``hi_ns`` None is ``inf``."""

    lo_ns: int
    hi_ns: int | None

    def __str__(self) -> str:
        hi = "inf" if self.hi_ns is None else _duration_text(self.hi_ns)
        return f"[{_duration_text(self.lo_ns)}, {hi}]"


@dataclass(frozen=True, slots=True)
class Atom:
    """``stream OP number``, or a boolean stream when ``op`` is None.

    ``term`` is the stream's tag; ``fields`` the path into a JSON object payload (empty: the
    payload itself).
    """

    term: Term
    fields: tuple[str, ...] = ()
    op: str | None = None
    number: float | None = None

    @property
    def stream(self) -> str:
        """The stream as written: ``Battery(robot)`` or ``BallTrack(field).speed``.

        A tag the formula syntax would misread (a dot in its functor, a keyword) is backquoted.
        """
        name = str(self.term)
        functor = self.term.functor
        if not functor.startswith("<") and ("." in functor or functor in _KEYWORDS):
            name = f"`{name}`"
        return name + "".join(f".{f}" for f in self.fields)

    def __str__(self) -> str:
        if self.op is None:
            return self.stream
        return f"{self.stream} {self.op} {_number_text(self.number)}"


@dataclass(frozen=True, slots=True)
class Const:
    """``true`` or ``false``."""

    value: bool

    def __str__(self) -> str:
        return "true" if self.value else "false"


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


Node = Atom | Const | Not | And | Or | Implies | Always | Eventually | Historically | Once | Until | Since
"""A node of a formula's syntax tree."""

_N = TypeVar("_N", bound=Node)

_FUTURE = (Always, Eventually, Until)

# binding strength, loosest first: what a child must reach to be written without parentheses
_IMPLIES, _OR, _AND, _BINARY, _UNARY = 1, 2, 3, 4, 5


def _level(node: Node) -> int:
    if isinstance(node, Implies):
        return _IMPLIES
    if isinstance(node, Or):
        return _OR
    if isinstance(node, And):
        return _AND
    if isinstance(node, Until | Since):
        return _BINARY
    return _UNARY


_Piece = str | tuple[Node, int]  # text as is, or a node written at least at a binding strength


def _pieces(node: Node) -> list[_Piece]:
    """How ``node`` is written: its own text around its operands, each with the binding strength
    it must reach to go without parentheses."""
    if isinstance(node, Atom | Const):
        return [str(node)]
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
    if isinstance(node, Atom | Const):
        return node
    if isinstance(node, Not | And | Or | Implies):
        return None
    return node.interval


def _same(a: Node, b: Node) -> bool:
    """Whether two trees are equal, node by node (iteratively)."""
    stack = [(a, b)]
    while stack:
        x, y = stack.pop()
        if x is y:
            continue
        if type(x) is not type(y) or _own(x) != _own(y):
            return False
        stack.extend(zip(children(x), children(y), strict=True))
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
        if isinstance(item, Atom | Const):
            out.append(repr(item))
            continue
        names = [f.name for f in fields(item)]
        pieces: list[str | Node] = [f"{type(item).__name__}("]
        for k, name in enumerate(names):
            value = getattr(item, name)
            pieces.append(("" if k == 0 else ", ") + f"{name}=")
            pieces.append(repr(value) if isinstance(value, Interval) else value)
        pieces.append(")")
        stack.extend(reversed(pieces))
    return "".join(out)


def _number_text(number: float | None) -> str:
    if number is None:
        return "?"
    return str(int(number)) if number.is_integer() and abs(number) < 1e15 else repr(number)


def children(node: Node) -> tuple[Node, ...]:
    """A node's operands, left to right (none for atoms and constants)."""
    if isinstance(node, Atom | Const):
        return ()
    if isinstance(node, And | Or | Implies | Until | Since):
        return (node.left, node.right)
    return (node.arg,)


def _walk(root: Node) -> list[Node]:
    """Every node, parents before children (iteratively: formulas may be deep)."""
    out: list[Node] = []
    stack = [root]
    while stack:
        node = stack.pop()
        out.append(node)
        stack.extend(reversed(children(node)))
    return out


@dataclass(frozen=True, slots=True)
class Formula:
    """A parsed formula: the text as written, its syntax tree and the terms it mentions.

    ``terms`` are the distinct streams' tags in order of first appearance (atoms on different
    fields of one term share it); :func:`parse` and :meth:`Formula.of` fill them in, so build a
    formula with one of those. ``str(formula)`` is the canonical text.
    """

    text: str
    root: Node
    terms: tuple[Term, ...] = field(default=())

    def __str__(self) -> str:
        return str(self.root)

    @property
    def past_only(self) -> bool:
        """Whether no future operator occurs: every state's verdict is decided at that state."""
        return not any(isinstance(node, _FUTURE) for node in _walk(self.root))

    @property
    def horizon_ns(self) -> int:
        """How far into the future a verdict may need to look: the largest sum of future upper
        bounds along a path from the root (0 for a past-only formula)."""
        return _future_horizon(self.root)

    @property
    def nodes(self) -> int:
        """How many nodes the syntax tree has: atoms, constants and operators."""
        return len(_walk(self.root))

    @property
    def operators(self) -> int:
        """How many operators (connectives and temporal operators, not atoms) the formula has."""
        return sum(1 for node in _walk(self.root) if not isinstance(node, Atom | Const))

    @classmethod
    def of(cls, root: Node, text: str | None = None) -> Formula:
        """A formula from a syntax tree built in code (its terms collected, its text written)."""
        terms: dict[Term, None] = {}
        for node in _walk(root):
            if isinstance(node, Atom):
                terms.setdefault(node.term, None)
        return cls(str(root) if text is None else text, root, tuple(terms))


def _future_horizon(root: Node) -> int:
    memo: dict[int, int] = {}
    for node in reversed(_walk(root)):  # children before parents
        below = max((memo[id(child)] for child in children(node)), default=0)
        own = 0
        if isinstance(node, _FUTURE):
            own = node.interval.hi_ns or 0
        memo[id(node)] = below + own
    return memo[id(root)]


# -- the parser

_KEYWORDS = frozenset(
    {"not", "and", "or", "implies", "always", "eventually", "historically", "once", "until", "since", "true", "false", "inf"}
)
_UNARY_TEMPORAL: dict[str, type[Always | Eventually | Historically | Once]] = {
    "always": Always,
    "eventually": Eventually,
    "historically": Historically,
    "once": Once,
}
_DELIMITERS = frozenset(" \t\r\n\f\v()[],<>=!.`")
_SPACE = re.compile(r"\s*")
_NUMBER = re.compile(r"-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_DURATION = re.compile(r"([0-9]+(?:\.[0-9]+)?)(ms|s)?(?![A-Za-z0-9_.])")
_FIELD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_OPERATOR = re.compile(r"<=|>=|==|!=|<|>")
_HINT_OPERATORS = {"=": "== (equality is written ==)", "!": "!= (inequality is written !=)"}
_FORMULA_START = "a formula: an atom such as Battery(robot) > 0.2, 'not', a temporal operator, '(' or true/false"


def parse(text: str) -> Formula:
    """Parse a formula; raises :class:`~dyknow.errors.FormulaError` naming the column and what was expected.

    Only the language's own bounds apply (:data:`MAX_FORMULA_CHARS`, :data:`MAX_DEPTH`); a
    formula from a caller the process does not trust goes through :func:`check_formula`.

    >>> str(parse("historically[0,2s](Battery(robot)>0.2)"))
    'historically[0, 2s] Battery(robot) > 0.2'
    """
    return _parse(text, None, None)


def check_formula(formula: str | Formula, limits: Limits | None = None) -> Formula:
    """Parse ``formula`` and hold it to ``limits`` (:class:`~dyknow.security.Limits`; its
    defaults when None): what a manager does with every formula before it requests or spawns
    anything for it. A :class:`Formula` is checked by its text.

    Besides the language's bounds (:func:`parse`), the formula may have at most
    ``limits.max_formula_nodes`` nodes (atoms, constants and operators), no interval bound beyond
    ``limits.max_window_ns`` (a past operator may still write ``inf``), and may look at most that
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


def _parse(text: str, max_nodes: int | None, max_window_ns: int | None) -> Formula:
    if not isinstance(text, str):
        raise FormulaError(f"a formula is text, got {type(text).__name__}", where="formula", expected="a str such as 'once[0, 1s] p'")
    if len(text) > MAX_FORMULA_CHARS:
        raise FormulaError(
            f"the formula has {len(text)} characters", where="formula", expected=f"at most {MAX_FORMULA_CHARS}", formula=text[:80] + "..."
        )
    parser = _Parser(text, max_nodes, max_window_ns)
    try:
        root = parser.formula(0)
    except RecursionError:  # a caller already deep in its stack: MAX_DEPTH levels did not fit
        raise parser.fail(
            "the formula nests deeper than this thread's stack allows", f"fewer levels of operators and parentheses (at most {MAX_DEPTH})"
        ) from None
    parser.skip()
    if not parser.at_end():
        hint = did_you_mean(parser.word(), ["and", "or", "implies", "until", "since"])
        raise parser.unexpected("the end of the formula, 'and', 'or', 'implies', 'until' or 'since'" + hint)
    return Formula.of(root, text)


class _Parser:
    """A recursive-descent reader over the text that says where and why it is malformed."""

    def __init__(self, text: str, max_nodes: int | None = None, max_window_ns: int | None = None) -> None:
        self.text = text
        self.pos = 0
        self.max_nodes = max_nodes
        self.max_window_ns = max_window_ns
        self.nodes = 0
        self.ahead: dict[int, int] = {}  # id(node) -> its future horizon, where not 0 (bounded windows only)

    def made(self, node: _N, column: int) -> _N:
        """Count a node built from the text at ``column``; refuse it past the bounds."""
        self.nodes += 1
        if self.max_nodes is not None and self.nodes > self.max_nodes:
            raise self.fail(
                f"the formula has more than {self.max_nodes} nodes",
                f"at most {self.max_nodes} atoms, constants and operators (Limits.max_formula_nodes)",
                column=column,
            )
        if self.max_window_ns is not None:
            below = max((self.ahead.get(id(kid), 0) for kid in children(node)), default=0)
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
            self.pos += 1
            return True
        return False

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

    # -- the grammar

    def formula(self, depth: int) -> Node:
        if depth > MAX_DEPTH:
            raise self.fail(f"the formula nests deeper than {MAX_DEPTH} levels", f"at most {MAX_DEPTH} levels of operators and parentheses")
        left = self.disjunction(depth)
        self.skip()
        at = self.pos
        if self.keyword("implies"):
            return self.made(Implies(left, self.formula(depth + 1)), at)
        return left

    def disjunction(self, depth: int) -> Node:
        node = self.conjunction(depth)
        self.skip()
        at = self.pos
        while self.keyword("or"):
            node = self.made(Or(node, self.conjunction(depth + 1)), at)
            self.skip()
            at = self.pos
        return node

    def conjunction(self, depth: int) -> Node:
        node = self.binary(depth)
        self.skip()
        at = self.pos
        while self.keyword("and"):
            node = self.made(And(node, self.binary(depth + 1)), at)
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
        return self.made(Until(left, right, interval) if op == "until" else Since(left, right, interval), at)

    def unary(self, depth: int) -> Node:
        if depth > MAX_DEPTH:
            raise self.fail(f"the formula nests deeper than {MAX_DEPTH} levels", f"at most {MAX_DEPTH} levels of operators and parentheses")
        self.skip()
        if self.at_end():
            raise self.fail("unexpected end of formula", _FORMULA_START)
        if self.char("("):
            inner = self.formula(depth + 1)
            if not self.char(")"):
                raise self.unexpected("')' closing the '(' before")
            return inner
        chunk = self.word()
        at = self.pos
        if chunk == "not":
            self.pos += 3
            return self.made(Not(self.unary(depth + 1)), at)
        if chunk in _UNARY_TEMPORAL:
            self.pos += len(chunk)
            interval = self.interval(chunk, future=chunk in ("always", "eventually"))
            return self.made(_UNARY_TEMPORAL[chunk](interval, self.unary(depth + 1)), at)
        if chunk in ("true", "false"):
            self.pos += len(chunk)
            return self.made(Const(chunk == "true"), at)
        if chunk in _KEYWORDS:
            raise self.fail(f"unexpected keyword '{chunk}'", _FORMULA_START)
        if chunk and self.text.startswith("[", self.pos + len(chunk)):
            operators = [*_UNARY_TEMPORAL, "until", "since"]
            raise self.fail(f"'{chunk}' is not a temporal operator", "one of " + ", ".join(operators) + did_you_mean(chunk, operators))
        return self.made(self.atom(), at)

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
                + ("" if future else "; a past operator may write inf for no upper bound"),
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
                    "a finite upper bound such as 2s (only past operators, historically, once and since, take inf)",
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

    def atom(self) -> Atom:
        self.skip()
        start = self.pos
        term = self.term()
        fields: list[str] = []
        while self.text.startswith(".", self.pos):
            self.pos += 1
            match = _FIELD.match(self.text, self.pos)
            if match is None:
                raise self.unexpected(f"a field name after '.' (letters, digits and '_', as in {term}.speed)")
            fields.append(match.group())
            self.pos = match.end()
        self.skip()
        match = _OPERATOR.match(self.text, self.pos)
        if match is None:
            if self.pos < len(self.text) and self.text[self.pos] in _HINT_OPERATORS:
                raise self.fail(f"unexpected {_quote(self.text[self.pos])}", _HINT_OPERATORS[self.text[self.pos]])
            return Atom(term, tuple(fields))
        op = match.group()
        self.pos = match.end()
        self.skip()
        number = _NUMBER.match(self.text, self.pos)
        if number is None or (number.end() < len(self.text) and self.text[number.end()] not in _DELIMITERS):
            stream = self.text[start : match.start()].strip()
            raise self.unexpected(f"a number after '{op}' (atoms compare a stream with a number: {stream} {op} 0.5)")
        self.pos = number.end()
        value = float(number.group())
        if value != value or value in (float("inf"), float("-inf")):  # pragma: no cover - the pattern has no inf or nan
            raise self.fail("the number is not finite", "a finite number")
        return Atom(term, tuple(fields), op, value)

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
            number = _NUMBER.match(text, start)
            if number is not None and number.group() not in ("-", "."):
                raise self.fail(
                    f"the number {number.group()} where a stream should be",
                    "a stream first, then the comparison: Battery(robot) > 0.2",
                )
            end = start
            while end < len(text) and text[end] not in _DELIMITERS:
                end += 1
            if end == start:
                raise self.unexpected(_FORMULA_START)
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


def _quote(text: str) -> str:
    return "'" + text.replace("'", "\\'") + "'" if len(text) <= 60 else "'" + text[:57].replace("'", "\\'") + "...'"
