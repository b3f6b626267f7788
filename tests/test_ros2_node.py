"""dyknow.ros2.node and dyknow.ros2.graph on real Zenoh sessions on loopback: entities and their
tokens come and go in pairs, use after close is refused, untyped subscriptions learn their type,
and what a hostile peer sends (malformed tokens, other types) is counted and refused."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

from dyknow.errors import ClosedError
from dyknow.ros2 import Graph, Received, Ros2Node, snapshot
from dyknow.ros2.names import ADMIN_SPACE, Durability, EntityKind, QoS
from dyknow.transport import Session, open_session
from tests.conftest import free_port, wait_until


@pytest.fixture
def sessions() -> Iterator[tuple[Session, Session]]:
    port = free_port()
    with (
        open_session(listen=[f"tcp/127.0.0.1:{port}"]) as a,
        open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as b,
    ):
        yield a, b


def string(node: Ros2Node, text: str) -> object:
    return node.types.message_class("std_msgs/msg/String")(data=text)


def test_entities_and_their_tokens_come_and_go_in_pairs(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    seen: list[tuple[str, bool]] = []
    with Graph(b, 12, lambda e, alive: seen.append((e.kind.value, alive))) as graph:
        node = Ros2Node(a, "pairs", domain=12)
        pub = node.create_publisher("/p", "std_msgs/msg/String")
        sub = node.create_subscription("/s", "std_msgs/msg/String", lambda r: None)
        wait_until(lambda: len(graph.view().entities) == 3, "node, publisher and subscription")
        assert graph.view().topics() == {"/p": ["std_msgs/msg/String"], "/s": ["std_msgs/msg/String"]}
        node.close()  # closes the subscription, then the publisher, then the node's own token
        node.close()
        wait_until(lambda: not graph.view().entities, "every token gone")
        assert sorted(seen) == sorted([("NN", True), ("MP", True), ("MS", True), ("NN", False), ("MP", False), ("MS", False)])
    with pytest.raises(ClosedError, match="publisher is closed"):
        pub.publish(string(node, "late"))
    with pytest.raises(ClosedError, match="node is closed"):
        node.create_publisher("/p", "std_msgs/msg/String")
    sub.close()  # safe again


def test_an_untyped_subscription_learns_the_type_then_refuses_others(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    got: list[Received] = []
    arrived = threading.Event()
    with Ros2Node(a, "talker", domain=13) as talker, Ros2Node(b, "listener", domain=13) as listener:
        sub = listener.create_subscription("/mixed", None, lambda r: (got.append(r), arrived.set()))
        assert snapshot(b, 13, timeout_s=0.3).topics() == {}  # no type yet: no MS token yet
        strings = talker.create_publisher("/mixed", "std_msgs/msg/String")
        wait_until(lambda: (strings.publish(string(talker, "first")), arrived.wait(0.05))[1], "the first message")
        assert sub.ros_type == "std_msgs/msg/String" and got[0].message.data == "first"
        wait_until(
            lambda: any(e.kind is EntityKind.SUBSCRIPTION for e in snapshot(b, 13, timeout_s=0.2).entities), "the MS token, now typed"
        )
        ints = talker.create_publisher("/mixed", "std_msgs/msg/Int32")
        ints.publish(talker.types.message_class("std_msgs/msg/Int32")(data=7))
        wait_until(lambda: sub.refused >= 1, "the other type refused")
        assert "std_msgs/msg/Int32" in str(sub.last_refusal)


def test_malformed_tokens_are_counted_and_ignored(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    with Graph(b, 14) as graph, a.declare_liveliness_token(f"{ADMIN_SPACE}/14/zid/0/0/XX/%/%/bogus"), Ros2Node(a, "fine", domain=14):
        wait_until(lambda: graph.malformed == 1 and graph.view().nodes() == ["/fine"], "one bad token counted, the good one kept")


def test_an_untyped_subscription_takes_the_type_its_publishers_announce(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    with Ros2Node(a, "talker", domain=15) as talker, Ros2Node(b, "listener", domain=15) as listener:
        talker.create_publisher("/announced", "sensor_msgs/msg/Image")
        wait_until(lambda: bool(snapshot(b, 15, timeout_s=0.2).publishers("/announced")), "the publisher's token")
        sub = listener.create_subscription("/announced", None, lambda r: None)
        assert sub.ros_type == "sensor_msgs/msg/Image" and sub.key.endswith(talker.types.type_hash("sensor_msgs/msg/Image"))
        wait_until(lambda: any(e.kind is EntityKind.SUBSCRIPTION for e in snapshot(a, 15, timeout_s=0.2).entities), "its MS token at once")


def test_an_oversized_sample_is_refused_before_it_is_copied(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    refused: list[str] = []
    taken: list[bytes] = []
    with b.declare_sample_subscriber(
        "0/big/**", lambda k, p, att: taken.append(p), max_bytes=100, on_refused=lambda k, why: refused.append(why)
    ):
        pub = a.declare_plain_publisher("0/big/x")
        try:
            wait_until(lambda: (pub.put(bytes(200)), bool(refused))[1], "the oversized sample refused")
            wait_until(lambda: (pub.put(bytes(50)), bool(taken))[1], "a small one taken")
        finally:
            pub.undeclare()
    assert "200 bytes, over the limit of 100" in refused[0]


def test_a_volatile_subscription_reads_an_advanced_publisher(sessions: tuple[Session, Session]) -> None:
    # rmw_zenoh_cpp's publishers are Zenoh advanced publishers (a cache, miss detection); a plain
    # subscriber must read them as it reads plain ones
    a, b = sessions
    got = threading.Event()
    with Ros2Node(a, "advanced", domain=16) as talker, Ros2Node(b, "plain", domain=16) as listener:
        listener.create_subscription("/adv", "std_msgs/msg/String", lambda r: got.set())
        pub = talker.create_publisher("/adv", "std_msgs/msg/String", QoS(durability=Durability.TRANSIENT_LOCAL, depth=3))
        wait_until(lambda: (pub.publish(string(talker, "live")), got.wait(0.05))[1], "a live message")
