"""dyknow certs: a development CA and certificates for TLS with mutual authentication."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from dyknow.certs import CertificateError, write_dev_certs
from tests.conftest import run_cli


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


@pytest.mark.process
def test_a_ca_and_one_certificate_per_name(tmp_path: Path) -> None:
    result = run_cli("certs", str(tmp_path), "--names", "robot,ground", "--json")
    assert result.returncode == 0, result.stderr
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["ca.key", "ca.pem", "ground.key", "ground.pem", "robot.key", "robot.pem"]
    ca = _cert(tmp_path / "ca.pem")
    robot = _cert(tmp_path / "robot.pem")
    assert robot.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "robot"
    assert robot.issuer == ca.subject
    robot.verify_directly_issued_by(ca)  # signed by the CA
    usage = robot.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(usage)
    alt = robot.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert alt.get_values_for_type(x509.DNSName) == ["robot", "localhost"]
    assert [str(a) for a in alt.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    for key in ("ca.key", "robot.key", "ground.key"):
        assert stat.S_IMODE((tmp_path / key).stat().st_mode) == 0o600


def test_an_existing_ca_is_reused_for_new_names(tmp_path: Path) -> None:
    write_dev_certs(tmp_path, ["a"])
    ca_before = (tmp_path / "ca.pem").read_bytes()
    written = write_dev_certs(tmp_path, ["b"], hosts=["10.0.0.2", "robot.local"])
    assert [p.name for p in written] == ["b.key", "b.pem"] and (tmp_path / "ca.pem").read_bytes() == ca_before
    alt = _cert(tmp_path / "b.pem").extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert alt.get_values_for_type(x509.DNSName) == ["b", "robot.local"]
    _cert(tmp_path / "b.pem").verify_directly_issued_by(_cert(tmp_path / "ca.pem"))


@pytest.mark.parametrize(
    ("names", "hosts", "message"),
    [
        (["ca"], ["localhost"], "name 'ca' cannot be a certificate name"),
        (["a/b"], ["localhost"], "name 'a/b' cannot be a certificate name"),
        ([], ["localhost"], "no names given"),
        (["a"], ["not a host"], "--hosts: host 'not a host' is neither a host name nor an IP address"),
    ],
)
def test_bad_names_are_refused_before_anything_is_written(tmp_path: Path, names: list[str], hosts: list[str], message: str) -> None:
    with pytest.raises(CertificateError, match=message):
        write_dev_certs(tmp_path / "out", names, hosts=hosts)
    assert not (tmp_path / "out").exists()


@pytest.mark.process
def test_a_broken_ca_is_not_overwritten(tmp_path: Path) -> None:
    (tmp_path / "ca.pem").write_text("not a certificate")
    (tmp_path / "ca.key").write_text("not a key")
    result = run_cli("certs", str(tmp_path), "--names", "a")
    assert result.returncode == 1 and "the CA there cannot be reused" in result.stderr
    assert (tmp_path / "ca.pem").read_text() == "not a certificate"
