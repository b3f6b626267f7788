"""``ros2:`` bindings: parsing, and ports bound to ROS 2 topics in a manager (spawn, set_config,
the model, destroy) and on the command line (--bind, --ros2-domain, echo ros2:, ros2 list)."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dyknow import Manager
from dyknow.client import Client
from dyknow.errors import BindingError, DyKnowError
from dyknow.message import Message
from dyknow.ros2 import Ros2Node, Ros2Source, TypeSupport, parse_binding, snapshot
from dyknow.ros2.names import Durability, QoS, Reliability
from dyknow.ros2.node import DEFAULT_MAX_MESSAGE_BYTES
from dyknow.testing import Sink
from dyknow.transport import open_session
from tests.conftest import UNIT_SPECS, CliProcess, ManagerProcess, free_port, run_cli, wait_until


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
        (
            "ros2:/cloud?max_bytes=65536&type=sensor_msgs/msg/PointCloud2",
            "/cloud",
            "sensor_msgs/msg/PointCloud2",
            QoS(),
            "ros2:/cloud?type=sensor_msgs/msg/PointCloud2&max_bytes=65536",
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
        ("ros2:/cloud?max_bytes=0", "max_bytes='0'; expected a whole number of bytes from 1 to 67108864"),
        ("ros2:/cloud?max_bytes=16MiB", "max_bytes='16MiB'"),
        ("ros2:/cloud?max_bytes=67108865", "from 1 to 67108864"),
        ("dyknow/x", "ros2:/TOPIC"),
    ],
)
def test_bad_bindings_are_refused_naming_the_option(text: str, problem: str) -> None:
    with pytest.raises(BindingError, match=problem):
        parse_binding(text)


def test_the_max_bytes_option() -> None:
    assert parse_binding("ros2:/cloud?max_bytes=1024").max_bytes == 1024
    assert parse_binding("ros2:/cloud").max_bytes is None  # the node's default


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


@pytest.mark.process
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


def test_every_late_subscriber_gets_the_latched_message_however_new_its_link(make_manager: Callable[..., Manager]) -> None:
    """Managers are Zenoh routers: one that has just linked may not have its neighbour's cache
    routed yet when its subscriber asks for history, and Zenoh never asked again (the second and
    third pairs of a process missed the latched message every time). The subscriber is declared
    again while it has received nothing, and gets it once."""
    for domain in (11, 12, 13):
        port = free_port()
        a = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=domain)
        a.spawn("publisher", "latched", bindings={"out": "ros2:/map?type=std_msgs/msg/String&durability=transient_local&depth=1"})
        a.unit("latched").emit(f"map {domain}")  # type: ignore[attr-defined]
        b = make_manager(connect=[f"tcp/127.0.0.1:{port}"], ros2_domain=domain)
        b.spawn("sink", "late", bindings={"in": "ros2:/map?type=std_msgs/msg/String&durability=transient_local&depth=1"})
        late = b.unit("late")
        assert late.wait_for(1, timeout_s=20)[0].payload == f"map {domain}"  # type: ignore[attr-defined]
        a.unit("latched").emit("after")  # type: ignore[attr-defined]
        assert [m.payload for m in late.wait_for(2, timeout_s=20)] == [f"map {domain}", "after"]  # type: ignore[attr-defined]
        b.close()
        a.close()


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


@pytest.mark.process
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


POINT_CLOUD = "sensor_msgs/msg/PointCloud2"


def cloud(types: TypeSupport, points: int, stamp_s: int = 1) -> bytes:
    """The CDR of an unorganised PointCloud2 of ``points`` points of x, y, z, intensity (float32)."""
    t = types.message_class
    fields = [t("sensor_msgs/msg/PointField")(name=name, offset=4 * i, datatype=7, count=1) for i, name in enumerate(("x", "y", "z", "i"))]
    header = t("std_msgs/msg/Header")(stamp=t("builtin_interfaces/msg/Time")(sec=stamp_s, nanosec=0), frame_id="lidar")
    data = np.arange(points * 4, dtype=np.float32).view(np.uint8)
    message = t(POINT_CLOUD)(
        header=header,
        height=1,
        width=points,
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * points,
        data=data,
        is_dense=True,
    )
    return types.serialize(message, POINT_CLOUD)


def test_a_message_over_the_bound_is_dropped_before_it_is_decoded(
    make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture
) -> None:
    port = free_port()
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=17)
    robot.spawn("sink", "snk", bindings={"in": f"ros2:/cloud?type={POINT_CLOUD}&max_bytes=100000"})
    source = robot.unit("snk.in.ros2")
    sink = robot.unit("snk")
    assert isinstance(source, Ros2Source) and isinstance(sink, Sink)
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
        Ros2Node(session, "lidar", domain=17) as lidar,
    ):
        pub = lidar.create_publisher("/cloud", POINT_CLOUD, QoS(keep_all=True))  # reliable keep-all: none lost on the way
        big, small = cloud(lidar.types, 10_000), cloud(lidar.types, 100)  # 160 kB and 1.6 kB
        wait_until(lambda: (pub.publish_cdr(big), source.oversized >= 1)[1], "the large cloud dropped")
        wait_until(lambda: (pub.publish_cdr(small), bool(sink.messages))[1], "a small cloud through")
    assert {m.payload["width"] for m in sink.messages} == {100}  # nothing over the bound reached the unit
    assert f"a payload of {len(big)} bytes, over the limit of 100000" in caplog.text
    assert f"ros2:/cloud?type={POINT_CLOUD}&max_bytes=100000 (unit 'snk.in.ros2') refused a message" in caplog.text


def test_a_manager_sets_the_bound_of_its_inputs(make_manager: Callable[..., Manager]) -> None:
    from dyknow.security import Limits

    assert Limits().max_ros2_message_bytes == DEFAULT_MAX_MESSAGE_BYTES == 16 << 20
    robot = make_manager(ros2_domain=18, limits=Limits(max_ros2_message_bytes=4096))
    robot.spawn("sink", "typed", bindings={"in": f"ros2:/a?type={POINT_CLOUD}"})
    robot.spawn("sink", "untyped", bindings={"in": "ros2:/b"})
    robot.spawn("sink", "chosen", bindings={"in": f"ros2:/c?type={POINT_CLOUD}&max_bytes=100"})
    bounds = {name: robot.unit(f"{name}.in.ros2").max_bytes for name in ("typed", "untyped", "chosen")}  # type: ignore[attr-defined]
    assert bounds == {"typed": 4096, "untyped": 4096, "chosen": 100}
    assert make_manager(ros2_domain=18).ros2_node().max_message_bytes == 16 << 20


def _peak_rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    raise AssertionError("no VmHWM")


@pytest.mark.process
def test_large_clouds_cost_a_manager_no_memory_on_typed_and_untyped_inputs(manager_process: Callable[..., ManagerProcess]) -> None:
    """A 60 MiB PointCloud2 cost 7-13 s of a manager's CPU and +900-1,000 MiB of memory, and an
    untyped input took a 48 MiB one (+528 MiB). By default a typed input takes at most 16 MiB and
    an untyped one 1 MiB: a 40 MiB cloud is dropped on both before it is copied (Zenoh itself
    reassembles it once), and the clouds under the bounds go through."""
    proc = manager_process("--ros2-domain", "19")
    with Client(proc.name, connect=[proc.endpoint], timeout_s=20) as client:
        client.spawn("sink", "typed", bindings={"in": f"ros2:/lidar?type={POINT_CLOUD}"})
        client.spawn("sink", "untyped", bindings={"in": "ros2:/lidar_any"})
        with (
            open_session(listen=["tcp/127.0.0.1:0"], connect=[proc.endpoint]) as session,
            Ros2Node(session, "lidar", domain=19) as lidar,
        ):
            typed = lidar.create_publisher("/lidar", POINT_CLOUD, QoS(keep_all=True))  # reliable keep-all: none lost on the way
            untyped = lidar.create_publisher("/lidar_any", POINT_CLOUD, QoS(keep_all=True))
            small = cloud(lidar.types, 100, stamp_s=int(time.time()))  # stamped now: a latency of moments
            for pub, unit in ((typed, "typed"), (untyped, "untyped")):  # both matched before the large clouds go
                wait_until(lambda p=pub, u=unit: (p.publish_cdr(small), _messages(client, u) >= 1)[1], f"a small cloud on {unit}")
            peak = _peak_rss_kib(proc.proc.pid)
            large = cloud(lidar.types, (40 << 20) // 16)
            # the small cloud after the large one is told by its stamp (1 s after 1970: a latency of
            # decades), not by a count: small clouds sent while matching may still be on their way
            marker = cloud(lidar.types, 100, stamp_s=1)
            for pub in (typed, untyped):
                pub.publish_cdr(large)
                pub.publish_cdr(marker)  # behind the large one on the same link: in once the large one was dealt with
            for unit in ("typed", "untyped"):
                wait_until(lambda u=unit: _latency_max_us(client, u) > 1e15, f"the small cloud after the large one on {unit}")
            grew = _peak_rss_kib(proc.proc.pid) - peak
            assert client.get_model()["manager"] == proc.name
    assert proc.stop() == 0
    assert grew < 128 * 1024, f"the manager's peak memory grew by {grew / 1024:.0f} MiB"
    stderr = proc.proc.stderr.read() if proc.proc.stderr else ""
    assert f"a payload of {len(large)} bytes, over the limit of {16 << 20}" in stderr
    assert f"a payload of {len(large)} bytes, over the limit of {1 << 20}" in stderr


def _messages(client: Client, unit: str) -> int:
    return int(client.get_statistics(unit)["ports"]["in"]["messages"])


def _latency_max_us(client: Client, unit: str) -> float:
    return float(client.get_statistics(unit)["ports"]["in"]["latency"]["max_us"])


def test_a_message_held_in_decoding_holds_no_one_else(make_manager: Callable[..., Manager], monkeypatch: pytest.MonkeyPatch) -> None:
    """A message is decoded on its input's own thread (the companion unit's lane), never on the
    Zenoh thread that received it: while one is held in decoding, the messages behind it are
    queued (the newest ``depth`` kept) and a get_model sent on the very link they come by is
    answered. Decoded on Zenoh's thread, the samples behind it filled Zenoh's queue for that
    subscriber and stalled the link, get_model's request with it."""
    port = free_port()
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=20)
    robot.spawn("sink", "snk", bindings={"in": "ros2:/chatter?type=std_msgs/msg/String&depth=5"})
    source = robot.unit("snk.in.ros2")
    assert isinstance(source, Ros2Source)
    types = robot.ros2_node().types
    decode = types.deserialize
    holding, release = threading.Event(), threading.Event()
    threads: list[str] = []

    def held(data: bytes, ros_type: str) -> object:
        threads.append(threading.current_thread().name)
        if not holding.is_set():
            holding.set()
            release.wait(60)
        return decode(data, ros_type)

    monkeypatch.setattr(types, "deserialize", held)
    try:
        with (
            open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
            Ros2Node(session, "talker", domain=20) as talker,
            Client(robot.name, session=session, timeout_s=10) as client,
        ):
            pub = talker.create_publisher("/chatter", "std_msgs/msg/String")  # drops, as rmw_zenoh's, rather than block
            text = talker.types.message_class("std_msgs/msg/String")
            wait_until(lambda: (pub.publish(text(data="first")), holding.is_set())[1], "a message in decoding")
            for i in range(3000):
                pub.publish(text(data=f"behind {i}"))
            model = client.get_model()  # on the same link, behind the 3,000
            answered_while_held = not release.is_set()
            dropped = source.dropped
    finally:
        release.set()
    assert answered_while_held and model["manager"] == robot.name
    assert dropped > 0  # the queue kept the newest 5
    assert threads[0].startswith("dyknow-"), threads[0]  # the lane's thread, not Zenoh's
    sink = robot.unit("snk")
    wait_until(lambda: len(sink.messages) >= 2, "the queued messages delivered once the decode ended")  # type: ignore[attr-defined]
    assert len(sink.messages) <= 1 + 5 + 1  # type: ignore[attr-defined]  # the held one, the queue's depth, one in flight


def test_a_clouds_data_stays_binary_to_a_unit_and_to_another_process(make_manager: Callable[..., Manager]) -> None:
    """A 32 MiB PointCloud2 became a 64 MiB-and-more JSON dict, which reached no one. Its data
    now comes as a numpy array: by reference to the bound unit, and as its bytes to a subscriber
    in another session (the message's JSON text is a few hundred bytes)."""
    port = free_port()
    robot = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=28)
    robot.spawn("sink", "snk", bindings={"in": f"ros2:/cloud?type={POINT_CLOUD}&max_bytes={48 << 20}"})
    sink = robot.unit("snk")
    assert isinstance(sink, Sink)
    received: list[Message] = []
    points = (32 << 20) // 16
    with (
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session,
        Ros2Node(session, "lidar", domain=28) as lidar,
        Client(robot.name, session=session, timeout_s=10) as client,
        client.declare_subscriber(f"dyknow/{robot.name}/snk.in.ros2/out", received.append),
    ):
        pub = lidar.create_publisher("/cloud", POINT_CLOUD, QoS(keep_all=True))  # reliable keep-all: none lost on the way
        small = cloud(lidar.types, 100)
        wait_until(lambda: (pub.publish_cdr(small), bool(received) and bool(sink.messages))[1], "small clouds to both")
        large = cloud(lidar.types, points)
        pub.publish_cdr(large)
        wait_until(lambda: any(m.payload["width"] == points for m in list(received)), "the large cloud in the other session")
    local = next(m.payload for m in sink.messages if m.payload["width"] == points)
    remote = next(m for m in received if m.payload["width"] == points)
    assert isinstance(local["data"], np.ndarray) and local["data"].nbytes == 32 << 20
    assert remote.nbytes < (32 << 20) + 2048, remote.nbytes  # the data's bytes and a little JSON
    assert isinstance(remote.payload["data"], np.ndarray) and np.array_equal(remote.payload["data"], local["data"])
    assert remote.payload["fields"] == local["fields"] and remote.payload["header"]["frame_id"] == "lidar"
