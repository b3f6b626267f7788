"""The replies a client takes: an honest manager's pass whole; any other is refused, naming the
manager, the service, the field and what was expected (issue 51)."""

from __future__ import annotations

import json
from typing import Any

import pytest

from dyknow import Client, Manager, replies
from dyknow.errors import ServiceError
from tests.conftest import wait_until


def _model(**changes: Any) -> dict[str, Any]:
    unit = {"name": "u1", "label": "relay", "state": "running", "protected": False, "bindings": {"in": "a", "out": "b"},
            "executor": "shared", "error": None, "traceback": None}  # fmt: skip
    model = {"manager": "evil", "units": [unit], "specs": [{"label": "relay"}], "requests": [{"tag": "T", "key": "k", "state": "active"}],
             "lost": [{"manager": "gone", "since_ns": 1, "why": "it stopped"}], "clocks": {"clock": "0000abcd"}, "next": None}  # fmt: skip
    model.update(changes)
    return model


def _unit(**changes: Any) -> list[dict[str, Any]]:
    return [{**_model()["units"][0], **changes}]


WRONG = [
    ([], "reply is a JSON array of 0 entries; expected a JSON object with the fields manager, units, specs"),
    (_model(units="x"), "reply.units is 'x'; expected a JSON array"),
    (_model(units=[{"name": "u1"}]), "reply.units[0].label is missing"),
    (_model(units=_unit(name="\x1b[2J")), r"reply.units[0].name is '\x1b[2J', not a unit name; expected letters, digits"),
    (_model(units=_unit(name="a\u202etxt")), r"reply.units[0].name is 'a\u202etxt', not a unit name"),
    (_model(units=_unit(protected="yes")), "reply.units[0].protected is 'yes'; expected true or false"),
    (_model(units=_unit(bindings={"out": 5})), "reply.units[0].bindings['out'] is 5; expected text"),
    (_model(manager="robot"), "reply.manager is 'robot', another manager's name; expected its own name, 'evil'"),
    (_model(manager="\x1b]0;x\x07"), r"reply.manager is '\x1b]0;x\x07', not a manager name"),
    (_model(lost=[{"manager": "gone", "since_ns": 10**30, "why": ""}]), "reply.lost[0].since_ns is 1000000000000000000000000000000"),
    (_model(next={"units": "2", "specs": 0}), "reply.next.units is '2'; expected a whole number"),
]


@pytest.mark.parametrize(("reply", "said"), WRONG)
def test_a_model_of_the_wrong_shape_is_refused_naming_the_field(reply: Any, said: str) -> None:
    with pytest.raises(ServiceError) as refused:
        replies.check_reply(reply, "evil", "get_model")
    assert str(refused.value).startswith(f"the reply of manager 'evil' to get_model: {said}"), str(refused.value)
    assert refused.value.details == {"reason": "malformed", "manager": "evil", "call": "get_model"}
    assert str(refused.value).isprintable()  # (what it quotes is escaped)


def test_a_model_of_the_right_shape_passes_whole_with_fields_a_newer_manager_adds() -> None:
    model = _model(units=_unit(something_new=[1, {"x": None}]), also_new=True)
    assert replies.check_reply(model, "evil", "get_model") is model


@pytest.mark.parametrize(
    ("data", "said"),
    [
        (b"[" * 100_000 + b"]" * 100_000, "it nests deeper than 64 levels; expected at most 64 levels (MAX_REPLY_DEPTH)"),
        (b"[" * 65 + b"]" * 65, "it nests deeper than 64 levels"),
        (b'{"a": \xff}', "it is not JSON (8 bytes: "),
        (b"", "it is not JSON (0 bytes: "),
    ],
)
def test_a_reply_that_is_not_json_or_nests_too_deep_is_refused(data: bytes, said: str) -> None:
    with pytest.raises(ServiceError) as refused:
        replies.decode_reply(data, "evil", "get_model")
    assert str(refused.value).startswith(f"the reply of manager 'evil' to get_model: {said}"), str(refused.value)
    assert refused.value.details["reason"] == "malformed"


def test_nan_and_infinity_read_as_null_so_what_is_printed_stays_json() -> None:
    reply = replies.decode_reply(b'{"a": NaN, "b": [Infinity, -Infinity], "c": 1e400}', "evil", "get_metrics")
    assert reply["a"] is None and reply["b"] == [None, None]
    json.dumps({k: v for k, v in reply.items() if k != "c"}, allow_nan=False)
    with pytest.raises(ServiceError, match=r"reply.time_ns is null; expected a time in ns"):  # (what is read must be a number)
        replies.check_reply({"manager": "evil", "time_ns": reply["a"]}, "evil", "get_metrics")
    with pytest.raises(ServiceError, match=r"reply.cpu_s is inf; expected a number under 10\*\*15"):  # (1e400 parses as inf)
        replies.check_reply({"manager": "evil", "time_ns": 1, "cpu_s": reply["c"]}, "evil", "get_metrics")


def test_every_reply_of_an_honest_manager_passes(make_manager: Any) -> None:
    """Every service the client reads, called on a real manager with data flowing (input ports
    have their latency and hop figures), a request and a monitor open: nothing is refused."""
    manager: Manager = make_manager()
    with Client(manager.name, connect=manager.endpoints, timeout_s=10) as client:
        assert client.spawn("periodic-source", "src", params={"rate_hz": 200})["state"] == "running"
        client.spawn("relay", "r", bindings={"in": f"dyknow/{manager.name}/src/out"})
        wait_until(lambda: client.get_statistics("r")["ports"]["in"]["messages"] > 2, "data through the relay")
        key = client.request("Ticks")
        monitor = client.monitor("historically[0, 1s] Ticks.value > 0")
        model = client.get_model()
        assert {"r", "src"} <= {u["name"] for u in model["units"]} and key in [r["key"] for r in model["requests"]]
        metrics = client.call_manager(manager.name, "get_metrics", {})
        assert {"src", "r"} <= {u["name"] for u in metrics["units"]}
        assert client.get_load()["max_lanes"] >= 1
        assert client.get_adaptations() == []
        assert client.get_config("r")["in"] == f"dyknow/{manager.name}/src/out"
        assert client.set_config("r", {"out": "elsewhere/out"})["out"] == "elsewhere/out"
        assert client.managers()[0]["manager"] == manager.name
        assert client.get_federated_model()["refused"] == {}
        assert client.release(monitor) == 0 and client.release(key) == 0
