"""Fuzzing the services: any request is answered or refused with a DyKnowError, and the manager lives.

Three layers: the request checks alone with many examples (fast), a systematic sweep of every
field of every service with a value of every JSON type, and fewer examples over a real Zenoh
session to a real manager. Derandomized and bounded for CI; ``tools/fuzz.py --targets
request,service`` runs the same properties randomized for longer.
"""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import example, given

from dyknow import Client, Manager, ServiceError
from dyknow.security import Limits
from dyknow.service import SCHEMAS, check_request
from dyknow.testing.fuzzing import (
    JSON_PROBES,
    ServiceCall,
    check_request_payload,
    check_service_call,
    derandomized,
    service_calls,
)
from dyknow.transport import Session, make_config


@derandomized(2000)
@given(service_calls())
@example(ServiceCall("spawn", b'{"label": "relay", "name": "r", "params": {"a": Infinity}}'))
@example(ServiceCall("get_model", b"[" * 10_000 + b"]" * 10_000))
@example(ServiceCall("measure", b'{"name": "battery", "value": NaN}'))
@example(ServiceCall("set_config", '{"bindings": {"in": "a/b"}}'.encode("utf-16"), "sink"))
def test_any_payload_is_checked_into_its_fields_or_refused(call: ServiceCall) -> None:
    check_request_payload(call)


# ---------------------------------------------------------------------- the systematic sweep

# A valid value of each field (so that the fields checked before the one under test pass).
VALID: dict[str, Any] = {
    "xml": "<transformation/>",
    "path": "mine.xml",
    "label": "relay",
    "name": "r1",
    "protected": True,
    "force": True,
    "robustness": True,
    "params": {},
    "bindings": {},
    "owner": "m1",
    "tag": "BallPosition(field)",
    "key": "dyknow/m1/r1/out",
    "value": 0.5,
    "standby": "warm",
    "page": {},
    "formula": "A > 1",
    "reorder_ms": 5,
    "brief": True,
    "health": True,
    "require": [],
    "holder": "0123456789abcdef",
}
# Which of the JSON_PROBES each field takes; every other probe is refused naming the field.
TEXT = {'"text"'}
ACCEPTS: dict[tuple[str, str], set[str]] = {
    ("add_transformation", "xml"): TEXT,
    ("add_transformation", "path"): TEXT,
    ("remove_transformation", "label"): TEXT,
    ("spawn", "label"): TEXT,
    ("spawn", "name"): TEXT,
    ("spawn", "protected"): {"true"},
    ("spawn", "params"): {"{}"},
    ("spawn", "bindings"): {"{}"},
    ("spawn", "owner"): TEXT,
    ("destroy", "name"): TEXT,
    ("destroy", "force"): {"true"},
    ("request", "tag"): TEXT,
    ("request", "standby"): set(),  # only "none" or "warm", none of the probes
    ("release", "key"): TEXT,
    ("measure", "name"): TEXT,
    ("measure", "value"): {"0", "1.5", "10**30", '"text"'},
    ("set_config", "bindings"): {"{}"},
    ("get_model", "page"): {"{}"},
    ("monitor", "formula"): TEXT,
    ("monitor", "reorder_ms"): {"0", "1.5"},
    ("monitor", "bindings"): {"{}"},
    ("monitor", "robustness"): {"true"},
    ("request", "require"): {"[]"},
    ("request", "holder"): set(),  # only hexadecimal client ids, none of the probes
    ("release", "holder"): set(),
    ("release", "force"): {"true"},
    ("monitor", "holder"): set(),
    ("get_summary", "brief"): {"true"},
    ("get_summary", "health"): {"true"},
}
SWEEP = [(service, field, probe) for service, fields in SCHEMAS.items() for field in fields for probe in JSON_PROBES]


def test_the_sweep_covers_every_field_of_every_service() -> None:
    assert set(ACCEPTS) == {(service, field) for service, fields in SCHEMAS.items() for field in fields}
    assert set(VALID) == {field for fields in SCHEMAS.values() for field in fields}


@pytest.mark.parametrize(("service", "field", "probe"), SWEEP, ids=[f"{s}.{f}={p}" for s, f, p in SWEEP])
def test_every_field_refuses_every_json_type_it_does_not_take_naming_the_field(service: str, field: str, probe: str) -> None:
    request = {name: VALID[name] for name in SCHEMAS[service]}
    request[field] = JSON_PROBES[probe]
    if probe in ACCEPTS[(service, field)]:
        assert check_request(service, request, Limits())[field] == JSON_PROBES[probe]
        return
    with pytest.raises(ServiceError) as refused:
        check_request(service, request, Limits())
    assert refused.value.where == f"field {field!r}"
    assert f"field {field!r}: got " in str(refused.value) and "; expected " in str(refused.value)


@pytest.mark.parametrize(
    ("service", "field"), [(s, f) for s, fields in SCHEMAS.items() for f, (required, _) in fields.items() if required]
)
def test_every_required_field_missing_is_refused_naming_it(service: str, field: str) -> None:
    request = {name: VALID[name] for name in SCHEMAS[service] if name != field}
    with pytest.raises(ServiceError, match=f"missing field {field!r}"):
        check_request(service, request, Limits())


# ---------------------------------------------------------------------- over Zenoh, to a real manager


@pytest.fixture
def target(manager: Manager) -> Any:
    """The manager with a protected unit 's' for the unit services, and a session to call it."""
    manager.spawn("sink", "s", protected=True)
    with Session(make_config(connect=manager.endpoints)) as session:
        yield manager, session


def test_any_call_over_zenoh_is_answered_or_refused_and_the_manager_lives(target: Any) -> None:
    manager, session = target

    @derandomized(300)
    @given(service_calls(units=("s",)))
    @example(ServiceCall("spawn", b'{"label": "failing", "name": "f", "params": {"fail_at": 1e30}}'))
    @example(ServiceCall("add_transformation", json.dumps({"xml": "<transformation><priority>" + "9" * 5000 + "</priority></transformation>"}).encode()))
    @example(ServiceCall("set_config", b'{"bindings": {"in": "**"}}', "s"))
    @example(ServiceCall("destroy", b'{"name": "s"}'))
    def call_and_check(call: ServiceCall) -> None:
        check_service_call(session, manager.name, call)  # get_model answers after each call too
        if "s" not in {unit.name for unit in manager.units()}:
            # protected: only a destroy with force removes it (this manager has no roles: anyone may)
            assert call.service == "destroy" and json.loads(call.payload) == {"name": "s", "force": True}, call
            manager.spawn("sink", "s", protected=True)

    call_and_check()
    with Client(manager.name, session=session) as client:
        model = client.get_model()
    assert model["manager"] == manager.name
    assert "s" in {unit["name"] for unit in model["units"]}
