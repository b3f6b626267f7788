"""TLS with mutual authentication and access control by role, enforced by Zenoh, over real links."""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from dyknow import AccessError, BindingError, Client, Manager, Message, PlanningError, ServiceError, UnitError, keys
from dyknow.access import ROLES, AccessControl, TlsFiles
from dyknow.certs import write_dev_certs
from dyknow.identity import Signer
from dyknow.security import Limits
from dyknow.testing import Sink
from dyknow.transport import Session, make_config
from tests.conftest import GENERIC_SPECS, CliProcess, end_process, free_port, run_cli, wait_until

NAMES = ["manager", "viewer", "operator", "admin", "stranger", "station", "robot", "router", "tuner"]
RELAY = """<transformation><label>extra-relay</label><source>transformations.generic:Relay</source>
  <ports><port type="in">in</port><port type="out">out</port></ports></transformation>"""


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("certs")
    write_dev_certs(folder, NAMES)
    return folder


def tls(certs: Path, name: str) -> TlsFiles:
    return TlsFiles(str(certs / "ca.pem"), str(certs / f"{name}.pem"), str(certs / f"{name}.key"))


@pytest.fixture
def secured(certs: Path, make_manager: Callable[..., Manager]) -> Manager:
    acl = AccessControl.from_dict({"roles": {"viewer": ["viewer"], "operator": ["operator"], "admin": ["admin"]}})
    manager = make_manager(listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=acl)
    manager.spawn("sink", "inbox", bindings={"in": "dyknow/ext/in"})
    manager.spawn("periodic-source", "ticks", params={"rate_hz": 100})
    return manager


@pytest.fixture
def client(secured: Manager, certs: Path) -> Iterator[Callable[[str], Client]]:
    opened: list[Client] = []

    def open_as(name: str) -> Client:
        c = Client(secured.name, connect=secured.endpoints, tls=tls(certs, name), timeout_s=1.5)
        opened.append(c)
        return c

    yield open_as
    for c in opened:
        c.close()


CALLS: list[tuple[str, str, Callable[[Client], Any]]] = [
    ("viewer", "get_model", lambda c: c.get_model()),
    ("viewer", "get_adaptations", lambda c: c.get_adaptations()),
    ("viewer", "get_config", lambda c: c.get_config("inbox")),
    ("viewer", "get_statistics", lambda c: c.get_statistics("inbox")),
    ("operator", "spawn", lambda c: c.spawn("relay", "r")),
    ("operator", "set_config", lambda c: c.set_config("inbox", {"in": "dyknow/ext/other"})),
    ("operator", "measure", lambda c: c.measure("battery", 0.5)),
    ("operator", "destroy", lambda c: c.destroy("ticks")),
    ("admin", "add_transformation", lambda c: c.add_transformation(RELAY)),
    ("admin", "remove_transformation", lambda c: c.remove_transformation("relay")),
]


@pytest.mark.parametrize("role", ROLES)
@pytest.mark.parametrize(("needs", "service", "call"), CALLS, ids=[c[1] for c in CALLS])
def test_each_role_against_each_service(client: Callable[[str], Client], role: str, needs: str, service: str, call: Callable[[Client], Any]) -> None:
    allowed = ROLES.index(role) >= ROLES.index(needs)
    c = client(role)
    if allowed:
        call(c)
    else:
        with pytest.raises(ServiceError, match=r"dropped the call to '\w+' without a reply: the manager's --acl does not let this client's certificate"):
            call(c)


def test_request_and_release_need_an_operator(secured: Manager, client: Callable[[str], Client]) -> None:
    with pytest.raises(ServiceError, match="without a reply"):
        client("viewer").request("Anything")
    with pytest.raises(PlanningError, match="nothing provides Anything"):
        client("operator").request("Anything")  # reaches the planner: refused for another reason
    with pytest.raises(ServiceError, match="without a reply"):
        client("viewer").release("dyknow/x/requests/Anything")
    with pytest.raises(UnitError, match="no request on key"):
        client("operator").release("dyknow/x/requests/Anything")


def test_no_role_or_no_certificate_reaches_nothing(secured: Manager, certs: Path) -> None:
    """A certificate of the CA without a role, or no certificate at all: not even the model."""
    with Client(secured.name, connect=secured.endpoints, tls=tls(certs, "stranger"), timeout_s=1.0) as c, pytest.raises(
        ServiceError, match=r"no answer from manager '\w+' at \S+: linked, but no manager is visible from here; expected a running manager"
    ):
        c.get_model()
    with pytest.raises(AccessError, match="is a TLS endpoint, and this client has no TLS files"):
        Client(secured.name, connect=secured.endpoints)
    plain = [e.replace("tls/", "tcp/") for e in secured.endpoints]
    with Client(secured.name, connect=plain, timeout_s=1.0) as c, pytest.raises(ServiceError, match="speaks TLS, and tcp/ connects without it"):
        c.get_model()


def test_a_certificate_from_another_ca_is_refused(secured: Manager, tmp_path: Path) -> None:
    write_dev_certs(tmp_path, ["admin"])  # the same name, another CA
    with Client(secured.name, connect=secured.endpoints, tls=tls(tmp_path, "admin"), timeout_s=1.0) as c, pytest.raises(ServiceError, match="is not signed by the CA of --tls-ca"):
        c.get_model()


def _publisher(certs: Path, name: str, endpoints: list[str]) -> Session:
    return Session(make_config(connect=endpoints, tls=tls(certs, name)))


@pytest.mark.parametrize(("role", "arrives"), [("operator", True), ("admin", True), ("viewer", False), ("stranger", False)])
def test_publishing_data_needs_an_operator(secured: Manager, certs: Path, role: str, arrives: bool) -> None:
    inbox = secured.unit("inbox")
    assert isinstance(inbox, Sink)
    with _publisher(certs, role, secured.endpoints) as session:
        publisher = session.declare_publisher("dyknow/ext/in")
        for i in range(50):
            publisher.put(Message({"i": i}, i, 0, 0, "dyknow/ext/in"))
            if inbox.messages:
                break
            threading.Event().wait(0.02)
        if arrives:
            inbox.wait_for(1)
        else:
            assert inbox.messages == []


@pytest.mark.parametrize(("role", "receives"), [("viewer", True), ("stranger", False)])
def test_subscribing_to_data_needs_a_viewer(secured: Manager, client: Callable[[str], Client], certs: Path, role: str, receives: bool) -> None:
    got = threading.Event()
    with Client(secured.name, connect=secured.endpoints, tls=tls(certs, role), timeout_s=1.0) as c, c.declare_subscriber(
        f"dyknow/{secured.name}/ticks/out", lambda msg: got.set()
    ):
        assert got.wait(3 if receives else 1) is receives


def test_acl_files_are_checked(tmp_path: Path) -> None:
    good = tmp_path / "acl.json5"
    good.write_text("{ roles: { viewer: ['a', 'b'], admin: ['c'] } }  // comments are fine")
    acl = AccessControl.load(good)
    assert acl.role_of("b") == "viewer" and acl.role_of("c") == "admin" and acl.role_of("z") is None
    config = acl.zenoh()
    assert config["default_permission"] == "deny" and [s["id"] for s in config["subjects"]] == ["viewer", "admin", "holder-0"]
    admin_rules = next(p for p in config["policies"] if p["subjects"] == ["admin"])["rules"]
    assert "viewer-calls" in admin_rules and "operator-calls" in admin_rules  # each role may what the ones before it may
    # the admin may request, so it holds: the tokens of its own clients only, everyone else's denied
    assert "operator-declares" in admin_rules and next(s for s in config["subjects"] if s["id"] == "holder-0")["cert_common_names"] == ["c"]
    holds = next(r for r in config["rules"] if r["id"] == "holder-0-holds")
    assert holds["key_exprs"] == [f"dyknow/*/*/*/holders/{keys.holder_scope('c')}$*"] and holds["messages"] == ["liveliness_token"]
    for text, message in [
        ("{ roles: { guest: ['a'] } }", "unknown role 'guest'; expected one of viewer, operator, admin"),
        ("{ roles: { viewer: 'a' } }", "roles.viewer: got 'a'; expected a list of certificate common names"),
        ("{ users: {} }", "the file must hold the field roles"),
        ("{ roles: ", "not JSON5"),
    ]:
        bad = tmp_path / "bad.json5"
        bad.write_text(text)
        with pytest.raises(AccessError, match=message):
            AccessControl.load(bad)


def test_tls_options_come_together(tmp_path: Path, certs: Path) -> None:
    assert TlsFiles.from_options(None, None, None) is None
    with pytest.raises(AccessError, match="--tls-key missing"):
        TlsFiles.from_options(str(certs / "ca.pem"), str(certs / "viewer.pem"), None)
    with pytest.raises(AccessError, match="--tls-cert: '.*nope.pem' is not a readable file"):
        TlsFiles.from_options(str(certs / "ca.pem"), str(tmp_path / "nope.pem"), str(certs / "viewer.key"))


def test_a_manager_listening_beyond_loopback_without_tls_is_exposed(make_manager: Callable[..., Manager]) -> None:
    assert make_manager().exposed() == []
    exposed = make_manager(listen=[f"tcp/0.0.0.0:{free_port()}"]).exposed()
    assert exposed and all(not e.startswith("tcp/127.") for e in exposed)


def _tls_args(certs: Path, name: str) -> list[str]:
    return ["--tls-ca", str(certs / "ca.pem"), "--tls-cert", str(certs / f"{name}.pem"), "--tls-key", str(certs / f"{name}.key")]


@pytest.mark.process
def test_the_command_line_speaks_tls_and_roles(certs: Path, tmp_path: Path, cli_process: Callable[..., CliProcess]) -> None:
    acl = tmp_path / "acl.json5"
    acl.write_text("{ roles: { viewer: ['viewer'], operator: ['operator'] } }")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    manager = cli_process("manager", "--name", "secure", "--listen", endpoint, "--specs", str(GENERIC_SPECS), "--acl", str(acl), "--json", *_tls_args(certs, "manager"))
    assert manager.line()["endpoints"] == [endpoint]
    conn = ["--manager", "secure", "--connect", endpoint, "--timeout", "2"]
    viewer = run_cli("model", "--json", *conn, *_tls_args(certs, "viewer"))
    assert viewer.returncode == 0 and json.loads(viewer.stdout)["manager"] == "secure"
    refused = run_cli("spawn", "relay", "r", *conn, *_tls_args(certs, "viewer"))
    assert refused.returncode == 1 and "dropped the call to 'spawn' without a reply" in refused.stderr
    assert run_cli("spawn", "relay", "r", *conn, *_tls_args(certs, "operator")).returncode == 0
    no_cert = run_cli("model", *conn)
    assert no_cert.returncode == 1 and "is a TLS endpoint, and this client has no TLS files" in no_cert.stderr
    partial = run_cli("model", *conn, "--tls-ca", str(certs / "ca.pem"))
    assert partial.returncode == 1 and "--tls-cert, --tls-key missing" in partial.stderr
    assert manager.stop() == 0


@pytest.mark.process
def test_a_manager_exposed_without_tls_warns(cli_process: Callable[..., CliProcess]) -> None:
    manager = cli_process("manager", "--name", "open", "--listen", f"tcp/0.0.0.0:{free_port()}", "--specs", str(GENERIC_SPECS), "--json")
    assert manager.line()["event"] == "ready"
    assert manager.stop() == 0
    assert manager.proc.stderr is not None
    assert "dyknow: warning: listening beyond this host without TLS" in manager.proc.stderr.read()


@pytest.mark.parametrize("station_role", ["manager", "operator", "viewer"])
def test_managers_federate_over_tls_with_the_manager_role(certs: Path, make_manager: Callable[..., Manager], station_role: str) -> None:
    """Managers of one system give each other the manager role: the station spawns the robot's
    camera over mutual TLS. As an operator the station may still spawn there, but the robot does
    not take it for a manager (only the manager role announces, serves and summarises); as a mere
    viewer it may not spawn either."""
    from dyknow.errors import DyKnowError
    from dyknow.testing import SCENARIO_HOSTS
    from tests.conftest import REPO, wait_until

    ontology = [REPO / "specs" / "dyknow.ttl"]
    endpoint = f"tls/127.0.0.1:{free_port()}"
    station_acl = AccessControl.from_dict({"roles": {"manager": ["robot"]}})
    robot_acl = AccessControl.from_dict({"roles": {station_role: ["station"]}})
    station = make_manager("station", specs=[SCENARIO_HOSTS["station"]], ontology=ontology, listen=[endpoint], tls=tls(certs, "station"), acl=station_acl)
    robot = make_manager("robot", specs=[SCENARIO_HOSTS["robot"]], ontology=ontology, listen=[f"tls/127.0.0.1:{free_port()}"], connect=[endpoint],
                         tls=tls(certs, "robot"), acl=robot_acl)  # fmt: skip
    wait_until(lambda: "robot" in station.reachable(), "the station to know the robot over TLS")
    if station_role == "manager":
        wait_until(lambda: "station" in robot.reachable(), "the robot to know the station")
    else:
        assert "station" not in robot.reachable()  # it cannot pose as a manager there
    if station_role == "viewer":
        with pytest.raises(DyKnowError, match="manager 'robot' dropped the call to 'spawn'"):
            station.request("BallTrack(field)")
        assert robot.units() == [] and station.get_model().requests == ()
        return
    key = station.request("BallTrack(field)")
    assert [u.label for u in robot.units()] == ["robot-camera"]
    station.spawn("consumer", "consumer", bindings={"in": key})
    sink = station.unit("consumer")
    assert isinstance(sink, Sink)
    sink.wait_for(3)


# ---------------------------------------------------------------------- a caller's rights, end to end


@pytest.fixture
def pair(certs: Path, make_manager: Callable[..., Manager]) -> tuple[Manager, Manager]:
    """Two managers with TLS and roles, the robot connected to the station. On the robot,
    'operator' is an operator and 'viewer' a viewer; on the station, 'viewer' is a viewer,
    'admin' an admin, and 'operator' has no role."""
    station_acl = AccessControl.from_dict({"roles": {"viewer": ["viewer"], "admin": ["admin"], "manager": ["robot"]}})
    robot_acl = AccessControl.from_dict({"roles": {"viewer": ["viewer"], "operator": ["operator"], "admin": ["admin"], "manager": ["station"]}})
    endpoint = f"tls/127.0.0.1:{free_port()}"
    station = make_manager("station", listen=[endpoint], tls=tls(certs, "station"), acl=station_acl)
    robot = make_manager("robot", listen=[f"tls/127.0.0.1:{free_port()}"], connect=[endpoint], tls=tls(certs, "robot"), acl=robot_acl)
    from tests.conftest import wait_until

    wait_until(lambda: "robot" in station.reachable() and "station" in robot.reachable(), "the two managers to know each other")
    return station, robot


def test_a_call_through_another_manager_keeps_its_callers_rights(pair: tuple[Manager, Manager], certs: Path) -> None:
    """A client connected only to the robot calls the station: the robot carries the call, and
    the station judges it by the caller's own signature, not by the robot's certificate (which
    has the manager role there). An operator of the robot with no role on the station gets
    nothing there, not even the model; the station's viewer reads but may not spawn; its admin
    keeps every right of an admin."""
    station, robot = pair
    via_robot = {"connect": robot.endpoints, "timeout_s": 3.0}
    with Client("station", tls=tls(certs, "operator"), **via_robot) as outsider:  # type: ignore[arg-type]
        assert outsider.call_manager("robot", "get_model", {})["manager"] == "robot"  # its rights on the robot hold
        with pytest.raises(AccessError, match="manager 'station': 'operator', which has no role here, may not call get_model"):
            outsider.get_model()
        with pytest.raises(AccessError, match="may not call spawn; expected a caller whose certificate has the role operator or admin or manager"):
            outsider.spawn("relay", "planted", protected=True)
    with Client("station", tls=tls(certs, "viewer"), **via_robot) as viewer:  # type: ignore[arg-type]
        assert viewer.get_model()["manager"] == "station"
        with pytest.raises(ServiceError, match="without a reply"):
            viewer.spawn("relay", "planted")  # a viewer on the robot too: the robot does not even carry it
    with Client("station", tls=tls(certs, "admin"), **via_robot) as admin:  # type: ignore[arg-type]
        assert admin.add_transformation(RELAY) == ["extra-relay"]
        admin.spawn("extra-relay", "kept", protected=True)
        admin.destroy("kept", force=True)
    assert station.units() == []
    with pytest.raises(AccessError, match="this client has no TLS files"):
        Client("station", connect=robot.endpoints, timeout_s=1.0)  # no certificate: no TLS link at all


@pytest.mark.process
def test_a_call_through_a_router_keeps_its_callers_rights(certs: Path, make_manager: Callable[..., Manager], cli_process: Callable[..., CliProcess], tmp_path: Path) -> None:
    """Clients and the manager meet at a router: the manager sees every call come by the
    router's link, and still judges each by its caller's signature against its own roles. The
    router's file is wider than the station's here ('stranger' is an operator there): the router
    carries the stranger's calls, and the station refuses them."""
    router_acl = tmp_path / "router.json5"
    router_acl.write_text("{ roles: { viewer: ['viewer'], operator: ['operator', 'stranger'], manager: ['station'], router: ['router'] } }")
    station_acl = AccessControl.from_dict({"roles": {"viewer": ["viewer"], "operator": ["operator"], "router": ["router"]}})
    port = free_port()
    router = cli_process("router", "--listen", f"tls/127.0.0.1:{port}", "--acl", str(router_acl), "--json", *_tls_args(certs, "router"))
    assert router.line()["event"] == "ready"
    hub = [f"tls/127.0.0.1:{port}"]
    make_manager("station", listen=[f"tls/127.0.0.1:{free_port()}"], connect=hub, tls=tls(certs, "station"), acl=station_acl)
    with Client("station", connect=hub, tls=tls(certs, "viewer"), timeout_s=5.0) as viewer:
        assert viewer.get_model()["manager"] == "station"
        with pytest.raises(ServiceError, match="without a reply"):
            viewer.spawn("relay", "r")  # the router itself does not carry a viewer's spawn
    with Client("station", connect=hub, tls=tls(certs, "operator"), timeout_s=5.0) as operator:
        assert operator.spawn("relay", "r")["state"] == "running"
    with Client("station", connect=hub, tls=tls(certs, "stranger"), timeout_s=5.0) as stranger:
        with pytest.raises(AccessError, match="manager 'station': 'stranger', which has no role here, may not call get_model"):
            stranger.get_model()
        with pytest.raises(AccessError, match="'stranger', which has no role here, may not call spawn"):
            stranger.spawn("relay", "planted")
    with Client("station", connect=hub, tls=tls(certs, "admin"), timeout_s=1.0) as nobody, pytest.raises(ServiceError, match="no answer"):
        nobody.get_model()  # no role at the router: it carries nothing of it
    assert router.stop() == 0


def test_unsigned_calls_are_refused_by_a_manager_with_roles(secured: Manager, certs: Path) -> None:
    """A plain Zenoh caller with an admin's certificate but no signature gets a clear refusal."""
    with Session(make_config(connect=secured.endpoints, tls=tls(certs, "admin"))) as session, pytest.raises(
        ServiceError, match="the call is not signed, and this manager checks every caller's identity"
    ):
        session.call(f"@dyknow/{secured.name}/get_model", b"{}", timeout_s=5.0, what="get_model")


def test_a_recorded_call_replayed_after_a_flood_is_refused(secured: Manager, certs: Path) -> None:
    """The attack of an on-path router: it records an admin's signed spawn as it passes, floods
    the manager with signed calls of its own, and replays the recording. The replay is refused
    as such and the unit does not come back; the flood's caller is remembered apart (its role
    was checked first)."""
    admin = Signer(tls(certs, "admin"))
    payload = json.dumps({"label": "relay", "name": "replayed"}).encode()
    recorded: list[bytes] = []

    def record(key: str, body: bytes) -> bytes:
        recorded.append(admin.sign(key, body))
        return recorded[-1]

    key = f"@dyknow/{secured.name}/spawn"
    with Session(make_config(connect=secured.endpoints, tls=tls(certs, "admin"))) as session:
        session.call(key, payload, timeout_s=5.0, what="spawn", sign=record)
        assert secured.has_unit("replayed")
        secured.destroy("replayed")
        with Client(secured.name, connect=secured.endpoints, tls=tls(certs, "viewer"), timeout_s=5.0) as flood:
            for _ in range(300):
                flood.get_adaptations()
        with pytest.raises(ServiceError, match="a replay of one already received"):
            session.call(key, payload, timeout_s=5.0, what="spawn", sign=lambda k, b: recorded[0])
    assert not secured.has_unit("replayed")


def test_calls_signed_ahead_do_not_lock_out_the_callers_honest_calls(certs: Path, make_manager: Callable[..., Manager]) -> None:
    """Issue 51, item 8, over real links: one holder of the viewer's certificate signs calls 290 s
    ahead (within the 300 s the manager takes) until their part of its ledger is full. Before,
    the next one raised the viewer's floor into the future and every honest call of the viewer
    was refused for minutes; now that call is refused, naming the clock, and the honest client of
    the same certificate is answered, for more calls than the ledger holds. A recorded call
    signed ahead is still refused as a replay."""
    acl = AccessControl.from_dict({"roles": {"viewer": ["viewer"], "admin": ["admin"]}})
    limits = Limits(max_caller_calls=100, max_caller_calls_ahead=100)
    manager = make_manager(listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=acl, limits=limits)
    attacker = Signer(tls(certs, "viewer"))
    signed: list[bytes] = []

    def ahead(key: str, body: bytes) -> bytes:
        signed.append(attacker.sign(key, body, time_ns=time.time_ns() + int(290e9)))
        return signed[-1]

    key = f"@dyknow/{manager.name}/get_adaptations"
    with Session(make_config(connect=manager.endpoints, tls=tls(certs, "viewer"))) as session:
        for _ in range(100):
            session.call(key, b"{}", timeout_s=5.0, what="get_adaptations", sign=ahead)
        with pytest.raises(ServiceError, match=r"signed \+2\d\d\.\d+ s ahead of this manager's clock, and the manager already remembers 100"):
            session.call(key, b"{}", timeout_s=5.0, what="get_adaptations", sign=ahead)
        with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "viewer"), timeout_s=5.0) as honest:
            for _ in range(150):  # more than the ledger holds of calls signed on time
                assert isinstance(honest.get_adaptations(), list)
        with pytest.raises(ServiceError, match="a replay of one already received"):
            session.call(key, b"{}", timeout_s=5.0, what="get_adaptations", sign=lambda k, b: signed[0])


# ---------------------------------------------------------------------- only a manager speaks for itself


def test_only_a_manager_serves_announces_and_summarises_under_its_name(pair: tuple[Manager, Manager], certs: Path) -> None:
    """An operator of the robot declares the station's own services, a liveliness token and a
    summary for a manager 'ghost', and a summary in the station's name: the robot (the manager
    of the operator's link) drops them all, so the admin's calls reach the real station (3 of 3),
    a viewer reads the real model (5 of 5), and no ghost is listed. The robot, a manager, may not
    serve in the station's name either: the station drops that declaration, so the station's
    own callers are answered by the station (the robot's own clients trust the robot: see
    docs/howto/security.md on what a compromised manager can do)."""
    from tests.conftest import wait_until

    station, robot = pair
    forged = json.dumps({"manager": "station", "units": [], "forged": True}).encode()
    stolen: dict[str, list[bytes]] = {"operator": [], "robot": []}

    def impostor(who: str) -> Callable[[str, bytes], tuple[bool, bytes]]:
        def answer(key: str, payload: bytes) -> tuple[bool, bytes]:
            stolen[who].append(payload)
            return True, forged if key.endswith(("get_model", "get_adaptations")) else b'{"labels": ["forged"]}'

        return answer

    with Session(make_config(connect=robot.endpoints, tls=tls(certs, "operator"))) as attacker:
        held = [
            attacker.declare_queryable("@dyknow/station/get_model", impostor("operator")),
            attacker.declare_queryable("@dyknow/station/add_transformation", impostor("operator")),
            attacker.declare_liveliness_token("@dyknow/ghost"),
            robot.session.declare_queryable("@dyknow/station/get_adaptations", impostor("robot")),
        ]
        ghost = {"manager": "ghost", "host": "x", "version": 1, "units": []}
        for name in ("ghost", "station"):
            attacker.put(f"@dyknow/{name}/summary", json.dumps({**ghost, "manager": name}))
        with Client("station", connect=robot.endpoints, tls=tls(certs, "admin"), timeout_s=3.0) as admin:
            for i in range(3):
                assert admin.add_transformation(RELAY.replace("extra-relay", f"added-{i}")) == [f"added-{i}"]
        with Client("station", connect=robot.endpoints, tls=tls(certs, "viewer"), timeout_s=3.0) as viewer:
            for _ in range(5):
                assert "forged" not in viewer.get_model()
        with Client("station", connect=station.endpoints, tls=tls(certs, "viewer"), timeout_s=3.0) as local:
            for _ in range(5):
                assert local.get_adaptations() == []
        for entity in held:
            entity.undeclare()
    assert {f"added-{i}" for i in range(3)} <= set(station.library.labels())
    assert stolen == {"operator": [], "robot": []}
    wait_until(lambda: "robot" in station.reachable(), "the station to list the robot")
    assert station.reachable() == {"robot"} and robot.reachable() == {"station"}


def test_a_port_may_not_bind_to_a_service_or_admin_key(manager: Manager) -> None:
    """An output bound to @dyknow/ghost would hold a fake manager's token; @/ is Zenoh's admin
    space. Refused at spawn and at set_config, locally and through the service, naming the port."""
    with pytest.raises(BindingError, match=r"port 'out' of unit 'r': '@dyknow/ghost' has a chunk starting with '@'"):
        manager.spawn("relay", "r", bindings={"out": "@dyknow/ghost"})
    manager.spawn("relay", "r")
    with Client(manager.name, connect=manager.endpoints) as client:
        for port, key in [("out", "@dyknow/ghost"), ("out", "x/@/y"), ("in", "@dyknow/**"), ("in", "@/**")]:
            with pytest.raises(BindingError, match=f"unit 'r' {'output' if port == 'out' else 'input'} port '{port}'"):
                client.set_config("r", {port: key})
    assert manager.get_config("r") == {"in": f"dyknow/{manager.name}/r/in", "out": f"dyknow/{manager.name}/r/out"}


def test_a_protected_unit_is_destroyed_only_by_an_admins_force(secured: Manager, client: Callable[[str], Client]) -> None:
    """A protected unit an operator spawned could be removed by nobody, an admin included, until
    a restart: an admin's destroy with force removes it; an operator's force is refused, naming
    the role it needs; without roles (local use) force is anyone's."""
    operator, admin = client("operator"), client("admin")
    operator.spawn("relay", "planted", protected=True)
    with pytest.raises(UnitError, match="the unit is protected .* so it cannot be destroyed without force"):
        admin.destroy("planted")
    with pytest.raises(AccessError, match=r"'operator', with the role operator, may not destroy a protected unit; expected an admin"):
        operator.destroy("planted", force=True)
    assert secured.has_unit("planted")
    admin.destroy("planted", force=True)
    assert not secured.has_unit("planted")
    operator.destroy("ticks", force=True)  # not protected: force changes nothing for it


def test_without_roles_force_destroys_a_protected_unit(manager: Manager) -> None:
    manager.spawn("relay", "kept", protected=True)
    with Client(manager.name, connect=manager.endpoints) as anyone:
        with pytest.raises(UnitError, match="without force"):
            anyone.destroy("kept")
        anyone.destroy("kept", force=True)
    assert not manager.has_unit("kept")


# ---------------------------------------------------------------------------- roles the file defines

REQUESTER_ACL = """{
  roles: { requester: ["operator"], viewer: ["viewer"] },
  define: {
    // may read and request streams, may not change units
    requester: { like: "viewer", calls: ["request", "release"] },
  },
}
"""


def test_a_defined_role_may_request_and_not_destroy(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """Transport and manager alike: the requester reads, requests and releases; spawn and destroy
    are dropped at its link (and refused by the manager's own check, whatever carries them)."""
    acl_file = tmp_path / "acl.json5"
    acl_file.write_text(REQUESTER_ACL)
    acl = AccessControl.load(acl_file)
    assert acl.role_of("operator") == "requester" and acl.may_call("operator", "request") and not acl.may_call("operator", "destroy")
    manager = make_manager(listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=acl)
    manager.spawn("periodic-source", "ticks")
    with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "operator"), timeout_s=2.0) as requester:
        assert [u["name"] for u in requester.get_model()["units"]] == ["ticks"]
        with pytest.raises(PlanningError, match="nothing provides Anything"):
            requester.request("Anything")  # it reached the planner
        with pytest.raises(UnitError, match="no request on key"):
            requester.release("dyknow/x/requests/Anything")
        for refused in (lambda: requester.destroy("ticks"), lambda: requester.spawn("relay", "r")):
            with pytest.raises(ServiceError, match="without a reply"):
                refused()
    assert [u.name for u in manager.units()] == ["ticks"]


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ('{ roles: { requester: ["a"] } }', r"acl.json5:1: roles.requester: unknown role 'requester'; expected one of viewer, operator"),
        ('{ roles: {},\n  define: { r: { like: "veiwer" } } }', r"acl.json5:2: define.r.like: like 'veiwer'; expected one of the built-in roles viewer, operator, admin \(did you mean 'viewer'\?\)"),
        ('{ roles: {},\n  define: {\n    r: { calls: ["get_model", "destory"] } } }', r"acl.json5:3: define.r.calls\[1\]: unknown service 'destory'; expected one of .* \(did you mean 'destroy'\?\)"),
        ('{ roles: {}, define: { r: { publish: ["@dyknow/x"] } } }', r"acl.json5:1: define.r.publish\[0\]: '@dyknow/x' is not a key expression under dyknow/"),
        ('{ roles: {}, define: { admin: { calls: [] } } }', r"define.admin: 'admin' is a built-in role"),
        ('{ roles: {}, define: { r: { cals: [] } } }', r"define.r: unknown field 'cals' \(did you mean 'calls'\?\)"),
        ('{ roles: {\n  admin: ["laptop"]\n  viewer: ["x"] } }', r"acl.json5:3: not JSON5: Unexpected \"v\" at column 3"),  # a syntax error: the file's line, not <string>
    ],
)  # fmt: skip
def test_a_bad_definition_is_located(tmp_path: Path, text: str, said: str) -> None:
    path = tmp_path / "acl.json5"
    path.write_text(text)
    with pytest.raises(AccessError, match=said):
        AccessControl.load(path)


def test_the_docs_acl_files_are_valid() -> None:
    """Every json5 block of the security guide is an ACL file that loads; its own role reads and requests."""
    import json5

    from tests.conftest import REPO

    blocks = re.findall(r"```json5\n(.*?)```", (REPO / "docs" / "howto" / "security.md").read_text(), re.DOTALL)
    acls = [AccessControl.from_dict(json5.loads(block)) for block in blocks]
    defined = next(a for a in acls if a.defined)
    assert defined.may_call("robot-ui", "request") and defined.may_call("robot-ui", "get_model")
    assert not defined.may_call("robot-ui", "destroy") and not defined.may_call("robot-ui", "set_config", unit=True)


# ---------------------------------------------------------------------- what is whose, and who may read what

OWNERS_ACL = """{
  roles: { admin: ["admin"], operator: ["operator"], requester: ["viewer"], watcher: ["stranger"] },
  define: {
    requester: { like: "viewer", calls: ["request", "release", "monitor"] },
    // may ask for monitors and read their verdicts, and nothing else
    watcher: { calls: ["monitor", "get_model", "release"], subscribe: ["dyknow/*/monitors/**"] },
  },
}
"""
SECRET = """<transformation><label>vault</label><source>transformations.generic:PeriodicSource</source>
  <params><param name="rate_hz" type="float">50</param></params>
  <ports><port type="out">out</port></ports><tags><tag port="out">Secret(vault)</tag></tags></transformation>"""


@pytest.fixture
def owners(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> Manager:
    (tmp_path / "acl.json5").write_text(OWNERS_ACL)
    (tmp_path / "vault.xml").write_text(SECRET)
    return make_manager(
        listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=AccessControl.load(tmp_path / "acl.json5"),
        specs=[GENERIC_SPECS, tmp_path / "vault.xml"], client_grace_s=0.2,
    )  # fmt: skip


def _held(manager: Manager, tag: str) -> dict[str, Any] | None:
    return next((r.to_dict() for r in manager.requests() if r.tag == tag), None)


def test_a_caller_releases_only_what_it_requested(owners: Manager, certs: Path) -> None:
    """The attack of the report: a requester releases an admin's held request (refused; the
    stream keeps its units), an operator adds a requirement to it and releases its own
    reference (the requirement goes with it); forcing is an admin's."""
    with ExitStack() as stack:
        admin, operator, requester = (
            stack.enter_context(Client(owners.name, connect=owners.endpoints, tls=tls(certs, n), timeout_s=5.0)) for n in ("admin", "operator", "viewer")
        )  # fmt: skip
        key = admin.request("Ticks")
        units = {u.name for u in owners.units()}
        with pytest.raises(AccessError, match=r"'viewer' holds no reference to the request on .*\(its references: 'admin' \(client [0-9a-f]+\)\)"):
            requester.release(key)
        with pytest.raises(AccessError, match=r"'viewer', with the role requester, may not force a release"):
            requester.release(key, force=True)
        operator.request("Ticks", require=["Ticks.value < 0"])
        assert _held(owners, "Ticks")["requirements"] == ["Ticks.value < 0"]  # type: ignore[index]
        assert operator.release(key) == 1
        held = _held(owners, "Ticks")
        assert held is not None and held["references"] == 1 and held["requirements"] == [] and {u.name for u in owners.units()} == units
        operator.request("Ticks", keep=True)
        assert admin.release(key, force=True) == 0
    assert _held(owners, "Ticks") is None


def test_a_requesters_held_request_stays_while_its_client_does(owners: Manager, certs: Path) -> None:
    """A role of the file's own that may request (like a viewer) may also declare its holder
    token, so the manager sees its client there and keeps what it holds (with a grace of 0.2 s
    it was released within 6 s while the client was connected)."""
    with Client(owners.name, connect=owners.endpoints, tls=tls(certs, "viewer"), timeout_s=5.0) as requester:
        requester.request("Ticks")
        wait_until(lambda: (_held(owners, "Ticks") or {}).get("absent") == [], "the manager to see the requester's client")
        assert list(_held(owners, "Ticks")["holders"].values()) == [1]  # type: ignore[index]
    wait_until(lambda: _held(owners, "Ticks") is None, "the closed requester's request released")


def test_a_client_cannot_keep_another_clients_request_alive(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """The attack of issue 51: a requester reads the holders of an operator's request from the
    model and, once the operator's client is gone, declares that client's holder token itself,
    within the grace, to keep the request alive. The ACL lets a certificate declare the tokens
    of its own clients only (their ids start with its scope), so the token is dropped at the
    requester's link and the request ends after the grace; and the service takes a client id
    only from the certificate whose scope it carries. The requester's own client still holds."""
    (tmp_path / "acl.json5").write_text(OWNERS_ACL)
    manager = make_manager(
        listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=AccessControl.load(tmp_path / "acl.json5"),
        specs=[GENERIC_SPECS], client_grace_s=3.0,
    )  # fmt: skip
    with ExitStack() as stack:
        requester = stack.enter_context(Client(manager.name, connect=manager.endpoints, tls=tls(certs, "viewer"), timeout_s=5.0))
        attacker = stack.enter_context(Session(make_config(connect=manager.endpoints, tls=tls(certs, "viewer"))))
        with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "operator"), timeout_s=5.0) as victim:
            key = victim.request("Ticks")
            wait_until(lambda: (_held(manager, "Ticks") or {}).get("absent") == [], "the manager to see the operator's client")
            (holder,) = _held(manager, "Ticks")["holders"]  # type: ignore[index]
            assert holder.startswith(keys.holder_scope("operator"))
        wait_until(lambda: (_held(manager, "Ticks") or {}).get("absent") == [holder], "the manager to see the operator's client gone")
        stack.enter_context(attacker.declare_liveliness_token(keys.holder_token(key, holder)))
        wait_until(lambda: _held(manager, "Ticks") is None, "the gone operator's request released, whoever declared its token", timeout_s=15)
        with pytest.raises(AccessError, match=rf"'viewer' may not hold through the client id '{holder}': .* start with its scope, {keys.holder_scope('viewer')} for 'viewer'"):
            requester.call_manager(manager.name, "request", {"tag": "Ticks", "holder": holder})
        assert manager.requests() == [] and manager.units() == []
        key = requester.request("Ticks")
        wait_until(lambda: (_held(manager, "Ticks") or {}).get("absent") == [], "the manager to see the requester's own client")
        assert requester.release(key) == 0


def test_one_caller_cannot_fill_a_shared_request(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """The attack of issue 51: a requester takes reference after reference on an admin's
    request, each with a client id of its own choosing, to fill it for everyone else. Its share
    is bounded (here 20 references, kept or held): past it, its own are refused naming the
    bound, and the others, the admin included, still request the stream."""
    (tmp_path / "acl.json5").write_text(OWNERS_ACL)
    manager = make_manager(
        listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=AccessControl.load(tmp_path / "acl.json5"),
        specs=[GENERIC_SPECS], limits=Limits(max_references_per_caller=20), client_grace_s=60.0,
    )  # fmt: skip
    with ExitStack() as stack:
        admin, operator, requester = (
            stack.enter_context(Client(manager.name, connect=manager.endpoints, tls=tls(certs, n), timeout_s=5.0)) for n in ("admin", "operator", "viewer")
        )  # fmt: skip
        key = admin.request("Ticks")
        scope = keys.holder_scope("viewer")
        refused = None
        for i in range(1000):
            try:
                requester.call_manager(manager.name, "request", {"tag": "Ticks", "holder": f"{scope}{i:016x}"})
            except AccessError as exc:
                refused = exc
                break
        assert refused is not None, "a thousand references of one caller"
        assert re.search(r"'viewer' \(client [0-9a-f]{32}\) holds 20 references to the request on '.*' already, its most; expected at most 20 references per caller", str(refused))
        with pytest.raises(AccessError, match="'viewer' holds 20 references"):
            requester.request("Ticks", keep=True)  # kept ones count too
        assert operator.request("Ticks") == key and admin.request("Ticks") == key
        with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "admin"), timeout_s=5.0) as another:
            assert another.request("Ticks", keep=True) == key
        held = _held(manager, "Ticks")
        assert held is not None and held["references"] == 1 + 20 + 3


def test_a_monitor_reads_only_what_its_caller_may_read(owners: Manager, certs: Path) -> None:
    """A role that may ask for monitors and read only their verdicts cannot learn a secret
    through threshold monitors: the term's stream is one it may not read, so the monitor is
    refused before anything is planned (the secret's source is not started); nor can a
    requester require a formula over it. What it may read, it may monitor."""
    with Client(owners.name, connect=owners.endpoints, tls=tls(certs, "stranger"), timeout_s=5.0) as watcher:
        for threshold in (1000, 5000, 4711):
            with pytest.raises(AccessError, match=r"'stranger' may not read Secret\(vault\) \(its stream is on 'dyknow/.*/requests/Secret\(vault\)'\)"):
                watcher.monitor(f"Secret(vault).pin > {threshold}")
        with pytest.raises(AccessError, match="may not read Ticks"):
            watcher.monitor("Ticks.value > 0")
    assert owners.units() == [] and owners.requests() == [] and owners.monitors() == []
    with Client(owners.name, connect=owners.endpoints, tls=tls(certs, "viewer"), timeout_s=5.0) as requester:
        key = requester.monitor("Secret(vault).pin > 4711")  # a requester (like a viewer) may read all data
        assert [m.key for m in owners.monitors()] == [key]
        assert requester.release(key) == 0
    assert owners.units() == []


def test_a_bound_term_reads_only_what_its_caller_may_read(owners: Manager, certs: Path) -> None:
    """A term bound to a key (dyknow.reasoning.bindings) needs the caller's right to subscribe to
    it; one bound to a ROS 2 topic, which the manager's node subscribes to for it, the right to
    spawn. Refused before anything is started."""
    with Client(owners.name, connect=owners.endpoints, tls=tls(certs, "stranger"), timeout_s=5.0) as watcher:
        with pytest.raises(AccessError, match=r"'stranger' may not read 'dyknow/vault/pin', so it may not bind Pin\(vault\) to it"):
            watcher.monitor("Pin(vault) > 4711", bindings={"Pin(vault)": "dyknow/vault/pin"})
    with Client(owners.name, connect=owners.endpoints, tls=tls(certs, "viewer"), timeout_s=5.0) as requester:
        with pytest.raises(AccessError, match=r"'viewer' may not bind Pin\(vault\) to the ROS 2 topic 'ros2:/vault/pin'"):
            requester.monitor("Pin(vault) > 4711", bindings={"Pin(vault)": "ros2:/vault/pin"})
        assert owners.units() == [] and owners.monitors() == []
        key = requester.monitor("Pin(vault) > 4711", bindings={"Pin(vault)": "dyknow/vault/pin"})  # a viewer may read all data
        assert [m.bound for m in owners.monitors()] == [{"Pin(vault)": "dyknow/vault/pin"}]
        assert requester.release(key) == 0
    assert owners.units() == []


def test_a_requirement_reads_only_what_its_caller_may_read(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """A requester allowed to read one request's stream requires a formula over the secret:
    refused, and nothing is planned for it."""
    (tmp_path / "acl.json5").write_text(
        '{ roles: { limited: ["operator"] }, define: { limited: { calls: ["request", "release"], subscribe: ["dyknow/*/requests/Ticks"] } } }'
    )
    (tmp_path / "vault.xml").write_text(SECRET)
    manager = make_manager(
        listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=AccessControl.load(tmp_path / "acl.json5"),
        specs=[GENERIC_SPECS, tmp_path / "vault.xml"],
    )  # fmt: skip
    with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "operator"), timeout_s=5.0) as limited:
        with pytest.raises(AccessError, match=r"'operator' may not read Secret\(vault\)"):
            limited.request("Ticks", require=["Secret(vault).pin > 4711"])
        assert manager.units() == [] and manager.requests() == []
        with pytest.raises(AccessError, match=r"may not read Secret\(vault\)"):
            limited.request("Secret(vault)")
        key = limited.request("Ticks", require=["Ticks.value >= 0"])
        assert _held(manager, "Ticks")["requirements"] == ["Ticks.value >= 0"]  # type: ignore[index]
        assert limited.release(key) == 0


@pytest.mark.process
def test_a_link_lost_mid_call_is_not_read_as_the_acl_refusing(certs: Path, tmp_path: Path) -> None:
    """A manager with --acl stops mid-call (SIGKILL: its links close at once): the admin's call
    fails saying the link closed, or the manager went, never that the ACL refused the admin, which
    would lead an operator to widen the ACL (issue 43). The ACL's own refusal still says so."""
    import subprocess
    import sys

    from tests.conftest import REPO, UNIT_SPECS, subprocess_env

    acl = tmp_path / "acl.json5"
    acl.write_text('{ roles: { admin: ["admin"], viewer: ["viewer"] } }')
    endpoint = f"tls/127.0.0.1:{free_port()}"
    files = ["--tls-ca", str(certs / "ca.pem"), "--tls-cert", str(certs / "manager.pem"), "--tls-key", str(certs / "manager.key")]
    argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", "secure", "--listen", endpoint, "--specs", str(UNIT_SPECS),
            "--acl", str(acl), "--json", *files]  # fmt: skip
    env = {**subprocess_env(), "DYKNOW_LOG": "INFO"}  # it says "spawn NAME" as a spawn call comes in
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
    said: list[str] = []
    threading.Thread(target=lambda: said.extend(proc.stderr or []), daemon=True).start()
    try:
        assert proc.stdout is not None and '"ready"' in proc.stdout.readline()
        with Client("secure", connect=[endpoint], tls=tls(certs, "viewer"), timeout_s=10) as viewer:
            with pytest.raises(ServiceError, match="the manager's --acl does not let this client's certificate") as refused:
                viewer.spawn("slow-setup", "nope")
            assert refused.value.details["reason"] == "dropped"
        with Client("secure", connect=[endpoint], tls=tls(certs, "admin"), timeout_s=30) as admin:
            failed: list[BaseException] = []

            def call() -> None:
                try:
                    admin.spawn("slow-setup", "slow", params={"setup_s": 60})
                except BaseException as exc:  # noqa: BLE001 - the test looks at it
                    failed.append(exc)

            calling = threading.Thread(target=call)
            calling.start()
            wait_until(lambda: any("spawn slow " in line for line in said), "the spawn to be under way")
            proc.kill()
            calling.join(60)
            assert len(failed) == 1 and isinstance(failed[0], ServiceError), failed
            message = str(failed[0])
            assert "acl" not in message.lower() and failed[0].details["reason"] in ("link-closed", "gone"), message
    finally:
        end_process(proc)


CHECKED = """<transformation><label>checked-ticks</label><source>transformations.generic:PeriodicSource</source>
  <params><param name="rate_hz" type="float">50</param></params>
  <ports><port type="out">out</port></ports><tags><tag port="out">Checked(ticks)</tag></tags>
  <requirements><requirement>Checked(ticks).value &gt;= 0</requirement></requirements></transformation>"""


def test_one_caller_cannot_take_the_whole_monitor_budget(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """Issue 51, item 4: an operator took all 20,000 monitor nodes in 1.9 s; everyone's monitors
    and requirements were then refused, and the specs' requirements went unwatched. With TLS and
    roles, four operators: the first's monitors stop at its share (a fifth of the nodes here:
    refused naming it and the bound), and so does its requirement past it; the others still
    monitor; once the callers hold all they may together, a request whose transformation
    requires a formula is still watched, from the manager's reserve."""
    from dyknow.reasoning import check_formula
    from dyknow.security import Limits

    formula = "Ticks.value > 0 and Ticks.value < 1000000 and Ticks.value != 7"
    n = check_formula(formula).nodes
    (tmp_path / "acl.json5").write_text('{ roles: { operator: ["operator", "robot", "station", "viewer"] } }')
    (tmp_path / "checked.xml").write_text(CHECKED)
    # a caller may hold 5 such monitors, all callers 16; the manager keeps 4 for its own
    manager = make_manager(
        listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=AccessControl.load(tmp_path / "acl.json5"),
        specs=[GENERIC_SPECS, tmp_path / "checked.xml"], limits=Limits(max_monitor_nodes=20 * n),
    )  # fmt: skip
    with ExitStack() as stack:
        mallory, robot, station, viewer = (
            stack.enter_context(Client(manager.name, connect=manager.endpoints, tls=tls(certs, name), timeout_s=5.0))
            for name in ("operator", "robot", "station", "viewer")
        )  # fmt: skip
        taken = 0
        with pytest.raises(AccessError) as refused:
            while taken < 20:
                mallory.monitor(formula)
                taken += 1
        assert taken == 5, f"one caller took {taken} monitors of {n} nodes"
        assert f"the monitors and requirements of caller 'operator' hold {5 * n} formula nodes" in str(refused.value)
        assert f"expected at most {5 * n} nodes a caller (Limits.monitor_nodes_caller_share" in str(refused.value)
        with pytest.raises(AccessError, match="caller 'operator'"):
            mallory.request("Ticks", require=["Ticks.value >= 0"])
        assert "Ticks.value >= 0" not in _held(manager, "Ticks")["requirements"]  # type: ignore[index]
        for other in (robot, station):
            for _ in range(5):
                other.monitor(formula)
        viewer.monitor(formula)  # the callers hold 16 of 20 now: all they may
        with pytest.raises(AccessError, match=r"the callers' monitors and requirements hold .* kept for its own requirements"):
            viewer.monitor(formula)
        key = robot.request("Checked(ticks)")
        checked = _held(manager, "Checked(ticks)")
        assert checked is not None and checked["state"] == "active" and checked["unwatched"] == []
        (watched,) = checked["spec_requirements"]
        assert watched["formula"] == "Checked(ticks).value >= 0"
        assert [u.state for u in manager.units() if u.bindings.get("verdicts") == watched["key"]] == ["running"]
        robot.release(key)


# ---------------------------------------------------------------------- the right to manage ROS 2 nodes

ROS2_ACL = """{
  roles: { viewer: ["viewer"], operator: ["operator"], tuner: ["tuner"], spawner: ["station"], router: ["router"] },
  define: {
    // reads like a viewer, and may manage the robot's nodes (no spawn, no request)
    tuner: { like: "viewer", calls: ["manage"] },
    // may spawn and destroy units, and not manage nodes
    spawner: { like: "viewer", calls: ["spawn", "destroy"] },
  },
}"""
CHANGE_STATE, GET_STATE = "lifecycle_msgs/srv/ChangeState", "lifecycle_msgs/srv/GetState"
CAMERA_NODE = """<node name="/cam" timeout-s="1">
  <label>camera-node</label>
  <topic type="std_msgs/msg/String">/cam/frames</topic>
  <tags><tag>Frames(cam)</tag></tags>
</node>"""


@pytest.fixture
def robot(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> Iterator[tuple[Manager, dict[str, Any]]]:
    """A manager with TLS and roles (ROS2_ACL), and the robot's ROS 2 side linked to it as
    rmw_zenoh's router would be, over TLS with a certificate under router: a lifecycle node /cam
    serving get_state and change_state (dyknow's Ros2Service), counting what reaches it."""
    from dyknow.ros2 import Ros2Node

    (tmp_path / "acl.json5").write_text(ROS2_ACL)
    (tmp_path / "node.xml").write_text(CAMERA_NODE)
    manager = make_manager(
        listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=AccessControl.load(tmp_path / "acl.json5"),
        specs=[GENERIC_SPECS, tmp_path / "node.xml"], ros2_domain=0,
    )  # fmt: skip
    node_state = {"id": 1, "changes": 0}

    def change(request: Any) -> dict[str, Any]:
        node_state["changes"] += 1
        node_state["id"] = 2 if request.transition.id == 1 else node_state["id"]
        return {"success": request.transition.id == 1}

    with Session(make_config(connect=manager.endpoints, tls=tls(certs, "router"))) as side, Ros2Node(side, "cam", domain=0) as node:
        node.create_service("/cam/get_state", GET_STATE, lambda r: {"current_state": {"id": node_state["id"], "label": "unconfigured"}})
        node.create_service("/cam/change_state", CHANGE_STATE, change)
        yield manager, node_state


def _ros2_call(manager: Manager, certs: Path, who: str, service: str, srv_type: str, request: dict[str, Any], timeout_s: float = 10) -> Any:
    from dyknow.ros2 import Ros2Node

    with Client(manager.name, connect=manager.endpoints, tls=tls(certs, who), timeout_s=5.0) as c, Ros2Node(c.session, f"caller_{who}", domain=0) as n:
        return n.create_client(service, srv_type).call(request, timeout_s=timeout_s)


def test_a_viewer_reads_ros2_nodes_and_only_a_role_with_manage_changes_them(robot: tuple[Manager, dict[str, Any]], certs: Path) -> None:
    """Issue 53, item 7: calling another node's lifecycle service through a manager with roles.
    A viewer reads the node's state, and its change_state is dropped at the manager's link (at
    once, never reaching the node); an operator and a role of the file's own that calls manage
    change it; a certificate with no role sees no server at all."""
    manager, node = robot
    assert _ros2_call(manager, certs, "viewer", "/cam/get_state", GET_STATE, {}).current_state.id == 1
    started = time.monotonic()
    with pytest.raises(ServiceError, match="1 server\\(s\\) up ended the request without an answer") as refused:
        _ros2_call(manager, certs, "viewer", "/cam/change_state", CHANGE_STATE, {"transition": {"id": 1}})
    assert refused.value.details["reason"] == "dropped" and time.monotonic() - started < 10
    assert node["changes"] == 0
    assert _ros2_call(manager, certs, "operator", "/cam/change_state", CHANGE_STATE, {"transition": {"id": 1}}).success is True
    assert _ros2_call(manager, certs, "tuner", "/cam/change_state", CHANGE_STATE, {"transition": {"id": 3}}).success is False
    assert node["changes"] == 2
    assert _ros2_call(manager, certs, "tuner", "/cam/get_state", GET_STATE, {}).current_state.id == 2
    with pytest.raises(ServiceError, match="no server of it came up"):
        _ros2_call(manager, certs, "stranger", "/cam/get_state", GET_STATE, {}, timeout_s=2)  # (it never comes up: any wait)


@pytest.mark.process
def test_dyknow_ros2_call_says_a_refused_call_needs_the_right_manage(robot: tuple[Manager, dict[str, Any]], certs: Path) -> None:
    manager, node = robot
    call = ["ros2", "call", "/cam/change_state", CHANGE_STATE, "{transition: {id: 1}}", "--connect", manager.endpoints[0], "--ros2-domain", "0"]
    refused = run_cli(*call, *_tls_args(certs, "viewer"))
    assert refused.returncode == 1, refused.stderr
    said = " ".join(refused.stderr.split())
    assert "the request ended at once without an answer: refused by the --acl of a manager or router on the way" in said, said
    assert "common name 'viewer'" in said and "expected a certificate whose role has the right manage" in said, said
    assert node["changes"] == 0
    allowed = run_cli(*call, "--json", *_tls_args(certs, "tuner"))
    assert allowed.returncode == 0, allowed.stderr
    assert json.loads(allowed.stdout)["response"] == {"success": True} and node["changes"] == 1
    graph = run_cli("ros2", "list", "--json", "--connect", manager.endpoints[0], "--ros2-domain", "0", "--timeout", "3", *_tls_args(certs, "viewer"))
    assert graph.returncode == 0, graph.stderr
    assert json.loads(graph.stdout)["services"]["/cam/change_state"]["servers"] == 1  # a viewer sees what it may not call


def test_spawning_a_managed_node_needs_the_right_manage(robot: tuple[Manager, dict[str, Any]], certs: Path) -> None:
    """A managed node's unit configures, activates and sets the parameters of the node its
    params name: a role that may spawn units but not manage nodes is refused it before anything
    starts, as a viewer is refused spawn; an operator's spawn goes on to the node (which answers
    get_state and change_state here, but publishes no frames: the unit fails on that)."""
    manager, node = robot
    with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "station"), timeout_s=10.0) as spawner:
        spawner.spawn("relay", "r")  # it may spawn
        with pytest.raises(AccessError, match=r"'station' may not spawn 'camera-node': it manages the ROS 2 node /cam .*expected a caller whose role has the right manage in this manager's --acl \(operator or admin or tuner or manager\)"):
            spawner.spawn("camera-node", "cam", params={"node": "/cam"})
    assert not manager.has_unit("cam") and node["changes"] == 0
    with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "viewer"), timeout_s=10.0) as viewer, pytest.raises(ServiceError, match="without a reply"):
        viewer.spawn("camera-node", "cam")
    with Client(manager.name, connect=manager.endpoints, tls=tls(certs, "operator"), timeout_s=30.0) as operator:
        info = operator.spawn("camera-node", "cam")
    assert node["changes"] >= 1 and info["state"] == "failed", info  # the manager configured the node for the operator


def test_the_right_manage_is_checked_and_located_in_the_acl_file(tmp_path: Path) -> None:
    acl = AccessControl.from_dict({"roles": {"viewer": ["v"], "operator": ["o"], "tuner": ["t"], "reader": ["r"], "ops": ["p"], "manager": ["m"]},
                                   "define": {"tuner": {"calls": ["manage"]}, "reader": {"like": "viewer"}, "ops": {"like": "operator"}}})  # fmt: skip
    assert [n for n in ("v", "o", "t", "r", "p", "m", "nobody") if acl.may_manage(n)] == ["o", "t", "p", "m"]
    assert acl.roles_for_manage() == ["operator", "admin", "tuner", "ops", "manager"]
    assert not acl.may_call("t", "manage")  # a right over nodes, not a manager's service
    config = acl.zenoh()
    rules = {r["id"]: r for r in config["rules"]}
    policy = {p["subjects"][0]: set(p["rules"]) for p in config["policies"]}
    tuner = next(s["id"] for s in config["subjects"] if s.get("cert_common_names") == ["t"] and s["id"].startswith("defined"))
    assert "operator-manages-ros2-nodes" in policy["operator"] and "operator-manages-ros2-nodes" in policy[tuner]
    assert "operator-manages-ros2-nodes" not in policy["viewer"] and "viewer-reads-ros2-nodes" in policy["viewer"]
    reader = next(s["id"] for s in config["subjects"] if s.get("cert_common_names") == ["r"])
    assert "viewer-reads-ros2-nodes" in policy[reader] and "operator-manages-ros2-nodes" not in policy[reader]
    assert "manager-manages-ros2-nodes" in policy["manager-0"] and "router-carries-ros2-graph" not in rules  # (no router listed)
    assert rules["operator-manages-ros2-nodes"]["key_exprs"] == ["*/**/change_state/*/*", "*/**/set_parameters/*/*", "*/**/set_parameters_atomically/*/*", "*/**/change_mode/*/*"]
    bad = tmp_path / "acl.json5"
    bad.write_text('{\n  roles: { tuner: ["t"] },\n  define: {\n    tuner: { like: "viewer", calls: ["get_model", "mange"] },\n  },\n}\n')
    with pytest.raises(AccessError, match=re.escape(f"{bad}:4: define.tuner.calls[1]: unknown service 'mange'; expected one of ") + r".*or manage \(the right to manage ROS 2 nodes\) \(did you mean 'manage'\?\)"):
        AccessControl.load(bad)


@pytest.mark.process
def test_a_real_rmw_zenoh_node_behind_its_router_is_managed_only_with_the_right(certs: Path, make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """The robot as it runs: a lifecycle node on rmw_zenoh (zenoh-ros2-sdk, tests/ros2_peer.py)
    linked over plain TCP to its router, which links to the manager over TLS with a certificate
    under router (as rmw_zenohd would). A viewer reads the node's state and its configure never
    reaches the node (the operator's, next, finds it unconfigured); a viewer may not set its
    parameters either; the manager's own NodeLifecycle drives it."""
    from dyknow.ros2.lifecycle import NodeLifecycle
    from tests.test_ros2_live import Peer

    (tmp_path / "acl.json5").write_text(ROS2_ACL)
    manager = make_manager(
        listen=[f"tls/127.0.0.1:{free_port()}"], tls=tls(certs, "manager"), acl=AccessControl.load(tmp_path / "acl.json5"), ros2_domain=0,
    )  # fmt: skip
    port = free_port()
    with Session(make_config(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=manager.endpoints, tls=tls(certs, "router"))):
        peer = Peer(str(port), "lifecycle", "cam", "/cam/frames")
        try:
            assert peer.line() == {"ready": True}
            assert _ros2_call(manager, certs, "viewer", "/cam/get_state", GET_STATE, {}).current_state.label == "unconfigured"
            with pytest.raises(ServiceError, match="ended the request without an answer") as refused:
                _ros2_call(manager, certs, "viewer", "/cam/change_state", CHANGE_STATE, {"transition": {"id": 1}})
            assert refused.value.details["reason"] == "dropped"
            parameters = "rcl_interfaces/srv/SetParameters"
            exposure = {"parameters": [{"name": "exposure", "value": {"type": 3, "double_value": 0.7}}]}
            with pytest.raises(ServiceError, match="ended the request without an answer"):
                _ros2_call(manager, certs, "viewer", "/cam/set_parameters", parameters, exposure)
            assert _ros2_call(manager, certs, "operator", "/cam/change_state", CHANGE_STATE, {"transition": {"id": 1}}).success is True
            assert peer.line() == {"transition": "configure", "exposure": 0.1}  # the viewer's set_parameters did not reach it either
            assert _ros2_call(manager, certs, "tuner", "/cam/set_parameters", parameters, exposure).results[0].successful is True
            with NodeLifecycle(manager.ros2_node(), "/cam", timeout_s=15) as node:
                assert node.bring_up() == ["activate"] and node.state() == (3, "active")
            assert peer.line() == {"transition": "activate"}
        finally:
            peer.close()
