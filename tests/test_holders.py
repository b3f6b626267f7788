"""Requests have owners: a client's requests end a grace period after the client is gone, unless
it kept them; the model shows who holds each; hostile holder ids are refused."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from typing import Any

import pytest

from dyknow import AccessError, Client, FormulaError, Limits, Manager, PlanningError, ServiceError
from dyknow.holders import MAX_HOLDERS, Holders
from dyknow.testing import SCENARIO_SPECS
from dyknow.transport import Session, make_config
from tests.conftest import REPO, free_port, run_cli, subprocess_env, wait_until

TAG = "BallPosition(field)"
ONTOLOGY = REPO / "specs" / "dyknow.ttl"


@pytest.fixture
def manager(make_manager: Callable[..., Manager]) -> Manager:
    return make_manager("owners", specs=[SCENARIO_SPECS], ontology=[ONTOLOGY], client_grace_s=0.5)


#: How long a call may take: a request planned beside CPU hogs took over the client's default 5 s once
#: (a slow manager is not what these tests are about).
CALL_S = 30.0


def _request(manager: Manager) -> dict[str, object] | None:
    return next((r.to_dict() for r in manager.requests() if r.tag == TAG), None)


def test_a_closed_clients_request_ends_after_the_grace_and_a_kept_one_stays(manager: Manager) -> None:
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as client:
        key = client.request(TAG)
        held = _request(manager)
        assert held is not None and held["references"] == 1 and held["kept"] == 0
        assert list(held["holders"].values()) == [1]  # type: ignore[union-attr]
    # (released on the holders' thread: the request goes first, then the units only it used)
    wait_until(lambda: _request(manager) is None and manager.units() == [], "the request of the closed client to be released, its units gone")
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as client:
        assert client.request(TAG, keep=True) == key
    assert not wait_until_false(lambda: _request(manager) is not None, seconds=1.5)  # well past the grace
    assert _request(manager) == {**_request(manager), "references": 1, "kept": 1, "holders": {}}  # type: ignore[dict-item]


def wait_until_false(condition: Callable[[], bool], seconds: float) -> bool:
    """Whether ``condition`` turned false within ``seconds`` (it should not)."""
    try:
        wait_until(lambda: not condition(), "never", timeout_s=seconds)
    except AssertionError:
        return False
    return True


def test_one_client_gone_leaves_the_others_reference(manager: Manager) -> None:
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as staying:  # (the first request plans and spawns)
        with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as leaving:
            key = staying.request(TAG)
            assert leaving.request(TAG) == key
            assert _request(manager)["references"] == 2  # type: ignore[index]
        wait_until(lambda: _request(manager)["references"] == 1, "the gone client's reference released")  # type: ignore[index]
        assert len(_request(manager)["holders"]) == 1  # type: ignore[arg-type]
        assert staying.release(key) == 0
    assert _request(manager) is None


@pytest.mark.process
def test_a_crashed_clients_request_ends_too(manager: Manager) -> None:
    script = (
        "import sys, time\nfrom dyknow import Client\n"
        f"c = Client({manager.name!r}, connect=[sys.argv[1]], lease_ms=1000)\nprint(c.request({TAG!r}), flush=True)\ntime.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script, manager.endpoints[0]], stdout=subprocess.PIPE, text=True, env=subprocess_env())
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip().endswith("requests/BallPosition(field)")
        assert _request(manager) is not None
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        wait_until(lambda: _request(manager) is None, "the crashed client's request released (its lease, then the grace)", timeout_s=30)
    finally:
        proc.kill()
        proc.communicate(timeout=10)


def test_a_bad_holder_id_is_refused_and_takes_nothing(manager: Manager) -> None:
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as client:
        with pytest.raises(ServiceError, match=r"field .holder.: got .\.\./\.\..; expected a client id: 8 to 32 hexadecimal digits"):
            client.call_manager(manager.name, "request", {"tag": TAG, "holder": "../.."})
    assert _request(manager) is None and manager.units() == []


@pytest.mark.process
def test_the_cli_keeps_its_request_and_says_how_to_release_it(make_manager: Callable[..., Manager]) -> None:
    manager = make_manager("kept", specs=[SCENARIO_SPECS], ontology=[ONTOLOGY], client_grace_s=0.5)
    conn = ["--connect", manager.endpoints[0], "--manager", manager.name]
    result = run_cli("request", TAG, *conn)
    key = result.stdout.strip()
    assert result.returncode == 0 and f"dyknow: the request is kept until released: dyknow release '{key}' --manager kept" in result.stderr
    assert not wait_until_false(lambda: _request(manager) is not None, seconds=1.5)
    model = json.loads(run_cli("model", "--json", *conn).stdout)
    assert model["requests"][0]["kept"] == 1 and model["requests"][0]["holders"] == {}


@pytest.mark.process
def test_the_manager_command_sets_the_grace(manager_process: Callable[..., Any]) -> None:
    proc = manager_process("--specs", str(SCENARIO_SPECS), "--ontology", str(ONTOLOGY), "--client-grace", "0")

    def requests() -> list[dict[str, Any]]:
        with Client(proc.name, connect=[proc.endpoint]) as looker:
            return list(looker.get_model()["requests"])

    with Client(proc.name, connect=[proc.endpoint]) as client:
        client.request(TAG)
        assert [r["tag"] for r in requests()] == [TAG]
    # released as soon as the client's token is gone (the default grace would keep it 10 s)
    wait_until(lambda: requests() == [], "the closed client's request released at once", timeout_s=5)


def test_a_holder_that_never_declares_its_token_is_released_once_it_had_time_to(manager: Manager) -> None:
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as client:
        client.call_manager(manager.name, "request", {"tag": TAG, "holder": "0123456789abcdef"})  # and no token, ever
        assert not wait_until_false(lambda: _request(manager) is not None, seconds=1.5)  # past the grace: its token may be on its way
        wait_until(lambda: _request(manager) is None, "the request of a holder without a token released", timeout_s=15)


# ---------------------------------------------------------------------- each gives back only its own


def test_a_client_may_not_release_another_clients_request(manager: Manager) -> None:
    """Another client (no roles here, so no certificate to tell callers apart: the client id
    does) cannot give back the first one's reference, with its own id or none; forcing it can
    (without roles every caller may what an admin may), and takes every reference."""
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as holder, Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as other:
        key = holder.request(TAG)
        units = {u.name for u in manager.units()}
        for attempt in (lambda: other.release(key), lambda: other.call_manager(manager.name, "release", {"key": key, "holder": "0123456789abcdef"})):
            with pytest.raises(AccessError, match=r"holds no reference to the request on 'dyknow/owners/requests/BallPosition\(field\)' \(its references: client [0-9a-f]+\)"):
                attempt()
        assert _request(manager)["references"] == 1 and {u.name for u in manager.units()} == units  # type: ignore[index]
        other.request(TAG, keep=True)
        assert other.release(key) == 1  # its own kept reference, not the holder's
        assert _request(manager)["holders"] == {holder._holder: 1}  # type: ignore[index]
        assert other.release(key, force=True) == 0
        assert _request(manager) is None


def test_a_requirement_goes_with_the_reference_that_added_it(manager: Manager) -> None:
    """A second client shares the request and requires a formula of it; when it releases its
    reference the requirement and its monitor go, and the first client's request runs on
    without it. A requirement both references added stays until both are gone."""
    formula = f"{TAG}.x < -1000"
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as first, Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as second:
        key = first.request(TAG)
        second.request(TAG, require=[formula])
        held = _request(manager)
        assert held is not None and held["requirements"] == [formula] and held["references"] == 2
        watchers = {u.name for u in manager.units()} - {u.name for u in manager.units() if "require" not in u.name}
        assert len(watchers) == 1
        assert second.release(key) == 1
        assert _request(manager)["requirements"] == []  # type: ignore[index]
        assert not watchers & {u.name for u in manager.units()}
        first.request(TAG, require=[formula])
        second.request(TAG, require=[formula])
        assert first.release(key) == 2 and _request(manager)["requirements"] == [formula]  # type: ignore[index]
        assert second.release(key) == 1 and _request(manager)["requirements"] == []  # type: ignore[index]


def test_a_failed_call_leaves_nothing_behind(manager: Manager) -> None:
    """A requirement whose term nothing provides fails the call: on a new request nothing of
    it stays, on a shared one no reference is added, and five failures leak nothing."""
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as client:
        for _ in range(5):
            with pytest.raises(PlanningError, match="Unheard"):
                client.request(TAG, require=["Unheard(x) > 0"])
        assert _request(manager) is None and manager.units() == []
        key = client.request(TAG)
        units = {u.name for u in manager.units()}
        for _ in range(5):
            with pytest.raises(PlanningError, match="Unheard"):
                client.request(TAG, require=[f"{TAG}.x > 0", "Unheard(x) > 0"])
        deep = " or ".join(f"P > {i}" for i in range(830))  # the report's 830-deep chain (9,010 characters)
        for _ in range(5):
            with pytest.raises(FormulaError, match="nodes"):
                client.request(TAG, require=[deep])
            with pytest.raises(FormulaError, match="nodes"):
                client.monitor(deep)
        held = _request(manager)
        assert held is not None and held["references"] == 1 and held["requirements"] == [] and {u.name for u in manager.units()} == units
        assert manager.monitors() == []
        assert client.release(key) == 0


def test_a_monitor_has_a_holder_too(manager: Manager) -> None:
    """A client's monitor is its own: another client cannot release it by its key, and it ends
    a grace period after its client is gone; a kept one stays until released."""
    formula = f"historically[0, 1s] {TAG}.x > 0"
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as other:
        with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as owner:
            key = owner.monitor(formula)
            with pytest.raises(AccessError, match=f"may not release the monitor on '{key}'"):
                other.release(key)
            assert [m.key for m in manager.monitors()] == [key]
        wait_until(lambda: manager.monitors() == [] and _request(manager) is None, "the closed client's monitor released, its term too")
        kept = other.monitor(formula, keep=True)
    assert not wait_until_false(lambda: [m.key for m in manager.monitors()] == [kept], seconds=1.5)
    assert manager.release(kept) == 0 and manager.monitors() == []


# ---------------------------------------------------------------------- no caller fills a shared request


def test_a_client_takes_at_most_its_share_of_a_request(make_manager: Callable[..., Manager]) -> None:
    """Without roles a caller is its client (issue 51): one client's references to a request are
    bounded (here 3), refused past it naming the bound, and the others still share the request;
    references kept without a client id count as one caller's."""
    manager = make_manager("share", specs=[SCENARIO_SPECS], ontology=[ONTOLOGY], limits=Limits(max_references_per_caller=3))
    with Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as greedy, Client(manager.name, connect=manager.endpoints, timeout_s=CALL_S) as other:
        key = greedy.request(TAG)
        assert greedy.request(TAG) == key and greedy.request(TAG) == key
        said = rf"client [0-9a-f]+ holds 3 references to the request on '{re.escape(key)}' already, its most; expected at most 3 references per caller"
        with pytest.raises(AccessError, match=said):
            greedy.request(TAG)
        assert other.request(TAG) == key and _request(manager)["references"] == 4  # type: ignore[index]
        for _ in range(3):
            other.request(TAG, keep=True)
        with pytest.raises(AccessError, match=r"a caller without a client id holds 3 references"):
            greedy.request(TAG, keep=True)
        assert greedy.release(key) == 6 and greedy.request(TAG) == key  # a reference given back makes room


def test_a_request_counts_its_callers_not_their_clients() -> None:
    """The holders a request keeps are bounded by callers: one caller's many clients never fill
    it for the others (issue 51: a requester's 1,000 client ids refused everyone else); past
    MAX_HOLDERS callers the next one is refused, naming the request."""
    key = "dyknow/m/requests/Ticks"
    with Session(make_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as session, Holders(session, "m", lambda k, h: None, grace_s=60) as holders:
        for i in range(2 * MAX_HOLDERS):
            holders.took(key, f"{i:032x}", "greedy")
        for i in range(MAX_HOLDERS - 1):
            holders.took(key, f"{i:016x}", None)  # (without roles each client is a caller of its own)
        with pytest.raises(ServiceError, match=f"request '{key}' has the clients of {MAX_HOLDERS} callers already"):
            holders.took(key, "ffff0000", "latecomer")
        holders.took(key, f"{2 * MAX_HOLDERS:032x}", "greedy")  # a caller already there: its share is the manager's to bound
        holders.gave_back(key, f"{0:016x}")
        holders.took(key, "ffff0000", "latecomer")
        assert len(holders.holders(key)) == 2 * MAX_HOLDERS + 1 + MAX_HOLDERS - 1
