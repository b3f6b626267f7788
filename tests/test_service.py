"""The services: one queryable per manager routes requests; refusals come back as typed errors."""

from __future__ import annotations

import json

import pytest

from dyknow import Manager, ServiceError, UnitError
from dyknow.service import MANAGER_SERVICES, UNIT_SERVICES
from dyknow.transport import Session, make_config


def _call(manager: Manager, key: str, payload: bytes) -> bytes:
    with Session(make_config(connect=manager.endpoints)) as session:
        return session.call(key, payload, timeout_s=5, what="test")


def test_every_service_answers(manager: Manager) -> None:
    assert json.loads(_call(manager, f"@dyknow/{manager.name}/get_model", b"{}"))["manager"] == manager.name
    manager.spawn("sink", "s")
    assert json.loads(_call(manager, f"@dyknow/{manager.name}/unit/s/get_config", b""))["in"] == f"dyknow/{manager.name}/s/in"
    assert set(MANAGER_SERVICES) >= {"spawn", "destroy", "get_model", "request", "release", "measure", "get_adaptations"}
    assert UNIT_SERVICES == ("get_config", "set_config", "get_statistics")


@pytest.mark.parametrize(
    ("path", "payload", "what"),
    [
        ("teleport", b"{}", "no service at '@dyknow/{m}/teleport' on manager '{m}'"),
        ("unit/s/explode", b"{}", "no service at '@dyknow/{m}/unit/s/explode' on manager '{m}'"),
        ("get_model", b"not json", "the request is not JSON"),
        ("get_model", b"[1, 2]", "the request is a JSON list"),
        ("spawn", b'{"label": "sink"}', "missing field 'name'"),
        ("spawn", b'{"label": "sink", "name": "s", "colour": 1}', "unknown field 'colour'"),
        ("spawn", b'{"label": "sink", "name": "s", "protected": "yes"}', "got 'yes'"),
    ],
)
def test_bad_requests_are_refused_with_a_reason(manager: Manager, path: str, payload: bytes, what: str) -> None:
    with pytest.raises(ServiceError) as refused:
        _call(manager, f"@dyknow/{manager.name}/{path}", payload)
    assert refused.value.kind == "ServiceError"
    assert str(refused.value.details["what"]).startswith(what.format(m=manager.name))
    if "no service" in what:
        assert "get_model" in str(refused.value.details["expected"]) and "unit/<name>/set_config" in str(refused.value.details["expected"])


def test_a_refusal_names_the_managers_error_class(manager: Manager) -> None:
    with pytest.raises(ServiceError) as refused:
        _call(manager, f"@dyknow/{manager.name}/destroy", b'{"name": "ghost"}')
    assert refused.value.kind == "UnitError" and refused.value.details["what"] == "no unit named 'ghost'"
    assert issubclass(UnitError, type(refused.value).__mro__[1])  # both are DyKnowErrors


def test_a_manager_without_services_is_not_reachable(make_manager: object) -> None:
    quiet = make_manager(serve=False)  # type: ignore[operator]
    with Session(make_config(connect=quiet.endpoints)) as session, pytest.raises(ServiceError, match="nothing serves"):
        session.call(f"@dyknow/{quiet.name}/get_model", b"{}", timeout_s=0.5, what="test")
