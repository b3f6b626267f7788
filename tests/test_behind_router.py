"""Managers behind a router, as a fleet deploys them (issue 40): each manager dials its router
only and holds that one link; the router carries everything between managers (summaries, calls,
data, liveliness), so planning across managers, failover on a kill and lost managers work as with
managers that link to each other. A standby router takes over when the first goes.

Links are counted as the kernel sees them (``ss``: established TCP sockets of a process).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from dyknow import Client, Manager
from dyknow.errors import TransportError
from dyknow.testing import CAMERA_IDS, SCENARIO_HOSTS, Sink
from dyknow.transport import Session, make_config
from tests.conftest import REPO, CliProcess, free_port, run_cli, subprocess_env, wait_until

ONTOLOGY = REPO / "specs" / "dyknow.ttl"
BOTTOM, CEILING = CAMERA_IDS["bottom"], CAMERA_IDS["ceiling"]
TRACK = "BallTrack(field)"


def links(pid: int) -> list[str]:
    """The remote end (``ADDRESS:PORT``) of each established TCP socket of process ``pid``."""
    out = subprocess.run(["ss", "-tnpH", "state", "established"], capture_output=True, text=True, check=True).stdout
    return sorted(line.split()[3] for line in out.splitlines() if f"pid={pid}," in line)


@pytest.fixture
def started(cli_process: Callable[..., CliProcess]) -> Iterator[Callable[..., CliProcess]]:
    """``dyknow ...`` processes that print a ready line first (checked); killed after the test."""

    def start(*args: str) -> CliProcess:
        proc = cli_process(*args, "--json", "--lease-ms", "2000")
        assert proc.line()["event"] == "ready"
        return proc

    yield start


def behind(started: Callable[..., CliProcess], name: str, *routers: str, dwell: bool = False) -> CliProcess:
    """The scenario's manager ``name`` behind ``routers``."""
    via = [arg for router in routers for arg in ("--router", router)]
    extra = ["--dwell", "0.5"] if dwell else []
    return started("manager", "--name", name, *via, "--specs", str(SCENARIO_HOSTS[name]), "--ontology", str(ONTOLOGY),
                   "--host", f"{name}-host", *extra)  # fmt: skip


@pytest.mark.process
def test_managers_behind_a_router_hold_one_link_each_and_plan_across_it(started: Callable[..., CliProcess]) -> None:
    """Acceptance (issue 40, items 1 and 4): one link per manager, to its router; a request planned
    across managers flows through the router; a SIGKILL of the producer's manager fails over to the
    other camera; the lost manager is shown."""
    port = free_port()
    hub = f"tcp/127.0.0.1:{port}"
    started("router", "--listen", hub)
    station = behind(started, "station", hub, dwell=True)
    robot = behind(started, "robot", hub)
    field = behind(started, "field", hub)
    via = ["--connect", hub]
    wait_until(lambda: len(json.loads(run_cli("managers", "--json", *via).stdout)) == 3, "all three managers listed through the router")
    for proc in (station, robot, field):
        assert links(proc.proc.pid) == [f"127.0.0.1:{port}"]  # the router, and no other manager

    with Client("station", connect=[hub]) as client:
        wait_until(lambda: len(client.call_manager("station", "get_summary", {})["units"]) == 0, "the station's summary")
        key = client.request(TRACK)
        got: list[int] = []
        sub = client.session.declare_subscriber(key, lambda msg: got.append(msg.payload["camera"]))
        wait_until(lambda: got.count(BOTTOM) > 3, "the robot's camera on the request's key, through the router")
        # data between managers goes through the router too: still one link each
        for proc in (station, robot, field):
            assert links(proc.proc.pid) == [f"127.0.0.1:{port}"]

        robot.proc.send_signal(signal.SIGKILL)
        wait_until(lambda: CEILING in got, "the field's camera on the same key")
        wait_until(
            lambda: any(e["cause"] == "manager 'robot' was lost" and e["key"] == key for e in client.get_adaptations()),
            "the adaptation recorded, naming the lost manager",
        )
        listed = json.loads(run_cli("managers", "--json", *via, "--manager", "station").stdout)
        assert [(x["manager"], x["state"]) for x in listed] == [("field", "up"), ("station", "up"), ("robot", "lost")]
        sub.undeclare()


@pytest.mark.process
def test_a_standby_router_takes_over_when_the_first_goes(started: Callable[..., CliProcess]) -> None:
    """``--router A --router B``: the managers hold one link, to A; when A is killed they dial B
    (one link again) and keep planning with each other."""
    a, b = free_port(), free_port()
    first, standby = f"tcp/127.0.0.1:{a}", f"tcp/127.0.0.1:{b}"
    router = started("router", "--listen", first)
    started("router", "--listen", standby, "--connect", first)
    managers = [behind(started, name, first, standby) for name in ("station", "field")]
    for proc in managers:
        wait_until(lambda p=proc: links(p.proc.pid) == [f"127.0.0.1:{a}"], "one link, to the first router")  # type: ignore[misc]
    router.proc.send_signal(signal.SIGKILL)
    for proc in managers:
        wait_until(lambda p=proc: links(p.proc.pid) == [f"127.0.0.1:{b}"], "one link, to the standby")  # type: ignore[misc]
    _field_camera_on_request(standby, "through the standby")


def _field_camera_on_request(router: str, how: str) -> None:
    """Through ``router``, the station and the field are both listed, and a request made of the
    station gets the field's camera on its key."""
    with Client("station", connect=[router]) as client:
        wait_until(lambda: [m["manager"] for m in client.managers()] == ["field", "station"], f"both listed {how}")
        key = client.request(TRACK)
        got: list[int] = []
        with client.session.declare_subscriber(key, lambda msg: got.append(msg.payload["camera"])):
            wait_until(lambda: got.count(CEILING) > 3, f"the field's camera on the station's request, {how}")


@pytest.mark.process
def test_the_python_api_puts_a_manager_behind_a_router(make_manager: Callable[..., Manager]) -> None:
    """``Manager(router=[...])``: no listener, one link to the router; a request on one manager is
    served by a unit of the other, through the router."""
    port = free_port()
    hub = f"tcp/127.0.0.1:{port}"

    def established() -> set[tuple[str, str]]:  # (local, remote) of this process's TCP links
        out = subprocess.run(["ss", "-tnpH", "state", "established"], capture_output=True, text=True, check=True).stdout
        return {(line.split()[2], line.split()[3]) for line in out.splitlines() if f"pid={os.getpid()}," in line}

    before = established()  # (links an earlier test of this worker process left, still closing, are not these managers')
    with Session(make_config(listen=[hub], mode="router")):
        station = make_manager("station", specs=[SCENARIO_HOSTS["station"]], ontology=[ONTOLOGY], router=[hub])
        robot = make_manager("robot", specs=[SCENARIO_HOSTS["robot"]], ontology=[ONTOLOGY], router=[hub])
        assert station.endpoints == [] and robot.endpoints == []
        wait_until(lambda: station.reachable() == {"robot"} and robot.reachable() == {"station"}, "each to know the other")
        key = station.request(TRACK)
        assert [u.label for u in robot.units()] == ["robot-camera"]
        station.spawn("consumer", "consumer", bindings={"in": key})
        sink = station.unit("consumer")
        assert isinstance(sink, Sink)
        sink.wait_until(lambda msg: msg.payload["camera"] == BOTTOM and msg.payload["frame"] > 3)
        # this process holds the router's sockets too (its accepted ends, from the router's port)
        # and both managers': one each, to the router, none between them
        mine = established() - before
        assert sorted(remote for local, remote in mine if local != f"127.0.0.1:{port}") == [f"127.0.0.1:{port}"] * 2, (mine, before)


@pytest.mark.process
def test_a_full_router_refuses_the_next_manager_which_says_so(make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture) -> None:
    """A router takes 10,000 sessions by default (Zenoh's own 1,000 refused the 1,001st manager of
    a fleet); one at its ``max_sessions`` refuses the next manager, whose warning names the
    bound, and that manager runs on, listed by none; a client it refuses says why; ``dyknow
    router --max-sessions`` takes a whole number of at least 1."""
    assert make_config(mode="router").get_json("transport/unicast/max_sessions") == "10000"
    assert make_config(mode="peer").get_json("transport/unicast/max_sessions") == "1000"  # (Zenoh's)
    hub = f"tcp/127.0.0.1:{free_port()}"
    with Session(make_config(listen=[hub], mode="router", max_sessions=1)):
        first = make_manager("first", router=[hub], specs=[])
        with caplog.at_level(logging.WARNING, logger="dyknow.manager"):
            second = make_manager("second", router=[hub], specs=[])
        said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("manager 'second'")]
        assert len(said) == 1 and f"no router of {hub} answers yet (none listens there, or it refused this manager: a router full at its --max-sessions" in said[0], said
        assert first.reachable() == set() and second.reachable() == set()
        assert [u.name for u in second.units()] == []  # it runs, alone
        # a client the full router refuses says so, not that no manager is there
        with Client("first", connect=[hub], timeout_s=2) as client:
            why = client.unreachable()
            assert why is not None and why.details == {"reason": "no-session"}, why
            assert f"{hub} accepts connections, but Zenoh did not open a session with this client there" in str(why)
        listed = run_cli("managers", "--connect", hub, "--timeout", "2")
        assert listed.returncode == 1 and "(a router at its --max-sessions refuses more sessions)" in listed.stderr, listed.stderr
    bad = run_cli("router", "--max-sessions", "0")
    assert bad.returncode == 2 and "--max-sessions: got '0'; expected a positive whole number" in bad.stderr, bad.stderr


@pytest.mark.process
def test_a_router_takes_a_thousand_sessions(started: Callable[..., CliProcess]) -> None:
    """``dyknow router`` uses no shared memory: with it, Zenoh 1.10 made a segment in /dev/shm for
    each session and refused every session after the 351st (a fleet of 1,000 managers behind one
    router had 351), nor looks through its file descriptors on the thread that accepts links
    (it refused every session after about 300). 1,000 client sessions link to it."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    started("router", "--listen", hub)
    with contextlib.ExitStack() as stack:
        for i in range(1000):
            try:
                stack.enter_context(Session(make_config(mode="client", listen=[], connect=[hub])))
            except TransportError as exc:
                raise AssertionError(f"session {i + 1} refused: {exc}") from None


@pytest.mark.process
def test_a_manager_behind_a_router_dials_nothing_else(tmp_path: Path) -> None:
    with pytest.raises(TransportError, match="a manager behind a router dials only its router"):
        Manager("m", router=["tcp/127.0.0.1:7447"], connect=["tcp/127.0.0.1:7448"])
    with pytest.raises(TransportError, match="a manager behind a router dials only its router"):
        Manager("m", router=["tcp/127.0.0.1:7447"], listen=["tcp/127.0.0.1:0"])
    bad = run_cli("manager", "--router", "tcp/127.0.0.1:7447", "--listen", "tcp/127.0.0.1:0")
    assert bad.returncode != 0 and "--router: a manager behind a router dials only its router" in bad.stderr
    tls = run_cli("manager", "--router", "tls/127.0.0.1:7447")
    assert tls.returncode != 0 and "tls/127.0.0.1:7447 is a TLS endpoint" in tls.stderr and "--router" in tls.stderr


@pytest.mark.process
def test_behind_a_router_each_client_keeps_its_own_rights(started: Callable[..., CliProcess], tmp_path: Path) -> None:
    """Roles (issue 40, item 4): one ACL file for the router and the two managers behind it, TLS
    everywhere. A client through the router gets its own rights at the station: a viewer reads and
    receives but may not destroy nor publish, a requester also requests, an operator also
    publishes, a certificate without a role gets nothing (as in tests/test_hosts.py, with managers
    that link to each other)."""
    from dyknow.certs import write_dev_certs

    pki = tmp_path / "pki"
    names = ["station", "robot", "hub", "admin", "viewer", "requester", "operator", "stranger"]
    write_dev_certs(pki, names, hosts=["127.0.0.1"])
    acl = tmp_path / "acl.json5"
    acl.write_text("""{ roles: { manager: ["station", "robot"], router: ["hub"], admin: ["admin"], viewer: ["viewer"],
                                requester: ["requester"], operator: ["operator"] },
                     define: { requester: { like: "viewer", calls: ["request", "release"] } } }""")

    def tls(name: str) -> list[str]:
        return ["--acl", str(acl), "--tls-ca", str(pki / "ca.pem"), "--tls-cert", str(pki / f"{name}.pem"), "--tls-key", str(pki / f"{name}.key")]

    hub = f"tls/127.0.0.1:{free_port()}"
    started("router", "--listen", hub, *tls("hub"))
    generic = str(REPO / "specs" / "generic.xml")
    station = started("manager", "--name", "station", "--specs", generic, "--router", hub, *tls("station"))
    started("manager", "--name", "robot", "--specs", generic, "--router", hub, *tls("robot"))
    assert links(station.proc.pid) == [hub.removeprefix("tls/")]
    identities = ["viewer", "requester", "operator", "stranger"]
    done = subprocess.run([sys.executable, "-m", "tests.netns_rights", hub, "station", str(pki), *identities],
                          capture_output=True, text=True, timeout=300, env=subprocess_env(), cwd=REPO)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    found = {r.pop("name"): r for r in map(json.loads, done.stdout.splitlines())}
    assert found == {
        "viewer": {"get_model": "reached", "destroy": "dropped", "request": "dropped", "receives": True, "publishes": False},
        "requester": {"get_model": "reached", "destroy": "dropped", "request": "reached", "receives": True, "publishes": False},
        "operator": {"get_model": "reached", "destroy": "reached", "request": "reached", "receives": True, "publishes": True},
        "stranger": {"get_model": "nothing", "destroy": "nothing", "request": "nothing", "receives": False, "publishes": False},
    }


@pytest.mark.process
def test_a_manager_starts_before_its_router_and_joins_it_when_it_comes(started: Callable[..., CliProcess]) -> None:
    """A robot may boot before its router: its manager starts (its own units run), says that no
    router answers yet, and joins the router once it comes, with one link."""
    port = free_port()
    hub = f"tcp/127.0.0.1:{port}"
    station = behind(started, "station", hub)
    field = behind(started, "field", hub)
    assert links(station.proc.pid) == []
    started("router", "--listen", hub)
    wait_until(lambda: links(station.proc.pid) == links(field.proc.pid) == [f"127.0.0.1:{port}"], "one link each, to the router")
    _field_camera_on_request(hub, "through the router")
    station.proc.terminate()
    assert station.proc.wait(10) == 0
    assert station.proc.stderr is not None and "no router of " + hub + " answers yet" in station.proc.stderr.read()


@contextlib.contextmanager
def _busy_then_router(caplog: pytest.LogCaptureFixture) -> Iterator[tuple[str, list[Any]]]:
    """An endpoint whose first listener accepts a connection and says nothing (a router too busy
    to open the session); once the caller logs that it tries again, a Zenoh router takes the port
    (listed in the list yielded with the endpoint)."""
    import socket
    import threading

    import zenoh

    port = free_port()
    hub = f"tcp/127.0.0.1:{port}"
    silent = socket.socket()
    silent.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    silent.bind(("127.0.0.1", port))
    silent.listen()
    routers: list[Any] = []

    def take_over() -> None:
        conn, _ = silent.accept()  # (the first try: never answered)
        wait_until(lambda: any("took the connection but not the session" in r.getMessage() for r in caplog.records), "the retry")
        conn.close()
        silent.close()
        routers.append(zenoh.open(make_config(listen=[hub], mode="router")))

    helper = threading.Thread(target=take_over, daemon=True)
    helper.start()
    try:
        with caplog.at_level(logging.INFO):
            yield hub, routers
        helper.join(30)
    finally:
        silent.close()
        for router in routers:
            router.close()


def test_a_busy_router_is_tried_again_rather_than_joined_as_a_router(make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture) -> None:
    """A router that accepts the connection but is slow to open the session (a fleet starting at
    once) is tried again, and the manager becomes its client: 137 of 1,000 managers starting at
    once gave up at the first try and joined as Zenoh routers, which receive every declaration of
    the fleet."""
    with _busy_then_router(caplog) as (hub, routers):
        manager = make_manager("patient", router=[hub], specs=[], lease_ms=1000)
        said = [r.getMessage() for r in caplog.records]
        assert not any("answers yet" in m for m in said), said
        (router,) = routers
        wait_until(lambda: manager.session.linked(), "the link to the router")
        assert manager.session.zid not in {str(z) for z in router.info.routers_zid()}  # (a client of it)


def test_a_client_tries_a_busy_router_again_and_lists_the_managers_behind_it(make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture) -> None:
    """A client (a command, the web tool) that gave up on a busy router at once fell back to a
    Zenoh peer, whose liveliness queries are answered from what it heard itself: it listed 0 of
    1,000 managers for ten minutes. It tries the router again within its timeout."""
    with _busy_then_router(caplog) as (hub, routers), Client("behind", connect=[hub], timeout_s=20) as client:
        make_manager("behind", router=[hub], specs=[])
        wait_until(lambda: client.manager_names(timeout_s=0.5) == ["behind"], "the manager behind the router listed")
        assert client.get_model()["manager"] == "behind"


def test_a_manager_behind_a_router_beyond_this_host_without_tls_is_exposed(make_manager: Callable[..., Manager]) -> None:
    """Anyone who reaches its router may call its services: the same warning sign as listening
    beyond this host without TLS (a documentation address: no router answers there)."""
    assert make_manager(router=[f"tcp/127.0.0.1:{free_port()}"], lease_ms=1000).exposed() == []
    assert make_manager(router=["tcp/192.0.2.1:7447"], lease_ms=1000).exposed() == ["tcp/192.0.2.1:7447"]


SHARED = """<transformations><transformation><label>shared-{name}</label><source>transformations.generic:PeriodicSource</source>
  <params><param name="rate_hz" type="float">5</param></params><ports><port type="out">out</port></ports>
  <tags><tag port="out">Shared</tag></tags></transformation></transformations>"""


def test_a_manager_behind_a_router_finds_a_provider_it_never_heard_of(make_manager: Callable[..., Manager]) -> None:
    """A Zenoh client's liveliness query just after its liveliness subscriber on the same key
    expression finds nothing: the directory asked who offers a tag only after watching it, and a
    manager behind a router planned nothing ("nothing provides Shared"). It now asks before and
    after the watch."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    with Session(make_config(listen=[hub], mode="router")):
        m0 = make_manager("m0", router=[hub])
        m1 = make_manager("m1", router=[hub])
        m1.add_transformation(SHARED.format(name="m1"))
        # the offer is on its way once m0 could see it; nothing of m1 was read before the request
        wait_until(lambda: bool(m0.session.alive("@dyknow/offers/Shared/*/*", timeout_s=1.0)), "m0 to see m1's offer")
        assert "m1" not in m0.peers()
        key = m0.request("Shared")
        (request,) = m0.get_model().requests
        assert request.key == key and request.labels == ("shared-m1@m1",), request.labels
