"""Formulas asked for by meaning (dyknow.reasoning.monitors): a manager plans a stream for every
term, keeps them flowing, and publishes the verdicts on a key that outlives failures."""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from dyknow import Client, FormulaError, Manager, Message, PlanningError
from dyknow.reasoning import evaluate
from dyknow.testing import CAMERA_IDS, SCENARIO_HOSTS, Sink
from tests.conftest import GENERIC_SPECS, REPO, UNIT_SPECS, free_port, wait_until

ONTOLOGY = REPO / "specs" / "dyknow.ttl"
TRACK = "BallTrack(field)"
BOTTOM, CEILING = CAMERA_IDS["bottom"], CAMERA_IDS["ceiling"]


@pytest.fixture
def system(make_manager: Callable[..., Manager]) -> Callable[..., dict[str, Manager]]:
    """The scenario's three managers on loopback (station, robot, field), deep queues."""

    def start(station_specs: Any = None, **kwargs: Any) -> dict[str, Manager]:
        hub = f"tcp/127.0.0.1:{free_port()}"
        managers: dict[str, Manager] = {}
        for i, name in enumerate(("station", "robot", "field")):
            specs = station_specs if name == "station" and station_specs is not None else SCENARIO_HOSTS[name]
            managers[name] = make_manager(name, specs=[specs], ontology=[ONTOLOGY], listen=[hub] if i == 0 else ["tcp/127.0.0.1:0"],
                                          connect=[] if i == 0 else [hub], queue_depth=100_000, **kwargs)  # fmt: skip
        for manager in managers.values():
            wait_until(lambda m=manager: len(m.reachable()) == 2, f"{manager.name} to see the others")  # type: ignore[misc]
        return managers

    return start


def _sink(manager: Manager, name: str, key: str, label: str = "consumer") -> Sink:
    manager.spawn(label, name, bindings={"in": key})
    sink = manager.unit(name)
    assert isinstance(sink, Sink)
    return sink


def test_a_monitor_asked_by_meaning_keeps_its_key_and_says_where_a_gap_was(system: Callable[..., dict[str, Manager]]) -> None:
    """'The robot's camera feeds the track': true while it does; the robot's manager goes, the
    term is re-planned onto the field's camera, the verdicts go on on the same key, the first one
    after says a gap occurred and why, and they turn false. Every verdict published equals
    evaluate() over the samples the monitor's stream carried (recorded beside it)."""
    m = system(dwell_s=0.5)
    station = m["station"]
    feed = station.request(TRACK)  # the monitor's term shares this request: a sink sees its samples
    samples = _sink(station, "samples", feed)
    formula = f"{TRACK}.camera == {BOTTOM}"
    key = station.monitor(formula)
    assert key == "dyknow/station/monitors/1"
    (info,) = station.monitors()
    assert info.terms == {TRACK: feed} and info.units == ("monitor-1",)
    assert station.get_model().to_dict()["monitors"][0]["formula"] == formula
    verdicts = _sink(station, "verdicts", key)
    verdicts.wait_until(lambda msg: msg.payload["verdict"] is True, timeout_s=10)
    before = len(verdicts.messages)  # (what comes while the robot closes counts: on a busy machine that is all of it)
    m["robot"].close()

    def after_close(what: Callable[[Message], bool]) -> Message | None:
        return next((msg for msg in list(verdicts.messages)[before:] if what(msg)), None)

    wait_until(lambda: after_close(lambda msg: "gap" in msg.payload) is not None, "a verdict saying where the gap was")
    gap = after_close(lambda msg: "gap" in msg.payload)
    assert gap is not None and gap.payload["gap"] == {"term": TRACK, "cause": "manager 'robot' was lost"}
    wait_until(lambda: after_close(lambda msg: msg.payload["verdict"] is False) is not None, "a false verdict after the gap")
    station.destroy("monitor-1")  # no more verdicts: compare what was published with the samples
    published = {msg.payload["t_ns"]: msg.payload["verdict"] for msg in verdicts.messages}
    expected = dict(evaluate(formula, {TRACK: [(msg.origin_ns / 1e9, msg.payload) for msg in samples.messages]}))
    assert published and all(expected[t_ns / 1e9] is verdict for t_ns, verdict in published.items())
    assert True in published.values() and False in published.values()


def test_a_monitor_released_takes_its_units_and_requests_down(system: Callable[..., dict[str, Manager]]) -> None:
    m = system()
    station = m["station"]
    with Client("station", connect=station.endpoints) as client:
        key = client.monitor(f"historically[0, 1s] {TRACK}.tracked > 0", reorder_ms=5)
        assert key == "dyknow/station/monitors/1" and [u.name for u in station.units() if u.name.startswith("monitor")] == ["monitor-1"]
        assert station.requests()[0].tag == TRACK
        client.release(key)
    assert not any(u.name.startswith("monitor") for u in station.units()) and station.requests() == []
    wait_until(lambda: m["robot"].units() == [], "the robot's camera to go with the request")


def test_a_bad_formula_or_a_term_nothing_provides_is_refused_and_nothing_stays(system: Callable[..., dict[str, Manager]]) -> None:
    m = system()
    station = m["station"]
    with Client("station", connect=station.endpoints) as client:
        with pytest.raises(FormulaError, match="column"):
            client.monitor(f"{TRACK}.camera ==")
        with pytest.raises(PlanningError, match="nothing provides Unheard"):
            client.monitor(f"{TRACK}.camera == 1 and Unheard(x) > 0")
        with pytest.raises(Exception, match="reorder_ms"):
            client.monitor(f"{TRACK}.camera == 1", reorder_ms=-1)
    assert station.requests() == [] and station.monitors() == [] and not station.units()


LEVELS = """<transformation><label>level(${Cam})</label><source>tests.units:Level</source>
  <args><arg label="Cam" class="dk:Camera"/></args>
  <params><param name="rate_hz" type="float">20</param><param name="value" type="float">1</param></params>
  <ports><port type="out">out</port></ports><tags><tag port="out">Fresh(${Cam})</tag></tags></transformation>"""


def test_a_quantified_formula_is_one_monitor_per_individual(make_manager: Callable[..., Manager]) -> None:
    """forall c in Camera: one monitor per camera of the ontology, each on its own key under the
    returned key expression; an unknown class, or a variable no term takes, is refused."""
    manager = make_manager(ontology=[ONTOLOGY], specs=[REPO / "tests" / "units.xml", REPO / "specs" / "generic.xml"], queue_depth=10_000)
    manager.add_transformation(LEVELS)
    key = manager.monitor("forall c in Camera: always[0, 100ms] Fresh(c).value > 0")
    assert key == f"dyknow/{manager.name}/monitors/1/*"
    (info,) = manager.monitors()
    assert sorted(i for i, _, _, _ in info.expansions) == ["bottom", "ceiling", "top"]
    assert {f for _, f, _, _ in info.expansions} == {f"always[0, 100ms] Fresh({c}).value > 0" for c in ("bottom", "ceiling", "top")}
    verdicts = _sink(manager, "verdicts", key, label="sink")
    wait_until(lambda: {m.key for m in verdicts.messages if m.payload["verdict"]} == {k for _, _, _, k in info.expansions}, "a true verdict per camera")
    with pytest.raises(FormulaError, match="the variable 'd' is not used in the formula"):
        manager.monitor("forall d in Camera: Fresh(c).value > 0")
    with pytest.raises(FormulaError, match="forall over 'dk:Nothing': unknown ontology class 'dk:Nothing'"):
        manager.monitor("forall c in dk:Nothing: Fresh(c).value > 0")
    with pytest.raises(FormulaError, match="expected 'in' after the variable: forall c in"):
        manager.monitor("forall c Camera: Fresh(c).value > 0")
    manager.release(key)
    assert manager.monitors() == [] and not any(u.name.startswith("monitor") for u in manager.units())


def test_a_nested_quantified_monitor_lives_as_long_as_its_holder(make_manager: Callable[..., Manager]) -> None:
    """Issue 54 item 1: ``forall a: forall b:`` over the ontology's 3 cameras, asked for by a
    client, is 9 pair monitors on ``<key>/<a>/<b>``; each one's verdicts go on for 60 s, six
    times the manager's grace for a holder that is gone. (They all stopped after the grace: the
    client's holder token was declared on ``<key>/*/holders/<id>``, the manager watched
    ``<key>/holders/<id>``, so the holder was never seen and its monitor released.) Released by
    the client, they all go."""
    manager = make_manager(ontology=[ONTOLOGY], specs=[REPO / "tests" / "units.xml", REPO / "specs" / "generic.xml"], queue_depth=10_000,
                           client_grace_s=10.0)  # fmt: skip
    manager.add_transformation(LEVELS)
    with Client(manager.name, connect=manager.endpoints, timeout_s=30) as client:
        key = client.monitor("forall a in Camera: forall b in Camera: a != b implies Fresh(a).value > 0 and Fresh(b).value > 0")
        assert key == f"dyknow/{manager.name}/monitors/1/*/*"
        (info,) = manager.monitors()
        pairs = {k for _, _, _, k in info.expansions}
        assert len(pairs) == 9 and f"dyknow/{manager.name}/monitors/1/top/bottom" in pairs
        verdicts = _sink(manager, "verdicts", key, label="sink")
        started = time.monotonic()
        wait_until(lambda: {m.key for m in verdicts.messages if m.payload["verdict"]} == pairs, "a true verdict per pair")
        time.sleep(max(0.0, 60.0 - (time.monotonic() - started)))
        seen = len(verdicts.messages)
        wait_until(lambda: {m.key for m in list(verdicts.messages)[seen:]} == pairs, "verdicts of every pair after 60 s")
        assert len(manager.monitors()) == 1 and len([u for u in manager.units() if u.name.startswith("monitor")]) == 9
        client.release(key)
    assert manager.monitors() == [] and not any(u.name.startswith("monitor") for u in manager.units())


def test_a_quantified_formula_is_bounded_before_it_is_expanded(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """Issue 38: a forall over 2,000 individuals with a 300-term body cost 134 s of manager CPU.
    Its cost (individuals times the body's nodes) is checked first now: refused at once, naming
    the count, the size and the bound, and nothing is requested or spawned."""
    ontology = tmp_path / "many.ttl"
    lines = ["@prefix ex: <http://example.org/many#> .", "@prefix owl: <http://www.w3.org/2002/07/owl#> .", "ex:Thing a owl:Class ."]
    lines += [f"ex:i{k} a ex:Thing ." for k in range(2000)]
    ontology.write_text("\n".join(lines) + "\n")
    manager = make_manager(ontology=[ontology])
    body = " or ".join(f"Level{k}(c) > 0" for k in range(150))  # 299 nodes
    with pytest.raises(FormulaError) as costly:
        manager.monitor(f"forall c in ex:Thing: {body}")
    assert costly.value.what == "forall over 'ex:Thing' expands to 2,000 formulas of 299 nodes each: 598,000 nodes"
    assert costly.value.expected == "at most 20,000 nodes in all (Limits.max_quantified_nodes): a smaller class or body"
    big = " or ".join(f"Level{k}(c) > 0" for k in range(300))  # 599 nodes: over the bound of one formula
    with pytest.raises(FormulaError) as large:
        manager.monitor(f"forall c in ex:Thing: {big}")
    assert large.value.what.startswith("the formula has more than 500 nodes")
    column = large.value.column
    assert column is not None and f"forall c in ex:Thing: {big}"[column - 1 :].startswith("or Level250(c)")  # the 501st node, in the whole text
    assert manager.monitors() == [] and manager.requests() == [] and manager.units() == []


# ---------------------------------------------------------------------------- the command line


LEVEL_SPEC = """<transformations><transformation><label>level</label><source>tests.units:Level</source>
  <params><param name="rate_hz" type="float">50</param><param name="value" type="float">2</param></params>
  <ports><port type="out">out</port></ports><tags><tag port="out">Fresh(x)</tag></tags></transformation></transformations>"""


@pytest.mark.process
def test_dyknow_monitor_prints_verdicts_as_they_come_and_releases_the_monitor(manager_process: Callable[..., Any], tmp_path: Any) -> None:
    import json

    from tests.conftest import run_cli

    (tmp_path / "level.xml").write_text(LEVEL_SPEC)
    proc = manager_process("--specs", str(tmp_path / "level.xml"))
    result = run_cli("monitor", "Fresh(x).value > 1 and once[0, 1s] Fresh(x).value > 1.5", "--duration", "2", "--json", *proc.client_args())
    assert result.returncode == 0, result.stderr
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(lines) > 20 and all(line["verdict"] is True and line["key"] == f"dyknow/{proc.name}/monitors/1" for line in lines)
    with Client(proc.name, connect=[proc.endpoint]) as client:
        model = client.get_model()
    assert model["monitors"] == [] and model["requests"] == []  # released when the command ended
    refused = run_cli("monitor", "Fresh(x).value >", *proc.client_args())
    assert refused.returncode == 1 and "formula column 17: unexpected end of formula" in refused.stderr and "Traceback" not in refused.stderr


def test_a_field_no_sample_holds_is_said_once_where_the_user_looks(make_manager: Callable[..., Manager], tmp_path: Any) -> None:
    """A typo in a field (valeu) gave 0 verdicts and nothing said: now the monitor warns once,
    naming the field and the fields the samples hold, in the model and on the verdicts key."""
    (tmp_path / "level.xml").write_text(LEVEL_SPEC)
    manager = make_manager(specs=[tmp_path / "level.xml", GENERIC_SPECS, UNIT_SPECS])
    key = manager.monitor("Fresh(x).valeu > 1")
    manager.spawn("sink", "watch", bindings={"in": key})
    watch = manager.unit("watch")
    assert isinstance(watch, Sink)
    wait_until(lambda: any(m.to_dict()["warnings"] for m in manager.monitors()), "the monitor's warning in the model")
    (info,) = manager.monitors()
    (warning,) = info.to_dict()["warnings"]
    assert "none of the first 20 samples of Fresh(x) holds the field 'valeu'" in warning and "value" in warning
    def said() -> list[Any]:
        return [m.payload for m in list(watch.messages) if isinstance(m.payload, dict) and "warning" in m.payload]

    wait_until(lambda: bool(said()), "the warning on the verdicts key")
    (payload,) = said()
    assert payload["field"] == "valeu" and "value" in payload["fields_seen"]


@pytest.mark.process
def test_dyknow_monitor_prints_times_since_it_started(manager_process: Callable[..., Any], tmp_path: Any) -> None:
    from tests.conftest import run_cli

    (tmp_path / "level.xml").write_text(LEVEL_SPEC)
    proc = manager_process("--specs", str(tmp_path / "level.xml"))
    result = run_cli("monitor", "Fresh(x).value > 1", "--duration", "2", *proc.client_args())
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines() if line.startswith("dyknow/")]
    assert lines and all(re.search(r"monitors/1  \+[0-9]+\.[0-9]{3} s  true", line) for line in lines), lines[:3]
    iso = run_cli("monitor", "Fresh(x).value > 1", "--duration", "1", "--iso", *proc.client_args())
    assert re.search(r"monitors/2  20[0-9]{2}-[0-9]{2}-[0-9]{2}T[0-9:.]+\+00:00  true", iso.stdout), iso.stdout[:300]


@pytest.mark.process
def test_dyknow_monitor_changes_only_prints_each_change_once(manager_process: Callable[..., Any], tmp_path: Any) -> None:
    """Issue 54 item 7: a formula whose verdict never changes (a level of 2 against 1) gives a
    line per state, and with --changes-only one line in all: its first verdict."""
    from tests.conftest import run_cli

    (tmp_path / "level.xml").write_text(LEVEL_SPEC)
    proc = manager_process("--specs", str(tmp_path / "level.xml"))
    every = run_cli("monitor", "Fresh(x).value > 1", "--duration", "2", *proc.client_args())
    once = run_cli("monitor", "Fresh(x).value > 1", "--duration", "2", "--changes-only", *proc.client_args())
    assert every.returncode == 0 and once.returncode == 0, once.stderr
    # while a monitor runs, the model's text names its unit's formula (not 'monitor-3' alone)
    import subprocess
    import sys

    from tests.conftest import subprocess_env, wait_until

    running = subprocess.Popen([sys.executable, "-m", "dyknow.cli", "monitor", "Fresh(x).value > 1", "--duration", "60", *proc.client_args()],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=subprocess_env())  # fmt: skip
    try:
        wait_until(lambda: any(line.endswith("running  monitors Fresh(x).value > 1") for line in run_cli("model", *proc.client_args()).stdout.splitlines()),
                   "the model's line of the monitor's unit, with its formula")  # fmt: skip
    finally:
        running.terminate()
        running.wait(30)
    verdicts = [[line for line in done.stdout.splitlines() if line.startswith("dyknow/")] for done in (every, once)]
    assert len(verdicts[0]) > 10 and len(verdicts[1]) == 1 and verdicts[1][0].rstrip().endswith("  true"), verdicts[1]


@pytest.mark.process
def test_dyknow_monitor_over_a_recording_is_evaluate_over_its_samples(tmp_path: Any) -> None:
    """The offline check: the same semantics over yesterday's data, state by state."""
    import json

    from dyknow import Message
    from dyknow.recording import Recorder
    from tests.conftest import run_cli

    samples = {"robot/battery": [(1_000_000_000 + i * 100_000_000, {"value": 1.0 - i * 0.07}) for i in range(14)],
               "robot/speed": [(1_050_000_000 + i * 300_000_000, {"value": float(i % 3)}) for i in range(5)]}  # fmt: skip
    path = tmp_path / "run.mcap"
    with Recorder((), path) as recorder:
        for key, series in samples.items():
            for seq, (t_ns, payload) in enumerate(series, start=1):
                recorder.write(Message(payload, seq, t_ns, t_ns, key))
    formula = "Speed(robot).value > 0 implies historically[0, 300ms] Battery(robot).value > 0.3"
    result = run_cli("monitor", formula, "--mcap", str(path), "--bind", "Battery(robot)=robot/battery", "--bind", "Speed(robot)=robot/speed", "--json")
    assert result.returncode == 0, result.stderr
    got = [(line["t_ns"], line["verdict"]) for line in map(json.loads, result.stdout.splitlines())]
    streams = {"Battery(robot)": [(t / 1e9, v) for t, v in samples["robot/battery"]], "Speed(robot)": [(t / 1e9, v) for t, v in samples["robot/speed"]]}
    assert [(round(t * 1e9), v) for t, v in evaluate(formula, streams)] == got
    assert {v for _, v in got} == {True, False}
    wrong = run_cli("monitor", formula, "--mcap", str(path), "--bind", "Battery(robot)=robot/batery", "--bind", "Speed(robot)=robot/speed")
    assert wrong.returncode == 1 and "the recording has no topic 'robot/batery'" in wrong.stderr and "did you mean 'robot/battery'" in wrong.stderr
    unbound = run_cli("monitor", formula, "--mcap", str(path), "--bind", "Speed(robot)=robot/speed")
    assert unbound.returncode == 1 and "no topic for Battery(robot)" in unbound.stderr
    # --changes-only: each change of the naive evaluator's verdicts, with the comparisons' values at it
    binds = ["--bind", "Battery(robot)=robot/battery", "--bind", "Speed(robot)=robot/speed"]
    changed = run_cli("monitor", formula, "--mcap", str(path), *binds, "--json", "--changes-only")
    rows = [json.loads(line) for line in changed.stdout.splitlines()]
    expected = [(t, v) for k, (t, v) in enumerate(got) if k == 0 or got[k - 1][1] is not v]
    assert [(r["t_ns"], r["verdict"]) for r in rows] == expected and len(expected) >= 2
    battery = dict(samples["robot/battery"])
    for row in rows:  # each side as the samples say at that time (the latest sample at or before it)
        level = battery[max(t for t in battery if t <= row["t_ns"])]["value"]
        speed = dict(samples["robot/speed"])[max(t for t, _ in samples["robot/speed"] if t <= row["t_ns"])]["value"]
        assert row["why"] == [f"Speed(robot).value > 0: {speed:.6g} > 0", f"Battery(robot).value > 0.3: {level:.6g} > 0.3"], row
    # --robustness: each subformula's robustness at each change, by hand from the quantitative
    # semantics: an atom x > c is x - c (the latest sample); historically is the least over the
    # window's states; implies is the larger of the premise's negation and the conclusion
    robust = run_cli("monitor", formula, "--mcap", str(path), *binds, "--json", "--changes-only", "--robustness")
    assert robust.returncode == 0, robust.stderr
    states = sorted({t for series in samples.values() for t, _ in series})

    def latest(key: str, t: int) -> float:
        return float(dict(samples[key])[max(s for s, _ in samples[key] if s <= t)]["value"])

    changed_rows = [json.loads(line) for line in robust.stdout.splitlines()]
    for row in changed_rows:  # (a past window at the trace's start reads the states there are)
        t = row["t_ns"]
        premise = latest("robot/speed", t) - 0
        window = min(latest("robot/battery", s) - 0.3 for s in states if t - 300_000_000 <= s <= t)
        expected = [max(-premise, window), premise, window, latest("robot/battery", t) - 0.3]
        said = [float(line.rsplit(": ", 1)[1]) for line in row["robustness"]]
        assert said == pytest.approx(expected, abs=1e-5), (row, expected)
        assert row["robustness"][0].startswith(f"{formula}: ")  # the whole formula first, then its subformulas
    assert len(changed_rows) == len(rows) >= 2
    refused = run_cli("monitor", formula, "--mcap", str(path), *binds, "--robustness")
    assert refused.returncode == 2 and "--robustness goes with --changes-only over a recording" in refused.stderr, refused.stderr


@pytest.mark.process
def test_dyknow_monitor_explains_each_change_of_a_foreach_object_over_its_own_samples(tmp_path: Any) -> None:
    """``foreach`` over a recording with ``--changes-only``: each object's changes, each with its
    body's comparisons over that object's own samples and the variable as the object's value
    (r2's speed, never r1's, beside it on the same key)."""
    import json

    from dyknow import Message
    from dyknow.recording import Recorder
    from tests.conftest import run_cli

    seen = [(1_000_000_000 + i * 50_000_000, {"id": ("r1", "r2")[i % 2], "speed": 1.9 if i in (7, 8, 9) else 0.2 + i / 100}) for i in range(20)]
    path = tmp_path / "seen.mcap"
    with Recorder((), path) as recorder:
        for seq, (t_ns, payload) in enumerate(seen, start=1):
            recorder.write(Message(payload, seq, t_ns, t_ns, "floor/seen"))
    formula = 'foreach r in Seen(floor).id: Seen(floor).speed < 1.5 or r == "r9"'
    done = run_cli("monitor", formula, "--mcap", str(path), "--bind", "Seen(floor)=floor/seen", "--json", "--changes-only")
    assert done.returncode == 0, done.stderr
    rows = [json.loads(line) for line in done.stdout.splitlines()]
    by_hand = []  # each object's changes, and its own latest sample at each
    for obj in ("r1", "r2"):
        own = [(t, p) for t, p in seen if p["id"] == obj]
        last = None
        for t, p in own:
            verdict = p["speed"] < 1.5
            if verdict is not last:
                by_hand.append((t, obj, verdict, [f"Seen(floor).speed < 1.5: {p['speed']:.6g} < 1.5", f'r == "r9": "{obj}" == "r9"']))
                last = verdict
    assert sorted((r["t_ns"], r["object"], r["verdict"], r["why"]) for r in rows) == sorted(by_hand)
    assert {r["object"] for r in rows if r["verdict"] is False} == {"r1", "r2"}
    # --robustness: each object's subformulas over its own samples, by hand: the atom is
    # 1.5 - its latest speed, the window the least of that over its own samples 100 ms back
    windowed = "foreach r in Seen(floor).id: historically[0, 100ms] Seen(floor).speed < 1.5"
    robust = run_cli("monitor", windowed, "--mcap", str(path), "--bind", "Seen(floor)=floor/seen", "--json", "--changes-only", "--robustness")
    assert robust.returncode == 0, robust.stderr
    robust_rows = [json.loads(line) for line in robust.stdout.splitlines()]
    assert {r["object"] for r in robust_rows if r["verdict"] is False} == {"r1", "r2"}
    for row in robust_rows:
        own = [(t, p["speed"]) for t, p in seen if p["id"] == row["object"] and t <= row["t_ns"]]
        window = min(1.5 - v for t, v in own if t >= row["t_ns"] - 100_000_000)
        said = [float(line.rsplit(": ", 1)[1]) for line in row["robustness"]]
        assert said == pytest.approx([window, 1.5 - own[-1][1]], abs=1e-6), row
    refused = run_cli("monitor", "forall r in ex:Robot: Battery(r) > 0", "--mcap", str(path), "--bind", "Battery(r)=floor/seen", "--changes-only", "--robustness")
    assert refused.returncode == 2 and "--robustness: a formula without forall or exists" in refused.stderr, refused.stderr


# ---------------------------------------------------------------------------- requirements close the loop


def test_a_false_requirement_moves_the_request_to_the_next_best_configuration(system: Callable[..., dict[str, Manager]]) -> None:
    """A request that requires its track to come from the ceiling camera starts on the robot's
    (the planner's preference): once the dwell time has passed, the requirement's false verdict
    is a fault, the request moves to the next-best configuration, and the adaptation names the
    formula as its cause; the verdicts are on a key of their own, the model lists the requirement."""
    m = system(dwell_s=0.3)
    station = m["station"]
    formula = f"{TRACK}.camera == {CEILING}"
    with Client("station", connect=station.endpoints) as client:
        key = client.request(TRACK, require=[formula])
        (info,) = client.get_model()["requests"]
    assert info["requirements"] == [formula] and "robot-camera@robot" in info["labels"]
    verdicts = _sink(station, "verdicts", f"{key}/requirements/1")
    wait_until(lambda: any(e.cause == f"requirement violated: {formula}" for e in station.get_adaptations()), "the requirement to make it adapt")
    moved = next(e for e in station.get_adaptations() if e.cause == f"requirement violated: {formula}")
    assert "robot-camera@robot" in moved.old and "ceiling-camera@field" in moved.new
    verdicts.wait_until(lambda msg: msg.payload["verdict"] is True, timeout_s=10)  # on the ceiling camera it holds
    # (the false verdicts came before the move, maybe before this sink subscribed: beside CPU hogs
    # the move was made before it; the adaptation's cause is the proof that one was false)
    station.release(key)
    assert station.requests() == [] and not any("require" in u.name for u in station.units())


def test_a_transformations_own_requirement_moves_its_requests_off_it(system: Callable[..., dict[str, Manager]], tmp_path: Any) -> None:
    """A spec may require formulas of its outputs: the station's detectors here require that the
    detections are not the bottom camera's. The request starts on the robot's bottom camera (the
    planner's preference), the requirement of ball-detector(bottom) is watched on that unit's
    output, its false verdict puts that transformation in back-off, the request moves to the
    ceiling camera, and the adaptation names the transformation and the formula; the model lists
    the watched requirement with its key, and a release takes its monitor down."""
    station_xml = (
        SCENARIO_HOSTS["station"]
        .read_text()
        .replace(
            '<tag port="out">BallObject(${Cam})</tag></tags>',
            f'<tag port="out">BallObject(${{Cam}})</tag></tags>\n    <requirements><requirement>BallObject(${{Cam}}).camera != {BOTTOM}</requirement></requirements>',
        )
    )
    assert "<requirements>" in station_xml
    (tmp_path / "station.xml").write_text(station_xml)
    m = system(station_specs=tmp_path / "station.xml", dwell_s=0.3)
    station = m["station"]
    formula = f"BallObject(bottom).camera != {BOTTOM}"
    cause = f"requirement of ball-detector(bottom) violated: {formula}"
    with Client("station", connect=station.endpoints) as client:
        key = client.request(TRACK)
        (info,) = client.get_model()["requests"]
    assert "robot-camera@robot" in info["labels"] and info["requirements"] == []
    (watched,) = info["spec_requirements"]
    assert watched["formula"] == formula and watched["transformation"] == "ball-detector(bottom)"
    _sink(station, "verdicts", watched["key"])  # (the key is served: a sink can bind it)
    wait_until(lambda: any(e.cause == cause for e in station.get_adaptations()), "the spec's requirement to make it adapt")
    moved = next(e for e in station.get_adaptations() if e.cause == cause)
    assert "robot-camera@robot" in moved.old and "ceiling-camera@field" in moved.new and "ball-detector(bottom)" not in moved.new
    # (its false verdict may have come before the sink subscribed: the cause is the proof of it)

    def watched_now() -> list[dict[str, Any]]:
        with Client("station", connect=station.endpoints) as client:
            (info,) = client.get_model()["requests"]
        return list(info["spec_requirements"])

    # (the adaptation is recorded before the new configuration's watches are set up: ask until they are)
    wait_until(lambda: [w["transformation"] for w in watched_now()] == ["ball-detector(ceiling)"], "the ceiling detector's requirement watched")
    (watched,) = watched_now()  # the ceiling's detector now, whose requirement holds
    assert watched["formula"] == f"BallObject(ceiling).camera != {BOTTOM}"
    ceiling = _sink(station, "ceiling-verdicts", watched["key"])
    ceiling.wait_until(lambda msg: msg.payload["verdict"] is True, timeout_s=10)
    station.release(key)
    assert station.requests() == [] and not any("require" in u.name for u in station.units() if not u.name.endswith("verdicts"))


def test_a_requirement_in_a_spec_that_does_not_read_is_refused_with_its_line(tmp_path: Any) -> None:
    from dyknow import SpecError
    from dyknow.spec import parse_specs

    xml = (
        "<transformation>\n  <label>t</label><source>a:B</source>\n"
        '  <ports><port type="out">out</port></ports><tags><tag port="out">Track(x)</tag></tags>\n'
        "  <requirements>\n    <requirement>always[0, 1s Track(x).ok</requirement>\n"
        "    <requirement>Other(x) &gt; 1</requirement>\n  </requirements>\n</transformation>\n"
    )
    with pytest.raises(SpecError) as caught:
        parse_specs(xml, "t.xml")
    message = str(caught.value)
    assert "t.xml:5: <requirement>: formula column 14" in message and "expected ']'" in message
    assert (
        "t.xml:6: <requirement>: 'Other(x) > 1' reads none of this transformation's outputs; expected a term that is one of its output tags (Track(x))"
        in message
    )
    (spec,) = parse_specs(xml.replace("always[0, 1s Track", "always[0, 1s] Track").replace("Other(x)", "Track(x).n"), "t.xml")
    assert spec.requirements == ("always[0, 1s] Track(x).ok", "Track(x).n > 1")
    (again,) = parse_specs(spec.to_xml(), "again.xml")  # written back and read (as another manager's summary is)
    assert again.requirements == spec.requirements and spec.to_dict()["requirements"] == list(spec.requirements)


def test_a_requirement_that_does_not_read_is_refused_before_anything_runs(system: Callable[..., dict[str, Manager]]) -> None:
    m = system()
    station = m["station"]
    with Client("station", connect=station.endpoints) as client, pytest.raises(FormulaError, match="formula column"):
        client.request(TRACK, require=[f"{TRACK}.camera =="])
    assert station.requests() == [] and station.units() == []


def test_the_tutorials_example_of_monitors_and_requirements_runs_as_written() -> None:
    """docs/tutorials/temporal.md: the block '# monitors and requirements, by meaning', verbatim."""
    import re

    page = (REPO / "docs" / "tutorials" / "temporal.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", page, re.DOTALL) if b.startswith("# monitors and requirements, by meaning"))
    exec(compile(block, "docs/tutorials/temporal.md (by meaning)", "exec"), {})  # its asserts are the test


@pytest.mark.process
def test_dyknow_monitor_checks_a_foreach_formula_over_a_recording_per_object(tmp_path: Any) -> None:
    """Issue 54 item 6 (part): a foreach formula over a recording from the CLI, its verdicts per
    object, the naive evaluator's over the same samples."""
    import json

    from dyknow import Message
    from dyknow.reasoning.syntax import parse
    from dyknow.recording import Recorder
    from dyknow.tags import Term
    from tests.conftest import run_cli
    from tests.reasoning_support import naive_evaluate_objects

    robots = [(1_000_000_000 + i * 100_000_000, {"id": f"r{i % 3}", "zone": "dock" if i % 4 else "aisle", "speed": 0.2 * (i % 5)}) for i in range(30)]
    limits = [(1_000_000_000, {"dock": 0.5, "aisle": 2.0})]
    path = tmp_path / "floor.mcap"
    with Recorder((), path) as recorder:
        for key, series in {"floor/robots": robots, "floor/limits": limits}.items():
            for seq, (t_ns, payload) in enumerate(series, start=1):
                recorder.write(Message(payload, seq, t_ns, t_ns, key))
    formula = "foreach r in Robots(floor).id: historically[0, 300ms] Robots(floor).speed < Limits(floor)[Robots(floor).zone]"
    binds = ["--bind", "Robots(floor)=floor/robots", "--bind", "Limits(floor)=floor/limits"]
    result = run_cli("monitor", formula, "--mcap", str(path), *binds, "--json", "--idle-ms", "1000")
    assert result.returncode == 0, result.stderr
    got: dict[str, list[tuple[int, bool | None]]] = {}
    for line in map(json.loads, result.stdout.splitlines()):
        got.setdefault(line["object"], []).append((line["t_ns"], line["verdict"]))
    root = parse(formula).root
    body = parse(str(root.body))  # type: ignore[union-attr]
    naive = naive_evaluate_objects("r", root.domain, body, {Term("Robots", ("floor",)): robots, Term("Limits", ("floor",)): limits}, 1_000_000_000)  # type: ignore[union-attr,arg-type]
    assert got == {key: sorted(v for life in lives for v in life) for key, lives in naive.items()}
    assert sorted(got) == ["r0", "r1", "r2"] and {v for rows in got.values() for _, v in rows} == {True, False}
    text = run_cli("monitor", formula, "--mcap", str(path), *binds, "--idle-ms", "1000")
    assert text.returncode == 0 and re.search(r"t=1\.000 s  r0  true", text.stdout), text.stdout[:300]
    assert re.search(r"^30 states of 3 objects: \d+ true, \d+ false, 0 unknown; false for r[0-2]", text.stdout.splitlines()[-1]), text.stdout[-300:]
