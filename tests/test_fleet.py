"""A fleet: what one manager pays must not grow with the number of managers (issue 40).

Thirty managers in this process on loopback, each its own Zenoh session: a planner finds the
two providers of a tag by their offers and reads no other summary; the listing pages through
the fleet; what the others announce is bounded.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable

import pytest

from dyknow import Client, Manager, keys
from dyknow.federation import MAX_CANDIDATES, MAX_OFFERS
from dyknow.transport import LivelinessToken, Session, make_config
from tests.conftest import free_port, run_cli, wait_until

FLEET = 30


def _offering(tag: str, label: str | None = None) -> str:
    """A spec of an idle source whose output carries ``tag``."""
    return f"""<transformations><transformation><label>{label or "offer-" + tag.lower()}</label><source>dyknow.testing:Source</source>
  <ports><port type="out">out</port></ports><tags><tag port="out">{tag}</tag></tags></transformation></transformations>"""


def _fleet(make_manager: Callable[..., Manager], providers: dict[str, str]) -> tuple[str, list[Manager]]:
    """``FLEET`` managers ``m00`` (the hub, the requester) to ``m29``; ``providers``: name -> a tag
    it offers besides the generic specs every one has. Returns the hub's endpoint and the fleet
    once ``m00`` sees every other's token. The others dial the hub and listen nowhere (a star,
    as behind a router: 30 routers of one process that mesh make Zenoh 1.10.2 panic as they close)."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    fleet = [make_manager("m00", listen=[hub], dwell_s=0.2)]
    for i in range(1, FLEET):
        name = f"m{i:02d}"
        fleet.append(make_manager(name, listen=[], connect=[hub], dwell_s=0.2))
        if name in providers:
            fleet[-1].add_transformation(_offering(providers[name]))
    wait_until(lambda: len(fleet[0].reachable()) == FLEET - 1, "m00 to see the whole fleet")
    return hub, fleet


def _provider(manager: Manager, key: str) -> str:
    (labels,) = [info.labels for info in manager.requests() if info.key == key]
    return next(label.rpartition("@")[2] for label in labels if "@" in label)


def test_a_provider_found_among_30_managers_of_which_2_offer_the_tag(make_manager: Callable[..., Manager]) -> None:
    """``m00`` requests ``Rare``, which only m07 and m23 offer: it finds both with one query,
    reads their summaries and no other, plans on one; when that one stops, the request moves to
    the other on the same key."""
    _, fleet = _fleet(make_manager, {"m07": "Rare", "m23": "Rare"})
    m00 = fleet[0]
    assert m00.peers() == {}  # nothing read before a plan needs it
    key = m00.request("Rare")
    first = _provider(m00, key)
    assert first in ("m07", "m23")
    assert set(m00.peers()) == {"m07", "m23"}  # the candidates' summaries only: not 29
    other = "m23" if first == "m07" else "m07"
    next(m for m in fleet if m.name == first).close()
    wait_until(lambda: _provider(m00, key) == other, f"the request to move to {other}")
    assert [info.key for info in m00.requests()] == [key]


@pytest.mark.process
def test_a_fleet_is_listed_in_pages(make_manager: Callable[..., Manager]) -> None:
    """``Client.managers_page`` and ``dyknow managers --limit/--after/--match`` page through 30
    managers: every one listed once, a page at a time, each page asking only its own managers."""
    hub, fleet = _fleet(make_manager, {})
    names = sorted(m.name for m in fleet)
    with Client("m00", connect=[hub]) as client:
        wait_until(lambda: len(client.manager_names()) == FLEET, "the client to see the fleet")
        seen: list[str] = []
        after = None
        pages = 0
        while True:
            page = client.managers_page(match="*", limit=7, after=after)
            assert page["total"] == FLEET and len(page["managers"]) <= 7
            seen.extend(m["manager"] for m in page["managers"])
            pages += 1
            after = page["next"]
            if after is None:
                break
        assert seen == names and pages == 5
        assert [m["manager"] for m in client.managers()] == names  # (the whole list, read in pages)
        brief = client.managers(match="m0*", limit=3)
        assert [(m["manager"], m["specs"], m["units"]) for m in brief] == [("m00", len(fleet[0].library), 0), ("m01", len(fleet[1].library), 0), ("m02", len(fleet[2].library), 0)]
        assert client.manager_names(match=["m1?", "m29"]) == [f"m1{i}" for i in range(10)] + ["m29"]
        models = client.get_federated_model(match="m2*", limit=4, after="m21")
        assert [m["manager"] for m in models["managers"]] == ["m22", "m23", "m24", "m25"] and models["next"] == "m25"
    listed = run_cli("managers", "--connect", hub, "--json", "--match", "m1*", "--limit", "4", "--after", "m13")
    assert listed.returncode == 0, listed.stderr
    assert [m["manager"] for m in json.loads(listed.stdout)] == ["m14", "m15", "m16", "m17"]
    assert "4 of 10 managers listed; continue with --after m17" in listed.stderr
    last = run_cli("managers", "--connect", hub, "--json", "--match", "m1*", "--after", "m17")
    assert [m["manager"] for m in json.loads(last.stdout)] == ["m18", "m19"] and "continue" not in last.stderr
    bad = run_cli("managers", "--connect", hub, "--match", "m/1")
    assert bad.returncode != 0 and "manager pattern 'm/1' cannot match a manager name" in bad.stderr


def test_offers_and_fake_providers_are_bounded(make_manager: Callable[..., Manager], caplog: pytest.LogCaptureFixture) -> None:
    """A manager whose library offers 1,500 tags announces 1,024 of them (a log line names it);
    40 fake managers that offer the tag a running request uses are followed at most 16 per tag
    (a log line names the tag), the request stays where it runs and a new one is planned; a
    newcomer asking who offers that tag reads at most 16 candidates (a log line says so), the real
    one among them."""
    caplog.set_level(logging.WARNING, logger="dyknow.federation")
    hub = f"tcp/127.0.0.1:{free_port()}"
    requester = make_manager("req", listen=[hub])
    many = "".join(f'<tag port="out">Many{i:04d}</tag>' for i in range(1500))
    big = make_manager("big", listen=[], connect=[hub], specs=[])
    big.add_transformation(f"""<transformations><transformation><label>many</label><source>dyknow.testing:Source</source>
      <ports><port type="out">out</port></ports><tags>{many}</tags></transformation></transformations>""")
    real = make_manager("real", listen=[], connect=[hub])
    real.add_transformation(_offering("Wanted"))
    wait_until(lambda: any("manager 'big' offers 1500 tags; announces 1024 of them" in r.getMessage() for r in caplog.records), "big's bound")
    with Session(make_config(connect=[hub])) as probe:
        wait_until(lambda: len(probe.alive("@dyknow/offers/**/big", timeout_s=0.5)) == MAX_OFFERS, "big's offers")
    wait_until(lambda: {"big", "real"} <= requester.reachable(), "the requester to see both")
    wanted = requester.request("Wanted")
    assert _provider(requester, wanted) == "real"
    with Session(make_config(connect=[hub])) as attacker:  # 40 managers that do not exist offer it too
        held = [attacker.declare_liveliness_token(keys.manager_token(f"fake{i:02d}")) for i in range(40)]
        held += [attacker.declare_liveliness_token(keys.offer_token("Wanted", (), f"fake{i:02d}")) for i in range(40)]
        wait_until(lambda: any(f"more than {MAX_CANDIDATES} managers offer @dyknow/offers/Wanted/()/*" in r.getMessage() for r in caplog.records),
                   "the requester's bound on candidates")  # fmt: skip
        many = requester.request("Many0000")  # planned while the fake candidates are asked in vain
        assert _provider(requester, many) == "big" and _provider(requester, wanted) == "real"
        assert set(requester.peers()) == {"big", "real"}  # no fake gave a summary
        newcomer = make_manager("newcomer", listen=[], connect=[hub], specs=[])
        offers = keys.offers_pattern("Wanted", ())
        wait_until(lambda: len(newcomer.session.alive(offers, timeout_s=0.5)) == 41, "the newcomer's session to know the 41 offers")
        came = newcomer.request("Wanted")  # the real provider answers for its offer: among the 16 chosen (issue 51)
        assert _provider(newcomer, came) == "real" and set(newcomer.peers()) == {"real"}
        said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("directory of 'newcomer'")]
        assert any(f"{MAX_CANDIDATES}" in line and "managers offer @dyknow/offers/Wanted/()/*" in line for line in said), said
        for entity in held:
            entity.undeclare()
    assert {info.key for info in requester.requests()} == {wanted, many}  # what ran before runs on


def _threads() -> int:
    """The threads of this process (Zenoh's and Python's)."""
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("Threads:"))


def test_offers_of_names_that_answer_for_nothing_never_hide_a_real_provider(make_manager: Callable[..., Manager]) -> None:
    """Issue 51: 300 managers that do not exist offer the tag (a token each, and a manager token),
    declared before the one real provider starts: a liveliness query finds them all, in an order
    that put the real one past the 64 answers kept (4 of 4 requests said "nothing provides").
    The managers that answer for their offers are asked too, and come first: the request is
    planned on the real provider; the fakes followed meanwhile (at most 16) cost no thread each."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    make_manager("hub", listen=[hub], specs=[])
    with Session(make_config(connect=[hub])) as attacker:
        held = [attacker.declare_liveliness_token(keys.offer_token("Wanted", (), f"fake{i:03d}")) for i in range(300)]
        held += [attacker.declare_liveliness_token(keys.manager_token(f"fake{i:03d}")) for i in range(300)]
        real = make_manager("real", listen=[], connect=[hub])
        real.add_transformation(_offering("Wanted"))
        newcomer = make_manager("newcomer", listen=[], connect=[hub], specs=[])
        offers = keys.offers_pattern("Wanted", ())
        wait_until(lambda: len(newcomer.session.alive(offers, timeout_s=0.5)) == 301, "the newcomer's session to know the 301 offers")
        threads = _threads()
        key = newcomer.request("Wanted")
        assert _provider(newcomer, key) == "real"
        directory = newcomer.directory
        assert directory is not None and "real" in directory.followed() and len(directory.followed()) <= MAX_CANDIDATES
        # three watches per manager followed, each a thread of its own before: 16 fakes, 48 threads
        assert _threads() - threads < 24, (threads, _threads())
        for entity in held:
            entity.undeclare()


def test_a_candidate_that_never_gives_its_summary_is_let_go_and_followed_again_when_it_starts_anew(monkeypatch: pytest.MonkeyPatch) -> None:
    """A token with nobody behind it (its summary never comes), found as the provider of a tag a
    plan needs, is let go after the asks in vain (here 2 over 0.5 s, 10 over 30 s in the
    product), with a warning; if that manager starts anew (its tokens go and come back), the
    watch of the tag sees its offer again and it is followed again."""
    from dyknow.errors import DyKnowError
    from dyknow.federation import Directory, Summary, directory

    monkeypatch.setattr(directory, "_GIVE_UP_ASKS", 2)
    monkeypatch.setattr(directory, "_GIVE_UP_S", 0.5)
    asked: list[str] = []

    def fetch(manager: str) -> bytes:
        asked.append(manager)
        raise DyKnowError("nobody answers", where=f"manager {manager!r}")

    def start(session: Session) -> list[LivelinessToken]:
        return [session.declare_liveliness_token(keys.manager_token("ghost")), session.declare_liveliness_token(keys.offer_token("Ghostly", (), "ghost"))]

    port = free_port()
    with Session(make_config(listen=[f"tcp/127.0.0.1:{port}"])) as one, Session(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as two:
        a = Directory(one, "a", summarize=lambda: Summary("a", "a-host", 1), fetch=fetch, on_change=lambda k, m: None)
        try:
            tokens = start(two)
            wait_until(lambda: "ghost" in a.alive(), "the ghost's token")
            # No summary came. The ghost is followed and asked: by the query, or by the tag's watch
            # a moment later when the query ran before its offer token reached this session (its
            # manager token came first: beside CPU hogs the query found no provider). It may be
            # let go already, 0.5 s after its first failure, when this thread comes back late.
            assert not a.discover([("Ghostly", ())])
            wait_until(lambda: asked[:1] == ["ghost"], "the ghost asked for its summary")
            wait_until(lambda: "ghost" not in a.followed(), "the ghost let go")
            assert a.refused().get("silent") == 1 and len(asked) >= 2
            before = len(asked)
            for token in tokens:
                token.undeclare()
            wait_until(lambda: "ghost" not in a.alive(), "the ghost's token gone")
            tokens = start(two)  # a new start of it
            wait_until(lambda: len(asked) > before, "the ghost followed and asked again")
            for token in tokens:
                token.undeclare()
        finally:
            a.close()


def test_a_provider_slow_to_give_its_summary_is_waited_for_and_planned_with() -> None:
    """A real provider whose summary takes 2.5 s to come (a loaded host, a large library: beside
    CPU hogs, a manager offering 1,500 tags gave its summary past the second a plan waited, and the
    request failed, "nothing provides") is still read: a tag none of whose candidates' summaries
    came waits longer for them (up to _PATIENT_S), ending at the first (issue 50)."""
    from dyknow.federation import Directory, Summary

    def fetch(manager: str) -> bytes:
        time.sleep(2.5)  # (a stand-in for the provider's slow answer)
        return json.dumps(Summary(manager, "slow-host", 1, "x").to_dict()).encode()

    port = free_port()
    with Session(make_config(listen=[f"tcp/127.0.0.1:{port}"])) as one, Session(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as two:
        a = Directory(one, "a", summarize=lambda: Summary("a", "a-host", 1), fetch=fetch, on_change=lambda k, m: None)
        tokens = [two.declare_liveliness_token(keys.manager_token("slow")), two.declare_liveliness_token(keys.offer_token("Slowly", (), "slow"))]
        try:
            wait_until(lambda: "slow" in a.alive() and len(one.alive(keys.offers_pattern("Slowly", ()), timeout_s=0.5)) == 1, "its tokens")
            assert a.discover([("Slowly", ())]) and a.peers()["slow"].host == "slow-host"
        finally:
            for token in tokens:
                token.undeclare()
            a.close()


def test_managers_coming_and_going_cost_nothing_to_one_that_does_not_follow_them(make_manager: Callable[..., Manager]) -> None:
    """Behind one router, a directory follows one provider (the candidate of a plan); 20 other
    managers start and stop: its watches deliver none of their tokens or goodbyes (joins cost the
    fleet N, not N x N), while a liveliness query lists them all; the provider it follows stopping
    is seen at once (its token, then its goodbye: lost, and why)."""
    from dyknow.federation import STOPPED, Directory, Summary

    hub = f"tcp/127.0.0.1:{free_port()}"
    changes: list[tuple[str, str]] = []
    with Session(make_config(listen=[hub], mode="router")), Session(make_config(connect=[hub])) as mine:
        provider = make_manager("provider", router=[hub])
        provider.add_transformation(_offering("Rare"))

        def fetch(manager: str) -> bytes:  # (what the provider's get_summary service answers)
            assert manager == "provider"
            return json.dumps(provider.summary().to_dict()).encode()

        watcher = Directory(mine, "watcher", summarize=lambda: Summary("watcher", "here", 1), fetch=fetch, on_change=lambda k, m: changes.append((k, m)))
        try:
            wait_until(lambda: mine.alive(keys.offers_pattern("Rare", ()), timeout_s=0.5) != [], "the provider's offer")
            assert watcher.discover([("Rare", ())]) and watcher.followed() == {"provider"} and set(watcher.peers()) == {"provider"}
            before = watcher.received()
            assert before.get("manager tokens") == 1  # the provider's, up
            others = [make_manager(f"j{i:02d}", router=[hub], specs=[]) for i in range(20)]
            wait_until(lambda: len(watcher.alive()) == 21, "the watcher to list the 21 others (by a query)")
            for other in others:
                other.close()
            wait_until(lambda: watcher.alive() == {"provider"}, "the 20 gone")
            after = watcher.received()  # none of their 40 tokens and 20 goodbyes came to it (Zenoh may say the provider's twice)
            assert after.get("goodbyes", 0) == 0 and after["manager tokens"] - before["manager tokens"] <= 1, (before, after)
            assert watcher.followed() == {"provider"} and watcher.lost() == {}
            provider.close()
            wait_until(lambda: ("lost", "provider") in changes, "the provider's loss")
            assert watcher.lost()["provider"][1] == STOPPED and watcher.peers() == {}
            assert watcher.received().get("goodbyes", 0) >= 1  # (its goodbye up, maybe gone by now)
        finally:
            watcher.close()


def test_what_a_request_needed_is_let_go_when_it_ends(make_manager: Callable[..., Manager]) -> None:
    """Two requests on two providers: the release of one lets go of its provider and of the watch
    of its tag's providers (not by least-recently-used eviction: at once), the other keeps its
    own; a release of the second frees the rest; asking again finds the provider again."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    requester = make_manager("req", listen=[hub], specs=[])
    for name, tag in (("one", "Rare"), ("two", "Other")):
        make_manager(name, listen=[], connect=[hub], specs=[]).add_transformation(_offering(tag))
    directory = requester.directory
    assert directory is not None
    rare, other = keys.offers_pattern("Rare", ()), keys.offers_pattern("Other", ())
    wait_until(lambda: all(requester.session.alive(p, timeout_s=0.5) for p in (rare, other)), "the providers' offers")
    first = requester.request("Rare")
    second = requester.request("Other")
    assert _provider(requester, first) == "one" and _provider(requester, second) == "two"
    assert directory.followed() == {"one", "two"} and {rare, other} <= directory.watched()
    requester.release(first)
    wait_until(lambda: directory.followed() == {"two"}, "the provider of the request that ended let go")
    assert rare not in directory.watched() and other in directory.watched() and set(requester.peers()) == {"two"}
    requester.release(second)
    wait_until(lambda: directory.followed() == set() and directory.watched() == set(), "everything let go")
    again = requester.request("Rare")
    assert _provider(requester, again) == "one" and directory.followed() == {"one"}


def test_a_manager_advertising_a_million_tags_is_refused_and_costs_the_others_nothing(caplog: pytest.LogCaptureFixture) -> None:
    """Two managers offer ``Rare``: ``good``, and ``evil``, whose summary offers a million tags
    (on a unit's output), or 100,000 in its library's specs: a planner takes good's summary and
    refuses evil's whole before reading its tags (counted; a log line names evil and the bound);
    evil's announced offers are its own bound's business (1,024, tested above)."""
    from dyknow.federation import MAX_SUMMARY_TAGS, Directory, Summary

    caplog.set_level(logging.WARNING, logger="dyknow.federation")
    million = {"manager": "evil", "host": "h", "version": 1, "clock": 1, "units": [
        {"name": "u", "label": "l", "outputs": {"out": "dyknow/evil/out"}, "tags": {"out": [f"T{i}" for i in range(1_000_000)]}, "healthy": True}]}
    spec = f"""<transformations><transformation><label>x</label><source>dyknow.testing:Source</source><ports><port type="out">out</port></ports>
      <tags>{"".join(f'<tag port="out">T{i}</tag>' for i in range(100_000))}</tags></transformation></transformations>"""
    specs = {"manager": "evil", "host": "h", "version": 2, "clock": 1, "specs": [spec]}
    good = {"manager": "good", "host": "h", "version": 1, "clock": 2, "units": [
        {"name": "u", "label": "l", "outputs": {"out": "dyknow/good/out"}, "tags": {"out": ["Rare"]}, "healthy": True}]}
    for hostile in (million, specs):
        served = {"evil": json.dumps(hostile).encode(), "good": json.dumps(good).encode()}
        assert len(served["evil"]) < 16 << 20  # (within the size bound: the tag bound refuses it)
        port = free_port()
        with Session(make_config(listen=[f"tcp/127.0.0.1:{port}"])) as one, Session(make_config(connect=[f"tcp/127.0.0.1:{port}"])) as two:
            held = [two.declare_liveliness_token(k) for m in ("evil", "good") for k in (keys.manager_token(m), keys.offer_token("Rare", (), m))]
            a = Directory(one, "a", summarize=lambda: Summary("a", "a-host", 1), fetch=served.__getitem__, on_change=lambda k, m: None)
            try:
                caplog.clear()
                wait_until(lambda: len(one.alive(keys.offers_pattern("Rare", ()), timeout_s=0.5)) == 2, "both offers")
                assert a.discover([("Rare", ())])
                assert set(a.peers()) == {"good"} and a.refused()["summary"] >= 1
                said = [r.getMessage() for r in caplog.records]
                assert any("manager 'evil'" in line and f"expected at most {MAX_SUMMARY_TAGS} (MAX_SUMMARY_TAGS)" in line for line in said), said
            finally:
                a.close()
                for token in held:
                    token.undeclare()


@pytest.mark.process  # (the listing is the command line's)
def test_a_flood_of_tokens_through_a_router_leaves_the_services_answering_and_the_managers_listed(make_manager: Callable[..., Manager]) -> None:
    """Issue 51: behind a router without TLS, one client with no role declared thousands of
    manager tokens and as many offers of the tag a request needs: the manager's ``request`` gave
    no answer in 30 s (its summary fetches of names nobody answers for held its fetchers, each for
    the calls' whole timeout), and ``dyknow managers`` said "no manager reachable" (the first
    page of names were all fakes). Now the request is planned on the real provider within the
    client's timeout, the model answers, and the listing puts the managers that answer first."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    with Session(make_config(listen=[hub], mode="router")):
        provider = make_manager("provider", router=[hub])
        provider.add_transformation(_offering("Wanted"))
        station = make_manager("station", router=[hub], specs=[])
        with Session(make_config(connect=[hub])) as attacker:
            fakes = [f"a{i:04d}" for i in range(1500)]  # (names that sort before the real ones)
            held = [attacker.declare_liveliness_token(keys.manager_token(name)) for name in fakes]
            held += [attacker.declare_liveliness_token(keys.offer_token("Wanted", (), name)) for name in fakes]
            offers = keys.offers_pattern("Wanted", ())
            wait_until(lambda: len(station.session.alive(offers, timeout_s=1.0)) == 1501, "the station's session to know the 1,501 offers")
            with Client("station", connect=[hub], timeout_s=10.0) as client:
                key = client.request("Wanted")  # within the client's 10 s
                assert _provider(station, key) == "provider"
                assert client.get_model()["manager"] == "station"
            # (a router answering for 3,000 tokens beside CPU hogs took over 2 s once: the listing looks again, as long as --timeout)
            listed = run_cli("managers", "--connect", hub, "--manager", "station", "--limit", "5", "--json", "--timeout", "30")
            assert listed.returncode == 0, listed.stderr
            rows = json.loads(listed.stdout)
            assert [(r["manager"], r["state"]) for r in rows[:2]] == [("provider", "up"), ("station", "up")]
            assert {r["state"] for r in rows[2:]} == {"silent"}
            for entity in held:
                entity.undeclare()
