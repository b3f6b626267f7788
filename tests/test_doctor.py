"""dyknow doctor: each diagnosis made on the situation created for real (a port taken, no manager,
an ACL refusing the caller, /dev/shm unusable in a mount namespace, a manager whose wall clock
libfaketime skews, multicast off with nothing to connect to, a router down), with its fix."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import AccessControl, Client, Manager, TlsFiles
from dyknow.certs import write_dev_certs
from dyknow.doctor import Diagnosis, check_config, check_port, check_shm, diagnose
from tests.conftest import (
    REPO,
    CliProcess,
    ManagerProcess,
    end_process,
    faked_clock,
    free_port,
    run_cli,
    subprocess_env,
    under_ci,
    wait_until,
)

CI = under_ci()


def _of(found: list[Diagnosis], check: str) -> list[Diagnosis]:
    return [d for d in found if d.check == check]


def _doctor(*args: str) -> tuple[int, list[dict[str, str]], str]:
    done = run_cli("doctor", "--json", *args, timeout=60)
    return done.returncode, json.loads(done.stdout or "[]"), done.stderr


def test_a_port_taken_by_another_program_is_named_with_a_free_one() -> None:
    with socket.socket() as squatter:
        squatter.bind(("127.0.0.1", 0))
        squatter.listen()
        endpoint = f"tcp/127.0.0.1:{squatter.getsockname()[1]}"
        (found,) = check_port([endpoint])
    assert found.status == "fail" and found.what.startswith(f"{endpoint} is taken by another program (it does not speak Zenoh)")
    assert "dyknow manager --listen tcp/127.0.0.1:" in found.fix and "--connect tcp/127.0.0.1:" in found.fix
    (free,) = check_port([endpoint])  # the squatter is gone
    assert free.status == "ok"


@pytest.mark.process
def test_a_port_held_by_a_manager_is_fine_for_clients(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process(name="robot")
    (found,) = check_port([proc.endpoint])
    assert found.status == "ok" and f"{proc.endpoint} is taken by dyknow manager 'robot': clients reach it there" in found.what
    assert "a second manager on this host needs another port" in found.what


@pytest.mark.process
def test_no_manager_reachable_says_nothing_listens_and_to_start_one() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    code, found, _ = _doctor("--connect", endpoint)
    assert code == 1
    (probe,) = [d for d in found if d["check"] == "endpoint"]
    assert probe["status"] == "fail" and "nothing listens on port" in probe["what"] and "dyknow manager --listen" in probe["fix"]
    (managers,) = [d for d in found if d["check"] == "managers"]
    assert managers["status"] == "fail" and managers["what"] == f"no manager reachable through {endpoint}"


@pytest.mark.process
def test_a_router_down_and_a_router_without_managers_are_told_apart(tmp_path: Path, manager_process: Callable[..., ManagerProcess]) -> None:
    hub = f"tcp/127.0.0.1:{free_port()}"
    router = CliProcess("router", "--listen", hub, "--json")
    try:
        assert router.line()["event"] == "ready"
        code, found, _ = _doctor("--connect", hub, "--listen", f"tcp/127.0.0.1:{free_port()}")
        (managers,) = [d for d in found if d["check"] == "managers"]
        assert code == 1 and managers["what"] == f"{hub} answers (a router or a peer), but no manager is connected to it"
        assert managers["fix"] == f"start a manager that connects there: dyknow manager --connect {hub}"
        manager_process("--connect", hub, name="robot")
        wait_until(lambda: _doctor("--connect", hub, "--manager", "robot", "--listen", f"tcp/127.0.0.1:{free_port()}")[0] == 0,
                   "the manager behind the router")  # fmt: skip
    finally:
        router.stop()
        router.close()
    code, found, _ = _doctor("--connect", hub, "--manager", "robot")
    (probe,) = [d for d in found if d["check"] == "endpoint"]
    assert code == 1 and probe["status"] == "fail" and probe["what"].endswith("the manager or router there is down, or listens elsewhere")
    assert f"dyknow router --listen {hub}" in probe["fix"]


def test_an_acl_that_gives_the_caller_no_role_is_named(tmp_path: Path, make_manager: Callable[..., Manager]) -> None:
    write_dev_certs(tmp_path, ["manager", "viewer", "stranger"])

    def tls(name: str) -> TlsFiles:
        return TlsFiles(str(tmp_path / "ca.pem"), str(tmp_path / f"{name}.pem"), str(tmp_path / f"{name}.key"))

    acl = AccessControl.from_dict({"roles": {"viewer": ["viewer"]}})
    manager = make_manager("robot", listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls("manager"), acl=acl)
    seen = diagnose(connect=manager.endpoints, manager="robot", tls=tls("viewer"))
    assert [d.status for d in _of(seen, "access")] == ["ok"]
    refused = diagnose(connect=manager.endpoints, manager="robot", tls=tls("stranger"))
    (managers,) = _of(refused, "managers")
    assert managers.status == "fail" and "no manager is visible: with --acl, a manager shows a certificate without a role nothing" in managers.what
    assert managers.fix == "give this certificate's common name a role in the managers' --acl file (viewer at least)"


@pytest.mark.process
def test_multicast_off_with_nothing_to_connect_to_finds_no_one(tmp_path: Path) -> None:
    config = tmp_path / "zenoh.json5"
    config.write_text('{ mode: "peer", scouting: { multicast: { enabled: false } } }')
    (found,) = check_config(str(config), [])
    assert found.status == "fail" and "multicast scouting is off and it connects nowhere" in found.what
    assert "--connect ENDPOINT" in found.fix
    code, listed, _ = _doctor("--zenoh-config", str(config))
    assert code == 1 and [d["status"] for d in listed if d["check"] == "config"] == ["fail"]
    (ok,) = check_config(str(config), ["tcp/127.0.0.1:7447"])
    assert ok.status == "ok"
    config.write_text('{ mode: "peer" }')  # multicast on, Zenoh's default: works on one segment only
    (relies,) = check_config(str(config), [])
    assert relies.status == "warn" and "multicast scouting alone" in relies.what


def test_shared_memory_here_works() -> None:
    (found,) = check_shm()
    assert found.status == "ok", found


@pytest.mark.namespaces
@pytest.mark.parametrize("mount", ["size=64k", "ro"], ids=["too-small", "read-only"])
def test_an_unusable_dev_shm_is_diagnosed_in_a_mount_namespace(mount: str) -> None:
    """/dev/shm replaced, in a mount namespace of the doctor's own, by a tmpfs too small for Zenoh's
    pool (a container's default) or read-only."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        if CI:
            pytest.fail("a mount namespace (unshare, root) is required under CI")
        pytest.skip("a mount namespace needs root and unshare")
    command = f"mount -t tmpfs -o {mount} tmpfs /dev/shm && exec {sys.executable} -m dyknow.cli doctor --json --connect tcp/127.0.0.1:{free_port()}"
    done = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", command], capture_output=True, text=True,
                          timeout=60, env=subprocess_env(), cwd=REPO)  # fmt: skip
    (shm,) = [d for d in json.loads(done.stdout) if d["check"] == "shm"]
    assert shm["status"] == "warn" and shm["what"].startswith("no usable shared memory: Unable to create POSIX shm segment"), done.stdout
    assert "are copied through the network stack instead" in shm["what"] and "--shm-size" in shm["fix"]


@pytest.mark.process
def test_a_skewed_clock_between_two_managers_is_named(faketime: Path) -> None:
    """The robot's manager runs with its wall clock 250 ms ahead (libfaketime), as an
    unsynchronised host's would be; the station estimates the offset, and doctor names it."""
    station_port, robot_port = free_port(), free_port()
    generic = ["--specs", str(REPO / "specs" / "generic.xml")]
    station = CliProcess("manager", "--name", "station", "--listen", f"tcp/127.0.0.1:{station_port}", "--json", *generic)
    robot_argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", "robot", "--listen", f"tcp/127.0.0.1:{robot_port}",
                  "--connect", f"tcp/127.0.0.1:{station_port}", "--json", *generic]  # fmt: skip
    robot = subprocess.Popen(robot_argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                             env={**subprocess_env(), **faked_clock(faketime, "+0.25")})  # fmt: skip
    try:
        assert station.line()["event"] == "ready"
        assert robot.stdout is not None and json.loads(robot.stdout.readline())["event"] == "ready"
        args = ["--connect", f"tcp/127.0.0.1:{station_port}", "--manager", "station", "--listen", f"tcp/127.0.0.1:{free_port()}"]
        with Client("station", connect=[f"tcp/127.0.0.1:{station_port}"]) as client:  # the station receives the robot's data:
            Client("robot", session=client.session).spawn("periodic-source", "src", params={"rate_hz": 50})  # it estimates
            client.spawn("relay", "rel", bindings={"in": "dyknow/robot/src/out"})  # the robot's clock (on demand, issue 40)

        def clocks() -> list[dict[str, str]]:
            return [d for d in _doctor(*args)[1] if d["check"] == "clocks" and d["status"] != "warn"]

        wait_until(lambda: bool(clocks()), "the managers' estimates of each other's clocks", timeout_s=60)
        code, found, _ = _doctor(*args)
        (skew,) = [d for d in found if d["check"] == "clocks"]
        assert code == 1 and skew["status"] == "fail", found
        assert skew["what"].startswith("the clocks of 'robot' and 'station' differ by 2") and "beyond 10 ms" in skew["what"]
        assert "chrony or NTP" in skew["fix"]
        code, found, _ = _doctor(*args, "--max-clock-offset-ms", "1000")
        assert code == 0 and [d["status"] for d in found if d["check"] == "clocks"] == ["ok"]
    finally:
        end_process(robot, grace_s=10)
        station.stop()
        station.close()
