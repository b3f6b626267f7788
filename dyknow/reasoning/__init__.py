"""Temporal reasoning over streams: formulas, their exact semantics, incremental monitors and the
monitor as a unit.

==========================  ==============================================================================
module                      what it holds
==========================  ==============================================================================
:mod:`~.syntax`             the language: :func:`parse`, :class:`Formula` and its syntax tree
:mod:`~.semantics`          what a formula means, exactly: states, Kleene verdicts, windows; :func:`evaluate`
:mod:`~.progression`        :class:`Monitor`: samples in, each state's :class:`Verdict` out as soon as decided
:mod:`~.unit`               :class:`FormulaMonitor`, the monitor as a unit, and :func:`monitor_spec` for its spec
==========================  ==============================================================================

Imports flow one way: ``syntax <- semantics <- progression <- unit``.

    >>> from dyknow.reasoning import evaluate
    >>> evaluate("once[0, 1s] Battery(robot) < 0.2", {"Battery(robot)": [(0.0, 0.5), (0.5, 0.1), (2.0, 0.4)]})
    [(0.0, False), (0.5, True), (2.0, False)]
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from dyknow.exports import lazy_exports

if TYPE_CHECKING:
    from dyknow.errors import FormulaError
    from dyknow.reasoning.progression import Monitor, Verdict
    from dyknow.reasoning.semantics import evaluate, evaluate_ns
    from dyknow.reasoning.syntax import Formula, parse
    from dyknow.reasoning.unit import FormulaMonitor, monitor_spec, term_ports

__all__ = [
    "Formula",
    "FormulaError",
    "FormulaMonitor",
    "Monitor",
    "Verdict",
    "evaluate",
    "evaluate_ns",
    "monitor_spec",
    "parse",
    "term_ports",
]

#: Where each public name is defined, imported on first use: a module that needs only the syntax
#: (the service's bounds, a spec's requirements) does not import the monitors (dyknow.exports).
_WHERE = {
    "Formula": "dyknow.reasoning.syntax",
    "FormulaError": "dyknow.errors",
    "FormulaMonitor": "dyknow.reasoning.unit",
    "Monitor": "dyknow.reasoning.progression",
    "Verdict": "dyknow.reasoning.progression",
    "evaluate": "dyknow.reasoning.semantics",
    "evaluate_ns": "dyknow.reasoning.semantics",
    "monitor_spec": "dyknow.reasoning.unit",
    "parse": "dyknow.reasoning.syntax",
    "term_ports": "dyknow.reasoning.unit",
}


def _restore_docstring(name: str, value: Any) -> None:  # Monitor and Verdict are compiled by mypyc
    from dyknow.resources import restore_docstrings

    restore_docstrings({name: value}, [name])


__getattr__, __dir__ = lazy_exports(__name__, globals(), _WHERE, after=_restore_docstring)
