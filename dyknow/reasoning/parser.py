"""The reader of formula text: a recursive-descent parser from text to a syntax tree whose kinds are checked.

:func:`parse_tree` reads the grammar stated in :mod:`dyknow.reasoning.syntax` into the nodes of
:mod:`dyknow.reasoning.tree`, holding the text to the language's bounds (:data:`MAX_FORMULA_CHARS`,
:data:`MAX_DEPTH`) and, when asked, to a manager's (nodes, windows, future horizon). What it
refuses, it refuses at a column: a :class:`~dyknow.errors.FormulaError` with ``where`` =
``formula column N`` that says what came and what was expected there.
"""

from __future__ import annotations

import re
from decimal import Decimal, InvalidOperation
from typing import TypeVar

from dyknow.errors import FormulaError, TagError, did_you_mean
from dyknow.reasoning.tree import (
    AGGREGATES,
    ANY,
    ARITY,
    BOOL,
    FAMILY_ARG,
    FUNCTIONS,
    FUTURE,
    KEYWORDS,
    LEAVES,
    NUM,
    RESERVED,
    STR,
    Aggregate,
    Always,
    And,
    Arith,
    Atom,
    Call,
    Const,
    Eventually,
    Fall,
    Historically,
    Implies,
    Index,
    Interval,
    Neg,
    Node,
    Not,
    Num,
    Once,
    Or,
    Prev,
    Quantifier,
    Rise,
    Since,
    Str,
    Stream,
    Until,
    Var,
    children,
    duration_text,
    family_term,
    kind_of,
    walk,
)
from dyknow.tags import NAME, Term, parse_term

__all__ = ["MAX_DEPTH", "MAX_FORMULA_CHARS", "parse_tree"]

MAX_FORMULA_CHARS: int = 10_000
"""The longest formula text :func:`~dyknow.reasoning.syntax.parse` reads."""

MAX_DEPTH: int = 64
"""The deepest nesting of operators and parentheses :func:`~dyknow.reasoning.syntax.parse` reads
(a chain of one operator counts once)."""

_NS_PER_S = 1_000_000_000

_N = TypeVar("_N", bound=Node)

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
_NAME_ARGS = re.compile(rf"\(\s*(?:{NAME.pattern})\s*(?:,\s*(?:{NAME.pattern})\s*)*\)")  # a tag's args: names only
_ARGUMENT_WINDOWS = (Always, Eventually, Until, Historically, Once, Since, Aggregate, Prev, Rise, Fall)
_HINT_OPERATORS = {"=": "== (equality is written ==)", "!": "!= (inequality is written !=)"}
_FORMULA_START = (
    "a condition: a comparison such as Battery(robot) > 0.2, a stream of boolean value, 'not', a temporal operator, "
    "rise(...), '(' or true/false"
)
_VALUE_START = "a value: a number, a string in quotes, a stream such as Speed(robot), '(' or a function such as abs(...)"


def parse_tree(text: str, max_nodes: int | None, max_window_ns: int | None, *, value: bool = False) -> Node:
    """The syntax tree of ``text``, a formula (or, with ``value``, an expression); with
    ``max_nodes`` and ``max_window_ns`` (None: unbounded) held to a manager's bounds as well.
    Raises :class:`~dyknow.errors.FormulaError` at the column where the text goes wrong."""
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
    return root


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
        if not isinstance(node, LEAVES):
            self.nodes += 1
        if self.max_nodes is not None and self.nodes > self.max_nodes:
            raise self.fail(
                f"the formula has more than {self.max_nodes} nodes",
                f"at most {self.max_nodes} atoms and operators (Limits.max_formula_nodes)",
                column=column,
            )
        kids = children(node)
        if isinstance(node, FUTURE) or any(id(kid) in self.future for kid in kids):
            self.future.add(id(node))
        if self.max_window_ns is not None:
            below = max((self.ahead.get(id(kid), 0) for kid in kids), default=0)
            ahead = below + ((node.interval.hi_ns or 0) if isinstance(node, FUTURE) else 0)
            if ahead > self.max_window_ns:
                op = type(node).__name__.lower()
                raise self.fail(
                    f"'{op}' here makes the formula look {duration_text(ahead)} ahead (the upper bounds of nested future operators add up)",
                    f"at most {duration_text(self.max_window_ns)} ahead (Limits.max_window_ns)",
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
        if match is None or match.group() in RESERVED:
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
        if chunk and self.after_word(chunk) == "[" and chunk not in AGGREGATES and chunk not in KEYWORDS and self.interval_ahead(chunk):
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
        if chunk in KEYWORDS:
            raise self.fail(f"unexpected keyword '{chunk}'", _VALUE_START if chunk not in ("not", "always") else _FORMULA_START)
        param = self.parameterized(depth, at)
        keys: list[Node] = []
        if param is not None:  # SpeedLimit(State(r).zone): a lookup into the term's family by its argument
            stream, argument, position = param
            keys.append(argument)
        else:
            position = -1
            stream = self.made(self.stream(), at)
            if not self.text.startswith("[", _SPACE.match(self.text, self.pos).end()):  # type: ignore[union-attr]  # \s* always matches
                return stream
        while True:  # stream[key] {[key] | .field}
            if self.char("["):
                key = self.formula(depth + 1)
                if self.kind(key) == BOOL:
                    raise self.fail(f"{_quote(str(key))} is a condition, and a key is a value", "a string (an object's key) or a number (an array's index)",
                                    column=self.column_of(key))  # fmt: skip
                keys.append(key)
                if not self.char("]"):
                    raise self.unexpected("']' closing the key")
            elif self.text.startswith(".", self.pos) and keys:
                match = _FIELD.match(self.text, self.pos + 1)
                if match is None:
                    raise self.unexpected("a field name after '.' (letters, digits and '_')")
                keys.append(self.made(Str(match.group()), self.pos + 1))
                self.pos = match.end()
            else:
                return self.made(Index(stream, tuple(keys), position), at)

    def parameterized(self, depth: int, at: int) -> tuple[Stream, Node, int] | None:
        """A parameterized term at ``at`` (``SpeedLimit(State(r).zone)``: one argument an expression
        computed at each state, the others names): its family stream (``SpeedLimit(*)``), the
        expression and its position; None (nothing read) for a term whose args are all names."""
        text = self.text
        if text.startswith(("`", "<"), at):
            return None  # a backquoted tag or an IRI functor: a tag as it is
        end = at
        while end < len(text) and text[end] not in _DELIMITERS:
            end += 1
        opening = _SPACE.match(text, end).end()  # type: ignore[union-attr]  # \s* always matches
        names = _NAME_ARGS.match(text, opening)
        if end == at or not text.startswith("(", opening) or ")" not in text[opening:]:
            return None  # (a '(' never closed: the tag's own reading says so)
        if names is not None and not any(self.variables.get(n) == ANY for n in NAME.findall(names.group())):
            return None  # names only (a foreach variable among them is the object's value: computed)
        functor = self.tag(text[at:end], at).functor
        self.pos = opening + 1
        args: list[str] = []
        found: tuple[Node, int] | None = None
        expected = "a name (Speed(r1)) or one expression over streams (SpeedLimit(State(r1).zone))"
        while True:
            self.skip()
            start = self.pos
            name = NAME.match(text, start)
            follows = _SPACE.match(text, name.end()).end() if name is not None else start  # type: ignore[union-attr]
            if name is not None and text.startswith((",", ")"), follows) and self.variables.get(name.group()) != ANY:  # (forall's stand in args; foreach's never)
                args.append(name.group())
                self.pos = follows
            else:
                argument = self.formula(depth + 1)
                if found is not None:
                    raise self.fail(f"a second computed argument of {functor}(...)", f"one argument computed at each state, the others names ({expected})",
                                    column=start)  # fmt: skip
                found = (self.argument(argument, functor, start), len(args))
                args.append(FAMILY_ARG)
            if self.char(")"):
                break
            if not self.char(","):
                raise self.unexpected(f"',' or ')' after argument {len(args)} of {functor}(...)")
        if found is None:  # names only, spelled so the quick check missed it: the tag's own reading says what is wrong
            self.tag(text[at : self.pos], at)
            return None
        family = self.made(Stream(family_term(functor, tuple(args))), at)
        return family, found[0], found[1]

    def argument(self, node: Node, functor: str, column: int) -> Node:
        """The computed argument of a parameterized term, checked: a value read from the streams'
        values at the state (the monitor plans a member per value it sees)."""
        where = f"an argument of {functor}(...)"
        if self.kind(node) == BOOL:
            raise self.fail(f"{_quote(str(node))} is a condition, and {where} is a value", "a string naming the member, such as State(r1).zone",
                            column=column)  # fmt: skip
        nodes = walk(node)
        for inner in nodes:
            if isinstance(inner, _ARGUMENT_WINDOWS) or (isinstance(inner, Call) and inner.fn == "robustness"):
                raise self.fail(f"{where} reads {_quote(str(inner))}, more than the state",
                                "an expression of the streams' values at the state (no windows, aggregates, prev, rise, fall or robustness)",
                                column=self.column_of(inner))  # fmt: skip
            if isinstance(inner, Index) and inner.param >= 0:
                raise self.fail(f"{where} is itself a parameterized term", "an argument over plain streams (State(r1).zone)", column=self.column_of(inner))
        if not any(isinstance(inner, Stream | Var) for inner in nodes):
            raise self.fail(f"{where} is the constant {_quote(str(node))}", f"a name, written as it is ({functor}(z1)), or an expression over streams",
                            column=column)  # fmt: skip
        return node

    def interval_ahead(self, word: str) -> bool:
        """Whether the ``[`` after ``word`` opens an interval (a comma outside parentheses and
        quotes before its ``]``: ``alwyas[0, 1s]``, a misspelt operator) rather than a lookup's
        key (``Limits[State(r).zone]``)."""
        text, depth, quote = self.text, 0, ""
        for k in range(self.text.index("[", self.pos + len(word)) + 1, len(text)):
            char = text[k]
            if quote:
                quote = "" if char == quote and text[k - 1] != "\\" else quote
            elif char in "\"'":
                quote = char
            elif char in "([":
                depth += 1
            elif char in ")]":
                if depth == 0:
                    return False
                depth -= 1
            elif char == "," and depth == 0:
                return True
        return False

    def function(self, fn: str, depth: int, at: int) -> Node:
        self.pos += len(fn)
        self.char("(")
        args = [self.formula(depth + 1)]
        while self.char(","):
            args.append(self.formula(depth + 1))
        arity = ARITY[fn]
        if not self.char(")"):
            raise self.unexpected(f"')' closing {fn}(...)" + (" or ',' before its second operand" if arity == 2 else ""))
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
        if fn == "dist":
            for arg in args:
                if self.kind(arg) != ANY:
                    raise self.fail(f"{_quote(str(arg))} is a {self.kind(arg)}, and dist takes points",
                                    "a stream whose value is a point: an object {x, y} or {x, y, z}, or an array of numbers, as in "
                                    "dist(Pose(r1).position, Pose(r2).position)", column=self.column_of(arg))  # fmt: skip
            return self.made(Call(fn, tuple(args)), at)
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
                f"the interval's lower bound {duration_text(lo)} is above its upper bound {duration_text(hi)}",
                "[a, b] with a <= b",
                column=lo_at,
            )
        longest = self.max_window_ns
        if longest is not None and max(lo, hi or 0) > longest:
            opened = self.text.rfind("[", 0, lo_at)
            raise self.fail(
                f"{_quote(op + self.text[opened : self.pos])} has the bound {duration_text(max(lo, hi or 0))}, beyond the longest window",
                f"bounds of at most {duration_text(longest)} (Limits.max_window_ns)"
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
            hint = did_you_mean(tag, KEYWORDS)
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
