"""A formula's values and verdicts at one state: reading a stream, arithmetic, comparisons, Kleene's three values.

What the atoms and expressions of :mod:`dyknow.reasoning.semantics` compute at a state, as
functions on plain values: the offline evaluator (:mod:`dyknow.reasoning.evaluator`) and the
incremental monitor (:mod:`dyknow.reasoning.progression`) both call them, so the two agree by
construction on what a value and an atom are. A verdict is an int (:data:`FALSE`,
:data:`UNKNOWN`, :data:`TRUE`); an unknown value is :data:`UNKNOWN_VALUE`. Compiled by mypyc
(setup.py): the monitor calls them at every state.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any, Final

__all__ = [
    "FALSE",
    "TRUE",
    "UNKNOWN",
    "UNKNOWN_VALUE",
    "arith",
    "as_value",
    "call",
    "compare",
    "distance",
    "exact_sum",
    "is_number",
    "lookup",
    "margin",
    "object_key",
    "read",
    "read_raw",
    "scalar",
    "truth",
    "verdict_of",
]

FALSE: Final = 0
"""A verdict as an int: false. Kleene's ``and`` is ``min``, ``or`` is ``max``, ``not`` is ``2 - v``."""
UNKNOWN: Final = 1
"""A verdict as an int: unknown (neither true nor false, or not decided yet)."""
TRUE: Final = 2
"""A verdict as an int: true."""


class _Unknown:
    """The one unknown value (a missing field, a value of the wrong kind, a division by zero)."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "UNKNOWN_VALUE"

    def __bool__(self) -> bool:
        return False


UNKNOWN_VALUE: Final = _Unknown()
"""What an expression gives where its value is unknown."""

_INF: Final = math.inf


def verdict_of(value: int) -> bool | None:
    """The verdict as Python sees it: True, False or None for unknown."""
    return True if value == TRUE else False if value == FALSE else None


def read(payload: Any, fields: tuple[str, ...]) -> Any:
    """A stream's value: ``payload`` down ``fields``, as a number, string or boolean; else unknown."""
    value = payload
    for name in fields:
        if type(value) is not dict:
            return UNKNOWN_VALUE
        value = value.get(name, UNKNOWN_VALUE)
    return scalar(value)


def read_raw(payload: Any, fields: tuple[str, ...]) -> Any:
    """``payload`` down ``fields`` as it is (an object or an array too: what a lookup or ``dist``
    reads); unknown where a field is missing or its parent is no object."""
    value = payload
    for name in fields:
        if type(value) is not dict:
            return UNKNOWN_VALUE
        value = value.get(name, UNKNOWN_VALUE)
    return value


def lookup(container: Any, key: Any) -> Any:
    """``container[key]`` as a lookup of the semantics: an object's member by a string key, or by
    a number's canonical text (``3`` and ``3.0`` find ``"3"``: JSON's keys are strings); an
    array's element by a number whose value is an integer from 0 (``2`` and ``2.0`` alike);
    unknown otherwise (a missing key, an index out of range, a key of another kind)."""
    kind = type(container)
    if kind is dict:
        if type(key) is str:
            return container.get(key, UNKNOWN_VALUE)
        text = object_key(key) if is_number(key) else None
        return UNKNOWN_VALUE if text is None else container.get(text, UNKNOWN_VALUE)
    if kind is list and is_number(key) and key - key == 0 and key == int(key):
        index = int(key)
        return container[index] if 0 <= index < len(container) else UNKNOWN_VALUE
    return UNKNOWN_VALUE


def scalar(value: Any) -> Any:
    """A value of the semantics: a number (finite), a string or a boolean as it is; else unknown."""
    kind = type(value)
    if kind is float:
        return value if value - value == 0.0 else UNKNOWN_VALUE  # NaN and infinities: unknown
    if kind is int or kind is str or kind is bool:
        return value
    if isinstance(value, bool):
        return bool(value)
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        value = float(value)
        return value if value - value == 0.0 else UNKNOWN_VALUE
    if isinstance(value, str):
        return str(value)
    return UNKNOWN_VALUE


def is_number(value: Any) -> bool:
    """Whether ``value`` is a number of the semantics: an ``int`` or a ``float`` (not a ``bool``)."""
    kind = type(value)
    return kind is int or kind is float


def arith(op: str, x: Any, y: Any) -> Any:
    """``x OP y`` on numbers (``op`` one of + - * /); unknown otherwise, on division by zero, and
    when the result is not finite."""
    if not is_number(x) or not is_number(y):
        return UNKNOWN_VALUE
    if op == "+":
        result = x + y
    elif op == "-":
        result = x - y
    elif op == "*":
        result = x * y
    else:
        if y == 0:
            return UNKNOWN_VALUE
        try:
            result = x / y
        except OverflowError:  # an int too large for a float
            return UNKNOWN_VALUE
    if type(result) is float and result - result != 0.0:
        return UNKNOWN_VALUE
    return result


def call(fn: str, args: Sequence[Any]) -> Any:
    """``abs(x)``, ``min(x, y)``, ``max(x, y)``, ``-x`` (``fn`` "neg"), ``sqrt(x)``,
    ``hypot(x, y)`` and ``pow(x, y)`` on numbers (``dist``: :func:`distance`); unknown otherwise,
    and where the result is not a finite real number: the square root of a negative number,
    ``pow(0, -1)``, ``pow(-8, 1/3)``, an overflow. ``sqrt``, ``hypot`` and ``pow`` compute in
    floating point (IEEE 754 doubles, as Python's ``math`` does): ``pow(2, 3)`` is ``8.0``."""
    if fn == "dist":
        return distance(args[0], args[1])
    for x in args:
        if not is_number(x):
            return UNKNOWN_VALUE
    if fn == "neg":
        return -args[0]
    if fn == "abs":
        return abs(args[0])
    if fn == "min":
        return args[0] if args[0] <= args[1] else args[1]
    if fn == "max":
        return args[0] if args[0] >= args[1] else args[1]
    try:
        if fn == "sqrt":
            x = float(args[0])
            if x < 0.0:
                return UNKNOWN_VALUE
            result = math.sqrt(x)
        elif fn == "hypot":
            result = math.hypot(float(args[0]), float(args[1]))
        else:
            result = math.pow(float(args[0]), float(args[1]))
    except (OverflowError, ValueError):  # (an int too large for a float; a result that is no real number)
        return UNKNOWN_VALUE
    return result if result - result == 0.0 else UNKNOWN_VALUE


def distance(p: Any, q: Any) -> Any:
    """``dist(p, q)``: the Euclidean distance of two points, each an object with the numbers
    ``x`` and ``y`` and, on both or on neither, ``z`` (other members are ignored: a pose's
    position may carry more), or two arrays of numbers of one length (at least 1); unknown
    otherwise, and when the distance is not finite."""
    if type(p) is dict and type(q) is dict:
        names = ("x", "y", "z") if "z" in p or "z" in q else ("x", "y")
        a: list[Any] = [p.get(name) for name in names]
        b: list[Any] = [q.get(name) for name in names]
    elif type(p) is list and type(q) is list and len(p) == len(q) and p:
        a, b = list(p), list(q)
    else:
        return UNKNOWN_VALUE
    diffs: list[float] = []
    for x, y in zip(a, b, strict=True):
        if not is_number(x) or not is_number(y):
            return UNKNOWN_VALUE
        try:
            diffs.append(float(x) - float(y))
        except OverflowError:
            return UNKNOWN_VALUE
    result = math.hypot(*diffs)
    return result if result - result == 0.0 else UNKNOWN_VALUE


def compare(op: str, x: Any, y: Any) -> int:
    """The verdict of ``x OP y`` (as **Atoms** in :mod:`dyknow.reasoning.semantics` states it)."""
    tx, ty = type(x), type(y)
    numbers = (tx is int or tx is float) and (ty is int or ty is float)
    if op == "==" or op == "!=":
        if not numbers and (tx is not ty or (tx is not str and tx is not bool)):
            return UNKNOWN
        same = x == y
        return TRUE if same == (op == "==") else FALSE
    if not numbers:
        return UNKNOWN
    if op == "<":
        holds = x < y
    elif op == "<=":
        holds = x <= y
    elif op == ">":
        holds = x > y
    else:
        holds = x >= y
    return TRUE if holds else FALSE


def margin(op: str, x: Any, y: Any, verdict: int) -> float | None:
    """The robustness of a decided atom ``x OP y`` (as **Robustness** in :mod:`dyknow.reasoning.semantics` states it)."""
    if verdict == UNKNOWN:
        return None
    tx, ty = type(x), type(y)
    if (tx is int or tx is float) and (ty is int or ty is float):
        try:
            if op == "<" or op == "<=":
                return float(y - x)
            if op == ">" or op == ">=":
                return float(x - y)
            if op == "==":
                return -float(abs(x - y))
            return float(abs(x - y))
        except OverflowError:
            return _INF if verdict == TRUE else -_INF
    return _INF if verdict == TRUE else -_INF


def truth(value: Any) -> int:
    """A value read as a condition: its verdict when it is a boolean, unknown otherwise."""
    if value is True:
        return TRUE
    if value is False:
        return FALSE
    return UNKNOWN


def as_value(verdict: int) -> Any:
    """A verdict used as a value: True, False or unknown."""
    return True if verdict == TRUE else False if verdict == FALSE else UNKNOWN_VALUE


def object_key(value: Any) -> str | None:
    """The object a ``foreach`` field's value names (as verdict keys carry it), or None for a
    value that names none (a boolean, null, a list, an object, NaN or an infinity: the sample
    belongs to no object).

    Identity is JSON's: the type (string or number) and the value. A number is one value however
    it is written (``1``, ``1.0`` and ``1e0`` are one object, as in JSON, which has one number
    type), and its key is its canonical text: an integer, or a float whose value is an integer
    below 2**53, as an integer (``"1"``); any other float as Python's shortest round-trip text
    (``"2.5"``). (Past 2**53 a float and an integer are told apart, as a JSON parser that reads
    integers exactly tells them.) A string is another
    object than every number: its key is the string itself, unless that is a number's canonical
    text or starts with a double quote, then its JSON text (the string ``"1"`` has the key
    ``'"1"'``, the number 1 ``'1'``), so that no two objects share a key. (They were ``1`` and
    ``"1"`` one object, ``1`` and ``1.0`` two.)"""
    kind = type(value)
    if kind is str:
        text: str = value
        return json.dumps(text, ensure_ascii=False) if text.startswith('"') or _is_number_key(text) else text
    if kind is int:
        return str(value)
    if kind is float and value - value == 0.0:
        return _number_key(value)
    return None


_SAFE_INTEGER: Final = 2**53


def _number_key(value: float) -> str:
    if value == int(value) and abs(value) < _SAFE_INTEGER:
        return str(int(value))
    return repr(value)


def _is_number_key(text: str) -> bool:
    """Whether ``text`` is the key of some number: the canonical text of what it reads as."""
    if not text or text[0] not in "-0123456789":  # (Python reads at most 4,300 digits: longer is no number)
        return False
    try:
        number = int(text) if text.lstrip("-").isdigit() else float(text)
    except ValueError:
        return False
    if isinstance(number, int):
        return str(number) == text
    return number - number == 0.0 and _number_key(number) == text


def exact_sum(values: Sequence[Any]) -> Any:
    """The sum of numbers as the semantics defines it: exact for ``int`` s, else the exactly rounded
    sum of the values as floats (``math.fsum``); unknown when that is not finite."""
    if all(type(x) is int for x in values):
        return sum(values)
    try:
        total = math.fsum(float(x) for x in values)
    except OverflowError:
        return UNKNOWN_VALUE
    return total if total - total == 0.0 else UNKNOWN_VALUE
