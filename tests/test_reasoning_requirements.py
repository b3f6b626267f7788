"""Issue 54 item 6: a file of requirements checked over a recording, for CI (``dyknow check``).

Every verdict is compared with the naive evaluator of ``tests/reasoning_support.py`` over the
same samples, each ``forall`` instance written out by hand (its terms substituted in the text),
so the expansion, the template bindings and the evaluation are each checked by something that
is not the code under test. A live run recorded while live monitors judged it is checked too:
the same verdicts at the same times.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

from dyknow import Message
from dyknow.errors import FormulaError
from dyknow.reasoning.requirements import check_recording, junit_xml, load_requirements
from dyknow.reasoning.syntax import parse
from dyknow.recording import Recorder
from dyknow.tags import Term
from tests.conftest import run_cli
from tests.reasoning_support import naive_evaluate_ns, naive_evaluate_objects

ROBOTS = ["r1", "r2", "r3"]
ONTOLOGY = """@prefix ex: <http://example.org/floor#> .
@prefix owl: <http://www.w3.org/2002/07/owl#> .
ex:Robot a owl:Class .
ex:r1 a ex:Robot .
ex:r2 a ex:Robot .
ex:r3 a ex:Robot .
"""
REQUIREMENTS = """# the floor's rules, as the safety engineer wrote them
[bindings]
"State(r)" = "floor/{r}/state"      # a template: State(r2) is read from floor/r2/state
"Limits(floor)" = "floor/limits"

[[requirement]]
name = "speed under the zone's limit"
formula = "forall r in ex:Robot: State(r).speed <= Limits(floor)[State(r).zone]"

[[requirement]]
name = "robots keep apart"
formula = "forall a in ex:Robot: forall b in ex:Robot: State(a).id == State(b).id or dist(State(a), State(b)) > 0.5"

[[requirement]]
name = "each robot seen is slow for 300 ms"
formula = "foreach r in Seen(floor).id: historically[0, 300ms] Seen(floor).speed < 1.5"
bindings = { "Seen(floor)" = "floor/seen" }
idle_ms = 1000

[[requirement]]
name = "the dock's limit is set"
formula = "Limits(floor).dock > 0"
"""


def states() -> dict[str, list[tuple[int, Any]]]:
    """Three robots' states (10 Hz, r2 speeding in the dock for a while, r1 and r3 meeting),
    the zone limits, and the robots seen (each sample one robot's)."""
    out: dict[str, list[tuple[int, Any]]] = {}
    for k, robot in enumerate(ROBOTS):
        series = []
        for i in range(30):
            t = 1_000_000_000 + i * 100_000_000 + k * 7_000_000
            zone = "dock" if (i + k) % 3 else "aisle"
            speed = 0.9 if robot == "r2" and 10 <= i < 14 else 0.3
            x = 2.0 * k if robot != "r3" or not 20 <= i < 23 else 0.2  # r3 next to r1 for three samples
            series.append((t, {"id": robot, "zone": zone, "speed": speed, "x": x, "y": 0.0}))
        out[f"floor/{robot}/state"] = series
    out["floor/limits"] = [(1_000_000_000 - 50_000_000, {"dock": 0.5, "aisle": 2.0})]
    out["floor/seen"] = [(1_000_000_000 + i * 50_000_000 + 3_000_000, {"id": ROBOTS[i % 3], "speed": 1.7 if i == 31 else 0.4}) for i in range(60)]
    return out


def record(path: Path, series: dict[str, list[tuple[int, Any]]]) -> None:
    with Recorder((), path) as recorder:
        for key, samples in series.items():
            for seq, (t_ns, payload) in enumerate(samples, start=1):
                recorder.write(Message(payload, seq, t_ns, t_ns, key))


def by_hand(series: dict[str, list[tuple[int, Any]]]) -> dict[str, dict[str, list[tuple[int, Any]]]]:
    """Each requirement's verdicts by instance, from the naive evaluator over formulas written out by hand."""
    limits = series["floor/limits"]

    def state(r: str) -> Term:
        return Term("State", (r,))

    speed: dict[str, list[tuple[int, Any]]] = {}
    for r in ROBOTS:
        formula = parse(f"State({r}).speed <= Limits(floor)[State({r}).zone]")
        speed[r] = naive_evaluate_ns(formula, {state(r): series[f"floor/{r}/state"], Term("Limits", ("floor",)): limits})
    apart: dict[str, list[tuple[int, Any]]] = {}
    for a in ROBOTS:
        for b in ROBOTS:
            formula = parse(f"State({a}).id == State({b}).id or dist(State({a}), State({b})) > 0.5")
            apart[f"{a}/{b}"] = naive_evaluate_ns(formula, {state(r): series[f"floor/{r}/state"] for r in {a, b}})
    body = parse("historically[0, 300ms] Seen(floor).speed < 1.5")
    domain = parse("foreach r in Seen(floor).id: true").root.domain  # type: ignore[attr-defined]
    objects = naive_evaluate_objects("r", domain, body, {Term("Seen", ("floor",)): series["floor/seen"]}, 1_000_000_000)  # type: ignore[arg-type]
    seen = {obj: sorted(v for life in lives for v in life) for obj, lives in objects.items()}
    dock = {"": naive_evaluate_ns(parse("Limits(floor).dock > 0"), {Term("Limits", ("floor",)): limits})}
    return {"speed under the zone's limit": speed, "robots keep apart": apart, "each robot seen is slow for 300 ms": seen,
            "the dock's limit is set": dock}  # fmt: skip


@pytest.fixture
def floor(tmp_path: Path) -> tuple[Path, Path, Path, dict[str, list[tuple[int, Any]]]]:
    series = states()
    recording = tmp_path / "floor.mcap"
    record(recording, series)
    (tmp_path / "requirements.toml").write_text(REQUIREMENTS)
    (tmp_path / "floor.ttl").write_text(ONTOLOGY)
    return tmp_path / "requirements.toml", recording, tmp_path / "floor.ttl", series


def test_every_requirement_of_a_file_gives_the_naive_evaluators_verdicts(floor: tuple[Path, Path, Path, Any]) -> None:
    """forall with an ontology (one series per robot, per pair), a template binding, a lookup,
    dist, a foreach with its own binding and idle time, and a plain formula: each series equals
    the naive evaluator's over a formula written out by hand."""
    from dyknow.ontology import Ontology

    requirements_path, recording, ontology, series = floor
    requirements = load_requirements(requirements_path)
    assert [r.where for r in requirements] == [f"{requirements_path}:{n}" for n in (6, 10, 14, 20)]
    results = check_recording(requirements, recording, individuals=Ontology.load([ontology]).individuals)
    expected = by_hand(series)
    for result in results:
        assert result.error is None, result.error
        assert result.verdicts == expected[result.requirement.name], result.requirement.name
    held = {r.requirement.name: r.held for r in results}
    assert held == {"speed under the zone's limit": False, "robots keep apart": False, "each robot seen is slow for 300 ms": False,
                    "the dock's limit is set": True}  # fmt: skip
    speed = results[0]
    assert sorted(speed.false_spans()) == ["r2"]  # only r2 sped in the dock
    assert sorted(results[1].false_spans()) == ["r1/r3", "r3/r1"]
    # explained: each atom's sides at the first state of each run of false verdicts, as the data says
    assert speed.why == {("r2", t): ["State(r2).speed <= Limits(floor)[State(r2).zone]: 0.9 <= 0.5"] for t in (2_007_000_000, 2_207_000_000)}
    assert results[1].why[("r1/r3", 3_014_000_000)] == ['State(r1).id == State(r3).id: "r1" == "r3"', "dist(State(r1), State(r3)) > 0.5: 0.2 > 0.5"]
    # a foreach's object: its body's atoms over its own samples (r2's 32nd sample, the only fast one)
    seen_at = series["floor/seen"][31][0]
    assert results[2].why == {("r2", seen_at): ["Seen(floor).speed < 1.5: 1.7 < 1.5"]}


@pytest.mark.process
def test_dyknow_check_exits_1_and_writes_the_same_junit_report_every_time(floor: tuple[Path, Path, Path, Any], tmp_path: Path) -> None:
    """The CLI as CI runs it: exit 1 (a requirement was false), a line per requirement, and a
    JUnit XML report whose failures say where and when; 10 runs, the same bytes."""
    requirements_path, recording, ontology, _ = floor
    reports = []
    for i in range(10):
        junit = tmp_path / f"report{i}.xml"
        done = run_cli("check", str(requirements_path), "--mcap", str(recording), "--ontology", str(ontology), "--junit", str(junit))
        assert done.returncode == 1, done.stderr
        reports.append(junit.read_bytes())
    assert len(set(reports)) == 1
    lines = done.stdout.splitlines()
    assert lines[0].startswith("FALSE  speed under the zone's limit") and "false for r2 at t=2.007 s" in lines[0], lines[0]
    assert "r2: false at t=2.007 s\n" in done.stdout and "r2: false from t=2.207 s to t=2.307 s" in done.stdout
    assert lines[-1] == "4 requirements: 1 held, 3 false, 0 not checked"
    suite = ET.fromstring(reports[0]).find("testsuite")
    assert suite is not None and (suite.get("tests"), suite.get("failures"), suite.get("errors")) == ("4", "3", "0")
    cases = {case.get("name"): case for case in suite.iter("testcase")}
    failure = cases["speed under the zone's limit"].find("failure")
    assert failure is not None and "r2: false at t=2.007 s" in (failure.text or "")
    assert cases["the dock's limit is set"].find("failure") is None
    as_json = run_cli("check", str(requirements_path), "--mcap", str(recording), "--ontology", str(ontology), "--json")
    rows = [json.loads(line) for line in as_json.stdout.splitlines()]
    assert [r["held"] for r in rows] == [False, False, False, True] and rows[0]["false"]["r2"][0][0] == 2_007_000_000


@pytest.mark.process
def test_dyknow_check_writes_every_verdict_to_an_mcap_file_foxglove_plots(floor: tuple[Path, Path, Path, Any], tmp_path: Path) -> None:
    """``--verdicts FILE.mcap``: a topic per requirement and instance, every verdict at its
    state's time (the recording's time base, so Foxglove shows both files on one timeline), a JSON
    schema with the fields a State Transitions panel plots, and the atoms' values at each change.
    Read back with the ``mcap`` library, against the naive evaluator's series."""
    from mcap.reader import make_reader

    requirements_path, recording, ontology, series = floor
    out = tmp_path / "verdicts.mcap"
    done = run_cli("check", str(requirements_path), "--mcap", str(recording), "--ontology", str(ontology), "--verdicts", str(out))
    assert done.returncode == 1, done.stderr
    expected = by_hand(series)
    got: dict[str, list[tuple[int, Any]]] = {}
    schemas: dict[str, Any] = {}
    whys: dict[str, list[tuple[int, Any]]] = {}
    with out.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            payload = json.loads(message.data)
            assert channel.message_encoding == "json" and schema is not None and schema.encoding == "jsonschema"
            schemas[channel.topic] = json.loads(schema.data)
            assert message.log_time == message.publish_time
            got.setdefault(channel.topic, []).append((message.log_time, payload["verdict"]))
            assert payload["state"] == {True: "true", False: "false", None: "unknown"}[payload["verdict"]]
            if "why" in payload:
                whys.setdefault(channel.topic, []).append((message.log_time, payload["why"]))
    want = {f"verdicts/{name.replace(' ', '_')}" + (f"/{instance}" if instance else ""): verdicts
            for name, by_instance in expected.items() for instance, verdicts in by_instance.items()}  # fmt: skip
    assert got == want
    topic = "verdicts/speed_under_the_zone's_limit/r2"
    assert schemas[topic]["properties"]["state"]["type"] == "string"
    # the atoms' values at each change of r2's verdict: the first verdict, each fall and each rise
    changes = [(t, v) for i, (t, v) in enumerate(want[topic]) if i == 0 or want[topic][i - 1][1] is not v]
    assert [t for t, _ in whys[topic]] == [t for t, _ in changes] and len(changes) == 5
    assert whys[topic][1] == (2_007_000_000, ["State(r2).speed <= Limits(floor)[State(r2).zone]: 0.9 <= 0.5"])
    assert "each_robot_seen_is_slow_for_300_ms/r1" in {t.removeprefix("verdicts/") for t in got}
    fell = [why for t, why in whys["verdicts/each_robot_seen_is_slow_for_300_ms/r2"] if t == series["floor/seen"][31][0]]
    assert fell == [["Seen(floor).speed < 1.5: 1.7 < 1.5"]]  # a foreach object's change, over its own samples


@pytest.mark.process
def test_a_requirement_that_cannot_be_checked_is_an_error_and_the_others_are_checked(floor: tuple[Path, Path, Path, Any], tmp_path: Path) -> None:
    """A typo in a formula, a term without a binding and a topic the recording lacks: each an
    error naming the file, the line and the requirement; the rest still checked, and the report
    has an <error> for each."""
    _, recording, _, _ = floor
    bad = tmp_path / "bad.toml"
    bad.write_text(
        '[bindings]\n"Limits(floor)" = "floor/limits"\n"Gone(x)" = "floor/gone"\n\n'
        '[[requirement]]\nname = "typo"\nformula = "Limits(floor).dock >"\n\n'
        '[[requirement]]\nname = "unbound"\nformula = "Limit(floor).dock > 0"\n\n'
        '[[requirement]]\nname = "no topic"\nformula = "Gone(x) > 0"\n\n'
        '[[requirement]]\nname = "fine"\nformula = "Limits(floor).aisle > 1"\n'
    )
    junit = tmp_path / "bad.xml"
    done = run_cli("check", str(bad), "--mcap", str(recording), "--junit", str(junit))
    assert done.returncode == 1
    lines = done.stdout.splitlines()
    assert lines[0].startswith(f"ERROR  typo      not checked: {bad}:5: requirement 'typo': formula column 21: unexpected end of formula"), lines[0]
    assert f"{bad}:9: requirement 'unbound': no topic for Limit(floor)" in lines[1] and "did you mean 'Limits(floor)'" in lines[1], lines[1]
    assert f"{bad}:13: requirement 'no topic': the recording has no topic 'floor/gone' (for Gone(x))" in lines[2], lines[2]
    assert lines[3].startswith("held   fine") and lines[-1] == "4 requirements: 1 held, 0 false, 3 not checked"
    suite = ET.fromstring(junit.read_bytes()).find("testsuite")
    assert suite is not None and (suite.get("failures"), suite.get("errors")) == ("0", "3")


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ("[[requirement]]\nname = 'a'\nformula = 'x > 0'\nformla = 'y'\n", ":1: requirement 1: unknown field 'formla'; expected one of"),
        ("[[requirement]]\nname = 'a'\n", ":1: requirement 1: no formula"),
        ("[[requirement]]\nname = 'a'\nformula = 'x > 0'\n[[requirement]]\nname = 'a'\nformula = 'x > 1'\n", ":4: requirement 2: a second requirement named 'a'"),
        ("[bindings]\n'State(r)' = 'floor/{robot}/state'\n[[requirement]]\nname = 'a'\nformula = 'x > 0'\n", "names {robot}, no argument of State(r)"),
        ("[bindigs]\n[[requirement]]\nname = 'a'\nformula = 'x'\n", "unknown table or key 'bindigs'; expected [bindings] and [[requirement]] tables (did you mean 'bindings'?)"),
        ("[[requirement]\nname = 'a'\n", "not TOML"),
        ("[bindings]\n", "no requirement"),
        ("[[requirement]]\nname = 'a'\nformula = 'x > 0'\nidle_ms = -1\n", "idle_ms = -1; expected a positive number of milliseconds"),
    ],
)
def test_a_malformed_requirements_file_is_refused_naming_its_line_and_field(tmp_path: Path, text: str, said: str) -> None:
    path = tmp_path / "r.toml"
    path.write_text(text)
    with pytest.raises(FormulaError) as refused:
        load_requirements(path)
    assert str(path) in str(refused.value) and said in str(refused.value), str(refused.value)


def test_a_junit_report_escapes_what_the_file_says() -> None:
    """Names and formulas are the user's text: a report with <, & and quotes in them is well-formed XML."""
    from dyknow.reasoning.requirements import Requirement, Result

    requirement = Requirement('a < b & "c"\x01', "x < 1 and y > 2", {"x": "x", "y": "y"}, where="r.toml:3")
    result = Result(requirement, {"": [(1_000, True), (2_000, False)]})
    root = ET.fromstring(junit_xml([result], recording="<run>.mcap"))
    case = root.find("testsuite/testcase")
    assert case is not None and case.get("name") == 'a < b & "c"\ufffd' and case.get("classname") == "r.toml"  # (no control character in XML)
    failure = case.find("failure")
    assert failure is not None and "x < 1 and y > 2" in (failure.text or "")


def test_a_live_run_recorded_then_checked_gives_the_live_monitors_verdicts(make_manager: Any, tmp_path: Path) -> None:
    """Two monitors run live on a manager (a window over a lookup, and a foreach) while a
    recorder records the keys they read; the recording checked afterwards as a requirements
    file gives every verdict the live monitors published, at the same times. The comparison
    starts once both the monitors and the recorder receive every key (the samples before may
    reach one and not the other), and past the longest window after it; it is made with the
    freshness each live monitor derived (tests/live_support.py)."""
    import time

    from dyknow.reasoning.objects import DEFAULT_IDLE_NS
    from dyknow.testing import Sink
    from dyknow.transport import Session, make_config
    from tests.conftest import free_port
    from tests.live_support import fresh_verdicts, from_start, publish_recorded

    manager = make_manager(listen=[f"tcp/127.0.0.1:{free_port()}"], queue_depth=100_000)  # (the sinks keep every verdict, however slow)
    plain = "historically[0, 300ms] State(r1).speed <= Limits(floor)[State(r1).zone]"
    objects = "foreach r in Seen(floor).id: historically[0, 200ms] Seen(floor).speed < 1.5"
    keys = {"State(r1)": "floor/r1/state", "Limits(floor)": "floor/limits", "Seen(floor)": "floor/seen"}
    watched, units, topics = {}, {}, {}
    for name, formula in (("plain", plain), ("objects", objects)):
        topics[name] = {t: k for t, k in keys.items() if t.split("(")[0] in formula}
        # (three keys from one session: on a loaded machine their samples reach the monitor out of time
        # order by more than a first reorder delay of 0 allows; what it would drop, the recording keeps)
        key = manager.monitor(formula, bindings=topics[name], reorder_ms=1000)
        manager.spawn("sink", name, bindings={"in": key})
        sink = manager.unit(name)
        assert isinstance(sink, Sink)
        watched[name] = sink
        (info,) = [m for m in manager.monitors() if m.key == key]
        units[name] = manager.unit(info.units[0])

    def verdicts(name: str) -> list[dict[str, Any]]:
        return [m.payload for m in list(watched[name].messages) if isinstance(m.payload, dict) and "verdict" in m.payload]

    live = tmp_path / "live.mcap"
    seq = [0]
    with Session(make_config(connect=manager.endpoints)) as session, Recorder(["floor/**"], live, connect=manager.endpoints) as recorder:
        publishers = {k: session.declare_publisher(k, reliable=True) for k in keys.values()}

        def put(key: str, payload: Any) -> None:
            seq[0] += 1
            now = time.time_ns()
            publishers[key].put(Message(payload, seq[0], now, now, key))

        def publish(i: int) -> None:
            put("floor/limits", {"dock": 0.5, "aisle": 2.0})
            put("floor/r1/state", {"zone": "dock" if i % 7 < 4 else "aisle", "speed": 0.9 if i % 40 == 3 else 0.3})
            put("floor/seen", {"id": f"r{i % 3}", "speed": 1.7 if i % 13 == 6 else 0.4})

        start_ns = publish_recorded(
            recorder,
            publish,
            lambda: bool(verdicts("plain") and verdicts("objects")),
            lambda t_ns: all(v and v[-1]["t_ns"] >= t_ns for v in map(verdicts, watched)),
            units.values,
            topics=3,
            count=150,
        )
    trimmed = from_start(live, start_ns, tmp_path / "trimmed.mcap")
    (tmp_path / "live.toml").write_text(
        "[bindings]\n" + "".join(f'"{t}" = "{k}"\n' for t, k in keys.items())
        + f'\n[[requirement]]\nname = "plain"\nformula = "{plain}"\n\n[[requirement]]\nname = "objects"\nformula = "{objects}"\n'
    )  # fmt: skip
    results = {r.requirement.name: r for r in check_recording(load_requirements(tmp_path / "live.toml"), trimmed)}
    settled = start_ns + 500_000_000  # past the longest window (300 ms) and a lookup's first sample
    for name, formula in (("plain", plain), ("objects", objects)):
        judged = [v for v in verdicts(name) if v["t_ns"] >= settled]
        assert len(judged) > 50, name  # (about 100: a state every 10 ms of sleep, fewer on a loaded machine)
        # up to the state each object has been judged to: an object's verdicts come in time order,
        # but one object's may be published before another's of an earlier state
        newest: dict[str, int] = {}
        for v in judged:
            newest[v.get("object", "")] = max(newest.get(v.get("object", ""), 0), v["t_ns"])
        upto = min(newest.values())
        ages = units[name].ages
        fresh = fresh_verdicts(formula, trimmed, topics[name], ages, idle_ns=DEFAULT_IDLE_NS if name == "objects" else None)
        expected = {k: v for k, v in fresh.items() if settled <= k[1] <= upto and v is not None}
        assert {(v.get("object", ""), v["t_ns"]): v["verdict"] for v in judged if v["t_ns"] <= upto} == expected, (name, ages)
        assert {v["verdict"] for v in judged} == {True, False}, name
        # and the requirements file (no freshness asked) decides each of them the same
        offline = {(key, t): v for key, series in results[name].verdicts.items() for t, v in series}
        assert all(offline[k] is v for k, v in expected.items()), name


def _relay(label: str, key: str, tag: str) -> str:
    """A spec bringing the stream on ``key`` to the planner as ``tag`` (a robot's driver's output)."""
    return f"""<transformation><label>{label}</label><source>transformations.generic:RemoteStream</source>
  <params><param name="key">{key}</param><param name="grace_s" type="float">5</param></params>
  <ports><port type="in">in</port><port type="out">out</port></ports><tags><tag port="out">{tag}</tag></tags></transformation>"""


def test_live_forall_monitors_recorded_then_checked_give_the_same_verdicts(make_manager: Any, tmp_path: Path) -> None:
    """``forall`` and nested ``forall`` over an ontology, live: their terms planned by meaning
    (each robot's state and the limits relayed from the keys their drivers publish on), a monitor
    per individual and per pair; the keys recorded meanwhile, then checked as a requirements file
    with ``--ontology`` and a template binding: every instance's verdicts equal the live ones, at
    the same times."""
    import time

    from dyknow.ontology import Ontology
    from dyknow.testing import Sink, Source
    from tests.live_support import fresh_verdicts, from_start, publish_recorded

    (tmp_path / "floor.ttl").write_text(ONTOLOGY)
    robots = ("r1", "r2", "r3")
    # (900 verdicts a second reach one sink: its queue holds every one, however long it waits for the CPU)
    manager = make_manager(ontology=[tmp_path / "floor.ttl"], listen=["tcp/127.0.0.1:0"], queue_depth=100_000)
    relays = [_relay(f"state-{r}", f"floor/{r}/state", f"State({r})") for r in robots] + [_relay("limits", "floor/limits", "Limits(floor)")]
    manager.add_transformation(f"<transformations>{''.join(relays)}</transformations>")
    drivers: dict[str, Source] = {}
    for key in [*(f"floor/{r}/state" for r in robots), "floor/limits"]:
        manager.spawn("publisher", key.replace("/", "-"), bindings={"out": key})
        driver = manager.unit(key.replace("/", "-"))
        assert isinstance(driver, Source)
        drivers[key] = driver
        driver.emit({"id": key, "zone": "dock", "speed": 0.3, "x": 0.0, "dock": 0.5, "aisle": 2.0})  # (a producer for the relays to find)
    formulas = {"speed": "forall r in ex:Robot: historically[0, 300ms] State(r).speed <= Limits(floor)[State(r).zone]",
                "apart": "forall a in ex:Robot: forall b in ex:Robot: State(a).id == State(b).id or abs(State(a).x - State(b).x) > 0.5"}  # fmt: skip
    watched: dict[str, tuple[str, Sink]] = {}
    for name, formula in formulas.items():  # (the relays run side by side: a reorder delay takes their samples in time order,
        key = manager.monitor(formula, reorder_ms=1000)  # however far one falls behind on a loaded machine)
        manager.spawn("sink", name, bindings={"in": key})
        sink = manager.unit(name)
        assert isinstance(sink, Sink)
        watched[name] = (key.split("/*")[0] + "/", sink)

    def verdicts(name: str) -> dict[str, list[dict[str, Any]]]:
        prefix, sink = watched[name]
        out: dict[str, list[dict[str, Any]]] = {}
        for m in list(sink.messages):
            if isinstance(m.payload, dict) and "verdict" in m.payload:
                out.setdefault(m.key.removeprefix(prefix), []).append(m.payload)
        return out

    def publish(i: int) -> None:
        now = time.time_ns()
        drivers["floor/limits"].emit({"dock": 0.5, "aisle": 2.0}, origin_ns=now)
        for k, r in enumerate(robots):
            state = {"id": r, "zone": "dock" if (i + k) % 5 else "aisle", "speed": 0.9 if (i + k) % 17 == 3 else 0.3, "x": 2.0 * k}
            if r == "r3" and i % 23 < 3:
                state["x"] = 0.2  # next to r1
            drivers[f"floor/{r}/state"].emit(state, origin_ns=now + k + 1)

    live = tmp_path / "live.mcap"
    with Recorder(["floor/**"], live, connect=manager.endpoints) as recorder:
        start_ns = publish_recorded(
            recorder,
            publish,
            lambda: len(verdicts("speed")) == 3 and len(verdicts("apart")) == 9,
            lambda t_ns: all(v[-1]["t_ns"] >= t_ns for name in formulas for v in verdicts(name).values()),
            lambda: [manager.unit(unit) for info in manager.monitors() for unit in info.units],
            topics=4,
            count=250,
        )
    trimmed = from_start(live, start_ns, tmp_path / "trimmed.mcap")
    (tmp_path / "live.toml").write_text(
        '[bindings]\n"State(r)" = "floor/{r}/state"\n"Limits(floor)" = "floor/limits"\n'
        + "".join(f'\n[[requirement]]\nname = "{name}"\nformula = "{formula}"\n' for name, formula in formulas.items())
    )  # fmt: skip
    checked = check_recording(load_requirements(tmp_path / "live.toml"), trimmed, individuals=Ontology.load([tmp_path / "floor.ttl"]).individuals)
    results = {r.requirement.name: r for r in checked}
    settled = start_ns + 500_000_000  # past the longest window (300 ms) and a lookup's first sample
    topics = {**{f"State({r})": f"floor/{r}/state" for r in robots}, "Limits(floor)": "floor/limits"}
    for name, instances in (("speed", 3), ("apart", 9)):
        assert results[name].error is None, results[name].error
        live_verdicts = verdicts(name)
        assert sorted(live_verdicts) == sorted(results[name].verdicts) and len(live_verdicts) == instances, (sorted(live_verdicts), sorted(results[name].verdicts))
        (info,) = [m for m in manager.monitors() if m.formula == formulas[name]]
        for _individual, formula, unit_name, verdict_key in info.expansions:
            instance = verdict_key.removeprefix(watched[name][0])
            judged = [v for v in live_verdicts[instance] if v["t_ns"] >= settled]
            assert len(judged) > 100, (name, instance)
            # with the freshness the live monitor derived (tests/live_support.py)
            ages = manager.unit(unit_name).ages
            fresh = fresh_verdicts(formula, trimmed, topics, ages)
            expected = {t: v for (_, t), v in fresh.items() if settled <= t <= judged[-1]["t_ns"] and v is not None}
            assert {v["t_ns"]: v["verdict"] for v in judged} == expected, (name, instance, ages)
            offline = dict(results[name].verdicts[instance])
            assert all(offline[t] is v for t, v in expected.items()), (name, instance)
    assert {v["verdict"] for v in verdicts("speed")["r2"]} == {True, False}
    assert {v["verdict"] for v in verdicts("apart")["r1/r3"]} == {True, False}


@pytest.mark.process
def test_the_how_to_pages_requirements_give_the_lines_it_shows(floor: tuple[Path, Path, Path, Any], tmp_path: Path) -> None:
    """docs/howto/requirements-in-ci.md: its requirements file, checked over this module's floor
    recording by its command, prints every line the page shows (and exits 1, as it says)."""
    import re

    from tests.conftest import REPO

    page = (REPO / "docs" / "howto" / "requirements-in-ci.md").read_text()
    toml = re.search(r"```toml\n(.*?)```", page, re.DOTALL)
    shown = re.search(r"```text\n(.*?)```", page, re.DOTALL)
    command = re.search(r"^dyknow check (\S+) --mcap \S+ --ontology \S+ --junit (\S+)$", page, re.MULTILINE)
    assert toml and shown and command
    (tmp_path / command.group(1)).write_text(toml.group(1))
    _, recording, ontology, _ = floor
    done = run_cli("check", str(tmp_path / command.group(1)), "--mcap", str(recording), "--ontology", str(ontology), "--junit", str(tmp_path / command.group(2)))
    assert done.returncode == 1, done.stderr
    printed = done.stdout.splitlines()
    assert [line for line in shown.group(1).splitlines() if line != "..." and line not in printed] == [], done.stdout


@pytest.mark.process
def test_dyknow_monitor_checks_a_forall_formula_over_a_recording_per_individual(floor: tuple[Path, Path, Path, Any]) -> None:
    """Issue 54 item 6: `dyknow monitor 'forall ...' --mcap --ontology` with a template binding:
    a series per individual, each the naive evaluator's over the formula written out by hand;
    without --ontology it says what is missing."""
    _, recording, ontology, series = floor
    formula = "forall r in ex:Robot: State(r).speed <= Limits(floor)[State(r).zone]"
    binds = ["--bind", "State(r)=floor/{r}/state", "--bind", "Limits(floor)=floor/limits"]
    done = run_cli("monitor", formula, "--mcap", str(recording), *binds, "--ontology", str(ontology), "--json")
    assert done.returncode == 0, done.stderr
    got: dict[str, list[tuple[int, Any]]] = {}
    for row in map(json.loads, done.stdout.splitlines()):
        got.setdefault(row["individual"], []).append((row["t_ns"], row["verdict"]))
    assert got == by_hand(series)["speed under the zone's limit"]
    missing = run_cli("monitor", formula, "--mcap", str(recording), *binds)
    assert missing.returncode == 2 and "needs --ontology FILE" in missing.stderr
