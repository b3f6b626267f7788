"""Spawning: the manager's running units, each made from its spec and given its proxy, and destroyed again.

A :class:`Spawner` imports a unit's class under the operator's source policy (a module beside a
trusted spec, or in a ``--path`` folder, is loaded without changing ``sys.path``), reads the
spawn's params as their declared types, binds the ports to keys, creates the unit and its
:class:`~dyknow.proxy.Proxy`, and keeps the running units: which changed and when (what the
adaptation loop's index follows), and which have outputs with a deadline.
"""

from __future__ import annotations

import collections
import importlib
import importlib.machinery
import importlib.util
import inspect
import logging
import math
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from dyknow import keys
from dyknow.adaptation import DeadlinePort
from dyknow.bus import LocalBus
from dyknow.errors import AccessError, BindingError, UnitError, did_you_mean
from dyknow.executor import Executor
from dyknow.manager.library import SOURCE_SYNTAX, Librarian
from dyknow.model import UnitInfo
from dyknow.proxy import Proxy, UnitState
from dyknow.reasoning.unit import FormulaMonitor, MonitorBudget
from dyknow.receiver import Receiver
from dyknow.ros2.bridge import Ros2Provider, UsesRos2
from dyknow.security import DataRoots, Limits, SourcePolicy
from dyknow.spec import TransformationSpec
from dyknow.spec.model import INT_RANGE, convert_param
from dyknow.transport import Session, check_key_expr
from dyknow.unit import Unit

__all__ = ["Spawner"]

log = logging.getLogger("dyknow.manager")  # one name for the manager, whichever part logs

_UNIT_LOG = 4096  # changes of units remembered (unit_changes); a reader further behind reads them all


class Spawner:
    """Creates and destroys the units of manager ``manager``, and keeps those that run.

    It shares the manager's ``lock``. ``check_open`` raises when the manager is closed, and
    ``closed`` says whether it is; ``emit(kind, proxy)`` tells the manager a unit was
    ``"spawned"``, ``"failed"`` or ``"destroyed"``. A unit that uses ROS 2 is given ``ros2``.
    """

    def __init__(
        self,
        manager: str,
        *,
        lock: threading.RLock,
        limits: Limits,
        librarian: Librarian,
        roots: DataRoots,
        session: Session,
        bus: LocalBus,
        receiver: Receiver,
        executor: Executor,
        queue_depth: int,
        monitor_budget: MonitorBudget,
        ros2: Ros2Provider,
        check_open: Callable[[], None],
        closed: Callable[[], bool],
        emit: Callable[[str, Proxy], None],
    ) -> None:
        self._manager = manager
        self._lock = lock
        self._limits = limits
        self._librarian = librarian
        self._roots = roots
        self._session = session
        self._bus = bus
        self._receiver = receiver
        self._executor = executor
        self._queue_depth = queue_depth
        self._monitor_budget = monitor_budget
        self._ros2 = ros2
        self._check_open = check_open
        self._closed = closed
        self._emit = emit
        self._units: dict[str, Proxy] = {}
        # which units changed, and when (a version each): what the adaptation loop's index reads
        self._unit_version = 0
        self._unit_log: collections.deque[tuple[int, str]] = collections.deque(maxlen=_UNIT_LOG)
        self._deadlines: dict[str, Proxy] = {}  # the units with deadline-ms outputs (the monitor watches them)
        self._starting: dict[str, threading.Lock] = {}  # units being spawned: held until spawn returns

    def spawn(
        self,
        label: str | TransformationSpec,
        name: str,
        *,
        protected: bool = False,
        params: Mapping[str, Any] | None = None,
        bindings: Mapping[str, str] | None = None,
        remote: bool = False,
        account: str | None = None,
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
        raises :class:`AccessError` and changes nothing. ``account``: whose share of the
        monitors' formula nodes a formula monitor takes (:class:`~dyknow.reasoning.unit.MonitorBudget`;
        None: the manager's own).
        """
        with self._lock:
            self._check_open()
            keys.check_name(name, "unit name")
            if isinstance(label, TransformationSpec) and not remote:
                self._librarian.trust([label])
            if len(self._units) + len(self._starting) >= self._limits.max_units:
                raise UnitError(
                    f"the manager already runs {len(self._units) + len(self._starting)} units, its most",
                    where=f"manager {self._manager!r}",
                    expected=f"at most {self._limits.max_units} units (--max-units): destroy some first",
                )
            if name in self._units or name in self._starting:
                running = self._units.get(name)
                state = f"label {running.label!r}, {running.state.value}" if running is not None else "being spawned"
                raise UnitError(
                    f"a unit named {name!r} already exists ({state})",
                    where=f"manager {self._manager!r}",
                    expected="another name, or destroy it first",
                )
            spec = label if isinstance(label, TransformationSpec) else self._librarian.library.get(label)
            values = _param_values(spec, params or {})
            ports = _bindings(spec, self._manager, name, bindings or {})
            confine = remote or (isinstance(label, str) and self._librarian.added_remotely(label))
            # The name is taken; the rest (import, setup()) runs without the manager's lock, so
            # other calls go on meanwhile. Calls that change this unit wait for the gate.
            gate = threading.Lock()
            gate.acquire()
            self._starting[name] = gate
        try:
            return self._start(spec, name, protected=protected, values=values, ports=ports, confine=confine, account=account)
        finally:
            with self._lock:
                del self._starting[name]
            gate.release()

    def _start(
        self,
        spec: TransformationSpec,
        name: str,
        *,
        protected: bool,
        values: dict[str, Any],
        ports: dict[str, str],
        confine: bool = False,
        account: str | None = None,
    ) -> UnitInfo:
        """Import, create and start a unit (its name is reserved; the manager lock is not held)."""
        cls = _import_unit(spec, self._librarian.sources, self._librarian.code_paths)
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
            unit.use_ros2(self._ros2)
        if isinstance(unit, FormulaMonitor):
            unit.use_budget(self._monitor_budget, account)
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
        self.changed(name)
        if self._closed():  # closed while it started: close() did not see it
            proxy.stop(0.5)
            self._check_open()
        if proxy.state is not UnitState.FAILED:
            self._emit("spawned", proxy)
        return _info(proxy)

    def settled(self, name: str, timeout_s: float = 60.0) -> None:
        """Wait until a spawn of ``name`` in flight has returned (calls on one unit stay in order)."""
        with self._lock:
            gate = self._starting.get(name)
        if gate is None:
            return
        if not gate.acquire(timeout=timeout_s):
            raise UnitError(f"still starting after {timeout_s:.0f} s", where=f"unit {name!r}", expected="a unit whose setup() returns")
        gate.release()

    def destroy(self, name: str, *, force: bool = False) -> None:
        """Stop unit ``name`` and remove it (see :meth:`dyknow.manager.Manager.destroy`)."""
        self.settled(name)
        with self._lock:
            self._check_open()
            proxy = self.proxy(name)
            if proxy.protected and not force:
                raise UnitError(
                    "the unit is protected (spawned with protected=True), so it cannot be destroyed without force",
                    where=f"unit {name!r}",
                    expected="destroy(name, force=True) (dyknow destroy NAME --force; an admin's, when the manager has roles)",
                )
            del self._units[name]
            self._deadlines.pop(name, None)
            self.changed(name)
        proxy.stop()
        log.info("unit %r destroyed", name)
        self._emit("destroyed", proxy)

    def _destroy_requested(self, proxy: Proxy) -> None:
        with self._lock:
            if self._closed() or self._units.get(proxy.name) is not proxy:
                return
            del self._units[proxy.name]
            self._deadlines.pop(proxy.name, None)
            self.changed(proxy.name)
        proxy.stop()
        log.info("unit %r destroyed itself", proxy.name)
        self._emit("destroyed", proxy)

    def _unit_failed(self, proxy: Proxy) -> None:
        self.changed(proxy.name)
        self._emit("failed", proxy)

    def close(self) -> list[Proxy]:
        """Forget every unit (the manager is closing, under its lock); returns their proxies, to stop."""
        proxies = list(self._units.values())
        self._units.clear()
        self._deadlines.clear()
        return proxies

    # ------------------------------------------------------------------ what runs

    def changed(self, name: str) -> None:
        """Unit ``name`` was spawned, destroyed, rebound or failed: a new version of the units."""
        with self._lock:
            self._unit_version += 1
            self._unit_log.append((self._unit_version, name))

    def unit_changes(self, since: int) -> tuple[int, list[str] | None]:
        """See :meth:`dyknow.manager.Manager.unit_changes`."""
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

    def proxy(self, name: str) -> Proxy:
        """The proxy of running unit ``name``; :class:`UnitError` listing the running units otherwise."""
        proxy = self._units.get(name)
        if proxy is None:
            known = list(self._units)
            listing = ", ".join(repr(k) for k in known) or "none"
            raise UnitError(
                f"no unit named {name!r}",
                where=f"manager {self._manager!r}",
                expected=f"one of the running units: {listing}{did_you_mean(name, known)}",
            )
        return proxy

    def get(self, name: str) -> Proxy | None:
        """The proxy of running unit ``name``, or None."""
        return self._units.get(name)

    def proxies(self) -> list[Proxy]:
        """A snapshot of the running units' proxies."""
        with self._lock:
            return list(self._units.values())

    def info(self, name: str) -> UnitInfo | None:
        """Unit ``name`` as the model shows it; None when it does not run."""
        proxy = self._units.get(name)
        return _info(proxy) if proxy is not None else None

    def infos(self) -> list[UnitInfo]:
        """A snapshot of every running unit, as the model shows them."""
        return [_info(p) for p in self.proxies()]

    def has(self, name: str) -> bool:
        """Whether a unit called ``name`` runs (in any state)."""
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

    def counts(self) -> dict[str, int]:
        """What it holds, by kind (under the manager's lock): see :meth:`dyknow.manager.Manager.resources`."""
        with self._lock:
            return {"units": len(self._units), "starting": len(self._starting), "deadline_units": len(self._deadlines)}


# ---------------------------------------------------------------------- a unit from its spec


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
    if not SOURCE_SYNTAX.fullmatch(spec.source):
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
