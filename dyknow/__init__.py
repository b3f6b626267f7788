"""dyknow: reconfigurable stream reasoning middleware for robots, on Eclipse Zenoh.

The public API::

    from dyknow import Manager, Unit, Client

    class Doubler(Unit):
        def on_message(self, port, msg):
            self.publish("out", msg.payload * 2)

The documentation site (``make docs``, from ``docs/``) explains the concepts: transformation
specs, the manager, units and their proxies.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from dyknow.exports import lazy_exports

if TYPE_CHECKING:
    from dyknow.access import AccessControl, TlsFiles
    from dyknow.adaptation import AdaptationEvent
    from dyknow.client import Client
    from dyknow.errors import (
        AccessError,
        BindingError,
        ClosedError,
        DyKnowError,
        FormulaError,
        LibraryError,
        OntologyError,
        PlanningError,
        RecordingError,
        ServiceError,
        SpecError,
        SpecIssue,
        TagError,
        TransportError,
        UnitError,
    )
    from dyknow.executor import Timer
    from dyknow.keys import default_key
    from dyknow.library import Library
    from dyknow.manager import Manager
    from dyknow.message import Message, PayloadError
    from dyknow.model import Model, RequestInfo, UnitEvent, UnitInfo
    from dyknow.ontology import Ontology
    from dyknow.planner import Plan, Planner, RunningUnit, plan
    from dyknow.proxy import UnitState, UnitStatistics
    from dyknow.recording import ChannelInfo, Player, RecordedMessage, Recorder, Recording, RecordingInfo
    from dyknow.security import Limits
    from dyknow.spec import (
        Constraint,
        Param,
        Port,
        Tag,
        Template,
        TransformationSpec,
        load_specs,
        parse_specs,
    )
    from dyknow.stats import LatencySummary, PortStatistics
    from dyknow.tags import Term, parse_term
    from dyknow.transport import DEFAULT_ENDPOINT
    from dyknow.unit import Unit

__version__ = "0.1.0"

__all__ = [
    "DEFAULT_ENDPOINT",
    "AccessControl",
    "AccessError",
    "AdaptationEvent",
    "BindingError",
    "ChannelInfo",
    "Client",
    "ClosedError",
    "Constraint",
    "DyKnowError",
    "FormulaError",
    "LatencySummary",
    "Library",
    "LibraryError",
    "Limits",
    "Manager",
    "Message",
    "Model",
    "Ontology",
    "OntologyError",
    "Param",
    "PayloadError",
    "Plan",
    "Planner",
    "PlanningError",
    "Player",
    "Port",
    "PortStatistics",
    "RecordedMessage",
    "Recorder",
    "Recording",
    "RecordingError",
    "RecordingInfo",
    "RequestInfo",
    "RunningUnit",
    "ServiceError",
    "SpecError",
    "SpecIssue",
    "Tag",
    "TagError",
    "Template",
    "Term",
    "Timer",
    "TlsFiles",
    "TransformationSpec",
    "TransportError",
    "Unit",
    "UnitError",
    "UnitEvent",
    "UnitInfo",
    "UnitState",
    "UnitStatistics",
    "__version__",
    "default_key",
    "load_specs",
    "parse_specs",
    "parse_term",
    "plan",
]

#: Where each public name is defined: imported on first use (``import dyknow`` stays cheap, so the
#: ``dyknow`` command starts fast; :mod:`dyknow.exports`).
_WHERE: dict[str, str] = {
    "AccessControl": "dyknow.access",
    "AccessError": "dyknow.errors",
    "AdaptationEvent": "dyknow.adaptation",
    "BindingError": "dyknow.errors",
    "ChannelInfo": "dyknow.recording",
    "Client": "dyknow.client",
    "ClosedError": "dyknow.errors",
    "Constraint": "dyknow.spec",
    "DEFAULT_ENDPOINT": "dyknow.transport",
    "DyKnowError": "dyknow.errors",
    "FormulaError": "dyknow.errors",
    "LatencySummary": "dyknow.stats",
    "Library": "dyknow.library",
    "LibraryError": "dyknow.errors",
    "Limits": "dyknow.security",
    "Manager": "dyknow.manager",
    "Message": "dyknow.message",
    "Model": "dyknow.model",
    "Ontology": "dyknow.ontology",
    "OntologyError": "dyknow.errors",
    "Param": "dyknow.spec",
    "PayloadError": "dyknow.message",
    "Plan": "dyknow.planner",
    "Planner": "dyknow.planner",
    "PlanningError": "dyknow.errors",
    "Player": "dyknow.recording",
    "Port": "dyknow.spec",
    "PortStatistics": "dyknow.stats",
    "RecordedMessage": "dyknow.recording",
    "Recorder": "dyknow.recording",
    "Recording": "dyknow.recording",
    "RecordingError": "dyknow.errors",
    "RecordingInfo": "dyknow.recording",
    "RequestInfo": "dyknow.model",
    "RunningUnit": "dyknow.planner",
    "ServiceError": "dyknow.errors",
    "SpecError": "dyknow.errors",
    "SpecIssue": "dyknow.errors",
    "Tag": "dyknow.spec",
    "TagError": "dyknow.errors",
    "Template": "dyknow.spec",
    "Term": "dyknow.tags",
    "Timer": "dyknow.executor",
    "TlsFiles": "dyknow.access",
    "TransformationSpec": "dyknow.spec",
    "TransportError": "dyknow.errors",
    "Unit": "dyknow.unit",
    "UnitError": "dyknow.errors",
    "UnitEvent": "dyknow.model",
    "UnitInfo": "dyknow.model",
    "UnitState": "dyknow.proxy",
    "UnitStatistics": "dyknow.proxy",
    "default_key": "dyknow.keys",
    "load_specs": "dyknow.spec",
    "parse_specs": "dyknow.spec",
    "parse_term": "dyknow.tags",
    "plan": "dyknow.planner",
}


def _restore_docstring(name: str, value: Any) -> None:
    from dyknow.resources import restore_docstrings

    restore_docstrings({name: value}, [name])


__getattr__, __dir__ = lazy_exports(__name__, globals(), _WHERE, after=_restore_docstring)
