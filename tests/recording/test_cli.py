"""The recording commands as real processes: dyknow record / replay / mcap cat / mcap info."""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dyknow import Manager
from dyknow.cli import main
from dyknow.errors import RecordingError
from dyknow.message import Message
from dyknow.recording import CLOCKS_TOPIC, RecordedMessage, Recording
from dyknow.transport import Session
from tests.conftest import UNIT_SPECS, CliProcess, ManagerProcess, free_port, run_cli, wait_until
from tests.recording.support import wait_matched

TEN = "TenMessages/TenMessages-ch-chx-mx-pad-rch-rsh-st-sum"


def readable(path: Path) -> int:
    """How many messages of a file being written are readable now (the clock records left out:
    the messages here come from this process, a clock the recorder's process does not know)."""
    try:
        with Recording(path, recover=True) as recording:
            return sum(1 for m in recording.messages() if m.topic != CLOCKS_TOPIC)
    except RecordingError:
        return 0


def streams(recording: Recording) -> list[RecordedMessage]:
    """The messages of a recording, its clock records left out."""
    return [m for m in recording.messages() if m.topic != CLOCKS_TOPIC]


def one_line_error(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 1, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line]
    assert len(lines) == 1, result.stderr
    return lines[0]


# --- record --------------------------------------------------------------------------------------


@pytest.mark.process
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_record_until_a_signal_finalizes_the_file(tmp_path: Path, listening: tuple[Session, str], cli_process: Callable[..., CliProcess], sig: int) -> None:
    session, endpoint = listening
    path = tmp_path / "signal.mcap"
    proc = cli_process("record", "rec/**", "-o", str(path), "--connect", endpoint, "--json")
    assert proc.line() == {"event": "ready", "file": str(path), "key_exprs": ["rec/**"]}
    image = np.arange(30 * 40 * 3, dtype=np.uint8).reshape(30, 40, 3)
    with session.declare_publisher("rec/json") as pub, session.declare_publisher("rec/image") as pub_image:
        wait_matched(pub)
        wait_matched(pub_image)
        for seq in range(1, 51):
            pub.put(Message({"n": seq}, seq, 1_000 + seq, 2_000 + seq, "rec/json"))
        pub_image.put(Message(image, 1, 5_000, 5_001, "rec/image"))
    wait_until(lambda: readable(path) == 51, "51 messages on disk")  # chunks reach the disk every second
    proc.proc.send_signal(sig)
    assert proc.proc.wait(30) == 0  # (it exits at once; a loaded machine may hold it up)
    assert proc.line() == {"event": "done", "file": str(path), "messages": 51, "topics": {"rec/json": 50, "rec/image": 1}, "bytes": path.stat().st_size}
    with Recording(path) as recording:  # finalized: summary and footer, no recovery needed
        assert recording.info.indexed and recording.problem is None and len(streams(recording)) == 51
        # and two clock records: the recorder's own clock, then this process's, which it does not know
        assert recording.info.message_count == 53 and [json.loads(m.data)["offset_ns"] for m in recording.messages() if m.topic == CLOCKS_TOPIC] == [0, None]
    cat = run_cli("mcap", "cat", str(path), "--json")
    assert cat.returncode == 0, cat.stderr
    lines = [json.loads(line) for line in cat.stdout.splitlines()]
    assert len(lines) == 51  # (cat replays the streams: not the clock records)
    assert lines[0] == {
        "topic": "rec/json", "sequence": 1, "log_time": 1_001, "publish_time": 2_001, "schema": "rec/json",
        "message_encoding": "json", "data_b64": base64.b64encode(b'{"n":1}').decode(),
    }  # fmt: skip
    assert lines[-1]["schema"] == "foxglove.RawImage" and lines[-1]["message_encoding"] == "protobuf"
    assert [line["log_time"] for line in lines] == sorted(line["log_time"] for line in lines)


@pytest.mark.process
def test_record_stops_by_itself_after_max_messages(tmp_path: Path, listening: tuple[Session, str], cli_process: Callable[..., CliProcess]) -> None:
    session, endpoint = listening
    path = tmp_path / "max.mcap"
    proc = cli_process("record", "max/**", "-o", str(path), "--connect", endpoint, "--max-messages", "5", "--compression", "lz4", "--json")
    assert proc.line()["event"] == "ready"
    with session.declare_publisher("max/x") as pub:
        wait_matched(pub)
        for seq in range(1, 11):
            pub.put(Message(f"text {seq}", seq, seq, seq, "max/x"))
        assert proc.proc.wait(20) == 0
    assert proc.line()["messages"] == 5
    with Recording(path) as recording:
        assert [m.data for m in streams(recording)] == [f"text {i}".encode() for i in range(1, 6)]
        assert recording.info.compressions == ("lz4",)


@pytest.mark.process
def test_record_stops_after_its_duration(tmp_path: Path, listening: tuple[Session, str]) -> None:
    _, endpoint = listening
    path = tmp_path / "duration.mcap"
    result = run_cli("record", "quiet/**", "-o", str(path), "--connect", endpoint, "--duration", "0.3")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == f"recorded 0 messages on 0 keys to {path} ({path.stat().st_size} bytes)"
    with Recording(path) as recording:
        assert recording.info.message_count == 0 and recording.problem is None


@pytest.mark.process
def test_a_killed_recorder_leaves_its_complete_chunks_readable(tmp_path: Path, listening: tuple[Session, str], cli_process: Callable[..., CliProcess]) -> None:
    session, endpoint = listening
    path = tmp_path / "killed.mcap"
    proc = cli_process("record", "kill/**", "-o", str(path), "--connect", endpoint, "--chunk-size", "2048", "--json")
    assert proc.line()["event"] == "ready"
    stop = threading.Event()
    with session.declare_publisher("kill/x") as pub:
        wait_matched(pub)

        def publish() -> None:
            seq = 0
            while not stop.is_set():
                seq += 1
                pub.put(Message({"seq": seq, "pad": "p" * 100}, seq, time.time_ns(), time.time_ns(), "kill/x"))
                stop.wait(0.0005)

        publisher = threading.Thread(target=publish)
        publisher.start()
        try:
            wait_until(lambda: readable(path) >= 300, "300 messages on disk")
            os.kill(proc.proc.pid, signal.SIGKILL)  # while messages keep coming
            assert proc.proc.wait(10) == -signal.SIGKILL
        finally:
            stop.set()
            publisher.join(10)
    with pytest.raises(RecordingError) as info:
        Recording(path)
    assert str(info.value).startswith(f"{path}: truncated at offset ")
    with Recording(path, recover=True) as recording:
        seqs = [json.loads(m.data)["seq"] for m in streams(recording)]
        assert recording.info.chunk_count >= 10
    assert seqs == list(range(1, len(seqs) + 1)) and len(seqs) >= 300  # every message of every complete chunk

    refused = run_cli("replay", str(path), "--rate", "max", "--wait", "0")
    assert one_line_error(refused).startswith(f"dyknow: error: {path}: truncated at offset ")
    assert "replay them with recover=True (dyknow replay --recover)" in refused.stderr
    recovered = run_cli("mcap", "cat", str(path), "--json", "--recover")
    assert recovered.returncode == 0, recovered.stderr
    assert [json.loads(base64.b64decode(json.loads(line)["data_b64"]))["seq"] for line in recovered.stdout.splitlines()] == seqs
    assert "truncated at offset" in recovered.stderr and "Traceback" not in recovered.stderr


@pytest.mark.process
def test_record_errors_are_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such" / "out.mcap"
    result = run_cli("record", "x/**", "-o", str(missing))
    assert one_line_error(result) == f"dyknow: error: {missing}: cannot create the file: No such file or directory (does the folder exist?)"
    if os.path.exists("/dev/full"):
        full = run_cli("record", "x/**", "-o", "/dev/full")
        assert one_line_error(full) == "dyknow: error: /dev/full: cannot write the file: No space left on device (the disk is full); nothing was recorded"


@pytest.mark.parametrize(
    "args",
    [
        ["record", "x/**", "-o", "u.mcap", "--max-messages", "0"],
        ["record", "x/**", "-o", "u.mcap", "--duration", "-1"],
        ["record", "x/**", "-o", "u.mcap", "--compression", "gzip"],
        ["record", "x/**"],
        ["replay", "f.mcap", "--rate", "0"],
        ["replay", "f.mcap", "--rate", "fast"],
        ["replay", "f.mcap", "--remap", "no-equals-sign"],
        ["mcap"],
        ["mcap", "dump", "f.mcap"],
    ],
)
def test_usage_errors_exit_2(args: list[str], capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "f.mcap").write_bytes(b"")  # never opened: the usage is refused first
    with pytest.raises(SystemExit) as info:
        main(args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err
    assert not (tmp_path / "u.mcap").exists()


def test_a_bad_key_expression_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["record", "x//y", "-o", str(tmp_path / "k.mcap")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("dyknow: error: key expression to record: 'x//y' is not a valid Zenoh key expression") and "\n" not in err


# --- replay --------------------------------------------------------------------------------------


@pytest.mark.process
def test_replay_feeds_camera_images_to_a_unit(data_dir: Path, make_manager: Callable[..., Manager]) -> None:
    pytest.importorskip("cv2")
    # --rate max sends the ten frames in one burst: a queue deeper than the default keep-last 8
    # holds them all while the sink's lane catches up (with 8, the oldest would be dropped, counted)
    manager = make_manager(specs=[UNIT_SPECS], queue_depth=16)
    manager.spawn("sink", "sink", bindings={"in": "camera/front"})
    path = data_dir / "mcap" / "real" / "custom-camera-model.mcap"
    result = run_cli(
        "replay", str(path), "--topics", "/image/compressed", "--remap", "/image/compressed=camera/front",
        "--rate", "max", "--wait", "10", "--connect", manager.endpoints[0], "--json",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    ready, done = (json.loads(line) for line in result.stdout.splitlines())
    assert ready == {"event": "ready", "file": str(path), "keys": {"/image/compressed": "camera/front"}}
    assert done == {"event": "done", "file": str(path), "messages": 10, "unmatched": {}}
    messages = manager.unit("sink").wait_for(10)
    assert all(m.payload.shape == (360, 520, 3) and m.payload.dtype == np.uint8 for m in messages)
    with Recording(path) as recording:  # the file's header fields: sequence and log time as origin
        stored = [(m.sequence, m.log_time_ns) for m in recording.messages() if m.topic == "/image/compressed"]
    assert [(m.seq, m.origin_ns) for m in messages] == stored


@pytest.mark.process
def test_echo_consumes_a_replayed_ros2_bag(data_dir: Path, listening: tuple[Session, str], cli_process: Callable[..., CliProcess]) -> None:
    _, endpoint = listening
    echo = cli_process("echo", "topic", "--count", "10", "--json", "--connect", endpoint)
    path = data_dir / "mcap" / "real" / "talker.mcap"
    replay = run_cli("replay", str(path), "--topics", "/topic", "--rate", "max", "--wait", "15", "--connect", endpoint)
    assert replay.returncode == 0, replay.stderr
    assert replay.stdout.splitlines() == [f"replaying {path} (/topic -> topic); Ctrl-C to stop", f"replayed 10 messages from {path}"]
    lines = [echo.line() for _ in range(10)]
    assert echo.proc.wait(10) == 0
    assert [line["payload"] for line in lines] == [{"data": f"Hello, world! {i}"} for i in range(10)]
    assert lines[0]["origin_ns"] == 1585866235112609068 and lines[0]["key"] == "topic"


@pytest.mark.process
def test_sigint_ends_a_looping_replay(data_dir: Path, listening: tuple[Session, str], cli_process: Callable[..., CliProcess]) -> None:
    session, endpoint = listening
    arrived = threading.Event()
    with session.declare_subscriber("mouse", lambda msg: arrived.set()):
        path = data_dir / "mcap" / "real" / "example.mcap"
        proc = cli_process("replay", str(path), "--loop", "--wait", "10", "--connect", endpoint, "--json")
        assert proc.line() == {"event": "ready", "file": str(path), "keys": {"mouse": "mouse"}}
        assert arrived.wait(20.0)  # it is replaying (at the original pace: 3 s per pass)
        proc.proc.send_signal(signal.SIGINT)
        assert proc.proc.wait(10) == 0
    done = proc.line()
    assert done["event"] == "done" and done["messages"] > 0


@pytest.mark.process
def test_replay_errors_are_one_line(tmp_path: Path, data_dir: Path) -> None:
    missing = run_cli("replay", str(tmp_path / "none.mcap"))
    assert one_line_error(missing) == f"dyknow: error: {tmp_path / 'none.mcap'}: cannot read the file: No such file or directory"
    talker = str(data_dir / "mcap" / "real" / "talker.mcap")
    unknown = run_cli("replay", talker, "--topics", "/topik")
    assert one_line_error(unknown).startswith(f"dyknow: error: {talker}: no topic matches '/topik'; expected one of its topics")
    assert "(did you mean '/topic'?)" in unknown.stderr


# --- mcap cat / info -----------------------------------------------------------------------------


@pytest.mark.process
def test_mcap_cat_json_contract(data_dir: Path) -> None:
    path = data_dir / "mcap" / "conformance" / f"{TEN}.mcap"
    result = run_cli("mcap", "cat", str(path), "--json")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    first = json.loads(lines[0])
    assert list(first) == ["topic", "sequence", "log_time", "publish_time", "schema", "message_encoding", "data_b64"]
    assert [(m["log_time"], m["sequence"]) for m in map(json.loads, lines)] == [(0, 0), (1, 2), (2, 1), (3, 3), (3, 4), (4, 6), (5, 5), (7, 7), (8, 8), (9, 9)]
    assert first == {"topic": "example", "sequence": 0, "log_time": 0, "publish_time": 0, "schema": "Example", "message_encoding": "a", "data_b64": "AQID"}
    filtered = run_cli("mcap", "cat", str(data_dir / "mcap" / "real" / "talker.mcap"), "--topics", "/topic", "--json")
    assert [json.loads(line)["topic"] for line in filtered.stdout.splitlines()] == ["/topic"] * 10
    text = run_cli("mcap", "cat", str(data_dir / "mcap" / "real" / "example.mcap"))
    assert text.stdout.splitlines()[0] == '1740566235448000000 mouse #0 [MouseEvent] {"clientX":1511,"clientY":974}'


@pytest.mark.process
def test_mcap_info(data_dir: Path) -> None:
    path = data_dir / "mcap" / "real" / "talker.mcap"
    result = run_cli("mcap", "info", str(path), "--json")
    assert result.returncode == 0, result.stderr
    info = json.loads(result.stdout)
    assert (info["message_count"], info["chunk_count"], info["compressions"], info["profile"]) == (20, 1, ["zstd"], "ros2")
    assert (info["start_ns"], info["end_ns"], info["problem"]) == (1585866235112411371, 1585866239643508139, None)
    assert [(c["topic"], c["message_count"], c["schema"]) for c in info["channels"]] == [
        ("/rosout", 10, "rcl_interfaces/msg/Log"), ("/parameter_events", 0, "rcl_interfaces/msg/ParameterEvent"), ("/topic", 10, "std_msgs/msg/String"),
    ]  # fmt: skip
    text = run_cli("mcap", "info", str(path))
    assert "messages:  20" in text.stdout and "     3 /topic  10 msgs  std_msgs/msg/String (ros2msg)  [cdr]" in text.stdout


@pytest.mark.process
def test_mcap_info_on_a_damaged_file(tmp_path: Path, data_dir: Path) -> None:
    data = (data_dir / "mcap" / "real" / "example.mcap").read_bytes()
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[: len(data) // 2])
    refused = run_cli("mcap", "info", str(path))
    assert one_line_error(refused).startswith(f"dyknow: error: {path}: truncated at offset ")
    recovered = run_cli("mcap", "info", str(path), "--recover", "--json")
    assert recovered.returncode == 0, recovered.stderr
    info = json.loads(recovered.stdout)
    assert info["problem"].startswith("truncated at offset ") and 0 < info["message_count"] < 111


# --- a replay's consumers elsewhere: through a router, through another manager, or none -----------------


def _sink_count(proc: ManagerProcess) -> int:
    """What reached the sink's input: handed to it, or dropped by its queue (a burst at --rate max
    overflows its 8 places)."""
    port = json.loads(run_cli("stats", "sink", "--json", *proc.client_args()).stdout)["ports"]["in"]
    return int(port["messages"]) + int(port["dropped"])


@pytest.mark.process
@pytest.mark.parametrize("via", ["router", "another manager"])
def test_a_replay_through_a_router_or_another_manager_waits_for_its_consumer(
    via: str, data_dir: Path, manager_process: Callable[..., ManagerProcess]
) -> None:
    """The operator connects to a router, or to a manager that is not the consumer's: the replay
    waits until Zenoh matches the consumer's subscriber there, and every message arrives (it used
    to exit 0 having delivered nothing)."""
    talker = data_dir / "mcap" / "real" / "talker.mcap"  # 10 messages on /topic
    router = None
    if via == "router":
        hub = f"tcp/127.0.0.1:{free_port()}"
        router = CliProcess("router", "--listen", hub, "--json")
        assert router.line()["event"] == "ready"
        entry = hub
        consumer = manager_process("--connect", hub, name="consumer")
    else:
        front = manager_process(name="front")
        entry = front.endpoint
        consumer = manager_process("--connect", front.endpoint, name="consumer")
    try:
        assert run_cli("spawn", "sink", "sink", "--bind", "in=replayed/talk", *consumer.client_args()).returncode == 0
        replay = run_cli("replay", str(talker), "--topics", "/topic", "--remap", "/topic=replayed/talk", "--rate", "max",
                         "--connect", entry, "--json", timeout=60)  # fmt: skip  (the default --wait, as an operator types it)
        assert replay.returncode == 0, replay.stderr
        assert json.loads(replay.stdout.splitlines()[-1]) == {"event": "done", "file": str(talker), "messages": 10, "unmatched": {}}
        wait_until(lambda: _sink_count(consumer) == 10, "the ten messages at the consumer")
    finally:
        if router is not None:
            router.stop()
            router.close()


@pytest.mark.process
def test_a_replay_that_delivers_nothing_says_so_and_fails(data_dir: Path, manager_process: Callable[..., ManagerProcess]) -> None:
    lonely = manager_process(name="lonely")
    talker = data_dir / "mcap" / "real" / "talker.mcap"
    replay = run_cli("replay", str(talker), "--topics", "/topic", "--rate", "max", "--wait", "0.5", "--connect", lonely.endpoint)
    assert replay.returncode == 1
    assert "replayed 10 messages" in replay.stdout
    assert "dyknow: error: no subscriber matched any key while the 10 messages were put (waited up to --wait 0.5 s" in replay.stderr
    assert "nothing was delivered; start the consumer first" in replay.stderr
