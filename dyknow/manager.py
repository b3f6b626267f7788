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
"""

from __future__ import annotations

import collections
import contextlib
import importlib
import importlib.machinery
import importlib.util
import inspect
import json
import logging
import math
import os
import re
import socket
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import replace
from typing import Any

from dyknow import clocks, keys, reach, service
from dyknow.access import AccessControl, TlsFiles
from dyknow.adaptation import ANCHOR_LABEL, DEFAULT_DWELL_S, AdaptationEvent, AdaptationLoop, DeadlinePort
from dyknow.bus import LocalBus
from dyknow.client import Client
from dyknow.errors import AccessError, BindingError, ClosedError, DyKnowError, LibraryError, TransportError, UnitError, did_you_mean
from dyknow.executor import DEFAULT_MAX_LANES, Executor
from dyknow.federation import STOPPED, Directory, Summary, SummaryUnit
from dyknow.holders import DEFAULT_GRACE_S, Holders
from dyknow.identity import Caller, Signer, Verifier
from dyknow.library import Library
from dyknow.message import CLOCK_ID
from dyknow.metrics import Metrics
from dyknow.model import LOCAL, Model, Owner, RequestInfo, UnitEvent, UnitInfo
from dyknow.ontology import Ontology
from dyknow.overload import DEFAULT_LAG_BUDGET_S, OverloadGuard, OverloadState, describe
from dyknow.priority import current_nice
from dyknow.proxy import DEFAULT_QUEUE_DEPTH, Proxy, UnitState, UnitStatistics
from dyknow.reasoning.monitors import MonitorInfo, Monitors
from dyknow.reasoning.syntax import Formula, check_formula
from dyknow.reasoning.unit import FormulaMonitor, MonitorBudget
from dyknow.receiver import Receiver
from dyknow.ros2.binding import is_ros2, parse_binding
from dyknow.ros2.bridge import UsesRos2
from dyknow.ros2.dds import DdsNode
from dyknow.ros2.node import Ros2Node
from dyknow.security import DEFAULT_SOURCES, DataRoots, Limits, SourcePolicy, is_loopback, module_of
from dyknow.spec import Template, TransformationSpec, load_specs, parse_specs
from dyknow.spec.model import INT_RANGE, Param, Port, convert_param
from dyknow.stats import PortCounters
from dyknow.tags import parse_term
from dyknow.transport import Session, check_key_expr, make_config
from dyknow.unit import Unit

__all__ = ["Manager"]

log = logging.getLogger(__name__)

_BUSY_ROUTER_S = 60.0  # how long a manager tries again a router that accepts connections but is slow to open a session
_UNIT_LOG = 4096  # changes of units remembered (unit_changes); a reader further behind reads them all


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
    ) -> None:
        self.name = keys.check_name(name, "manager name")
        if ontology is None or isinstance(ontology, Ontology):
            self.ontology: Ontology | None = ontology
        else:
            paths_ = list(ontology)
            self.ontology = Ontology.load(paths_) if paths_ else None  # bad ontologies fail first
        self.limits = limits = limits or Limits()
        self.library = Library(max_specs=limits.max_library_specs, max_bytes=limits.max_library_bytes)
        self._sources = SourcePolicy([*DEFAULT_SOURCES, *allow_sources])
        self._code_paths: list[str] = []  # folders unit modules are looked for in (--path, the trusted specs' own)
        for folder in code_paths:
            if not os.path.isdir(folder):
                raise LibraryError(f"code path {os.fspath(folder)!r} is not a folder", expected="a folder holding unit modules (--path DIR)")
            self._code_paths.append(os.path.abspath(folder))
        self._remote_labels: set[str] = set()  # added through the service: their params are checked
        spec_objs = [s for s in specs if isinstance(s, TransformationSpec)]
        paths = [s for s in specs if not isinstance(s, TransformationSpec)]
        if paths:
            # bad specs fail before anything starts
            loaded = load_specs(
                paths, individuals=self._individuals if self.ontology is not None else None, max_expansions=limits.max_expansions
            )
            self._trust(loaded)
            self.library.add(loaded)
        self._trust(spec_objs)
        self.library.add(spec_objs)
        spec_dirs = [p if os.path.isdir(p) else os.path.dirname(os.path.abspath(p)) for p in (os.fspath(q) for q in paths)]
        self._roots = DataRoots(write=data_roots, read=spec_dirs)
        self._queue_depth = queue_depth
        self._lock = threading.RLock()
        self._metrics: Metrics | None = None
        self._units: dict[str, Proxy] = {}
        # which units changed, and when (a version each): what the adaptation loop's index reads
        self._unit_version = 0
        self._unit_log: collections.deque[tuple[int, str]] = collections.deque(maxlen=_UNIT_LOG)
        self._deadlines: dict[str, Proxy] = {}  # the units with deadline-ms outputs (the monitor watches them)
        self._starting: dict[str, threading.Lock] = {}  # units being spawned: held until spawn returns
        self._closed = False
        # ROS 2 (dyknow.ros2): the node is made when first needed (or now, when named); ports
        # bound to ros2: topics are wired through a companion unit each: (unit, port) -> (companion, binding)
        self._ros2: Ros2Node | None = None
        self._dds: DdsNode | None = None
        self._dds_config = dds_config
        self._ros2_options = (ros2_domain, ros2_node, ros2_namespace)
        self._ros2_ports: dict[tuple[str, str], tuple[str, str]] = {}
        access = acl if isinstance(acl, AccessControl) or acl is None else AccessControl.load(acl)
        self._tls = tls.check() if tls is not None else None
        self._verifier: Verifier | None = None
        if access is not None:
            if self._tls is None:
                raise AccessError(
                    "roles (--acl) are given by certificate, and the manager has none",
                    where=f"manager {self.name!r}",
                    expected="--tls-ca, --tls-cert and --tls-key with --acl (dyknow certs writes development ones)",
                )
            self._verifier = Verifier(self._tls.ca, access)
            own = Signer(self._tls).common_name
            if own != self.name:
                log.warning(
                    "manager %r runs with the certificate of %r: managers whose --acl lists it under manager accept its "
                    "services, summary and liveliness only from a certificate named after it",
                    self.name,
                    own,
                )
        self._access = access
        if zenoh_config is None:  # (Zenoh would say only "Missing TLS private key")
            reach.check_endpoints(listen or (), self._tls, option="--listen", who=f"manager {self.name!r}")
            reach.check_endpoints(connect, self._tls, option="--connect", who=f"manager {self.name!r}")
            if self._tls is not None and listen and not any(e.startswith("tls/") for e in [*listen, *connect]):
                log.warning(
                    "manager %r has TLS files but no tls/ endpoint (--listen, --connect): every link is plain TCP, and no "
                    "caller has a certificate for its roles",
                    self.name,
                )
        self.host = host or socket.gethostname()
        self._routers = list(router)
        if router:
            if listen or connect:
                raise TransportError(
                    "a manager behind a router dials only its router",
                    where=f"manager {self.name!r}",
                    expected="router endpoints alone (--router), or --listen/--connect without --router",
                )
            if zenoh_config is None:
                reach.check_endpoints(router, self._tls, option="--router", who=f"manager {self.name!r}")

        def session(mode: str) -> Session:
            return Session(
                make_config(
                    listen=[] if router else listen,
                    connect=list(router or connect),
                    config_file=zenoh_config,
                    tls=self._tls,
                    access=access,
                    lease_ms=lease_ms,
                    max_message_bytes=limits.max_message_bytes,
                    mode=mode,
                )
            )

        # A router: managers reach each other through any path (a third manager, a dyknow router)
        # when they cannot link directly, and keep trying the links they were told to make; peers
        # see only the peers they link to (issue 43). Behind a router, a Zenoh client of it: one
        # link, which the router routes everything through, and only what the manager asks for
        # comes down it (issue 40); it dials the router again when the link goes, or a standby.
        if not router:
            self._session = session("router")
        else:
            opened = reach.open_patiently(lambda: session("client"), router, patience_s=_BUSY_ROUTER_S, who=f"manager {self.name!r}")
            if opened is not None:
                self._session = opened
            else:
                # (a Zenoh client does not start without its router; a robot's manager must run
                # its own units meanwhile: a router without a listener keeps dialling, one link each)
                log.warning(
                    "manager %r: no router of %s answers yet (none listens there, or it refused this manager: a router full at its "
                    "--max-sessions, or TLS); it runs meanwhile and dials them until they do (holding a link to each that answers, not "
                    "only to the first), linked as a Zenoh router, which receives every declaration of the fleet: in a large fleet, "
                    "restart it once its router is up (it then links as a client)",
                    self.name,
                    ", ".join(router),
                )
                self._session = session("router")
        # calls to the other managers, signed with this manager's certificate (dyknow.identity)
        self._peers = Client(self.name, session=self._session, timeout_s=3.0, tls=self._tls)
        self._owners: dict[str, str] = {}  # unit -> the manager whose request it serves
        self._version = 0
        self._started_ns = time.time_ns()
        self._directory: Directory | None = None
        self._clocks: clocks.ClockTracker | None = None  # the peers' clock offsets (dyknow.clocks)
        self._clock_token: Any = None  # says whose clock this process's clock id is
        self._clocks_asked: dict[int, float] = {}  # unknown clock ids asked about -> when (monotonic)
        self._data_peers: set[str] = set()  # managers whose data reached this one: their clocks estimated until they go
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
        self._workers: service.Workers | None = None
        self._holders: Holders | None = None
        self._monitor_budget = MonitorBudget(limits)  # the cells its formula monitors share
        self._adaptation = AdaptationLoop(self, dwell_s=dwell_s)
        self.on_unit_event(self._adaptation.unit_event)
        self._monitors = Monitors(
            self.name,
            request=self.request,
            release=self._adaptation.release,
            spawn=lambda spec, name, bindings: self.spawn(spec, name, bindings=bindings),
            destroy=self.destroy,
            unit=self.unit,
            individuals=self._individuals if self.ontology is not None else None,
            max_expansions=self.limits.max_expansions,
            limits=self.limits,
            budget=self._monitor_budget.check,
        )
        self._adaptation.on_event(lambda event: self._monitors.adapted(event.key, event.cause) if event.kind == "adapted" else None)
        self._measurement_subs = []
        try:
            for pattern in keys.measurement_patterns(self.name):
                self._measurement_subs.append(self._session.declare_raw_subscriber(pattern, self._measurement_sample))
        except DyKnowError:
            self.close()
            raise
        if serve:
            try:
                self._holders = Holders(self._session, self.name, self._release_gone, grace_s=client_grace_s)
                self._workers = service.Workers(
                    self.name,
                    # clock exchanges are answered on Zenoh's thread, where their times are taken
                    self._session.declare_service_channel(keys.services_pattern(self.name), at_once={keys.clock_key(self.name): clocks.answer}),
                    service.dispatcher(
                        self.name, self._manager_handlers(), self._unit_service, limits, verifier=self._verifier, access=self._access
                    ),
                )
            except DyKnowError:
                self.close()
                raise
        if federate if federate is not None else serve:
            try:
                # clocks on demand: those of the managers this one exchanges data or calls with (issue 40)
                self._clocks = clocks.ClockTracker(self._session, in_use=self._peers_in_use, wanted=self._clock_peers)
                self._clock_token = self._session.declare_liveliness_token(keys.clock_token(CLOCK_ID, self.name))
                self._directory = Directory(
                    self._session,
                    self.name,
                    summarize=self.summary,
                    fetch=self._fetch_summary,
                    on_change=self._peer_changed,
                    in_use=self._peers_in_use,
                )
            except DyKnowError:
                self.close()
                raise
        if self._tls is None and self.exposed():
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
            for sub in self._measurement_subs:
                sub.undeclare()
            proxies = list(self._units.values())
            self._units.clear()
            self._deadlines.clear()
        if self._directory is not None:  # first: the others then know it stopped, and did not crash
            self._directory.say_goodbye()
        if self._workers is not None:
            self._workers.close(timeout_s / 4)
        if self._holders is not None:
            self._holders.close()
        self._adaptation.close(timeout_s / 2)  # releases what its requests run on other managers
        if self._directory is not None:
            self._directory.close(timeout_s / 4)
        if self._clocks is not None:
            self._clocks.close()
        if self._clock_token is not None:
            self._clock_token.undeclare()
        per_unit = min(0.5, timeout_s / max(1, len(proxies)))
        for proxy in reversed(proxies):
            proxy.stop(per_unit)
        self._executor.close(timeout_s)
        self._receiver.close()
        if self._ros2 is not None:
            self._ros2.close()
        if self._dds is not None:
            self._dds.close()
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

    def _ros2_domain(self) -> int:
        domain = self._ros2_options[0]
        if domain is None:
            text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
            if not text.isdigit():
                raise BindingError(f"ROS_DOMAIN_ID={text!r}", where=f"manager {self.name!r}", expected="a number from 0 to 232")
            domain = int(text)
        return domain

    def ros2_node(self) -> Ros2Node:
        """The manager's ROS 2 node on rmw_zenoh (made on first use): named ``ros2_node`` (default:
        the manager's name, with ``-`` and ``.`` as ``_``) in ``ros2_namespace``, on ROS domain
        ``ros2_domain`` (default: ``ROS_DOMAIN_ID``, else 0)."""
        with self._lock:
            self._check_open()
            if self._ros2 is None:
                _, node, namespace = self._ros2_options
                name = node or re.sub(r"[^A-Za-z0-9_]", "_", self.name)
                if name[0].isdigit():
                    name = "_" + name
                self._ros2 = Ros2Node(
                    self._session, name, namespace=namespace, domain=self._ros2_domain(), max_message_bytes=self.limits.max_ros2_message_bytes
                )
            return self._ros2

    def dds_node(self) -> DdsNode:
        """The manager's DDS participant for ``ros2dds:`` bindings (made on first use), on ROS
        domain ``ros2_domain``, configured by ``dds_config`` (Cyclone XML; default: loopback only)."""
        with self._lock:
            self._check_open()
            if self._dds is None:
                self._dds = DdsNode(
                    domain=self._ros2_domain(),
                    config=self._dds_config,
                    types=self.ros2_node().types if self._ros2 else None,
                    max_message_bytes=self.limits.max_ros2_message_bytes,
                )
            return self._dds

    def exposed(self) -> list[str]:
        """The endpoints this manager listens on beyond this host without TLS, or the routers it
        sits behind there (anyone who reaches them reaches the manager): a warning sign."""
        return [e for e in [*self.endpoints, *self._routers] if not e.startswith("tls/") and not _loopback(e)]

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
        individuals = self._individuals if self.ontology is not None else None
        limit = self.limits.max_expansions
        if remote:
            if not isinstance(spec, str) or not spec.lstrip().startswith("<"):
                raise AccessError(
                    "a remote caller may only send XML text",
                    where="field 'xml'",
                    expected="the spec's XML (the client reads files on its side)",
                )
            specs = parse_specs(
                spec, path or "<remote>", individuals=individuals, max_expansions=limit, max_bytes=self.limits.max_expansion_bytes
            )
            for one in specs:
                self._sources.check(one.source, where=f"transformation {one.label!r} ({one.location})")
        elif isinstance(spec, TransformationSpec):
            specs = [spec]
        elif isinstance(spec, Template):
            specs = spec.expand(individuals, max_expansions=limit)
        elif isinstance(spec, os.PathLike) or (isinstance(spec, str) and not spec.lstrip().startswith("<")):
            specs = load_specs([spec], individuals=individuals, max_expansions=limit)
        elif isinstance(spec, str):
            specs = parse_specs(spec, path or "<add_transformation>", individuals=individuals, max_expansions=limit)
        else:
            raise LibraryError(f"add_transformation got a {type(spec).__name__}", expected="a spec, a template, XML text or a path")
        added = {s.label for s in specs}
        was_remote = added & self._remote_labels
        if remote:
            self._remote_labels.update(added)
        else:
            self._trust(specs)
            self._remote_labels.difference_update(added)
        try:
            labels = self.library.add(specs)
        except LibraryError:  # past the library's bounds: nothing added, the labels as they were
            self._remote_labels.difference_update(added - was_remote)
            self._remote_labels.update(was_remote)
            raise
        self._adaptation.library_changed()
        self.changed()
        return labels

    def remove_transformation(self, label: str) -> bool:
        """Forget the spec with ``label``; returns whether there was one. Running units stay."""
        self._check_open()
        removed = self.library.remove(label)
        self._remote_labels.discard(label)
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
    ) -> UnitInfo:
        """Start a unit of transformation ``label`` named ``name`` (see :meth:`_spawn`).

        A binding ``ros2:/TOPIC?...`` (:mod:`dyknow.ros2.binding`) wires the port to a ROS 2 topic
        through a companion unit ``<name>.<port>.ros2`` (a :class:`~dyknow.ros2.bridge.Ros2Source`
        or :class:`~dyknow.ros2.bridge.Ros2Sink`), spawned after the unit and destroyed with it; if
        one cannot start, the unit is destroyed again and the error raised.
        """
        ros2 = {port: key for port, key in (bindings or {}).items() if is_ros2(key)}
        if not ros2:
            return self._spawn(label, name, protected=protected, params=params, bindings=bindings, remote=remote)
        spec = label if isinstance(label, TransformationSpec) else self.library.get(label)
        plan = self._ros2_plan(spec, name, ros2)
        plain = {port: key for port, key in (bindings or {}).items() if port not in ros2}
        plain.update((port, key) for port, (_, _, key, _) in plan.items())
        info = self._spawn(label, name, protected=protected, params=params, bindings=plain, remote=remote)
        try:
            self._start_companions(name, plan)
        except BaseException:
            with contextlib.suppress(DyKnowError):
                self.destroy(name, force=True)
            raise
        return replace(info, bindings=self._shown(name, info.bindings))

    def _ros2_plan(
        self, spec: TransformationSpec, name: str, ros2: Mapping[str, str]
    ) -> dict[str, tuple[str, TransformationSpec, str, str]]:
        """Port -> (companion name, companion spec, the key the port binds to, the binding), checked."""
        ports = {p.name: p for p in spec.ports}
        plan = {}
        for port, text in ros2.items():
            where = f"port {port!r} of unit {name!r}"
            if port not in ports:
                raise BindingError(
                    f"no port {port!r}",
                    where=f"transformation {spec.label!r}",
                    expected=f"one of {', '.join(ports)}{did_you_mean(port, ports)}",
                )
            binding = parse_binding(text, where=where)
            output = ports[port].direction == "out"
            if binding.ros_type is None and output:
                raise BindingError(f"{text!r} names no type", where=where, expected=f"ros2:{binding.topic}?type=pkg/msg/Type for an output")
            if binding.ros_type is not None:
                (self.dds_node() if binding.dds else self.ros2_node()).types.check(binding.ros_type, where=where)
            companion = keys.check_name(f"{name}.{port}.ros2", "companion unit name")
            cspec = _ROS2_SINK if output else _ROS2_SOURCE
            key = keys.default_key(self.name, companion, "in" if output else "out")
            plan[port] = (companion, cspec, key, binding.uri())
        return plan

    def _start_companions(self, name: str, plan: Mapping[str, tuple[str, TransformationSpec, str, str]]) -> None:
        for port, (companion, cspec, _key, uri) in plan.items():
            info = self._spawn(cspec, companion, params={"binding": uri})
            if info.state == "failed":
                with contextlib.suppress(DyKnowError):
                    self.destroy(companion, force=True)
                raise BindingError(f"{uri}: {info.error}", where=f"port {port!r} of unit {name!r}")
            with self._lock:
                self._ros2_ports[(name, port)] = (companion, uri)

    def _drop_companions(self, name: str, ports: Iterable[str] | None = None) -> None:
        with self._lock:
            gone = [(k, v[0]) for k, v in self._ros2_ports.items() if k[0] == name and (ports is None or k[1] in ports)]
            for k, _ in gone:
                del self._ros2_ports[k]
        for _, companion in gone:
            with contextlib.suppress(DyKnowError):
                self.destroy(companion, force=True)

    def _shown(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """``bindings`` with each port wired to ROS 2 shown as its ``ros2:`` binding."""
        with self._lock:
            return {port: self._ros2_ports.get((name, port), (None, key))[1] for port, key in bindings.items()}

    def _spawn(
        self,
        label: str | TransformationSpec,
        name: str,
        *,
        protected: bool = False,
        params: Mapping[str, Any] | None = None,
        bindings: Mapping[str, str] | None = None,
        remote: bool = False,
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
        """
        with self._lock:
            self._check_open()
            keys.check_name(name, "unit name")
            if isinstance(label, TransformationSpec) and not remote:
                self._trust([label])
            if len(self._units) + len(self._starting) >= self.limits.max_units:
                raise UnitError(
                    f"the manager already runs {len(self._units) + len(self._starting)} units, its most",
                    where=f"manager {self.name!r}",
                    expected=f"at most {self.limits.max_units} units (--max-units): destroy some first",
                )
            if name in self._units or name in self._starting:
                running = self._units.get(name)
                state = f"label {running.label!r}, {running.state.value}" if running is not None else "being spawned"
                raise UnitError(
                    f"a unit named {name!r} already exists ({state})",
                    where=f"manager {self.name!r}",
                    expected="another name, or destroy it first",
                )
            spec = label if isinstance(label, TransformationSpec) else self.library.get(label)
            values = _param_values(spec, params or {})
            ports = _bindings(spec, self.name, name, bindings or {})
            confine = remote or (isinstance(label, str) and label in self._remote_labels)
            # The name is taken; the rest (import, setup()) runs without the manager's lock, so
            # other calls go on meanwhile. Calls that change this unit wait for the gate.
            gate = threading.Lock()
            gate.acquire()
            self._starting[name] = gate
        try:
            return self._start(spec, name, protected=protected, values=values, ports=ports, confine=confine)
        finally:
            with self._lock:
                del self._starting[name]
            gate.release()

    def _start(
        self, spec: TransformationSpec, name: str, *, protected: bool, values: dict[str, Any], ports: dict[str, str], confine: bool = False
    ) -> UnitInfo:
        """Import, create and start a unit (its name is reserved; the manager lock is not held)."""
        cls = _import_unit(spec, self._sources, self._code_paths)
        if confine:  # file params, as the spec declares them and as the (trusted) class does
            modes = {p.name: p.mode or "read" for p in spec.params if p.type == "path"} | dict(cls.path_params)
            for param, mode in modes.items():
                where = f"param {param!r} of unit {name!r}"
                if param not in values:  # the unit would choose a file of its own, wherever it likes
                    roots = ", ".join(str(r) for r in self._roots.roots(mode)) or "a --data-root folder"
                    raise AccessError(
                        "is not given, and a unit spawned for a remote caller may not fall back to a file of its own choosing",
                        where=where,
                        expected=f"the param given, in the spawn or in the spec's <params>: a file to {mode} under {roots}",
                    )
                values[param] = self._roots.resolve(values[param], mode, where=where)
        try:
            unit = cls()
        except Exception as exc:
            raise UnitError(f"{spec.source}() raised {type(exc).__name__}: {exc}", where=f"cannot create unit {name!r}") from exc
        if isinstance(unit, UsesRos2):
            unit.use_ros2(self)
        if isinstance(unit, FormulaMonitor):
            unit.use_budget(self._monitor_budget)
        proxy = Proxy(
            name=name,
            spec=spec,
            unit=unit,
            params=values,
            bindings=ports,
            session=self._session,
            bus=self._bus,
            receiver=self._receiver,
            executor=self._executor,
            protected=protected,
            queue_depth=self._queue_depth,
            on_failure=self._unit_failed,
            on_destroy_request=self._destroy_requested,
        )
        with self._lock:
            self._check_open()
            self._units[name] = proxy
            if any(port.deadline_ms for port in spec.outputs):
                self._deadlines[name] = proxy
        proxy.start()
        self._unit_changed(name)
        if self._closed:  # closed while it started: close() did not see it
            proxy.stop(0.5)
            self._check_open()
        if proxy.state is not UnitState.FAILED:
            self._emit("spawned", proxy)
        return _info(proxy)

    def _settled(self, name: str, timeout_s: float = 60.0) -> None:
        """Wait until a spawn of ``name`` in flight has returned (calls on one unit stay in order)."""
        with self._lock:
            gate = self._starting.get(name)
        if gate is None:
            return
        if not gate.acquire(timeout=timeout_s):
            raise UnitError(f"still starting after {timeout_s:.0f} s", where=f"unit {name!r}", expected="a unit whose setup() returns")
        gate.release()

    def destroy(self, name: str, *, force: bool = False) -> None:
        """Stop unit ``name`` and remove it from the model. A protected unit only with ``force``
        (through the service: by an admin, or by anyone when the manager has no roles).

        A unit still being spawned is destroyed once its spawn returns."""
        self._settled(name)
        with self._lock:
            self._check_open()
            proxy = self._proxy(name)
            if proxy.protected and not force:
                raise UnitError(
                    "the unit is protected (spawned with protected=True), so it cannot be destroyed without force",
                    where=f"unit {name!r}",
                    expected="destroy(name, force=True) (dyknow destroy NAME --force; an admin's, when the manager has roles)",
                )
            del self._units[name]
            self._deadlines.pop(name, None)
            self._unit_changed(name)
        proxy.stop()
        log.info("unit %r destroyed", name)
        self._emit("destroyed", proxy)
        self._drop_companions(name)

    def _destroy_requested(self, proxy: Proxy) -> None:
        with self._lock:
            if self._closed or self._units.get(proxy.name) is not proxy:
                return
            del self._units[proxy.name]
            self._deadlines.pop(proxy.name, None)
            self._unit_changed(proxy.name)
        proxy.stop()
        log.info("unit %r destroyed itself", proxy.name)
        self._emit("destroyed", proxy)
        self._drop_companions(proxy.name)

    def _unit_failed(self, proxy: Proxy) -> None:
        self._unit_changed(proxy.name)
        self._emit("failed", proxy)

    def _unit_changed(self, name: str) -> None:
        with self._lock:
            self._unit_version += 1
            self._unit_log.append((self._unit_version, name))

    def unit_changes(self, since: int) -> tuple[int, list[str] | None]:
        """The version of the units now, and the names of those spawned, destroyed, rebound or
        failed after version ``since`` (None when the log no longer reaches back that far: read
        :meth:`units` again). What the adaptation loop's index follows."""
        with self._lock:
            version = self._unit_version
            if since == version:
                return version, []
            changes = self._unit_log
            if since < 0 or since > version or not changes or changes[0][0] > since + 1:
                return version, None
            names: list[str] = []
            for serial, name in reversed(changes):
                if serial <= since:
                    break
                names.append(name)
        return version, list(dict.fromkeys(names))

    def unit_info(self, name: str) -> UnitInfo | None:
        """Unit ``name`` as :meth:`units` shows it; None when it does not run."""
        proxy = self._units.get(name)
        return _info(proxy) if proxy is not None else None

    def on_unit_event(self, listener: Callable[[UnitEvent], None]) -> Callable[[], None]:
        """Call ``listener(event)`` whenever a unit is spawned, fails or is destroyed.

        The listener runs on the thread where it happened and must be quick. Returns a function
        that removes the listener.
        """
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener) if listener in self._listeners else None

    def _emit(self, kind: str, proxy: Proxy) -> None:
        if kind == "destroyed":
            self._owners.pop(proxy.name, None)
        self.changed()
        event = UnitEvent(kind, proxy.name, proxy.label, time.time_ns(), proxy.error if kind == "failed" else None)
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception:
                log.exception("unit event listener failed on %s", event)

    def unit(self, name: str) -> Unit:
        """The Python object of running unit ``name`` (for embedding and tests)."""
        return self._proxy(name).unit

    def units(self) -> list[UnitInfo]:
        """A snapshot of every running unit (the model's ``units``)."""
        with self._lock:
            proxies = list(self._units.values())
        return [_info(p) for p in proxies]

    def has_unit(self, name: str) -> bool:
        """Whether a unit called ``name`` runs (in any state) on this manager."""
        return name in self._units

    def deadline_ports(self) -> list[DeadlinePort]:
        """The output ports with a ``deadline-ms`` of every live unit, with their message counts."""
        with self._lock:
            proxies = list(self._deadlines.values())
        return [
            DeadlinePort(proxy.name, proxy.label, port.name, int(port.deadline_ms * 1e6), proxy.published(port.name), proxy.started_ns)
            for proxy in proxies
            if proxy.alive
            for port in proxy.spec.outputs
            if port.deadline_ms
        ]

    def resources(self) -> dict[str, int]:
        """What the manager holds for its units, by kind: every count returns to its value before
        a unit was spawned once the unit is destroyed (nothing grows with spawns and destroys)."""
        with self._lock:
            counts = {
                "units": len(self._units),
                "starting": len(self._starting),
                "deadline_units": len(self._deadlines),
                "owners": len(self._owners),
            }
        counts["bus_ports"] = len(self._bus)
        counts["subscribers"] = len(self._receiver)
        counts["routes"] = self._receiver.routes()
        counts["lanes"] = self._executor.lanes()
        counts["shed_units"] = sum(1 for p in list(self._units.values()) if p.shed)
        counts["timers"] = self._executor.timers()
        counts["watched_deadlines"] = self._adaptation.monitor.watched()
        return counts

    def publish_event(self, kind: str, event: Mapping[str, Any]) -> None:
        """Publish ``event`` as JSON on ``dyknow/<manager>/events/<kind>`` (adaptations, say)."""
        self._session.put(keys.event_key(self.name, kind), json.dumps(event))

    def _proxy(self, name: str) -> Proxy:
        proxy = self._units.get(name)
        if proxy is None:
            known = list(self._units)
            listing = ", ".join(repr(k) for k in known) or "none"
            raise UnitError(
                f"no unit named {name!r}",
                where=f"manager {self.name!r}",
                expected=f"one of the running units: {listing}{did_you_mean(name, known)}",
            )
        return proxy

    def _trust(self, specs: Iterable[TransformationSpec]) -> None:
        """Specs from the operator (files at start, the Python API): their modules may be loaded,
        and are looked for beside the spec file too."""
        for spec in specs:
            folder = os.path.dirname(os.path.abspath(spec.path)) if os.path.isfile(spec.path) else None
            if folder is not None and folder not in self._code_paths:
                self._code_paths.append(folder)
            if self._sources.allows(spec.source) or not _SOURCE_SYNTAX.fullmatch(spec.source):
                continue  # allowed already, or not a source at all (refused with its own message at spawn)
            self._sources.allow(module_of(spec.source))

    def _individuals(self, class_ref: str) -> list[str]:
        if self.ontology is None:
            raise LibraryError(f"template arg class {class_ref!r} needs an ontology", expected="ontology=[...] (--ontology FILE)")
        return self.ontology.individuals(class_ref)

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
        operator's). Raises :class:`~dyknow.planner.PlanningError` (with the explanation) when
        nothing fits, :class:`~dyknow.errors.AccessError` when the owner may not read a stream
        it names; when it raises, nothing of the call remains.
        """
        self._check_open()
        return self._adaptation.request(tag, standby=standby, require=require, owner=owner, readable=self._reader(owner))

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

    def monitor(self, formula: str, *, reorder_ms: float = 0.0, owner: Owner = LOCAL) -> str:
        """Monitor a temporal formula over the streams its terms name; returns the key of its
        verdicts (see :mod:`dyknow.reasoning.monitors`; ``forall c in Class: ...`` gives one
        monitor per individual and a key expression for them all).

        Each term is requested as :meth:`request` does, so the planner finds its stream by
        meaning and the adaptation loop keeps it flowing; ``reorder_ms`` is the monitor's reorder
        delay. :meth:`release` of the key takes it down (only by ``owner``, or forced). Raises
        :class:`~dyknow.errors.FormulaError`, :class:`~dyknow.planner.PlanningError`, or
        :class:`~dyknow.errors.AccessError` when ``owner`` may not read a term's stream.
        """
        self._check_open()
        info = self._monitors.add(formula, reorder_ms=reorder_ms, owner=owner, readable=self._reader(owner))
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

    def measure(self, name: str, value: float | str) -> None:
        """Record the latest value of a measure (battery, say); constraints are checked against it."""
        self._check_open()
        keys.check_name(name, "measurement name")
        self._check_measurement(name, value)
        self._adaptation.measure(name, value)
        self.changed()

    def _check_measurement(self, name: str, value: object) -> None:
        """:class:`LibraryError` naming the measurement when constraints could not use ``value``."""
        where = f"measurement {name!r}"
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise LibraryError(f"got {value!r}", where=where, expected="a finite number, or text")
        if isinstance(value, float) and not math.isfinite(value):
            raise LibraryError(f"got {value!r}", where=where, expected="a finite number")
        if isinstance(value, str):
            numeric = sorted({s.label for s in self.library.specs() for c in s.constraints if c.measure == name and not isinstance(c.value, str)})
            if numeric:
                raise LibraryError(
                    f"got the text {value[:40]!r}", where=where, expected=f"a number: the constraints of {', '.join(numeric[:3])} compare it with numbers"
                )

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

    def _measurement_sample(self, key: str, payload: bytes) -> None:
        name = key.rsplit("/", 1)[-1]
        try:
            # a put on a wildcard key ('dyknow/**/in') reaches this subscription too: only a
            # concrete key names a measurement
            keys.check_name(name, "measurement name")
            if "*" in key or "$" in key:
                raise UnitError(f"{key[:200]!r} is a key expression with wildcards", expected="a concrete key such as dyknow/measurements/battery")
        except UnitError as exc:
            log.warning("measurement on %s ignored: %s", key[:200], exc)
            return
        try:
            value = json.loads(payload)
            if isinstance(value, dict):
                host = value.get("host")
                if host is not None and key.startswith(keys.measurement_key("")) and host != self.host:
                    return  # a measurement of another machine: its managers take it
                value = value["value"]
            if not isinstance(value, (int, float, str)) or isinstance(value, bool):
                raise ValueError(f"got {value!r}")
        except (ValueError, KeyError, TypeError) as exc:
            log.warning('measurement on %s ignored: %s; expected a JSON number or {"value": x}', key, exc)
            return
        try:
            self._check_measurement(name, value)
        except LibraryError as exc:
            log.warning("measurement on %s ignored: %s", key, exc)
            return
        self._adaptation.measure(name, value)
        self.changed()

    # ------------------------------------------------------------------ model and proxy services

    def get_model(self) -> Model:
        """All running units (label, state, protection, bindings) and all stored specs.

        A running unit whose output fell silent past its ``deadline-ms`` shows the state "stalled".
        """
        with self._lock:
            proxies = list(self._units.values())
        stalled = set(self._adaptation.knowledge.stalled)
        infos = tuple(
            replace(info, state="stalled") if info.name in stalled and info.state == "running" else info for info in map(_info, proxies)
        )
        if self._ros2_ports:
            infos = tuple(replace(info, bindings=self._shown(info.name, info.bindings)) for info in infos)
        estimates = self._clocks.estimates() if self._clocks is not None else {}
        clock_view = {"clock": f"{CLOCK_ID:08x}", **{name: e.to_dict() for name, e in sorted(estimates.items())}}
        monitors = tuple(m.to_dict() for m in self._monitors.infos())
        lost = self._directory.lost() if self._directory is not None else {}
        gone = tuple({"manager": name, "since_ns": since, "why": why} for name, (since, why) in sorted(lost.items()))
        peers = tuple(sorted(self._directory.alive())) if self._directory is not None else ()  # (whose tokens are up)
        return Model(self.name, infos, self.library.specs(), tuple(self.requests()), clock_view, monitors, gone, self.load(), peers)

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
        with self._lock:
            proxies = [p for p in self._units.values() if not p.protected]
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
        with self._lock:
            proxies = list(self._units.values())
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
        return self._shown(name, self._proxy(name).get_config())

    def set_config(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """Rebind ports of unit ``name`` atomically at runtime; returns the new bindings."""
        self._check_open()
        self._settled(name)
        proxy = self._proxy(name)
        ros2 = {port: key for port, key in bindings.items() if is_ros2(key)} if isinstance(bindings, Mapping) else {}
        with self._lock:
            wired = [port for port in bindings if (name, port) in self._ros2_ports] if isinstance(bindings, Mapping) else []
        if not ros2 and not wired:
            try:
                return proxy.set_config(bindings)
            finally:
                self._unit_changed(name)
        # A port rewired to or from ROS 2 is not switched atomically: its old companion goes first.
        plan = self._ros2_plan(proxy.spec, name, ros2)
        self._drop_companions(name, wired)
        self._start_companions(name, plan)
        plain = {port: key for port, key in bindings.items() if port not in ros2}
        plain.update((port, key) for port, (_, _, key, _) in plan.items())
        try:
            return self._shown(name, proxy.set_config(plain))
        finally:
            self._unit_changed(name)

    def get_statistics(self, name: str) -> UnitStatistics:
        """Uptime, reconfigurations, per-port messages, bytes, drops and latency of unit ``name``."""
        self._check_open()
        return self._proxy(name).get_statistics()

    def queue_depths(self, name: str) -> dict[str, int]:
        """How many messages each input port of unit ``name`` holds, waiting for it."""
        return self._proxy(name).queued()

    def port_counters(self, name: str) -> dict[str, PortCounters]:
        """The counters of each input port of unit ``name`` (for :mod:`dyknow.metrics`)."""
        return self._proxy(name).input_counters()

    @property
    def metrics(self) -> Metrics:
        """The manager's figures for operators: ``metrics.snapshot()`` (what ``get_metrics``
        answers, ``dyknow top`` shows) and what :class:`~dyknow.metrics.MetricsExporter` serves
        to Prometheus."""
        with self._lock:
            if self._metrics is None:
                self._metrics = Metrics(self)
            return self._metrics

    # ------------------------------------------------------------------ Zenoh services

    # ------------------------------------------------------------------ several managers

    def summary(self) -> Summary:
        """What this manager offers the others: host, library, running units, measurements."""
        stalled = self._adaptation.knowledge.stalled
        with self._lock:
            proxies = list(self._units.values())
            self._version += 1
            version = self._version
        units = tuple(
            SummaryUnit(
                p.name,
                p.label,
                {port.name: p.get_config()[port.name] for port in p.spec.outputs},
                {port.name: p.spec.tags_for(port.name) for port in p.spec.outputs},
                p.alive and p.name not in stalled,
                self._owners.get(p.name),
            )
            for p in proxies
            if p.label != ANCHOR_LABEL
        )
        library = f"{self._started_ns}.{self.library.version}"
        return Summary(
            self.name, self.host, version, library, self.library.specs(), units, self.measurements, len(self._adaptation.requests()), CLOCK_ID
        )

    @property
    def directory(self) -> Directory | None:
        """What this manager knows of the others (None when it does not federate): whom it
        follows, the tags whose providers it watches, what it refused (:class:`dyknow.federation.Directory`)."""
        return self._directory

    def peers(self) -> dict[str, Summary]:
        """The other managers this one reaches, with their last summary (empty when not federated)."""
        return self._directory.peers() if self._directory is not None else {}

    def discover(self, wanted: Collection[tuple[str, tuple[str, ...]]], *, need: str | None = None) -> bool:
        """Find the managers that offer the tags ``wanted`` and follow them (see
        :meth:`dyknow.federation.Directory.discover`); True when one was added. ``need``: the tag
        of the request that asks (let go when no open request has it: :meth:`changed`)."""
        return self._directory.discover(wanted, need=need) if self._directory is not None else False

    def reachable(self) -> set[str]:
        """The names of the other managers whose liveliness token is up (followed or not): a
        liveliness query when called, at most once a second (:meth:`dyknow.federation.Directory.alive`)."""
        return self._directory.alive() if self._directory is not None else set()

    def _peers_in_use(self) -> set[str]:
        """The managers this one exchanges data and calls with: those whose units its requests
        use, and those whose requests its units serve."""
        used = set(self._owners.values())
        for info in self._adaptation.requests():
            used.update(ref.rpartition("@")[2] for ref in (*info.units, *info.standby) if "@" in ref)
        # and those where units it spawned still run (a request's, being taken down as it ends)
        used.update(ref.rpartition("@")[2] for ref in list(self._adaptation.knowledge.remote) if "@" in ref)
        return used

    def changed(self) -> None:
        """This manager's model changed: the other managers hear of it (a summary, debounced)."""
        if self._directory is not None:
            self._directory.changed()
            # what the requests that ended needed (their candidates, the watches of their tags) is let go
            self._directory.keep({r.tag for r in list(self._adaptation.knowledge.requests.values())})
        if self._clocks is not None:
            self._clocks.reconcile()  # a manager may be in use now, or no longer

    def spawn_on(self, manager: str, label: str, name: str, *, bindings: Mapping[str, str]) -> None:
        """Spawn a unit on another manager, through its spawn service, for a request of this one."""
        info = self._peers.call_manager(manager, "spawn", {"label": label, "name": name, "bindings": dict(bindings), "owner": self.name})
        if info.get("state") == "failed":
            raise UnitError(f"failed at start: {info.get('error')}", where=f"unit {name!r} on manager {manager!r}")

    def destroy_on(self, manager: str, name: str) -> None:
        """Destroy a unit this manager spawned on another one."""
        self._peers.call_manager(manager, "destroy", {"name": name})

    def set_config_on(self, manager: str, name: str, bindings: Mapping[str, str]) -> None:
        """Rebind ports of a unit on another manager."""
        self._peers.call_unit(manager, name, "set_config", {"bindings": dict(bindings)})

    def _fetch_summary(self, manager: str) -> bytes:
        return json.dumps(self._peers.call_manager(manager, "get_summary", {})).encode()

    def _clock_peers(self) -> dict[str, tuple[str, int]]:
        """The managers whose clocks to estimate (on demand, issue 40): those this one exchanges
        data or calls with, and those whose clocks stamp data it received with no offset known.
        Such a clock id of a manager not followed yet is looked up by its clock token (at most
        8 ids a second, each once in 10 s): its manager is then followed, and tracked next round."""
        directory = self._directory
        if directory is None:
            return {}
        peers = directory.peers()
        used = self._peers_in_use()
        unknown = clocks.CLOCKS.unknown()
        for name, s in peers.items():  # whose data arrived: kept until it goes (once known, its data says no more)
            if s.clock in unknown and len(self._data_peers) < 256:
                self._data_peers.add(name)
        wanted = {
            name: (keys.clock_key(name), s.clock)
            for name, s in peers.items()
            if s.clock and s.clock != CLOCK_ID and (name in used or name in self._data_peers)  # one process, one clock: nothing to estimate
        }
        now = time.monotonic()
        for clock, at in list(self._clocks_asked.items()):
            if now - at > 10.0:
                del self._clocks_asked[clock]
        known = {s.clock for s in peers.values()}
        for clock in sorted(unknown - known)[:8]:
            if clock in self._clocks_asked or len(self._clocks_asked) >= 1024:
                continue
            self._clocks_asked[clock] = now

            def found(tokens: list[str], count: int, clock: int = clock) -> None:
                for token in tokens:
                    name = token.rpartition("/")[2]
                    if name != self.name:
                        directory.follow(name)

            try:
                self._session.ask_alive(keys.clock_token(clock, "*"), timeout_s=1.0, limit=2, done=found)
            except DyKnowError as exc:
                log.debug("no answer about clock %08x: %s", clock, exc)
        return wanted

    def _peer_changed(self, kind: str, manager: str) -> None:
        if self._clocks is not None:
            if kind == "lost":
                self._data_peers.discard(manager)
                self._clocks.untrack(manager)
            else:
                self._clocks.reconcile()  # maybe one to estimate now
        if kind == "lost":
            with self._lock:
                orphans = [unit for unit, owner in self._owners.items() if owner == manager]
            destroyed = []
            for unit in orphans:  # units that served the lost manager's requests
                try:
                    self.destroy(unit)
                    destroyed.append(unit)
                except DyKnowError as exc:
                    log.debug("unit %r of lost manager %r: %s", unit, manager, exc)
            why = self._directory.lost().get(manager, (0, "it is gone"))[1] if self._directory is not None else "it is gone"
            # one line: a manager that stopped is no fault; one that vanished is
            log.log(
                logging.INFO if why == STOPPED else logging.WARNING,
                "manager %r was lost (%s)%s",
                manager,
                why,
                f"; destroyed the units it had asked for: {', '.join(destroyed)}" if destroyed else "",
            )
        self._adaptation.peer_changed(kind, manager)

    def _brief(self) -> dict[str, Any]:
        """What a listing of the managers shows (``get_summary`` with ``brief``): counts, no library."""
        with self._lock:
            units = sum(1 for p in self._units.values() if p.label != ANCHOR_LABEL)
        return {"manager": self.name, "host": self.host, "specs": len(self.library), "units": units, "requests": len(self._adaptation.requests())}

    def _manager_handlers(self) -> dict[str, service.Handler]:
        return {
            "add_transformation": lambda r, c: {"labels": self.add_transformation(r["xml"], path=r.get("path") or "<remote>", remote=True)},
            "remove_transformation": lambda r, c: {"removed": self.remove_transformation(str(r["label"]))},
            "spawn": self._serve_spawn,
            "destroy": self._serve_destroy,
            "get_model": self._serve_model,
            "request": self._serve_request,
            "release": self._serve_release,
            "monitor": self._serve_monitor,
            "measure": self._serve_measure,
            "get_adaptations": lambda r, c: [e.to_dict() for e in self.get_adaptations()],
            "get_summary": lambda r, c: self._brief() if r.get("brief") else self.summary().to_dict(),
            "get_load": lambda r, c: self.load(),
            "get_metrics": lambda r, c: self.metrics.snapshot(),
        }

    def _serve_model(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        page = request.get("page", {})
        return self.get_model().page(page.get("units", 0), page.get("specs", 0), max_bytes=self.limits.max_reply_bytes)

    def _serve_spawn(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        owner = request.get("owner")
        log.info("spawn %s for %s", request.get("name"), owner)
        if owner and self._directory is not None:
            self._directory.follow(str(owner), at_once=True)  # its loss (or goodbye) is this one's concern now
        info = self.spawn(
            request["label"],
            request["name"],
            protected=bool(request.get("protected", False)),
            params=request.get("params") or {},
            bindings=request.get("bindings") or {},
            remote=True,
        )
        if owner:
            self._owners[info.name] = owner
            self.changed()
        return info.to_dict()

    def _serve_destroy(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        force = bool(request.get("force", False))
        unit = self._units.get(str(request["name"]))
        if force and caller is not None and caller.role != "admin" and unit is not None and unit.protected:
            role = f"the role {caller.role}" if caller.role else "no role"
            raise AccessError(
                f"{caller.common_name!r}, with {role}, may not destroy a protected unit",
                where=f"unit {request['name']!r} on manager {self.name!r}",
                expected="an admin (force: true is for admins), or destroy without force",
            )
        self.destroy(str(request["name"]), force=force)
        return {"destroyed": request["name"]}

    def _serve_release(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        key = str(request["key"])
        holder = request.get("holder")  # (checked with the request: dyknow.service)
        force = bool(request.get("force", False))
        if force and caller is not None and caller.role != "admin":
            role = f"the role {caller.role}" if caller.role else "no role"
            raise AccessError(
                f"{caller.common_name!r}, with {role}, may not force a release",
                where=f"{key!r} on manager {self.name!r}",
                expected="an admin (force: true is for admins), or a release of what the caller requested",
            )
        remaining = self.release(key, owner=_owner(caller, holder), force=force)
        if holder is not None and self._holders is not None and remaining > 0:
            self._holders.gave_back(key, holder)
        return {"released": key, "references": remaining}

    def _serve_request(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        holder = request.get("holder")  # (checked with the request, before anything is taken: dyknow.service)
        owner = _owner(caller, holder)
        key = self.request(str(request["tag"]), standby=request.get("standby"), require=request.get("require", ()), owner=owner)
        if holder is not None and self._holders is not None:
            try:
                self._holders.took(key, holder)
            except DyKnowError:
                self.release(key, owner=owner)
                raise
        return {"key": key, "kept": holder is None}

    def _serve_monitor(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        holder = request.get("holder")
        owner = _owner(caller, holder)
        key = self.monitor(str(request["formula"]), reorder_ms=float(request.get("reorder_ms", 0.0)), owner=owner)
        if holder is not None and self._holders is not None:
            try:
                self._holders.took(key, holder)
            except DyKnowError:
                self.release(key, owner=owner)
                raise
        return {"key": key, "kept": holder is None}

    def _serve_measure(self, request: dict[str, Any], caller: Caller | None) -> dict[str, Any]:
        self.measure(str(request["name"]), request["value"])
        return {"measured": request["name"]}

    def _unit_service(self, name: str, what: str, request: dict[str, Any], caller: Caller | None) -> Any:
        if what == "get_config":
            return self.get_config(name)
        if what == "set_config":
            bindings = request.get("bindings")
            if not isinstance(bindings, dict):
                raise BindingError(f"set_config got {bindings!r}", where=f"unit {name!r}", expected='{"bindings": {port: key}}')
            return self.set_config(name, bindings)
        return self.get_statistics(name).to_dict()


# ---------------------------------------------------------------------- helpers


def _owner(caller: Caller | None, holder: str | None) -> Owner:
    """Who a service call takes a reference for: its caller's name (with roles) and its client."""
    return Owner(caller.common_name if caller is not None else None, holder)


def _info(proxy: Proxy) -> UnitInfo:
    return UnitInfo(
        name=proxy.name,
        label=proxy.label,
        state=proxy.state.value,
        protected=proxy.protected,
        bindings=proxy.get_config(),
        executor=proxy.executor_description,
        error=proxy.error,
        traceback=proxy.traceback,
        spec=proxy.spec,
        started_ns=proxy.started_ns,
    )


def _loopback(endpoint: str) -> bool:
    return is_loopback(endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]"))


_SOURCE_SYNTAX = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*")


def _import_from(module_name: str, folders: Sequence[str]) -> Any:
    """Import ``module_name``; when its top-level package is not importable, look for it in
    ``folders`` (in order) and load it from there, leaving ``sys.path`` as it is."""
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        top = module_name.partition(".")[0]
        if exc.name != top or not folders:
            raise
        found = importlib.machinery.PathFinder.find_spec(top, list(folders))
        if found is None or found.loader is None:
            raise
        module = importlib.util.module_from_spec(found)
        sys.modules[top] = module
        try:
            found.loader.exec_module(module)
        except BaseException:
            sys.modules.pop(top, None)
            raise
        return importlib.import_module(module_name)


def _import_unit(spec: TransformationSpec, sources: SourcePolicy, folders: Sequence[str] = ()) -> type[Unit]:
    where = f"transformation {spec.label!r} ({spec.path}:{spec.line})"
    module_name, sep, class_name = spec.source.partition(":")
    if not _SOURCE_SYNTAX.fullmatch(spec.source):
        raise UnitError(f"source {spec.source!r} is not importable", where=where, expected="'package.module:Class'")
    sources.check(spec.source, where)  # before anything is imported
    try:
        # imported already: skip the import machinery (it keeps a little for every call)
        module = sys.modules.get(module_name) or _import_from(module_name, folders)
    except ModuleNotFoundError as exc:
        looked = f" (looked beside the specs and in --path folders: {', '.join(folders)})" if folders else ""
        raise UnitError(
            f"cannot import module {module_name!r} named in its source: {exc}{looked}",
            where=where,
            expected=f"{module_name.partition('.')[0]}.py (or a package of that name) beside the spec file or in a folder given with "
            "--path DIR (code_paths=), an installed package, or one on PYTHONPATH",
        ) from exc
    except Exception as exc:
        raise UnitError(f"importing module {module_name!r} failed: {type(exc).__name__}: {exc}", where=where) from exc
    cls = getattr(module, class_name, None)
    if cls is None:
        units = [n for n, v in vars(module).items() if inspect.isclass(v) and issubclass(v, Unit) and v is not Unit]
        raise UnitError(
            f"module {module_name!r} has no {class_name!r}",
            where=where,
            expected="a Unit subclass"
            + (f" such as {', '.join(repr(u) for u in units)}" if units else "")
            + did_you_mean(class_name, units),
        )
    if not (inspect.isclass(cls) and issubclass(cls, Unit)):
        raise UnitError(f"{spec.source!r} is a {type(cls).__name__}, not a unit", where=where, expected="a subclass of dyknow.Unit")
    return cls


def _param_values(spec: TransformationSpec, overrides: Mapping[str, Any]) -> dict[str, Any]:
    values = spec.param_values()
    declared = {p.name: p for p in spec.params}
    for name, value in overrides.items():
        param = declared.get(name)
        if param is None:
            listing = ", ".join(repr(n) for n in declared) or "none"
            raise UnitError(
                f"no param {name!r}", where=f"transformation {spec.label!r}", expected=f"one of {listing}{did_you_mean(name, declared)}"
            )
        values[name] = _coerce(param.type, value, f"param {name!r} of {spec.label!r}")
    return values


def _coerce(kind: str, value: Any, what: str) -> Any:
    """A spawn-time param value as its declared type: text is read as the spec format reads it."""
    try:
        if kind == "string":
            return str(value)
        if isinstance(value, str):
            return convert_param(kind, value.strip())
        if kind == "bool" and isinstance(value, bool):
            return value
        if kind == "int" and isinstance(value, int | float) and not isinstance(value, bool) and float(value).is_integer():
            if INT_RANGE[0] <= int(value) <= INT_RANGE[1]:
                return int(value)
            raise UnitError(
                f"got {str(value)[:40]}", where=what, expected="a whole number from -2**63 to 2**63-1 (int params are 64-bit)"
            )
        if kind == "float" and isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
    except (TypeError, ValueError, OverflowError):
        pass
    expected = {"bool": "true or false", "int": "a whole number", "float": "a number", "string": "text"}[kind]
    raise UnitError(f"got {value!r}", where=what, expected=f"{expected} ({kind})")


def _bindings(spec: TransformationSpec, manager: str, unit: str, overrides: Mapping[str, str]) -> dict[str, str]:
    ports = {p.name: p for p in spec.ports}
    result = {name: keys.default_key(manager, unit, name) for name in ports}
    for name, key in result.items():  # a port name from a remote spec can be long: so can the key
        check_key_expr(key, what=f"port {name!r} of unit {unit!r}", concrete=ports[name].direction == "out")
    for name, key in overrides.items():
        port = ports.get(name)
        if port is None:
            listing = ", ".join(repr(n) for n in ports)
            raise BindingError(
                f"no port {name!r}", where=f"transformation {spec.label!r}", expected=f"one of {listing}{did_you_mean(name, ports)}"
            )
        what = f"port {name!r} of unit {unit!r}"
        result[name] = keys.check_data_key(check_key_expr(key, what=what, concrete=port.direction == "out"), what)
    return result


_ROS2_BINDING = (Param("binding", "string", ""),)
_ROS2_SOURCE = TransformationSpec(
    "ros2-source", "dyknow.ros2.bridge:Ros2Source", _ROS2_BINDING, (Port("out", "out"),), description="a ROS 2 topic as a dyknow stream"
)
_ROS2_SINK = TransformationSpec(
    "ros2-sink", "dyknow.ros2.bridge:Ros2Sink", _ROS2_BINDING, (Port("in", "in"),), description="a dyknow stream as a ROS 2 topic"
)
