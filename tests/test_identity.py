"""Signed calls (dyknow.identity): the wire format against OpenSSL and a parser written from the
module's documentation, and every way a call is refused."""

from __future__ import annotations

import datetime
import hashlib
import shutil
import struct
import subprocess
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dyknow import AccessError
from dyknow.access import AccessControl, TlsFiles
from dyknow.certs import write_dev_certs
from dyknow.identity import WINDOW_S, Caller, Signer, Verifier
from tests.conftest import apt_install

KEY = "@dyknow/station/spawn"
PAYLOAD = b'{"label": "relay", "name": "r"}'
ACL = AccessControl.from_dict({"roles": {"viewer": ["viewer"], "admin": ["alice"], "manager": ["robot"]}})


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("certs")
    write_dev_certs(folder, ["alice", "viewer", "robot", "stranger"])
    return folder


def tls(certs: Path, name: str) -> TlsFiles:
    return TlsFiles(str(certs / "ca.pem"), str(certs / f"{name}.pem"), str(certs / f"{name}.key"))


def issue(certs: Path, name: str, key: object, *, days: tuple[int, int] = (-1, 30), client: bool = True) -> TlsFiles:
    """A certificate for ``key`` signed by the development CA in ``certs`` (other key kinds,
    other validity periods, other usages than ``dyknow certs`` writes)."""
    ca_key = serialization.load_pem_private_key((certs / "ca.key").read_bytes(), password=None)
    ca = x509.load_pem_x509_certificate((certs / "ca.pem").read_bytes())
    now = datetime.datetime.now(datetime.UTC)
    usage = [ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH] if client else [ExtendedKeyUsageOID.SERVER_AUTH]
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca.subject)
        .public_key(key.public_key())  # type: ignore[attr-defined]
        .serial_number(x509.random_serial_number())
        .not_valid_before(now + datetime.timedelta(days=days[0]))
        .not_valid_after(now + datetime.timedelta(days=days[1]))
        .add_extension(x509.ExtendedKeyUsage(usage), critical=False)
        .sign(ca_key, hashes.SHA256())  # type: ignore[arg-type]
    )
    stem = certs / f"{name}-{type(key).__name__}-{days[0]}-{client}"
    stem.with_suffix(".pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    stem.with_suffix(".key").write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())  # type: ignore[attr-defined]
    )
    return TlsFiles(str(certs / "ca.pem"), str(stem.with_suffix(".pem")), str(stem.with_suffix(".key")))


def parse(attachment: bytes) -> dict[str, object]:
    """The attachment taken apart as the module's documentation lays it out (written from the
    table, not from the module's code)."""
    assert attachment[:4] == b"DKC1"
    time_ns = int.from_bytes(attachment[4:12], "big")
    nonce = attachment[12:28]
    n = int.from_bytes(attachment[28:30], "big")
    cert = attachment[30 : 30 + n]
    m = int.from_bytes(attachment[30 + n : 32 + n], "big")
    sig = attachment[32 + n : 32 + n + m]
    assert len(attachment) == 32 + n + m
    signed = b"dyknow-call-v1\n" + KEY.encode() + b"\n" + struct.pack(">Q", time_ns) + nonce + hashlib.sha256(PAYLOAD).digest()
    return {"time_ns": time_ns, "nonce": nonce, "cert": cert, "sig": sig, "signed": signed}


@pytest.fixture(scope="module")
def openssl() -> str:
    """The openssl command (Debian's package; installed with apt-get when missing and run as root)."""
    found = shutil.which("openssl")
    if found is None:
        apt_install("openssl")
        found = shutil.which("openssl")
    if found is None:
        pytest.fail("openssl is not installed (apt-get install openssl)")
    return found


@pytest.mark.process
@pytest.mark.parametrize("kind", ["ec", "rsa", "ed25519"])
def test_openssl_verifies_what_a_signer_signs(certs: Path, tmp_path: Path, openssl: str, kind: str) -> None:
    """The signature is what the documentation says, over what it says: OpenSSL checks it with the
    public key of the certificate the attachment carries, over bytes built from the table."""
    files = tls(certs, "alice") if kind == "ec" else issue(
        certs, f"alice-{kind}", rsa.generate_private_key(65537, 2048) if kind == "rsa" else ed25519.Ed25519PrivateKey.generate()
    )  # fmt: skip
    before = datetime.datetime.now(datetime.UTC).timestamp()
    parts = parse(Signer(files).sign(KEY, PAYLOAD))
    assert before - 1 <= int(parts["time_ns"]) / 1e9 <= before + 60  # type: ignore[call-overload]
    cert = x509.load_der_x509_certificate(parts["cert"])  # type: ignore[arg-type]
    (tmp_path / "pub.pem").write_bytes(cert.public_key().public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
    (tmp_path / "signed").write_bytes(parts["signed"])  # type: ignore[arg-type]
    (tmp_path / "sig").write_bytes(parts["sig"])  # type: ignore[arg-type]
    if kind == "ed25519":  # pure Ed25519 signs the message itself
        argv = [openssl, "pkeyutl", "-verify", "-pubin", "-inkey", "pub.pem", "-rawin", "-in", "signed", "-sigfile", "sig"]
    else:
        argv = [openssl, "dgst", "-sha256", "-verify", "pub.pem", "-signature", "sig", "signed"]
    result = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 0 and "Verified" in result.stdout + result.stderr, result.stdout + result.stderr
    assert Verifier(files.ca, ACL).verify(KEY, PAYLOAD, Signer(files).sign(KEY, PAYLOAD)).common_name == cert.subject.rfc4514_string()[3:]


def test_a_verified_call_names_its_caller_and_the_role_this_manager_gives_it(certs: Path) -> None:
    verifier = Verifier(str(certs / "ca.pem"), ACL)
    for name, role in [("alice", "admin"), ("viewer", "viewer"), ("robot", "manager"), ("stranger", None)]:
        caller = verifier.verify(KEY, PAYLOAD, Signer(tls(certs, name)).sign(KEY, PAYLOAD))
        assert (caller.common_name, caller.role) == (name, role)


def test_every_kind_of_forged_or_stale_call_is_refused_saying_why(certs: Path, tmp_path: Path) -> None:
    verifier = Verifier(str(certs / "ca.pem"), ACL)
    alice = Signer(tls(certs, "alice"))
    good = alice.sign(KEY, PAYLOAD)

    def refused(match: str, key: str = KEY, payload: bytes = PAYLOAD, attachment: bytes | None = good, **kw: int) -> None:
        with pytest.raises(AccessError, match=match):
            verifier.verify(key, payload, attachment, **kw)

    refused("the call is not signed, and this manager checks every caller's identity", attachment=None)
    refused("does not verify with the certificate of 'alice'", payload=PAYLOAD + b" ")
    refused("does not verify", key="@dyknow/robot/spawn")  # signed for another manager
    now = int(parse(good)["time_ns"])  # type: ignore[call-overload]
    refused(r"signed \+301\.0 s from this manager's clock; expected within 300 s", now_ns=now - int((WINDOW_S + 1) * 1e9))
    refused(r"signed -301\.0 s from", now_ns=now + int((WINDOW_S + 1) * 1e9))
    verifier.verify(KEY, PAYLOAD, good)
    refused("a replay of one already received")
    for broken, why in [
        (good[:20], "malformed: 20 bytes"),
        (b"XKC1" + good[4:], "does not start with DKC1"),
        (good + b"x", "a signature of"),
        (good[:28] + b"\x00\x00" + good[30:], "a certificate of 0 bytes"),
    ]:
        refused(why, attachment=broken)
    write_dev_certs(tmp_path / "other", ["alice"])  # the same name, another CA
    refused("the certificate of 'alice' is not signed by this manager's CA", attachment=Signer(tls(tmp_path / "other", "alice")).sign(KEY, PAYLOAD))
    expired = issue(certs, "old", ec.generate_private_key(ec.SECP256R1()), days=(-30, -1))
    refused("the certificate of 'old' is valid from .* UTC, not now", attachment=Signer(expired).sign(KEY, PAYLOAD))
    server_only = issue(certs, "server", ec.generate_private_key(ec.SECP256R1()), client=False)
    refused("the certificate of 'server' is not for clients", attachment=Signer(server_only).sign(KEY, PAYLOAD))


def test_a_signer_refuses_a_key_that_is_not_its_certificates(certs: Path) -> None:
    mixed = TlsFiles(str(certs / "ca.pem"), str(certs / "alice.pem"), str(certs / "viewer.key"))
    with pytest.raises(AccessError, match=r"the key in .*viewer\.key is not the key of the certificate .*alice\.pem"):
        Signer(mixed)


# ---------------------------------------------------------------------- replay, whatever the flood


def _flood(verifier: Verifier, signer: Signer, calls: int, start_ns: int) -> None:
    """``calls`` fresh calls of ``signer``, signed 1 ms apart from ``start_ns``, all accepted."""
    for i in range(calls):
        when = start_ns + i * 1_000_000
        verifier.verify(KEY, PAYLOAD, signer.sign(KEY, PAYLOAD, time_ns=when), now_ns=when)


def test_a_call_replayed_after_another_callers_flood_is_refused(certs: Path) -> None:
    """An on-path router records an admin's call, floods the manager with more signed calls of
    its own than the manager remembers in all, then replays the recording inside the window:
    refused, since each caller's calls are remembered apart (the flood fills the router's
    ledger, not the admin's)."""
    verifier = Verifier(str(certs / "ca.pem"), ACL, budget=500)
    now = 1_800_000_000_000_000_000  # a fixed wall clock, so the test needs no sleeps
    recorded = Signer(tls(certs, "alice")).sign(KEY, PAYLOAD, time_ns=now)
    verifier.verify(KEY, PAYLOAD, recorded, now_ns=now)
    _flood(verifier, Signer(tls(certs, "robot")), 1_200, now + 1)  # over twice the budget
    assert verifier.remembered() == {"alice": 1, "robot": 500}
    with pytest.raises(AccessError, match="a replay of one already received"):
        verifier.verify(KEY, PAYLOAD, recorded, now_ns=now + int(151e9))  # 151 s later, as in the attack


def test_a_call_replayed_after_its_own_callers_flood_is_refused(certs: Path) -> None:
    """When the admin itself makes more calls than its ledger holds, its oldest are forgotten and
    its floor rises with them: the recorded call is refused as older than the floor, while the
    admin's new calls go on being accepted."""
    verifier = Verifier(str(certs / "ca.pem"), ACL, budget=300)
    alice = Signer(tls(certs, "alice"))
    now = 1_800_000_000_000_000_000
    recorded = alice.sign(KEY, PAYLOAD, time_ns=now)
    verifier.verify(KEY, PAYLOAD, recorded, now_ns=now)
    _flood(verifier, alice, 1_000, now + 1)
    assert verifier.remembered() == {"alice": 300}
    with pytest.raises(AccessError, match="signed before the 300 most recent calls of 'alice'"):
        verifier.verify(KEY, PAYLOAD, recorded, now_ns=now + int(2e9))
    later = now + int(3e9)
    verifier.verify(KEY, PAYLOAD, alice.sign(KEY, PAYLOAD, time_ns=later), now_ns=later)  # new calls still work


def test_a_window_of_calls_out_of_order_is_accepted_once_each(certs: Path) -> None:
    """Calls of one caller that arrive out of order (threads, several links) are accepted as
    long as the ledger holds them, each once; a naive model (a set of every nonce ever seen)
    agrees on every verdict while the budget is not exceeded."""
    import random

    verifier = Verifier(str(certs / "ca.pem"), ACL, budget=1_000)
    alice = Signer(tls(certs, "alice"))
    now = 1_800_000_000_000_000_000
    calls = [(now + i * 1_000_000, alice.sign(KEY, PAYLOAD, time_ns=now + i * 1_000_000)) for i in range(400)]
    order = calls + random.Random(7).sample(calls, 200)  # every call, then 200 replays
    random.Random(8).shuffle(order)
    seen: set[bytes] = set()
    for _when, attachment in order:
        replay = attachment in seen
        seen.add(attachment)
        if replay:
            with pytest.raises(AccessError, match="replay"):
                verifier.verify(KEY, PAYLOAD, attachment, now_ns=now + int(1e9))
        else:
            verifier.verify(KEY, PAYLOAD, attachment, now_ns=now + int(1e9))


def test_calls_signed_ahead_never_lock_out_calls_signed_on_time(certs: Path) -> None:
    """Issue 51, item 8: calls signed 290 s ahead (within the 300 s window) filled the caller's
    ledger, and the next one raised its floor 290 s into the future: the caller's honest calls
    were refused for minutes (with a shared certificate, one client locked out the others).
    Calls signed ahead have their own part of the ledger now: they never raise the floor, one
    past its budget is refused instead, and calls signed on time go on being accepted, however
    many; every replay is still refused."""
    verifier = Verifier(str(certs / "ca.pem"), ACL, budget=300, ahead_budget=300)
    alice = Signer(tls(certs, "alice"))
    now = 1_800_000_000_000_000_000
    ahead = [alice.sign(KEY, PAYLOAD, time_ns=now + int(290e9) + i) for i in range(301)]
    for attachment in ahead[:300]:
        verifier.verify(KEY, PAYLOAD, attachment, now_ns=now)
    with pytest.raises(AccessError, match=r"signed \+290\.000 s ahead of this manager's clock, and the manager already remembers 300 calls"):
        verifier.verify(KEY, PAYLOAD, ahead[300], now_ns=now)
    honest = now + 1_000_000
    verifier.verify(KEY, PAYLOAD, alice.sign(KEY, PAYLOAD, time_ns=honest - 500_000), now_ns=honest)  # (refused before)
    _flood(verifier, alice, 1_000, honest + 1)  # over three times the budget, each at the clock: all accepted
    assert verifier.remembered() == {"alice": 600}
    for when in (now + int(2e9), now + int(289e9)):  # replays of the calls signed ahead: remembered, whatever came between
        with pytest.raises(AccessError, match="a replay of one already received"):
            verifier.verify(KEY, PAYLOAD, ahead[0], now_ns=when)
    with pytest.raises(AccessError, match="signed -301.0 s from this manager's clock"):
        verifier.verify(KEY, PAYLOAD, ahead[0], now_ns=now + int(591e9))  # (and out of the window once it has left)


def test_calls_signed_ahead_and_on_time_against_a_naive_model(certs: Path) -> None:
    """Ten simulated minutes of one certificate shared by an honest client (its calls signed at
    the manager's clock, 0-50 ms before they arrive) and an attacker (calls signed up to 299 s
    ahead, 27 a second, and replays of anything seen): the honest client's calls are all
    accepted, every replay is refused, and the ledger stays within its budgets."""
    import random

    rng = random.Random(51)
    verifier = Verifier(str(certs / "ca.pem"), ACL, budget=200, ahead_budget=200)
    shared = Signer(tls(certs, "alice"))
    start = 1_800_000_000_000_000_000
    accepted: list[bytes] = []
    for step in range(2_000):
        now = start + step * 300_000_000  # one step every 300 ms
        for _ in range(8):  # the attacker: refused once its calls signed ahead fill their part, never an error of another kind
            attachment = shared.sign(KEY, PAYLOAD, time_ns=now + rng.randrange(1, int(299e9)))
            try:
                verifier.verify(KEY, PAYLOAD, attachment, now_ns=now)
                accepted.append(attachment)
            except AccessError as exc:
                assert "ahead of this manager's clock, and the manager already remembers 200 calls" in str(exc)
        attachment = shared.sign(KEY, PAYLOAD, time_ns=now - rng.randrange(0, 50_000_000))
        verifier.verify(KEY, PAYLOAD, attachment, now_ns=now)  # the honest client: always accepted
        accepted.append(attachment)
        if rng.random() < 0.3:
            with pytest.raises(AccessError, match="replay|signed before the|from this manager's clock"):
                verifier.verify(KEY, PAYLOAD, rng.choice(accepted), now_ns=now)
        assert verifier.remembered()["alice"] <= 400


def test_nothing_is_remembered_of_a_call_its_role_may_not_make(certs: Path) -> None:
    """The role is checked before the nonce is stored: a stranger (no role) and a viewer calling
    what only an admin may cost the manager no memory, however many calls they make."""
    verifier = Verifier(str(certs / "ca.pem"), ACL)

    def admin_only(caller: Caller) -> None:
        if caller.role != "admin":
            raise AccessError(f"{caller.common_name!r} may not call spawn")

    for name in ("stranger", "viewer"):
        signer = Signer(tls(certs, name))
        for _ in range(50):
            with pytest.raises(AccessError, match="may not call spawn"):
                verifier.verify(KEY, PAYLOAD, signer.sign(KEY, PAYLOAD), allowed=admin_only)
    stranger = Signer(tls(certs, "stranger"))
    for _ in range(50):
        assert verifier.verify(KEY, PAYLOAD, stranger.sign(KEY, PAYLOAD)).role is None  # (no role: refused by the caller's check)
    assert verifier.remembered() == {}
    verifier.verify(KEY, PAYLOAD, Signer(tls(certs, "alice")).sign(KEY, PAYLOAD), allowed=admin_only)
    assert verifier.remembered() == {"alice": 1}
