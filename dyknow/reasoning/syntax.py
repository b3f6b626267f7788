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
nesting), because formulas reach a manager over the network as unit params.

Parse errors are :class:`~dyknow.errors.FormulaError` with ``where`` = ``formula column N``
(1-based), saying what came and what was expected there. ``str(formula)`` writes a formula back
with only the parentheses it needs; parsing that text gives the same tree.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation

from dyknow.errors import FormulaError, TagError, did_you_mean
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
    "children",
    "parse",
]

COMPARISONS: tuple[str, ...] = ("<", "<=", ">", ">=", "==", "!=")
"""The comparison operators of atoms."""

MAX_FORMULA_CHARS: int = 10_000
"""The longest formula text :func:`parse` reads."""

MAX_DEPTH: int = 100
"""The deepest nesting of operators and parentheses :func:`parse` reads."""

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


@dataclass(frozen=True, slots=True)
class Not:
    """``not arg``."""

    arg: Node

    def __str__(self) -> str:
        return f"not {_wrap(self.arg, _UNARY)}"


@dataclass(frozen=True, slots=True)
class And:
    """``left and right``."""

    left: Node
    right: Node

    def __str__(self) -> str:
        return f"{_wrap(self.left, _AND)} and {_wrap(self.right, _BINARY)}"


@dataclass(frozen=True, slots=True)
class Or:
    """``left or right``."""

    left: Node
    right: Node

    def __str__(self) -> str:
        return f"{_wrap(self.left, _OR)} or {_wrap(self.right, _AND)}"


@dataclass(frozen=True, slots=True)
class Implies:
    """``left implies right``: ``(not left) or right``."""

    left: Node
    right: Node

    def __str__(self) -> str:
        return f"{_wrap(self.left, _OR)} implies {_wrap(self.right, _IMPLIES)}"


@dataclass(frozen=True, slots=True)
class Always:
    """``always[a, b] arg`` (future): ``arg`` at every state between ``a`` and ``b`` from now."""

    interval: Interval
    arg: Node

    def __str__(self) -> str:
        return f"always{self.interval} {_wrap(self.arg, _UNARY)}"


@dataclass(frozen=True, slots=True)
class Eventually:
    """``eventually[a, b] arg`` (future): ``arg`` at some state between ``a`` and ``b`` from now."""

    interval: Interval
    arg: Node

    def __str__(self) -> str:
        return f"eventually{self.interval} {_wrap(self.arg, _UNARY)}"


@dataclass(frozen=True, slots=True)
class Historically:
    """``historically[a, b] arg`` (past): ``arg`` at every state between ``b`` and ``a`` ago."""

    interval: Interval
    arg: Node

    def __str__(self) -> str:
        return f"historically{self.interval} {_wrap(self.arg, _UNARY)}"


@dataclass(frozen=True, slots=True)
class Once:
    """``once[a, b] arg`` (past): ``arg`` at some state between ``b`` and ``a`` ago."""

    interval: Interval
    arg: Node

    def __str__(self) -> str:
        return f"once{self.interval} {_wrap(self.arg, _UNARY)}"


@dataclass(frozen=True, slots=True)
class Until:
    """``left until[a, b] right`` (future)."""

    left: Node
    right: Node
    interval: Interval

    def __str__(self) -> str:
        return f"{_wrap(self.left, _UNARY)} until{self.interval} {_wrap(self.right, _UNARY)}"


@dataclass(frozen=True, slots=True)
class Since:
    """``left since[a, b] right`` (past)."""

    left: Node
    right: Node
    interval: Interval

    def __str__(self) -> str:
        return f"{_wrap(self.left, _UNARY)} since{self.interval} {_wrap(self.right, _UNARY)}"


Node = Atom | Const | Not | And | Or | Implies | Always | Eventually | Historically | Once | Until | Since
"""A node of a formula's syntax tree."""

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


def _wrap(node: Node, least: int) -> str:
    return f"({node})" if _level(node) < least else str(node)


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

    >>> str(parse("historically[0,2s](Battery(robot)>0.2)"))
    'historically[0, 2s] Battery(robot) > 0.2'
    """
    if not isinstance(text, str):
        raise FormulaError(f"a formula is text, got {type(text).__name__}", where="formula", expected="a str such as 'once[0, 1s] p'")
    if len(text) > MAX_FORMULA_CHARS:
        raise FormulaError(
            f"the formula has {len(text)} characters", where="formula", expected=f"at most {MAX_FORMULA_CHARS}", formula=text[:80] + "..."
        )
    parser = _Parser(text)
    root = parser.formula(0)
    parser.skip()
    if not parser.at_end():
        hint = did_you_mean(parser.word(), ["and", "or", "implies", "until", "since"])
        raise parser.unexpected("the end of the formula, 'and', 'or', 'implies', 'until' or 'since'" + hint)
    return Formula.of(root, text)


class _Parser:
    """A recursive-descent reader over the text that says where and why it is malformed."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.pos = 0

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
        if self.keyword("implies"):
            return Implies(left, self.formula(depth + 1))
        return left

    def disjunction(self, depth: int) -> Node:
        node = self.conjunction(depth)
        while self.keyword("or"):
            node = Or(node, self.conjunction(depth + 1))
        return node

    def conjunction(self, depth: int) -> Node:
        node = self.binary(depth)
        while self.keyword("and"):
            node = And(node, self.binary(depth + 1))
        return node

    def binary(self, depth: int) -> Node:
        left = self.unary(depth)
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
        return Until(left, right, interval) if op == "until" else Since(left, right, interval)

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
        if chunk == "not":
            self.pos += 3
            return Not(self.unary(depth + 1))
        if chunk in _UNARY_TEMPORAL:
            self.pos += len(chunk)
            interval = self.interval(chunk, future=chunk in ("always", "eventually"))
            return _UNARY_TEMPORAL[chunk](interval, self.unary(depth + 1))
        if chunk in ("true", "false"):
            self.pos += len(chunk)
            return Const(chunk == "true")
        if chunk in _KEYWORDS:
            raise self.fail(f"unexpected keyword '{chunk}'", _FORMULA_START)
        if chunk and self.text.startswith("[", self.pos + len(chunk)):
            operators = [*_UNARY_TEMPORAL, "until", "since"]
            raise self.fail(f"'{chunk}' is not a temporal operator", "one of " + ", ".join(operators) + did_you_mean(chunk, operators))
        return self.atom()

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
