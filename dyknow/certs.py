"""Development certificates for TLS with mutual authentication (``dyknow certs``).

:func:`write_dev_certs` writes a certificate authority (``ca.pem``, ``ca.key``) and, for each
name, a certificate and key signed by it (``<name>.pem``, ``<name>.key``). The name is the
certificate's common name, which is what access control (``dyknow manager --acl``) matches roles
against. Each certificate is valid for TLS clients and servers, for the host names and addresses
given (``localhost`` and ``127.0.0.1`` by default, plus the name itself when it is a host name).

An existing ``ca.pem``/``ca.key`` in the folder is reused, so certificates can be added later for
new names. Keys are written readable by their owner only. These are for development and tests:
for a deployment, use the certificates of your own CA (any PEM files work with ``--tls-*``).
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dyknow.errors import DyKnowError

__all__ = ["CertificateError", "DEFAULT_HOSTS", "write_dev_certs"]

#: The host names and addresses every development certificate is valid for.
DEFAULT_HOSTS: tuple[str, ...] = ("localhost", "127.0.0.1")

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
_HOST = re.compile(r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*")


class CertificateError(DyKnowError):
    """Certificates cannot be written: a bad name, an unreadable CA, a folder that cannot be written."""


def write_dev_certs(
    directory: str | os.PathLike[str], names: Iterable[str], *, hosts: Sequence[str] = DEFAULT_HOSTS, days: int = 825
) -> list[Path]:
    """Write a development CA (or reuse the one in ``directory``) and a certificate per name.

    Returns the paths written. Raises :class:`CertificateError` naming the problem.
    """
    folder = Path(directory)
    chosen = list(dict.fromkeys(names))
    if not chosen:
        raise CertificateError("no names given", expected="at least one name, such as --names manager,operator")
    for name in chosen:
        if not _NAME.fullmatch(name) or name in ("ca",):
            raise CertificateError(
                f"name {name!r} cannot be a certificate name", expected="letters, digits, '_', '-' or '.' (up to 64), and not 'ca'"
            )
    for host in hosts:
        if not _is_ip(host) and not _HOST.fullmatch(host):
            raise CertificateError(f"host {host!r} is neither a host name nor an IP address", where="--hosts")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CertificateError(f"cannot create the folder: {exc.strerror or exc}", where=str(folder)) from exc
    written: list[Path] = []
    ca_key, ca_cert = _load_ca(folder)
    if ca_cert is None or ca_key is None:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_cert = _ca_certificate(ca_key, days)
        written += [_write_key(folder / "ca.key", ca_key), _write_pem(folder / "ca.pem", ca_cert)]
    for name in chosen:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _leaf_certificate(name, key, ca_key, ca_cert, hosts, days)
        written += [_write_key(folder / f"{name}.key", key), _write_pem(folder / f"{name}.pem", cert)]
    return written


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def _load_ca(folder: Path) -> tuple[ec.EllipticCurvePrivateKey | None, x509.Certificate | None]:
    key_path, cert_path = folder / "ca.key", folder / "ca.pem"
    if not key_path.exists() and not cert_path.exists():
        return None, None
    try:
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    except (OSError, ValueError, TypeError) as exc:
        raise CertificateError(
            f"the CA there cannot be reused ({type(exc).__name__}: {exc})",
            where=str(folder),
            expected="ca.pem and ca.key written by dyknow certs, or neither",
        ) from exc
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise CertificateError("ca.key is not an elliptic-curve key", where=str(folder), expected="ca.key written by dyknow certs")
    return key, cert


def _validity(days: int) -> tuple[datetime.datetime, datetime.datetime]:
    now = datetime.datetime.now(datetime.UTC)
    return now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)


def _ca_certificate(key: ec.EllipticCurvePrivateKey, days: int) -> x509.Certificate:
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "dyknow development CA")])
    start, end = _validity(days)
    return (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )  # fmt: skip
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )


def _leaf_certificate(
    name: str,
    key: ec.EllipticCurvePrivateKey,
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    hosts: Sequence[str],
    days: int,
) -> x509.Certificate:
    alt: list[x509.GeneralName] = []
    for host in dict.fromkeys([*(h for h in [name] if _HOST.fullmatch(h) and not _is_ip(h)), *hosts]):
        alt.append(x509.IPAddress(ipaddress.ip_address(host)) if _is_ip(host) else x509.DNSName(host))
    start, end = _validity(days)
    return (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> Path:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as file:
            file.write(data)
        os.chmod(path, 0o600)
    except OSError as exc:
        raise CertificateError(f"cannot write the key: {exc.strerror or exc}", where=str(path)) from exc
    return path


def _write_pem(path: Path, cert: x509.Certificate) -> Path:
    try:
        path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    except OSError as exc:
        raise CertificateError(f"cannot write the certificate: {exc.strerror or exc}", where=str(path)) from exc
    return path
