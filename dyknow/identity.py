"""Who is calling: every service call signed by its caller and checked by the manager, end to end.

Zenoh's access control (:mod:`dyknow.access`) judges each message by the certificate of the link
it came by, that is by the *neighbour*: a call that a client makes through a router, or through
another manager it is connected to, reaches a manager with the router's or that manager's
certificate, and would get that neighbour's rights. So a manager with roles (``--acl``) also
checks each call itself: the caller signs it with the key of its TLS certificate, and the manager
verifies the certificate against its CA, the signature, the time and that the call is not a
replay, then looks up the role of the certificate's common name in its own ACL. A call keeps its
caller's rights whatever carries it, and only those.

**The signed call, version 1.** A call is a Zenoh query on a service key ``KEY`` with a JSON
payload ``PAYLOAD``; its attachment is::

    offset  size      field
    0       4         magic, the bytes "DKC1"
    4       8         time_ns: the caller's wall clock, nanoseconds since the Unix epoch (big-endian, unsigned)
    12      16        nonce: random bytes, never used twice
    28      2         n: the length of CERT (big-endian, 1 <= n <= 4096)
    30      n         CERT: the caller's X.509 certificate, DER
    30+n    2         m: the length of SIG (big-endian, 1 <= m <= 1024)
    32+n    m         SIG: the signature (see below)

nothing after it. SIG signs the bytes::

    b"dyknow-call-v1\\n" + KEY (UTF-8) + b"\\n" + time_ns (8 bytes, big-endian) + nonce + SHA-256(PAYLOAD)

with the certificate's key: ECDSA with SHA-256 (DER-encoded signature) for an EC key, RSA
PKCS #1 v1.5 with SHA-256 for an RSA key, Ed25519 for an Ed25519 key. The manager accepts the
call when CERT is signed by its CA and valid now (and, if it lists extended key usages, allows
client authentication), SIG verifies, ``time_ns`` is within :data:`WINDOW_S` of the manager's
own clock, the certificate's common name has a role that may make the call, and the nonce was
not seen within that window. The signature covers the key, so a call signed for one manager or
service is refused by any other.

**No replay within the window, whatever the flood.** Nothing is remembered of a call before its
caller's role is known to allow it, so callers without a role cost nothing. Each caller (common
name) has a ledger of its own: the nonces of its calls still within the window, in two parts.

- Calls signed *on time*, at or before the manager's clock when they arrive: at most
  :data:`NONCE_BUDGET` of them. When they are that many, the oldest call (by ``time_ns``) makes
  room and the ledger's *floor* rises to that call's time: from then on a call of this caller
  signed at or before the floor is refused. So a nonce is only ever forgotten together with
  every call as old as it; and since only calls signed at or before the manager's clock are
  ever forgotten early, the floor never rises past that clock.
- Calls signed *ahead* of the manager's clock (a clock running ahead, or a forged time): at most
  :data:`AHEAD_BUDGET` of them, each kept until it leaves the window, never forgotten earlier,
  so they never raise the floor. When they are that many, a further call signed ahead is
  refused, naming how far ahead it was signed; calls signed on time are not.

So a recorded call replayed later is refused either as seen, as older than the floor, or as
outside the window, however many calls (anyone's, or the same caller's) came between. A caller
that makes more than :data:`NONCE_BUDGET` calls in :data:`WINDOW_S` only has its own calls that
arrive later than that many newer ones refused. Calls signed ahead, by a clock or by anyone
holding the same certificate, never make a call signed on time refused: they never raise the
floor, and only calls signed ahead wait for room among them.
"""

from __future__ import annotations

import datetime
import hashlib
import heapq
import os
import struct
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, padding, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dyknow.access import AccessControl, TlsFiles
from dyknow.errors import AccessError
from dyknow.security import Limits

__all__ = [
    "AHEAD_BUDGET",
    "MAGIC",
    "MAX_CERT_BYTES",
    "MAX_SIGNATURE_BYTES",
    "NONCE_BUDGET",
    "WINDOW_S",
    "Caller",
    "Signer",
    "Verifier",
    "signed_bytes",
]

#: The first four bytes of a signed call's attachment.
MAGIC = b"DKC1"
#: How far a call's time may be from the manager's clock, either way (seconds): hosts must agree
#: on the time this closely (chrony or NTP keeps them far closer).
WINDOW_S = 300.0
#: The largest certificate and signature a call may carry.
MAX_CERT_BYTES = 4096
MAX_SIGNATURE_BYTES = 1024

_DOMAIN = b"dyknow-call-v1\n"
_HEAD = struct.Struct(">4sQ16sH")
#: The calls signed on time a manager remembers per caller within the window (see the module
#: documentation; ``Limits.max_caller_calls``): about 70 calls a second, sustained over the whole
#: window, before the caller's floor rises.
NONCE_BUDGET = Limits().max_caller_calls
#: The calls signed ahead of the manager's clock it remembers per caller (``Limits.max_caller_calls_ahead``).
AHEAD_BUDGET = Limits().max_caller_calls_ahead
_CERTS = 256  # verified certificates remembered


def signed_bytes(key: str, time_ns: int, nonce: bytes, payload: bytes) -> bytes:
    """What a caller signs for a call of ``payload`` on ``key`` (see the module documentation)."""
    return _DOMAIN + key.encode() + b"\n" + time_ns.to_bytes(8, "big") + nonce + hashlib.sha256(payload).digest()


@dataclass(frozen=True, slots=True)
class Caller:
    """Who made a call, as the manager established it: the certificate's common name and the
    role this manager's ACL gives it (None: none)."""

    common_name: str
    role: str | None


def _common_name(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    value = names[0].value if names else ""
    return value if isinstance(value, str) else value.decode(errors="replace")


class Signer:
    """Signs calls with the certificate and key of a :class:`~dyknow.access.TlsFiles`.

    :class:`AccessError` naming the file when the certificate or key cannot be read, the key is
    of a kind no call can be signed with, or the key is not the certificate's.
    """

    def __init__(self, tls: TlsFiles) -> None:
        try:
            cert = x509.load_pem_x509_certificate(Path(tls.cert).read_bytes())
        except (OSError, ValueError) as exc:
            raise AccessError(f"cannot read the certificate: {exc}", where=f"--tls-cert {tls.cert}", expected="a PEM certificate") from exc
        try:
            key = serialization.load_pem_private_key(Path(tls.key).read_bytes(), password=None)
        except (OSError, ValueError, TypeError, UnsupportedAlgorithm) as exc:
            raise AccessError(
                f"cannot read the private key: {exc}", where=f"--tls-key {tls.key}", expected="an unencrypted PEM private key"
            ) from exc
        if not isinstance(key, ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey | ed25519.Ed25519PrivateKey):
            raise AccessError(
                f"a {type(key).__name__} cannot sign calls", where=f"--tls-key {tls.key}", expected="an EC, RSA or Ed25519 key"
            )
        mine = key.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
        theirs = cert.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
        if mine != theirs:
            raise AccessError(
                f"the key in {tls.key} is not the key of the certificate {tls.cert}",
                where="--tls-key",
                expected="the private key the certificate was issued for",
            )
        self._key = key
        self._der = cert.public_bytes(serialization.Encoding.DER)
        if len(self._der) > MAX_CERT_BYTES:
            raise AccessError(f"a certificate of {len(self._der)} bytes", where=f"--tls-cert {tls.cert}", expected=f"at most {MAX_CERT_BYTES}")
        self.common_name = _common_name(cert)

    def sign(self, key: str, payload: bytes, *, time_ns: int | None = None, nonce: bytes | None = None) -> bytes:
        """The attachment that signs a call of ``payload`` on ``key`` (now, with a fresh nonce)."""
        when = time.time_ns() if time_ns is None else time_ns
        once = os.urandom(16) if nonce is None else nonce
        data = signed_bytes(key, when, once, payload)
        private = self._key
        if isinstance(private, ec.EllipticCurvePrivateKey):
            signature = private.sign(data, ec.ECDSA(hashes.SHA256()))
        elif isinstance(private, rsa.RSAPrivateKey):
            signature = private.sign(data, padding.PKCS1v15(), hashes.SHA256())
        else:
            signature = private.sign(data)
        return _HEAD.pack(MAGIC, when, once, len(self._der)) + self._der + struct.pack(">H", len(signature)) + signature


@dataclass(slots=True)
class _Ledger:
    """One caller's calls within the window: nonce -> time, the times of those signed on time and
    of those signed ahead in a heap each, and the floor."""

    seen: dict[bytes, int] = field(default_factory=dict)
    times: list[tuple[int, bytes]] = field(default_factory=list)  # signed at or before the clock when they came
    ahead: list[tuple[int, bytes]] = field(default_factory=list)  # signed after it: kept until they leave the window
    floor_ns: int = -1  # calls signed at or before it are refused (their nonces may be forgotten)


class Verifier:
    """Checks signed calls for one manager: its CA, its ACL's roles.

    :meth:`verify` returns the :class:`Caller` or raises :class:`AccessError` saying what is wrong
    with the call. Thread-safe (the manager's service threads call it side by side).
    ``budget``: the calls signed on time remembered per caller within the window
    (:data:`NONCE_BUDGET`); ``ahead_budget``: those signed ahead of the clock (:data:`AHEAD_BUDGET`).
    """

    def __init__(
        self,
        ca: str | os.PathLike[str],
        access: AccessControl,
        *,
        window_s: float = WINDOW_S,
        budget: int = NONCE_BUDGET,
        ahead_budget: int = AHEAD_BUDGET,
    ) -> None:
        try:
            self._ca = x509.load_pem_x509_certificate(Path(ca).read_bytes())
        except (OSError, ValueError) as exc:
            raise AccessError(f"cannot read the CA certificate: {exc}", where=f"--tls-ca {os.fspath(ca)}", expected="a PEM certificate") from exc
        self._access = access
        self._window_ns = int(window_s * 1e9)
        self._budget = max(1, budget)
        self._ahead_budget = max(1, ahead_budget)
        self._lock = threading.Lock()
        self._certs: OrderedDict[bytes, tuple[str, datetime.datetime, datetime.datetime]] = OrderedDict()
        self._ledgers: dict[str, _Ledger] = {}

    def verify(
        self,
        key: str,
        payload: bytes,
        attachment: bytes | None,
        *,
        now_ns: int | None = None,
        allowed: Callable[[Caller], None] | None = None,
    ) -> Caller:
        """The caller of a call of ``payload`` on ``key`` with ``attachment``; :class:`AccessError` when it cannot be trusted.

        ``allowed(caller)`` raises when the caller's role may not make this call: it runs before
        anything of the call is remembered (a caller without a role is never remembered either).
        """
        if not attachment:
            raise AccessError(
                "the call is not signed, and this manager checks every caller's identity (it runs with --acl)",
                where="call",
                expected="a dyknow client given --tls-ca, --tls-cert and --tls-key (its certificate's common name needs a role)",
            )
        when, nonce, der, signature = _parse(attachment)
        now = time.time_ns() if now_ns is None else now_ns
        if abs(now - when) > self._window_ns:
            raise AccessError(
                f"the call was signed {(when - now) / 1e9:+.1f} s from this manager's clock",
                where="call",
                expected=f"within {self._window_ns / 1e9:g} s: synchronise the hosts' clocks (chrony or NTP)",
            )
        name, cert = self._certificate(der, now)
        try:
            _verify_signature(cert.public_key(), signature, signed_bytes(key, when, nonce, payload))
        except InvalidSignature:
            raise AccessError(
                f"the signature of the call does not verify with the certificate of {name!r}", where="call",
                expected="a call signed with the key of the certificate it carries",
            ) from None  # fmt: skip
        caller = Caller(name, self._access.role_of(name))
        if allowed is not None:
            allowed(caller)
        if caller.role is not None:
            with self._lock:
                self._remember(name, nonce, when, now)
        return caller

    def remembered(self) -> dict[str, int]:
        """How many calls are remembered, per caller (common name)."""
        with self._lock:
            return {name: len(ledger.seen) for name, ledger in self._ledgers.items()}

    def _certificate(self, der: bytes, now_ns: int) -> tuple[str, x509.Certificate]:
        digest = hashlib.sha256(der).digest()
        now = datetime.datetime.fromtimestamp(now_ns / 1e9, tz=datetime.UTC)
        try:
            cert = x509.load_der_x509_certificate(der)
        except ValueError as exc:
            raise AccessError(f"the call carries no readable certificate: {exc}", where="call") from None
        with self._lock:
            known = self._certs.get(digest)
            if known is not None:
                self._certs.move_to_end(digest)
        if known is None:
            try:
                cert.verify_directly_issued_by(self._ca)
            except (ValueError, TypeError, InvalidSignature, UnsupportedAlgorithm):
                raise AccessError(
                    f"the certificate of {_common_name(cert)!r} is not signed by this manager's CA",
                    where="call",
                    expected="a certificate issued by the CA the manager was given (--tls-ca)",
                ) from None
            try:
                usages = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
            except x509.ExtensionNotFound:
                usages = None
            if usages is not None and ExtendedKeyUsageOID.CLIENT_AUTH not in usages:
                raise AccessError(
                    f"the certificate of {_common_name(cert)!r} is not for clients", where="call",
                    expected="a certificate whose extended key usage includes client authentication",
                )  # fmt: skip
            known = (_common_name(cert), cert.not_valid_before_utc, cert.not_valid_after_utc)
            with self._lock:
                self._certs[digest] = known
                while len(self._certs) > _CERTS:
                    self._certs.popitem(last=False)
        name, not_before, not_after = known
        if not not_before <= now <= not_after:
            raise AccessError(
                f"the certificate of {name!r} is valid from {not_before:%Y-%m-%d %H:%M} to {not_after:%Y-%m-%d %H:%M} UTC, not now",
                where="call",
                expected="a certificate valid now",
            )
        return name, cert

    def _remember(self, name: str, nonce: bytes, when: int, now: int) -> None:
        """Note the call in its caller's ledger, or raise when it is a replay (under the lock)."""
        ledger = self._ledgers.get(name)
        if ledger is None:
            ledger = self._ledgers[name] = _Ledger()
        if nonce in ledger.seen:
            raise AccessError("the call is a replay of one already received", where="call", expected="a new call (a fresh nonce)")
        if when <= ledger.floor_ns:
            raise AccessError(
                f"the call was signed before the {self._budget:,} most recent calls of {name!r} that this manager remembers: "
                "it is a replay, or it arrived too late",
                where="call",
                expected=f"a new call; a caller making over {self._budget:,} calls in {self._window_ns / 1e9:g} s sees its late calls refused",
            )
        times, ahead = ledger.times, ledger.ahead
        for heap in (times, ahead):
            while heap and heap[0][0] < now - self._window_ns:  # outside the window: refused by their time anyway
                expired, forgotten = heapq.heappop(heap)
                ledger.seen.pop(forgotten, None)
                ledger.floor_ns = max(ledger.floor_ns, expired)  # (and should the clock step back)
        if when > now:  # signed ahead: never forgotten before it leaves the window, so it never raises the floor
            if len(ahead) >= self._ahead_budget:
                raise AccessError(
                    f"the call was signed {(when - now) / 1e9:+.3f} s ahead of this manager's clock, and the manager already "
                    f"remembers {len(ahead):,} calls of {name!r} signed ahead of it, each until it leaves the {self._window_ns / 1e9:g} s window",
                    where="call",
                    expected=f"a call signed at or before the manager's clock (of those signed ahead, at most {self._ahead_budget:,} "
                    "are taken): synchronise the hosts' clocks (chrony or NTP), and give each client a certificate of its own",
                )
            ledger.seen[nonce] = when
            heapq.heappush(ahead, (when, nonce))
            return
        while len(times) >= self._budget:  # (each signed at or before the clock when it came: the floor stays behind it)
            oldest, forgotten = heapq.heappop(times)
            ledger.seen.pop(forgotten, None)
            ledger.floor_ns = max(ledger.floor_ns, oldest)
        if when <= ledger.floor_ns:  # (it was the oldest itself)
            raise AccessError(
                f"the call was signed before the {self._budget:,} most recent calls of {name!r} that this manager remembers",
                where="call",
                expected="a new call",
            )
        ledger.seen[nonce] = when
        heapq.heappush(times, (when, nonce))


def _parse(attachment: bytes) -> tuple[int, bytes, bytes, bytes]:
    def bad(why: str) -> AccessError:
        return AccessError(f"the call's signature is malformed: {why}", where="call", expected="a call signed as dyknow.identity describes")

    if len(attachment) < _HEAD.size + 2:
        raise bad(f"{len(attachment)} bytes")
    magic, when, nonce, n = _HEAD.unpack_from(attachment)
    if magic != MAGIC:
        raise bad("it does not start with DKC1")
    if not 1 <= n <= MAX_CERT_BYTES or len(attachment) < _HEAD.size + n + 2:
        raise bad(f"a certificate of {n} bytes")
    der = attachment[_HEAD.size : _HEAD.size + n]
    (m,) = struct.unpack_from(">H", attachment, _HEAD.size + n)
    start = _HEAD.size + n + 2
    if not 1 <= m <= MAX_SIGNATURE_BYTES or len(attachment) != start + m:
        raise bad(f"a signature of {m} bytes in an attachment of {len(attachment)}")
    return when, nonce, der, attachment[start:]


def _verify_signature(public: object, signature: bytes, data: bytes) -> None:
    if isinstance(public, ec.EllipticCurvePublicKey):
        public.verify(signature, data, ec.ECDSA(hashes.SHA256()))
    elif isinstance(public, rsa.RSAPublicKey):
        public.verify(signature, data, padding.PKCS1v15(), hashes.SHA256())
    elif isinstance(public, ed25519.Ed25519PublicKey):
        public.verify(signature, data)
    else:
        raise InvalidSignature
