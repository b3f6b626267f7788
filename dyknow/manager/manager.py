"""The Manager: its parts composed, its lifecycle, and the public interface over them.

A :class:`Manager` joins the network (:mod:`~dyknow.manager.network`), composes its parts
(:mod:`~dyknow.manager.library`, :mod:`~dyknow.manager.spawning`, :mod:`~dyknow.manager.ros2`,
:mod:`~dyknow.manager.measurements`, :mod:`~dyknow.manager.peers`,
:mod:`~dyknow.manager.services`) with the bus, the executor, the adaptation loop and the formula
monitors, and answers for them all: every public method is here, and the parts call each other
only through what it hands them. It keeps what crosses its parts: the unit events, the requests
and monitors, the model, the load and what it sheds when it falls behind; and it closes
everything in reverse order.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any

from dyknow import keys
from dyknow.access import AccessControl, TlsFiles
from dyknow.adaptation import ANCHOR_LABEL, DEFAULT_DWELL_S, AdaptationEvent, AdaptationLoop, DeadlinePort, Flaps
from dyknow.bus import LocalBus
from dyknow.client import Client
from dyknow.errors import AccessError, BindingError, ClosedError, DyKnowError
from dyknow.executor import DEFAULT_MAX_LANES, Executor
from dyknow.federation import Directory, Summary
from dyknow.holders import DEFAULT_GRACE_S, Holders
from dyknow.manager.feeds import MeasureFeeds
from dyknow.manager.health import DIAGNOSTICS_MIDDLEWARES, Health, StatusSource
from dyknow.manager.library import Librarian
from dyknow.manager.measurements import Measurements
from dyknow.manager.modes import mode_infos
from dyknow.manager.network import Network
from dyknow.manager.peers import Peers
from dyknow.manager.ros2 import Ros2Wiring, ros2_bindings
from dyknow.manager.services import Services
from dyknow.manager.spawning import Spawner
from dyknow.memory import Trimmer
from dyknow.message import CLOCK_ID
from dyknow.metrics import Metrics
from dyknow.model import LOCAL, Model, Owner, RequestInfo, UnitEvent, UnitInfo
from dyknow.ontology import Ontology
from dyknow.overload import DEFAULT_LAG_BUDGET_S, OverloadGuard, OverloadState, describe
from dyknow.priority import current_nice
from dyknow.proxy import DEFAULT_QUEUE_DEPTH, Proxy, UnitStatistics
from dyknow.reasoning.monitors import MonitorInfo, Monitors
from dyknow.reasoning.syntax import Formula, check_formula
from dyknow.reasoning.unit import FormulaMonitor, MonitorBudget
from dyknow.receiver import Receiver
from dyknow.ros2.dds import DdsNode
from dyknow.ros2.diagnostics import DiagnosticStatus
from dyknow.ros2.node import Ros2Node
from dyknow.security import DataRoots, Limits
from dyknow.spec import Template, TransformationSpec
from dyknow.spec.model import MANAGED_NODE_SOURCE
from dyknow.stats import PortCounters
from dyknow.tags import parse_term
from dyknow.transport import Session, check_key_expr
from dyknow.unit import Unit

__all__ = ["Manager"]

log = logging.getLogger("dyknow.manager")  # one name for the manager, whichever part logs


class Manager:
    """Spawns units from transformation specs and serves the DyKnow services. A context manager.

    ``specs``: spec files, directories of ``*.xml`` files, or specs to load at start.
    ``listen``/``connect``: Zenoh endpoints (default: listen on a free loopback port, connect to
    nothing); ``zenoh_config``: a json5 Zenoh configuration file to join a real deployment instead.
    ``router``: the manager sits behind these Zenoh routers (``dyknow router``), as in a fleet: it
    dials the first that answers and holds that one link, listens on nothing, and reaches every
    other manager through it (a Zenoh client); the others are standbys it dials when the link is
    lost. Not with ``listen`` or ``connect``.
    ``serve``: declare the Zenoh services so other processes can call this manager.
    ``queue_depth``: the input queue size of ports whose spec sets none. ``stall_budget_s`` and
    ``slow_callback_s``: when a unit leaves the shared thread (see :mod:`dyknow.executor`);
    ``max_lanes``: the most threads the manager runs units on, whatever the load (units that ask
    for a thread of their own aside). ``overload_lag_s``: how long a message may wait for its
    unit's turn before the manager counts as overloaded and sheds its least important work (see
    :mod:`dyknow.overload`).
    ``dwell_s``: how long a request keeps a configuration before switching for a better one.
    ``damping``: how relapses are damped (:class:`~dyknow.adaptation.Flaps`: suspects whose
    requirement is false again, transformations that fail again, managers lost again).

    Where units' code comes from: an installed package, ``PYTHONPATH``, or a module or package
    beside a spec file the operator gave (at start or through the Python API) or in one of
    ``code_paths`` (``--path DIR``): a unit's module that is not importable otherwise is looked
    for there (``thermo.py`` beside ``thermo.xml`` is found), without changing ``sys.path``.

    Security (see :mod:`dyknow.security`): ``allow_sources`` adds unit sources the manager may
    load (beyond ``dyknow``, ``transformations`` and the modules its specs name);
    ``data_roots`` are the folders file params may name for remote callers (reads also may name
    the folders of ``specs``); ``limits`` bound what one request may cost. The Python API is
    trusted: it may pass any source and any path. ``tls``: TLS with mutual authentication
    (:class:`~dyknow.access.TlsFiles`); ``acl``: roles by certificate common name
    (:class:`~dyknow.access.AccessControl`, or the path of its JSON5 file), enforced by Zenoh.

    Several managers (see :mod:`dyknow.federation`): ``federate`` (default: when it serves) makes
    the manager announce itself and its summary and plan over the libraries and units of every
    manager it reaches. ``host`` names the machine it runs on (default: the host name);
    ``lease_ms``: how soon a silent link, so a cut-off manager, is given up (Zenoh's lease).

    Requests made by a :class:`~dyknow.client.Client` are held by it (:mod:`dyknow.holders`):
    ``client_grace_s`` after the client is gone, the references it held are released.

    ``diagnostics``: publish the health of its requirements, monitored formulas, requests and
    managed nodes on ROS 2's ``/diagnostics`` (:mod:`dyknow.manager.health`), ``"ros2"`` on its
    ROS 2 node (rmw_zenoh), ``"ros2dds"`` on its DDS participant; None (the default): not
    published (:meth:`diagnostic_statuses` still says them).

    It is the adaptation loop's :class:`~dyknow.adaptation.Runtime`.
    """

    def __init__(
        self,
        name: str,
        *,
        specs: Iterable[str | os.PathLike[str] | TransformationSpec] = (),
        listen: Sequence[str] | None = None,
        connect: Sequence[str] = (),
        router: Sequence[str] = (),
        zenoh_config: str | os.PathLike[str] | None = None,
        serve: bool = True,
        ontology: Ontology | Iterable[str | os.PathLike[str]] | None = None,
        queue_depth: int = DEFAULT_QUEUE_DEPTH,
        stall_budget_s: float = 0.02,
        slow_callback_s: float = 0.002,
        max_lanes: int = DEFAULT_MAX_LANES,
        overload_lag_s: float = DEFAULT_LAG_BUDGET_S,
        dwell_s: float = DEFAULT_DWELL_S,
        damping: Flaps | None = None,
        allow_sources: Iterable[str] = (),
        code_paths: Iterable[str | os.PathLike[str]] = (),
        data_roots: Iterable[str | os.PathLike[str]] = (),
        limits: Limits | None = None,
        tls: TlsFiles | None = None,
        acl: AccessControl | str | os.PathLike[str] | None = None,
        host: str | None = None,
        lease_ms: int | None = None,
        federate: bool | None = None,
        client_grace_s: float = DEFAULT_GRACE_S,
        ros2_domain: int | None = None,
        ros2_node: str | None = None,
        ros2_namespace: str = "/",
        dds_config: str | None = None,
        diagnostics: str | None = None,
    ) -> None:
        self.name = keys.check_name(name, "manager name")
        if diagnostics not in (None, *DIAGNOSTICS_MIDDLEWARES):
            raise BindingError(
                f"diagnostics={diagnostics!r}",
                where=f"manager {name!r}",
                expected="'ros2' (on the manager's ROS 2 node, rmw_zenoh), 'ros2dds' (on its DDS participant) or None (not published)",
            )
        if ontology is None or isinstance(ontology, Ontology):
            self.ontology: Ontology | None = ontology
        else:
            paths_ = list(ontology)
            self.ontology = Ontology.load(paths_) if paths_ else None  # bad ontologies fail first
        self.limits = limits = limits or Limits()
        # the specs loaded at start and added at runtime, and where their units' code may come from
        self._librarian = librarian = Librarian(
            specs=specs, ontology=self.ontology, limits=limits, allow_sources=allow_sources, code_paths=code_paths
        )
        self.library = librarian.library
        self._roots = DataRoots(write=data_roots, read=librarian.spec_dirs)
        self._lock = threading.RLock()
        self._metrics: Metrics | None = None
        self._closed = False
        network = Network(
            self.name,
            listen=listen,
            connect=connect,
            router=router,
            zenoh_config=zenoh_config,
            tls=tls,
            acl=acl,
            lease_ms=lease_ms,
            limits=limits,
        )
        self._network = network
        self._access = network.access
        self._session = network.session
        self.host = host or socket.gethostname()
        # calls to the other managers, signed with this manager's certificate (dyknow.identity)
        calls = Client(self.name, session=self._session, timeout_s=3.0, tls=network.tls)
        self._bus = LocalBus()
        self._receiver = Receiver(self._session, self.name)
        self._guard = OverloadGuard(
            self.name,
            lag_budget_s=overload_lag_s,
            priorities=self._shed_priorities,
            apply=self._apply_shed,
            on_change=self._overload_changed,
            clock_ns=time.time_ns,
        )
        self._executor = Executor(
            name, stall_budget_s=stall_budget_s, slow_callback_s=slow_callback_s, max_lanes=max_lanes, on_load=self._guard.reading
        )
        self._listeners: list[Callable[[UnitEvent], None]] = []
        self._services: Services | None = None
        self._holders: Holders | None = None
        self._monitor_budget = MonitorBudget(limits)  # the cells its formula monitors share
        self._trimmer = Trimmer(self.name)  # gives back the memory of formula monitors gone
        self._spawner = Spawner(
            self.name,
            lock=self._lock,
            limits=limits,
            librarian=librarian,
            roots=self._roots,
            session=self._session,
            bus=self._bus,
            receiver=self._receiver,
            executor=self._executor,
            queue_depth=queue_depth,
            monitor_budget=self._monitor_budget,
            ros2=self,
            check_open=self._check_open,
            closed=lambda: self._closed,
            emit=self._emit,
        )
        # ROS 2 (dyknow.ros2): the node is made when first needed (or now, when named); ports
        # bound to ros2: topics are wired through a companion unit each
        self._ros2 = Ros2Wiring(
            self.name,
            session=self._session,
            limits=limits,
            lock=self._lock,
            check_open=self._check_open,
            spawner=self._spawner,
            library=self.library,
            options=(ros2_domain, ros2_node, ros2_namespace),
            dds_config=dds_config,
        )
        self._adaptation = AdaptationLoop(self, dwell_s=dwell_s, damping=damping)
        self._peers = Peers(
            self.name,
            self.host,
            session=self._session,
            client=calls,
            lock=self._lock,
            spawner=self._spawner,
            library=self.library,
            adaptation=self._adaptation,
        )
        self.on_unit_event(self._adaptation.unit_event)
        self._monitors = Monitors(
            self.name,
            request=self.request,
            release=self._adaptation.release,
            spawn=lambda spec, name, bindings, owner: self.spawn(spec, name, bindings=bindings, owner=owner),
            destroy=self.destroy,
            unit=self.unit,
            individuals=librarian.individuals_or_none(),
            max_expansions=self.limits.max_expansions,
            limits=self.limits,
            budget=self._monitor_budget.check,
        )
        self._adaptation.on_event(lambda event: self._monitors.adapted(event.key, event.cause) if event.kind == "adapted" else None)
        self._measurements = Measurements(
            self.name, self.host, session=self._session, library=self.library, adaptation=self._adaptation, changed=self.changed
        )
        self._feeds = MeasureFeeds(
            record=self.measure,
            constraints=lambda name: [c for spec in self.library.specs() for c in spec.constraints if c.measure == name],
            spawn=lambda spec, name, bindings: self.spawn(spec, name, bindings=bindings, protected=True),
            unit=self.unit,
            destroy=lambda name: self.destroy(name, force=True),
        )
        try:
            self._measurements.declare()
        except DyKnowError:
            self.close()
            raise
        if serve:
            try:
                self._holders = Holders(self._session, self.name, self._release_gone, grace_s=client_grace_s)
                self._services = Services(
                    self, session=self._session, peers=self._peers, holders=self._holders, verifier=network.verifier, access=self._access
                )
            except DyKnowError:
                self.close()
                raise
        if federate if federate is not None else serve:
            try:
                self._peers.federate()
            except DyKnowError:
                self.close()
                raise
        if network.tls is None and self.exposed():
            log.warning(
                "manager %r is reachable beyond this host without TLS (%s): anyone who reaches it may call its services",
                self.name,
                ", ".join(self.exposed()),
            )
        if ros2_node is not None:
            try:
                self.ros2_node()
            except DyKnowError:
                self.close()
                raise
        # its health on /diagnostics (dyknow.manager.health): the statuses are kept whether or not published
        self._health = Health(self._ros2.node_name(), self, self._adaptation.knowledge)
        self.on_unit_event(self._health.unit_event)
        self._adaptation.on_event(lambda event: self._health.notify())
        if diagnostics is not None:
            try:
                self._health.publish_on(self.dds_node() if diagnostics == "ros2dds" else self.ros2_node())
            except DyKnowError:
                self.close()
                raise
        log.info("manager %r ready with %d specs", self.name, len(self.library))

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> Manager:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self, timeout_s: float = 2.0) -> None:
        """Destroy every unit (protected ones too), stop the threads, close the session. Safe twice.

        Bounded by about ``timeout_s``: a unit stuck in a callback does not hold it up.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._measurements.undeclare()
            proxies = self._spawner.close()  # (the feeds' units among them)
        if hasattr(self, "_health"):  # first: it reads the units (not made when __init__ failed before it)
            self._health.close()
        self._peers.say_goodbye()  # first: the others then know it stopped, and did not crash
        if self._services is not None:
            self._services.close(timeout_s / 4)
        if self._holders is not None:
            self._holders.close()
        self._adaptation.close(timeout_s / 2)  # releases what its requests run on other managers
        self._peers.close(timeout_s / 4)
        per_unit = min(0.5, timeout_s / max(1, len(proxies)))
        for proxy in reversed(proxies):
            proxy.stop(per_unit)
        self._executor.close(timeout_s)
        self._trimmer.close()
        self._receiver.close()
        self._ros2.close()
        self._session.close()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise ClosedError("the manager is closed", where=f"manager {self.name!r}", expected="a new Manager")

    @property
    def session(self) -> Session:
        """The manager's Zenoh session (for clients and tools living in the same process)."""
        return self._session

    def ros2_node(self) -> Ros2Node:
        """The manager's ROS 2 node on rmw_zenoh (made on first use): named ``ros2_node`` (default:
        the manager's name, with ``-`` and ``.`` as ``_``) in ``ros2_namespace``, on ROS domain
        ``ros2_domain`` (default: ``ROS_DOMAIN_ID``, else 0)."""
        return self._ros2.ros2_node()

    def dds_node(self) -> DdsNode:
        """The manager's DDS participant for ``ros2dds:`` bindings (made on first use), on ROS
        domain ``ros2_domain``, configured by ``dds_config`` (Cyclone XML; default: loopback only)."""
        return self._ros2.dds_node()

    def exposed(self) -> list[str]:
        """The endpoints this manager listens on beyond this host without TLS, or the routers it
        sits behind there (anyone who reaches them reaches the manager): a warning sign."""
        return self._network.exposed()

    @property
    def endpoints(self) -> list[str]:
        """The Zenoh locators this manager listens on, e.g. ``['tcp/127.0.0.1:7447']``."""
        return self._session.endpoints()

    # ------------------------------------------------------------------ library services

    def add_transformation(
        self, spec: TransformationSpec | Template | str | os.PathLike[str], *, path: str | None = None, remote: bool = False
    ) -> list[str]:
        """Store a spec, or every expansion of a template; returns the labels added.

        ``spec`` is a :class:`TransformationSpec`, a :class:`Template`, XML text, or the path of a
        spec file. An existing label is replaced. ``remote``: the spec came through the service,
        from a caller the manager does not trust: it must be XML text, every source it names
        must be allowed (:class:`AccessError` otherwise, before anything is imported or added),
        and the file params of its units are confined to the data roots when they are spawned.
        """
        self._check_open()
        labels = self._librarian.add(spec, path=path, remote=remote)
        self._adaptation.library_changed()
        self.changed()
        return labels

    def remove_transformation(self, label: str) -> bool:
        """Forget the spec with ``label``; returns whether there was one. Running units stay."""
        self._check_open()
        removed = self._librarian.remove(label)
        if removed:
            self._adaptation.library_changed()
            self.changed()
        return removed

    # ------------------------------------------------------------------ units

    def spawn(
        self,
        label: str | TransformationSpec,
        name: str,
        *,
        protected: bool = False,
        params: Mapping[str, Any] | None = None,
        bindings: Mapping[str, str] | None = None,
        remote: bool = False,
        owner: Owner = LOCAL,
    ) -> UnitInfo:
        """Start a unit of transformation ``label`` named ``name``.

        ``label`` names a spec of the library; a :class:`TransformationSpec` that is not in the
        library may be given directly instead (the request anchors are spawned so).
        ``params`` override the spec's param values (strings are parsed as the declared type);
        ``bindings`` bind ports to keys other than the default ``dyknow/<manager>/<name>/<port>``.
        A source that cannot be imported, or that is not a Unit, raises :class:`UnitError` and
        changes nothing. An exception in the unit's ``setup()`` leaves it in the model as failed.
        ``remote``: for a caller the manager does not trust (the service): the file params are
        confined to the data roots (so are those of specs added remotely, always); a refusal
        raises :class:`AccessError` and changes nothing.

        A binding ``ros2:/TOPIC?...`` (:mod:`dyknow.ros2.binding`) wires the port to a ROS 2 topic
        through a companion unit ``<name>.<port>.ros2`` (a :class:`~dyknow.ros2.bridge.Ros2Source`
        or :class:`~dyknow.ros2.bridge.Ros2Sink`), spawned after the unit and destroyed with it; if
        one cannot start, the unit is destroyed again and the error raised.

        ``owner``: whom it is spawned for (the services pass the caller): a formula monitor's
        nodes count against that caller's share of the monitors' nodes
        (:class:`~dyknow.reasoning.unit.MonitorBudget`; the Python API's against none). On a
        manager with roles, a managed ROS 2 node's unit (a spec's ``<node>``: it configures,
        activates and sets the parameters of the node its params name) needs a caller with the
        right ``manage`` (:meth:`~dyknow.access.AccessControl.may_manage`); else
        :class:`AccessError`, and nothing is started.
        """
        self._check_manages(label, params, owner)
        ros2 = ros2_bindings(bindings or {})
        account = owner.account()
        if not ros2:
            return self._spawner.spawn(label, name, protected=protected, params=params, bindings=bindings, remote=remote, account=account)
        return self._ros2.spawn(
            label, name, protected=protected, params=params, bindings=bindings or {}, ros2=ros2, remote=remote, account=account
        )

    def _check_manages(self, label: str | TransformationSpec, params: Mapping[str, Any] | None, owner: Owner) -> None:
        """Refuse a managed node's unit to a caller without the right ``manage`` (see :meth:`spawn`)."""
        access, caller = self._access, owner.caller
        if access is None or owner.local or caller is None:
            return
        try:
            spec = label if isinstance(label, TransformationSpec) else self.library.get(label)
        except DyKnowError:
            return  # (no such spec: the spawn says so)
        if spec.source != MANAGED_NODE_SOURCE or access.may_manage(caller):
            return
        node = (params or {}).get("node") or next((p.value for p in spec.params if p.name == "node"), "?")
        raise AccessError(
            f"{caller!r} may not spawn {spec.label!r}: it manages the ROS 2 node {str(node)[:200]} (its lifecycle and parameters)",
            where=f"manager {self.name!r}",
            expected=f"a caller whose role has the right manage in this manager's --acl ({' or '.join(access.roles_for_manage())})",
        )

    def destroy(self, name: str, *, force: bool = False) -> None:
        """Stop unit ``name`` and remove it from the model. A protected unit only with ``force``
        (through the service: by an admin, or by anyone when the manager has no roles).

        A unit still being spawned is destroyed once its spawn returns."""
        self._spawner.destroy(name, force=force)

    def unit_changes(self, since: int) -> tuple[int, list[str] | None]:
        """The version of the units now, and the names of those spawned, destroyed, rebound or
        failed after version ``since`` (None when the log no longer reaches back that far: read
        :meth:`units` again). What the adaptation loop's index follows."""
        return self._spawner.unit_changes(since)

    def unit_info(self, name: str) -> UnitInfo | None:
        """Unit ``name`` as :meth:`units` shows it; None when it does not run."""
        return self._spawner.info(name)

    def on_unit_event(self, listener: Callable[[UnitEvent], None]) -> Callable[[], None]:
        """Call ``listener(event)`` whenever a unit is spawned, fails or is destroyed.

        The listener runs on the thread where it happened and must be quick. Returns a function
        that removes the listener.
        """
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener) if listener in self._listeners else None

    def _emit(self, kind: str, proxy: Proxy) -> None:
        """The spawner says a unit was spawned, failed or was destroyed (its companions go with it)."""
        if kind == "destroyed":
            self._peers.unit_gone(proxy.name)
        self.changed()
        event = UnitEvent(kind, proxy.name, proxy.label, time.time_ns(), proxy.error if kind == "failed" else None)
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception:
                log.exception("unit event listener failed on %s", event)
        if kind == "destroyed":
            self._ros2.drop(proxy.name)
            if isinstance(proxy.unit, FormulaMonitor):  # (their states and object ids: the most memory units free at once)
                self._trimmer.soon()

    def unit(self, name: str) -> Unit:
        """The Python object of running unit ``name`` (for embedding and tests)."""
        return self._spawner.proxy(name).unit

    def units(self) -> list[UnitInfo]:
        """A snapshot of every running unit (the model's ``units``)."""
        return self._spawner.infos()

    def has_unit(self, name: str) -> bool:
        """Whether a unit called ``name`` runs (in any state) on this manager."""
        return self._spawner.has(name)

    def deadline_ports(self) -> list[DeadlinePort]:
        """The output ports with a ``deadline-ms`` of every live unit, with their message counts."""
        return self._spawner.deadline_ports()

    def resources(self) -> dict[str, int]:
        """What the manager holds for its units, by kind: every count returns to its value before
        a unit was spawned once the unit is destroyed (nothing grows with spawns and destroys)."""
        with self._lock:
            counts = self._spawner.counts()
            counts["owners"] = self._peers.owned()
        counts["bus_ports"] = len(self._bus)
        counts["subscribers"] = len(self._receiver)
        counts["routes"] = self._receiver.routes()
        counts["lanes"] = self._executor.lanes()
        counts["shed_units"] = sum(1 for p in self._spawner.proxies() if p.shed)
        counts["timers"] = self._executor.timers()
        counts["watched_deadlines"] = self._adaptation.monitor.watched()
        metrics = self._metrics
        counts["metrics_units"] = metrics.tracked() if metrics is not None else 0
        return counts

    def publish_event(self, kind: str, event: Mapping[str, Any]) -> None:
        """Publish ``event`` as JSON on ``dyknow/<manager>/events/<kind>`` (adaptations, say)."""
        self._session.put(keys.event_key(self.name, kind), json.dumps(event))

    # ------------------------------------------------------------------ requests (self-adaptation)

    def request(self, tag: str, *, standby: str | None = None, require: Sequence[str] = (), owner: Owner = LOCAL) -> str:
        """Provide a stream of ``tag`` (e.g. ``"BallPosition(field)"``); returns its key.

        The planner chooses the transformations, reusing what already runs; they are spawned and
        wired, and the stream is relayed onto a key that stays the same while the configuration
        adapts to failures, stalls and measurements. Requesting the same tag again shares it.
        ``standby="warm"`` also keeps the next-best configuration running, so that a fault only
        moves the stream onto it (``"none"``, the default: re-plan and spawn when it breaks).
        ``require``: temporal formulas the stream must satisfy (``BallTrack(field).predicted
        implies eventually[0, 1.5s] not BallTrack(field).predicted``): a false verdict moves the
        request to its next-best configuration, the formula named as the cause (see
        :meth:`dyknow.adaptation.AdaptationLoop.request`); they belong to this reference.
        ``owner``: who takes the reference (the services pass the caller; the Python API is the
        operator's; a caller's requirements count against its share of the monitors' formula
        nodes, :class:`~dyknow.reasoning.unit.MonitorBudget`). Raises
        :class:`~dyknow.planner.PlanningError` (with the explanation) when nothing fits,
        :class:`~dyknow.errors.AccessError` when the owner may not read a stream it names, when its
        requirements would take it past its share, or when the owner's caller holds
        ``limits.max_references_per_caller`` references to the request already,
        :class:`~dyknow.errors.UnitError` when a requirement of the chosen transformations cannot
        be watched (the stream is never served unchecked); when it raises, nothing of the call
        remains.
        """
        self._check_open()
        account = owner.account()
        if account is not None and require:
            # the caller's share of the monitors' nodes, for all its formulas at once (each monitor checks its own again)
            texts = list(dict.fromkeys(str(text) for text in require))
            self._monitor_budget.check(*(check_formula(text, self.limits) for text in texts), account=account)
        bound = None if owner.local else self.limits.max_references_per_caller
        return self._adaptation.request(tag, standby=standby, require=require, owner=owner, readable=self._reader(owner), max_references=bound)

    def release(self, key: str, *, owner: Owner = LOCAL, force: bool = False) -> int:
        """Give back a request, or a monitor (the key :meth:`monitor` returned); its units are
        destroyed when no other request uses them. Returns how many references to the request
        remain (it stays while any does; 0: it is gone).

        ``owner`` gives back a reference it took (the Python API may give back any);
        :class:`~dyknow.errors.AccessError` when it holds none. ``force`` gives back every
        reference, whoever took it (on a manager with roles, the services allow it to admins).
        """
        self._check_open()
        if self._monitors.release(key, owner=owner, force=force):
            if self._holders is not None:
                self._holders.forget(key)
            self.changed()
            return 0
        remaining = self._adaptation.release(key, owner=owner, force=force)
        if remaining == 0:
            if self._holders is not None:
                self._holders.forget(key)
            self.changed()  # (what only it needed of the other managers is let go)
        return remaining

    def _release_gone(self, key: str, holder: str) -> None:
        """The client ``holder`` is gone (:mod:`dyknow.holders`): what it held on ``key`` goes."""
        owner = self._monitors.owner(key)
        if owner is not None:
            if owner.holder == holder:
                self.release(key, force=True)
            return
        if self._adaptation.release_holder(key, holder) == 0 and self._holders is not None:
            self._holders.forget(key)

    def monitor(
        self, formula: str, *, reorder_ms: float = 0.0, owner: Owner = LOCAL, bindings: Mapping[str, str] | None = None, robustness: bool = False
    ) -> str:
        """Monitor a temporal formula over the streams its terms name; returns the key of its
        verdicts (see :mod:`dyknow.reasoning.monitors`; ``forall c in Class: ...`` gives one
        monitor per individual and a key expression for them all).

        Each term is requested as :meth:`request` does, so the planner finds its stream by
        meaning and the adaptation loop keeps it flowing; ``reorder_ms`` is the monitor's reorder
        delay. ``bindings`` bind terms to what exists instead, with no spec: a term -> a Zenoh
        key, ``ros2:/TOPIC`` (rmw_zenoh, on this manager's node) or ``ros2dds:/TOPIC`` (DDS, on
        its participant), as in ``{"Odom(r1)": "ros2:/r1/odom"}`` (:mod:`dyknow.reasoning.bindings`).
        ``robustness``: each change of a verdict also says each subformula's robustness
        (``"robustness_of"``, :class:`~dyknow.reasoning.unit.FormulaMonitor`).
        :meth:`release` of the key takes it down (only by ``owner``, or forced). Raises
        :class:`~dyknow.errors.FormulaError`, :class:`~dyknow.errors.BindingError` (a binding
        that is not valid, named), :class:`~dyknow.planner.PlanningError`, or
        :class:`~dyknow.errors.AccessError` when ``owner`` may not read a term's stream or source.
        """
        self._check_open()
        info = self._monitors.add(
            formula,
            reorder_ms=reorder_ms,
            owner=owner,
            readable=self._reader(owner),
            bindings=bindings,
            check_key=lambda key, where: check_key_expr(key, what=where),
            readable_source=self._source_reader(owner),
            robustness=robustness,
        )
        self.changed()
        return info.key

    def check_formula(self, formula: str) -> Formula:
        """``formula`` parsed and held to this manager's bounds (:func:`~dyknow.reasoning.check_formula`)
        and to the formula nodes its monitors may still take; :class:`~dyknow.errors.FormulaError`
        otherwise. Requests, requirements and monitors call it before they request anything."""
        parsed = check_formula(formula, self.limits)
        self._monitor_budget.check(parsed)
        return parsed

    def _reader(self, owner: Owner) -> Callable[[str], None] | None:
        """A check that ``owner`` may read the stream of a tag (its request's key), on a manager
        with roles; None when everything may be read (no roles, or the Python API)."""
        access = self._access
        caller = owner.caller
        if access is None or owner.local or caller is None:
            return None
        manager = self.name

        def readable(tag: str) -> None:
            key = keys.request_key(manager, str(parse_term(tag)))
            if not access.may_read(caller, key):
                roles = access.roles_for_read(key)
                raise AccessError(
                    f"{caller!r} may not read {tag} (its stream is on {key!r}), so it may not ask for it, monitor it or require it",
                    where=f"manager {manager!r}",
                    expected=f"a caller whose role may subscribe to {key!r} in this manager's --acl ({' or '.join(roles) or 'none'})",
                )

        return readable

    def _source_reader(self, owner: Owner) -> Callable[[str, str], None] | None:
        """A check that ``owner`` may read a bound term's source, on a manager with roles: a Zenoh
        key its role may subscribe to; a ROS 2 topic only when its role may spawn (the manager's
        node subscribes for it, as it would for a spawned :class:`~dyknow.ros2.bridge.Ros2Source`).
        None when everything may be read."""
        access = self._access
        caller = owner.caller
        if access is None or owner.local or caller is None:
            return None
        manager = self.name

        def readable(source: str, term: str) -> None:
            if source.startswith(keys.ROS2_SCHEMES):
                if not access.may_call(caller, "spawn"):
                    raise AccessError(
                        f"{caller!r} may not bind {term} to the ROS 2 topic {source!r}",
                        where=f"manager {manager!r}",
                        expected=f"a caller whose role may spawn units in this manager's --acl ({' or '.join(access.roles_for_call('spawn')) or 'none'})",
                    )
            elif not access.may_read(caller, source):
                raise AccessError(
                    f"{caller!r} may not read {source!r}, so it may not bind {term} to it",
                    where=f"manager {manager!r}",
                    expected=f"a caller whose role may subscribe to {source!r} in this manager's --acl ({' or '.join(access.roles_for_read(source)) or 'none'})",
                )

        return readable

    def monitors(self) -> list[MonitorInfo]:
        """The formulas this manager monitors."""
        return self._monitors.infos()

    def requests(self) -> list[RequestInfo]:
        """The active requests: tag, key, state ("active" or "degraded"), units, holders (and
        those whose client is not seen now)."""
        found = self._adaptation.requests()
        holders = self._holders
        if holders is None:
            return found
        return [replace(info, absent=tuple(h for h in info.holders if not holders.alive(info.key, h))) for info in found]

    def add_status_source(self, source: StatusSource) -> Callable[[], None]:
        """Add a source of ``/diagnostics`` statuses: ``source()`` returns
        :class:`~dyknow.ros2.diagnostics.DiagnosticStatus` objects (named ``<node name>: <what>``, the node's name
        being :attr:`ros2_node_name`), called about once a second and on changes, on the
        publisher's thread (it must return at once). Returns a function that removes it. See
        :mod:`dyknow.manager.health` for the statuses built in."""
        return self._health.add_source(source)

    def diagnostic_statuses(self) -> list[DiagnosticStatus]:
        """The statuses the manager publishes on ``/diagnostics`` when asked to (``diagnostics``),
        as they are now: its requirements, monitored formulas, requests, managed nodes, and those
        of the sources added (:meth:`add_status_source`)."""
        return self._health.statuses()

    @property
    def ros2_node_name(self) -> str:
        """The name of the manager's ROS 2 node (``ros2_node``, else its name made a ROS 2 name);
        its ``/diagnostics`` statuses are named after it."""
        return self._ros2.node_name()

    def measure(self, name: str, value: float | str) -> None:
        """Record the latest value of a measure (battery, say); constraints are checked against it."""
        self._check_open()
        self._measurements.record(name, value)

    def measure_from(self, name: str, source: str) -> None:
        """Take measure ``name`` from a stream: ``SOURCE[#FIELD]``, a ROS 2 topic (``ros2:``,
        ``ros2dds:``) or a Zenoh key, and a field path into its samples, such as
        ``"ros2dds:/water_visibility?type=std_msgs/msg/Float64#data"`` (:mod:`dyknow.manager.feeds`).
        Replaces an earlier feed of the measure."""
        self._check_open()
        self._feeds.add(name, source)

    def remove_measure_feed(self, name: str) -> bool:
        """Stop taking measure ``name`` from its stream (its latest value stays); whether it was fed."""
        return self._feeds.remove(name)

    @property
    def measure_feeds(self) -> dict[str, str]:
        """Each measure taken from a stream, and its ``SOURCE[#FIELD]``."""
        return self._feeds.feeds()

    @property
    def measurements(self) -> dict[str, float | str]:
        """The latest value of every measure."""
        return dict(self._adaptation.knowledge.measurements)

    def get_adaptations(self) -> list[AdaptationEvent]:
        """Every adaptation so far (each with its recovery time once the stream recovered)."""
        return self._adaptation.history()

    def on_adaptation(self, listener: Callable[[AdaptationEvent], None]) -> Callable[[], None]:
        """Call ``listener(event)`` for every adaptation event; returns a function that removes it."""
        return self._adaptation.on_event(listener)

    # ------------------------------------------------------------------ model and proxy services

    def get_model(self) -> Model:
        """All running units (label, state, protection, bindings) and all stored specs.

        A running unit whose output fell silent past its ``deadline-ms`` shows the state "stalled".
        """
        units = self.units()
        stalled = set(self._adaptation.knowledge.stalled)
        infos = tuple(replace(info, state="stalled") if info.name in stalled and info.state == "running" else info for info in units)
        if self._ros2.any():
            infos = tuple(replace(info, bindings=self._ros2.shown(info.name, info.bindings)) for info in infos)
        estimates = self._peers.clock_estimates()
        clock_view = {"clock": f"{CLOCK_ID:08x}", **{name: e.to_dict() for name, e in sorted(estimates.items())}}
        monitors = tuple(m.to_dict() for m in self._monitors.infos())
        directory = self._peers.directory
        lost = directory.lost() if directory is not None else {}
        gone = tuple({"manager": name, "since_ns": since, "why": why} for name, (since, why) in sorted(lost.items()))
        peers = tuple(sorted(directory.alive())) if directory is not None else ()  # (whose tokens are up)
        requests = tuple(self.requests())
        modes = tuple(mode_infos(infos, requests, self._adaptation.history(), self.measurements))
        return Model(self.name, infos, self.library.specs(), requests, clock_view, monitors, gone, self.load(), peers, modes)

    # ------------------------------------------------------------------ load (dyknow.executor, dyknow.overload)

    def load(self) -> dict[str, Any]:
        """How the manager keeps up: its lanes (kind, units, busy fraction, lag, queue, whether
        its thread is stuck), the bound on them, the process's niceness (:mod:`dyknow.priority`)
        and its overload state (``"ok"`` or ``"overloaded"``, with what it sheds). The JSON form;
        the model's ``executor``."""
        executor = self._executor
        return {
            "max_lanes": executor.max_lanes,
            "nice": current_nice(),
            "threads": executor.threads(),
            "lanes": [lane.to_dict() for lane in executor.lane_infos()],
            "overload": self._guard.state.to_dict(),
        }

    @property
    def overload(self) -> OverloadState:
        """The manager's overload state now (see :mod:`dyknow.overload`)."""
        return self._guard.state

    def _shed_priorities(self) -> list[tuple[str, int]]:
        """Every unit that may be shed, with its priority: its spec's, or that of a more important
        request it serves (the most important transformation of the request's configuration)."""
        proxies = [p for p in self._spawner.proxies() if not p.protected]
        boost: dict[str, int] = {}
        by_key: dict[str, int] = {}
        for info in self._adaptation.requests():
            found = [self.library.get(label).priority for label in info.labels if label in self.library]
            if not found:
                continue
            best = min(found)
            by_key[info.key] = best
            for unit in (*info.units, *info.standby):
                boost[unit] = min(best, boost.get(unit, best))
        out = []
        for proxy in proxies:
            priority = proxy.spec.priority
            if proxy.label == ANCHOR_LABEL:
                priority = by_key.get(proxy.get_config().get("out", ""), priority)
            out.append((proxy.name, min(priority, boost.get(proxy.name, priority))))
        return out

    def _apply_shed(self, shed: Mapping[int, int]) -> int:
        """Run the units of each priority in ``shed`` at that setting, every other one at full rate."""
        priorities = dict(self._shed_priorities()) if shed else {}
        proxies = self._spawner.proxies()
        slowed = 0
        for proxy in proxies:
            setting = shed.get(priorities[proxy.name], 0) if proxy.name in priorities else 0
            proxy.shed = setting
            slowed += setting != 0
        return slowed

    def _overload_changed(self, state: OverloadState, entered: bool | None) -> None:
        """The guard changed the state (on the watchdog's thread): one log line, an event."""
        self._executor.keep_measuring = self._guard.shedding
        if entered is True:
            # (other processes taking the CPU also show as lag, and a niceness is what answers that)
            hint = "; if other processes take the CPU, dyknow manager --nice -20 (or -10) gives it precedence" if current_nice() >= 0 else ""
            log.warning("manager %r is %s%s", self.name, describe(state), hint)
        elif entered is False:
            log.info("manager %r keeps up again: %s", self.name, describe(state))
        else:
            log.info("manager %r: %s", self.name, describe(state))
        try:
            self.publish_event("overload", state.to_dict())
        except DyKnowError as exc:
            log.debug("overload event of manager %r not published: %s", self.name, exc)

    def get_config(self, name: str) -> dict[str, str]:
        """Port -> key expression bindings of unit ``name``."""
        self._check_open()
        return self._ros2.shown(name, self._spawner.proxy(name).get_config())

    def set_config(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """Rebind ports of unit ``name`` atomically at runtime; returns the new bindings."""
        self._check_open()
        self._spawner.settled(name)
        proxy = self._spawner.proxy(name)
        ros2 = ros2_bindings(bindings) if isinstance(bindings, Mapping) else {}
        wired = self._ros2.wired(name, bindings) if isinstance(bindings, Mapping) else []
        if not ros2 and not wired:
            try:
                return proxy.set_config(bindings)
            finally:
                self._spawner.changed(name)
        # A port rewired to or from ROS 2 is not switched atomically: its old companion goes first.
        plain = self._ros2.rewire(name, proxy.spec, bindings, ros2, wired)
        try:
            return self._ros2.shown(name, proxy.set_config(plain))
        finally:
            self._spawner.changed(name)

    def get_statistics(self, name: str) -> UnitStatistics:
        """Uptime, reconfigurations, per-port messages, bytes, drops and latency of unit ``name``."""
        self._check_open()
        return self._spawner.proxy(name).get_statistics()

    def queue_depths(self, name: str) -> dict[str, int]:
        """How many messages each input port of unit ``name`` holds, waiting for it."""
        return self._spawner.proxy(name).queued()

    def port_counters(self, name: str) -> dict[str, PortCounters]:
        """The counters of each input port of unit ``name`` (for :mod:`dyknow.metrics`)."""
        return self._spawner.proxy(name).input_counters()

    @property
    def metrics(self) -> Metrics:
        """The manager's figures for operators: ``metrics.snapshot()`` (what ``get_metrics``
        answers, ``dyknow top`` shows) and what :class:`~dyknow.metrics.MetricsExporter` serves
        to Prometheus."""
        with self._lock:
            if self._metrics is None:
                self._metrics = Metrics(self)
            return self._metrics


    # ------------------------------------------------------------------ several managers

    def summary(self) -> Summary:
        """What this manager offers the others: host, library, running units, measurements."""
        return self._peers.summary()

    @property
    def directory(self) -> Directory | None:
        """What this manager knows of the others (None when it does not federate): whom it
        follows, the tags whose providers it watches, what it refused (:class:`dyknow.federation.Directory`)."""
        return self._peers.directory

    def peers(self) -> dict[str, Summary]:
        """The other managers this one reaches, with their last summary (empty when not federated)."""
        return self._peers.peers()

    def discover(self, wanted: Collection[tuple[str, tuple[str, ...]]], *, need: str | None = None) -> bool:
        """Find the managers that offer the tags ``wanted`` and follow them (see
        :meth:`dyknow.federation.Directory.discover`); True when one was added. ``need``: the tag
        of the request that asks (let go when no open request has it: :meth:`changed`)."""
        return self._peers.discover(wanted, need=need)

    def reachable(self) -> set[str]:
        """The names of the other managers whose liveliness token is up (followed or not): a
        liveliness query when called, at most once a second (:meth:`dyknow.federation.Directory.alive`)."""
        return self._peers.reachable()

    def changed(self) -> None:
        """This manager's model changed: the other managers hear of it (a summary, debounced)."""
        self._peers.changed()

    def spawn_on(self, manager: str, label: str, name: str, *, bindings: Mapping[str, str]) -> None:
        """Spawn a unit on another manager, through its spawn service, for a request of this one."""
        self._peers.spawn_on(manager, label, name, bindings=bindings)

    def destroy_on(self, manager: str, name: str) -> None:
        """Destroy a unit this manager spawned on another one."""
        self._peers.destroy_on(manager, name)

    def set_config_on(self, manager: str, name: str, bindings: Mapping[str, str]) -> None:
        """Rebind ports of a unit on another manager."""
        self._peers.set_config_on(manager, name, bindings)

