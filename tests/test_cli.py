"""The command line, run as real processes: offline commands, a manager driven over Zenoh."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from dyknow import Manager
from dyknow.testing import SCENARIO_SPECS, Sink
from tests.conftest import REPO, ManagerProcess, free_port, run_cli, subprocess_env, wait_until

SPECS = REPO / "tests" / "specs"


@pytest.mark.process
def test_validate_accepts_good_specs() -> None:
    result = run_cli("validate", str(REPO / "specs"), str(SPECS / "listing1_fixed.xml"))
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("ok: ")


@pytest.mark.process
def test_validate_reports_every_error_located() -> None:
    broken = SPECS / "broken" / "several_errors.xml"
    result = run_cli("validate", str(SPECS / "listing1.xml"), str(broken))
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert lines[0] == (
        f"{SPECS / 'listing1.xml'}:18: <tag> @port: no port named 'raw-camera'; "
        "expected one of 'undist', 'rawcamera' (did you mean 'rawcamera'?)"
    )
    assert len(lines) > 3 and all(line.startswith(f"{broken}:") for line in lines[1:])
    assert "Traceback" not in result.stderr and result.stdout == ""


@pytest.mark.process
def test_validate_refuses_a_requirement_over_the_formula_bounds(tmp_path: Path) -> None:
    """Issue 51, item 10: a requirement a manager could not watch (a two-day window: at most one)
    is an error of the spec, as the manager refuses it when it is added."""
    spec = tmp_path / "watched.xml"
    spec.write_text(
        "<transformation><label>watched</label><source>transformations.generic:Relay</source>\n"
        '  <ports><port type="in">in</port><port type="out">out</port></ports><tags><tag port="out">Track(x)</tag></tags>\n'
        "  <requirements><requirement>always[0, 172800s] Track(x).ok</requirement></requirements>\n"
        "</transformation>\n"
    )
    result = run_cli("validate", "--skip-sources", str(spec))
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.strip() == (
        f"{spec}:3: <requirement>: formula column 7: 'always[0, 172800s]' has the bound 172800s, beyond the longest window "
        "in 'always[0, 172800s] Track(x).ok'; expected bounds of at most 86400s (Limits.max_window_ns)"
    )


@pytest.mark.process
def test_validate_missing_path() -> None:
    result = run_cli("validate", "/nonexistent/specs")
    assert result.returncode == 1
    assert result.stderr.strip() == "/nonexistent/specs: no such file or directory; expected a spec file or a directory of *.xml files"


@pytest.mark.process
def test_expand_json_contract() -> None:
    result = run_cli("expand", str(SPECS / "listing1_fixed.xml"), "--json")
    assert result.returncode == 0, result.stderr
    expanded = json.loads(result.stdout)
    assert [t["label"] for t in expanded] == ["undistort(cam1)", "undistort(cam2)", "undistort(cam3)"]
    assert expanded[1] == {
        "label": "undistort(cam2)",
        "source": "package/Undistort",
        "params": {"config-path": "/path/to/configuration/cam2/"},
        "ports": [{"name": "undist", "direction": "out"}, {"name": "rawcamera", "direction": "in"}],
        "tags": [{"port": "undist", "tag": "Undistorted(cam2)"}, {"port": "rawcamera", "tag": "RawRGB(cam2)"}],
    }


@pytest.mark.process
def test_client_commands_drive_a_manager_process(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process()
    conn = proc.client_args()

    spawned = run_cli("spawn", "periodic-source", "src", "--param", "rate_hz=200", "--json", *conn)
    assert spawned.returncode == 0, spawned.stderr
    assert json.loads(spawned.stdout)["state"] == "running"
    assert run_cli("spawn", "relay", "r1", "--protect", "--bind", f"in=dyknow/{proc.name}/src/out", *conn).returncode == 0

    model = json.loads(run_cli("model", "--json", *conn).stdout)
    assert [(u["name"], u["protected"]) for u in model["units"]] == [("src", False), ("r1", True)]
    assert {"periodic-source", "relay", "sink"} <= {s["label"] for s in model["specs"]}

    got = run_cli("config", "get", "r1", "--json", *conn)
    assert json.loads(got.stdout) == {"in": f"dyknow/{proc.name}/src/out", "out": f"dyknow/{proc.name}/r1/out"}
    echo = run_cli("echo", f"dyknow/{proc.name}/r1/out", "--count", "5", "--json", *conn)
    assert echo.returncode == 0, echo.stderr
    messages = [json.loads(line) for line in echo.stdout.splitlines()]
    assert len(messages) == 5 and all(m["payload"]["bytes"] == 16 and m["latency_us"] > 0 for m in messages)

    changed = run_cli("config", "set", "r1", "out=demo/elsewhere", "--json", *conn)
    assert json.loads(changed.stdout)["out"] == "demo/elsewhere"
    stats = json.loads(run_cli("stats", "r1", "--json", *conn).stdout)
    assert stats["reconfigurations"] == 1 and stats["ports"]["in"]["messages"] > 0
    assert stats["ports"]["in"]["latency"]["count"] > 0

    refused = run_cli("destroy", "r1", *conn)
    assert refused.returncode == 1
    assert refused.stderr.strip() == (
        "dyknow: error: unit 'r1': the unit is protected (spawned with protected=True), so it cannot be destroyed without force; "
        "expected destroy(name, force=True) (dyknow destroy NAME --force; an admin's, when the manager has roles)"
    )
    assert run_cli("destroy", "src", *conn).returncode == 0

    # the paper's Listing 1 names a source no manager may import: refused when added, nothing added
    foreign = run_cli("add-spec", str(SPECS / "listing1_fixed.xml"), *conn)
    assert foreign.returncode == 1 and "source 'package/Undistort' is not importable" in foreign.stderr
    assert len(foreign.stderr.strip().splitlines()) == 1
    bad = run_cli("add-spec", str(SPECS / "listing1.xml"), *conn)
    assert bad.returncode == 1 and bad.stderr.startswith(f"{SPECS / 'listing1.xml'}:18: <tag> @port")
    relays = SPECS / "listing1_fixed.xml"
    added = run_cli("add-spec", "-", "--json", *conn, stdin=relays.read_text().replace("package/Undistort", "transformations.generic:Relay"))
    assert json.loads(added.stdout)["labels"] == ["undistort(cam1)", "undistort(cam2)", "undistort(cam3)"]
    assert json.loads(run_cli("remove-spec", "undistort(cam2)", "--json", *conn).stdout)["removed"] is True
    assert "undistort(cam2)" not in {s["label"] for s in json.loads(run_cli("model", "--json", *conn).stdout)["specs"]}

    assert proc.stop(signal.SIGTERM) == 0


@pytest.mark.process
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_manager_shuts_down_cleanly_on_signals(manager_process: Callable[..., ManagerProcess], sig: int) -> None:
    proc = manager_process()
    assert run_cli("spawn", "periodic-source", "src", *proc.client_args()).returncode == 0
    proc.proc.send_signal(sig)
    assert proc.proc.wait(timeout=5) == 0
    assert proc.proc.stderr is not None and "Traceback" not in proc.proc.stderr.read()


@pytest.mark.process
def test_no_manager_is_one_clear_line() -> None:
    result = run_cli("model", "--connect", f"tcp/127.0.0.1:{free_port()}", "--manager", "ghost", "--timeout", "1")
    assert result.returncode == 1
    assert result.stderr.strip().startswith("dyknow: error: cannot reach manager 'ghost': the connection to tcp/127.0.0.1:")
    assert result.stderr.strip().endswith("; expected the endpoint a manager listens on (its --listen) in --connect, and that manager running")
    assert len(result.stderr.strip().splitlines()) == 1


@pytest.mark.process
def test_usage_errors_exit_2() -> None:
    result = run_cli("config", "set", "x", "nonsense", "--timeout", "0.1")
    assert result.returncode == 2 and "expected NAME=VALUE" in result.stderr


@pytest.mark.process
def test_a_second_process_feeds_a_units_input(manager: Manager) -> None:
    manager.spawn("sink", "s", bindings={"in": "fleet/ticks"})
    script = textwrap.dedent(
        f"""
        import threading
        from dyknow import Manager
        with Manager("remote", specs=[{str(REPO / 'specs' / 'generic.xml')!r}], connect={manager.endpoints!r}) as m:
            m.spawn("periodic-source", "src", params={{"rate_hz": 100, "count": 3000}}, bindings={{"out": "fleet/ticks"}})
            threading.Event().wait()  # until the test kills it
        """
    )
    child = subprocess.Popen([sys.executable, "-c", script], env=subprocess_env(), stderr=subprocess.PIPE, text=True)
    try:
        sink = manager.unit("s")
        assert isinstance(sink, Sink)
        got = sink.wait_for(20, timeout_s=20)
        # (the other process's clock is estimated once its data arrives: on demand, issue 40)
        wait_until(lambda: manager.get_statistics("s").ports[0].hop.count > 0, "a hop corrected by the remote's clock")
    finally:
        child.kill()
        child.wait(10)
        if child.stderr is not None:
            child.stderr.close()
    seqs = [m.seq for m in got]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)  # in order, no duplicates
    assert all(m.key == "fleet/ticks" and m.payload == bytes(16) for m in got)
    assert all(m.send_ns >= m.origin_ns for m in got)
    stats = manager.get_statistics("s").ports[0]
    # (the other process's clock is corrected by its estimated offset: a hop shorter than the
    # estimate's uncertainty may read 0, never less)
    assert stats.messages >= 20 and stats.hop.count > 0 and stats.hop.p50_us >= 0


@pytest.mark.process
def test_manager_listen_conflict_is_one_clear_line(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process()
    port = proc.endpoint.rsplit(":", 1)[1]
    result = subprocess.run(
        [sys.executable, "-m", "dyknow.cli", "manager", "--name", "second", "--listen", proc.endpoint],
        capture_output=True, text=True, timeout=30, env=subprocess_env(),
    )  # fmt: skip
    assert result.returncode == 1
    assert f"127.0.0.1:{port}" in result.stderr and "Address already in use" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


@pytest.mark.process
def test_manager_with_broken_specs_refuses_to_start(tmp_path: Path) -> None:
    result = run_cli("manager", "--name", "x", "--listen", f"tcp/127.0.0.1:{free_port()}", "--specs", str(SPECS / "listing1.xml"))
    assert result.returncode == 1
    assert result.stderr.startswith(f"{SPECS / 'listing1.xml'}:18:")


@pytest.mark.process
def test_echo_times_out_with_a_clear_message(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process()
    start = time.monotonic()
    result = run_cli("echo", "nothing/here", "--count", "1", "--timeout-total", "0.5", *proc.client_args())
    assert result.returncode == 1 and "received 0 of 1 messages on 'nothing/here'" in result.stderr
    assert time.monotonic() - start < 30


SCENARIO = SCENARIO_SPECS
ONTOLOGY = REPO / "specs" / "dyknow.ttl"


@pytest.mark.process
def test_plan_json_contract() -> None:
    result = run_cli("plan", "--specs", str(SCENARIO), "--ontology", str(ONTOLOGY), "--request", "BallPosition(field)",
                     "--measure", "battery=0.1", "--json")  # fmt: skip
    assert result.returncode == 0, result.stderr
    planned = json.loads(result.stdout)
    assert planned["request"] == "BallPosition(field)"
    assert planned["output"] == {"unit": "tracker", "port": "out", "key": "dyknow/dyknow/tracker/out"}
    assert [u["label"] for u in planned["units"]] == [
        "ceiling-camera", "subsampler(ceiling)", "ball-detector(ceiling)", "localization(ceiling)", "tracker",
    ]  # fmt: skip
    assert all(u["new"] and u["manager"] == "dyknow" for u in planned["units"]) and set(planned["units"][0]) == {"name", "label", "new", "manager"}
    assert planned["connections"][0] == {"from": "ceiling-camera.out", "to": "subsampler-ceiling.in", "key": "dyknow/dyknow/ceiling-camera/out"}


@pytest.mark.process
def test_plan_failure_explains_and_exits_1() -> None:
    result = run_cli("plan", "--specs", str(SCENARIO), "--ontology", str(ONTOLOGY), "--request", "BallPosition(field)",
                     "--measure", "battery=0.1", "--unavailable", "ceiling-camera")  # fmt: skip
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.startswith("cannot plan BallPosition(field):")
    assert "robot-camera (port out): constraint violated: battery = 0.1, needs >= 0.25" in result.stderr
    assert "ceiling-camera (port out): unavailable" in result.stderr
    missing = run_cli("plan", "--specs", str(SCENARIO), "--request", "BallPosition(field)")
    assert missing.returncode == 1 and "no ontology is loaded (also at lines 31, 38); expected --ontology FILE" in missing.stderr  # (once per file)


@pytest.mark.process
def test_request_measure_release_over_the_cli(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process("--specs", str(SCENARIO), "--ontology", str(ONTOLOGY))
    conn = proc.client_args()
    requested = run_cli("request", "BallPosition(field)", "--json", *conn)
    assert requested.returncode == 0, requested.stderr
    key = json.loads(requested.stdout)["key"]
    assert key == f"dyknow/{proc.name}/requests/BallPosition(field)"
    echo = run_cli("echo", key, "--count", "3", "--json", *conn)
    assert echo.returncode == 0 and [json.loads(x)["payload"]["camera"] for x in echo.stdout.splitlines()] == [1, 1, 1]
    assert run_cli("measure", "battery=0.1", *conn).returncode == 0
    echo = run_cli("echo", key, "--count", "40", "--json", *conn)
    assert json.loads(echo.stdout.splitlines()[-1])["payload"]["camera"] == 3  # the ceiling camera now
    history = json.loads(run_cli("adaptations", "--json", *conn).stdout)
    assert history[0]["cause"] == "measurement battery = 0.1" and history[0]["adaptation_ms"] > 0
    impossible = run_cli("request", "Teleport(x)", *conn)
    assert impossible.returncode == 1 and "nothing provides Teleport(x)" in impossible.stderr
    assert run_cli("release", key, *conn).returncode == 0
    model = json.loads(run_cli("model", "--json", *conn).stdout)
    assert model["units"] == [] and model["requests"] == []


@pytest.mark.process
def test_managers_and_echo_show_clocks_as_the_manager_estimates_them(manager_process: Callable[..., ManagerProcess]) -> None:
    """Two manager processes, two clocks of one machine (the true offset is 0). ``managers`` shows
    each manager's offset from --manager's clock with its uncertainty; ``echo`` corrects the age
    of a message stamped by the other manager's clock, and says "clock unknown" for a clock
    --manager does not know (a plain process's, here this test's)."""
    from dyknow import Client, Message
    from dyknow.transport import Session, make_config

    a = manager_process(name="clk-a")
    b = manager_process("--connect", a.endpoint, name="clk-b")
    conn = a.client_args()
    with Client("clk-a", connect=[a.endpoint]) as client:
        # clk-a estimates clk-b's clock once it receives clk-b's data (on demand, issue 40)
        Client("clk-b", session=client.session).spawn("periodic-source", "feed", params={"rate_hz": 50})
        client.spawn("relay", "fed", bindings={"in": "dyknow/clk-b/feed/out"})
        wait_until(lambda: "clk-b" in client.clocks(), "clk-a's estimate of clk-b's clock")
        other = client.clocks()["clk-b"].clock

    listed = run_cli("managers", "--json", *conn)
    assert listed.returncode == 0, listed.stderr
    clocks = {m["manager"]: m["clock"] for m in json.loads(listed.stdout)}
    assert clocks["clk-a"] == {"offset_us": 0.0, "uncertainty_us": 0.0}
    assert clocks["clk-b"] is not None and abs(clocks["clk-b"]["offset_us"]) <= clocks["clk-b"]["uncertainty_us"]
    text = run_cli("managers", *conn).stdout
    assert "clk-a" in text and "clock +0.0 us +/- 0.0" in text and text.count("clock ") == 2, text

    assert run_cli("spawn", "periodic-source", "src", "--param", "rate_hz=200", *b.client_args()).returncode == 0
    echo = run_cli("echo", "dyknow/clk-b/src/out", "--count", "3", "--json", *conn)
    assert echo.returncode == 0, echo.stderr
    for line in echo.stdout.splitlines():
        message = json.loads(line)
        assert message["origin_clock"] == f"{other:08x}"  # stamped by clk-b's process
        assert message["latency_us"] is not None and message["uncertainty_us"] > 0

    stop = threading.Event()

    def publish() -> None:  # a clock clk-a knows nothing of: this process's
        with Session(make_config(connect=[a.endpoint])) as session:
            publisher = session.declare_publisher("clk/plain")
            seq = 0
            while not stop.wait(0.02):
                seq += 1
                publisher.put(Message({"n": seq}, seq, time.time_ns(), time.time_ns(), "clk/plain"))

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        unknown = run_cli("echo", "clk/plain", "--count", "2", "--json", *conn)
        plain = run_cli("echo", "clk/plain", "--count", "1", *conn)
    finally:
        stop.set()
        thread.join(10)
    assert unknown.returncode == 0, unknown.stderr
    assert all(json.loads(x)["latency_us"] is None and json.loads(x)["uncertainty_us"] is None for x in unknown.stdout.splitlines())
    assert "age clock unknown" in plain.stdout, plain.stdout


@pytest.mark.process
def test_what_a_new_user_trips_on_is_said_plainly(manager_process: Callable[..., ManagerProcess]) -> None:
    """Empty listings say so; release says how many references remain; echo prints JSON a user
    can paste, and says when the --manager it was given is not there (with the close match)."""
    proc = manager_process("--specs", str(SCENARIO), "--ontology", str(ONTOLOGY), name="engine")
    conn = proc.client_args()
    assert run_cli("adaptations", *conn).stdout.strip() == "no adaptations on manager 'engine' yet"
    assert "  no units" in run_cli("model", *conn).stdout
    key = run_cli("request", "BallPosition(field)", *conn).stdout.strip()
    assert run_cli("request", "BallPosition(field)", *conn).stdout.strip() == key
    first = run_cli("release", key, *conn)
    assert first.stdout.strip() == f"released one reference to {key}; 1 more remain, so it runs on until they are released too"
    second = run_cli("release", key, "--json", *conn)
    assert json.loads(second.stdout) == {"released": key, "references": 0}
    assert run_cli("spawn", "ceiling-camera", "cam", *conn).returncode == 0
    assert run_cli("spawn", "subsampler(ceiling)", "sub", "--bind", "in=dyknow/engine/cam/out", *conn).returncode == 0
    assert run_cli("spawn", "ball-detector(ceiling)", "det", "--bind", "in=dyknow/engine/sub/hsv", *conn).returncode == 0
    typo = run_cli("echo", "dyknow/engine/det/out", "--count", "1", "--connect", proc.endpoint, "--manager", "engin")
    assert typo.returncode == 0, typo.stderr
    assert "dyknow: warning: no manager 'engin' is reachable (reachable: engine (did you mean 'engine'?))" in typo.stderr
    printed = typo.stdout.split(": ", 1)[1].strip()  # "KEY #SEQ age ...: PAYLOAD"
    assert json.loads(printed)["camera"] == 3  # JSON, as the unit published it


def test_echo_describes_arrays_inside_a_payload() -> None:
    from dyknow.cli.common import payload_json

    payload = {"width": 2, "data": np.zeros(8, np.uint8), "fields": [{"a": np.zeros((2, 3), np.float32)}], "raw": b"\x01"}
    assert payload_json(payload) == {
        "width": 2,
        "data": {"ndarray": {"dtype": "uint8", "shape": [8]}},
        "fields": [{"a": {"ndarray": {"dtype": "float32", "shape": [2, 3]}}}],
        "raw": {"bytes": 1, "base64": "AQ=="},
    }


# ------------------------------------------------------------------------------------------- shipped files, from anywhere


def _outside(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``dyknow ARGS`` from an empty folder outside the checkout."""
    return subprocess.run([sys.executable, "-m", "dyknow.cli", *args], capture_output=True, text=True, timeout=60,
                          env=subprocess_env(), cwd=tmp_path)  # fmt: skip


@pytest.mark.process
def test_shipped_specs_have_a_name_that_works_from_any_folder(tmp_path: Path) -> None:
    assert REPO not in tmp_path.parents
    done = _outside(tmp_path, "validate", "@shipped", "--ontology", "@shipped/dyknow.ttl")
    assert done.returncode == 0 and done.stdout.startswith("ok: "), done.stderr
    done = _outside(tmp_path, "validate", "specs/", "--ontology", "specs/dyknow.ttl")  # the checkout's path, from elsewhere
    assert done.returncode == 2 and f"specs/: no such file in {tmp_path}; dyknow's shipped copy is @shipped (dyknow paths)" in done.stderr
    done = _outside(tmp_path, "plan", "--specs", "@testing/scenario-station.xml", "--ontology", "@shipped/dyknow.ttl", "--manager",
                    "station", "--request", "BallTrack(field)", "--peer", "robot=@testing/scenario-robot.xml", "--json")  # fmt: skip
    assert done.returncode == 0 and '"manager":"robot"' in done.stdout, done.stderr


@pytest.mark.process
def test_a_misspelled_shipped_name_says_which_exist(tmp_path: Path) -> None:
    done = _outside(tmp_path, "validate", "@shiped")
    assert done.returncode == 2
    assert "no shipped folder '@shiped' (did you mean '@shipped'?); expected one of @shipped, @testing" in done.stderr
    done = _outside(tmp_path, "manager", "--specs", "@shipped/visoin.xml")
    assert done.returncode == 2 and "is not shipped; @shipped holds dyknow.ttl, generic.xml" in done.stderr


@pytest.mark.process
def test_paths_prints_where_the_shipped_files_are(tmp_path: Path) -> None:
    done = _outside(tmp_path, "paths", "--json")
    assert done.returncode == 0, done.stderr
    found = json.loads(done.stdout)
    shipped = Path(found["folders"]["@shipped"]["path"])
    assert (shipped / "generic.xml").is_file() and "dyknow.ttl" in found["folders"]["@shipped"]["files"]
    assert "scenario-station.xml" in found["folders"]["@testing"]["files"]
    assert {"pipeline.xml", "modes.yaml"} <= set(found["folders"]["@pipeline"]["files"])
    text = _outside(tmp_path, "paths").stdout
    assert f"@shipped   {shipped}" in text and "@testing" in text and "@pipeline" in text
    # (the pipeline robot's spec from any folder: its mode file beside it is found)
    done = _outside(tmp_path, "validate", "@pipeline/pipeline.xml")
    assert done.returncode == 0, done.stdout + done.stderr


@pytest.mark.process
def test_a_units_exception_shows_where_in_its_code_in_the_log_model_and_stats(manager_process: Callable[..., ManagerProcess]) -> None:
    """``KeyError: 'speed'`` alone says nothing of where: the log names the file and line, and
    ``dyknow model`` and ``dyknow stats`` show the last frames of the traceback."""
    proc = manager_process()
    client = proc.client_args()
    assert run_cli("spawn", "failing", "f", "--bind", "in=t/in", *client).returncode == 0
    assert run_cli("spawn", "periodic-source", "src", "--param", "rate_hz=20", "--bind", "out=t/in", *client).returncode == 0
    units = REPO / "tests" / "units.py"
    line = next(n for n, text in enumerate(units.read_text().splitlines(), 1) if 'raise RuntimeError(f"boom at message' in text)

    def failed() -> bool:
        model = json.loads(run_cli("model", "--json", *client).stdout)
        return any(u["name"] == "f" and u["state"] == "failed" for u in model["units"])

    wait_until(failed, "the failing unit failed")
    model = run_cli("model", *client).stdout
    assert "error: on_message('in'): RuntimeError: boom at message 1" in model
    assert "traceback (last " in model and f'File "{units}", line {line}, in on_message' in model
    stats = run_cli("stats", "f", *client).stdout
    assert f'File "{units}", line {line}, in on_message' in stats and "RuntimeError: boom at message 1" in stats
    proc.stop()
    assert proc.proc.stderr is not None
    log = proc.proc.stderr.read()
    assert f"RuntimeError: boom at message 1 at {units}:{line} in on_message (dyknow stats f shows the traceback)" in log


@pytest.mark.process
def test_a_misspelled_endpoint_protocol_names_the_protocols() -> None:
    """Zenoh says only "Unicast not supported for tpc protocol"."""
    expected = "no Zenoh link protocol 'tpc' (did you mean 'tcp'?); expected PROTOCOL/ADDRESS:PORT with PROTOCOL one of tcp, tls, udp, quic, ws"
    for argv, option in ((["model", "--connect", "tpc/127.0.0.1:7447"], "--connect"), (["manager", "--listen", "tpc/127.0.0.1:0"], "--listen"),
                         (["record", "x/**", "-o", "x.mcap", "--connect", "tpc/127.0.0.1:7447"], "--connect")):  # fmt: skip
        done = run_cli(*argv)
        assert done.returncode == 1 and f"dyknow: error: {option}: tpc/127.0.0.1:" in done.stderr and expected in done.stderr, done.stderr
        assert "Unicast not supported" not in done.stderr


def _subparsers(parser: object) -> dict[str, object]:
    import argparse

    found: dict[str, object] = {}
    for action in getattr(parser, "_actions", []):
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found[name] = sub
                found.update({f"{name} {k}": v for k, v in _subparsers(sub).items()})
    return found


def test_every_positional_argument_has_help_and_every_example_parses() -> None:
    """``dyknow config --help`` said ``action``, ``name``, ``bindings`` and nothing more."""
    import argparse
    import shlex

    from dyknow.cli import _parser

    parser = _parser()
    commands = _subparsers(parser)
    missing = [f"{name} {a.dest}" for name, sub in commands.items() for a in sub._actions  # type: ignore[attr-defined]
               if not a.option_strings and not isinstance(a, argparse._SubParsersAction) and not a.help]  # fmt: skip
    assert missing == []
    examples = [line.strip() for sub in commands.values() for line in (sub.epilog or "").splitlines()[1:]]  # type: ignore[attr-defined]
    assert len(examples) >= 15
    for command in ("spawn", "config", "stats", "request", "monitor"):
        assert (commands[command].epilog or "").startswith("examples:"), command  # type: ignore[attr-defined]
    for line in examples:
        words = shlex.split(line.split("  #")[0])
        assert words[0] == "dyknow", line
        parser.parse_args(words[1:])  # (exits, failing the test, on an example that does not parse)


#: What a command that fails to reach a manager never needs: numpy (a payload that is an array
#: imports it), TLS and ACL readers, the services' checks and the formula parser they pull in, the
#: clock estimates (most of the failing command's start-up when they were imported: benchmarks/operator.py).
_NOT_TO_FAIL = ["numpy", "rdflib", "cryptography", "json5", "ssl", "dyknow.service", "dyknow.reasoning.syntax", "dyknow.clocks",
                "dyknow.model", "dyknow.holders", "secrets", "concurrent.futures"]  # fmt: skip


@pytest.mark.process
@pytest.mark.parametrize(
    ("argv", "absent"),
    [
        (["--help"], ["numpy", "zenoh", "rdflib", "cryptography", "dyknow.manager", "dyknow.client", "dyknow.spec.reader"]),
        (["validate", "--help"], ["zenoh", "rdflib", "cryptography", "dyknow.manager", "dyknow.client"]),
        (["model", "--connect", "tcp/127.0.0.1:9"], [*_NOT_TO_FAIL, "dyknow.manager", "dyknow.planner", "dyknow.spec.reader", "cv2"]),
    ],
    ids=["help", "validate --help", "model, failing"],
)
def test_a_command_imports_what_it_needs_only(argv: list[str], absent: list[str]) -> None:
    """The start-up of ``dyknow`` (0.55 s for --help when it imported everything): what each
    command imports is checked here; the time itself is measured by benchmarks/operator.py."""
    imported = _imported_by(argv)
    assert [m for m in absent if m in imported] == []
    assert "dyknow.transport" in imported or argv[-1] == "--help"  # (the failing model did get as far as Zenoh)


def _imported_by(argv: list[str]) -> set[str]:
    """The modules ``dyknow ARGV`` imported, run in a child process."""
    code = (
        "import sys\nfrom dyknow.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        "print(' '.join(sorted(m for m in sys.modules)), file=sys.stderr)"
    )
    done = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=60, env=subprocess_env())
    return set(done.stderr.splitlines()[-1].split())


@pytest.mark.process
def test_a_misspelled_manager_is_said_without_importing_more(manager_process: Callable[..., ManagerProcess]) -> None:
    """Told a manager is not there (and which are), the command still needs none of them."""
    robot = manager_process(name="robot")
    imported = _imported_by(["model", "--manager", "robt", "--connect", robot.endpoint, "--timeout", "60"])
    assert [m for m in _NOT_TO_FAIL if m in imported] == []
    assert "dyknow.client" in imported


_RUN_SCRIPT = """
import atexit, sys, threading, time
from pathlib import Path
import dyknow.cli as cli
from dyknow.transport import open_session

out = Path(sys.argv[1])
command = cli.main

def main(argv):  # a command that leaves a session open, a thread running and an exit handler
    session = open_session(listen=[], connect=[])  # left open: closed on the way out
    session.declare_subscriber("run/**", lambda message: None)
    atexit.register(lambda: (out / "atexit").write_text(str(session.closed)))

    def late() -> None:
        time.sleep(0.3)
        (out / "thread").write_text("done")

    threading.Thread(target=late).start()
    print("said before", end="")  # (not flushed)
    return command(argv)

cli.main = main
cli.run(sys.argv[2:])
print("never")
"""


@pytest.mark.process
@pytest.mark.parametrize(
    ("argv", "code", "said"),
    [
        (["--version"], 0, ""),
        (["validate", "/nonexistent/specs"], 1, "/nonexistent/specs: no such file or directory"),
        (["config", "set", "x", "nonsense"], 2, "expected NAME=VALUE"),
    ],
)
def test_the_program_ends_with_its_commands_code_after_what_python_does_at_exit(tmp_path: Path, argv: list[str], code: int, said: str) -> None:
    """``dyknow`` ends without the interpreter's teardown (where a Zenoh thread calling into
    Python aborted a manager that had stopped cleanly, exit -6): what Python does at exit is still
    done, in its order: sessions closed, the program's threads joined, exit handlers run, output
    flushed, and the command's own code returned."""
    done = subprocess.run(
        [sys.executable, "-c", _RUN_SCRIPT, str(tmp_path), *argv], capture_output=True, text=True, timeout=60, env=subprocess_env()
    )
    assert done.returncode == code, done.stderr
    assert done.stdout.startswith("said before") and "never" not in done.stdout
    assert said in done.stderr
    assert (tmp_path / "thread").read_text() == "done"
    assert (tmp_path / "atexit").read_text() == "True"  # the session was closed before the exit handlers


@pytest.mark.unit
def test_the_installed_program_is_run() -> None:
    from importlib.metadata import entry_points

    (script,) = entry_points(group="console_scripts", name="dyknow")
    assert script.value == "dyknow.cli:run"


# ---------------------------------------------------------------------- a manager's word is shown, never obeyed (issue 51)


class Impostor:
    """A Zenoh router posing as manager ``name``, as anyone can without TLS (or a router on the
    way): its liveliness token, and its services answered with ``replies[service]`` as given
    (``(ok, bytes)``: a reply, or a refusal), whatever a manager would say."""

    def __init__(self, name: str = "evil", tokens: tuple[str, ...] = ()) -> None:
        from dyknow import keys
        from dyknow.transport import Session, make_config

        self.name = name
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.replies: dict[str, tuple[bool, bytes]] = {}
        self.session = Session(make_config(listen=[self.endpoint], mode="router"))
        self.held = [  # (an entity no one holds is undeclared)
            self.session.declare_queryable(keys.services_pattern(name), lambda key, payload: self.replies.get(key.rpartition("/")[2], (True, b"{}"))),
            *(self.session.declare_liveliness_token(token) for token in tokens),
            self.session.declare_liveliness_token(keys.manager_token(name)),
        ]  # fmt: skip

    def args(self) -> list[str]:
        """The options that point a client command at the impostor."""
        return ["--connect", self.endpoint, "--manager", self.name, "--timeout", "5"]

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def impostor() -> Iterator[Impostor]:
    fake = Impostor(tokens=("@dyknow/\u202eevil", "@dyknow/a b"))
    yield fake
    fake.close()


ESCAPES = "\x1b]0;pwned\x07\x1b[2J\x9b31m\u202e"  # a window title, clear screen, a C1 CSI, a right-to-left override
SHOWN_ESCAPES = r"\x1b]0;pwned\x07\x1b[2J\x9b31m\u202e"


def _unharmed(result: subprocess.CompletedProcess[str]) -> None:
    """Nothing the command printed holds a character a terminal would act on but a line's end."""
    for stream in (result.stdout, result.stderr):
        acted = sorted({c for c in stream if not c.isprintable() and c != "\n"})
        assert acted == [], (acted, stream[-2000:])
    assert "internal error" not in result.stderr and "Traceback" not in result.stderr, result.stderr


@pytest.mark.process
def test_what_a_hostile_manager_says_is_shown_escaped_never_obeyed(impostor: Impostor) -> None:
    """Terminal escapes in every field people read of ``model``, ``managers`` and ``hz`` (a
    window title, a clear screen, a fake line, U+202E) are shown escaped; tokens of names no
    manager has are not listed; ``--json`` keeps every field as it came, in ASCII JSON."""
    unit = {"name": "u1", "label": f"relay{ESCAPES}", "state": f"running{ESCAPES}", "protected": False,
            "bindings": {f"in{ESCAPES}": f"k{ESCAPES}"}, "error": f"boom\nmanager robot: 0 units{ESCAPES}", "traceback": f"  File x{ESCAPES}\nE"}
    model = {"manager": "evil", "units": [unit], "specs": [{"label": f"spec{ESCAPES}"}],
             "requests": [{"tag": f"T{ESCAPES}", "key": "k", "state": "active"}], "lost": [{"manager": "gone", "since_ns": 1, "why": ESCAPES}]}
    impostor.replies = {"get_model": (True, json.dumps(model).encode()),
                        "get_summary": (True, json.dumps({"host": f"host{ESCAPES}", "specs": 1, "units": 1, "requests": 1}).encode())}  # fmt: skip
    shown = run_cli("model", *impostor.args())
    _unharmed(shown)
    assert shown.returncode == 0, shown.stderr
    assert f"  u1 (relay{SHOWN_ESCAPES}) running{SHOWN_ESCAPES}" in shown.stdout
    assert rf"      error: boom\nmanager robot: 0 units{SHOWN_ESCAPES}" in shown.stdout  # (no fake line of its own)
    assert not any(line.startswith("manager robot") for line in shown.stdout.splitlines())
    as_json = run_cli("model", "--json", *impostor.args())
    assert as_json.returncode == 0 and as_json.stdout.isascii(), as_json.stderr
    assert json.loads(as_json.stdout)["units"][0] == {**unit}  # (machines get every byte as it came)
    listed = run_cli("managers", *impostor.args())
    _unharmed(listed)
    assert listed.returncode == 0, listed.stderr
    lines = listed.stdout.splitlines()
    assert f" host host{SHOWN_ESCAPES} " in lines[0] and lines[1].endswith(f": {SHOWN_ESCAPES}"), listed.stdout
    assert [line.split()[0] for line in lines] == ["evil", "gone"]  # (the tokens @dyknow/<U+202E>evil and '@dyknow/a b' name no manager)
    done = threading.Event()

    def publish() -> None:
        while not done.wait(0.01):
            impostor.session.put(f"dyknow/evil/\u202eexe.txt{ESCAPES}/out", b"x")

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    try:
        rates = run_cli("hz", "dyknow/evil/**", "--duration", "2", "--every", "0.5", *impostor.args())
    finally:
        done.set()
        publisher.join()
    _unharmed(rates)
    assert rates.returncode == 0 and r"dyknow/evil/\u202eexe.txt" in rates.stdout, rates.stdout + rates.stderr


DEEP = b"[" * 100_000 + b"]" * 100_000


@pytest.mark.process
@pytest.mark.parametrize(
    ("argv", "service", "reply", "said"),
    [
        (["model"], "get_model", (True, DEEP), "dyknow: error: the reply of manager 'evil' to get_model: it nests deeper than 64 levels"),
        (["model"], "get_model", (True, b"[1, 2]"), "the reply of manager 'evil' to get_model: reply is a JSON array of 2 entries"),
        (["model"], "get_model", (True, b'{"manager": "evil", "units": [{"name": "\\u001b[2J"}], "specs": []}'),
         r"reply.units[0].name is '\x1b[2J', not a unit name; expected letters, digits"),
        (["model"], "get_model", (False, DEEP), "dyknow: error: [[[["),  # a refusal nested past the parser's stack: said as it came, shortened
        (["model"], "get_model", (False, b'{"error": "UnitError", "message": "x", "what": ' + b"[" * 70 + b"]" * 70 + b"}"),
         "its error nests deeper than 64 levels"),
        (["model", "--all"], "get_model", (True, DEEP), "dyknow: error: the reply of manager 'evil' to get_model: it nests deeper than 64 levels"),
        (["managers"], "get_summary", (True, DEEP), "dyknow: error: the reply of manager 'evil' to get_summary: it nests deeper than 64 levels"),
        (["managers"], "get_summary", (True, b'"a summary"'), "to get_summary: reply is 'a summary'; expected a JSON object"),
        (["top", "--once", "--only", "--interval", "0.1"], "get_metrics", (True, b'{"manager": "evil", "time_ns": "now"}'),
         "manager evil: the reply of manager 'evil' to get_metrics: reply.time_ns is 'now'"),
        (["top", "--once", "--only", "--interval", "0.1"], "get_metrics", (True, DEEP), "it nests deeper than 64 levels"),
        (["doctor"], "get_model", (True, DEEP), "FAIL access    the reply of manager 'evil' to get_model: it nests deeper than 64 levels"),
        (["stats", "u1"], "get_statistics", (True, b"{}"), "to get_statistics: reply.name is missing; expected the fields name, label"),
        (["request", "T"], "request", (True, b'{"key": ["k"]}'), "to request: reply.key is a JSON array of 1 entries; expected text"),
    ],
)
def test_a_reply_of_the_wrong_shape_is_named_never_an_internal_error(
    impostor: Impostor, argv: list[str], service: str, reply: tuple[bool, bytes], said: str
) -> None:
    """A reply nested 100,000 deep (or 65), of another type, or with a field no manager sends:
    one clear line naming the manager, the call and what was expected, exit 1, never exit 70."""
    impostor.replies = {service: reply}
    result = run_cli(*argv, *impostor.args())
    _unharmed(result)
    assert result.returncode == 1, (result.returncode, result.stdout, result.stderr)
    assert said in result.stdout + result.stderr, result.stdout + result.stderr
