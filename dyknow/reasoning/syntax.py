"""The language of temporal formulas: its grammar, and :func:`parse`, which reads a text into a :class:`Formula`.

A formula is text::

    historically[0, 2s] Battery(robot) > 0.2
    Speed(robot) < SpeedLimit(zone)
    abs(Pose(robot).x - Goal(robot).x) < 0.1
    Speed(r1) < Limits(floor)[State(r1).zone]
    Speed(r1) < SpeedLimit(State(r1).zone)
    dist(Pose(r1).position, Pose(r2).position) > 1.5
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
                | ('abs' | 'sqrt' | 'prev' | 'rise' | 'fall' | 'robustness') '(' formula ')'
                | ('min' | 'max' | 'hypot' | 'pow' | 'dist') '(' formula ',' formula ')'
                | '(' formula ')'
                | VAR                                                    a quantifier's variable, in its body
                | stream ['[' formula ']' {'[' formula ']' | '.' FIELD}]  a lookup: Limits(floor)[State(r).zone]
                | FUNCTOR '(' args ')' {'[' formula ']' | '.' FIELD}     a parameterized term: SpeedLimit(State(r).zone)
    stream     := TERM {'.' FIELD}                                       Battery(robot), BallTrack(field).speed
    args       := (NAME | sum) {',' (NAME | sum)}                        one of them an expression, the others names
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
  with them: ``+ - * /``, unary ``-``, ``abs``, ``min`` and ``max`` of two, ``sqrt``, ``hypot``
  and ``pow``, ``prev`` (the value at the previous state), ``robustness(F)`` (a condition's
  robustness: how far from changing) and the aggregates of a past window.
- **Lookups** read a stream's JSON object (or array) by a key computed at each state:
  ``Limits(floor)[State(r).zone]`` is the member of ``Limits(floor)`` named by the zone the
  robot is in, so one atom states a limit per zone however many zones there are. Keys chain
  (``Limits(floor)[z]["speed"]``), and a field after a key is a key (``Limits(floor)[z].speed``).
  A key is a string or a number (an array's index), never a condition. ``dist(p, q)`` is the
  distance of two points: streams (or lookups) whose values are ``{x, y}`` or ``{x, y, z}``
  objects, or arrays of numbers.
- **Parameterized terms** compute an argument at each state: ``SpeedLimit(State(r).zone)`` is the
  stream ``SpeedLimit(z)`` of the zone ``z`` the robot is in then, one of the streams
  ``SpeedLimit(z1)``, ``SpeedLimit(z2)``, ... (its *members*), so a limit per zone needs no map
  of them all in one stream. One argument is an expression over the streams' values at the state
  (streams, fields, lookups, arithmetic, functions but ``robustness``: no window, aggregate,
  ``prev``, ``rise`` or ``fall``, no other parameterized term), the others names
  (``SpeedLimit(floor, State(r).zone)``; a ``forall`` variable stands in them as in any term).
  Fields and keys may follow (``SpeedLimit(State(r).zone).value``). A ``foreach`` variable as an
  argument is one computed (its object's value): ``foreach r in Seen(floor).id: Speed(r) < 1``
  reads, for each robot seen, its own ``Speed(r1)``, ``Speed(r2)``, .... A monitor plans a member the
  first time its argument is seen, as it makes a ``foreach`` object's instance
  (:mod:`dyknow.reasoning.monitors`); the semantics reads it as a lookup into the members'
  latest values (:mod:`dyknow.reasoning.semantics`). **Conditions** (what ``and``, ``or``,
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

The tree's nodes are defined in :mod:`dyknow.reasoning.tree` and the parser in
:mod:`dyknow.reasoning.parser`; this module re-exports the nodes, so a formula's reader imports
everything from here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from dyknow.reasoning.parser import MAX_DEPTH, MAX_FORMULA_CHARS, parse_tree
from dyknow.reasoning.tree import (
    AGGREGATES,
    ARITHMETIC,
    COMPARISONS,
    FUTURE,
    LEAVES,
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
    kind_of,
    raw_reads,
    walk,
)
from dyknow.security import Limits
from dyknow.tags import Term

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
    "Index",
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
    # what is computed once from the (immutable) tree: a foreach monitor builds a monitor of its
    # body per object, and walking the tree again each time was most of an object's cost
    _known: dict[str, object] = field(default_factory=dict, compare=False, hash=False, repr=False)

    def __str__(self) -> str:
        return str(self.root)

    def _once(self, name: str, compute: Callable[[Node], object]) -> object:
        """``compute(root)``, computed on first use and kept (the tree never changes)."""
        if name not in self._known:
            self._known[name] = compute(self.root)
        return self._known[name]

    def memo(self, name: str, compute: Callable[[Formula], object]) -> object:
        """``compute(formula)``, computed on first use and kept with the formula under ``name``
        (the tree never changes): what a reader works out once from it, as a monitor the plan of
        its nodes (a foreach monitor makes one monitor of its body per object). A ``compute``
        that raises keeps nothing."""
        if name not in self._known:
            self._known[name] = compute(self)
        return self._known[name]

    @property
    def walked(self) -> list[Node]:
        """Every node of the tree, parents before children (:func:`walk`), computed once; do not change it."""
        return self._once("walk", walk)  # type: ignore[return-value]

    @property
    def raw(self) -> set[int]:
        """The ids of the nodes read as they are (:func:`~dyknow.reasoning.tree.raw_reads`), computed once; do not change it."""
        return self._once("raw", raw_reads)  # type: ignore[return-value]

    @property
    def past_only(self) -> bool:
        """Whether no future operator occurs: every state's verdict is decided at that state."""
        return not any(isinstance(node, FUTURE) for node in walk(self.root))

    @property
    def horizon_ns(self) -> int:
        """How far into the future a verdict may need to look: the largest sum of future upper
        bounds along a path from the root (0 for a past-only formula)."""
        return self._once("horizon", _future_horizon)  # type: ignore[return-value]

    @property
    def reach_ns(self) -> int | None:
        """How far into the past a verdict may read: the largest sum of past upper bounds (past
        windows, aggregates, and a state for prev, rise and fall) along a path from the root;
        None when a past window is unbounded (it reads back to the first state)."""
        return self._once("reach", _past_reach)  # type: ignore[return-value]

    @property
    def nodes(self) -> int:
        """How many atoms and operators the syntax tree has (the leaves, streams and constants,
        are not counted: they cost a monitor nothing per state): what the bounds count."""
        return sum(1 for node in walk(self.root) if not isinstance(node, LEAVES))

    @property
    def operators(self) -> int:
        """How many operators (connectives, temporal operators, arithmetic, aggregates; not
        leaves nor atoms) the formula has."""
        return sum(1 for node in walk(self.root) if not isinstance(node, (*LEAVES, Atom)))

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
        if isinstance(node, FUTURE):
            own = node.interval.hi_ns or 0
        memo[id(node)] = below + own
    return memo[id(root)]


def parse(text: str) -> Formula:
    """Parse a formula; raises :class:`~dyknow.errors.FormulaError` naming the column and what was expected.

    Only the language's own bounds apply (:data:`MAX_FORMULA_CHARS`, :data:`MAX_DEPTH`); a
    formula from a caller the process does not trust goes through :func:`check_formula`.

    >>> str(parse("historically[0,2s](Battery(robot)>0.2)"))
    'historically[0, 2s] Battery(robot) > 0.2'
    >>> str(parse("abs(Pose(robot).x-Goal(robot).x)<0.1"))
    'abs(Pose(robot).x - Goal(robot).x) < 0.1'
    """
    return Formula.of(parse_tree(text, None, None), text)


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
    return Formula.of(parse_tree(text, limits.max_formula_nodes, limits.max_window_ns), text)


def parse_value(text: str) -> Formula:
    """Parse an expression (a value, or a condition) rather than a formula: ``avg[0, 1s] Speed(robot)``;
    :func:`~dyknow.reasoning.semantics.evaluate_values_ns` computes it at every state."""
    return Formula.of(parse_tree(text, None, None, value=True), text)
