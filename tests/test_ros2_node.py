"""dyknow.ros2.node and dyknow.ros2.graph on real Zenoh sessions on loopback: entities and their
tokens come and go in pairs, use after close is refused, untyped subscriptions learn their type,
and what a hostile peer sends (malformed tokens, other types) is counted and refused."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest

from dyknow.errors import ClosedError
from dyknow.ros2 import Graph, Received, Ros2Node, graph, snapshot
from dyknow.ros2.graph import PublisherWatch
from dyknow.ros2.names import ADMIN_SPACE, HASH_NOT_SUPPORTED, Durability, Entity, EntityKind, QoS
from dyknow.ros2.node import UNTYPED_MAX_MESSAGE_BYTES
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


def test_messages_are_decoded_off_zenohs_thread_from_a_bounded_queue(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    got: list[str] = []
    threads: set[str] = set()
    first, release = threading.Event(), threading.Event()

    def slow(received: Received) -> None:
        threads.add(threading.current_thread().name)
        got.append(received.message.data)
        first.set()
        release.wait(20)

    with Ros2Node(a, "talker", domain=21) as talker, Ros2Node(b, "listener", domain=21) as listener:
        sub = listener.create_subscription("/queued", "std_msgs/msg/String", slow, QoS(depth=5))
        pub = talker.create_publisher("/queued", "std_msgs/msg/String", QoS(keep_all=True))  # blocks rather than drop: all 50 arrive
        wait_until(lambda: (pub.publish(string(talker, "first")), first.is_set())[1], "a message in on_message")
        for i in range(50):
            pub.publish(string(talker, f"m{i}"))
        wait_until(lambda: sub.dropped >= 45, "the queue at its depth, the oldest dropped")
        release.set()
        wait_until(lambda: got[-1:] == ["m49"], "the newest delivered")
    assert len(got) <= 1 + 5 + 1 and got[-5:] == [f"m{i}" for i in range(45, 50)]  # the newest five, in order
    assert threads == {"dyknow-ros2-listener"}  # the node's delivery thread, not Zenoh's


def test_an_oversized_message_is_dropped_naming_the_topic_the_size_and_the_bound(
    sessions: tuple[Session, Session], caplog: pytest.LogCaptureFixture
) -> None:
    a, b = sessions
    got: list[str] = []
    with Ros2Node(a, "talker", domain=22) as talker, Ros2Node(b, "listener", domain=22, max_message_bytes=4096) as listener:
        typed = listener.create_subscription("/big", "std_msgs/msg/String", lambda r: got.append(r.message.data))
        chosen = listener.create_subscription("/bigger", "std_msgs/msg/String", lambda r: got.append(r.message.data), max_bytes=100_000)
        untyped = listener.create_subscription("/any", None, lambda r: got.append(r.message.data))
        assert (typed.max_bytes, chosen.max_bytes, untyped.max_bytes) == (4096, 100_000, 4096)
        pubs = {topic: talker.create_publisher(topic, "std_msgs/msg/String", QoS(keep_all=True)) for topic in ("/big", "/bigger", "/any")}
        wait_until(lambda: (pubs["/big"].publish(string(talker, "x" * 5000)), typed.oversized >= 1)[1], "the large one dropped")
        wait_until(lambda: (pubs["/bigger"].publish(string(talker, "y" * 5000)), "y" * 5000 in got)[1], "under its own bound: taken")
        wait_until(lambda: (pubs["/big"].publish(string(talker, "small")), "small" in got)[1], "a small one taken")
    assert "x" * 5000 not in got and typed.refused == typed.oversized
    assert "ROS 2 subscription on /big refused a message (1 so far): a payload of 5009 bytes, over the limit of 4096" in caplog.text


def test_an_untyped_subscription_takes_at_most_one_mib(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    got: list[int] = []
    with Ros2Node(a, "talker", domain=23) as talker, Ros2Node(b, "listener", domain=23) as listener:
        sub = listener.create_subscription("/blob", None, lambda r: got.append(len(r.message.data)))
        assert sub.max_bytes == UNTYPED_MAX_MESSAGE_BYTES == 1 << 20
        pub = talker.create_publisher("/blob", "std_msgs/msg/UInt8MultiArray", QoS(keep_all=True))
        blob = talker.types.message_class("std_msgs/msg/UInt8MultiArray")
        layout = talker.types.message_class("std_msgs/msg/MultiArrayLayout")(dim=[], data_offset=0)
        wait_until(lambda: (pub.publish(blob(layout=layout, data=np.zeros(2 << 20, np.uint8))), sub.oversized >= 1)[1], "2 MiB dropped")
        wait_until(lambda: (pub.publish(blob(layout=layout, data=np.zeros(1000, np.uint8))), bool(got))[1], "1 kB taken")
    assert set(got) == {1000}


def _fake_publisher(session: Session, domain: int, topic: str, i: int, ros_type: str = "std_msgs/msg/String") -> object:
    """A publisher's liveliness token and nothing else, as anyone on the network may declare."""
    entity = Entity(
        domain, f"f{i:031x}", 1, 100 + i, EntityKind.PUBLISHER, "/", f"fake{i}", "/", topic, ros_type, HASH_NOT_SUPPORTED, QoS()
    )
    return session.declare_liveliness_token(entity.token())


def test_a_publisher_watch_sees_its_topic_only(sessions: tuple[Session, Session]) -> None:
    a, b = sessions
    seen: list[tuple[str, bool]] = []
    others = [_fake_publisher(a, 24, f"/other{i}", i) for i in range(20)]
    with PublisherWatch(b, 24, "/watched", lambda e, alive: seen.append((e.node, alive))) as watch, Ros2Node(a, "real", domain=24) as real:
        pub = real.create_publisher("/watched", "std_msgs/msg/String")
        wait_until(lambda: seen == [("/real", True)], "the topic's publisher")
        pub.close()
        wait_until(lambda: seen == [("/real", True), ("/real", False)], "it gone")
        assert watch.overflow == 0 and watch.view() == []
    for token in others:
        token.undeclare()  # type: ignore[attr-defined]


def test_a_crowded_watch_asks_before_it_says_the_last_publisher_went(
    sessions: tuple[Session, Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tokens over the watch's bound are left out, not forgotten: when the last publisher it kept
    goes, it asks which are still up, and reports those before the one that went."""
    monkeypatch.setattr(graph, "MAX_TOPIC_PUBLISHERS", 5)
    a, b = sessions
    alive: set[str] = set()
    emptied: list[int] = []

    def changed(entity: Entity, up: bool) -> None:
        (alive.add if up else alive.discard)(entity.node)
        if not alive:
            emptied.append(len(alive))

    with open_session(listen=["tcp/127.0.0.1:0"], connect=a.endpoints()) as attacker:
        fakes = [_fake_publisher(attacker, 25, "/crowded", i) for i in range(5)]
        with PublisherWatch(b, 25, "/crowded", changed) as watch:
            wait_until(lambda: len(alive) == 5, "the five fakes kept")
            with Ros2Node(a, "real", domain=25) as real:
                real.create_publisher("/crowded", "std_msgs/msg/String")
                wait_until(lambda: watch.overflow >= 1, "the real publisher left out")
                assert "/real" not in alive
                for token in fakes:
                    token.undeclare()  # type: ignore[attr-defined]
                wait_until(lambda: alive == {"/real"}, "the real one found by asking")
                assert emptied == []  # never "no publisher" while the real one was up
            wait_until(lambda: not alive, "the real one gone")
