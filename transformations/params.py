"""Reading unit params: typed access with range checks and messages that name the param.

The manager already converts each param to the type its spec declares (string, int, float, bool);
these helpers add what a spec cannot say: ranges, lists of numbers in a string (``"40,80,80"``)
and sizes (``"640x480"``). Every failure is a :class:`~transformations.errors.ParamError` whose
fields name the param (``where``: ``param 'rate_hz'``), say what came in (``what``: ``got -1``)
and what was expected (``expected``: ``a number >= 0``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Any

from dyknow.spec.model import BOOL_WORDS
from transformations.errors import ParamError

__all__ = ["choice", "flag", "number", "numbers", "size", "text", "whole"]

_MISSING = object()


def _get(params: Mapping[str, Any], name: str, default: Any) -> Any:
    value = params.get(name, default)
    if value is _MISSING:
        raise ParamError("is missing", where=f"param {name!r}", expected="it in the spec or at spawn time")
    return value


def number(
    params: Mapping[str, Any],
    name: str,
    default: float | None = None,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    integer: bool = False,
) -> float:
    """Param ``name`` as a finite number in ``[low, high]`` (``(low, high]`` with ``low_open``).

    ``integer`` refuses fractions (the value is still returned as a float; see :func:`whole`).
    """
    value = _get(params, name, _MISSING if default is None else default)
    kind = "a whole number" if integer else "a number"
    try:
        if isinstance(value, bool):
            raise TypeError
        result = float(value)
    except (TypeError, ValueError):
        raise ParamError(f"got {value!r}", where=f"param {name!r}", expected=kind) from None
    if not math.isfinite(result) or (integer and not result.is_integer()):
        raise ParamError(f"got {value!r}", where=f"param {name!r}", expected=kind)
    too_low = low is not None and (result <= low if low_open else result < low)
    too_high = high is not None and result > high
    if too_low or too_high:
        lo = "" if low is None else (f"> {low:g}" if low_open else f">= {low:g}")
        hi = "" if high is None else f"<= {high:g}"
        raise ParamError(f"got {value!r}", where=f"param {name!r}", expected=f"{kind} {' and '.join(p for p in (lo, hi) if p)}")
    return result


def whole(
    params: Mapping[str, Any], name: str, default: int | None = None, *, low: int | None = None, high: int | None = None
) -> int:
    """Param ``name`` as a whole number in ``[low, high]``."""
    return int(number(params, name, None if default is None else float(default), low=low, high=high, integer=True))


def flag(params: Mapping[str, Any], name: str, default: bool = False) -> bool:
    """Param ``name`` as a bool: a bool, or text the spec format's ``bool`` accepts (true, false, 1, 0)."""
    value = _get(params, name, default)
    if isinstance(value, bool):
        return value
    lowered = str(value).strip().lower()
    if lowered in BOOL_WORDS:
        return BOOL_WORDS[lowered]
    raise ParamError(f"got {value!r}", where=f"param {name!r}", expected="true or false")


def text(params: Mapping[str, Any], name: str, default: str | None = None, *, required: bool = False) -> str:
    """Param ``name`` as stripped text; ``required`` refuses an empty value."""
    value = str(_get(params, name, _MISSING if default is None else default)).strip()
    if required and not value:
        raise ParamError("is empty", where=f"param {name!r}", expected="a value")
    return value


def choice(params: Mapping[str, Any], name: str, options: tuple[str, ...], default: str) -> str:
    """Param ``name`` as one of ``options`` (case-insensitive)."""
    value = text(params, name, default).lower()
    if value not in options:
        listing = ", ".join(repr(o) for o in options)
        raise ParamError(f"got {value!r}", where=f"param {name!r}", expected=f"one of {listing}")
    return value


def numbers(value: Any, name: str, count: int, *, low: float | None = None, high: float | None = None) -> tuple[float, ...]:
    """``count`` numbers from text such as ``"40,80,80"`` (commas and/or spaces), each in range."""
    parts = [p for p in re.split(r"[\s,;]+", str(value).strip()) if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ParamError(f"got {value!r}", where=f"param {name!r}", expected=f"{count} numbers separated by commas")
    for v in values:
        if (low is not None and v < low) or (high is not None and v > high):
            if low is not None and high is not None:
                bounds = f"in [{low:g}, {high:g}]"
            else:  # one bound only
                bounds = f">= {low:g}" if low is not None else f"<= {high:g}"
            raise ParamError(f"got {value!r}", where=f"param {name!r}", expected=f"every number {bounds}")
    return values


def size(value: Any, name: str) -> tuple[int, int] | None:
    """An image size ``"WxH"`` (or ``"W,H"``) as ``(width, height)``; None for an empty value."""
    raw = str(value).strip()
    if not raw:
        return None
    match = re.fullmatch(r"(\d+)\s*[x,X ]\s*(\d+)", raw)
    if match is None or int(match.group(1)) <= 0 or int(match.group(2)) <= 0:
        raise ParamError(f"got {value!r}", where=f"param {name!r}", expected="an image size such as '640x480'")
    return int(match.group(1)), int(match.group(2))
