"""The client: a manager's services from another session, with the manager's own errors."""

from __future__ import annotations

import re
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import BindingError, Client, LibraryError, Manager, Message, SpecError, UnitError
from dyknow.transport import MAX_QUERIERS
from tests.conftest import GENERIC_SPECS, CliProcess, ManagerProcess, free_port, run_cli, wait_until

RELAY = """<transformation><label>my-relay</label><source>transformations.generic:Relay</source>
  <ports><port type="in">in</port><port type="out">out</port></ports></transformation>"""


def test_the_client_mirrors_the_managers_services(manager: Manager) -> None:
    with Client(manager.name, connect=manager.endpoints, timeout_s=5) as client:
        assert client.add_transformation(RELAY) == ["my-relay"]
        info = client.spawn("my-relay", "r", bindings={"in": "c/in"})
        assert info["state"] == "running" and info["bindings"] == {"in": "c/in", "out": f"dyknow/{manager.name}/r/out"}
        assert [u["name"] for u in client.get_model()["units"]] == ["r"]
        assert client.set_config("r", {"out": "c/out"}) == {"in": "c/in", "out": "c/out"}
        assert client.get_config("r") == manager.get_config("r")
        assert client.get_statistics("r")["reconfigurations"] == 1
        client.measure("battery", 0.5)
        assert manager.measurements == {"battery": 0.5}
        assert client.get_adaptations() == []
        client.destroy("r")
        assert client.remove_transformation("my-relay") is True
        assert client.remove_transformation("my-relay") is False
        assert manager.get_model().units == ()


def test_refusals_raise_the_managers_error_class(manager: Manager) -> None:
    with Client(manager.name, connect=manager.endpoints) as client:
        with pytest.raises(LibraryError, match="no transformation labelled 'nope'"):
            client.spawn("nope", "x")
        client.spawn("sink", "s")
        with pytest.raises(BindingError, match="no port 'inn'"):
            client.set_config("s", {"inn": "a/b"})
        with pytest.raises(UnitError, match="a unit named 's' already exists"):
            client.spawn("sink", "s")
        with pytest.raises(SpecError) as bad_spec:
            client.add_transformation("<transformation><label>x</label></transformation>")
        assert [i.element for i in bad_spec.value.issues] == ["<transformation>", "<transformation>"]


def test_a_spec_file_is_read_on_the_clients_side(manager: Manager, tmp_path: Path) -> None:
    with Client(manager.name, connect=manager.endpoints) as client:
        assert "relay" in client.add_transformation(GENERIC_SPECS)
        with pytest.raises(SpecError, match=r"missing\.xml: cannot read"):
            client.add_transformation(tmp_path / "missing.xml")


def test_declare_subscriber_receives_a_stream(manager: Manager) -> None:
    manager.spawn("periodic-source", "src", params={"rate_hz": 200})
    got: list[Message] = []
    three = threading.Event()

    def on_message(msg: Message) -> None:
        got.append(msg)
        if len(got) >= 3:
            three.set()

    with Client(manager.name, connect=manager.endpoints) as client, client.declare_subscriber(f"dyknow/{manager.name}/src/**", on_message):
        assert three.wait(10)
    assert got[0].key == f"dyknow/{manager.name}/src/out" and got[1].seq > got[0].seq


def test_close_is_safe_twice_and_a_given_session_stays_open(manager: Manager) -> None:
    client = Client(manager.name, connect=manager.endpoints)
    client.close()
    client.close()
    with Client(manager.name, session=manager.session) as borrowed:
        assert borrowed.get_model()["manager"] == manager.name
    assert not manager.session.closed


def test_a_client_calling_ever_new_units_keeps_a_bounded_number_of_queriers(manager: Manager) -> None:
    for i in range(80):
        manager.spawn("sink", f"s{i}")
    with Client(manager.name, connect=manager.endpoints) as client:
        threads = threading.active_count()
        for i in range(80):
            assert client.get_config(f"s{i}") == manager.get_config(f"s{i}")
        assert client.session.queriers() <= MAX_QUERIERS
        # no thread per querier (64 more); the process also runs the manager, whose pools may
        # start a thread of their own meanwhile (one did, beside a full run): a few are allowed
        assert threading.active_count() - threads < 8, (threads, [t.name for t in threading.enumerate()])
        assert client.get_statistics("s0")["name"] == "s0"  # an evicted querier is declared again


@pytest.mark.process
def test_a_call_to_a_manager_that_is_gone_ends_at_once_saying_so(manager_process: Callable[..., ManagerProcess]) -> None:
    """Its liveliness token went away (killed here; a host cut off is the same once its lease
    expires): the call does not wait its whole timeout for the service to come back, it says the
    manager is gone. A manager never seen, where nothing listens, is refused at once too."""
    import signal

    from dyknow import ServiceError

    proc = manager_process()
    with Client(proc.name, connect=[proc.endpoint], timeout_s=60.0) as client:
        assert client.get_model()["manager"] == proc.name
        proc.proc.send_signal(signal.SIGKILL)
        proc.proc.wait(10)
        wait_until(lambda: proc.name not in client.manager_names(timeout_s=0.5), "the token to go")
        said = []
        for _ in range(50):  # the client's own watch of the tokens may hear of it a moment later
            with pytest.raises(ServiceError) as refused:
                client.get_model()
            said.append(str(refused.value))
            if "is gone" in said[-1]:
                break
        assert re.search(rf"manager {proc.name!r} is gone: its liveliness token went away .* s ago", said[-1]), said
    with Client("never-seen", connect=[proc.endpoint], timeout_s=60) as other, pytest.raises(ServiceError, match="was refused: nothing listens on port"):
        other.get_model()  # nothing listens there any more: said at once, without waiting for the timeout


@pytest.mark.process
def test_a_client_sees_every_manager_leave_stopped_or_vanished_until_it_comes_back(
    manager_process: Callable[..., ManagerProcess], cli_process: Callable[..., CliProcess]
) -> None:
    """A tool's client watches every manager's token and goodbye (a manager watches only those it
    follows): one stopped is lost as stopped, one killed as vanished, and one back is not lost."""
    import signal

    from dyknow.keys import LOSS_STOPPED, LOSS_VANISHED

    hub = f"tcp/127.0.0.1:{free_port()}"
    assert cli_process("router", "--listen", hub, "--json").line()["event"] == "ready"
    calm, doomed = manager_process("--connect", hub, name="calm"), manager_process("--connect", hub, name="doomed")
    with Client("calm", connect=[hub], timeout_s=30) as client:
        wait_until(lambda: {"calm", "doomed"} <= set(client.manager_names(timeout_s=0.5)), "both managers")
        assert client.seen_lost() == []
        calm.proc.send_signal(signal.SIGTERM)  # (it says goodbye as it stops)
        doomed.proc.send_signal(signal.SIGKILL)
        wait_until(lambda: len(client.seen_lost()) == 2, "both losses seen")
        wait_until(lambda: client.seen_lost()[0]["why"] == LOSS_STOPPED, "the goodbye (it may come after the token's end)")
        lost = client.seen_lost()
        assert [(m["manager"], m["why"]) for m in lost] == [("calm", LOSS_STOPPED), ("doomed", LOSS_VANISHED)]
        assert all(isinstance(m["since_ns"], int) and m["since_ns"] > 0 for m in lost)
        manager_process("--connect", hub, name="doomed")
        wait_until(lambda: [m["manager"] for m in client.seen_lost()] == ["calm"], "the manager back to be no longer lost")


@pytest.mark.process
def test_clocks_are_the_managers_as_it_estimates_them(manager_process: Callable[..., ManagerProcess], make_manager: Callable[..., Manager]) -> None:
    """Two manager processes: two clocks of one machine (the true offset is 0). A manager
    estimates the clock of another only while it exchanges data with it (issue 40): none while
    they are idle; once clk-b's stream reaches a unit of clk-a, clk-a finds whose clock stamps
    it (its clock token), and gives its own clock (offset 0) and the other's, with an
    uncertainty that holds. A manager of the client's own process shares its clock: nothing to
    estimate, and none listed."""
    a = manager_process(name="clk-a")
    b = manager_process("--connect", a.endpoint, name="clk-b")
    with Client("clk-a", connect=[a.endpoint]) as client, Client("clk-b", connect=[a.endpoint]) as other:
        wait_until(lambda: client.manager_names() == ["clk-a", "clk-b"], "both managers up")
        threading.Event().wait(1.5)  # (a reconcile of the clocks to estimate runs every second)
        assert list(client.clocks()) == ["clk-a"]  # idle: the other's clock is not estimated
        other.spawn("periodic-source", "src", params={"rate_hz": 50})
        client.spawn("relay", "rel", bindings={"in": "dyknow/clk-b/src/out"})
        wait_until(lambda: "clk-b" in client.clocks(), "clk-a's estimate of clk-b's clock, whose data it receives")
        clocks = client.clocks()
        assert set(clocks) == {"clk-a", "clk-b"}
        own, other = clocks["clk-a"], clocks["clk-b"]
        assert own.clock == int(client.get_model()["clocks"]["clock"], 16) and (own.offset_ns, own.uncertainty_ns) == (0, 0)
        assert other.clock == int(client.get_model("clk-b")["clocks"]["clock"], 16) != own.clock
        assert abs(other.offset_ns) <= other.uncertainty_ns and other.samples >= 1
    assert b.proc.poll() is None
    here = make_manager("clk-here")
    with Client(here.name, session=here.session) as client:
        assert list(client.clocks()) == ["clk-here"]


def test_a_call_that_times_out_names_the_call_the_manager_the_wait_and_what_may_have_happened() -> None:
    """A manager that serves its services but answers none in time (a busy one): Zenoh says only
    ``Timeout``; the client names the call, the manager, the time waited, --timeout, and whether
    the request may still be carried out (a read: no; a spawn: yes). Its clock exchange, answered
    at once on Zenoh's thread, says the link is up: busy or stuck, not cut (issue 52)."""
    from dyknow import ServiceError, clocks, keys
    from dyknow.transport import Session, make_config
    from tests.conftest import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Session(make_config(listen=[endpoint], connect=[])) as busy:
        busy.declare_liveliness_token(keys.manager_token("busy"))
        # calls queued, never answered; clock exchanges answered at once, as a manager does
        busy.declare_service_channel(keys.services_pattern("busy"), at_once={keys.clock_key("busy"): clocks.answer})
        with Client("busy", connect=[endpoint], timeout_s=1.0) as client:
            with pytest.raises(ServiceError) as read:
                client.get_model()
            with pytest.raises(ServiceError) as change:
                client.spawn("relay", "r")
    said = str(read.value)
    assert said.startswith(f"no answer from manager 'busy' at {endpoint} to 'get_model' within 1 s (waited ")
    assert "--timeout" in said and "it only reads, so nothing was changed" in said
    assert read.value.details["reason"] == "timeout" and read.value.details["may_have_run"] is False
    assert read.value.details["link"] == "up" and "so the link is up: it is busy or stuck" in said and "is cut" not in said
    said = str(change.value)
    assert "to 'spawn' within 1 s" in said and "may still be carried out" in said and "check whether it was done (dyknow model)" in said
    assert change.value.details["may_have_run"] is True


@pytest.mark.process
@pytest.mark.timeout(120)
def test_a_fresh_client_finds_a_manager_that_is_there_every_time(
    manager_process: Callable[..., ManagerProcess], cli_process: Callable[..., CliProcess]
) -> None:
    """A call that does not find its service at once asks whether the manager is there, and ends
    at once when it is not (the next test). It must never say so of one that is: asked by a fresh
    client 20 times in a row, each manager answers, whether it announces itself (a liveliness
    token), does not (--alone: no token, its service only) or sits behind a router. (While the
    client's watch of the managers' tokens is on its way, Zenoh answered a liveliness query of
    that session from what it had heard so far: nothing, in 19 of 30 fresh sessions.)"""
    announced = manager_process(name="there")
    alone = manager_process("--alone", name="lonely")
    hub = f"tcp/127.0.0.1:{free_port()}"
    router = cli_process("router", "--listen", hub, "--json")
    assert router.line()["event"] == "ready"
    behind = manager_process("--connect", hub, name="behind")
    for name, endpoint in ((announced.name, announced.endpoint), (alone.name, alone.endpoint), (behind.name, hub)):
        for attempt in range(20):
            with Client(name, connect=[endpoint], timeout_s=10) as client:
                assert client.get_model()["manager"] == name, (name, attempt)


@pytest.mark.process
@pytest.mark.timeout(20)
def test_a_manager_not_there_is_said_at_once_naming_those_that_are(
    manager_process: Callable[..., ManagerProcess], cli_process: Callable[..., CliProcess]
) -> None:
    """The network's answer (which managers' tokens are up, whole) and a call that reached
    nothing: said at once, not after the timeout (60 s: the test's own timeout ends it first)."""
    from dyknow import ServiceError

    robot = manager_process(name="robot")
    with Client("robt", connect=[robot.endpoint], timeout_s=60) as client, pytest.raises(ServiceError) as misspelled:
        client.get_model()
    assert misspelled.value.details == {"reason": "no-such-manager", "managers": ["robot"]}
    assert str(misspelled.value).endswith("no manager 'robt' among those reachable (robot); expected --manager one of robot (did you mean 'robot'?)")
    hub = f"tcp/127.0.0.1:{free_port()}"
    router = cli_process("router", "--listen", hub, "--json")
    assert router.line()["event"] == "ready"
    with Client("robot", connect=[hub], timeout_s=60) as client, pytest.raises(ServiceError) as none:
        client.get_model()
    assert none.value.details == {"reason": "no-manager", "managers": []}
    assert str(none.value) == (
        f"cannot reach manager 'robot': linked to {hub}, but no manager is there (no manager's liveliness token is up); "
        f"expected a running manager (dyknow manager --name robot) that this endpoint reaches (--connect); "
        "or --wait S for one that is starting"
    )
    done = run_cli("model", "--manager", "robt", "--connect", robot.endpoint, "--timeout", "60")
    assert done.returncode == 1 and done.stderr.strip().endswith("expected --manager one of robot (did you mean 'robot'?)")
