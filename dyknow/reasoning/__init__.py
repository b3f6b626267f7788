"""Temporal reasoning over streams: formulas, their exact semantics, incremental monitors and the
monitor as a unit.

==========================  ==============================================================================
module                      what it holds
==========================  ==============================================================================
:mod:`~.syntax`             the language: :func:`parse`, :func:`check_formula`, :class:`Formula`
:mod:`~.tree`               a formula's syntax tree: its nodes, walked, written back and compared
:mod:`~.parser`             the reader of formula text, which refuses what is malformed at its column
:mod:`~.semantics`          what a formula means, exactly: states, Kleene verdicts, windows; :func:`evaluate`
:mod:`~.values`             values and verdicts at one state (streams read, arithmetic, atoms), the monitor's too
:mod:`~.evaluator`          every node over a whole trace at once: the work of :func:`evaluate`
:mod:`~.progression`        :class:`Monitor`: samples in, each state's :class:`Verdict` out as soon as decided
:mod:`~.nodes`              the monitor's node kinds decided at their state: values, atoms, ``not``, ``and``, ``or``
:mod:`~.aggregates`         its aggregates of a past window: ``count``, ``sum``, ``avg``, ``min``, ``max``, ...
:mod:`~.past`               its ``since``, ``once`` and ``historically`` nodes
:mod:`~.future`             its ``until``, ``eventually`` and ``always`` nodes
:mod:`~.windows`            the window machinery: operands' verdicts as sorted positions, bisected and pruned
:mod:`~.pending`            the pending-state forest: which states still wait for their verdict
:mod:`~.timeline`           the timeline the nodes share: the retained states' times, the terms' stale spans
:mod:`~.robustness`         the robustness of each state, for a monitor asked for it
:mod:`~.objects`            :class:`ObjectMonitor`: a ``foreach`` formula, one monitor per object
:mod:`~.quantify`           ``forall``/``exists`` over an ontology class, expanded for a manager
:mod:`~.unit`               :class:`FormulaMonitor`, the monitor as a unit, and :func:`monitor_spec` for its spec
:mod:`~.bindings`           terms bound to what exists (a Zenoh key, a ROS 2 topic), read instead of planned
:mod:`~.monitors`           monitors asked of a manager by meaning, each term planned or bound
:mod:`~.offline`            a formula over a recording: the same semantics, yesterday's data
:mod:`~.explain`            why a verdict is what it is: each comparison with its sides' values at a state
:mod:`~.requirements`       a file of requirements checked over a recording, for CI (``dyknow check``)
==========================  ==============================================================================

Imports flow one way (a module imports only from those on its left): ``tree <- parser <- syntax
<- quantify <- semantics``; ``values <- evaluator <- semantics``; and ``values, syntax <- robustness
<- timeline <- pending <- nodes <- windows <- aggregates, past, future <- progression <- objects <-
unit``; ``syntax <- bindings <- unit, monitors, offline <- requirements``; ``semantics <- explain
<- unit, offline``.

    >>> from dyknow.reasoning import evaluate
    >>> evaluate("once[0, 1s] Battery(robot) < 0.2", {"Battery(robot)": [(0.0, 0.5), (0.5, 0.1), (2.0, 0.4)]})
    [(0.0, False), (0.5, True), (2.0, False)]
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from dyknow.exports import lazy_exports

if TYPE_CHECKING:
    from dyknow.errors import FormulaError
    from dyknow.reasoning.objects import ObjectMonitor
    from dyknow.reasoning.progression import Monitor, Verdict
    from dyknow.reasoning.requirements import Requirement, Result, check_recording, junit_xml, load_requirements, write_verdicts
    from dyknow.reasoning.semantics import evaluate, evaluate_ns, evaluate_objects_ns, evaluate_values_ns
    from dyknow.reasoning.syntax import Formula, check_formula, parse, parse_value
    from dyknow.reasoning.unit import FormulaMonitor, monitor_spec, term_ports

__all__ = [
    "Formula",
    "FormulaError",
    "FormulaMonitor",
    "Monitor",
    "ObjectMonitor",
    "Requirement",
    "Result",
    "Verdict",
    "check_formula",
    "check_recording",
    "evaluate",
    "evaluate_ns",
    "evaluate_objects_ns",
    "evaluate_values_ns",
    "junit_xml",
    "load_requirements",
    "monitor_spec",
    "parse",
    "parse_value",
    "term_ports",
    "write_verdicts",
]

#: Where each public name is defined, imported on first use: a module that needs only the syntax
#: (the service's bounds, a spec's requirements) does not import the monitors (dyknow.exports).
_WHERE = {
    "Formula": "dyknow.reasoning.syntax",
    "FormulaError": "dyknow.errors",
    "FormulaMonitor": "dyknow.reasoning.unit",
    "Monitor": "dyknow.reasoning.progression",
    "ObjectMonitor": "dyknow.reasoning.objects",
    "Requirement": "dyknow.reasoning.requirements",
    "Result": "dyknow.reasoning.requirements",
    "Verdict": "dyknow.reasoning.progression",
    "check_formula": "dyknow.reasoning.syntax",
    "check_recording": "dyknow.reasoning.requirements",
    "evaluate": "dyknow.reasoning.semantics",
    "evaluate_ns": "dyknow.reasoning.semantics",
    "evaluate_objects_ns": "dyknow.reasoning.semantics",
    "evaluate_values_ns": "dyknow.reasoning.semantics",
    "junit_xml": "dyknow.reasoning.requirements",
    "load_requirements": "dyknow.reasoning.requirements",
    "monitor_spec": "dyknow.reasoning.unit",
    "parse": "dyknow.reasoning.syntax",
    "parse_value": "dyknow.reasoning.syntax",
    "term_ports": "dyknow.reasoning.unit",
    "write_verdicts": "dyknow.reasoning.requirements",
}


def _restore_docstring(name: str, value: Any) -> None:  # Monitor and Verdict are compiled by mypyc
    from dyknow.resources import restore_docstrings

    restore_docstrings({name: value}, [name])


_exported, __dir__ = lazy_exports(__name__, globals(), _WHERE, after=_restore_docstring)

#: Names of 0.1 that now say their time unit (0.2): still served, with a DeprecationWarning.
_RENAMED = {"evaluate_values": "evaluate_values_ns", "evaluate_objects": "evaluate_objects_ns"}


def __getattr__(name: str) -> Any:
    if name in _RENAMED:
        import warnings

        new = _RENAMED[name]
        warnings.warn(f"dyknow.reasoning.{name} is now {new}: the same function, whose name says its times are nanoseconds "
                      "(evaluate takes seconds, as time.time; the _ns ones nanoseconds, as time.time_ns)", DeprecationWarning, stacklevel=2)  # fmt: skip
        return _exported(new)
    return _exported(name)
