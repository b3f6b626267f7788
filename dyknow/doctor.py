"""``dyknow doctor``: what stands between this machine and a working set-up, each with its fix.

Each check returns :class:`Diagnosis` records (``ok``, ``warn`` or ``fail``, what was found and
the fix); :func:`diagnose` runs them in the order a set-up depends on them:

==============  ==========================================================================================
check           what it finds
==============  ==========================================================================================
config          a Zenoh configuration file (``--zenoh-config``) that can find no one: multicast scouting
                off and no endpoint to connect to (or one that relies on multicast alone)
shm             no usable ``/dev/shm``: Zenoh's shared memory cannot be made (a container's 64 MiB
                default, a read-only mount), so large payloads are copied instead
port            the port a manager would listen on (``--listen``; without it, the first ``--connect`` endpoint
                when it is this host's address) taken: by a dyknow manager (clients reach it), another Zenoh
                node, or another program
endpoints       each ``--connect`` endpoint probed (:mod:`dyknow.reach`): nothing listens (the manager or
                router there is down), no route, a silent host, TLS refused either way
managers        the managers reachable through them; none (a router that answers with no manager
                behind it is told apart), or not the one ``--manager`` names: LOST (since when, why, as
                which managers saw it), or never there (with the close match)
access          each manager answers ``get_model``: an ACL (``--acl``) that gives this certificate no
                role, or a role that may not read, is named with the certificate's common name
lost            the managers the others knew and lost, and that are not back (:mod:`dyknow.presence`):
                vanished (crashed, or cut off past their lease) fails, stopped (a goodbye) warns
requests        each manager's requests that are degraded (a provider lost, a requirement false), and why
clocks          the offsets between the managers' clocks, as each estimates the others' (:mod:`dyknow.clocks`):
                one beyond ``max_offset_ms`` (an unsynchronised host)
==============  ==========================================================================================

Nothing here changes anything: the checks bind a port for an instant, open a client session, and
call read-only services.
"""

from __future__ import annotations

import errno
import os
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dyknow.access import TlsFiles
from dyknow.errors import DyKnowError, ServiceError, did_you_mean
from dyknow.presence import THIS_CLIENT, Loss, merge
from dyknow.replies import MALFORMED

__all__ = [
    "DEFAULT_MAX_OFFSET_MS",
    "Diagnosis",
    "check_clocks",
    "check_config",
    "check_federation",
    "check_port",
    "check_shm",
    "diagnose",
]

#: The clock offset between two managers beyond which doctor fails (milliseconds): NTP on a LAN
#: keeps hosts within about 1 ms, chrony within a fraction of that.
DEFAULT_MAX_OFFSET_MS = 10.0

STATUSES = ("ok", "warn", "fail")


@dataclass(frozen=True, slots=True)
class Diagnosis:
    """One finding: its ``check``, ``status`` (ok, warn or fail), ``what`` was found and the ``fix``."""

    check: str
    status: str
    what: str
    fix: str = ""

    def to_dict(self) -> dict[str, str]:
        """The JSON form (``dyknow doctor --json``)."""
        return {"check": self.check, "status": self.status, "what": self.what, "fix": self.fix}

    def lines(self) -> list[str]:
        """The finding as people read it: a line, and the fix's (when there is one)."""
        mark = {"ok": "ok  ", "warn": "WARN", "fail": "FAIL"}[self.status]
        return [f"{mark} {self.check:<9} {self.what}", *([f"               fix: {self.fix}"] if self.fix else [])]

    def __str__(self) -> str:
        return "\n".join(self.lines())


def _split(endpoint: str) -> tuple[str, str, int] | None:
    proto, sep, rest = endpoint.partition("/")
    host, colon, port = rest.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    if not sep or not colon or not port.isdigit() or proto not in ("tcp", "tls"):
        return None
    return proto, host.strip("[]"), int(port)


def check_config(zenoh_config: str | None, connect: Sequence[str]) -> list[Diagnosis]:
    """A Zenoh configuration file that can find no one, or relies on multicast alone."""
    if zenoh_config is None:
        return [Diagnosis("config", "ok", "dyknow's defaults: a loopback peer, multicast scouting off, connecting to --connect")]
    import json5

    path = Path(zenoh_config)
    try:
        config = json5.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return [Diagnosis("config", "fail", f"cannot read the Zenoh configuration {path}: {exc}", "a json5 file (--zenoh-config)")]
    if not isinstance(config, dict):
        return [Diagnosis("config", "fail", f"{path} holds no JSON object", "a Zenoh json5 configuration")]

    def get(*names: str) -> Any:
        node: Any = config
        for name in names:
            node = node.get(name) if isinstance(node, dict) else None
        return node

    endpoints = get("connect", "endpoints") or []
    if isinstance(endpoints, dict):  # per mode: {router: [...], peer: [...], client: [...]}
        endpoints = [e for v in endpoints.values() for e in (v or [])]
    multicast = get("scouting", "multicast", "enabled")
    multicast = True if multicast is None else bool(multicast)  # Zenoh's default: on
    mode = get("mode") or "peer"
    if endpoints or connect:
        return [Diagnosis("config", "ok", f"{path}: mode {mode}, connects to {', '.join([*endpoints, *connect])}")]
    if not multicast:
        return [
            Diagnosis(
                "config",
                "fail",
                f"{path}: multicast scouting is off and it connects nowhere (no connect/endpoints, no --connect): "
                "this session can find no manager, router or peer",
                "give it an endpoint to connect to: --connect ENDPOINT (such as tcp/127.0.0.1:7447), or connect/endpoints in the file; "
                "or turn scouting/multicast/enabled on where the network carries multicast",
            )
        ]
    return [
        Diagnosis(
            "config",
            "warn",
            f"{path}: finds the others by multicast scouting alone (no connect/endpoints)",
            "fine on one network segment that carries multicast; across routers, in containers or over Wi-Fi, give --connect ENDPOINT",
        )
    ]


def check_shm() -> list[Diagnosis]:
    """Whether Zenoh's shared memory can be made here, as a publisher of a large payload does."""
    from dyknow.transport import SHM_POOL_BYTES, SHM_THRESHOLD, shared_memory_problem

    where = Path("/dev/shm")
    free = ""
    try:
        stats = os.statvfs(where)
        free = f"; {where} has {stats.f_bavail * stats.f_frsize / 2**20:.0f} MiB free"
    except OSError as exc:
        free = f"; {where}: {exc.strerror or exc}"
    problem = shared_memory_problem()
    if problem is None:
        return [Diagnosis("shm", "ok", f"Zenoh shared memory works (a {SHM_POOL_BYTES >> 20} MiB pool{free})")]
    return [
        Diagnosis(
            "shm",
            "warn",
            f"no usable shared memory: {problem}{free}; payloads of {SHM_THRESHOLD >> 10} KiB and more (images) are copied "
            "through the network stack instead (more CPU and latency), nothing fails",
            f"a writable tmpfs of at least {SHM_POOL_BYTES >> 20} MiB on {where} (Docker: --shm-size=256m, or --ipc=host)",
        )
    ]


def check_port(listen: Sequence[str], tls: TlsFiles | None = None, *, connecting: bool = False) -> list[Diagnosis]:
    """Whether each port a manager would listen on is free, and if not, what holds it.
    ``connecting``: ``listen`` is where this host connects (no ``--listen`` given): an address
    that is another host's is no fault (a client host has no port of its own to check)."""
    found = []
    for endpoint in listen:
        parts = _split(endpoint)
        if parts is None:
            continue
        _, host, port = parts
        if port == 0:
            continue
        try:
            with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
                sock.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRNOTAVAIL and connecting:
                found.append(Diagnosis("port", "ok", f"{endpoint} is another host's address: this host connects there, and listens "
                                                     "nowhere (--listen ENDPOINT checks a port a manager here would take)"))  # fmt: skip
                continue
            if exc.errno != errno.EADDRINUSE:
                found.append(Diagnosis("port", "fail", f"cannot listen on {endpoint}: {exc.strerror or exc}", "an address of this host"))
                continue
            found.append(_holder(endpoint, host, port, tls))
            continue
        found.append(Diagnosis("port", "ok", f"{endpoint} is free for a manager to listen on"))
    return found


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def _holder(endpoint: str, host: str, port: int, tls: TlsFiles | None) -> Diagnosis:
    """What listens on a port that is taken: a dyknow manager, another Zenoh node, or another program."""
    from dyknow.client import Client

    proto = endpoint.partition("/")[0]
    other = f"{proto}/{host}:{_free_port(host)}"
    try:
        with Client("dyknow", connect=[endpoint], tls=tls, timeout_s=1.0) as client:
            names = client.manager_names(timeout_s=1.0)
            linked = client.session.linked()
    except DyKnowError:
        names, linked = [], False
    if names:
        return Diagnosis(
            "port",
            "ok",
            f"{endpoint} is taken by dyknow manager {', '.join(repr(n) for n in names)}: clients reach it there "
            f"(a second manager on this host needs another port: dyknow manager --listen {other})",
        )
    holder = "another Zenoh node (a router or a peer, no dyknow manager)" if linked else "another program (it does not speak Zenoh)"
    return Diagnosis(
        "port",
        "fail",
        f"{endpoint} is taken by {holder}: a manager cannot listen there, and clients that connect there find no manager",
        f"dyknow manager --listen {other}, and --connect {other} on every client command (port {other.rpartition(':')[2]} is free now)",
    )


def check_endpoints(connect: Sequence[str], tls: TlsFiles | None) -> list[Diagnosis]:
    """Each ``--connect`` endpoint probed with plain sockets (and TLS): see :mod:`dyknow.reach`."""
    from dyknow.reach import probe_all

    found = []
    for finding in probe_all(list(connect), tls, timeout_s=1.0):
        if finding.kind == "ok":
            found.append(Diagnosis("endpoint", "ok", f"{finding.endpoint} answers"))
        elif finding.kind == "refused":
            found.append(
                Diagnosis(
                    "endpoint",
                    "fail",
                    f"{finding.what}: the manager or router there is down, or listens elsewhere",
                    f"start it (dyknow manager --listen {finding.endpoint}, or dyknow router --listen {finding.endpoint}), "
                    "or --connect where it listens",
                )
            )
        elif finding.kind == "unknown":
            found.append(Diagnosis("endpoint", "warn", f"{finding.endpoint}: not probed ({finding.what or 'a protocol the probe does not speak'})"))
        else:
            found.append(Diagnosis("endpoint", "fail", finding.what, finding.expected))
    return found


def check_managers(client: Any, manager: str, connect: Sequence[str], signed: bool = False) -> tuple[list[Diagnosis], list[str]]:
    """The managers reachable, and whether ``manager`` is among them (``signed``: the client has a
    certificate, so managers with an ACL may show it nothing)."""
    names = sorted(client.manager_names(timeout_s=1.5))
    if not names and client.timeout_s > 1.5:  # (a loaded host answers late: look once more, as long as --timeout allows)
        names = sorted(client.manager_names(timeout_s=client.timeout_s))
    where = ", ".join(connect) or "the Zenoh configuration's endpoints"
    if not names:
        if client.session.linked():
            if signed:
                return [
                    Diagnosis(
                        "managers",
                        "fail",
                        f"linked through {where}, but no manager is visible: with --acl, a manager shows a certificate "
                        "without a role nothing",
                        "give this certificate's common name a role in the managers' --acl file (viewer at least)",
                    )
                ], []
            return [
                Diagnosis(
                    "managers",
                    "fail",
                    f"{where} answers (a router or a peer), but no manager is connected to it",
                    f"start a manager that connects there: dyknow manager --connect {connect[0] if connect else 'ENDPOINT'}",
                )
            ], []
        return [Diagnosis("managers", "fail", f"no manager reachable through {where}", "start one (dyknow manager), or --connect where one listens")], []
    return [Diagnosis("managers", "ok", f"reachable: {', '.join(names)}")], names


def check_named(manager: str, names: Sequence[str], lost: Mapping[str, Loss]) -> list[Diagnosis]:
    """Whether ``manager`` (``--manager``) is among ``names``, the managers reachable; when not,
    whether it is one of those ``lost`` (never then called a misspelling)."""
    if manager in names:
        return []
    loss = lost.get(manager)
    if loss is not None:
        return [Diagnosis("managers", "warn" if loss.stopped else "fail", loss.said(), loss.fix())]
    if not names:
        return []
    return [
        Diagnosis(
            "managers",
            "warn",
            f"no manager {manager!r} among them, nor lost as far as they know{did_you_mean(manager, names)}",
            f"--manager {names[0]}" + (f" (or one of {', '.join(names[1:])})" if len(names) > 1 else ""),
        )
    ]


def check_federation(models: Mapping[str, Mapping[str, Any]], lost: Mapping[str, Loss], manager: str) -> list[Diagnosis]:
    """The managers lost and not back (but ``manager``, said by :func:`check_named`), and each
    manager's degraded requests (``models``: each manager's, by name)."""
    found = [Diagnosis("lost", "warn" if loss.stopped else "fail", loss.said(), loss.fix()) for name, loss in lost.items() if name != manager]
    for name, model in models.items():
        for request in model.get("requests", []):
            if request.get("state") != "degraded":
                continue
            why = request.get("reason") if isinstance(request.get("reason"), str) else "no reason given (an older manager)"
            found.append(
                Diagnosis(
                    "requests",
                    "warn",
                    f"manager {name!r}: request {request['tag']} ({request['key']}) is degraded: {why}",
                    "it runs on what is left and returns to a full configuration by itself once one exists (a lost provider back, "
                    f"a requirement holding again); dyknow plan '{request['tag']}' --manager {name} says what is missing now",
                )
            )
    if models and not found:
        found.append(Diagnosis("lost", "ok", f"no manager lost, no request degraded (asked: {', '.join(sorted(models))})"))
    return found


def check_access(client: Any, names: Sequence[str], models: dict[str, Mapping[str, Any]] | None = None) -> list[Diagnosis]:
    """Each manager asked for its model (kept in ``models``, by name): refusals by an ACL
    named with the certificate."""
    found = []
    for name in names:
        try:
            model = client.get_model(name)
            if models is not None:
                models[name] = model
        except ServiceError as exc:
            if exc.details.get("reason") in ("dropped", "no-role"):
                found.append(Diagnosis("access", "fail", f"manager {name!r}: {exc.what}", exc.expected or "a role for this certificate in its --acl"))
            elif exc.details.get("reason") == MALFORMED:  # (something answers as it, and not as a manager does)
                found.append(Diagnosis("access", "fail", f"{exc.where}: {exc.what}", exc.expected or ""))
            else:
                found.append(Diagnosis("access", "fail", f"manager {name!r} did not answer get_model: {exc}"))
            continue
        except DyKnowError as exc:
            found.append(Diagnosis("access", "fail", f"manager {name!r} did not answer get_model: {exc}"))
            continue
        found.append(Diagnosis("access", "ok", f"manager {name!r} answers this client"))
    return found


def check_clocks(client: Any, names: Sequence[str], max_offset_ms: float = DEFAULT_MAX_OFFSET_MS) -> list[Diagnosis]:
    """The offset of every pair of managers' clocks, as each estimates the others'."""
    found: list[Diagnosis] = []
    worst: dict[tuple[str, str], tuple[float, float]] = {}
    for name in names:
        try:
            estimates = client.clocks(name)
        except DyKnowError:
            continue
        for other, estimate in estimates.items():
            if other == name or other not in names:
                continue
            pair = (min(name, other), max(name, other))
            offset_ms, uncertainty_ms = abs(estimate.offset_ns) / 1e6, estimate.uncertainty_ns / 1e6
            if pair not in worst or offset_ms - uncertainty_ms > worst[pair][0] - worst[pair][1]:
                worst[pair] = (offset_ms, uncertainty_ms)
    for (a, b), (offset_ms, uncertainty_ms) in sorted(worst.items()):
        if offset_ms - uncertainty_ms > max_offset_ms:
            found.append(
                Diagnosis(
                    "clocks",
                    "fail",
                    f"the clocks of {a!r} and {b!r} differ by {offset_ms:.1f} ms (+/- {uncertainty_ms:.1f}), beyond {max_offset_ms:g} ms: "
                    "ages across them are corrected by the estimate, but timestamps a unit reads (a formula's times, a recording's) "
                    "disagree by that much",
                    "synchronise the hosts' clocks: chrony or NTP on each (PTP for better than a millisecond)",
                )
            )
        else:
            found.append(Diagnosis("clocks", "ok", f"{a!r} and {b!r}: {offset_ms:.3f} ms apart (+/- {uncertainty_ms:.3f})"))
    if len(names) > 1 and not worst:
        found.append(Diagnosis("clocks", "warn", "no clock offsets known yet between the managers (they estimate them within seconds of meeting)"))
    return found


def diagnose(
    *,
    connect: Sequence[str],
    listen: Sequence[str] = (),
    manager: str = "dyknow",
    zenoh_config: str | None = None,
    tls: TlsFiles | None = None,
    max_offset_ms: float = DEFAULT_MAX_OFFSET_MS,
) -> list[Diagnosis]:
    """Every check, in the order a set-up depends on them (see the module documentation)."""
    from dyknow.client import Client

    found = check_config(zenoh_config, connect)
    found += check_shm()
    found += check_port(listen or connect[:1], tls, connecting=not listen)
    if connect:
        found += check_endpoints(connect, tls)
    if any(d.status == "fail" for d in found if d.check == "config"):
        return found
    try:
        client = Client(manager, connect=list(connect), zenoh_config=zenoh_config, tls=tls, timeout_s=2.0)
    except DyKnowError as exc:
        return [*found, Diagnosis("managers", "fail", f"cannot open a session: {exc}")]
    with client:
        managers, names = check_managers(client, manager, connect, signed=tls is not None)
        found += managers
        models: dict[str, Mapping[str, Any]] = {}
        if names:
            found += check_access(client, names, models)
        reports = [(THIS_CLIENT, client.seen_lost()), *((name, client.lost_managers(name, model=model)) for name, model in models.items())]
        lost = merge(reports, up=names)
        found += check_named(manager, names, lost)
        found += check_federation(models, lost, manager)
        if names:
            found += check_clocks(client, names, max_offset_ms)
    return found
