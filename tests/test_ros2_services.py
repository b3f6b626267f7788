"""dyknow.ros2.services (ROS 2 services on rmw_zenoh) on real Zenoh sessions on loopback, and
against an rmw_zenoh implementation dyknow did not write (zenoh-ros2-sdk, tests/ros2_peer.py, a
child process) both ways: dyknow's client calls the SDK's server, the SDK's client calls dyknow's
server (a node's, and a unit's), and ``dyknow ros2 call`` / ``dyknow ros2 list`` end to end.
Keys, tokens and attachments as rmw_zenoh's ``docs/design.md`` states them; what a hostile peer
sends (oversized requests, bad attachments, floods) is refused and counted."""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from dyknow import Manager
from dyknow.errors import BindingError, ClosedError, ServiceError
from dyknow.ros2 import Attachment, Graph, Ros2Node, Ros2Server
from dyknow.spec import TransformationSpec
from dyknow.spec.model import Param
from dyknow.transport import Session, open_session
from tests.conftest import free_port, run_cli, wait_until
from tests.test_ros2_live import Peer

CHANGE_STATE, GET_STATE = "lifecycle_msgs/srv/ChangeState", "lifecycle_msgs/srv/GetState"


@pytest.fixture
def sessions() -> Iterator[tuple[Session, Session]]:
    port = free_port()
    with (
        open_session(listen=[f"tcp/127.0.0.1:{port}"]) as a,
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as b,
    ):
        yield a, b


@pytest.fixture
def peers() -> Iterator[Callable[..., Peer]]:
    started: list[Peer] = []

    def start(*args: str) -> Peer:
        peer = Peer(*args)
        started.append(peer)
        assert peer.line() == {"ready": True}
        return peer

    yield start
    for peer in started:
        peer.close()


def state(request: Any) -> dict[str, Any]:
    return {"current_state": {"id": 3, "label": "active"}}


def test_a_call_gets_its_response_and_the_tokens_come_and_go(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    seen: list[tuple[str, bool]] = []
    with Graph(b, 41, lambda e, alive: seen.append((e.kind.value, alive))) as graph:
        server_node, client_node = Ros2Node(a, "server", domain=41), Ros2Node(b, "caller", domain=41)
        server = server_node.create_service("/robot/change_state", CHANGE_STATE, lambda r: {"success": r.transition.id == 3})
        client = client_node.create_client("/robot/change_state", CHANGE_STATE)
        assert client.call({"transition": {"id": 3}}, timeout_s=10).success is True
        assert client.call(client.request(transition={"id": 4}), timeout_s=10).success is False  # a message object too
        assert server.key == f"41/robot/change_state/lifecycle_msgs::srv::dds_::ChangeState_/{server.type_hash}"
        wait_until(lambda: graph.view().services() == {"/robot/change_state": {"types": [CHANGE_STATE], "servers": 1, "clients": 1}}, "SS and SC")
        assert (server.received, server.answered, server.refused, server.failed) == (2, 2, 0, 0)
        client.close()
        server.close()
        server.close()  # safe twice
        wait_until(lambda: graph.view().services() == {}, "both tokens gone")
        assert sorted(kind for kind, alive in seen if not alive) == ["SC", "SS"]
        with pytest.raises(ClosedError, match="client is closed"):
            client.call({}, timeout_s=1)
        server_node.close()
        client_node.close()
        with pytest.raises(ClosedError, match="node is closed"):
            client_node.create_client("/robot/change_state", CHANGE_STATE)


def test_a_service_that_never_answers_is_an_error_naming_it_and_the_time_waited(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    with Ros2Node(a, "server", domain=42) as server_node, Ros2Node(b, "caller", domain=42) as client_node:
        nobody = client_node.create_client("/nobody/get_state", GET_STATE)
        started = time.monotonic()
        with pytest.raises(ServiceError, match=r"ROS 2 service /nobody/get_state \(lifecycle_msgs/srv/GetState\): no answer in 0\.[5-9] s"):
            nobody.call({}, timeout_s=0.5)
        assert time.monotonic() - started < 5  # the timeout, and what a loaded machine adds to a wake-up (1.3 s seen beside hogs)
        blocked = threading.Event()
        server_node.create_service("/slow/get_state", GET_STATE, lambda r: (blocked.wait(10), state(r))[1])
        slow = client_node.create_client("/slow/get_state", GET_STATE)
        with pytest.raises(ServiceError, match=r"/slow/get_state .*no answer in 0\.[5-9] s \(1 server\(s\) up\)"):
            slow.call({}, timeout_s=0.7)
        blocked.set()


def test_a_handler_that_raises_answers_nothing_and_is_logged(sessions: tuple[Session, Session], caplog: pytest.LogCaptureFixture) -> None:
    a, b = sessions

    def fails(request: Any) -> Any:
        raise RuntimeError("the driver is gone")

    with Ros2Node(a, "server", domain=43) as server_node, Ros2Node(b, "caller", domain=43) as client_node:
        server = server_node.create_service("/broken/get_state", GET_STATE, fails)
        wrong = server_node.create_service("/wrong/get_state", GET_STATE, lambda r: {"no_such_field": 1})
        with pytest.raises(ServiceError, match="ended the request without an answer"):
            client_node.create_client("/broken/get_state", GET_STATE).call({}, timeout_s=10)
        with pytest.raises(ServiceError, match="ended the request without an answer"):
            client_node.create_client("/wrong/get_state", GET_STATE).call({}, timeout_s=10)
        assert server.failed == 1 and wrong.failed == 1
    assert "ROS 2 service /broken/get_state: the handler failed on request #1, answered nothing" in caplog.text
    assert "the driver is gone" in caplog.text and "no_such_field" in caplog.text


def test_concurrent_calls_each_get_their_own_response(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    with Ros2Node(a, "server", domain=44) as server_node, Ros2Node(b, "caller", domain=44) as client_node:
        server_node.create_service("/echo", CHANGE_STATE, lambda r: {"success": r.transition.id % 2 == 0})
        client = client_node.create_client("/echo", CHANGE_STATE)
        assert client.wait_for_service(10)
        got: dict[int, bool] = {}

        def call(i: int) -> None:
            got[i] = client.call({"transition": {"id": i}}, timeout_s=10).success

        threads = [threading.Thread(target=call, args=(i,)) for i in range(20)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(20)
    assert got == {i: i % 2 == 0 for i in range(20)}


def test_what_a_hostile_client_sends_is_bounded(sessions: tuple[Session, Session]) -> None:
    """Oversized requests and bad attachments are dropped unanswered and counted; a flood over
    max_pending is dropped, not queued; the server still answers a good request afterwards."""
    a, b = sessions
    release = threading.Event()
    with Ros2Node(a, "server", domain=45) as server_node, Ros2Node(b, "caller", domain=45) as client_node:
        server = server_node.create_service(
            "/guarded", "rcl_interfaces/srv/SetParameters", lambda r: (release.wait(10), {"results": []})[1], max_bytes=2000, max_pending=2
        )
        client = client_node.create_client("/guarded", "rcl_interfaces/srv/SetParameters")
        big = {"parameters": [{"name": "x", "value": {"type": 4, "string_value": "y" * 5000}}]}
        with pytest.raises(ServiceError, match="without an answer"):
            client.call(big, timeout_s=5)
        assert server.refused == 1 and "a request of 5" in str(server.last_refusal) and "over the limit of 2000" in str(server.last_refusal)
        ended = threading.Event()
        for attachment in (None, b"short", Attachment(1, 0, bytes(16)).encode()[:-1]):
            ended.clear()
            b.query_plain(server.key, bytes(8), attachment, timeout_s=5, on_reply=lambda *x: None, on_error=lambda t: None, done=ended.set)
            assert ended.wait(10)
        assert server.refused == 4 and "attachment" in str(server.last_refusal)
        results: list[str] = []

        def call() -> None:
            try:
                client.call({"parameters": []}, timeout_s=10)
                results.append("answered")
            except ServiceError:
                results.append("dropped")

        threads = [threading.Thread(target=call) for _ in range(5)]
        for t in threads:
            t.start()
        wait_until(lambda: results.count("dropped") == 3, "three requests over max_pending dropped")
        assert server.refused == 7 and "2 requests already wait" in str(server.last_refusal)
        release.set()
        for t in threads:
            t.join(20)
        assert sorted(results) == ["answered", "answered", "dropped", "dropped", "dropped"]


def test_a_client_takes_only_the_reply_naming_its_call(sessions: tuple[Session, Session]) -> None:
    """Replies are not consolidated: of what several queryables on the key answer, the client
    takes the one whose attachment names its GID and sequence number, and refuses (counts) a
    malformed attachment."""
    a, b = sessions
    with Ros2Node(a, "server", domain=48) as server_node, Ros2Node(b, "caller", domain=48) as client_node:
        client = client_node.create_client("/contested", CHANGE_STATE)
        types = server_node.types
        types.service(CHANGE_STATE)
        lie = types.serialize(types.message_class("lifecycle_msgs/srv/ChangeState_Response")(success=False), "lifecycle_msgs/srv/ChangeState_Response")

        def impostor(query: Any) -> None:  # another call's sequence number, and another client's GID
            meta = Attachment.decode(query.attachment)
            query.reply(lie, Attachment(meta.sequence_number + 1, 0, meta.gid).encode())

        with (
            a.declare_plain_queryable(client.key, impostor),
            a.declare_plain_queryable(client.key, lambda q: q.reply(lie, Attachment(1, 0, bytes(16)).encode())),
            a.declare_plain_queryable(client.key, lambda q: q.reply(lie, b"not an attachment")),
        ):
            server_node.create_service("/contested", CHANGE_STATE, lambda r: {"success": True})
            for _ in range(3):
                assert client.call({"transition": {"id": 3}}, timeout_s=10).success is True
            wait_until(lambda: client.refused == 3, "each malformed attachment refused (they may come after the answer)")


def test_bad_arguments_are_refused_with_what_was_expected(sessions: tuple[Session, Session]) -> None:
    a, _ = sessions
    with Ros2Node(a, "node", domain=46) as node:
        with pytest.raises(BindingError, match="unknown service type 'lifecycle_msgs/srv/ChangeStat'.*did you mean.*ChangeState"):
            node.create_client("/x", "lifecycle_msgs/srv/ChangeStat")
        with pytest.raises(BindingError, match="service type 'lifecycle_msgs/msg/State'.*'std_srvs/srv/Trigger'"):
            node.create_service("/x", "lifecycle_msgs/msg/State", state)
        with pytest.raises(BindingError, match="'x' is not a fully qualified topic name"):
            node.create_client("x", GET_STATE)
        client = node.create_client("/x", CHANGE_STATE)
        with pytest.raises(BindingError, match="unknown field|transitio"):
            client.call({"transitio": {"id": 3}}, timeout_s=1)


class StateServer(Ros2Server):
    """Answers GetState with the number of requests it answered, from the unit's own thread."""

    def setup(self) -> None:
        self.answered = 0
        self.threads: set[str] = set()
        super().setup()

    def handle(self, request: Any) -> Any:
        self.answered += 1
        self.threads.add(threading.current_thread().name)
        return {"current_state": {"id": 3, "label": f"{self.name} #{self.answered}"}}


STATE_SERVER = TransformationSpec(
    "state-server",
    "tests.test_ros2_services:StateServer",
    (Param("service", "string", "/robot/get_state"), Param("type", "string", GET_STATE)),
    (),
    (),
)


def test_a_unit_serves_a_service_on_its_own_thread(make_manager: Callable[..., Manager]) -> None:
    port = free_port()
    manager = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=47)
    manager.spawn(STATE_SERVER, "states")
    with open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as session, Ros2Node(session, "caller", domain=47) as node:
        client = node.create_client("/robot/get_state", GET_STATE)
        assert client.call({}, timeout_s=10).current_state.label == "states #1"
        assert client.call({}, timeout_s=10).current_state.label == "states #2"
        unit = manager.unit("states")
        assert isinstance(unit, StateServer) and unit.ros2_service is not None and unit.ros2_service.answered == 2
        assert len(unit.threads) == 1 and next(iter(unit.threads)).startswith(f"dyknow-{manager.name}-")  # the unit's lane, not Zenoh's
        manager.destroy("states")
        wait_until(lambda: client.servers == 0, "the service's token gone with the unit")


# -- against zenoh-ros2-sdk (rmw_zenoh, another implementation), and the CLI


@pytest.fixture
def router() -> Iterator[tuple[Session, int]]:
    port = free_port()
    with open_session(listen=[f"tcp/127.0.0.1:{port}"]) as session:
        yield session, port


@pytest.mark.process
def test_our_client_calls_the_sdks_server(router: tuple[Session, int], peers: Callable[..., Peer]) -> None:
    session, port = router
    changes = peers(str(port), "serve", "/camera_top/change_state", CHANGE_STATE)
    states = peers(str(port), "serve", "/camera_top/get_state", GET_STATE)
    with Ros2Node(session, "dyknow_caller") as node:
        assert node.create_client("/camera_top/change_state", CHANGE_STATE).call({"transition": {"id": 3, "label": "activate"}}, 15).success
        assert changes.line() == {"request": {"transition": {"id": 3, "label": "activate"}}}
        response = node.create_client("/camera_top/get_state", GET_STATE).call({}, 15)
        assert (response.current_state.id, response.current_state.label) == (3, "active")
        assert states.line() == {"request": {}}


@pytest.mark.process
def test_the_sdks_client_calls_our_server(router: tuple[Session, int], peers: Callable[..., Peer]) -> None:
    session, port = router
    with Ros2Node(session, "dyknow_server") as node:
        server = node.create_service("/camera_top/change_state", CHANGE_STATE, lambda r: {"success": r.transition.id == 3})
        caller = peers(str(port), "call", "/camera_top/change_state", CHANGE_STATE, '{"transition": {"id": 3}}')
        assert caller.line() == {"response": {"success": True}}
        assert server.answered >= 1 and server.refused == 0


@pytest.mark.process
def test_the_sdks_client_calls_a_units_service(make_manager: Callable[..., Manager], peers: Callable[..., Peer]) -> None:
    port = free_port()
    manager = make_manager(listen=[f"tcp/127.0.0.1:{port}"], ros2_domain=0)
    manager.spawn(STATE_SERVER, "states")
    caller = peers(str(port), "call", "/robot/get_state", GET_STATE, "{}")
    assert caller.line() == {"response": {"current_state": {"id": 3, "label": "states #1"}}}


@pytest.mark.process
def test_dyknow_ros2_call_and_list_end_to_end(router: tuple[Session, int], peers: Callable[..., Peer]) -> None:
    _, port = router
    connect = ("--connect", f"tcp/127.0.0.1:{port}")
    peers(str(port), "serve", "/camera_top/change_state", CHANGE_STATE)
    called = run_cli("ros2", "call", "/camera_top/change_state", CHANGE_STATE, "{transition: {id: 3}}", *connect)
    assert called.returncode == 0, called.stderr
    assert called.stdout.startswith("requester: making request: lifecycle_msgs/srv/ChangeState") and '"success": true' in called.stdout
    as_json = run_cli("ros2", "call", "/camera_top/change_state", CHANGE_STATE, '{"transition": {"id": 2}}', "--json", *connect)
    assert as_json.returncode == 0, as_json.stderr
    assert json.loads(as_json.stdout)["response"] == {"success": False}
    listed = run_cli("ros2", "list", "--json", *connect)
    assert json.loads(listed.stdout)["services"] == {"/camera_top/change_state": {"types": [CHANGE_STATE], "servers": 1, "clients": 0}}
    missing = run_cli("ros2", "call", "/nobody/get_state", GET_STATE, "--timeout", "1", *connect)
    assert missing.returncode == 1
    assert re.search(r"ROS 2 service /nobody/get_state \(lifecycle_msgs/srv/GetState\): no answer in \d+\.\d s \(no server of it came up\)", missing.stderr), missing.stderr


@pytest.mark.parametrize(
    ("text", "fields"),
    [("", {}), ("{}", {}), ('{"transition": {"id": 3}}', {"transition": {"id": 3}}), ("{transition: {id: 3}}", {"transition": {"id": 3}}),
     ("transition:\n  id: 3\n  label: configure", {"transition": {"id": 3, "label": "configure"}})],
)  # fmt: skip
def test_a_request_is_read_as_ros2_service_call_reads_it(text: str, fields: dict[str, Any]) -> None:
    from dyknow.cli.ros2 import parse_request

    assert parse_request(text) == fields


def test_a_request_that_is_no_mapping_is_a_usage_error() -> None:
    from dyknow.cli.common import UsageError
    from dyknow.cli.ros2 import parse_request

    with pytest.raises(UsageError, match="expected a mapping"):
        parse_request("[1, 2]")
    with pytest.raises(UsageError, match="does not parse"):
        parse_request("{transition: {id: 3}")


