"""Hostile callers: no remote code loading, files only under the data roots, bounded requests.

Everything here arrives over real Zenoh sessions, as it would from another machine.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from dyknow import AccessError, BindingError, Client, LibraryError, Manager, ServiceError, SpecError, TransformationSpec
from dyknow.security import DataRoots, SourcePolicy, bounded_glob
from dyknow.transport import Session, make_config
from tests.conftest import ManagerProcess, wait_until

EVIL = '''
import pathlib
pathlib.Path(__file__).with_name("IMPORTED").write_text("the module ran")
from dyknow import Unit
class Thing(Unit):
    pass
'''


def spec_xml(label: str, source: str, params: str = "", ports: str = '<port type="in">in</port>') -> str:
    return f"<transformation><label>{label}</label><source>{source}</source><params>{params}</params><ports>{ports}</ports></transformation>"


@pytest.fixture
def evil(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[str, Path]:
    """A module on the manager's path (a name of its own per test) that leaves a file behind when imported."""
    module = f"evil_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{module}.py").write_text(EVIL)
    monkeypatch.syspath_prepend(str(tmp_path))
    return module, tmp_path / "IMPORTED"


def test_a_foreign_source_is_refused_when_added_and_never_imported(manager: Manager, evil: tuple[str, Path]) -> None:
    module, marker = evil
    with Client(manager.name, connect=manager.endpoints) as client:
        with pytest.raises(AccessError) as refused:
            client.add_transformation(spec_xml("thing", f"{module}:Thing"))
        assert refused.value.what == f"source '{module}:Thing' is not allowed on this manager"
        assert refused.value.where == "transformation 'thing' (<client>:1)"
        assert "--allow-source PATTERN" in str(refused.value.expected)
        with pytest.raises(AccessError, match="source 'os:system' is not allowed"):
            client.add_transformation(spec_xml("shell", "os:system"))
        assert "thing" not in {s["label"] for s in client.get_model()["specs"]}
    assert not marker.exists()  # nothing was imported
    manager.add_transformation(spec_xml("thing", f"{module}:Thing"))  # the operator, through Python: trusted
    manager.spawn("thing", "t")
    assert marker.exists()


def test_allow_source_lets_an_operator_add_modules(make_manager: Callable[..., Manager], evil: tuple[str, Path]) -> None:
    module, marker = evil
    manager = make_manager(allow_sources=[module])
    with Client(manager.name, connect=manager.endpoints) as client:
        assert client.add_transformation(spec_xml("thing", f"{module}:Thing")) == ["thing"]
        assert not marker.exists()  # adding imports nothing
        client.spawn("thing", "t")
    assert marker.exists()


def test_the_module_is_checked_before_every_import() -> None:
    """Even a spec that reached the library some other way cannot import a module outside the list."""
    policy = SourcePolicy()
    assert policy.allows("transformations.generic:Relay") and policy.allows("dyknow.testing:Sink")
    assert not policy.allows("evil_module:Thing") and not policy.allows("transformationsx.a:B") and not policy.allows("os:system")
    policy.allow("mypkg.units:Camera", "other*")
    assert policy.allows("mypkg.units:Camera") and not policy.allows("mypkg.units:Lidar") and policy.allows("other_pkg.x:Y")
    with pytest.raises(AccessError, match="is not a source pattern"):
        policy.allow("a b")


@pytest.fixture
def data(tmp_path: Path) -> Path:
    root = tmp_path / "data"
    root.mkdir()
    (root / "frames").mkdir()
    (tmp_path / "secret.txt").write_text("root:*:0:0")
    (root / "escape").symlink_to(tmp_path / "secret.txt")
    return root


@pytest.fixture
def rooted(make_manager: Callable[..., Manager], data: Path) -> Iterator[tuple[Manager, Client]]:
    manager = make_manager(data_roots=[data], specs=[Path("specs/recording.xml"), Path("specs/sources.xml"), Path("tests/units.xml")])
    with Client(manager.name, connect=manager.endpoints) as client:
        yield manager, client


@pytest.mark.parametrize(
    ("label", "param", "value", "problem"),
    [
        ("recorder", "path", "/etc/cron.d/x", "'/etc/cron.d/x' is outside the data roots"),
        ("recorder", "path", "../secret.txt", "'../secret.txt' leaves its folder ('..' or '~')"),
        ("recorder", "path", "~/.ssh/authorized_keys", "leaves its folder"),
        ("recorder", "path", "frames/*.mcap", "is a glob"),
        ("replay(Recorded)", "file", "escape", "'escape' is outside the data roots"),  # a symlink out of the root
        ("replay(Recorded)", "file", "/etc/shadow", "'/etc/shadow' is outside the data roots"),
        ("image-folder-source(bottom)", "path", "/*/*/*/*/*/*/*.nothing", "is outside the data roots"),
        ("video-source(bottom)", "path", "/dev/video0", "is outside the data roots"),
    ],
)
def test_remote_file_params_stay_under_the_data_roots(rooted: tuple[Manager, Client], label: str, param: str, value: str, problem: str) -> None:
    manager, client = rooted
    with pytest.raises(AccessError) as refused:
        client.spawn(label, "u", params={param: value})
    assert refused.value.where == f"param {param!r} of unit 'u'" and problem in refused.value.what
    assert not manager.has_unit("u")


def test_remote_file_params_under_a_root_work(rooted: tuple[Manager, Client], data: Path) -> None:
    manager, client = rooted
    info = client.spawn("recorder", "rec", params={"path": "run.mcap"})
    assert info["state"] == "running"
    assert manager.unit("rec").params["path"] == str(data.resolve() / "run.mcap")  # resolved once, under the root
    client.destroy("rec")
    assert (data / "run.mcap").stat().st_size > 0


def test_the_local_api_may_name_any_path(rooted: tuple[Manager, Client], tmp_path: Path) -> None:
    manager, _ = rooted
    manager.spawn("recorder", "rec", params={"path": str(tmp_path / "anywhere.mcap")})
    assert manager.unit("rec").params["path"] == str(tmp_path / "anywhere.mcap")


def test_without_a_data_root_a_remote_caller_writes_nothing(manager: Manager) -> None:
    manager.add_transformation(Path("specs/recording.xml"))
    with Client(manager.name, connect=manager.endpoints) as client, pytest.raises(AccessError, match="may not name files to write"):
        client.spawn("recorder", "rec")


def test_a_remotely_added_spec_is_confined_even_when_spawned_locally(rooted: tuple[Manager, Client], tmp_path: Path) -> None:
    """Its defaults come from the caller, and the class declares its file params whatever the spec says."""
    manager, client = rooted
    sneaky = spec_xml("sneaky", "transformations.recording:RecorderUnit", f'<param name="path" type="string">{tmp_path}/x.mcap</param>')
    client.add_transformation(sneaky)
    with pytest.raises(AccessError, match="is outside the data roots"):
        manager.spawn("sneaky", "s")  # e.g. by the planner for a request
    assert not (tmp_path / "x.mcap").exists()


def test_globs_are_bounded_in_entries_and_time(tmp_path: Path) -> None:
    for i in range(30):
        (tmp_path / f"{i}.png").write_bytes(b"")
    assert len(bounded_glob(str(tmp_path / "*.png"))) == 30
    with pytest.raises(AccessError, match="is too costly"):
        bounded_glob(str(tmp_path / "*.png"), max_entries=10)
    started = time.monotonic()
    with pytest.raises(AccessError, match="is too costly"):
        bounded_glob("/*/*/*/*/*/*/*.nothing")
    assert time.monotonic() - started < 10  # bounded (2 s by default), not a walk of the whole disk
    roots = DataRoots(read=[tmp_path])
    assert roots.resolve("*.png", "read", "p") == str(tmp_path.resolve() / "*.png")


# ---------------------------------------------------------------------- hostile requests, real process


@pytest.fixture
def hostile_target(manager_process: Callable[..., ManagerProcess]) -> Iterator[tuple[ManagerProcess, Session]]:
    proc = manager_process()
    with Session(make_config(connect=[proc.endpoint])) as session:
        yield proc, session


def _call(session: Session, proc: ManagerProcess, service: str, payload: bytes) -> bytes:
    return session.call(f"@dyknow/{proc.name}/{service}", payload, timeout_s=10, what=service)


HOSTILE = [
    ("get_model", b"{" + b" " * 10_000_000 + b"}", "the request has 10,000,002 bytes; expected at most 1,048,576 (--max-request-bytes)"),
    ("spawn", json.dumps({"label": "relay", "name": "n" * 70_000}).encode(), "field 'name': got a str of 70002 characters; expected a name of at most 128 bytes"),
    ("spawn", json.dumps({"label": "relay", "name": "r", "bindings": {"out": "k/" * 35_000}}).encode(), "field 'bindings.out': got a str of"),
    ("get_model", b"[" * 100_000 + b"]" * 100_000, "request: the request's JSON nests too deep; expected at most 32 levels"),
    ("get_model", b"\xff\xfe not json", "request: the request is not JSON"),
    ("spawn", b'{"label": "relay", "name": "r", "bindings": {"in": 5}}', "field 'bindings.in': got 5; expected a key expression"),
    ("destroy", b'{"name": "x", "force": true}', "service 'destroy': unknown field 'force'; expected the fields name"),
    ("measure", b'{"name": "battery", "value": {"a": 1}}', "field 'value': got {'a': 1}; expected a finite number, or text of at most 256 bytes"),
    ("add_transformation", b'{"xml": "/etc/passwd"}', "field 'xml': a remote caller may only send XML text"),
]


def test_hostile_requests_are_refused_and_the_manager_keeps_serving(hostile_target: tuple[ManagerProcess, Session]) -> None:
    proc, session = hostile_target
    for service, payload, message in HOSTILE:
        with pytest.raises(ServiceError) as refused:
            _call(session, proc, service, payload)
        assert message in str(refused.value), (service, str(refused.value)[:300])
        assert json.loads(_call(session, proc, "get_model", b"{}"))["manager"] == proc.name  # still serving
    # a port name too long for a key: the spec is stored, its unit is refused before any key is declared
    long_port = spec_xml("long", "transformations.generic:Relay", ports=f'<port type="in">in</port><port type="out">{"p" * 70_000}</port>')
    _call(session, proc, "add_transformation", json.dumps({"xml": long_port}).encode())
    with pytest.raises(ServiceError, match="a key expression of 70.* bytes is too long"):
        _call(session, proc, "spawn", json.dumps({"label": "long", "name": "l"}).encode())
    assert proc.stop(signal.SIGTERM) == 0


BOMB = """<transformation><label>b${A}${B}${C}${D}${E}${F}</label><source>transformations.generic:Relay</source><args>"""
BOMB += "".join(f'<arg label="{a}">{{0;1;2;3;4;5;6;7;8;9}}</arg>' for a in "ABCDEF")
BOMB += """</args><ports><port type="out">out</port></ports></transformation>"""


def test_a_template_bomb_is_refused_at_its_location(hostile_target: tuple[ManagerProcess, Session], tmp_path: Path) -> None:
    proc, session = hostile_target
    started = time.monotonic()
    with Client(proc.name, connect=[proc.endpoint], session=session) as client, pytest.raises(SpecError) as refused:
        client.add_transformation(BOMB)
    assert time.monotonic() - started < 5
    issue = refused.value.issues[0]
    assert (issue.element, issue.what, issue.expected) == (
        "<transformation>",
        "expands to 1,000,000 transformations (10 x 10 x 10 x 10 x 10 x 10 arg values)",
        "at most 10,000",
    )
    assert proc.stop(signal.SIGTERM) == 0


def test_a_spec_loaded_locally_is_bounded_too(tmp_path: Path) -> None:
    (tmp_path / "bomb.xml").write_text(BOMB)
    with pytest.raises(SpecError, match="expands to 1,000,000"):
        Manager("bounded", specs=[tmp_path / "bomb.xml"], serve=False, listen=[])
    from tests.conftest import run_cli

    result = run_cli("validate", str(tmp_path / "bomb.xml"))
    assert result.returncode == 1 and "bomb.xml:1: <transformation>: expands to 1,000,000" in result.stderr
    small = BOMB.replace('<arg label="D">{0;1;2;3;4;5;6;7;8;9}</arg><arg label="E">{0;1;2;3;4;5;6;7;8;9}</arg><arg label="F">{0;1;2;3;4;5;6;7;8;9}</arg>', "")
    (tmp_path / "small.xml").write_text(small.replace("${D}${E}${F}", ""))
    assert run_cli("validate", str(tmp_path / "small.xml")).returncode == 0  # 1,000 expansions: fine
    refused = run_cli("validate", str(tmp_path / "small.xml"), "--max-expansions", "500")
    assert refused.returncode == 1 and "expands to 1,000 transformations (10 x 10 x 10 arg values); expected at most 500" in refused.stderr


def test_spec_objects_given_locally_are_trusted(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager()
    spec = TransformationSpec(label="x", source="tests.units:Counter")
    with pytest.raises(LibraryError, match="no transformation labelled 'x'"):  # not in the library
        manager.spawn("x", "x1")
    assert manager.spawn(spec, "x1").state == "running"


# ---------------------------------------------------------------------- units that would freeze a manager


def test_forwarding_units_bound_into_a_cycle_are_refused_naming_the_ports(hostile_target: tuple[ManagerProcess, Session]) -> None:
    """Two relays bound into a cycle, or a relay reading ``dyknow/**`` (its own output among it),
    would pass one message round forever: the spawn or set_config that closes the cycle is
    refused, naming the ports, and nothing changes."""
    proc, session = hostile_target
    with Client(proc.name, connect=[proc.endpoint], session=session) as client:
        client.spawn("relay", "a", bindings={"in": "x/b", "out": "x/a"})
        with pytest.raises(BindingError, match=r"b\.in \(x/a\) -> b\.out \(x/b\) -> a\.in \(x/b\) -> a\.out \(x/a\) -> b\.in"):
            client.spawn("relay", "b", bindings={"in": "x/a", "out": "x/b"})
        with pytest.raises(BindingError, match=rf"r\.in \(dyknow/\*\*\) -> r\.out \(dyknow/{proc.name}/r/out\) -> r\.in"):
            client.spawn("relay", "r", bindings={"in": "dyknow/**"})
        client.spawn("relay", "b", bindings={"in": "x/a", "out": "x/c"})
        with pytest.raises(BindingError, match=r"b\.out \(x/b\)"):
            client.set_config("b", {"out": "x/b"})
        assert client.get_config("b") == {"in": "x/a", "out": "x/c"}
        assert sorted(u["name"] for u in client.get_model()["units"]) == ["a", "b"]
    assert proc.stop(signal.SIGTERM) == 0


def test_a_cycle_of_python_units_leaves_the_manager_serving_and_it_stops_on_sigterm(
    hostile_target: tuple[ManagerProcess, Session],
) -> None:
    """Units that run Python may mean a feedback loop, so their cycle is allowed; one message
    then circles as fast as the units go. Other callers are still answered (each call here
    gives up after 1 s) and SIGTERM stops the manager within 5 s."""
    proc, session = hostile_target
    with Client(proc.name, connect=[proc.endpoint], session=session) as client:
        client.spawn("forwarder", "f1", bindings={"a": "x/f2", "b": "x/unused", "out": "x/f1"})
        client.spawn("forwarder", "f2", bindings={"a": "x/f1", "b": "x/unused", "out": "x/f2"})
        session.put("x/f1", b"round and round")
        wait_until(lambda: _messages(client, "f1") > 10_000, "the message circles")
    with Client(proc.name, connect=[proc.endpoint], timeout_s=1.0) as other:
        for _ in range(5):
            assert other.get_model()["manager"] == proc.name
        circled = _messages(other, "f1")
    assert circled > 10_000
    started = time.monotonic()
    assert proc.stop(signal.SIGTERM, timeout_s=5.0) == 0
    assert time.monotonic() - started < 5.0


def _messages(client: Client, unit: str) -> int:
    return sum(p["messages"] for p in client.get_statistics(unit)["ports"].values() if p["direction"] == "in")


def test_sigterm_stops_a_manager_within_its_deadline_even_when_a_unit_never_lets_go(
    manager_process: Callable[..., ManagerProcess],
) -> None:
    """A unit's teardown() that never returns would hold the manager's close() for good: past
    the 5 s deadline the process exits anyway, with status 1 and every thread's stack on stderr."""
    proc = manager_process()
    with Client(proc.name, connect=[proc.endpoint]) as client:
        client.spawn("stuck-in-teardown", "stuck")
    started = time.monotonic()
    code = proc.stop(signal.SIGTERM, timeout_s=15.0)
    took = time.monotonic() - started
    assert code == 1 and 4.0 < took < 10.0, (code, took)
    stderr = proc.proc.stderr.read() if proc.proc.stderr else ""
    assert "Timeout (0:00:05)!" in stderr and "in teardown" in stderr, stderr[-2000:]
