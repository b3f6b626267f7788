"""Computation units: the base class users subclass.

A unit is a Python class named in a transformation spec's ``<source>`` (``package.module:Class``).
The manager instantiates it with no arguments, binds its ports, sets a few attributes, and calls
its hooks. A minimal unit::

    from dyknow import Unit

    class Doubler(Unit):
        def on_message(self, port, msg):
            self.publish("out", msg.payload * 2)

Hooks (override the ones you need; all run on the unit's executor thread, never two at once):

- ``setup()``: once, after the ports are bound; acquire resources, create timers. An exception
  here marks the unit failed.
- ``on_message(port, msg)``: for each message arriving on an input port.
- ``on_reconfigure(changes)``: after ports were rebound at runtime, with ``{port: new_key}``.
- ``teardown()``: once, when the unit is destroyed; release resources.
- ``run(stop)``: optional blocking loop (a camera read loop, say) on a thread of its own; return
  when the ``stop`` event is set. Publishing from it is safe.

Attributes set before ``setup()``: ``name`` (the instance name), ``label`` (its spec's label),
``params`` (typed values from the spec, with spawn-time overrides) and ``log`` (a logger: the
shared ``dyknow.unit`` logger, the unit's name in front of each message and in ``record.unit``). Those
names and the methods below are the unit's interface with dyknow; other attribute names are
free for the unit's own state.

How a unit is wired: the unit's proxy (:mod:`dyknow.proxy`) calls :func:`attach` once, before
``setup()``, handing over itself as the unit's :class:`UnitRuntime`; every service
below goes through it. This module knows only that small protocol, not the proxy. To run a unit
in a test, spawn it in a manager, or use :mod:`dyknow.testing`.

Set the class attribute ``dedicated_thread = True`` for units whose callbacks are known to be slow
(heavy image processing): they get a thread of their own from the start instead of after their
first slow callbacks.

Set ``forward_to = "out"`` for a unit that passes every message on unchanged (a relay, a bridge
between keys): dyknow then publishes each message arriving on any input on that output itself,
origin time and payload as they came, and no Python of the unit runs per message. A payload from
another process goes on as the bytes it arrived as. Such a unit does not override ``on_message``
(the manager refuses one that does); it may still publish from timers or ``run``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from dyknow.errors import UnitError

if TYPE_CHECKING:
    from dyknow.executor import Timer
    from dyknow.message import Message

__all__ = ["Unit", "UnitRuntime", "attach"]


class UnitRuntime(Protocol):
    """What a unit needs of the runtime that runs it; a unit's proxy provides it."""

    def publish(self, port: str, payload: Any, origin_ns: int | None = None) -> None:
        """Send ``payload`` from output ``port``."""
        ...

    def create_timer(self, period_s: float, callback: Callable[[], None], first_s: float | None = None) -> Timer:
        """Call ``callback`` every ``period_s`` seconds on the unit's thread."""
        ...

    def request_destroy(self) -> None:
        """Destroy the unit (after the callback running now)."""
        ...

    def has_subscribers(self, port: str) -> bool:
        """Whether anyone receives output ``port`` now."""
        ...

    def reject(self, port: str, reason: str, *, expected: bool = False) -> None:
        """Count and log an unusable input message."""
        ...

    def get_config(self) -> dict[str, str]:
        """The port -> key bindings."""
        ...

    def set_config(self, changes: Mapping[str, str]) -> dict[str, str]:
        """Rebind some ports; returns the new bindings."""
        ...

    def fail(self, reason: str) -> None:
        """Mark the unit failed."""
        ...

    def watch_liveliness(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """Call ``on_change(key, alive)`` as producers on ``key_expr`` appear and vanish."""
        ...

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn()`` on the unit's thread, like its other callbacks (from any thread)."""
        ...


#: The services of :class:`UnitRuntime`, by name.
_SERVICES = frozenset(name for name in vars(UnitRuntime) if not name.startswith("_"))


class _Detached:
    """The runtime of a unit that no manager runs: every service says how to run the unit."""

    def __getattr__(self, name: str) -> Any:
        if name not in _SERVICES:
            # help(), pydoc, Sphinx's autodoc, copy and pickle probe for dunders such as
            # __objclass__ and expect AttributeError: only the services answer with advice
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        raise UnitError(
            f"the unit is not running, so it cannot {name.replace('_', ' ')}",
            expected="a unit spawned by a Manager (or run by dyknow.testing.UnitHarness in a test)",
        )

    def __repr__(self) -> str:
        return "<no runtime: the unit is not running>"


_DETACHED: Any = _Detached()


class Unit:
    """Base class of computation units: subclass it, override the hooks you need, name the class in
    a transformation spec's ``<source>`` (``mypkg.doubler:Doubler``).

    Example::

        from dyknow import Unit

        class Doubler(Unit):
            def setup(self):                   # once, after the ports are bound
                self.factor = self.params["factor"]

            def on_message(self, port, msg):   # each message on an input port
                self.log.debug("got %s on %s", msg.seq, port)
                self.publish("out", msg.payload * self.factor)

    Set by dyknow before ``setup()``:

    - ``name``: the unit's instance name (``dyknow spawn doubler NAME``);
    - ``label``: its transformation spec's label;
    - ``params``: the spec's typed params, with spawn-time overrides (``--param factor=3``);
    - ``log``: a logger that puts the unit's name in front of each message.

    Hooks, on the unit's thread, never two at once: ``setup()``, ``on_message(port, msg)``,
    ``on_reconfigure(changes)``, ``teardown()``, and ``run(stop)`` (a blocking loop on a thread of
    its own). Services: ``publish``, ``create_timer``, ``reject``, ``fail``, ``has_subscribers``,
    ``get_config``, ``set_config``, ``watch_liveliness``, ``call_soon``, ``destroy``.

    Class attributes: ``dedicated_thread`` (slow callbacks: a thread of its own from the start),
    ``forward_to`` (pass every message on unchanged, without Python per message), ``path_params``
    (params that name files). The module documentation has the details;
    :class:`dyknow.testing.UnitHarness` runs one in a test.
    """

    #: Run this unit's callbacks on a thread of its own from the start.
    dedicated_thread: ClassVar[bool] = False

    #: The output port on which dyknow itself publishes every input message unchanged, instead of
    #: calling ``on_message`` (see the module documentation); None: ``on_message`` handles them.
    forward_to: ClassVar[str | None] = None

    #: The params that name files, and what the unit does with them: ``{"path": "write"}``.
    #: For a remote caller the manager confines them to its data roots, whatever the spec says.
    path_params: ClassVar[Mapping[str, str]] = {}

    name: str
    label: str
    params: Mapping[str, Any]
    log: logging.Logger | logging.LoggerAdapter  # type: ignore[type-arg]
    _runtime: UnitRuntime = _DETACHED

    # -- hooks

    def setup(self) -> None:
        """Called once after the ports are bound. Override to acquire resources and create timers."""

    def on_message(self, port: str, msg: Message) -> None:
        """Called for each message arriving on input port ``port``. Override it."""

    def on_reconfigure(self, changes: Mapping[str, str]) -> None:
        """Called after ports were rebound at runtime; ``changes`` maps port to its new key."""

    def teardown(self) -> None:
        """Called once when the unit is destroyed. Override to release resources."""

    def run(self, stop: threading.Event) -> None:
        """Optional blocking loop on a thread of its own; return when ``stop`` is set."""

    # -- services for the unit

    def publish(self, port: str, payload: Any, *, origin_ns: int | None = None) -> None:
        """Publish ``payload`` on output ``port``.

        The origin timestamp is taken from the message being handled (so it propagates through
        every hop), or is now when the unit publishes outside a callback (a source); pass
        ``origin_ns`` (``time.time_ns()`` clock) to set it explicitly, e.g. to a capture time.

        Publishing hands the payload over: numpy arrays become read-only, because local receivers
        get the very same object; copy an array first if you need to keep writing to it.
        """
        self._runtime.publish(port, payload, origin_ns)

    def create_timer(self, period_s: float, callback: Callable[[], None], *, first_s: float | None = None) -> Timer:
        """Call ``callback`` every ``period_s`` seconds on the unit's thread; returns the timer.

        The first call comes after ``first_s`` seconds (default: one period); a source that should
        deliver as soon as it starts passes ``first_s=0``.
        """
        return self._runtime.create_timer(period_s, callback, first_s)

    def destroy(self) -> None:
        """Ask the manager to destroy this unit (after the current callback returns).

        Refused with :class:`~dyknow.errors.UnitError` when the unit is protected.
        """
        self._runtime.request_destroy()

    def has_subscribers(self, port: str) -> bool:
        """Whether anyone (a local unit or another process) receives output ``port`` now.

        Lets a unit skip producing an output nobody consumes (a colour conversion, say).
        """
        return self._runtime.has_subscribers(port)

    def reject(self, port: str, reason: str, *, expected: bool = False) -> None:
        """Report that the message just received on ``port`` was unusable, and carry on.

        For bad input that is not the unit's fault (an image of the wrong shape, say): it is
        counted per port in the statistics (``rejected``, ``last_rejection``) and logged, and the
        unit keeps running. Raising instead would mark the unit failed. ``expected``: a rejection
        that is no one's mistake (a sample that came too late after its producer was switched) is
        counted alike but logged at INFO, not as a warning.
        """
        self._runtime.reject(port, reason, expected=expected)

    def set_config(self, bindings: Mapping[str, str]) -> dict[str, str]:
        """Rebind some of this unit's own ports (``{port: key}``) atomically; returns the new bindings.

        What the proxy's ``set_config`` service does, from inside the unit. Works from ``setup()``
        too, e.g. to subscribe to a key given as a param.
        """
        return self._runtime.set_config(bindings)

    def fail(self, reason: str) -> None:
        """Declare this unit failed (from any thread): it stops and the manager adapts around it."""
        self._runtime.fail(reason)

    def watch_liveliness(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """Call ``on_change(key, alive)`` when producers on ``key_expr`` appear or vanish.

        Every dyknow output port announces itself on its key, so this notices another process
        crashing within milliseconds. ``on_change`` runs like the unit's other callbacks (on its
        thread, never at the same time as them); an exception in it fails the unit.
        """
        self._runtime.watch_liveliness(key_expr, on_change)

    def call_soon(self, fn: Callable[[], None]) -> None:
        """Run ``fn()`` on the unit's thread as soon as it is free, like the unit's other callbacks
        (never at the same time as them; an exception in it fails the unit). Callable from any
        thread: a library's callback thread hands its work over this way, so that slow work (a
        decode, say) never holds the thread that called it. Dropped once the unit stops.
        """
        self._runtime.call_soon(fn)

    def get_config(self) -> dict[str, str]:
        """The current port -> key expression bindings (what the proxy's ``get_config`` serves)."""
        return self._runtime.get_config()


def attach(
    unit: Unit, runtime: UnitRuntime, *, name: str, label: str, params: Mapping[str, Any], log: logging.Logger | logging.LoggerAdapter  # type: ignore[type-arg]
) -> None:
    """Called by dyknow once per unit, before ``setup()``: set its attributes and its runtime.

    Not for units to call (a function of this module, not a method, so that ``help(Unit)`` shows
    what a unit's author uses). ``publish`` is bound straight to the runtime's, which saves a call
    on every message (:meth:`Unit.publish` still documents it).
    """
    unit.name = name
    unit.label = label
    unit.params = params
    unit.log = log
    unit._runtime = runtime
    unit.publish = runtime.publish  # type: ignore[method-assign]
