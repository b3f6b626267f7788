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

from dyknow import AccessError, BindingError, Client, LibraryError, Manager, ServiceError, SpecError, TransformationSpec, UnitError
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


def test_a_data_root_that_is_not_a_folder_is_refused_at_start(tmp_path: Path) -> None:
    """A --data-root that does not exist (or is a file) would refuse every file named under it,
    silently until a caller tried: the manager refuses to start, naming it."""
    with pytest.raises(AccessError, match=r"--data-root .*missing: .*missing does not exist; expected an existing folder .*mkdir -p"):
        Manager("roots", data_roots=[tmp_path / "missing"], serve=False)
    (tmp_path / "file").write_text("")
    with pytest.raises(AccessError, match=r"file is not a folder"):
        DataRoots(write=[tmp_path / "file"])


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
    ("destroy", b'{"name": "x", "now": true}', "service 'destroy': unknown field 'now'; expected the fields name, force"),
    ("measure", b'{"name": "battery", "value": {"a": 1}}', "field 'value': got {'a': 1}; expected a finite number, or text of at most 256 bytes"),
    ("add_transformation", b'{"xml": "/etc/passwd"}', "field 'xml': a remote caller may only send XML text"),
]


@pytest.mark.process
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


@pytest.mark.process
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


@pytest.mark.process
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


@pytest.mark.process
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


@pytest.mark.process
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


@pytest.mark.process
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


# ---------------------------------------------------------------------- the second round's attacks


def _image(path: Path) -> None:
    import cv2
    import numpy as np

    assert cv2.imwrite(str(path), np.full((8, 8, 3), 128, np.uint8))


def test_globs_and_folders_reaching_outside_through_a_symlink_are_refused(rooted: tuple[Manager, Client], data: Path, tmp_path: Path) -> None:
    """``l*k/*.png`` matched the files of a folder outside the root through a symbolic link
    inside it (the literal ``link/...`` was refused); a folder inside whose files link outside
    did the same. Every match is resolved before the unit is spawned, and the refusal says
    nothing of what lies outside."""
    manager, client = rooted
    outside = tmp_path / "outside-secrets"
    outside.mkdir()
    _image(outside / "secret.png")
    (data / "link").symlink_to(outside)
    (data / "innocent").mkdir()
    (data / "innocent" / "a.png").symlink_to(outside / "secret.png")
    _image(data / "frames" / "f1.png")
    for value in ["l*k/*.png", "*/*.png", "innocent", "innocent/*.png", "link"]:
        with pytest.raises(AccessError) as refused:
            client.spawn("image-folder-source(bottom)", "u", params={"path": value})
        message = str(refused.value)
        assert refused.value.where == "param 'path' of unit 'u'", message
        assert "outside" in message and "outside-secrets" not in message and "secret.png" not in message, message
    assert not manager.has_unit("u")
    assert client.spawn("image-folder-source(bottom)", "u", params={"path": "frames/*.png"})["state"] == "running"
    assert client.spawn("image-folder-source(top)", "v", params={"path": "frames"})["state"] == "running"


def test_a_remote_spec_may_not_leave_a_file_param_to_the_units_default(
    rooted: tuple[Manager, Client], data: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A spec added remotely without ``path`` (recorder) or ``file`` (replay) made the unit fall
    back to its own default, in the manager's working directory: refused, naming the param."""
    manager, client = rooted
    work = tmp_path / "working-directory"
    work.mkdir()
    monkeypatch.chdir(work)
    client.add_transformation(spec_xml("bare-recorder", "transformations.recording:RecorderUnit"))
    client.add_transformation(spec_xml("bare-replay", "transformations.recording:ReplaySource", ports='<port type="out">out</port>'))
    for label, param, mode in [("bare-recorder", "path", "write"), ("bare-replay", "file", "read")]:
        with pytest.raises(AccessError) as refused:
            client.spawn(label, "bare")
        assert refused.value.where == f"param {param!r} of unit 'bare'"
        assert "is not given" in refused.value.what and f"a file to {mode} under" in str(refused.value.expected)
        with pytest.raises(AccessError, match="is not given"):
            manager.spawn(label, "bare")  # the planner's spawn of a remotely added spec: confined too
    assert list(work.iterdir()) == [] and not manager.has_unit("bare")
    assert client.spawn("recorder", "rec")["state"] == "running"  # the shipped spec names its default: under the root
    assert manager.unit("rec").params["path"] == str(data.resolve() / "recording.mcap")


@pytest.mark.parametrize(
    ("call", "says"),
    [
        (lambda c: c.spawn("relay", "victim\n"), r"unit name 'victim\n' is not a valid name"),
        (lambda c: c.spawn("relay", "victim\u202e"), "is not a valid name"),
        (lambda c: c.spawn("rel\u202eay", "r"), r"field 'label': 'rel\u202eay' holds the character U+202E"),
        (lambda c: c.spawn("x" * 300, "r"), "field 'label': a label of 300 bytes"),
        (lambda c: c.remove_transformation(" relay"), "has spaces at an end"),
        (lambda c: c.measure("**", 1.0), "measurement name '**' is not a valid name"),
        (lambda c: c.measure("bat\ttery", 1.0), "is not a valid name"),
        (lambda c: c.add_transformation(spec_xml("x" * 1000, "transformations.generic:Relay")), "<client>:1: <label>: a label of 1000 bytes"),
        (lambda c: c.add_transformation(spec_xml("evil\u202eexe.gpj", "transformations.generic:Relay")), r"<label>: 'evil\u202eexe.gpj' holds the character U+202E"),
        (lambda c: c.add_transformation(spec_xml("tab\tbed", "transformations.generic:Relay")), "holds the character U+0009"),
    ],
)
def test_names_and_labels_are_checked_one_way_everywhere(manager: Manager, call: Callable[[Client], object], says: str) -> None:
    """A unit name with a trailing newline was accepted beside the name without it; labels of
    1,000 characters or with U+202E were accepted that no other service could then name."""
    before = (sorted(manager.library.labels()), [u.name for u in manager.units()], manager.measurements)
    with Client(manager.name, connect=manager.endpoints) as client, pytest.raises((ServiceError, SpecError, LibraryError, UnitError)) as refused:
        call(client)
    assert says in str(refused.value), str(refused.value)
    assert (sorted(manager.library.labels()), [u.name for u in manager.units()], manager.measurements) == before


def test_the_local_api_checks_names_and_labels_the_same_way(manager: Manager) -> None:
    with pytest.raises(UnitError, match="is not a valid name"):
        manager.spawn("relay", "victim\n")
    with pytest.raises(UnitError, match="measurement name '\\*\\*' is not a valid name"):
        manager.measure("**", 1.0)
    with pytest.raises(SpecError, match="holds the character U\\+202E"):
        manager.add_transformation(spec_xml("a\u202eb", "transformations.generic:Relay"))


def test_puts_on_wildcard_keys_are_no_measurements(manager: Manager) -> None:
    """An operator's put on ``dyknow/**/in`` or ``dyknow/measurements/**`` reached the manager's
    measurement subscriptions and became measurements named ``in`` and ``**``."""
    with Session(make_config(connect=manager.endpoints)) as session:
        session.call(f"@dyknow/{manager.name}/get_model", b"{}", timeout_s=10, what="get_model")  # the link is up
        for key in ["dyknow/**/in", "dyknow/measurements/**", f"dyknow/{manager.name}/measurements/*", "dyknow/measurements/b$*"]:
            session.put(key, b"0.5")
        session.put("dyknow/measurements/battery", b"0.25")  # after them, on the same session: it comes last
        wait_until(lambda: "battery" in manager.measurements, "the real measurement")
    assert manager.measurements == {"battery": 0.25}


@pytest.mark.process
def test_a_template_whose_expansions_hold_too_much_text_is_refused_before_it_expands(hostile_target: tuple[ManagerProcess, Session]) -> None:
    """A 31 KiB spec expanded to 10,000 transformations of 30 KB each (get_model then returned
    291 MiB). What the expansions would hold is bounded in bytes before any is built."""
    proc, session = hostile_target
    values = "{" + ";".join(f"v{i}" for i in range(100)) + "}"
    bomb = (
        f"<transformation><label>t${{A}}${{B}}</label><source>transformations.generic:Relay</source>"
        f"<description>{'x' * 30_000}</description>"
        f'<args><arg label="A">{values}</arg><arg label="B">{values}</arg></args>'
        '<ports><port type="out">out</port></ports></transformation>'
    )
    assert 30_000 < len(bomb) < 32 * 1024
    started = time.monotonic()
    with Client(proc.name, connect=[proc.endpoint], session=session) as client:
        with pytest.raises(SpecError) as refused:
            client.add_transformation(bomb)
        issue = refused.value.issues[0]
        assert issue.element == "<transformation>" and issue.what.startswith("expands to 10,000 transformations of up to 30")
        assert issue.expected == "at most 16,777,216 bytes (--max-expansion-bytes)"
        assert time.monotonic() - started < 5
        assert client.get_model()["specs"] == json.loads(_call(session, proc, "get_model", b"{}"))["specs"]
        assert not any(s["label"].startswith("tv") for s in client.get_model()["specs"])
    assert proc.stop(signal.SIGTERM) == 0


def test_a_large_model_comes_in_pages_of_bounded_size(make_manager: Callable[..., Manager]) -> None:
    """get_model answers at most max_reply_bytes at a time; Client.get_model gathers the pages
    into the same model the manager holds."""
    from dyknow.security import Limits

    manager = make_manager(limits=Limits(max_reply_bytes=64 * 1024))
    xml = "<transformations>" + "".join(
        f"<transformation><label>s{i}</label><source>transformations.generic:Relay</source><description>{'d' * 1000}</description>"
        '<ports><port type="in">in</port><port type="out">out</port></ports></transformation>'
        for i in range(300)
    ) + "</transformations>"
    manager.add_transformation(xml)
    for i in range(40):
        manager.spawn("s0", f"u{i}")
    with Session(make_config(connect=manager.endpoints)) as session, Client(manager.name, session=session) as client:
        page: dict[str, int] = {}
        seen = {"units": 0, "specs": 0}
        pages = 0
        while True:
            raw = session.call(f"@dyknow/{manager.name}/get_model", json.dumps({"page": page} if page else {}).encode(), timeout_s=10, what="get_model")
            assert len(raw) <= 64 * 1024
            reply = json.loads(raw)
            assert reply["total"] == {"units": 40, "specs": len(manager.library.labels())}
            seen["units"] += len(reply["units"])
            seen["specs"] += len(reply["specs"])
            pages += 1
            if reply["next"] is None:
                break
            page = reply["next"]
        assert pages > 3 and seen == {"units": 40, "specs": len(manager.library.labels())}
        whole = client.get_model()
        local = manager.get_model().to_dict()
        for model in (whole, local):  # the watchdog's last load reading may change between the two reads
            reading = model["executor"]["overload"]
            assert {"lag_ms", "busy", "cpu"} <= reading.keys()
            reading.update(lag_ms=None, busy=None, cpu=None)
        assert whole == local
        with pytest.raises(ServiceError, match="field 'page.units': got -1; expected a whole number from 0"):
            session.call(f"@dyknow/{manager.name}/get_model", b'{"page": {"units": -1}}', timeout_s=10, what="get_model")


def test_a_manager_runs_at_most_max_units(make_manager: Callable[..., Manager]) -> None:
    """1,000 relays cost 45 MiB and slowed get_model eightfold, with no cap: the cap is a limit
    of its own (--max-units), for local and remote spawns alike."""
    from dyknow.security import Limits

    manager = make_manager(limits=Limits(max_units=3))
    for i in range(3):
        manager.spawn("relay", f"r{i}")
    with pytest.raises(UnitError, match=r"the manager already runs 3 units, its most; expected at most 3 units \(--max-units\)"):
        manager.spawn("relay", "r3")
    with Client(manager.name, connect=manager.endpoints) as client, pytest.raises(UnitError, match="at most 3 units"):
        client.spawn("relay", "r3")
    manager.destroy("r0")
    manager.spawn("relay", "r3")
    assert sorted(u.name for u in manager.units()) == ["r1", "r2", "r3"]


def _peak_rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    raise AssertionError("no VmHWM")


@pytest.mark.process
def test_oversized_messages_are_dropped_as_they_arrive(manager_process: Callable[..., ManagerProcess]) -> None:
    """Four 400 MiB get_model calls were each refused, but only once in memory (RSS peaked at
    1.5 GiB); 200 MiB data puts were delivered. Zenoh now drops a message over the manager's
    --max-message-bytes fragment by fragment while it reassembles it: the manager's peak memory
    grows by far less than one such message, the calls go unanswered, the data never arrives,
    a message under the bound does, and others are served meanwhile."""
    import zenoh

    proc = manager_process("--max-message-bytes", str(8 << 20))
    big = b"{" + b" " * (256 << 20) + b"}"
    with Client(proc.name, connect=[proc.endpoint], timeout_s=10) as client, zenoh.open(make_config(connect=[proc.endpoint])) as attacker:
        client.spawn("sink", "s", bindings={"in": "big/data"})
        publisher = attacker.declare_publisher("big/data", congestion_control=zenoh.CongestionControl.BLOCK)  # nothing dropped on the way
        wait_until(lambda: publisher.matching_status.matching, "the sink to match the attacker's publisher")
        before = _peak_rss_kib(proc.proc.pid)
        for _ in range(2):
            replies = list(attacker.get(f"@dyknow/{proc.name}/get_model", payload=big, timeout=3.0))
            assert all(reply.ok is None for reply in replies)  # dropped on arrival: only the querier's own timeout
            publisher.put(big)
            assert client.get_model()["manager"] == proc.name  # others are served
        publisher.put(b'"' + b"m" * (4 << 20) + b'"')  # under the bound: delivered, after the big ones
        wait_until(lambda: _messages(client, "s") >= 1, "the message under the bound")
        assert _messages(client, "s") == 1
        grew = _peak_rss_kib(proc.proc.pid) - before
        publisher.undeclare()
    assert grew < 128 * 1024, f"the manager's peak memory grew by {grew / 1024:.0f} MiB"
    assert proc.stop(signal.SIGTERM) == 0
