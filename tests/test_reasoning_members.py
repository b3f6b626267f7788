"""Parameterized terms live (issue 54 item 2): ``SpeedLimit(State(r1).zone)`` plans the speed
limit of a zone the first time the robot is seen in it (dyknow.reasoning.members), a member
bound to what exists is read from the start, and a zone no spec serves is said once."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import Manager
from dyknow.reasoning import FormulaMonitor
from dyknow.testing import Sink
from dyknow.transport import open_session
from tests.conftest import GENERIC_SPECS, UNIT_SPECS, wait_until

FORMULA = "Speed(r1) < SpeedLimit(State(r1).zone).value"
ROBOT = {"State(r1)": "robot/r1/state", "Speed(r1)": "robot/r1/speed"}
LIMITS = {"z1": 1.5, "z2": 0.5, "z3": 1.0}
S = 1_000_000_000


def _limits_spec(tmp_path: Path) -> Path:
    """A limit per zone, each its own source (none for z9)."""
    units = "".join(
        f"""<transformation type="unit"><label>limit-{zone}</label><source>tests.units:Level</source>
             <params><param name="value" type="float">{value}</param><param name="rate_hz" type="float">20</param></params>
             <ports><port type="out">out</port></ports><tags><tag port="out">SpeedLimit({zone})</tag></tags></transformation>"""
        for zone, value in LIMITS.items()
    )
    path = tmp_path / "limits.xml"
    path.write_text(f"<transformations>{units}</transformations>")
    return path


class _Robot:
    """What the robot runs already: its zone and speed on two keys, 20 times a second."""

    def __init__(self, manager: Manager) -> None:
        self.zone, self.speed = "z1", 1.0
        self._lock = threading.Lock()  # (a move is whole between two samples: never a new speed in the old zone)
        self._stop = threading.Event()
        self._session = open_session(connect=manager.endpoints)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            with self._lock:
                self._session.put(ROBOT["State(r1)"], f'{{"zone": "{self.zone}"}}')
                self._session.put(ROBOT["Speed(r1)"], str(self.speed))

    def move(self, zone: str, speed: float | None = None) -> None:
        with self._lock:
            self.zone = zone
            if speed is not None:
                self.speed = speed

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._session.close()


@pytest.fixture
def robot_manager(make_manager: Callable[..., Manager], tmp_path: Path) -> Manager:
    return make_manager(specs=[GENERIC_SPECS, UNIT_SPECS, _limits_spec(tmp_path)], listen=["tcp/127.0.0.1:0"], queue_depth=10_000)


def _planned(manager: Manager) -> set[str]:
    return {info.tag for info in manager.requests()}


def test_a_zone_s_limit_is_planned_when_the_robot_is_first_seen_in_it(robot_manager: Manager) -> None:
    """Nothing is planned before the robot says where it is; in z1 its limit (1.5) is planned and
    1.0 < 1.5 holds; in z2 (0.5) it does not; z9, which no spec serves, is warned about once and
    gives no verdict; z1 again plans nothing new. Released, the limits and their relays go."""
    manager = robot_manager
    key = manager.monitor(FORMULA, bindings=ROBOT)
    assert _planned(manager) == set()  # no zone seen yet: nothing planned
    manager.spawn("sink", "verdicts", bindings={"in": key})
    sink = manager.unit("verdicts")
    assert isinstance(sink, Sink)
    robot = _Robot(manager)
    try:
        sink.wait_until(lambda msg: msg.payload.get("verdict") is True, timeout_s=30)
        assert _planned(manager) == {"SpeedLimit(z1)"}
        robot.move("z2")
        sink.wait_until(lambda msg: msg.payload.get("verdict") is False, timeout_s=30)
        assert _planned(manager) == {"SpeedLimit(z1)", "SpeedLimit(z2)"}
        false = next(msg for msg in sink.messages if msg.payload.get("verdict") is False)
        assert "SpeedLimit(State(r1).zone).value" in " ".join(false.payload.get("why", []))
        robot.move("z9")
        sink.wait_until(lambda msg: "SpeedLimit(z9)" in msg.payload.get("warning", ""), timeout_s=30)
        (info,) = manager.monitors()
        assert any("no stream for SpeedLimit(z9)" in w for w in info.warnings)
        assert set(info.terms) == {*ROBOT, "SpeedLimit(z1)", "SpeedLimit(z2)"}  # (each member's key: its request)
        robot.move("z1")
        before = len(sink.messages)
        sink.wait_until(lambda msg: len(sink.messages) > before + 3 and msg.payload.get("verdict") is True, timeout_s=30)
        assert _planned(manager) == {"SpeedLimit(z1)", "SpeedLimit(z2)"}
    finally:
        robot.close()
    relays = [u for u in manager.units() if u.label == "member-relay"]
    assert len(relays) == 2
    manager.release(key)
    assert _planned(manager) == set()
    wait_until(lambda: not [u for u in manager.units() if u.label in ("member-relay", "formula-monitor")], "the monitor and its relays to go")


def test_a_member_bound_to_what_exists_is_read_from_the_start_and_never_planned(robot_manager: Manager) -> None:
    """``SpeedLimit(z1)`` bound to a key the floor publishes: no request for it, its samples
    relayed from the start; z2, not bound, planned as it is seen."""
    manager = robot_manager
    key = manager.monitor(FORMULA, bindings={**ROBOT, "SpeedLimit(z1)": "floor/limits/z1"})
    manager.spawn("sink", "verdicts", bindings={"in": key})
    sink = manager.unit("verdicts")
    assert isinstance(sink, Sink)
    robot = _Robot(manager)
    stop = threading.Event()

    def floor() -> None:
        with open_session(connect=manager.endpoints) as session:
            while not stop.wait(0.05):
                session.put("floor/limits/z1", '{"value": 0.8}')

    thread = threading.Thread(target=floor, daemon=True)
    thread.start()
    try:
        sink.wait_until(lambda msg: msg.payload.get("verdict") is False, timeout_s=30)  # 1.0 < 0.8: the floor's limit, not the spec's 1.5
        assert _planned(manager) == set()
        robot.move("z2", 0.2)
        sink.wait_until(lambda msg: msg.payload.get("verdict") is True, timeout_s=30)
        assert _planned(manager) == {"SpeedLimit(z2)"}
    finally:
        stop.set()
        thread.join()
        robot.close()
    monitor = next(manager.unit(u) for u in manager.monitors()[0].units)
    assert isinstance(monitor, FormulaMonitor) and monitor.families.seen == {"SpeedLimit(*)": {"z1", "z2"}}
    manager.release(key)


def test_a_live_run_recorded_then_checked_gives_the_same_verdicts_as_its_members_planned(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """Live, the zones' limits are planned as the robot enters them (each relayed from the key its
    driver publishes on); the keys recorded meanwhile are checked as a requirements file whose
    template binds every recorded limit (``"SpeedLimit(z)" = "floor/limits/{z}"``): the verdicts
    equal the live ones, at the same times."""
    import time

    from dyknow.reasoning import check_recording, load_requirements
    from dyknow.recording import Recorder
    from dyknow.testing import Source
    from tests.live_support import fresh_verdicts, from_start, publish_recorded

    def relay(label: str, key: str, tag: str) -> str:
        return f"""<transformation><label>{label}</label><source>transformations.generic:RemoteStream</source>
          <params><param name="key">{key}</param><param name="grace_s" type="float">5</param></params>
          <ports><port type="in">in</port><port type="out">out</port></ports><tags><tag port="out">{tag}</tag></tags></transformation>"""

    manager = make_manager(listen=["tcp/127.0.0.1:0"], queue_depth=100_000)
    zones = {"dock": 0.5, "aisle": 2.0}
    keys = {"floor/r1/state": "State(r1)", **{f"floor/limits/{z}": f"SpeedLimit({z})" for z in zones}}
    relays = "".join(relay("relay-" + k.replace("/", "-"), k, tag) for k, tag in keys.items())
    manager.add_transformation(f"<transformations>{relays}</transformations>")
    drivers: dict[str, Source] = {}
    for key in keys:
        manager.spawn("publisher", key.replace("/", "-"), bindings={"out": key})
        driver = manager.unit(key.replace("/", "-"))
        assert isinstance(driver, Source)
        drivers[key] = driver
    formula = "historically[0, 300ms] State(r1).speed <= SpeedLimit(State(r1).zone)"
    # (a limit comes through two relays more than the state does: on a loaded machine, seconds later;
    # the delay takes their samples in time order)
    key = manager.monitor(formula, reorder_ms=3000)
    manager.spawn("sink", "verdicts", bindings={"in": key})
    sink = manager.unit("verdicts")
    assert isinstance(sink, Sink)

    def verdicts() -> list[dict[str, object]]:
        return [m.payload for m in list(sink.messages) if isinstance(m.payload, dict) and "verdict" in m.payload]

    def publish(i: int) -> None:
        now = time.time_ns()
        for zone, limit in zones.items():
            drivers[f"floor/limits/{zone}"].emit(limit, origin_ns=now)
        drivers["floor/r1/state"].emit({"zone": "dock" if i % 5 else "aisle", "speed": 0.9 if i % 17 == 3 else 0.3}, origin_ns=now + 1)

    live = tmp_path / "live.mcap"
    with Recorder(["floor/**"], live, connect=manager.endpoints) as recorder:
        start_ns = publish_recorded(
            recorder,
            publish,
            lambda: len({info.tag for info in manager.requests()}) == 3 and len(verdicts()) > 20,
            lambda t_ns: verdicts()[-1]["t_ns"] >= t_ns,  # type: ignore[operator]
            lambda: [manager.unit(manager.monitors()[0].units[0])],
            topics=3,
            count=250,
        )
    trimmed = from_start(live, start_ns, tmp_path / "trimmed.mcap")
    (tmp_path / "live.toml").write_text(
        f'[bindings]\n"State(r)" = "floor/{{r}}/state"\n"SpeedLimit(z)" = "floor/limits/{{z}}"\n\n[[requirement]]\nname = "limit"\nformula = "{formula}"\n'
    )
    (result,) = check_recording(load_requirements(tmp_path / "live.toml"), trimmed)
    assert result.error is None, result.error
    settled = start_ns + 500_000_000  # past the window (300 ms) and each limit's first sample
    judged = [v for v in verdicts() if v["t_ns"] >= settled]  # type: ignore[operator]
    assert len(judged) > 100
    unit = manager.unit(manager.monitors()[0].units[0])
    assert isinstance(unit, FormulaMonitor) and unit.monitor.late == 0
    # the live monitor's terms have the freshness it derived from their rates (a publisher starved
    # for longer makes its states unknown there); over the same samples with the same ages, the
    # semantics gives every verdict it published
    fresh = fresh_verdicts(formula, trimmed, {term: k for k, term in keys.items()}, unit.ages)
    expected = {t: v for (_, t), v in fresh.items() if settled <= t <= judged[-1]["t_ns"] and v is not None}  # type: ignore[operator]
    assert {v["t_ns"]: v["verdict"] for v in judged} == expected, unit.ages
    assert {v["verdict"] for v in judged} == {True, False}
    # and the requirements file (no freshness asked) decides each of them the same
    offline = dict(result.verdicts[""])
    assert all(offline[t] is v for t, v in expected.items())


@pytest.mark.process
def test_dyknow_monitor_reads_a_parameterized_term_s_members_from_a_recording(tmp_path: Path) -> None:
    """``dyknow monitor`` over an MCAP file: the members bound one by one, or by a template of
    the functor (every recorded topic it matches a member); the naive evaluator's verdicts; no
    member bound at all is said, naming the term."""
    import json

    from dyknow import Message
    from dyknow.reasoning.tree import family_term
    from dyknow.recording import Recorder
    from dyknow.tags import Term
    from tests.conftest import run_cli
    from tests.reasoning_support import naive_evaluate_ns

    series = {
        "floor/limits/dock": [(0, 0.5), (3 * S, 0.4)],
        "floor/limits/aisle": [(S // 2, 2.0)],
        "floor/r1/state": [(i * S, {"zone": ["aisle", "dock", "yard", "dock"][i % 4], "speed": [1.5, 0.45, 0.1, 0.45][i % 4]}) for i in range(1, 9)],
    }
    recording = tmp_path / "floor.mcap"
    with Recorder((), recording) as recorder:
        for key, samples in series.items():
            for seq, (t_ns, payload) in enumerate(samples, start=1):
                recorder.write(Message(payload, seq, t_ns, t_ns, key))
    formula = "State(r1).speed < SpeedLimit(State(r1).zone)"
    from dyknow.reasoning import parse

    members = {Term("SpeedLimit", (z,)): series[f"floor/limits/{z}"] for z in ("dock", "aisle")}
    expected = naive_evaluate_ns(parse(formula), {Term("State", ("r1",)): series["floor/r1/state"], **members})
    assert family_term("SpeedLimit", ("*",)) in parse(formula).terms
    assert {v for _, v in expected} == {True, False, None}  # the yard has no limit: unknown
    one_by_one = ["--bind", "State(r1)=floor/r1/state", "--bind", "SpeedLimit(dock)=floor/limits/dock", "--bind", "SpeedLimit(aisle)=floor/limits/aisle"]
    by_template = ["--bind", "State(r)=floor/{r}/state", "--bind", "SpeedLimit(z)=floor/limits/{z}"]
    for binds in (one_by_one, by_template):
        done = run_cli("monitor", formula, "--mcap", str(recording), *binds, "--json")
        assert done.returncode == 0, done.stderr
        assert [(row["t_ns"], row["verdict"]) for row in map(json.loads, done.stdout.splitlines())] == expected, binds
    missing = run_cli("monitor", formula, "--mcap", str(recording), "--bind", "State(r1)=floor/r1/state")
    assert missing.returncode == 1 and "no topic for a member of SpeedLimit(*)" in missing.stderr, missing.stderr


def test_the_arguments_a_monitor_sees_are_handed_on_once_each_names_only_and_at_most_max_members() -> None:
    """What the unit hands the manager: each new value of an argument once (those seen before a
    watcher, when it comes), of a frame each element's, never a value that is no name (a
    number, a string with a space, an object), and at most MAX_MEMBERS a family."""
    from dyknow.reasoning import parse
    from dyknow.reasoning.families import MAX_MEMBERS
    from dyknow.reasoning.members import LiveFamilies

    formula = parse("foreach r in Seen(floor).id: Seen(floor).speed < SpeedLimit(Seen(floor).zone) and Speed(x) < SpeedLimit(Zone(x))")
    terms = [str(t) for t in formula.terms]
    families = LiveFamilies([formula], terms)
    assert set(families.ports) == {terms.index("SpeedLimit(*)")}
    seen_k, zone_k = terms.index("Seen(floor)"), terms.index("Zone(x)")
    assert set(families.reads) == {seen_k, zone_k}
    families.observe(seen_k, [{"id": 1, "zone": "dock"}, {"id": 2, "zone": "aisle"}, {"id": 3, "zone": "dock"}])  # a frame
    families.observe(zone_k, "ramp")
    families.observe(zone_k, 3)
    families.observe(zone_k, "no name")
    families.observe(zone_k, {"zone": "dock"})
    handed: list[tuple[str, str]] = []
    families.watch(lambda family, arg: handed.append((family, arg)))
    assert handed == [("SpeedLimit(*)", "dock"), ("SpeedLimit(*)", "aisle"), ("SpeedLimit(*)", "ramp")]
    for n in range(MAX_MEMBERS + 10):
        families.observe(zone_k, f"z{n}")
    assert len(handed) == MAX_MEMBERS and families.full == ["SpeedLimit(*)"]
    value = families.value(next(iter(families.ports)), 5 * S, {"arg": "dock", "value": 0.5})
    assert value == {"dock": 0.5}
    assert families.value(next(iter(families.ports)), 4 * S, {"arg": "aisle", "value": 2.0}) == {"aisle": 2.0}  # dock's sample came after 4 s
    assert families.value(next(iter(families.ports)), 6 * S, "0.5") is None  # no relay's


def test_requirements_of_requests_and_specs_refuse_a_parameterized_term(manager: Manager) -> None:
    """A request's requirement, and a transformation's, read fixed terms: a parameterized one is
    refused, named, and nothing is requested."""
    from dyknow import SpecError
    from dyknow.errors import FormulaError
    from dyknow.spec import parse_specs

    with pytest.raises(FormulaError, match=r"a request's requirement has the parameterized term SpeedLimit\(\*\)"):
        manager.request("Ticks", require=["Ticks.count < SpeedLimit(State(r1).zone)"])
    assert manager.requests() == []
    xml = (
        "<transformation>\n  <label>t</label><source>a:B</source>\n"
        '  <ports><port type="out">out</port></ports><tags><tag port="out">Track(x)</tag></tags>\n'
        "  <requirements>\n    <requirement>Track(x).v &lt; SpeedLimit(State(r1).zone)</requirement>\n  </requirements>\n</transformation>\n"
    )
    with pytest.raises(SpecError, match=r"t\.xml:5: <requirement>: a transformation's requirement has the parameterized term SpeedLimit\(\*\)"):
        parse_specs(xml, "t.xml")


_OBJECT_FORMULAS = [
    "foreach r in Seen(floor).id: Speed(r) < 1",
    "foreach r in Seen(floor).id: historically[0, 2ms] Speed(r) <= Seen(floor).speed",
    "foreach r in Seen(floor).id: Seen(floor).speed < SpeedLimit(Seen(floor).zone) or once[0, 1ms] Speed(r) > 2",
    "foreach r in Seen(floor).id: eventually[0, 2ms] Speed(r) < SpeedLimit(Zone(x))",
]


@pytest.mark.parametrize("text", _OBJECT_FORMULAS)
def test_a_foreach_variable_as_an_argument_gives_each_object_its_own_member(text: str) -> None:
    """``foreach r in Seen(floor).id: Speed(r) < 1``: each object reads the member its value
    names (``Speed(r1)`` for r1), the naive evaluator's verdicts per object and life over random
    traces (members missing, objects no member has, junk), live (an object monitor pushed the
    members by name) as offline."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from dyknow.reasoning import parse
    from dyknow.reasoning.objects import ObjectMonitor
    from dyknow.reasoning.semantics import evaluate_objects_ns
    from dyknow.reasoning.syntax import Quantifier, Stream
    from dyknow.reasoning.tree import is_family, member_arg
    from dyknow.tags import Term, parse_term
    from tests.reasoning_support import naive_evaluate_objects

    formula = parse(text)
    root = formula.root
    assert isinstance(root, Quantifier) and isinstance(root.domain, Stream)
    ms = 1_000_000
    names = ["Seen(floor)", "Speed(r1)", "Speed(r2)", "SpeedLimit(dock)", "SpeedLimit(aisle)", "Zone(x)"]
    read = {str(t) for t in formula.terms}
    read |= {n for n in names for f in formula.terms if is_family(f) and member_arg(f, parse_term(n)) is not None}

    @settings(max_examples=150, derandomize=True, deadline=None)
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        trace: dict[str, list[tuple[int, object]]] = {}
        for name in names:
            if name not in ("Seen(floor)", "Zone(x)") and not data.draw(st.sampled_from([True, True, False])):  # (members may be missing)
                continue
            t, rows = data.draw(st.integers(0, 3)), []
            for _ in range(data.draw(st.integers(1, 12))):
                if name == "Seen(floor)":
                    value: object = {"id": data.draw(st.sampled_from(["r1", "r2", "r3", 7, "r1"])), "speed": data.draw(st.sampled_from([0.5, 1.5, 2.5])),
                                     "zone": data.draw(st.sampled_from(["dock", "aisle", "yard"]))}  # fmt: skip
                elif name == "Zone(x)":
                    value = data.draw(st.sampled_from(["dock", "aisle", "no name", 3]))
                else:
                    value = data.draw(st.sampled_from([0.5, 1.5, 2.5, "fast", None]))
                rows.append((t * ms, value))
                t += data.draw(st.sampled_from([0, 1, 1, 2]))
            trace[name] = rows
        idle = 5 * ms
        got = evaluate_objects_ns(formula, trace, idle_ns=idle)
        body = type(formula).of(root.body)
        expected = naive_evaluate_objects(root.var, root.domain, body, {parse_term(k): v for k, v in trace.items()}, idle)
        assert got == expected, (text, trace)
        # live, the members pushed by name in time order: the same trace at distinct times (a stream's
        # samples at one time reduced to the later one, each stream at its own offset), as offline
        spread = {k: [(16 * t + j, v) for i, (t, v) in enumerate(rows) if i + 1 == len(rows) or rows[i + 1][0] != t]
                  for j, (k, rows) in enumerate(trace.items())}  # fmt: skip
        monitor = ObjectMonitor(formula, idle_ns=16 * idle)
        ordered = sorted((t, k, v) for k, rows in spread.items() if k in read for t, v in rows)
        pushed = [pair for t, k, v in ordered for pair in monitor.push(k, t, v)] + monitor.close()
        offline = evaluate_objects_ns(formula, spread, idle_ns=16 * idle)
        decided = {(key, t): v for key, lives in offline.items() for life in lives for t, v in life if v is not None}
        assert {(key, v.t_ns): v.verdict for key, v in pushed} == decided, (text, spread)
        assert Term("Speed", ("r1",)) not in formula.terms  # (the family, not a term of its own)

    check()
