"""Zenoh, behind a small surface. The only package of dyknow that imports ``zenoh``.

The default session is a Zenoh *peer* that talks over loopback only: multicast scouting is off,
it listens on ``tcp/127.0.0.1`` (a given port, or any free one) and connects to the endpoints it is
given. Gossip scouting stays on so that peers which connect to a manager also find each other and
exchange data directly. A manager's session is a Zenoh *router* (``mode="router"``): routers route
for each other over any path, so two managers that cannot link directly still reach each other
through a third one or a ``dyknow router``, where peers see only the peers they link to. A Zenoh
configuration file (json5) replaces these defaults to join a real deployment.

A session bounds how long its dead links hold it up (the kernel drops a link whose data goes
unacknowledged for a lease), dials a lost link again within a second, ends a dial under way when
it closes, and is closed before the interpreter's threads end at exit. A call that ends without
an answer says why, as far as it can be told: the link closed, the service's owner went, or the
request was dropped on its way (an access control).

Entities mirror Zenoh's: ``declare_*`` returns an object with ``undeclare()`` (safe twice) that is
also a context manager. Zenoh errors are wrapped in :class:`~dyknow.errors.TransportError` with the
Rust source location trimmed off.

==========================  ==============================================================================
module                      what it holds
==========================  ==============================================================================
:mod:`~.session`            :class:`Session` (and :func:`open_session`): declarations, liveliness, calls
:mod:`~.entities`           what a session declares: :class:`Publisher`, :class:`Subscriber`, :class:`Queryable`,
                            :class:`ServiceChannel`, :class:`LivelinessToken`, ...
:mod:`~.calls`              a session's service calls: its queriers, and why a call got no answer
:mod:`~.config`             :func:`make_config`: endpoints and their schemes, modes, TLS and access control
:mod:`~.links`              dead links bounded by the lease, dials under way ended (:func:`abort_dials`),
                            links to other routers as they come and go (:class:`RouterLinks`)
:mod:`~.key_exprs`          key expressions: :func:`check_key_expr`, :func:`is_wild`, :func:`key_exprs_intersect`
:mod:`~.shared_memory`      Zenoh shared memory for large payloads
:mod:`~.runtime`            Zenoh's threads (:data:`ZENOH_RUNTIME`), callbacks on them, its errors in words
==========================  ==============================================================================

Imports flow one way: ``runtime <- key_exprs, shared_memory, links, config <- entities, calls <- session``.
"""

from __future__ import annotations

from dyknow.transport.calls import MAX_QUERIERS
from dyknow.transport.config import DEFAULT_ENDPOINT, SCHEMES, check_schemes, make_config
from dyknow.transport.config import ROUTER_MAX_SESSIONS as ROUTER_MAX_SESSIONS
from dyknow.transport.entities import (
    LivelinessSubscriber,
    LivelinessToken,
    PlainPublisher,
    Publisher,
    Queryable,
    ServiceChannel,
    ServiceRequest,
    Subscriber,
)
from dyknow.transport.key_exprs import check_key_expr, is_wild, key_exprs_intersect
from dyknow.transport.links import RouterLink as RouterLink
from dyknow.transport.links import RouterLinks as RouterLinks
from dyknow.transport.links import abort_dials as abort_dials
from dyknow.transport.links import bound_unacknowledged as bound_unacknowledged
from dyknow.transport.runtime import ZENOH_RUNTIME
from dyknow.transport.session import MAX_ALIVE_KEYS as MAX_ALIVE_KEYS
from dyknow.transport.session import Session
from dyknow.transport.session import open_session as open_session
from dyknow.transport.shared_memory import SHM_POOL_BYTES as SHM_POOL_BYTES
from dyknow.transport.shared_memory import SHM_THRESHOLD as SHM_THRESHOLD
from dyknow.transport.shared_memory import shared_memory_problem

# (the names imported "as" themselves are imported from here too, by the doctor, the command
# line, the benchmarks and the tests, though not part of __all__)
__all__ = [
    "DEFAULT_ENDPOINT",
    "MAX_QUERIERS",
    "SCHEMES",
    "ZENOH_RUNTIME",
    "LivelinessSubscriber",
    "LivelinessToken",
    "PlainPublisher",
    "Publisher",
    "Queryable",
    "ServiceChannel",
    "ServiceRequest",
    "Session",
    "Subscriber",
    "check_key_expr",
    "check_schemes",
    "is_wild",
    "key_exprs_intersect",
    "make_config",
    "shared_memory_problem",
]
