"""``ros2:`` bindings: parsing, and ports bound to ROS 2 topics in a manager (spawn, set_config,
the model, destroy) and on the command line (--bind, --ros2-domain, echo ros2:, ros2 list)."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable

import pytest

from dyknow import Manager
from dyknow.errors import BindingError, DyKnowError
from dyknow.ros2 import Ros2Node, parse_binding, snapshot
from dyknow.ros2.names import Durability, QoS, Reliability
from dyknow.transport import open_session
from tests.conftest import UNIT_SPECS, CliProcess, free_port, run_cli, wait_until


@pytest.mark.parametrize(
    ("text", "topic", "ros_type", "qos", "uri"),
    [
        ("ros2:/chatter", "/chatter", None, QoS(), "ros2:/chatter"),
        ("ros2:/a/b?type=std_msgs/msg/String", "/a/b", "std_msgs/msg/String", QoS(), "ros2:/a/b?type=std_msgs/msg/String"),
        (
            "ros2:/cam?reliability=best_effort&depth=1&type=sensor_msgs/msg/Image",
            "/cam",
            "sensor_msgs/msg/Image",
            QoS(Reliability.BEST_EFFORT, depth=1),
            "ros2:/cam?type=sensor_msgs/msg/Image&reliability=best_effort&depth=1",
        ),
        (
            "ros2:/map?durability=transient_local&depth=1",
            "/map",
            None,
            QoS(durability=Durability.TRANSIENT_LOCAL, depth=1),
            "ros2:/map?durability=transient_local&depth=1",
        ),
    ],
)
def test_bindings_parse_and_write_back(text: str, topic: str, ros_type: str | None, qos: QoS, uri: str) -> None:
    binding = parse_binding(text)
    assert (binding.topic, binding.ros_type, binding.qos) == (topic, ros_type, qos)
    assert binding.uri() == uri and parse_binding(uri) == binding


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("ros2:chatter", "fully qualified"),
        ("ros2:/chatter?typ=std_msgs/msg/String", "did you mean 'type'"),
        ("ros2:/chatter?type=String", "std_msgs/msg/String"),
        ("ros2:/chatter?reliability=sometimes", "reliable or best_effort"),
        ("ros2:/chatter?depth=0", "from 1 to 10000"),
        ("ros2:/chatter?depth=1&depth=2", "twice"),
        ("dyknow/x", "ros2:/TOPIC"),
    ],
)
def test_bad_bindings_are_refused_naming_the_option(text: str, problem: str) -> None:
    with pytest.raises(BindingError, match=problem):
        parse_binding(text)


def test_the_decode_option() -> None:
    binding = parse_binding("ros2:/cam/compressed?type=sensor_msgs/msg/CompressedImage&decode=bgr")
    assert binding.decode and binding.uri() == "ros2:/cam/compressed?type=sensor_msgs/msg/CompressedImage&decode=bgr"
    with pytest.raises(BindingError, match="decode='rgb'"):
        parse_binding("ros2:/cam/compressed?decode=rgb")


@pytest.fixture
def ros(make_manager: Callable[..., Manager]) -> Manager:
    return make_manager(ros2_domain=7, ros2_node="dk", ros2_namespace="/robot")


def test_a_port_bound_to_ros2_shows_its_binding_and_its_companion(ros: Manager) -> None:
    info = ros.spawn("publisher", "src", bindings={"out": "ros2:/chatter?type=std_msgs/msg/String"})
    assert info.bindings == {"out": "ros2:/chatter?type=std_msgs/msg/String"}
    assert ros.get_config("src") == {"out": "ros2:/chatter?type=std_msgs/msg/String"}
    units = {u.name: u for u in ros.get_model().units}
    assert units["src"].bindings == {"out": "ros2:/chatter?type=std_msgs/msg/String"}
    assert units["src.out.ros2"].label == "ros2-sink"
    view = snapshot(ros.session, 7)
    assert view.nodes() == ["/robot/dk"]
    assert view.topics() == {"/chatter": ["std_msgs/msg/String"]}
    ros.destroy("src")
    assert [u.name for u in ros.get_model().units] == []
    wait_until(lambda: snapshot(ros.session, 7, timeout_s=0.2).topics() == {}, "the publisher's token gone")


def test_set_config_moves_a_port_to_ros2_and_back(ros: Manager) -> None:
    ros.spawn("sink", "snk")
    assert ros.set_config("snk", {"in": "ros2:/echo?type=std_msgs/msg/String"}) == {"in": "ros2:/echo?type=std_msgs/msg/String"}
    assert "snk.in.ros2" in [u.name for u in ros.get_model().units]
    assert ros.set_config("snk", {"in": "ros2:/other?type=std_msgs/msg/String"}) == {"in": "ros2:/other?type=std_msgs/msg/String"}
    assert ros.set_config("snk", {"in": "robot/plain"}) == {"in": "robot/plain"}
    assert [u.name for u in ros.get_model().units] == ["snk"]


def test_messages_cross_between_two_managers_over_ros2(make_manager: Callable[..., Manager]) -> None:
    port = free_port()
    a = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=3)
    b = make_manager(connect=[f"tcp/127.0.0.1:{port}"], ros2_domain=3)
    b.spawn("sink", "snk", bindings={"in": "ros2:/relay?type=geometry_msgs/msg/Twist"})
    a.spawn("publisher", "src", bindings={"out": "ros2:/relay?type=geometry_msgs/msg/Twist"})
    sink = b.unit("snk")
    deadline = time.monotonic() + 20
    while not sink.messages:  # type: ignore[attr-defined]
        assert time.monotonic() < deadline
        a.unit("src").emit({"linear": {"x": 0.5}})  # type: ignore[attr-defined]
        time.sleep(0.05)
    assert sink.messages[0].payload["linear"] == {"x": 0.5, "y": 0.0, "z": 0.0}  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("bindings", "problem"),
    [
        ({"out": "ros2:/chatter"}, "names no type"),
        ({"out": "ros2:/chatter?type=std_msgs/msg/Strin"}, "did you mean 'std_msgs/msg/String'"),
        ({"nope": "ros2:/chatter"}, "no port 'nope'"),
    ],
)
def test_bad_ros2_bindings_change_nothing(ros: Manager, bindings: dict[str, str], problem: str) -> None:
    with pytest.raises(DyKnowError, match=problem):
        ros.spawn("publisher", "src", bindings=bindings)
    assert ros.get_model().units == ()


def test_a_payload_that_does_not_fit_is_rejected_and_counted(ros: Manager) -> None:
    ros.spawn("publisher", "src", bindings={"out": "ros2:/chatter?type=std_msgs/msg/String"})
    ros.unit("src").emit({"not": "text"})  # type: ignore[attr-defined]
    wait_until(lambda: ros.get_statistics("src.out.ros2").ports[0].rejected == 1, "one rejection")
    assert "text (str)" in str(ros.get_statistics("src.out.ros2").ports[0].last_rejection)
    assert ros.get_model().units[1].state == "running"


def test_the_cli_binds_lists_and_echoes(tmp_path: object) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    manager = CliProcess(
        "manager", "--name", "rc", "--specs", str(UNIT_SPECS), "--listen", endpoint, "--ros2-domain", "4", "--ros2-node", "dk_rc", "--json"
    )
    try:
        assert manager.line()["event"] == "ready"
        spawned = run_cli(
            "spawn", "sink", "snk", "--bind", "in=ros2:/from_ros?type=std_msgs/msg/String", "--manager", "rc", "--connect", endpoint
        )
        assert spawned.returncode == 0, spawned.stderr
        listed = run_cli("ros2", "list", "--json", "--connect", endpoint, "--ros2-domain", "4")
        assert listed.returncode == 0, listed.stderr
        graph = json.loads(listed.stdout)
        assert "/dk_rc" in graph["nodes"] and graph["topics"]["/from_ros"] == ["std_msgs/msg/String"]
        with open_session(listen=["tcp/127.0.0.1:0"], connect=[endpoint]) as session, Ros2Node(session, "talker", domain=4) as node:
            pub = node.create_publisher("/from_ros", "std_msgs/msg/String")
            stop = threading.Event()

            def talk() -> None:
                while not stop.wait(0.05):
                    pub.publish(node.types.message_class("std_msgs/msg/String")(data="hi"))

            talker = threading.Thread(target=talk, daemon=True)
            talker.start()
            try:
                echoed = run_cli(
                    "echo", "ros2:/from_ros", "--count", "2", "--json", "--connect", endpoint, "--ros2-domain", "4", "--timeout-total", "20"
                )
            finally:
                stop.set()
                talker.join(10)  # before the node closes its publisher under it
        assert echoed.returncode == 0, echoed.stderr
        lines = [json.loads(line) for line in echoed.stdout.splitlines()]
        assert [line["payload"] for line in lines] == ["hi", "hi"]
        assert lines[0]["type"] == "std_msgs/msg/String" and lines[0]["measured_from"] == "source_timestamp"
        model = run_cli("config", "get", "snk", "--manager", "rc", "--connect", endpoint, "--json")
        assert json.loads(model.stdout) == {"in": "ros2:/from_ros?type=std_msgs/msg/String"}
        bad = run_cli("spawn", "publisher", "p", "--bind", "out=ros2:/x", "--manager", "rc", "--connect", endpoint)
        assert bad.returncode != 0 and "names no type" in bad.stderr
    finally:
        manager.stop()
        manager.close()


def test_a_transient_local_output_reaches_a_late_subscriber(make_manager: Callable[..., Manager]) -> None:
    port = free_port()
    a = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=6)
    a.spawn("publisher", "latched", bindings={"out": "ros2:/map?type=std_msgs/msg/String&durability=transient_local&depth=1"})
    a.unit("latched").emit("the map")  # type: ignore[attr-defined]
    b = make_manager(connect=[f"tcp/127.0.0.1:{port}"], ros2_domain=6)  # joins after the message was sent
    b.spawn("sink", "late", bindings={"in": "ros2:/map?type=std_msgs/msg/String&durability=transient_local&depth=1"})
    assert b.unit("late").wait_for(1, timeout_s=20)[0].payload == "the map"  # type: ignore[attr-defined]


def test_the_readmes_relay_echoes_a_topic(make_manager: Callable[..., Manager]) -> None:
    port = free_port()
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=8)  # generic.xml has the relay
    robot.spawn("relay", "echo", bindings={"in": "ros2:/chatter", "out": "ros2:/chatter_echo?type=std_msgs/msg/String"})
    got: list[str] = []
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
        Ros2Node(session, "talker", domain=8) as node,
    ):
        node.create_subscription("/chatter_echo", "std_msgs/msg/String", lambda r: got.append(r.message.data))
        pub = node.create_publisher("/chatter", "std_msgs/msg/String")
        deadline = time.monotonic() + 20
        while not got:
            assert time.monotonic() < deadline, "nothing echoed in 20 s"
            pub.publish(node.types.message_class("std_msgs/msg/String")(data="ping"))
            time.sleep(0.05)
    assert got[0] == "ping"


def test_a_humble_publisher_without_type_hash_reaches_an_untyped_input(make_manager: Callable[..., Manager]) -> None:
    port = free_port()
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=9)
    robot.spawn("sink", "snk", bindings={"in": "ros2:/humble_chatter"})
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
        Ros2Node(session, "humble", domain=9) as node,
    ):
        pub = node.create_publisher("/humble_chatter", "std_msgs/msg/String", humble=True)
        assert pub.key.endswith("/TypeHashNotSupported")
        sink = robot.unit("snk")
        deadline = time.monotonic() + 20
        while not sink.messages:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            pub.publish(node.types.message_class("std_msgs/msg/String")(data="from humble"))
            time.sleep(0.05)
    assert sink.messages[0].payload == "from humble"  # type: ignore[attr-defined]


def test_echo_reads_a_dds_topic(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager(ros2_domain=11)
    manager.spawn("publisher", "talker", bindings={"out": "ros2dds:/dds_chatter?type=std_msgs/msg/String"})
    stop = threading.Event()

    def talk() -> None:
        while not stop.wait(0.05):
            manager.unit("talker").emit("over dds")  # type: ignore[attr-defined]

    talker = threading.Thread(target=talk, daemon=True)
    talker.start()
    try:
        echoed = run_cli(
            "echo",
            "ros2dds:/dds_chatter?type=std_msgs/msg/String",
            "--count",
            "1",
            "--json",
            "--ros2-domain",
            "11",
            "--timeout-total",
            "30",
        )
    finally:
        stop.set()
        talker.join(10)  # before the manager closes under it
    assert echoed.returncode == 0, echoed.stderr
    assert json.loads(echoed.stdout.splitlines()[0])["payload"] == "over dds"


def test_a_units_own_set_config_refuses_a_ros2_binding(ros: Manager) -> None:
    ros.spawn("sink", "snk")
    with pytest.raises(BindingError, match="is a ROS 2 binding, not a key"):
        ros.unit("snk").set_config({"in": "ros2:/chatter"})  # the proxy's: keys only; the manager's wires ROS 2
    assert ros.get_config("snk")["in"].endswith("/snk/in")


def test_a_bound_input_waits_across_a_publisher_restart(make_manager: Callable[..., Manager]) -> None:
    port = free_port()
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=10)
    robot.spawn("sink", "snk", bindings={"in": "ros2:/restarting?type=std_msgs/msg/String"})
    sink = robot.unit("snk")
    for text in ("before", "after"):  # the talker's node goes away between the two
        with (
            open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
            Ros2Node(session, "talker", domain=10) as node,
        ):
            pub = node.create_publisher("/restarting", "std_msgs/msg/String")
            deadline = time.monotonic() + 20
            while not any(m.payload == text for m in sink.messages):  # type: ignore[attr-defined]
                assert time.monotonic() < deadline, f"no {text!r} in 20 s"
                pub.publish(node.types.message_class("std_msgs/msg/String")(data=text))
                time.sleep(0.05)
    assert {u.name: u.state for u in robot.get_model().units}["snk.in.ros2"] == "running"


def test_a_publisher_of_another_type_hash_is_named_in_the_log(
    make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture
) -> None:
    port = free_port()
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=12)
    robot.spawn("sink", "snk", bindings={"in": "ros2:/hashed?type=std_msgs/msg/String"})
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
        Ros2Node(session, "humble", domain=12) as node,
    ):
        node.create_publisher("/hashed", "std_msgs/msg/String", humble=True)  # TypeHashNotSupported: another key
        wait_until(lambda: "so none of its messages will match" in caplog.text, "the warning")
    assert "/humble of /hashed announces std_msgs/msg/String TypeHashNotSupported" in caplog.text
