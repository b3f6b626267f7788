"""Terms bound to what exists: a formula's term read from a given Zenoh key or ROS 2 topic, not planned.

A binding is ``TERM=SOURCE`` (``dyknow monitor F --bind TERM=SOURCE``, ``bindings=`` of
:meth:`Manager.monitor <dyknow.manager.Manager.monitor>` and :meth:`Client.monitor
<dyknow.client.Client.monitor>`); SOURCE is one of

- ``ros2:/TOPIC[?OPTION=VALUE&...]``: a ROS 2 topic on rmw_zenoh,
- ``ros2dds:/TOPIC[?OPTION=VALUE&...]``: the same topic on DDS (the options, ``type=pkg/msg/Type``
  among them, as :mod:`dyknow.ros2.binding` states them),
- anything else: a Zenoh key (or key expression) as a port binds to it.

A bound term skips planning: the manager binds the monitor's input of that term to SOURCE itself,
and for a ROS 2 topic wires it through a :class:`~dyknow.ros2.bridge.Ros2Source` on its own node
or DDS participant (a companion of the monitor, bounded as every ROS 2 input is). The field path
after the term selects into each sample as for any stream: ``Odom(r1).twist.twist.linear.x`` reads
the nested field of an ``nav_msgs/msg/Odometry`` (messages come as dicts of their fields,
:mod:`dyknow.ros2.convert`). The formula language has no indexing, so a field path cannot reach
into an array (``covariance``, a ``LaserScan``'s ``ranges``): such a field's value is unknown.

**Samples.** A bound term's sample that is text, or bytes, holding one JSON value is read as that
value (:func:`sample_value`): a plain Zenoh publisher's ``1.5`` is the number 1.5, ``true`` is
true, ``{"x": 2}`` an object whose field ``.x`` a formula reads (a manager's measurement keys
take a JSON number the same way; their ``{"value": x}`` is read here as ``TERM.value``). Text that is not
JSON stays text (``manual``); bytes that are not UTF-8 JSON stay bytes, whose value is unknown.
The offline evaluation (:mod:`dyknow.reasoning.offline`) reads every sample so, so a formula over
a recording of the same samples gives the same verdicts.

**Mistakes.** :func:`check_bindings` refuses, before anything is started and naming the binding
(``binding 'Odom(r1)=ros:/r1/odom'``): a term that does not read or is no term of the formula, a
scheme that is not ``ros2:`` or ``ros2dds:`` (``ros:/x``), a ROS 2 topic name or option that is not
valid, a key with an empty chunk, a ``#``, ``?`` or space, or a chunk starting with ``@``; any
other key Zenoh refuses is refused by the manager's check of it. A binding with ``forall``/``exists`` is refused (its terms are the expansion's). A
parameterized term's member may be bound (``SpeedLimit(z1)=limits/z1`` for
``SpeedLimit(State(r).zone)``): it is read from the start, and never planned
(:mod:`dyknow.reasoning.members`). A
term bound to a source that never publishes gives no verdict from its samples (its values are
unknown, never false), and the monitor says so once: a ``{"warning": ...}`` on its verdicts naming
the binding, ``quiet_ms`` after it started (:class:`~dyknow.reasoning.unit.FormulaMonitor`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Mapping
from typing import Any

from dyknow.errors import BindingError, DyKnowError, FormulaError, TagError, did_you_mean
from dyknow.keys import ROS2_SCHEMES, check_data_key
from dyknow.reasoning.syntax import Formula, Quantifier, walk
from dyknow.reasoning.tree import is_family, member_arg
from dyknow.tags import parse_term

__all__ = ["MAX_TEXT_VALUE", "check_bindings", "check_source", "is_ros2_source", "sample_value", "topic_of"]

#: The longest text (or bytes) a bound term's sample may be to be read as JSON; a longer one stays as it is.
MAX_TEXT_VALUE = 65536

_SCHEME = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*:/")


def is_ros2_source(source: str) -> bool:
    """Whether ``source`` is a ``ros2:`` or ``ros2dds:`` topic (else it is a Zenoh key)."""
    return source.startswith(ROS2_SCHEMES)


def topic_of(source: str) -> str:
    """The ROS 2 topic a ``ros2:``/``ros2dds:`` source names (options left out); a key as it is."""
    for scheme in ROS2_SCHEMES:
        if source.startswith(scheme):
            return source[len(scheme) :].partition("?")[0]
    return source


def check_bindings(
    formula: Formula, bindings: Mapping[str, str], *, check_key: Callable[[str, str], object] | None = None
) -> dict[str, str]:
    """``bindings`` (term as written -> source) checked against ``formula``: each term written as
    the formula writes it (``dk:Odom(r1)`` is ``Odom(r1)``) -> its source. Raises
    :class:`~dyknow.errors.FormulaError` for a term that does not read or is not the formula's,
    :class:`~dyknow.errors.BindingError` for a source that is not valid (see the module
    documentation); each names the binding. ``check_key(key, where)`` checks a Zenoh key further
    (the manager's: Zenoh's own check)."""
    terms = [str(t) for t in formula.terms]
    out: dict[str, str] = {}
    for written, source in bindings.items():
        where = f"binding {str(written)[:200]}={str(source)[:300]}"
        if not isinstance(written, str) or not isinstance(source, str):
            raise FormulaError(f"a binding of {type(written).__name__} to {type(source).__name__}", where=where, expected="TERM=SOURCE, both text")
        try:
            term = str(parse_term(written))
        except TagError as exc:
            raise FormulaError(f"the term does not read: {exc.what}", where=where, expected="TERM=SOURCE, such as Odom(r1)=ros2:/r1/odom") from None
        if term not in terms and not any(member_arg(f, parse_term(term)) is not None for f in formula.terms if is_family(f)):
            raise FormulaError(
                f"{term!r} is no term of the formula",
                where=where,
                expected=f"one of {', '.join(terms) or 'its terms (it has none)'}{did_you_mean(term, terms)}",
            )
        if term in out:
            raise FormulaError(f"{term} is bound twice", where=where, expected="one source for each term")
        if _quantified(formula):
            raise FormulaError(
                "a binding in a formula with forall or exists", where=where,
                expected="bindings in formulas without forall or exists (foreach may stay): bind each individual's formula",
            )  # fmt: skip
        out[term] = check_source(source, where, check_key)
    return out


def _quantified(formula: Formula) -> bool:
    """Whether ``formula`` has a ``forall``/``exists`` (over an ontology class)."""
    return any(isinstance(node, Quantifier) and node.kind in ("forall", "exists") for node in walk(formula.root))


def check_source(source: str, where: str, check_key: Callable[[str, str], object] | None = None) -> str:
    """``source`` checked (the module documentation says what is refused; ``where`` names the
    binding in the error), written as dyknow writes it: a ROS 2 source's options in a fixed order."""
    if not source or source != source.strip():
        raise BindingError(f"the source {source!r}", where=where, expected="ros2:/TOPIC, ros2dds:/TOPIC or a Zenoh key, without spaces around")
    if is_ros2_source(source):
        from dyknow.ros2.binding import parse_binding

        try:
            return parse_binding(source, where=where).uri()
        except DyKnowError as exc:  # (a type's own check names the type, not the binding)
            if exc.where is not None and exc.where.startswith(where):
                raise
            raise BindingError(exc.what, where=f"{where}: {exc.where}" if exc.where else where, expected=exc.expected) from None
    scheme = _SCHEME.match(source)
    if scheme is not None:
        given = scheme.group()[:-1]
        raise BindingError(
            f"the scheme {given!r}",
            where=where,
            expected=f"ros2:/TOPIC (rmw_zenoh), ros2dds:/TOPIC (DDS) or a Zenoh key{did_you_mean(given, list(ROS2_SCHEMES))}",
        )
    check_data_key(source, where)
    if any(not chunk for chunk in source.split("/")) or any(c in source for c in "#? "):
        raise BindingError(
            f"the key {source[:200]!r} has an empty chunk or a '#', '?' or space",
            where=where,
            expected="a Zenoh key of chunks separated by single '/', like 'robots/r1/battery'",
        )
    if check_key is not None:
        check_key(source, where)
    return source


def sample_value(payload: Any) -> Any:
    """A bound term's sample as the formula reads it: text or bytes holding one JSON value (at
    most :data:`MAX_TEXT_VALUE` long) is that value; anything else is as it came."""
    kind = type(payload)
    if kind is not str and kind is not bytes:
        return payload
    if len(payload) > MAX_TEXT_VALUE:
        return payload
    try:
        return json.loads(payload, parse_constant=_refuse_constant)
    except (ValueError, RecursionError):  # (UnicodeDecodeError is a ValueError)
        return payload


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON value")
