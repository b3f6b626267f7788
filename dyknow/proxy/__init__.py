"""The proxy of a unit: binds its named ports to Zenoh key expressions and runs its callbacks.

One proxy per running unit. It

- binds every port to a key expression (by default ``dyknow/<manager>/<unit>/<port>``) and can
  rebind any subset of them atomically while the unit runs (``set_config``), without restarting
  the unit or touching the other ports;
- delivers messages: to local input ports through the manager's :class:`~dyknow.bus.LocalBus` by
  reference (no copy, no serialization), and to and from other processes through Zenoh;
- queues each input in a bounded queue (keep-last by default, like a Zenoh ring channel; or
  drop-new) and counts drops, so a slow unit never blocks its upstream;
- measures every message at every input port (age since origin, time since the previous hop) and
  counts messages and bytes per port (``get_statistics``);
- isolates failures: an exception in ``setup``, a callback or ``run`` marks the unit failed, with
  its error and traceback, and the rest of the manager carries on.

Its job is the executor's *job* for the unit (see :mod:`dyknow.executor`), and the proxy is the
unit's :class:`~dyknow.unit.UnitRuntime`: the proxy owns the wiring, handing itself to the unit
through :func:`dyknow.unit.attach` when it is created.

==========================  ==============================================================================
module                      what it holds
==========================  ==============================================================================
:mod:`~.proxy`              :class:`Proxy`: the unit's lifecycle, its ports bound and rebound, failure
                            isolation, statistics (:class:`UnitStatistics`); the unit's runtime
:mod:`~.job`                :class:`~.job.UnitJob`: the unit's callbacks run on its lane or inline, timed,
                            moved when slow, shed under load; what it publishes; :class:`UnitState`
:mod:`~.ports`              :class:`InputPort`, :class:`OutputPort`: queues, counters, a message's age and hop
==========================  ==============================================================================

Imports flow one way: ``ports <- job <- proxy``.
"""

from __future__ import annotations

from dyknow.proxy.job import UnitState
from dyknow.proxy.ports import InputPort, OutputPort
from dyknow.proxy.proxy import DEFAULT_QUEUE_DEPTH, Proxy, UnitStatistics

__all__ = ["DEFAULT_QUEUE_DEPTH", "InputPort", "OutputPort", "Proxy", "UnitState", "UnitStatistics"]
