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
from dyknow.resources import restore_docstrings
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


restore_docstrings(globals(), __all__)
