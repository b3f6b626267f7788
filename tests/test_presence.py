"""dyknow.presence: the losses the managers remember, merged as a tool shows them (one per manager)."""

from __future__ import annotations

from dyknow import keys
from dyknow.presence import THIS_CLIENT, Loss, merge


def test_one_loss_per_manager_the_earliest_with_everyone_who_saw_it_and_none_of_those_back() -> None:
    reports = [
        (THIS_CLIENT, [{"manager": "robot", "since_ns": 300, "why": keys.LOSS_VANISHED}]),
        ("station", [{"manager": "robot", "since_ns": 100, "why": keys.LOSS_VANISHED}, {"manager": "field", "since_ns": 5, "why": keys.LOSS_STOPPED}]),
        ("dock", [{"manager": "robot", "since_ns": 200, "why": keys.LOSS_STOPPED}, {"manager": "arm", "since_ns": 7, "why": keys.LOSS_VANISHED}]),
    ]
    merged = merge(reports, up=["arm"])
    assert list(merged) == ["field", "robot"]  # by name; the arm is back
    assert merged["robot"] == Loss("robot", 100, keys.LOSS_VANISHED, (THIS_CLIENT, "station", "dock"))
    assert merged["field"].stopped and not merged["robot"].stopped


def test_a_loss_said_names_when_why_and_who_saw_it() -> None:
    loss = Loss("robot", 1_000_000_000, keys.LOSS_VANISHED, ("station",))
    said = loss.said(now_ns=13_300_000_000)
    assert said.startswith("manager 'robot' is LOST since ") and "(12.3 s ago, as station saw it): its liveliness token went away" in said
    assert "as a, b and c saw it" in Loss("robot", 0, "", ("a", "b", "c")).said(now_ns=0)
    assert "as a, b and 3 others saw it" in Loss("robot", 0, "", ("a", "b", "c", "d", "e")).said(now_ns=0)
    error = loss.error("tls/10.1.0.1:7447")
    assert error.details["reason"] == "lost" and error.details["seen_by"] == ["station"] and "the link to it" in str(error)
