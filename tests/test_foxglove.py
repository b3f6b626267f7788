"""``dyknow foxglove``: live streams over the Foxglove WebSocket protocol, read back by a client
that speaks the protocol itself (aiohttp's WebSocket client, subprotocol ``foxglove.sdk.v1``, the
name the foxglove-sdk server accepts for the protocol of Foxglove's ws-protocol spec).

The client checks what Foxglove relies on: the advertised channels (topic, message encoding,
schema name and schema), and the binary message-data frames (opcode 0x01, subscription id,
log time, payload), decoded as the schema says.
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import aiohttp
import numpy as np
import pytest

from dyknow import Client, Manager, Message
from dyknow.foxglove import Bridge
from dyknow.recording import COMPRESSED_IMAGE, NDARRAY, PROTOBUF_SCHEMAS, RAW_IMAGE, image_array, protobuf
from dyknow.testing import SCENARIO_HOSTS, SCENARIO_SPECS
from dyknow.transport import Session, make_config
from tests.conftest import REPO, CliProcess, faked_clock, free_port, run_cli, subprocess_env, wait_until

SUBPROTOCOL = "foxglove.sdk.v1"
UNKNOWN_CHANNEL = "Unknown channel ID: "  # the SDK server's status for a subscription to a channel it does not know


@dataclass
class Seen:
    """What a Foxglove client learned from the server so far."""

    server_info: dict[str, Any] | None = None
    channels: dict[int, dict[str, Any]] = field(default_factory=dict)  # advertised and not withdrawn, by id
    unadvertised: list[int] = field(default_factory=list)
    messages: dict[int, list[tuple[int, bytes]]] = field(default_factory=dict)  # subscription id -> (log time, payload)
    subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id, as asked
    resent: int = 0  # subscriptions sent again after the SDK's "Unknown channel ID" for an advertised channel

    def channel(self, topic: str) -> dict[str, Any] | None:
        return next((c for c in self.channels.values() if c["topic"] == topic), None)


async def pump(ws: aiohttp.ClientWebSocketResponse, seen: Seen, until: Callable[[], bool], what: str, timeout_s: float = 30.0) -> None:
    """Read the server's messages into ``seen`` until ``until()`` holds (fails after ``timeout_s``)."""

    async def read() -> None:
        while not until():
            msg = await ws.receive()
            if msg.type == aiohttp.WSMsgType.TEXT:
                data = json.loads(msg.data)
                if data["op"] == "serverInfo":
                    seen.server_info = data
                elif data["op"] == "advertise":
                    seen.channels.update((c["id"], c) for c in data["channels"])
                elif data["op"] == "unadvertise":
                    seen.unadvertised += data["channelIds"]
                    for gone in data["channelIds"]:
                        seen.channels.pop(gone, None)
                elif data["op"] == "status" and data["message"].startswith(UNKNOWN_CHANNEL):
                    await resubscribe(ws, seen, int(data["message"].removeprefix(UNKNOWN_CHANNEL)))
            elif msg.type == aiohttp.WSMsgType.BINARY:
                assert msg.data[0] == 0x01, f"binary opcode {msg.data[0]}"  # message data
                subscription, log_time = struct.unpack_from("<IQ", msg.data, 1)
                seen.messages.setdefault(subscription, []).append((log_time, msg.data[13:]))
            else:
                raise AssertionError(f"the server ended the connection ({msg.type}) before {what}")

    try:
        await asyncio.wait_for(read(), timeout_s)
    except TimeoutError:
        counts = {sub: len(got) for sub, got in seen.messages.items()}
        raise AssertionError(f"{what} within {timeout_s} s; seen {sorted(c['topic'] for c in seen.channels.values())}, "
                             f"messages by subscription {counts}, channels withdrawn {seen.unadvertised}") from None  # fmt: skip


async def resubscribe(ws: aiohttp.ClientWebSocketResponse, seen: Seen, channel_id: int) -> None:
    """Send again a subscription the server refused for a channel it advertised and never withdrew.

    foxglove-sdk's server (0.30, ``ConnectedClient::advertise_channels`` in ``connected_client.rs``)
    sends a new channel's advertisement before it records the channel as advertised to the client,
    so a client that subscribes at once can be told "Unknown channel ID" when the thread creating
    the channel is preempted between the two (seen beside CPU hogs). A channel advertised before
    the client connected is recorded before the client is read, so only channels created while it
    watches are affected; a client such as this one subscribes again.
    """
    if channel_id not in seen.channels:
        return  # withdrawn: the refusal is right
    again = {s: c for s, c in seen.subscriptions.items() if c == channel_id}
    seen.resent += len(again)
    await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": [{"id": s, "channelId": c} for s, c in again.items()]}))


async def subscribe(ws: aiohttp.ClientWebSocketResponse, subscriptions: dict[int, int], seen: Seen | None = None) -> None:
    """Subscribe: subscription id -> channel id (remembered in ``seen``, to be sent again if refused)."""
    if seen is not None:
        seen.subscriptions.update(subscriptions)
    await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": [{"id": s, "channelId": c} for s, c in subscriptions.items()]}))


def raw_image(data: bytes) -> tuple[np.ndarray, int]:
    """A ``foxglove.RawImage`` protobuf message as an array, and its timestamp in ns."""
    fields = protobuf.decode(data)
    stamp = protobuf.decode(protobuf.last(fields, 1, b""))
    array = image_array(
        protobuf.last(fields, 2, 0),
        protobuf.last(fields, 3, 0),
        protobuf.text(fields, 4),
        protobuf.last(fields, 5, 0),
        protobuf.last(fields, 6, b""),
    )
    return array, protobuf.last(stamp, 1, 0) * 1_000_000_000 + protobuf.last(stamp, 2, 0)


def check_protobuf_channel(channel: dict[str, Any] | None, schema_name: str) -> None:
    assert channel is not None
    assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == ("protobuf", schema_name, "protobuf")
    assert base64.b64decode(channel["schema"]) == PROTOBUF_SCHEMAS[schema_name]  # the FileDescriptorSet recordings embed


def check_json_channel(channel: dict[str, Any] | None, key: str) -> dict[str, Any]:
    assert channel is not None
    assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == ("json", key, "jsonschema")
    schema = json.loads(channel["schema"])
    assert schema["title"] == key and schema["type"] == "object"
    return dict(schema)


# --- the command, against a manager running the scenario -----------------------------------------


@pytest.mark.process
def test_foxglove_serves_live_images_and_json(make_manager: Callable[..., Manager], cli_process: Callable[..., CliProcess]) -> None:
    manager = make_manager(
        specs=[SCENARIO_SPECS, REPO / "specs" / "generic.xml"], ontology=[REPO / "specs" / "dyknow.ttl"], listen=["tcp/127.0.0.1:0"]
    )
    manager.add_transformation(REPO / "specs" / "sources.xml")
    manager.spawn("synthetic-scene(ceiling)", "scene", params={"rate_hz": 30, "width": 160, "height": 120})
    image_key = f"dyknow/{manager.name}/scene/out"
    json_key = manager.request("BallTrack(field)")
    verdict_key = manager.monitor("BallTrack(field).tracked >= 1")  # its verdicts: what a State Transitions panel plots
    proc = cli_process("foxglove", "--connect", manager.endpoints[0], "--port", "0", "--json")  # KEYEXPR: dyknow/** by default
    ready = proc.line()
    assert ready["event"] == "ready" and ready["url"].startswith("ws://127.0.0.1:"), ready

    async def watch() -> tuple[Seen, dict[str, Any]]:
        seen = Seen()
        async with aiohttp.ClientSession() as http, http.ws_connect(ready["url"], protocols=[SUBPROTOCOL]) as ws:
            assert ws.protocol == SUBPROTOCOL
            await pump(
                ws, seen, lambda: all(seen.channel(k) is not None for k in (image_key, json_key, verdict_key)), "the three channels advertised"
            )
            assert seen.server_info is not None and seen.server_info["name"] == "dyknow"
            image, track, verdicts = seen.channel(image_key), seen.channel(json_key), seen.channel(verdict_key)
            assert image is not None and track is not None and verdicts is not None
            await subscribe(ws, {1: image["id"], 2: track["id"], 3: verdicts["id"]}, seen)
            await pump(ws, seen, lambda: all(len(seen.messages.get(i, [])) >= 3 for i in (1, 2, 3)), "messages on the three")
        return seen, {"image": image, "track": track, "verdicts": verdicts}

    try:
        seen, channels = asyncio.run(watch())
    except AssertionError as exc:  # say what the units sent and what the bridge said
        sent = {name: [p.messages for p in manager.get_statistics(name).ports] for name in ("scene", "tracker") if manager.has_unit(name)}
        proc.proc.kill()
        stderr = proc.proc.stderr.read() if proc.proc.stderr else ""
        raise AssertionError(f"{exc}; sent by the units {sent}; the bridge's stderr: {stderr[-2000:]}") from None
    check_protobuf_channel(channels["image"], RAW_IMAGE)
    for log_time, data in seen.messages[1]:
        frame, stamp = raw_image(data)
        assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8 and frame.any()
        assert stamp == log_time > 0  # the capture time, in the message and in the frame
    assert not all(np.array_equal(raw_image(seen.messages[1][0][1])[0], raw_image(d)[0]) for _, d in seen.messages[1][1:])  # live
    schema = check_json_channel(channels["track"], json_key)
    assert schema["properties"]["tracked"] == {"type": "number"}
    tracks = [json.loads(data) for _, data in seen.messages[2]]
    assert all(isinstance(t, dict) and t["tracked"] >= 1 for t in tracks)
    assert [t["tracked"] for t in tracks] == sorted(t["tracked"] for t in tracks)
    assert all(log_time > 0 for log_time, _ in seen.messages[2])
    # a monitor's verdicts: a JSON channel whose schema has the boolean a State Transitions panel plots
    verdict_schema = check_json_channel(channels["verdicts"], verdict_key)
    assert verdict_schema["properties"]["verdict"] in ({"type": "boolean"}, {}) and verdict_schema["properties"]["t"] == {"type": "number"}
    said = [json.loads(data) for _, data in seen.messages[3]]
    assert [v["verdict"] for v in said][-1] is True and all(log_time > 0 for log_time, _ in seen.messages[3])
    assert proc.stop() == 0


@pytest.mark.process
def test_foxglove_refuses_a_bad_key_expression_in_one_line() -> None:
    result = run_cli("foxglove", "robot//camera", "--connect", f"tcp/127.0.0.1:{free_port()}", "--port", "0")
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.startswith("dyknow: error: key expression to serve: 'robot//camera' is not a valid Zenoh key expression")
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


@pytest.mark.process
def test_foxglove_refuses_a_bad_port_and_a_port_in_use() -> None:
    bad = run_cli("foxglove", "--port", "70000")
    assert bad.returncode == 2 and "--port: got 70000; expected 0 to 65535" in bad.stderr
    session = Session(make_config(listen=["tcp/127.0.0.1:0"]))
    try:
        with Client("x", session=session) as client, Bridge(client, ["busy/**"], port=0) as first:
            busy = run_cli("foxglove", "--port", str(first.port), "--connect", session.endpoints()[0])
    finally:
        session.close()
    assert busy.returncode == 1 and "Traceback" not in busy.stderr
    assert busy.stderr.startswith(
        f"dyknow: error: Foxglove WebSocket server: cannot listen on 127.0.0.1:{first.port} (Address already in use"
    )


# --- the bridge in this process: every kind of payload, type changes, the channel bound ----------


@pytest.fixture
def publishing() -> Iterator[tuple[Session, dict[str, Any]]]:
    """A listening session that publishes ``payloads`` (key -> payload, changeable) every 20 ms."""
    session = Session(make_config(listen=["tcp/127.0.0.1:0"]))
    payloads: dict[str, Any] = {}
    stop = threading.Event()

    def run() -> None:
        publishers: dict[str, Any] = {}
        seq = 0
        while not stop.wait(0.02):
            seq += 1
            for key, payload in list(payloads.items()):
                if key not in publishers:
                    publishers[key] = session.declare_publisher(key)
                publishers[key].put(Message(payload, seq, 1_000_000_000 * seq, 1_000_000_000 * seq + 1, key))
        for pub in publishers.values():
            pub.undeclare()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    yield session, payloads
    stop.set()
    thread.join(5)
    session.close()


def test_bridge_maps_every_payload_kind_and_follows_type_changes(
    publishing: tuple[Session, dict[str, Any]], caplog: pytest.LogCaptureFixture
) -> None:
    session, payloads = publishing
    jpeg = b"\xff\xd8\xff\xe0" + bytes(range(64))
    payloads.update({
        "fox/mono16": np.arange(12, dtype="<u2").reshape(3, 4),
        "fox/jpeg": jpeg,
        "fox/matrix": np.linspace(0.0, 1.0, 6).reshape(2, 3),
        "fox/text": "héllo",
        "fox/list": [1, 2.5, None],
        "fox/bytes": b"\x00\x01binary",
        "fox/changes": {"x": 1},
    })  # fmt: skip
    shown = {k for k in payloads if k != "fox/bytes"}
    caplog.set_level(logging.WARNING, logger="dyknow.foxglove")
    with Client("x", connect=session.endpoints()) as client, Bridge(client, ["fox/**"], port=0, max_channels=len(shown)) as bridge:
        assert bridge.url == f"ws://127.0.0.1:{bridge.port}"
        wait_until(lambda: set(bridge.topics) == shown, "a channel for each key that can be shown")
        payloads["fox/extra"] = {"beyond": "the bound"}  # (fox/bytes, never served, may be the first refused)
        wait_until(lambda: bridge.refused > 0, "messages on keys beyond the bound refused")

        async def watch() -> tuple[Seen, dict[str, dict[str, Any]]]:
            seen = Seen()
            async with aiohttp.ClientSession() as http, http.ws_connect(bridge.url, protocols=[SUBPROTOCOL]) as ws:
                await pump(ws, seen, lambda: {c["topic"] for c in seen.channels.values()} == shown, "every channel advertised")
                channels = {c["topic"]: c for c in seen.channels.values()}
                ids = {topic: n for n, topic in enumerate(sorted(shown), start=1)}
                await subscribe(ws, {ids[t]: channels[t]["id"] for t in shown}, seen)
                await pump(ws, seen, lambda: all(seen.messages.get(n) for n in ids.values()), "a message on every channel")
                # a key whose payload type changes: its channel is withdrawn and a new one advertised
                old = channels["fox/changes"]["id"]
                payloads["fox/changes"] = np.zeros((2, 2), np.uint8)
                await pump(ws, seen, lambda: old in seen.unadvertised and seen.channel("fox/changes") is not None, "the new channel")
                new = seen.channel("fox/changes")
                assert new is not None
                await subscribe(ws, {100: new["id"]}, seen)
                await pump(ws, seen, lambda: bool(seen.messages.get(100)), "a message on the new channel")
                return seen, {topic: {**channel, "subscription": ids[topic]} for topic, channel in channels.items()} | {
                    "new": {**new, "subscription": 100}
                }

        seen, channels = asyncio.run(watch())
        assert "fox/extra" not in bridge.topics and seen.channel("fox/extra") is None
    first = {topic: seen.messages[c["subscription"]][0][1] for topic, c in channels.items()}
    check_protobuf_channel(channels["fox/mono16"], RAW_IMAGE)
    assert np.array_equal(raw_image(first["fox/mono16"])[0], payloads["fox/mono16"])
    check_protobuf_channel(channels["fox/jpeg"], COMPRESSED_IMAGE)
    fields = protobuf.decode(first["fox/jpeg"])
    assert (bytes(protobuf.last(fields, 2, b"")), protobuf.text(fields, 3)) == (jpeg, "jpeg")
    check_protobuf_channel(channels["fox/matrix"], NDARRAY)
    fields = protobuf.decode(first["fox/matrix"])
    assert protobuf.text(fields, 1) == "<f8" and protobuf.uints(fields[2]) == [2, 3]
    check_json_channel(channels["fox/text"], "fox/text")
    assert json.loads(first["fox/text"]) == {"text": "héllo"}
    check_json_channel(channels["fox/list"], "fox/list")
    assert json.loads(first["fox/list"]) == {"value": [1, 2.5, None]}
    check_json_channel(channels["fox/changes"], "fox/changes")
    assert json.loads(first["fox/changes"]) == {"x": 1}
    check_protobuf_channel(channels["new"], RAW_IMAGE)
    assert np.array_equal(raw_image(seen.messages[100][0][1])[0], np.zeros((2, 2), np.uint8))
    for messages in seen.messages.values():
        assert all(log_time % 1_000_000_000 == 0 for log_time, _ in messages)  # the publisher's origin_ns
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("'fox/bytes' are not served: Foxglove cannot show application/octet-stream payloads" in w for w in warnings), warnings
    assert sum(f"{len(shown)} channels already: messages on further keys" in w for w in warnings) == 1, warnings


def test_the_bridge_is_closed_to_other_web_pages(make_manager: Callable[..., Manager]) -> None:
    """A web page cannot open the bridge: a WebSocket upgrade with another page's Origin, or a
    DNS-rebound Host, is refused with a 403 that says why; the Foxglove web app's origin, the
    bridge's own and a desktop app (no Origin) are served; --allow-origin adds one."""
    import http.client

    manager = make_manager()

    def upgrade(port: int, **headers: str) -> tuple[int, str]:
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        try:
            connection.putrequest("GET", "/", skip_host="Host" in headers)
            base = {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Version": "13",
                    "Sec-WebSocket-Key": base64.b64encode(b"0123456789abcdef").decode(), "Sec-WebSocket-Protocol": SUBPROTOCOL}  # fmt: skip
            for name, value in {**base, **headers}.items():
                connection.putheader(name, value)
            connection.endheaders()
            answer = connection.getresponse()
            return answer.status, answer.read(200).decode(errors="replace") if answer.status != 101 else ""
        finally:
            connection.close()

    with Client(manager.name, connect=manager.endpoints) as client, Bridge(client, ["dyknow/**"], port=0, origins=["https://app.foxglove.dev", "http://lichtblick.local:8080"]) as bridge:
        status, text = upgrade(bridge.port, Origin="http://evil.example")
        assert status == 403 and "Origin 'http://evil.example' is not allowed" in text
        status, text = upgrade(bridge.port, Host=f"evil.example:{bridge.port}")
        assert status == 403 and "is not a name this server serves" in text
        status, _ = upgrade(bridge.port, **{"Sec-Fetch-Site": "cross-site"})
        assert status == 403
        for headers in ({}, {"Origin": "https://app.foxglove.dev"}, {"Origin": f"http://127.0.0.1:{bridge.port}"}, {"Origin": "http://lichtblick.local:8080"}):
            assert upgrade(bridge.port, **headers)[0] == 101, headers


@pytest.mark.process
def test_a_message_from_a_host_whose_clock_is_ahead_is_logged_at_this_hosts_time(make_manager: Callable[..., Manager], faketime: Any) -> None:
    """The robot's manager runs with its wall clock 10 s ahead (libfaketime): its camera's frames
    are stamped 10 s in the future, and the bridge logs them at the time they were captured on
    this host's clock, corrected by the offset the station estimates (to within the frames' few
    milliseconds of travel; uncorrected they would be 10 s off)."""
    station = make_manager("station", listen=[f"tcp/127.0.0.1:{free_port()}"])
    robot = subprocess.Popen(
        [sys.executable, "-m", "dyknow.cli", "manager", "--name", "robot", "--listen", f"tcp/127.0.0.1:{free_port()}",
         "--connect", station.endpoints[0], "--specs", str(SCENARIO_HOSTS["robot"]), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**subprocess_env(), **faked_clock(faketime, "+10")},
    )  # fmt: skip
    try:
        assert robot.stdout is not None and json.loads(robot.stdout.readline())["event"] == "ready"
        with Client("station", connect=station.endpoints) as client:
            Client("robot", session=client.session).spawn("robot-camera", "cam", bindings={"out": "fox/robot"})
            station.spawn("relay", "seen", bindings={"in": "fox/robot"})  # the station receives the robot's data: it estimates its clock
            wait_until(lambda: "robot" in client.clocks(), "the station to estimate the robot's clock")
            assert abs(client.clocks()["robot"].offset_ns - 10_000_000_000) < 100_000_000  # what libfaketime was asked for
            with Bridge(client, ["fox/**"], port=0) as bridge:
                assert bridge.clocks is not None and bridge.clocks.fetched.wait(10)

                async def watch() -> list[tuple[int, int]]:
                    seen = Seen()
                    arrived: list[tuple[int, int]] = []  # (log time, when it arrived here)
                    async with aiohttp.ClientSession() as http, http.ws_connect(bridge.url, protocols=[SUBPROTOCOL]) as ws:
                        await pump(ws, seen, lambda: seen.channel("fox/robot") is not None, "the robot's channel")
                        channel = seen.channel("fox/robot")
                        assert channel is not None
                        await subscribe(ws, {1: channel["id"]}, seen)
                        while len(arrived) < 20:
                            count = len(arrived)
                            await pump(ws, seen, lambda: len(seen.messages.get(1, [])) > count, "a frame")  # noqa: B023 (awaited here)
                            arrived += [(log_time, time.time_ns()) for log_time, _ in seen.messages[1][count:]]
                    return arrived

                arrived = asyncio.run(watch())
            assert bridge.unknown_clock == 0
            uncertainty_ns = client.clocks()["robot"].uncertainty_ns
        for log_time, now in arrived:
            # captured here before it arrived (a corrected time is true within its estimate's
            # uncertainty: a frame 0.05 ms in travel once came 0.055 ms "early"), not 10 s ahead
            assert -uncertainty_ns <= now - log_time < 1_000_000_000, ((now - log_time) / 1e6, uncertainty_ns / 1e6)
    finally:
        robot.terminate()
        robot.communicate(timeout=10)
