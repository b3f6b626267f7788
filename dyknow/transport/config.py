"""Zenoh configurations: endpoints and their schemes, peers, routers and clients, TLS and access control.

Without a configuration file a session is a Zenoh *peer* that talks over loopback only: multicast
scouting is off, it listens on ``tcp/127.0.0.1`` (a given port, or any free one) and connects to
the endpoints it is given. Gossip scouting stays on so that peers which connect to a manager also
find each other and exchange data directly. A manager's session is a Zenoh *router*
(``mode="router"``): routers route for each other over any path, so two managers that cannot link
directly still reach each other through a third one or a ``dyknow router``, where peers see only
the peers they link to. A Zenoh configuration file (json5) replaces these defaults to join a real
deployment.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Final

import zenoh

from dyknow.access import AccessControl, TlsFiles
from dyknow.errors import TransportError, did_you_mean
from dyknow.transport.runtime import error_text

__all__ = ["DEFAULT_ENDPOINT", "ROUTER_MAX_SESSIONS", "SCHEMES", "check_schemes", "lease_and_dials", "make_config"]

#: Where ``dyknow manager`` listens and where clients connect when told nothing else.
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: How many sessions a router (``dyknow router``, a manager) accepts at once by default (as
#: rmw_zenoh's router configuration does; Zenoh's own default is 1,000).
ROUTER_MAX_SESSIONS: Final = 10_000


#: The link protocols of the Zenoh that dyknow installs (eclipse-zenoh's wheel leaves out
#: unixpipe, serial and vsock).
SCHEMES: Final = ("tcp", "tls", "udp", "quic", "ws", "unixsock-stream")


def check_schemes(endpoints: Iterable[str], option: str) -> None:
    """Refuse an endpoint whose protocol Zenoh does not speak (``tpc/...``), naming the ones it
    does (Zenoh itself says only "Unicast not supported for tpc protocol")."""
    for endpoint in endpoints:
        scheme, slash, _ = endpoint.partition("/")
        if slash and scheme not in SCHEMES:  # (no protocol at all: Zenoh's own error, at make_config)
            raise TransportError(
                f"{endpoint}: no Zenoh link protocol {scheme!r}{did_you_mean(scheme, SCHEMES)}",
                where=option,
                expected=f"PROTOCOL/ADDRESS:PORT with PROTOCOL one of {', '.join(SCHEMES)} (such as tcp/127.0.0.1:7447)",
            )


def make_config(
    *,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] = (),
    config_file: str | os.PathLike[str] | None = None,
    tls: TlsFiles | None = None,
    access: AccessControl | None = None,
    lease_ms: int | None = None,
    mode: str = "peer",
    max_message_bytes: int | None = None,
    open_timeout_ms: int | None = None,
    max_sessions: int | None = None,
    shared_memory: bool = True,
) -> zenoh.Config:
    """Build a Zenoh configuration.

    Without ``config_file``: a loopback-only peer (multicast scouting off, gossip on) listening on
    ``listen`` (default: any free port on 127.0.0.1) and connecting to ``connect``. With
    ``config_file``: that json5 file, with ``listen``/``connect`` applied on top when given.
    ``tls``: TLS with mutual authentication on ``tls/HOST:PORT`` endpoints (this process's
    certificate for both listening and connecting, the CA to verify the peer's). ``access``: the
    roles to enforce, as Zenoh access control. ``lease_ms``: how long a silent link lives before
    Zenoh closes it (default 10,000 ms): what a peer cut off from the network takes to be noticed;
    shorter detects sooner, at the cost of keep-alive traffic and of false alarms on a slow link.
    ``mode``: "peer" (default), "router" (a manager, and ``dyknow router``: Zenoh routes
    between routers over any path, so two managers that cannot link directly still reach each
    other through a third or a router, where peers would not) or "client" (a leaf that only
    connects: :class:`~dyknow.client.Client` sessions; give it ``listen=[]``).
    ``max_message_bytes``: the largest message this session takes in (Zenoh's
    ``transport/link/rx/max_message_size``, 1 GiB by default). Zenoh drops a larger one while it
    reassembles it, fragment by fragment, so an oversized message costs at most this much memory.
    ``open_timeout_ms``: how long one attempt to open a link may take (Zenoh's
    ``transport/unicast/open_timeout``; by default the lease, from 2 to 10 s). A lost link is
    dialled again after 0.25 s, then up to every 1 s (half the lease when shorter).
    ``max_sessions``: how many sessions (managers, clients, routers) may link to this one at
    once (Zenoh's ``transport/unicast/max_sessions``); by default 10,000 for a router (Zenoh's
    own 1,000 refused the 1,001st manager of a fleet behind a ``dyknow router``), Zenoh's
    1,000 otherwise. ``shared_memory=False``: no Zenoh shared memory on this session's links, unless
    ``config_file`` says otherwise (``dyknow router``: it carries between hosts, and Zenoh 1.10 made a segment in /dev/shm for
    every session that negotiated it, refusing every session after the 351st).
    """
    for option, endpoints in (("--listen", listen or ()), ("--connect", connect)):
        check_schemes(endpoints, option)
    try:
        if config_file is not None:
            path = Path(config_file)
            if not path.is_file():
                raise TransportError("no such Zenoh configuration file", where=str(path), expected="a json5 file")
            try:
                config = zenoh.Config.from_file(str(path))
            except zenoh.ZError as exc:
                raise TransportError(f"not a valid Zenoh configuration: {error_text(exc)}", where=str(path)) from exc
        else:
            config = zenoh.Config()
            config.insert_json5("mode", json.dumps(mode))
            config.insert_json5("scouting/multicast/enabled", "false")
            config.insert_json5("scouting/gossip/enabled", "true")
            # One link per pair: when both dial each other (two peers that learn of each other
            # at once), the pair holds two TCP links, and after a silent cut closing them blocked
            # both of Zenoh's receive threads for up to 10 s (its fixed SO_LINGER, see "dead
            # links" in dyknow.transport.links), so nothing was read from the healthy links meanwhile. Only the
            # greater id dials. Routers (managers are) also dial the routers they hear of, for a
            # direct path; the path through the others stays when it cannot be made.
            config.insert_json5(
                "scouting/gossip/autoconnect_strategy",
                '{ peer: { to_router: "always", to_peer: "greater-zid" }, router: { to_router: "greater-zid", to_peer: "greater-zid" } }',
            )
            if mode == "router":
                config.insert_json5("scouting/gossip/autoconnect", '{ router: ["router"], peer: ["router", "peer"] }')
            # Dial again soon after a link is lost (Zenoh: after 1 s, then up to every 4 s), each
            # attempt bounded (Zenoh: 10 s): an attempt started while the link was down waits for
            # TCP's next SYN, 1, 3 then 7 s on, so a link back was used up to 4 s late (issue 43).
            # With attempts of at most 2 s (or the lease, up to 10 s), a SYN leaves every 1.25 s.
            lease = lease_ms if lease_ms is not None else 10_000
            retry = {"period_init_ms": 250, "period_max_ms": max(250, min(1000, lease // 2)), "period_increase_factor": 2}
            config.insert_json5("connect/retry", json.dumps(retry))
            if open_timeout_ms is None:
                open_timeout_ms = max(2000, min(10_000, lease))
            # Shared memory only where dyknow asks for it (unit payloads of SHM_THRESHOLD and up, in
            # a pool made on first use): Zenoh's own transport optimization put every message over
            # 3 KiB (the managers' summaries among them) in a 16 MiB pool of each session, and
            # every process mapped every other's, so an idle manager's memory grew with the number
            # of managers (benchmarks/memory.py).
            config.insert_json5("transport/shared_memory/transport_optimization/enabled", "false")
            config.insert_json5("scouting/delay", "0")
            # The admin space tells a manager which port it got when asked for port 0.
            config.insert_json5("adminspace/enabled", "true")
            if listen is None:
                listen = ["tls/127.0.0.1:0" if tls is not None else "tcp/127.0.0.1:0"]
        if listen is not None:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect or config_file is None:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if mode == "client" and config_file is None:
            # like a peer, a client opens before what it connects to is up, and keeps trying
            config.insert_json5("connect/exit_on_failure", "false")
        if tls is not None:
            prefix = "transport/link/tls"
            config.insert_json5(f"{prefix}/root_ca_certificate", json.dumps(tls.ca))
            for side in ("listen", "connect"):
                config.insert_json5(f"{prefix}/{side}_certificate", json.dumps(tls.cert))
                config.insert_json5(f"{prefix}/{side}_private_key", json.dumps(tls.key))
            config.insert_json5(f"{prefix}/enable_mtls", "true")
        if access is not None:
            config.insert_json5("access_control", json.dumps(access.zenoh()))
        if lease_ms is not None:
            if lease_ms < 100:
                raise TransportError(f"got {lease_ms} ms", where="lease", expected="at least 100 ms")
            config.insert_json5("transport/link/tx/lease", str(int(lease_ms)))
        if open_timeout_ms is not None:
            config.insert_json5("transport/unicast/open_timeout", str(max(100, int(open_timeout_ms))))
        if not shared_memory and config_file is None:
            config.insert_json5("transport/shared_memory/enabled", "false")
        if max_sessions is None and mode == "router" and config_file is None:
            max_sessions = ROUTER_MAX_SESSIONS
        if max_sessions is not None:
            if max_sessions < 1:
                raise TransportError(f"got {max_sessions}", where="max_sessions", expected="a whole number of at least 1")
            config.insert_json5("transport/unicast/max_sessions", str(int(max_sessions)))
        if max_message_bytes is not None:
            if max_message_bytes < 65536:
                raise TransportError(f"got {max_message_bytes} bytes", where="max_message_bytes", expected="at least 65,536")
            config.insert_json5("transport/link/rx/max_message_size", str(int(max_message_bytes)))
    except zenoh.ZError as exc:
        raise TransportError(f"invalid Zenoh endpoint: {error_text(exc)}", where=f"listen={listen!r} connect={list(connect)!r}") from exc
    return config


def lease_and_dials(config: zenoh.Config) -> tuple[int, list[str]]:
    """The lease (ms) of a configuration, and the endpoints it dials (a list, or one per mode)."""
    try:
        lease = json.loads(config.get_json("transport/link/tx/lease"))
        lease_ms = int(lease) if isinstance(lease, int) and not isinstance(lease, bool) and lease > 0 else 10_000
    except (zenoh.ZError, ValueError):
        lease_ms = 10_000
    try:
        found = json.loads(config.get_json("connect/endpoints"))
    except (zenoh.ZError, ValueError):
        found = []
    listed = found if isinstance(found, list) else [e for v in found.values() if isinstance(v, list) for e in v] if isinstance(found, dict) else []
    return lease_ms, [str(e) for e in listed]

