"""Temporal reasoning over streams: formulas, their exact semantics, incremental monitors and the
monitor as a unit.

==========================  ==============================================================================
module                      what it holds
==========================  ==============================================================================
:mod:`~.syntax`             the language: :func:`parse`, :func:`check_formula`, :class:`Formula`, its tree
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

from dyknow.errors import FormulaError
from dyknow.reasoning.progression import Monitor, Verdict
from dyknow.reasoning.semantics import evaluate, evaluate_ns
from dyknow.reasoning.syntax import Formula, check_formula, parse
from dyknow.reasoning.unit import FormulaMonitor, monitor_spec, term_ports
from dyknow.resources import restore_docstrings

__all__ = [
    "Formula",
    "FormulaError",
    "FormulaMonitor",
    "Monitor",
    "Verdict",
    "check_formula",
    "evaluate",
    "evaluate_ns",
    "monitor_spec",
    "parse",
    "term_ports",
]

restore_docstrings(globals(), __all__)  # Monitor and Verdict are compiled by mypyc
