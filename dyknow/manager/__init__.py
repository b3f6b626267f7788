"""The manager: a library of transformation specs and the units spawned from them.

A manager owns one Zenoh session, a :class:`~dyknow.library.Library`, the running units (each
with its :class:`~dyknow.proxy.Proxy`), the local bus between them and the executor that runs
them. Its services, as Python methods and as Zenoh services (see :mod:`dyknow.service`):

- ``add_transformation`` / ``remove_transformation``: manage the library (a template adds one
  spec per substitution; an existing label is replaced);
- ``spawn(label, name, protected=False)`` / ``destroy(name)``: start and stop units (protected
  units refuse destroy; a unit may destroy itself);
- ``get_model()``: every running unit with its label, state, protection and bindings, plus every
  stored spec;
- per unit: ``get_config``, ``set_config``, ``get_statistics`` (the proxy services).

Usage::

    with Manager("robot", specs=["specs/"]) as manager:
        manager.spawn("periodic-source", "src")
        manager.spawn("relay", "relay1", bindings={"in": "dyknow/robot/src/out"})

The :class:`Manager` (:mod:`~dyknow.manager.manager`) is composed of parts, a module each, that
know the manager only through what they are given:

- :mod:`~dyknow.manager.network`: its Zenoh session, over its endpoints or behind routers, with
  its TLS files and roles checked first;
- :mod:`~dyknow.manager.library`: the specs loaded at start and added at runtime, and who gave
  each (the operator's are trusted, a remote caller's confined);
- :mod:`~dyknow.manager.spawning`: the running units, each imported under the operator's source
  policy, given its params, bindings and proxy, and destroyed again;
- :mod:`~dyknow.manager.ros2`: its ROS 2 node and DDS participant, and the companion units of
  ports bound to ROS 2 topics;
- :mod:`~dyknow.manager.measurements`: the values of measures its specs' constraints read;
- :mod:`~dyknow.manager.peers`: the manager among the others (its summary, its calls on them, the
  units it runs for them, their clocks);
- :mod:`~dyknow.manager.services`: its Zenoh services, answered through its public interface.
"""

from __future__ import annotations

from dyknow.manager.manager import Manager

__all__ = ["Manager"]
