"""ROS 2 interop: dyknow streams as ROS 2 topics and ROS 2 topics as dyknow streams, natively on
rmw_zenoh's protocol and on DDS (no bridge process).

Modules, one per concept: :mod:`~dyknow.ros2.names` (keys, liveliness tokens, QoS strings, GIDs),
:mod:`~dyknow.ros2.attachment` (the 33-byte attachment), :mod:`~dyknow.ros2.types` (message
types, RIHS01 hashes, CDR), :mod:`~dyknow.ros2.convert` (messages <-> dyknow payloads),
:mod:`~dyknow.ros2.binding` (``ros2:`` bindings), :mod:`~dyknow.ros2.node` (a ROS 2 node on a
dyknow session), :mod:`~dyknow.ros2.services` (service clients and servers on rmw_zenoh), :mod:`~dyknow.ros2.graph` (the graph from the tokens), :mod:`~dyknow.ros2.dds` (the same topics
over DDS, Cyclone DDS), :mod:`~dyknow.ros2.bridge` (the units between the two),
:mod:`~dyknow.ros2.lifecycle` (another node's lifecycle and parameters, through its services),
:mod:`~dyknow.ros2.managed` (a node dyknow did not spawn as a provider the planner chooses)
and :mod:`~dyknow.ros2.diagnostics` (``/diagnostics`` published and read). Needs the
``ros2`` extra (``rosbags``, ``xxhash``, ``cyclonedds``), each imported only when used.
"""

from __future__ import annotations

from dyknow.ros2.attachment import Attachment
from dyknow.ros2.binding import DDS_SCHEME, SCHEME, Ros2Binding, is_ros2, parse_binding
from dyknow.ros2.bridge import Ros2Provider, Ros2Server, Ros2Sink, Ros2Source, UsesRos2
from dyknow.ros2.dds import DdsClient, DdsNode, DdsPublisher, DdsService, DdsSubscription
from dyknow.ros2.diagnostics import DiagnosticsPublisher, DiagnosticsSource, DiagnosticStatus
from dyknow.ros2.graph import Graph, GraphView, snapshot
from dyknow.ros2.lifecycle import NodeLifecycle
from dyknow.ros2.managed import ManagedNode
from dyknow.ros2.names import QoS, data_key, parse_data_key, parse_token
from dyknow.ros2.node import Received, Ros2Node, Ros2Publisher, Ros2Subscription
from dyknow.ros2.services import Ros2Client, Ros2Service
from dyknow.ros2.types import TypeSupport

__all__ = [
    "DDS_SCHEME",
    "SCHEME",
    "Attachment",
    "DdsClient",
    "DdsNode",
    "DdsPublisher",
    "DdsService",
    "DdsSubscription",
    "DiagnosticStatus",
    "DiagnosticsPublisher",
    "DiagnosticsSource",
    "Graph",
    "GraphView",
    "ManagedNode",
    "NodeLifecycle",
    "QoS",
    "Received",
    "Ros2Binding",
    "Ros2Client",
    "Ros2Node",
    "Ros2Provider",
    "Ros2Publisher",
    "Ros2Server",
    "Ros2Service",
    "Ros2Sink",
    "Ros2Source",
    "Ros2Subscription",
    "TypeSupport",
    "UsesRos2",
    "data_key",
    "is_ros2",
    "parse_binding",
    "parse_data_key",
    "parse_token",
    "snapshot",
]
