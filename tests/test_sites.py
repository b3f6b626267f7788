"""Two sites joined by their routers (issue 40, item 3), for real: network namespaces (root needed).

Site A (the station, the field, its gateway ``gw-a``) and site B (the robot, its gateway ``gw-b``)
are two networks whose hosts cannot reach each other; the gateways also share a third network,
the WAN. The commands are those of ``docs/howto/router.md`` (section "Several sites joined by their
routers"), run as written on the hosts and with the addresses their comments name (``--json``
added to the routers' and managers' lines, to read their ready line; the ``pki/`` folder given
whole): each gateway runs a ``dyknow router``, ``gw-b``'s dials ``gw-a``'s over the WAN (the one
link between the sites), every manager sits behind its site's router (``--router``), every link is
TLS with mutual authentication, and every process has its own ``/dev/shm``. The request on site A
is planned with the robot's camera on site B and its stream flows through both routers; a
SIGKILL of the robot's manager moves it to the field's camera on site A.

Under ``CI=true`` this must run; elsewhere it skips when namespaces cannot be made.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from dyknow.testing import CAMERA_IDS
from dyknow.testing.hosts import Hosts
from tests.conftest import need_hosts, subprocess_env
from tests.test_hosts import Child

pytestmark = pytest.mark.namespaces  # every test here: see CONTRIBUTING.md, 'Tiers'

REPO = Path(__file__).resolve().parent.parent
PAGE = REPO / "docs" / "howto" / "router.md"
BOTTOM, CEILING = CAMERA_IDS["bottom"], CAMERA_IDS["ceiling"]
SITES = {"site-a": ["station", "field", "gw-a"], "site-b": ["robot", "gw-b"], "wan": ["gw-a", "gw-b"]}
# the page's addresses: site A 10.1.0.0/24, site B 10.2.0.0/24, the WAN 192.168.9.0/24
ADDRESSES = {"station": "10.1.0.2", "field": "10.1.0.3", "gw-a": "10.1.0.1", "gw-a@wan": "192.168.9.1",
             "robot": "10.2.0.5", "gw-b": "10.2.0.1", "gw-b@wan": "192.168.9.2"}  # fmt: skip
# a TCP connection attempt from one host to an address: "reached" (refused: the host answered) or why not
PROBE = (
    "import socket, sys\n"
    "try:\n"
    "    socket.create_connection((sys.argv[1], 9), timeout=2)\n"
    "except ConnectionRefusedError:\n"
    "    print('reached')\n"
    "except OSError as exc:\n"
    "    print(exc)\n"
)


def _docs_two_sites() -> list[tuple[str, str]]:
    """The page's two-site example: (the host its comment names, command line) in order; the
    lines "on any machine" run on gw-a."""
    block = next(b for b in re.findall(r"```sh\n(.*?)```", PAGE.read_text(), re.DOTALL) if "# on gw-a" in b)
    steps, host = [], "gw-a"
    for line in block.replace("\\\n", " ").splitlines():
        if line.startswith("#"):
            named = re.match(r"# on ([\w-]+)", line)
            host = named.group(1) if named and named.group(1) in ADDRESSES else "gw-a"
        elif line.strip():
            steps.append((host, " ".join(line.split())))
    return steps


def links(hosts: Hosts, host: str, pid: int) -> list[str]:
    """The remote end of each established TCP socket of process ``pid`` on ``host``."""
    out = subprocess.run(hosts.command(host, ["ss", "-tnpH", "state", "established"]), capture_output=True, text=True, check=True).stdout
    return sorted(line.split()[3] for line in out.splitlines() if f"pid={pid}," in line)


class Sites:
    """The page's two sites, started as its lines say (every line run, the request made and
    echoed), and an observer on the station that requests the track too (``tests.netns_observer``).
    ``edit(host, argv)``: a line's command as run instead (None: not run), for a variant of the page."""

    def __init__(self, hosts: Hosts, folder: Path, edit: Callable[[str, list[str]], list[str] | None] | None = None) -> None:
        self.hosts, self.pki = hosts, folder / "pki"
        self.children: list[Child] = []
        self.served: dict[str, Child] = {}
        self.ready: dict[str, dict[str, Any]] = {}  # the ready line of each router and manager, by host
        env = {**subprocess_env(), "DYKNOW_LOG": "INFO"}
        dyknow = [sys.executable, "-m", "dyknow.cli"]

        def run(host: str, argv: list[str]) -> subprocess.CompletedProcess[str]:
            return subprocess.run(hosts.command(host, argv), capture_output=True, text=True, timeout=120, env=env, cwd=folder)

        self.run = run  # (a test's own lines too)
        started = 0
        for host, line in _docs_two_sites():
            edited = [*dyknow, *shlex.split(line)[1:]] if edit is None else edit(host, [*dyknow, *shlex.split(line)[1:]])
            if edited is None:
                continue
            argv = edited
            started += argv[3] == "manager"
            if argv[3] in ("router", "manager"):
                self.served[host] = self.child(host, [w.replace("pki/", f"{self.pki}/") for w in argv] + ["--json"])
                ready = self.ready[host] = self.served[host].next("ready", timeout_s=60)
                if argv[3] == "manager":
                    assert ready["endpoints"] == [] and len(ready["router"]) == 1, ready
                continue
            done = run(host, argv)
            if argv[3] == "managers":  # an operator waits for every manager of both sites to show up
                deadline = time.monotonic() + 60
                while len(json.loads(run(host, [*argv, "--json"]).stdout or "[]")) != started:
                    assert time.monotonic() < deadline, run(host, [*argv, "--json"])
                    time.sleep(0.2)
                done = run(host, argv)
            assert done.returncode == 0, (line, done.stdout, done.stderr[-3000:])
            if argv[3] == "request":
                assert done.stdout.strip() == "dyknow/station/requests/BallTrack(field)"
            if argv[3] == "echo":
                assert done.stdout.count("dyknow/station/requests/BallTrack(field) #") == 5, done.stdout
        self.a_site, self.a_wan = f"{hosts.address('gw-a')}:7447", f"{hosts.address('gw-a', 'wan')}:7447"
        self.b_site = f"{hosts.address('gw-b')}:7447"
        self.observer = self.child("station", [*dyknow[:2], "tests.netns_observer", f"tls/{self.a_site}", "station", "BallTrack(field)",
                                               str(self.pki / "ca.pem"), str(self.pki / "station.pem"), str(self.pki / "station.key")])  # fmt: skip
        self.observer.next("key", timeout_s=60)

    def child(self, host: str, argv: list[str]) -> Child:
        self.children.append(Child(self.hosts, host, argv))
        return self.children[-1]

    def gateway_links(self) -> int:
        """gw-b's links to gw-a's WAN endpoint."""
        return links(self.hosts, "gw-b", self.served["gw-b"].proc.pid).count(self.a_wan)

    def close(self) -> None:
        for child in reversed(self.children):
            child.close()
        for child in self.children:
            print(f"----- {child.host}\n{child.stderr[-3000:]}")


def _namespaces() -> None:
    need_hosts()


def _until(condition: Callable[[], bool], what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"{what} within {timeout_s} s"
        time.sleep(0.2)


def test_the_docs_two_sites_serve_a_request_from_the_other_site_and_fail_over_to_their_own(tmp_path: Path) -> None:
    _namespaces()
    steps = _docs_two_sites()
    assert [h for h, _ in steps] == ["gw-a", "gw-a", "gw-b", "station", "field", "robot", "station", "station", "station"], steps
    with Hosts(["station", "field", "gw-a", "robot", "gw-b"], networks=SITES, addresses=ADDRESSES) as hosts:
        # the sites cannot reach each other but through the gateways' routers
        for a, b in (("station", hosts.address("robot")), ("robot", hosts.address("station")), ("field", hosts.address("gw-b", "wan"))):
            said = subprocess.run(hosts.command(a, [sys.executable, "-c", PROBE, b]), capture_output=True, text=True, timeout=30).stdout
            assert "Network is unreachable" in said, (a, b, said)
        sites = Sites(hosts, tmp_path)
        try:
            observer, served = sites.observer, sites.served
            observer.next("camera", camera=BOTTOM, timeout_s=60)  # the robot's camera, on site B
            # one link per manager, to its site's router; one between the sites, router to router
            for name, router in (("station", sites.a_site), ("field", sites.a_site), ("robot", sites.b_site)):
                assert links(hosts, name, served[name].proc.pid) == [router]
            assert sites.gateway_links() == 1
            # the station exchanges clocks with the robot through both routers: the hop from the
            # robot's camera into the station's first unit is corrected by its estimate
            _until(lambda: {p["unit"]: p for p in observer.ask("ports")}["subsampler(bottom)"]["uncertainty_us"] > 0,
                   "the robot's clock known to the station")  # fmt: skip

            served["robot"].proc.kill()  # SIGKILL
            observer.next("camera", camera=CEILING, timeout_s=60)  # the field's camera, on site A
            assert sorted(m["manager"] for m in observer.ask("managers")) == ["field", "station"]
            model = observer.ask("model station")[0]  # the lost manager is shown (the loss came first)
            assert model["peers"] == ["field"] and [x["manager"] for x in model["lost"]] == ["robot"], model
            causes = [e["cause"] for e in observer.ask("adaptations")]
            assert "manager 'robot' was lost" in causes, causes
        finally:
            sites.close()


def test_a_cut_between_the_sites_fails_over_and_heals_by_itself(tmp_path: Path) -> None:
    """The WAN link of site B's gateway goes down (the sites apart, every host up): site A loses
    the robot once the lease expires and takes the field's camera; the link back, the routers
    link again by themselves, the robot is listed again and the request returns to its camera. A
    request only the robot serves is degraded meanwhile; rebuilt, its camera on the robot has the
    name (and key) it had, not robot-camera-2 (issue 52)."""
    _namespaces()
    with Hosts(["station", "field", "gw-a", "robot", "gw-b"], networks=SITES, addresses=ADDRESSES) as hosts:
        sites = Sites(hosts, tmp_path)
        try:
            observer = sites.observer
            observer.next("camera", camera=BOTTOM, timeout_s=60)
            # gw-b's ready line names the router it dials and, linked, the one there (or says so once linked: issue 52)
            gateways, ready = {"gw-a": "gw-b", "gw-b": "gw-a"}, sites.ready["gw-b"]
            assert ready["connect"] == [f"tls/{sites.a_wan}"] and [r["peer"] for r in ready["routers"]] in (["gw-a"], []), ready
            if not ready["routers"]:
                sites.served["gw-b"].next("link-up", peer="gw-a")
            # and a stream only the robot serves: degraded during the cut, rebuilt as the robot is back
            line = next(line for _, line in _docs_two_sites() if line.startswith("dyknow request ")).replace("BallTrack(field)", "RawImage(bottom)")
            assert sites.run("station", [sys.executable, "-m", "dyknow.cli", *shlex.split(line)[1:]]).returncode == 0
            units = {u["name"]: u["bindings"] for u in observer.ask("model robot")[0]["units"]}  # the robot's camera: its name, its keys
            hosts.cut("gw-b", network="wan")
            observer.next("camera", camera=CEILING, timeout_s=60)
            assert [x["manager"] for x in observer.ask("model station")[0]["lost"]] == ["robot"]
            _until(lambda: sites.gateway_links() == 0, "the link between the routers given up")
            down = {gw: sites.served[gw].next("link-down", peer=peer) for gw, peer in gateways.items()}  # each names the other
            hosts.restore("gw-b")
            _until(lambda: sites.gateway_links() == 1, "the routers to link again", timeout_s=90)
            for gw, peer in gateways.items():  # ... and says it came back, after how long (in its log too)
                up = sites.served[gw].next("link-up", peer=peer)
                assert up["zid"] == down[gw]["zid"] and up["down_s"] > 0 and down[gw]["address"].startswith("tls/192.168.9."), (up, down)
                assert f"link to router {peer} (tls/192.168.9." in sites.served[gw].said() and " up again after " in sites.served[gw].said()
            observer.next("camera", camera=BOTTOM, timeout_s=60)  # the preferred camera back, after the dwell
            assert sorted(m["manager"] for m in observer.ask("managers")) == ["field", "robot", "station"]
            for name, router in (("station", sites.a_site), ("field", sites.a_site), ("robot", sites.b_site)):
                assert links(hosts, name, sites.served[name].proc.pid) == [router]  # the managers' own links never went
            # the robot's camera, gone with the station's loss, was spawned again under its name and key (issue 52)
            assert {u["name"]: u["bindings"] for u in observer.ask("model robot")[0]["units"]} == units and list(units) == ["robot-camera"]
        finally:
            sites.close()
