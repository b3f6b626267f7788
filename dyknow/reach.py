"""Why a client cannot reach a manager: each endpoint probed, and the failures told apart.

Zenoh says only that it could not connect. When a client's session has no link, the client asks
:func:`probe` about each ``--connect`` endpoint, with plain sockets and Python's TLS (no Zenoh):

- ``refused``: nothing listens on that port (the TCP connection was refused at once);
- ``unreachable``: no route to the host (the network said so at once);
- ``silent``: the host did not answer a TCP connection within the probe's time (down, cut off, or
  a firewall drops the packets): known only when that time has passed;
- ``tls-listener``: a ``tcp/`` endpoint whose listener speaks TLS (use ``tls/``);
- ``tls-untrusted``: the listener's certificate is not signed by this client's CA (``--tls-ca``),
  is not valid for the address connected to, or has expired;
- ``tls-rejected``: the listener refused this client's certificate (another CA, or none);
- ``ok``: TCP (and TLS) went through: the failure is elsewhere (a role, a manager's name);
- ``no-session``: TCP (and TLS) went through, but Zenoh did not open a session there (a router
  at its ``--max-sessions``): told by the client, which tried (:func:`no_session`).

:func:`check_endpoints` refuses at once what cannot work whatever runs there: a ``tls/``
endpoint without TLS files. Every finding names the option to change.
"""

from __future__ import annotations

import errno
import logging
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

from dyknow.access import TlsFiles
from dyknow.errors import AccessError, TransportError

if TYPE_CHECKING:
    import ssl

log = logging.getLogger(__name__)
T = TypeVar("T")

__all__ = ["DEFINITE", "Finding", "answering", "check_endpoints", "dial", "no_session", "open_patiently", "probe", "probe_all"]

#: The kinds of finding that fail a call at once: nothing listens now, no route, TLS refused either
#: way (waiting would not help; a manager that starts there later is reached by the next call).
DEFINITE: frozenset[str] = frozenset({"refused", "unreachable", "tls-listener", "tls-untrusted", "tls-rejected"})
_ALERT_WAIT_S = 0.5  # how long the probe waits, after its TLS handshake, for the listener to refuse its certificate
_TLS_OPTIONS = "--tls-ca, --tls-cert and --tls-key (TlsFiles)"
_REFUSED_AT_ONCE_S = 1.0  # a session refused sooner than this was refused, not timed out (open_patiently)


@dataclass(frozen=True, slots=True)
class Finding:
    """What a probe of one endpoint found: ``kind`` (see the module documentation), ``what`` went
    wrong and what was ``expected`` (the option or file to change)."""

    endpoint: str
    kind: str
    what: str = ""
    expected: str = ""

    @property
    def definite(self) -> bool:
        """Whether waiting would not help: the call fails at once (see :data:`DEFINITE`)."""
        return self.kind in DEFINITE


def no_session(endpoint: str) -> Finding:
    """The finding for an endpoint that accepted the connection (TCP, and TLS when probed) but
    where Zenoh did not open a session with this client: not definite (a router makes room as
    sessions end)."""
    return Finding(
        endpoint,
        "no-session",
        f"{endpoint} accepts connections, but Zenoh did not open a session with this client there "
        "(a router at its --max-sessions refuses more sessions)",
        "a router with room for this client (dyknow router --max-sessions N; 10,000 by default), or another --connect endpoint",
    )


def _split(endpoint: str) -> tuple[str, str, int] | None:
    """``(protocol, host, port)`` of ``tcp/HOST:PORT`` or ``tls/HOST:PORT`` (``[v6]`` too), else None."""
    proto, sep, rest = endpoint.partition("/")
    rest = rest.split("#", 1)[0].split("?", 1)[0]
    host, colon, port = rest.rpartition(":")
    if not sep or not colon or not port.isdigit() or not host:
        return None
    return proto, host.strip("[]"), int(port)


def check_endpoints(endpoints: Sequence[str], tls: TlsFiles | None, *, option: str = "--connect", who: str = "this client") -> None:
    """Refuse what cannot work whatever runs there: a ``tls/`` endpoint without TLS files
    (:class:`AccessError`, as for the other TLS options, naming them; ``option`` and ``who`` say
    whose endpoints)."""
    if tls is None:
        bare = [e for e in endpoints if e.startswith("tls/")]
        if bare:
            raise AccessError(
                f"{', '.join(bare)} is a TLS endpoint, and {who} has no TLS files",
                where=option,
                expected=f"{_TLS_OPTIONS} with a tls/ endpoint (or tcp/ without TLS)",
            )


def _connect(endpoint: str, timeout_s: float) -> socket.socket | Finding:
    """A TCP connection to ``endpoint`` (``tcp/`` or ``tls/``), or the finding of why there is none."""
    parts = _split(endpoint)
    if parts is None or parts[0] not in ("tcp", "tls"):
        return Finding(endpoint, "unknown")
    _, host, port = parts
    try:
        return socket.create_connection((host, port), timeout=timeout_s)
    except ConnectionRefusedError:
        return Finding(
            endpoint,
            "refused",
            f"the connection to {endpoint} was refused: nothing listens on port {port} of {host}",
            "the endpoint a manager listens on (its --listen) in --connect, and that manager running",
        )
    except TimeoutError:
        return Finding(
            endpoint,
            "silent",
            f"{host} did not answer a connection to port {port} within {timeout_s:g} s: it is down, cut off, or a firewall drops the packets",
            "a host this machine reaches (--connect), or a longer --timeout on a slow link",
        )
    except OSError as exc:
        if exc.errno in (errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EADDRNOTAVAIL) or isinstance(exc, socket.gaierror):
            return Finding(
                endpoint,
                "unreachable",
                f"{host} cannot be reached from here ({exc.strerror or exc})",
                "an address of the manager's host on a network this machine is on (--connect)",
            )
        return Finding(endpoint, "unknown", f"{endpoint}: {exc.strerror or exc}")


def probe(endpoint: str, tls: TlsFiles | None, timeout_s: float = 1.0) -> Finding:
    """Probe one endpoint (see the module documentation); never raises."""
    sock = _connect(endpoint, timeout_s)
    if isinstance(sock, Finding):
        return sock
    parts = _split(endpoint)
    assert parts is not None
    proto, host, _ = parts
    with sock:
        if proto == "tcp":
            return _plain(endpoint, sock, host, min(timeout_s, 1.0))
        if tls is None:  # (check_endpoints refuses this before any probe)
            return Finding(endpoint, "ok")
        return _tls(endpoint, sock, host, tls, min(timeout_s, 1.0))


def _plain(endpoint: str, sock: socket.socket, host: str, timeout_s: float) -> Finding:
    """A ``tcp/`` endpoint: does its listener speak TLS? (a plain Zenoh listener waits for more
    bytes after a TLS greeting, so the handshake times out)."""
    import ssl  # (here and in _tls: a probe that finds nothing listening never needs it, and the command starts faster)

    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    sock.settimeout(timeout_s)
    try:
        with context.wrap_socket(sock, server_hostname=host):
            pass
    except ssl.SSLError as exc:
        if "ALERT" not in (exc.reason or ""):
            return Finding(endpoint, "ok")
    except OSError:
        return Finding(endpoint, "ok")
    tls_endpoint = "tls/" + endpoint.partition("/")[2]
    return Finding(
        endpoint,
        "tls-listener",
        f"the listener at {endpoint} speaks TLS, and tcp/ connects without it",
        f"--connect {tls_endpoint}, with {_TLS_OPTIONS}",
    )


def _tls(endpoint: str, sock: socket.socket, host: str, tls: TlsFiles, timeout_s: float) -> Finding:
    """A ``tls/`` endpoint: the handshake as Zenoh makes it (mutual, the name verified), then a
    short wait for the listener to refuse this client's certificate."""
    import ssl

    try:
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        context.load_verify_locations(tls.ca)
        context.load_cert_chain(tls.cert, tls.key)
    except (OSError, ssl.SSLError) as exc:  # (TlsFiles.check refuses these first)
        return Finding(endpoint, "unknown", f"cannot load the TLS files: {exc}")
    sock.settimeout(timeout_s)
    try:
        conn = context.wrap_socket(sock, server_hostname=host)
    except ssl.SSLCertVerificationError as exc:
        message = exc.verify_message or str(exc)
        if exc.verify_code in (62, 64) or "mismatch" in message:
            return Finding(
                endpoint,
                "tls-untrusted",
                f"the certificate of the listener at {endpoint} is not valid for {host!r} ({message})",
                f"certificates made for the address clients connect to (dyknow certs DIR --names ... --hosts ...,{host}), "
                "or --connect with a name the certificate holds",
            )
        if exc.verify_code == 10 or "expired" in message:
            return Finding(
                endpoint, "tls-untrusted", f"the certificate of the listener at {endpoint} has expired", "a new certificate for the manager"
            )
        return Finding(
            endpoint,
            "tls-untrusted",
            f"the certificate of the listener at {endpoint} is not signed by the CA of --tls-ca {tls.ca} ({message})",
            "--tls-ca the CA file of the manager's deployment (the one that signed its certificate)",
        )
    except ssl.SSLError as exc:
        return _refused_certificate(endpoint, exc, tls)
    except OSError as exc:
        return Finding(endpoint, "unknown", f"TLS handshake with {endpoint}: {exc.strerror or exc}")
    with conn:
        conn.settimeout(_ALERT_WAIT_S)
        try:
            conn.recv(1)  # with TLS 1.3 the listener judges the client's certificate after the handshake
        except ssl.SSLError as exc:
            return _refused_certificate(endpoint, exc, tls)
        except OSError:
            pass
    return Finding(endpoint, "ok")


def _refused_certificate(endpoint: str, exc: ssl.SSLError, tls: TlsFiles) -> Finding:
    reason = (exc.reason or str(exc)).lower().replace("_", " ")
    if "alert" not in reason:
        return Finding(endpoint, "unknown", f"TLS with {endpoint}: {exc}")
    if "certificate required" in reason:
        why = "it asked for a certificate"
    elif "expired" in reason:
        why = "the certificate has expired"
    else:  # unknown ca, bad certificate, decrypt error (a CA of the same name, another key)
        why = "it is not signed by the CA the manager trusts"
    return Finding(
        endpoint,
        "tls-rejected",
        f"the listener at {endpoint} refused this client's certificate --tls-cert {tls.cert} ({reason.split('alert', 1)[-1].strip()}): {why}",
        "a certificate signed by the manager's CA (the --tls-ca it runs with), with its key",
    )


def dial(endpoints: Sequence[str], timeout_s: float = 1.0) -> list[Finding]:
    """A TCP connection to each of ``endpoints`` (``tcp/`` or ``tls/``), side by side: a finding
    each, ``ok`` for one that accepted (its TLS not looked at) and the connection's own failure
    otherwise (``refused``, ``unreachable``, ``silent`` after ``timeout_s``). Returns as soon as
    one accepts (the others then ``unknown``), or once all have failed; endpoints of other
    protocols count as accepting (they are not probed)."""
    found: list[Finding | None] = [None] * len(endpoints)
    lock = threading.Lock()
    settled = threading.Condition(lock)

    def run(i: int, endpoint: str) -> None:
        parts = _split(endpoint)
        if parts is None or parts[0] not in ("tcp", "tls"):
            result: Finding = Finding(endpoint, "ok")
        else:
            sock = _connect(endpoint, timeout_s)
            if not isinstance(sock, Finding):
                sock.close()
                sock = Finding(endpoint, "ok")
            result = sock
        with settled:
            found[i] = result
            settled.notify_all()

    for i, endpoint in enumerate(endpoints):
        threading.Thread(target=run, args=(i, endpoint), name="dyknow-probe", daemon=True).start()
    with settled:
        settled.wait_for(
            lambda: all(f is not None for f in found) or any(f is not None and f.kind == "ok" for f in found), timeout_s + 1.0
        )
        return [f if f is not None else Finding(e, "unknown") for f, e in zip(found, endpoints, strict=True)]


def answering(endpoints: Sequence[str], timeout_s: float = 1.0) -> bool:
    """Whether a TCP connection to any of ``endpoints`` is accepted within ``timeout_s`` (see :func:`dial`)."""
    return any(f.kind == "ok" for f in dial(endpoints, timeout_s))


def open_patiently(open_client: Callable[[], T], endpoints: Sequence[str], *, patience_s: float, who: str) -> T | None:
    """``open_client()`` (a Zenoh client session of ``endpoints``), or None when none of them
    takes it. Zenoh says only "Unable to connect". An endpoint that accepts the connection but
    lets the session's handshake run out of time is busy (a fleet starting at once: 137 of 1,000
    managers gave up at their first try, and every one that then joined as a Zenoh router loaded
    the router with the fleet's declarations): tried again every second for up to
    ``patience_s``. Nothing listening, or a refusal that comes at once (a router full at its
    ``--max-sessions``, TLS), is not waited for. Other errors are raised."""
    deadline = time.monotonic() + patience_s
    while True:
        tried = time.monotonic()
        try:
            return open_client()
        except TransportError as exc:
            if "Unable to connect" not in str(exc):
                raise
        busy = time.monotonic() - tried >= _REFUSED_AT_ONCE_S and answering(endpoints, timeout_s=1.0)
        if not busy or time.monotonic() + 1.0 >= deadline:
            return None
        log.info("%s: %s took the connection but not the session in time (busy): trying again in 1 s", who, ", ".join(endpoints))
        threading.Event().wait(1.0)  # (time.sleep fails under a faked clock: libfaketime's clock_nanosleep)


def probe_all(endpoints: Sequence[str], tls: TlsFiles | None, timeout_s: float = 1.0) -> list[Finding]:
    """:func:`probe` of every endpoint, side by side (the slowest bounds the time)."""
    found: list[Finding | None] = [None] * len(endpoints)

    def run(i: int, endpoint: str) -> None:
        found[i] = probe(endpoint, tls, timeout_s)

    threads = [threading.Thread(target=run, args=(i, e), name="dyknow-probe", daemon=True) for i, e in enumerate(endpoints)]
    deadline = time.monotonic() + timeout_s + 2 * _ALERT_WAIT_S + 1.0
    for t in threads:
        t.start()
    for t in threads:
        t.join(max(0.0, deadline - time.monotonic()))
    return [f if f is not None else Finding(e, "unknown") for f, e in zip(found, endpoints, strict=True)]
