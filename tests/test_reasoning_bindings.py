"""Formulas over what exists (dyknow.reasoning.bindings): a term bound to a Zenoh key, an rmw_zenoh
topic or a DDS topic, with no spec, live through a manager and offline over a recording; the
field path after the term reads into the messages; bad bindings are refused naming them, and
nothing running is touched."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh  # a plain Zenoh publisher stands in for a robot's existing key

from dyknow import BindingError, FormulaError, Manager, Message, SpecError
from dyknow.reasoning import monitor_spec, parse, term_ports
from dyknow.reasoning.bindings import check_bindings, sample_value
from dyknow.reasoning.offline import evaluate_recording
from dyknow.recording import Recorder
from dyknow.spec import parse_specs
from dyknow.testing import Sink
from dyknow.transport import make_config
from tests.conftest import GENERIC_SPECS, REPO, UNIT_SPECS, free_port, run_cli, wait_until

ONTOLOGY = REPO / "specs" / "dyknow.ttl"

TWIST = "geometry_msgs/msg/TwistStamped"
# the peers publish their i-th TwistStamped stamped i s (+ 5 ns) with twist.linear.x = i % 2
FORMULA = "Vel(r1).twist.linear.x < 0.5 and Vel(r1).header.stamp.sec > 0"


def _sink(manager: Manager, name: str, key: str) -> Sink:
    manager.spawn("sink", name, bindings={"in": key})
    sink = manager.unit(name)
    assert isinstance(sink, Sink)
    return sink


def _verdicts(sink: Sink) -> list[dict[str, Any]]:
    return [m.payload for m in list(sink.messages) if isinstance(m.payload, dict) and "verdict" in m.payload]


def _check_twist_verdicts(sink: Sink) -> None:
    """Both verdicts come, and each is the formula's at its state: the sample stamped i s has x = i % 2."""
    wait_until(lambda: {v["verdict"] for v in _verdicts(sink)} == {True, False}, "true and false verdicts", timeout_s=30)
    got = _verdicts(sink)
    assert all(v["t_ns"] % 1_000_000_000 == 5 for v in got)  # each state is a message's header.stamp
    assert all(v["verdict"] is ((v["t_ns"] // 1_000_000_000) % 2 == 0) for v in got), got[:6]


# ---------------------------------------------------------------------------- the rules, without a system


@pytest.mark.parametrize(
    ("bindings", "error", "says"),
    [
        ({"Odom(r1)": "ros:/r1/odom"}, BindingError, "binding Odom(r1)=ros:/r1/odom: the scheme 'ros:'"),
        ({"Odom(r1)": "ros2:/r1//odom"}, BindingError, "binding Odom(r1)=ros2:/r1//odom"),
        ({"Odom(r1)": "ros2:/r1/odom?tipe=nav_msgs/msg/Odometry"}, BindingError, "option 'tipe'"),
        ({"Odom(r2)": "r2/odom"}, FormulaError, "binding Odom(r2)=r2/odom: 'Odom(r2)' is no term of the formula"),
        ({"Odom(r1": "r1/odom"}, FormulaError, "binding Odom(r1=r1/odom: the term does not read"),
        ({"Odom(r1)": "@dyknow/m/odom"}, BindingError, "a chunk starting with '@'"),
        ({"Odom(r1)": "r1//odom"}, BindingError, "binding Odom(r1)=r1//odom: the key 'r1//odom' has an empty chunk"),
        ({"Odom(r1)": ""}, BindingError, "ros2:/TOPIC, ros2dds:/TOPIC or a Zenoh key"),
    ],
)
def test_a_bad_binding_is_refused_naming_it(bindings: dict[str, str], error: type[Exception], says: str) -> None:
    with pytest.raises(error) as raised:
        check_bindings(parse("Odom(r1).twist.twist.linear.x < 1.5"), bindings)
    assert says in str(raised.value)


def test_bindings_are_written_as_the_formula_writes_its_terms() -> None:
    formula = parse("Odom(r1).twist.twist.linear.x < 1.5 and Battery(r1) > 0.2")
    bound = check_bindings(formula, {"Odom( r1 )": "ros2dds:/r1/odom?type=nav_msgs/msg/Odometry", "Battery(r1)": "robots/r1/battery"})
    assert bound == {"Odom(r1)": "ros2dds:/r1/odom?type=nav_msgs/msg/Odometry", "Battery(r1)": "robots/r1/battery"}
    foreach = parse("foreach t in Track(field).id: Track(field).speed < 3")  # one monitor per object: bindings stay
    assert check_bindings(foreach, {"Track(field)": "tracker/tracks"}) == {"Track(field)": "tracker/tracks"}
    with pytest.raises(FormulaError, match="a binding in a formula with forall or exists"):
        check_bindings(parse("forall c in Camera: Fresh(c) > 0"), {"Fresh(c)": "x"})


@pytest.mark.parametrize(
    ("payload", "value"),
    [
        (b"1.5", 1.5), ("1.5", 1.5), (b"true", True), (b'{"x": {"y": 2}}', {"x": {"y": 2}}), ("manual", "manual"),
        ('"manual"', "manual"), (b"\xff\x00", b"\xff\x00"), (b"NaN", b"NaN"), ({"x": 1}, {"x": 1}), (3, 3),
    ],
)  # fmt: skip
def test_a_bound_terms_text_is_read_as_json_when_it_is(payload: Any, value: Any) -> None:
    assert sample_value(payload) == value and type(sample_value(payload)) is type(value)


# ---------------------------------------------------------------------------- a Zenoh key, live and offline


def test_a_zenoh_key_bound_live_gives_the_verdicts_a_recording_of_it_gives(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """A plain Zenoh publisher puts numbers as text and bytes (and one JSON object, one word): the
    monitor bound to its key decides each state as the offline evaluation of the same samples does
    (an unknown state, whose verdict is never published live, is None offline)."""
    manager = make_manager(listen=[f"tcp/127.0.0.1:{free_port()}"])
    formula = "Battery(r1) > 0.2 and Battery(r1) <= 1"
    key = manager.monitor(formula, bindings={"Battery(r1)": "robots/r1/battery"})
    sink = _sink(manager, "watch", key)
    sent: list[Any] = [b"0.5", "0.3", b"0.1", b"n/a", b'{"level": 0.9}', "0.25", b"7", b"0.9"]
    with zenoh.open(make_config(connect=manager.endpoints)) as plain:
        publisher = plain.declare_publisher("robots/r1/battery", congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: publisher.matching_status.matching, "the monitor to subscribe")
        warm = 0
        while not _verdicts(sink):  # until the path is up (a put right after matching may not arrive yet)
            warm += 1
            publisher.put(b"0.6")
            time.sleep(0.05)
        wait_until(lambda: len(_verdicts(sink)) >= warm, "the warm-up's verdicts")
        first = len(_verdicts(sink))
        for payload in sent:
            publisher.put(payload)
        wait_until(lambda: len(_verdicts(sink)) >= first + 5, "the verdicts of the known states")
        publisher.undeclare()
    live = [v["verdict"] for v in _verdicts(sink)[first:]]
    # each change of the verdict says why: both comparisons with the value of its state (issue 54 item 7)
    known = [0.5, 0.3, 0.1, 0.25, 7, 0.9]  # the states with a number (the others are unknown, never published)
    whys = [v.get("why") for v in _verdicts(sink)[first:]]
    assert whys == [None if k == 0 or live[k] is live[k - 1] else [f"Battery(r1) > 0.2: {x:g} > 0.2", f"Battery(r1) <= 1: {x:g} <= 1"]
                    for k, x in enumerate(known)], whys  # fmt: skip
    path = tmp_path / "battery.mcap"
    with Recorder((), path) as recorder:
        for seq, payload in enumerate(sent, start=1):
            recorder.write(Message(payload, seq, seq * 1_000_000, seq * 1_000_000, "robots/r1/battery"))
    offline = [verdict for _, verdict in evaluate_recording(formula, path, {"Battery(r1)": "robots/r1/battery"})]
    assert offline == [True, True, False, None, None, True, False, True]
    assert live == [v for v in offline if v is not None]
    (info,) = manager.monitors()
    assert info.to_dict()["bindings"] == {"Battery(r1)": "robots/r1/battery"} and manager.requests() == []


def test_a_foreach_formula_reads_frames_a_plain_publisher_puts_as_json(make_manager: Callable[..., Manager]) -> None:
    """A tracker that is no dyknow unit puts its tracks as a JSON list: one frame, a sample per object."""
    manager = make_manager(listen=[f"tcp/127.0.0.1:{free_port()}"])
    key = manager.monitor("foreach t in Track(field).id: Track(field).speed < 3", bindings={"Track(field)": "tracker/tracks"})
    sink = _sink(manager, "watch", key)
    with zenoh.open(make_config(connect=manager.endpoints)) as plain:
        publisher = plain.declare_publisher("tracker/tracks", congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: publisher.matching_status.matching, "the monitor to subscribe")
        while {v.get("object") for v in _verdicts(sink)} != {"1", "2"}:
            publisher.put('[{"id": 1, "speed": 2.0}, {"id": 2, "speed": 5.0}]')
            time.sleep(0.05)
    assert {v["object"]: v["verdict"] for v in _verdicts(sink)} == {"1": True, "2": False}


def test_a_binding_to_a_source_that_never_publishes_is_warned_about_naming_it(make_manager: Callable[..., Manager]) -> None:
    """No sample, no verdict (never a false one), and a warning that names the binding."""
    manager = make_manager()
    spec = monitor_spec("Battery(r1) > 0.2", bound={"Battery(r1)": "robots/r1/nothing"}, quiet_ms=200)
    manager.spawn(spec, "quiet", bindings={term_ports(spec)["Battery(r1)"]: "robots/r1/nothing", "verdicts": "quiet/verdicts"})
    sink = _sink(manager, "watch", "quiet/verdicts")
    (message,) = sink.wait_for(1)
    assert message.payload["binding"] == "robots/r1/nothing" and message.payload["term"] == "Battery(r1)"
    assert "no sample of Battery(r1) from its binding Battery(r1)=robots/r1/nothing in 0.2 s" in message.payload["warning"]
    assert not _verdicts(sink)


def test_a_bad_binding_leaves_what_runs_as_it_was(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager()
    key = manager.monitor("Battery(r1) > 0.2", bindings={"Battery(r1)": "robots/r1/battery"})
    before = sorted(u.name for u in manager.get_model().units)
    for bindings, error, says in [
        ({"Battery(r1)": "robots/r1/**/x/**/**"}, BindingError, "binding Battery(r1)=robots/r1/**/x/**/**"),  # Zenoh refuses it
        ({"Battery(r1)": "ros:/r1/battery"}, BindingError, "the scheme 'ros:'"),
        ({"Battery(r2)": "robots/r2/battery"}, FormulaError, "did you mean 'Battery(r1)'"),
        ({"Battery(r1)": "ros2dds:/r1/battery_nobody_writes"}, BindingError, "announced none"),  # no type, and no writer to say it
    ]:
        with pytest.raises(error, match=".") as raised:
            manager.monitor("Battery(r1) > 0.2", bindings=bindings)
        assert says in str(raised.value)
        assert sorted(u.name for u in manager.get_model().units) == before
    assert [m.key for m in manager.monitors()] == [key]


def test_a_binding_in_a_formula_over_a_class_is_refused(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager(ontology=[ONTOLOGY])
    with pytest.raises(FormulaError, match="binding Fresh.c.=x: a binding in a formula with forall or exists"):
        manager.monitor("forall c in Camera: Fresh(c) > 0", bindings={"Fresh(c)": "x"})
    assert manager.monitors() == []


# ---------------------------------------------------------------------------- ROS 2 topics: rmw_zenoh and DDS


@pytest.fixture
def sdk_peers() -> Iterator[Callable[..., Any]]:
    from tests.test_ros2_live import Peer

    started: list[Peer] = []

    def start(*args: str) -> Peer:
        peer = Peer(*args)
        started.append(peer)
        return peer

    yield start
    for peer in started:
        peer.close()


@pytest.mark.process
def test_a_term_bound_to_an_rmw_zenoh_topic_reads_the_fields_of_its_messages(make_manager: Callable[..., Manager], sdk_peers: Callable[..., Any]) -> None:
    port = free_port()
    manager = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=0, ros2_node="dyknow_robot")
    key = manager.monitor(FORMULA, bindings={"Vel(r1)": "ros2:/r1/cmd_vel"})
    sink = _sink(manager, "watch", key)
    peer = sdk_peers(str(port), "talk", "/r1/cmd_vel", TWIST)
    assert peer.line() == {"ready": True}
    _check_twist_verdicts(sink)
    (info,) = manager.monitors()
    assert info.bound == {"Vel(r1)": "ros2:/r1/cmd_vel"} and manager.requests() == []
    assert manager.release(key) == 0 and manager.monitors() == []
    assert not [u for u in manager.get_model().units if u.name.startswith("monitor-")]  # its ROS 2 companion went with it


def test_a_ros2_topic_nobody_publishes_is_warned_about_in_the_model(make_manager: Callable[..., Manager]) -> None:
    """Through the manager, with its default quiet time (5 s): the warning names the binding, and
    no verdict came."""
    manager = make_manager(ros2_domain=0, ros2_node="dyknow_quiet")
    key = manager.monitor(FORMULA, bindings={"Vel(r1)": f"ros2:/nobody/cmd_vel?type={TWIST}"})
    sink = _sink(manager, "watch", key)
    wait_until(lambda: bool(manager.monitors()[0].warnings), "the monitor's warning", timeout_s=30)
    (warning,) = manager.monitors()[0].warnings
    assert f"no sample of Vel(r1) from its binding Vel(r1)=ros2:/nobody/cmd_vel?type={TWIST} in 5 s" in warning
    assert not _verdicts(sink)


@pytest.mark.process
def test_a_term_bound_to_a_dds_topic_reads_the_fields_of_an_rclpy_talkers_messages(make_manager: Callable[..., Manager]) -> None:
    from tests.conftest import dds_domain
    from tests.test_ros2_dds import Rclpy

    domain = dds_domain()
    manager = make_manager(ros2_domain=domain)
    talker = Rclpy(domain, "talk", "/r1/cmd_vel", TWIST)
    try:
        talker.ready()
        key = manager.monitor(FORMULA, bindings={"Vel(r1)": f"ros2dds:/r1/cmd_vel?type={TWIST}"})
        _check_twist_verdicts(_sink(manager, "watch", key))
    finally:
        talker.close()


# ---------------------------------------------------------------------------- the command line


@pytest.mark.process
def test_dyknow_monitor_binds_a_term_to_a_key_against_a_manager_process(manager_process: Callable[..., Any]) -> None:
    proc = manager_process()
    stop = threading.Event()

    def publish() -> None:
        with zenoh.open(make_config(connect=[proc.endpoint])) as plain:
            publisher = plain.declare_publisher("robots/r1/battery")
            while not stop.wait(0.02):
                publisher.put(b"0.15")

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        result = run_cli("monitor", "Battery(r1) < 0.2", "--bind", "Battery(r1)=robots/r1/battery", "--duration", "3", "--json",
                         *proc.client_args())  # fmt: skip
        text = run_cli("monitor", "Battery(r1) < 0.2", "--bind", "Battery(r1)=robots/r1/battery", "--duration", "1", *proc.client_args())
    finally:
        stop.set()
        thread.join(10)
    assert result.returncode == 0, result.stderr
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(lines) > 5 and all(line["verdict"] is True for line in lines), lines[:3]
    assert text.returncode == 0 and "Battery(r1) from robots/r1/battery" in text.stdout.splitlines()[0]
    for bind, says in [
        ("Battery(r1)=ros:/r1/battery", "binding Battery(r1)=ros:/r1/battery: the scheme 'ros:'"),
        ("Battery(r2)=robots/r2/battery", "'Battery(r2)' is no term of the formula"),
        ("Battery(r1)=robots/**/x/**/**", "binding Battery(r1)=robots/**/x/**/**"),  # refused by the manager (Zenoh)
    ]:
        refused = run_cli("monitor", "Battery(r1) < 0.2", "--bind", bind, "--duration", "1", *proc.client_args())
        assert refused.returncode == 1 and says in refused.stderr and "Traceback" not in refused.stderr, refused.stderr


@pytest.mark.process
def test_dyknow_monitor_over_a_recording_takes_the_live_ros2_bindings(tmp_path: Path) -> None:
    path = tmp_path / "cmd.mcap"
    with Recorder((), path) as recorder:
        for i in range(1, 7):
            payload = {"header": {"stamp": {"sec": i, "nanosec": 5}}, "twist": {"linear": {"x": float(i % 2)}}}
            recorder.write(Message(payload, i, i * 1_000_000_000 + 5, i * 1_000_000_000 + 5, "/r1/cmd_vel"))
    result = run_cli("monitor", FORMULA, "--mcap", str(path), "--bind", "Vel(r1)=ros2:/r1/cmd_vel", "--json")
    assert result.returncode == 0, result.stderr
    assert [line["verdict"] for line in map(json.loads, result.stdout.splitlines())] == [False, True, False, True, False, True]


# ---------------------------------------------------------------------------- in a spec: a requirement's bindings

LIMITED = """<transformations><transformation><label>level(${R})</label><source>tests.units:Level</source>
  <args><arg label="R">{r1}</arg></args>
  <params><param name="rate_hz" type="float">50</param><param name="value" type="float">2</param></params>
  <ports><port type="out">out</port></ports><tags><tag port="out">Fresh(${R})</tag></tags>
  <requirements><requirement>Fresh(${R}).value &lt; Limit(${R}).max</requirement></requirements>
  <bindings><binding term="Limit(${R})">limits/${R}</binding></bindings>
</transformation></transformations>"""


def test_a_specs_requirement_reads_a_bound_term_from_its_key(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """The requirement's other term is bound to a key a plain Zenoh publisher puts JSON on: it is
    not requested, its monitor reads the key, and a limit below the level makes it false."""
    (tmp_path / "limited.xml").write_text(LIMITED)
    manager = make_manager(specs=[tmp_path / "limited.xml", GENERIC_SPECS, UNIT_SPECS], listen=[f"tcp/127.0.0.1:{free_port()}"])
    (spec,) = [s for s in manager.library.specs() if s.label == "level(r1)"]
    assert spec.bindings == (("Limit(r1)", "limits/r1"),) and '<binding term="Limit(r1)">limits/r1</binding>' in spec.to_xml()
    manager.request("Fresh(r1)")
    (request,) = manager.requests()
    (watched,) = request.spec_requirements
    assert [r.tag for r in manager.requests()] == ["Fresh(r1)"]  # Limit(r1) is read, not requested
    (monitor,) = [u.name for u in manager.units() if "spec-require" in u.name]
    assert manager.get_config(monitor)["t1"] == "limits/r1"
    verdicts = _sink(manager, "watch", watched["key"])
    with zenoh.open(make_config(connect=manager.endpoints)) as plain:
        publisher = plain.declare_publisher("limits/r1", congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: publisher.matching_status.matching, "the requirement's monitor to subscribe")
        while not any(v["verdict"] is True for v in _verdicts(verdicts)):
            publisher.put('{"max": 3}')
            time.sleep(0.05)
        publisher.put('{"max": 1.5}')
        wait_until(lambda: _verdicts(verdicts)[-1]["verdict"] is False, "the lower limit's false verdict")


@pytest.mark.parametrize(
    ("binding", "says"),
    [
        ('<binding term="Limit(r2)">limits/r2</binding>', "<binding> @term: 'Limit(r2)' is no term of a requirement"),
        ('<binding term="Fresh(r1)">limits/r1</binding>', "'Fresh(r1)' is an output tag of this transformation"),
        ('<binding term="Limit(r1)">ros:/limits</binding>', "binding Limit(r1)=ros:/limits: the scheme 'ros:'"),
        ('<binding term="Limit(r1)">ros2:/limits?type=oops</binding>', "binding Limit(r1)=ros2:/limits?type=oops"),
        ('<binding term="Limit(r1)"></binding>', "<binding>: empty"),
        ('<binding term="Limit(r1)">limits//r1</binding>', "binding Limit(r1)=limits//r1: the key 'limits//r1' has an empty chunk"),
        ("<binding>limits/r1</binding>", "term"),
    ],
)
def test_a_specs_bad_binding_is_a_located_error(binding: str, says: str) -> None:
    xml = LIMITED.replace('<binding term="Limit(${R})">limits/${R}</binding>', binding)
    with pytest.raises(SpecError) as raised:
        parse_specs(xml, "limited.xml")
    assert says in str(raised.value) and "limited.xml:6:" in str(raised.value), str(raised.value)


def test_a_verdict_that_flips_at_every_sample_is_explained_at_most_as_often_as_the_bound_says(make_manager: Callable[..., Manager]) -> None:
    """200 samples 1 ms apart (in sample time) flip the verdict each time: every change is
    published, but only 8 at once and then one per 50 ms of sample time carry "why" (each
    costs an evaluation of the formula's comparisons), each of them right."""
    from dyknow.reasoning.unit import EXPLAIN_BURST, EXPLAIN_GAP_NS
    from dyknow.transport import Session

    manager = make_manager(listen=[f"tcp/127.0.0.1:{free_port()}"], queue_depth=10_000)  # (the sink keeps every verdict)
    key = manager.monitor("Level(x) > 0.5", bindings={"Level(x)": "levels/x"})
    sink = _sink(manager, "watch", key)
    with Session(make_config(connect=manager.endpoints)) as session:
        publisher = session.declare_publisher("levels/x", reliable=True)
        wait_until(lambda: publisher.matched, "the monitor to subscribe")
        start = time.time_ns() - 10_000_000_000
        n = 0
        while not _verdicts(sink):  # the path up (the first may be lost before it is)
            n += 1
            publisher.put(Message(1.0, n, start + n * 1_000_000, start + n * 1_000_000, "levels/x"))
            time.sleep(0.05)
        first = n
        for k in range(1, 201):
            n += 1
            publisher.put(Message(float(k % 2), n, start + n * 1_000_000, start + n * 1_000_000, "levels/x"))
        after = start + first * 1_000_000

        def flips() -> list[dict[str, Any]]:
            return [v for v in _verdicts(sink) if v["t_ns"] > after]

        try:
            wait_until(lambda: len(flips()) >= 199, "a verdict per sample (the last one's state may stay open)")
        except AssertionError:
            raise AssertionError(f"{len(flips())} flips; {[(u.name, [(p.port, p.messages, p.dropped) for p in manager.get_statistics(u.name).ports]) for u in manager.units()]}") from None
    assert [v["verdict"] for v in flips()] == [k % 2 == 1 for k in range(1, len(flips()) + 1)]
    explained = [v for v in flips() if "why" in v]
    allowed = EXPLAIN_BURST + 200 * 1_000_000 // EXPLAIN_GAP_NS
    assert EXPLAIN_BURST - 1 <= len(explained) <= allowed, len(explained)  # (the warm-up's first verdict took a token)
    assert all(v["why"] == [f"Level(x) > 0.5: {1 if v['verdict'] else 0} > 0.5"] for v in explained), explained[:3]
