"""Zenoh key expressions: checked before use, told apart when wild, matched against each other."""

from __future__ import annotations

import re

import zenoh

from dyknow.errors import BindingError
from dyknow.keys import MAX_KEY_BYTES
from dyknow.transport.runtime import error_text

__all__ = ["check_key_expr", "is_wild", "key_exprs_intersect"]

_WILD = re.compile(r"\*|\$\*")


def check_key_expr(key: str, *, what: str = "key expression", concrete: bool = False) -> str:
    """Return ``key`` if Zenoh accepts it, else raise :class:`BindingError` naming ``what``.

    With ``concrete=True`` wildcards are refused too (a publisher needs one concrete key).
    """
    if not isinstance(key, str) or not key:
        raise BindingError(f"got {key!r}", where=what, expected="a non-empty Zenoh key expression like 'robot/camera/image'")
    if len(key.encode()) > MAX_KEY_BYTES:
        raise BindingError(
            f"a key expression of {len(key.encode())} bytes is too long", where=what, expected=f"at most {MAX_KEY_BYTES} bytes"
        )
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise BindingError(
            f"{key!r} is not a valid Zenoh key expression ({error_text(exc)})",
            where=what,
            expected="chunks separated by '/', like 'robot/camera/image'",
        ) from exc
    if concrete and is_wild(key):
        raise BindingError(f"{key!r} has wildcards", where=what, expected="a concrete key to publish on, like 'robot/camera/image'")
    return key


def is_wild(key: str) -> bool:
    """Whether ``key`` holds a wildcard (``*``, ``**`` or ``$*``)."""
    return _WILD.search(key) is not None


def key_exprs_intersect(a: str, b: str) -> bool:
    """Whether some key matches both key expressions."""
    if not is_wild(a) and not is_wild(b):
        return a == b
    return zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))

