"""The manager on the network: its Zenoh session, over its endpoints or behind routers, with TLS and roles.

What cannot work whatever runs elsewhere is refused before the session opens (roles without a
certificate, a ``tls/`` endpoint without TLS files, routers with other endpoints); what is probably
a mistake is logged (a certificate named after another manager, TLS files with no ``tls/``
endpoint). Behind routers, the manager dials them patiently (:func:`dyknow.reach.open_patiently`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

from dyknow import reach
from dyknow.access import AccessControl, TlsFiles
from dyknow.errors import AccessError, TransportError
from dyknow.identity import Signer, Verifier
from dyknow.security import Limits, is_loopback
from dyknow.transport import Session, make_config

__all__ = ["Network"]

log = logging.getLogger("dyknow.manager")  # one name for the manager, whichever part logs

_BUSY_ROUTER_S = 60.0  # how long a manager tries again a router that accepts connections but is slow to open a session


class Network:
    """Manager ``manager`` on the network: its ``session``, its ``tls`` files (checked), its roles
    (``access``, with the ``verifier`` of its callers' certificates) and the ``routers`` it sits
    behind (see :class:`~dyknow.manager.Manager` for the options)."""

    def __init__(
        self,
        manager: str,
        *,
        listen: Sequence[str] | None,
        connect: Sequence[str],
        router: Sequence[str],
        zenoh_config: str | os.PathLike[str] | None,
        tls: TlsFiles | None,
        acl: AccessControl | str | os.PathLike[str] | None,
        lease_ms: int | None,
        limits: Limits,
    ) -> None:
        access = acl if isinstance(acl, AccessControl) or acl is None else AccessControl.load(acl)
        self.tls = tls.check() if tls is not None else None
        self.verifier: Verifier | None = None
        if access is not None:
            if self.tls is None:
                raise AccessError(
                    "roles (--acl) are given by certificate, and the manager has none",
                    where=f"manager {manager!r}",
                    expected="--tls-ca, --tls-cert and --tls-key with --acl (dyknow certs writes development ones)",
                )
            self.verifier = Verifier(self.tls.ca, access, budget=limits.max_caller_calls, ahead_budget=limits.max_caller_calls_ahead)
            own = Signer(self.tls).common_name
            if own != manager:
                log.warning(
                    "manager %r runs with the certificate of %r: managers whose --acl lists it under manager accept its "
                    "services, summary and liveliness only from a certificate named after it",
                    manager,
                    own,
                )
        self.access = access
        if zenoh_config is None:  # (Zenoh would say only "Missing TLS private key")
            reach.check_endpoints(listen or (), self.tls, option="--listen", who=f"manager {manager!r}")
            reach.check_endpoints(connect, self.tls, option="--connect", who=f"manager {manager!r}")
            if self.tls is not None and listen and not any(e.startswith("tls/") for e in [*listen, *connect]):
                log.warning(
                    "manager %r has TLS files but no tls/ endpoint (--listen, --connect): every link is plain TCP, and no "
                    "caller has a certificate for its roles",
                    manager,
                )
        self.routers = list(router)
        if router:
            if listen or connect:
                raise TransportError(
                    "a manager behind a router dials only its router",
                    where=f"manager {manager!r}",
                    expected="router endpoints alone (--router), or --listen/--connect without --router",
                )
            if zenoh_config is None:
                reach.check_endpoints(router, self.tls, option="--router", who=f"manager {manager!r}")

        def session(mode: str) -> Session:
            return Session(
                make_config(
                    listen=[] if router else listen,
                    connect=list(router or connect),
                    config_file=zenoh_config,
                    tls=self.tls,
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
            self.session = session("router")
        else:
            opened = reach.open_patiently(lambda: session("client"), router, patience_s=_BUSY_ROUTER_S, who=f"manager {manager!r}")
            if opened is not None:
                self.session = opened
            else:
                # (a Zenoh client does not start without its router; a robot's manager must run
                # its own units meanwhile: a router without a listener keeps dialling, one link each)
                log.warning(
                    "manager %r: no router of %s answers yet (none listens there, or it refused this manager: a router full at its "
                    "--max-sessions, or TLS); it runs meanwhile and dials them until they do (holding a link to each that answers, not "
                    "only to the first), linked as a Zenoh router, which receives every declaration of the fleet: in a large fleet, "
                    "restart it once its router is up (it then links as a client)",
                    manager,
                    ", ".join(router),
                )
                self.session = session("router")

    def exposed(self) -> list[str]:
        """The endpoints the manager listens on beyond this host without TLS, or the routers it
        sits behind there (anyone who reaches them reaches the manager)."""
        return [e for e in [*self.session.endpoints(), *self.routers] if not e.startswith("tls/") and not _loopback(e)]


def _loopback(endpoint: str) -> bool:
    return is_loopback(endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]"))
