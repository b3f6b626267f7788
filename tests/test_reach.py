"""Failures told apart: each mistake an operator makes reaching a manager gets its own message,
naming the option or file to change, and a non-zero exit (real managers, real TLS, real links)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from dyknow import AccessError, Client, Manager, ServiceError
from dyknow.access import AccessControl, TlsFiles
from dyknow.certs import write_dev_certs
from dyknow.reach import probe
from dyknow.testing.hosts import Hosts
from tests.conftest import REPO, free_port, need_hosts, run_cli, subprocess_env


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two CAs: ``pki`` (the manager's, with robot and laptop) and ``pki/other`` (laptop again)."""
    folder = tmp_path_factory.mktemp("pki")
    write_dev_certs(folder, ["robot", "laptop", "stranger"])
    write_dev_certs(folder / "other", ["laptop"])
    # a CA file that trusts both CAs: the client then trusts the manager, and its certificate of
    # the other CA passes its own checks, so only the manager can refuse it
    (folder / "both.pem").write_bytes((folder / "ca.pem").read_bytes() + (folder / "other" / "ca.pem").read_bytes())
    return folder


def tls(pki: Path, name: str, ca: str = "ca.pem") -> TlsFiles:
    return TlsFiles(str(pki / ca), str(pki / f"{name}.pem"), str(pki / f"{name}.key"))


def tls_args(files: TlsFiles) -> list[str]:
    return ["--tls-ca", files.ca, "--tls-cert", files.cert, "--tls-key", files.key]


@pytest.fixture
def robot(pki: Path, make_manager: Callable[..., Manager]) -> Manager:
    acl = AccessControl.from_dict({"roles": {"viewer": ["laptop"]}})
    return make_manager("robot", listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(pki, "robot"), acl=acl)


def fails(
    manager: Manager, files: TlsFiles | None, endpoint: str | None = None, name: str = "robot", timeout_s: float = 5.0
) -> ServiceError:
    with (
        Client(name, connect=[endpoint or manager.endpoints[0]], tls=files, timeout_s=timeout_s) as client,
        pytest.raises(ServiceError) as failed,
    ):
        client.get_model()
    return failed.value


def test_the_right_files_reach_the_manager(robot: Manager, pki: Path) -> None:
    with Client("robot", connect=robot.endpoints, tls=tls(pki, "laptop")) as client:
        assert client.get_model()["manager"] == "robot"
    assert probe(robot.endpoints[0], tls(pki, "laptop")).kind == "ok"


def test_a_refused_connection_is_said_at_once(pki: Path) -> None:
    port = free_port()
    with Client("robot", connect=[f"tcp/127.0.0.1:{port}"], timeout_s=30) as client, pytest.raises(ServiceError) as failed:
        client.get_model()  # (the 30 s timeout is not waited for: the test's own timeout would end it first)
    assert f"the connection to tcp/127.0.0.1:{port} was refused: nothing listens on port {port} of 127.0.0.1" in str(failed.value)
    assert "expected the endpoint a manager listens on (its --listen) in --connect" in str(failed.value)


@pytest.mark.timeout(20)
def test_the_managers_ca_unknown_to_the_client(robot: Manager, pki: Path) -> None:
    error = fails(robot, tls(pki / "other", "laptop"), timeout_s=30)
    assert f"is not signed by the CA of --tls-ca {pki / 'other' / 'ca.pem'}" in str(error)
    assert "expected --tls-ca the CA file of the manager's deployment" in str(error)


@pytest.mark.timeout(20)
def test_a_client_certificate_the_manager_does_not_trust(robot: Manager, pki: Path) -> None:
    files = TlsFiles(str(pki / "both.pem"), str(pki / "other" / "laptop.pem"), str(pki / "other" / "laptop.key"))
    error = fails(robot, files, timeout_s=30)
    assert f"refused this client's certificate --tls-cert {files.cert}" in str(error)
    assert "it is not signed by the CA the manager trusts; expected a certificate signed by the manager's CA" in str(error)


@pytest.mark.timeout(20)
def test_tcp_to_a_tls_listener(robot: Manager, pki: Path) -> None:
    endpoint = robot.endpoints[0].replace("tls/", "tcp/")
    for files in (tls(pki, "laptop"), None):  # TLS files given to a tcp/ endpoint, or none at all
        error = fails(robot, files, endpoint, timeout_s=30)
        assert f"the listener at {endpoint} speaks TLS" in str(error)
        assert f"expected --connect {robot.endpoints[0]}, with --tls-ca, --tls-cert and --tls-key" in str(error)


def test_a_tls_endpoint_without_tls_files(robot: Manager) -> None:
    with pytest.raises(AccessError, match=r"--connect: tls/\S+ is a TLS endpoint, and this client has no TLS files; expected --tls-ca"):
        Client("robot", connect=robot.endpoints)


@pytest.mark.process
def test_files_that_do_not_belong_together_name_the_files(pki: Path) -> None:
    mismatched = TlsFiles(str(pki / "ca.pem"), str(pki / "laptop.pem"), str(pki / "robot.key"))
    with pytest.raises(
        AccessError, match=f"--tls-key: the key in {pki / 'robot.key'} is not the key of the certificate {pki / 'laptop.pem'}"
    ):
        mismatched.check()
    foreign = TlsFiles(str(pki / "ca.pem"), str(pki / "other" / "laptop.pem"), str(pki / "other" / "laptop.key"))
    with pytest.raises(
        AccessError, match=f"--tls-cert: the certificate {pki / 'other' / 'laptop.pem'} is not signed by the CA of {pki / 'ca.pem'}"
    ):
        foreign.check()
    # the manager's own files, at start, before anything listens
    started = run_cli("manager", "--name", "m", "--listen", f"tls/127.0.0.1:{free_port()}", *tls_args(mismatched))
    assert started.returncode == 1
    assert started.stderr.strip() == (
        f"dyknow: error: --tls-key: the key in {pki / 'robot.key'} is not the key of the certificate {pki / 'laptop.pem'}; "
        "expected the private key the certificate was issued for (NAME.key beside NAME.pem)"
    )


@pytest.mark.timeout(20)
def test_a_misspelled_manager_gets_a_close_match(robot: Manager, pki: Path) -> None:
    """Said once the others are seen and it is not, without waiting for the (long) timeout."""
    error = fails(robot, tls(pki, "laptop"), name="robt", timeout_s=30)
    assert str(error).endswith("no manager 'robt' among those reachable (robot); expected --manager one of robot (did you mean 'robot'?)")


def test_a_certificate_without_a_role_sees_nothing(robot: Manager, pki: Path) -> None:
    error = fails(robot, tls(pki, "stranger"), timeout_s=1.0)
    assert "linked, but no manager is visible from here" in str(error)
    assert "whose --acl gives this client's certificate (common name 'stranger') a role" in str(error)


def test_a_call_dropped_for_the_callers_role(robot: Manager, pki: Path) -> None:
    with Client("robot", connect=robot.endpoints, tls=tls(pki, "laptop")) as client, pytest.raises(ServiceError) as failed:
        client.spawn("relay", "r")
    assert "dropped the call to 'spawn' without a reply: the manager's --acl does not let this client's certificate " in str(failed.value)
    assert "(common name 'laptop'" in str(failed.value)
    assert str(failed.value).endswith(
        "a role that may call 'spawn' in the manager's --acl file (operator or admin, or a role its define lists it in)"
    )


@pytest.mark.process
@pytest.mark.timeout(30)
def test_every_mistake_on_the_command_line_has_its_message_and_exit_1(robot: Manager, pki: Path) -> None:
    endpoint, port = robot.endpoints[0], robot.endpoints[0].rsplit(":", 1)[1]
    laptop = tls_args(tls(pki, "laptop"))
    cases = {
        "refused": (["--connect", endpoint.replace(port, str(free_port())), *laptop], "was refused: nothing listens on port"),
        "another CA": (["--connect", endpoint, *tls_args(tls(pki / "other", "laptop"))], "is not signed by the CA of --tls-ca"),
        "tcp/": (["--connect", endpoint.replace("tls/", "tcp/"), *laptop], "speaks TLS, and tcp/ connects without it"),
        "no TLS files": (["--connect", endpoint], "is a TLS endpoint, and this client has no TLS files"),
        "key": (["--connect", endpoint, *tls_args(TlsFiles(str(pki / "ca.pem"), str(pki / "laptop.pem"), str(pki / "robot.key")))], "is not the key of the certificate"),
    }  # fmt: skip
    for case, (args, said) in cases.items():
        result = run_cli("model", "--manager", "robot", "--timeout", "20", *args)
        assert result.returncode == 1 and said in result.stderr, (case, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1, (case, result.stderr)
    for command in (["managers"], ["model", "--all"], ["echo", "dyknow/**"]):  # (echo would wait for ever)
        none = run_cli(*command, "--connect", f"tcp/127.0.0.1:{free_port()}")
        assert none.returncode == 1 and "cannot reach any manager: the connection to" in none.stderr, (command, none.stderr)
    listed = run_cli("managers", "--json", "--connect", endpoint, *laptop, "--lease-ms", "2000")
    assert listed.returncode == 0 and [m["manager"] for m in json.loads(listed.stdout)] == ["robot"]
    dropped = run_cli("destroy", "x", "--manager", "robot", "--connect", endpoint, *laptop)
    assert dropped.returncode == 1 and "dropped the call to 'destroy'" in dropped.stderr


@pytest.mark.process
def test_a_spec_not_removed_exits_1(robot: Manager, pki: Path, make_manager: Callable[..., Manager]) -> None:
    plain = make_manager()
    result = run_cli("remove-spec", "no-such-label", "--manager", plain.name, "--connect", plain.endpoints[0])
    assert result.returncode == 1 and "nothing removed" in result.stdout


# ---------------------------------------------------------------------------- another host


@pytest.fixture
def two_hosts() -> Iterator[Hosts]:
    need_hosts()
    with Hosts(["laptop", "robot"]) as made:
        yield made


@pytest.mark.namespaces
@pytest.mark.timeout(60)
def test_a_host_without_the_manager_and_a_silent_host(two_hosts: Hosts) -> None:
    """Nothing listens on the robot: refused at once. The robot cut off: silent, said after the timeout."""
    robot = two_hosts.address("robot")

    def model(timeout: str) -> subprocess.CompletedProcess[str]:
        argv = [sys.executable, "-m", "dyknow.cli", "model", "--manager", "robot", "--connect", f"tcp/{robot}:7447", "--timeout", timeout]
        return subprocess.run(two_hosts.command("laptop", argv), capture_output=True, text=True, timeout=40, env=subprocess_env(), cwd=REPO)

    refused = model("30")
    assert refused.returncode == 1 and f"the connection to tcp/{robot}:7447 was refused" in refused.stderr, refused.stderr
    two_hosts.cut("robot")
    silent = model("2")
    assert silent.returncode == 1, silent.stderr
    assert (
        f"{robot} did not answer a connection to port 7447 within 1 s: it is down, cut off, or a firewall drops the packets"
        in silent.stderr
    )
    assert "expected a host this machine reaches (--connect)" in silent.stderr


@pytest.mark.process
def test_a_manager_or_router_with_a_tls_endpoint_and_no_tls_files(
    make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture, pki: Path
) -> None:
    """Said naming the option (Zenoh says only "Missing TLS private key"); TLS files with no tls/
    endpoint at all are a warning (every link is plain TCP)."""
    with pytest.raises(AccessError, match=r"--listen: tls/\S+ is a TLS endpoint, and manager 'lonely' has no TLS files; expected --tls-ca"):
        make_manager("lonely", listen=[f"tls/127.0.0.1:{free_port()}"])
    router = run_cli("router", "--listen", f"tls/127.0.0.1:{free_port()}")
    assert router.returncode == 1 and "is a TLS endpoint, and the router has no TLS files" in router.stderr
    make_manager("plain", listen=[f"tcp/127.0.0.1:{free_port()}"], tls=tls(pki, "robot"))
    assert "manager 'plain' has TLS files but no tls/ endpoint (--listen, --connect): every link is plain TCP" in caplog.text


@pytest.mark.timeout(20)
def test_a_manager_certificate_not_made_for_the_address(tmp_path: Path, make_manager: Callable[..., Manager]) -> None:
    """Certificates made for the name localhost only, connected to by address: said at once, with the fix."""
    write_dev_certs(tmp_path, ["robot", "laptop"], hosts=["localhost"])
    manager = make_manager("robot", listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(tmp_path, "robot"))
    error = fails(manager, tls(tmp_path, "laptop"), timeout_s=30)
    assert f"the certificate of the listener at {manager.endpoints[0]} is not valid for '127.0.0.1'" in str(error)
    assert "expected certificates made for the address clients connect to (dyknow certs DIR --names ... --hosts ...,127.0.0.1)" in str(
        error
    )
