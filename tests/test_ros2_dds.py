"""ROS 2 over DDS: a dyknow manager (``ros2dds:`` bindings, Cyclone DDS) and real rclpy nodes
(the ROS 2 wheels, rmw_fastrtps_cpp) exchanging ``std_msgs/String`` and ``sensor_msgs/Image`` on
loopback, both directions. Each test runs on a ROS domain of its own (discovery is unicast to
127.0.0.1 on both sides: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and dyknow's loopback config)."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dyknow import Manager
from dyknow.errors import BindingError, ServiceError
from dyknow.ros2 import parse_binding
from dyknow.ros2.dds import FASTDDS_PROFILE
from tests.conftest import REPO, dds_domain, run_cli, subprocess_env, wait_until

PEER = Path(__file__).with_name("ros2_rclpy_peer.py")


class Rclpy:
    """An rclpy node in a child process; JSON lines out, stopped by closing its stdin."""

    def __init__(self, domain: int, *args: str, type_propagation: bool = False) -> None:
        env = subprocess_env()
        env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
        # Fast DDS 3 sends type objects for sequences of plain types that Cyclone 11 refuses (both log
        # "invalid type object"), and then an Image never matches: the ROS side turns type propagation off
        if not type_propagation:
            env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_PROFILE)
        self.proc = subprocess.Popen(
            [sys.executable, str(PEER), *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=REPO,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.lines.put(json.loads(line))

    def ready(self) -> None:
        try:
            assert self.lines.get(timeout=30) == {"ready": True}
        except queue.Empty:
            self.proc.kill()  # its stderr is read before close() closes it
            stderr = self.proc.stderr.read() if self.proc.stderr else ""
            self.close()
            raise AssertionError(f"rclpy did not start within 30 s: {stderr[-2000:]}") from None

    def send(self, line: str) -> None:
        """A command for the peer (a lifecycle node's "fail" or "stall")."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            self.proc.stdin.close()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture
def domain() -> int:
    """A DDS domain of this test's own (no other test of a parallel run is on it)."""
    return dds_domain()


@pytest.fixture
def rclpy_node(domain: int) -> Iterator[Callable[..., Rclpy]]:
    started: list[Rclpy] = []

    def start(*args: str, type_propagation: bool = False) -> Rclpy:
        node = Rclpy(domain, *args, type_propagation=type_propagation)
        started.append(node)
        node.ready()
        return node

    yield start
    for node in started:
        node.close()


@pytest.fixture
def dds_manager(make_manager: Callable[..., Manager], domain: int) -> Manager:
    return make_manager(ros2_domain=domain)


def test_dds_bindings_write_back() -> None:
    assert parse_binding("ros2dds:/chatter?type=std_msgs/msg/String").uri() == "ros2dds:/chatter?type=std_msgs/msg/String"
    assert parse_binding("ros2dds:/chatter").dds


@pytest.mark.process
def test_an_untyped_dds_input_takes_the_type_its_writers_announce(dds_manager: Manager, rclpy_node: Callable[..., Rclpy]) -> None:
    rclpy_node("talk", "/chatter", "std_msgs/msg/String")
    dds_manager.spawn("sink", "listener", bindings={"in": "ros2dds:/chatter"})
    assert dds_manager.unit("listener").wait_for(1, timeout_s=30)[0].payload.startswith("hello ")  # type: ignore[attr-defined]
    with pytest.raises(BindingError, match="announced none"):
        dds_manager.spawn("sink", "nobody", bindings={"in": "ros2dds:/nobody_writes_this"})


@pytest.mark.process
def test_a_unit_reads_an_rclpy_talker_over_dds(dds_manager: Manager, rclpy_node: Callable[..., Rclpy]) -> None:
    dds_manager.spawn("sink", "listener", bindings={"in": "ros2dds:/chatter?type=std_msgs/msg/String"})
    rclpy_node("talk", "/chatter", "std_msgs/msg/String", type_propagation=True)  # Fast DDS as it comes
    msgs = dds_manager.unit("listener").wait_for(3, timeout_s=30)  # type: ignore[attr-defined]
    assert all(m.payload.startswith("hello ") for m in msgs)
    assert 0 <= time.time_ns() - msgs[0].origin_ns < 30e9  # the DDS source timestamp


@pytest.mark.process
def test_a_unit_reads_rclpy_images_over_dds(dds_manager: Manager, rclpy_node: Callable[..., Rclpy]) -> None:
    dds_manager.spawn("sink", "viewer", bindings={"in": "ros2dds:/image?type=sensor_msgs/msg/Image"})
    rclpy_node("talk", "/image", "sensor_msgs/msg/Image")
    msg = dds_manager.unit("viewer").wait_for(1, timeout_s=30)[0]  # type: ignore[attr-defined]
    assert np.array_equal(msg.payload, np.arange(18, dtype=np.uint8).reshape(2, 3, 3)[:, :, ::-1])
    assert msg.origin_ns % 1_000_000_000 == 5  # the header stamp


@pytest.mark.process
@pytest.mark.parametrize("ros_type", ["std_msgs/msg/String", "sensor_msgs/msg/Image"])
def test_an_rclpy_listener_reads_what_dyknow_publishes_over_dds(
    dds_manager: Manager, rclpy_node: Callable[..., Rclpy], ros_type: str
) -> None:
    dds_manager.spawn("publisher", "talker", bindings={"out": f"ros2dds:/from_dyknow?type={ros_type}"})
    listener = rclpy_node("listen", "/from_dyknow", ros_type)
    payload: Any = "from dyknow" if ros_type.endswith("String") else np.arange(24, dtype=np.uint8).reshape(2, 4, 3)
    deadline = time.monotonic() + 30
    while True:
        dds_manager.unit("talker").emit(payload, origin_ns=1_700_000_000_250_000_000)  # type: ignore[attr-defined]
        try:
            got = listener.lines.get(timeout=0.1)
            break
        except queue.Empty:
            assert time.monotonic() < deadline, "rclpy received nothing in 30 s"
    if ros_type.endswith("String"):
        assert got == {"data": "from dyknow"}
    else:
        assert got == {
            "encoding": "bgr8",
            "height": 2,
            "width": 4,
            "step": 12,
            "data": list(range(24)),
            "stamp": [1_700_000_000, 250_000_000],
        }


def test_two_managers_of_one_process_share_a_dds_domain(make_manager: Callable[..., Manager], domain: int) -> None:
    a, b = make_manager(ros2_domain=domain), make_manager(ros2_domain=domain)
    b.spawn("sink", "snk", bindings={"in": "ros2dds:/between?type=geometry_msgs/msg/Twist"})
    a.spawn("publisher", "src", bindings={"out": "ros2dds:/between?type=geometry_msgs/msg/Twist"})
    deadline = time.monotonic() + 30
    while not b.unit("snk").messages:  # type: ignore[attr-defined]
        assert time.monotonic() < deadline, "nothing crossed in 30 s"
        a.unit("src").emit({"angular": {"z": 1.5}})  # type: ignore[attr-defined]
        time.sleep(0.05)
    assert b.unit("snk").messages[0].payload["angular"]["z"] == 1.5  # type: ignore[attr-defined]
    with pytest.raises(BindingError, match="configured already"):
        make_manager(ros2_domain=domain, dds_config="<CycloneDDS/>").dds_node()


@pytest.mark.process
def test_ros2_list_shows_the_dds_topics(dds_manager: Manager, rclpy_node: Callable[..., Rclpy], domain: int) -> None:
    dds_manager.spawn("publisher", "talker", bindings={"out": "ros2dds:/from_dyknow?type=std_msgs/msg/String"})
    rclpy_node("talk", "/chatter", "std_msgs/msg/String")
    listed = run_cli("ros2", "list", "--dds", "--json", "--ros2-domain", str(domain), "--timeout", "3")
    assert listed.returncode == 0, listed.stderr
    topics = json.loads(listed.stdout)["topics"]
    assert topics["/chatter"] == ["std_msgs/msg/String"] and topics["/from_dyknow"] == ["std_msgs/msg/String"]


@pytest.mark.process
def test_a_tagged_dds_topic_is_left_when_its_writer_goes(
    make_manager: Callable[..., Manager], domain: int, rclpy_node: Callable[..., Rclpy]
) -> None:
    from dyknow.spec import TransformationSpec
    from dyknow.spec.model import Param, Port, Tag
    from dyknow.testing import SCENARIO_SPECS
    from tests.test_adaptation import ONTOLOGY, Events

    camera = TransformationSpec(
        "dds-camera(bottom)",
        "dyknow.ros2.bridge:Ros2Source",
        (
            Param("binding", "string", "ros2dds:/image?type=sensor_msgs/msg/Image"),
            Param("require_publisher", "bool", True),
            Param("wait_s", "float", 20.0),
        ),
        (Port("out", "out"),),
        (Tag("out", "RawImage(bottom)"),),
        priority=0,
    )
    robot = make_manager(specs=[SCENARIO_SPECS, camera], ontology=[ONTOLOGY], dwell_s=0.3, ros2_domain=domain)
    events = Events(robot)
    talker = rclpy_node("talk", "/image", "sensor_msgs/msg/Image")
    robot.request("RawImage(bottom)")
    assert "dds-camera(bottom)" in {u.label for u in robot.get_model().units}
    talker.close()  # the rclpy node ends: its writer is no longer matched
    event = events.wait("adapted", timeout_s=30)
    assert "dds-camera(bottom)" in event.old and "robot-camera" in event.new, event.to_dict()


def _udp_receive_buffers(pid: int) -> list[int]:
    """The receive buffer sizes (``ss``'s ``rb``) of process ``pid``'s UDP sockets."""
    out = subprocess.run(["ss", "-uamnp"], capture_output=True, text=True, check=True).stdout
    sizes, owner = [], False
    for line in out.splitlines():
        if "users:" in line:
            owner = f"pid={pid}," in line
        if owner and "skmem:(" in line:
            sizes.append(int(line.split("skmem:(", 1)[1].split(",rb", 1)[1].split(",", 1)[0]))
    return sizes


@pytest.mark.process
def test_the_shipped_fast_dds_profile_gives_rclpy_large_udp_buffers(rclpy_node: Callable[..., Rclpy]) -> None:
    """With the kernel's default 208 kB, a third of a 640x480 image's datagrams from Cyclone were
    dropped (benchmarks/ros2.py: p50 159 ms, 17 % of the frames lost); the profile asks for 4 MB,
    as far as net.core.rmem_max lets it."""
    listener = rclpy_node("listen", "/image", "sensor_msgs/msg/Image")
    rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    rmem_default = int(Path("/proc/sys/net/core/rmem_default").read_text())
    wanted = min(4 * 1024 * 1024, rmem_max)
    assert wanted > rmem_default, f"net.core.rmem_max is {rmem_max}: raise it to 4194304 (see docs/howto/ros2.md)"
    sizes = _udp_receive_buffers(listener.proc.pid)
    assert sizes and max(sizes) >= wanted, sizes  # (the kernel reports twice what was set)


# -- services over DDS: rq/<service>Request and rr/<service>Reply

CHANGE_STATE, GET_STATE = "lifecycle_msgs/srv/ChangeState", "lifecycle_msgs/srv/GetState"


@pytest.mark.process
def test_our_dds_client_drives_an_rclpy_lifecycle_node(domain: int, rclpy_node: Callable[..., Rclpy]) -> None:
    from dyknow.ros2.dds import DdsNode

    camera = rclpy_node("lifecycle", "camera_top")
    with DdsNode(domain=domain) as participant:
        get_state = participant.create_client("/camera_top/get_state", GET_STATE)
        change_state = participant.create_client("/camera_top/change_state", CHANGE_STATE)
        assert get_state.call({}, timeout_s=15).current_state.label == "unconfigured"
        assert change_state.call({"transition": {"id": 3}}, timeout_s=15).success is False  # activate from unconfigured: refused
        assert change_state.call({"transition": {"id": 1}}, timeout_s=15).success is True  # configure
        assert camera.lines.get(timeout=10) == {"transition": "configure", "exposure": 0.1}
        assert change_state.call({"transition": {"id": 3}}, timeout_s=15).success is True  # activate
        assert camera.lines.get(timeout=10) == {"transition": "activate"}
        state = get_state.call({}, timeout_s=15).current_state
        assert (state.id, state.label) == (3, "active")


@pytest.mark.process
def test_an_rclpy_client_does_not_take_the_answers_of_a_dds_service(domain: int, rclpy_node: Callable[..., Rclpy]) -> None:
    """What cannot work with these peers, and why: the request reaches dyknow's service and is
    answered, but rmw_fastrtps takes a response only when its related sample identity (RTPS
    inline QoS) names the request, and Cyclone DDS writes none (docs/howto/ros2.md). Should this
    start to pass the other way, the documentation is wrong."""
    from dyknow.ros2.dds import DdsNode

    with DdsNode(domain=domain) as participant:
        server = participant.create_service("/dyknow/get_state", GET_STATE, lambda r: {"current_state": {"id": 3, "label": "active"}})
        caller = rclpy_node("call", "/dyknow/get_state", GET_STATE, "{}", "10")
        assert caller.lines.get(timeout=30) == {"service": "found"}
        # (the caller asks every 0.5 s for 10 s: answers are written while it asks, and it takes
        # none. It asked for 3 s: once, in a whole suite, no request reached the server by then)
        wait_until(lambda: server.answered >= 1, "the server to answer a request while the caller asks", timeout_s=30)
        assert caller.lines.get(timeout=30) == {"response": None, "why": "no answer"}
        assert server.received >= server.answered and server.refused == 0


def test_a_dds_call_nobody_answers_names_the_service_and_the_time_waited(domain: int) -> None:
    from dyknow.errors import ServiceError
    from dyknow.ros2.dds import DdsNode

    with DdsNode(domain=domain) as participant:
        client = participant.create_client("/nobody/get_state", GET_STATE)
        started = time.monotonic()
        with pytest.raises(ServiceError, match=r"ROS 2 service /nobody/get_state \(lifecycle_msgs/srv/GetState\) over DDS: no answer in 0\.[5-9] s"):
            client.call({}, timeout_s=0.5)
        assert time.monotonic() - started < 5  # the timeout, and what a loaded machine adds to a wake-up (1.3 s seen beside hogs)


def test_a_dds_service_answers_a_dds_client(domain: int) -> None:
    from dyknow.ros2.dds import DdsNode

    def fails_on_4(request: Any) -> Any:
        if request.transition.id == 4:
            raise RuntimeError("no")
        return {"success": request.transition.id == 3}

    with DdsNode(domain=domain) as participant:
        server = participant.create_service("/robot/change_state", CHANGE_STATE, fails_on_4)
        client = participant.create_client("/robot/change_state", CHANGE_STATE)
        assert client.call({"transition": {"id": 3}}, timeout_s=15).success is True
        assert client.call({"transition": {"id": 2}}, timeout_s=15).success is False
        with pytest.raises(ServiceError, match=r"no answer in 0\.[5-9] s"):
            client.call({"transition": {"id": 4}}, timeout_s=0.5)
        assert (server.received, server.answered, server.failed) == (3, 2, 1)


def test_a_read_only_dds_call_asks_again_when_its_answer_is_lost_and_no_other_does(domain: int) -> None:
    """Over DDS a response is lost when the server has not yet matched the client's reader
    (beside CPU hogs, a new client's ``get_parameters`` waited its whole timeout, answered by
    the next client at once). A read-only call writes its request again each ``resend_s``; a
    call that changes something is written once, for a second ``change_state`` would be refused
    or done twice. Here the server answers nothing to its first request, as when it is lost."""
    from dyknow.ros2.dds import DdsNode
    from dyknow.ros2.services import READ_ONLY_SERVICES

    assert GET_STATE in READ_ONLY_SERVICES and CHANGE_STATE not in READ_ONLY_SERVICES
    seen: list[int] = []

    def lost_first(request: Any) -> Any:
        seen.append(1)
        if len(seen) == 1:
            raise RuntimeError("lost")  # (a handler's exception answers nothing)
        return {"current_state": {"id": 3, "label": "active"}}

    def never(request: Any) -> Any:
        raise RuntimeError("lost")

    with DdsNode(domain=domain) as participant:
        server = participant.create_service("/robot/get_state", GET_STATE, lost_first)
        client = participant.create_client("/robot/get_state", GET_STATE)
        assert client.call({}, timeout_s=30, resend_s=0.2).current_state.label == "active"
        assert server.failed == 1 and server.answered >= 1
        mute = participant.create_service("/mute/get_state", GET_STATE, never)
        once = participant.create_client("/mute/get_state", GET_STATE)
        with pytest.raises(ServiceError, match=r"no answer in \d+\.\d s"):
            once.call({}, timeout_s=2.0)  # (written once: its only answer lost)
        wait_until(lambda: mute.received >= 1, "the request to reach the server")
        assert mute.received == 1
        with pytest.raises(BindingError, match=r"resend every 0\.01 s"):
            client.call({}, timeout_s=1.0, resend_s=0.01)


@pytest.mark.process
def test_dyknow_ros2_call_and_list_over_dds(domain: int, rclpy_node: Callable[..., Rclpy]) -> None:
    rclpy_node("lifecycle", "camera_top")
    called = run_cli("ros2", "call", "/camera_top/get_state", GET_STATE, "--dds", "--ros2-domain", str(domain), "--json", "--timeout", "15")
    assert called.returncode == 0, called.stderr
    assert json.loads(called.stdout)["response"] == {"current_state": {"id": 1, "label": "unconfigured"}}
    listed = run_cli("ros2", "list", "--dds", "--json", "--ros2-domain", str(domain), "--timeout", "3")
    services = json.loads(listed.stdout)["services"]
    assert services["/camera_top/change_state"] == {"types": [CHANGE_STATE], "servers": 1, "clients": 0}
    assert services["/camera_top/get_state"]["types"] == [GET_STATE]


@pytest.mark.process
def test_a_dds_write_that_waits_for_acknowledgements_lets_other_threads_run(domain: int, rclpy_node: Callable[..., Rclpy]) -> None:
    """A reliable write waits while its reader has not acknowledged enough (here: the reader's
    process is stopped). It must wait without the interpreter lock: Cyclone's binding kept it,
    and a manager froze whole (its /diagnostics thread in the write, Cyclone's receive thread
    waiting for the lock to run a listener, so no acknowledgement was ever read)."""
    import os
    import signal

    from dyknow.ros2.convert import to_message
    from dyknow.ros2.dds import DdsNode
    from dyknow.ros2.names import QoS

    listener = rclpy_node("listen", "/blocked", "std_msgs/msg/String")
    with DdsNode(domain=domain) as participant:
        pub = participant.create_publisher("/blocked", "std_msgs/msg/String", QoS(keep_all=True))
        first = to_message("first", "std_msgs/msg/String", participant.types, origin_ns=0)
        big = to_message("x" * 250_000, "std_msgs/msg/String", participant.types, origin_ns=0)
        deadline = time.monotonic() + 30
        while True:  # matched both ways: the listener has read a message
            pub.publish(first)
            try:
                if listener.lines.get(timeout=0.1) == {"data": "first"}:
                    break
            except queue.Empty:
                assert time.monotonic() < deadline, "rclpy received nothing in 30 s"
        ticks: list[float] = []
        done = threading.Event()

        def tick() -> None:
            while not done.is_set():
                ticks.append(time.monotonic())
                time.sleep(0.005)

        ticker = threading.Thread(target=tick, daemon=True)
        os.kill(listener.proc.pid, signal.SIGSTOP)  # no acknowledgement from now on
        try:
            ticker.start()
            for _ in range(400):  # Cyclone holds up a writer past some 500 kB unacknowledged
                started = time.monotonic()
                try:
                    pub.publish(big)
                except BindingError:
                    pass  # the write gave up after the QoS's max_blocking_time (1 s)
                ended = time.monotonic()
                if ended - started >= 0.5:
                    break
            else:
                raise AssertionError("no write waited: the stopped reader was not holding the writer up")
        finally:
            done.set()
            os.kill(listener.proc.pid, signal.SIGCONT)
        ticker.join(5)
        during = [t for t in ticks if started + 0.1 < t < ended - 0.1]
        assert during, f"no other thread ran during a write that waited {ended - started:.2f} s"


def test_a_unicast_dds_configuration_names_the_address_it_refuses() -> None:
    from dyknow.ros2.dds import unicast_config

    config = unicast_config("10.77.0.2", ["10.77.0.1", "fd00::1"])
    assert '<NetworkInterface address="10.77.0.2"/>' in config and '<Peer address="10.77.0.1"/><Peer address="fd00::1"/>' in config
    assert "<AllowMulticast>false</AllowMulticast>" in config
    with pytest.raises(BindingError, match=r"peers 'robot\.local'.*expected an IPv4 or IPv6 address"):
        unicast_config("10.77.0.2", ["robot.local"])
    with pytest.raises(BindingError, match=r"address '10\.77\.0\.2\"/>'"):
        unicast_config('10.77.0.2"/>', [])
