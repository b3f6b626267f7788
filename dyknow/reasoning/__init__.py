"""Temporal reasoning over streams: formulas, their exact semantics and incremental monitors."""

from __future__ import annotations

from dyknow.errors import FormulaError
from dyknow.reasoning.progression import Monitor, Verdict
from dyknow.reasoning.semantics import evaluate, evaluate_ns
from dyknow.reasoning.syntax import Formula, parse

__all__ = ["Formula", "FormulaError", "Monitor", "Verdict", "evaluate", "evaluate_ns", "parse"]
