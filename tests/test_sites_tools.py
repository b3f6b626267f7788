"""An operator's tools during a cut between two sites (issue 52), for real: network namespaces.

The two sites of ``docs/howto/router.md`` (``tests/test_sites.py``), without the field's camera,
so that the station's request has nothing left when the robot is lost: it is degraded. The
gateways' lease is long (:data:`GATEWAY_LEASE_MS`), so that a call made just after the WAN link
goes down meets the robot still listed (its token is held until the lease expires). Each tool is
run as an operator on the station runs it, with the station's certificate, and must say what
happened: the robot LOST (since when, why, as the station saw it), the request degraded, the
link cut before the lease expires; and ``doctor`` on a client host passes a healthy set-up.

Under ``CI=true`` this must run; elsewhere it skips when namespaces cannot be made.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from dyknow.testing import CAMERA_IDS
from dyknow.testing.hosts import Hosts
from tests.conftest import need_hosts, subprocess_env
from tests.test_sites import ADDRESSES, SITES, Sites, _until

pytestmark = pytest.mark.namespaces  # see CONTRIBUTING.md, 'Tiers'

BOTTOM = CAMERA_IDS["bottom"]
#: The lease between the gateways (ms): a call made just after the cut, a command's start and its
#: --timeout of 2 s, ends well within it (the managers keep the page's 2,000 ms to their router).
GATEWAY_LEASE_MS = 25_000
TRACK = "BallTrack(field)"
REQUEST_KEY = f"dyknow/station/requests/{TRACK}"


def _without_the_field(host: str, argv: list[str]) -> list[str] | None:
    """The page's lines, but the field's manager (site A's own camera) is not started, and the
    gateways hold their link for :data:`GATEWAY_LEASE_MS`."""
    if host == "field":
        return None
    if argv[3] == "router":
        at = argv.index("--lease-ms")
        return [*argv[: at + 1], str(GATEWAY_LEASE_MS), *argv[at + 2 :]]
    return argv


def test_during_a_cut_between_the_sites_every_tool_says_what_happened(tmp_path: Path) -> None:
    need_hosts(faults=True)  # (its cut is silent: nftables drops the packets)
    with Hosts(["station", "field", "gw-a", "robot", "gw-b"], networks=SITES, addresses=ADDRESSES) as hosts:
        sites = Sites(hosts, tmp_path, edit=_without_the_field)
        pki = sites.pki
        station = ["--connect", f"tls/{sites.a_site}", "--lease-ms", "2000",
                   "--tls-ca", str(pki / "ca.pem"), "--tls-cert", str(pki / "station.pem"), "--tls-key", str(pki / "station.key")]  # fmt: skip

        def dyknow(*argv: str) -> subprocess.CompletedProcess[str]:
            """A command as an operator on the station runs it."""
            command = [sys.executable, "-m", "dyknow.cli", *argv, *station]
            done = subprocess.run(hosts.command("station", command), capture_output=True, text=True, timeout=120, env=subprocess_env(), cwd=tmp_path)
            print(f"$ dyknow {' '.join(argv)}\n{done.stdout}{done.stderr}")
            return done

        try:
            observer = sites.observer
            observer.next("camera", camera=BOTTOM, timeout_s=60)  # the robot's camera, on site B
            robot_units = [u["name"] for u in observer.ask("model robot")[0]["units"]]
            assert robot_units, "the robot runs the camera's units for the station"

            # 1. doctor on a client host, the page's set-up healthy: its port check is of no port
            #    of the router's (it listens nowhere), and nothing fails
            done = dyknow("doctor", "--manager", "station")
            assert done.returncode == 0, done.stdout
            assert f"ok   port      tls/{sites.a_site} is another host's address" in done.stdout

            hosts.cut("gw-b", network="wan", silent=True)  # (a dropped link: only the lease tells, no error on a socket)
            cut = time.monotonic()
            # 6. before the lease expires: the robot is still listed; a call to it names the cut
            done = dyknow("model", "--manager", "robot", "--timeout", "2")
            assert time.monotonic() - cut < GATEWAY_LEASE_MS / 1000, "the call ended within the gateways' lease"
            assert done.returncode == 1
            assert "the link to it is cut" in done.stderr and "it is busy or stuck" not in done.stderr, done.stderr

            def lost() -> list[str]:
                return [x["manager"] for x in observer.ask("model station")[0]["lost"]]

            _until(lambda: lost() == ["robot"], "the station to lose the robot", timeout_s=GATEWAY_LEASE_MS / 1000 + 60)
            _until(lambda: [r["state"] for r in observer.ask("model station")[0]["requests"]] == ["degraded"], "the request degraded")

            # 2. doctor says what the station knows: the robot lost, the request degraded
            done = dyknow("doctor", "--manager", "station")
            assert done.returncode == 1, done.stdout
            assert "FAIL lost      manager 'robot' is LOST since " in done.stdout and "as station saw it" in done.stdout, done.stdout
            assert f"WARN requests  manager 'station': request {TRACK} ({REQUEST_KEY}) is degraded: " in done.stdout, done.stdout
            done = dyknow("doctor", "--manager", "robot")
            assert done.returncode == 1
            assert "FAIL managers  manager 'robot' is LOST since " in done.stdout, done.stdout
            assert "fix: --manager station" not in done.stdout and "among them" not in done.stdout, done.stdout

            # 3. one-shot commands: a lost manager, never a misspelling
            for argv in (["model", "--manager", "robot"], ["request", TRACK, "--manager", "robot"],
                         ["top", "--once", "--only", "--interval", "0.2", "--manager", "robot"]):  # fmt: skip
                done = dyknow(*argv)
                assert done.returncode == 1, argv
                said = done.stderr + done.stdout
                assert "manager 'robot' is LOST since " in said and "as station saw it" in said, (argv, said)
                assert "--manager one of" not in said and "the link to it" in said, (argv, said)

            # 4. top shows the loss and the degraded request; hz says why its keys are silent
            done = dyknow("top", "--once", "--interval", "0.2", "--manager", "station")
            assert done.returncode == 0, done.stderr
            assert "\nmanager 'robot' is LOST since " in done.stdout, done.stdout
            assert f"request {TRACK} on {REQUEST_KEY}: DEGRADED: " in done.stdout, done.stdout
            done = dyknow("hz", f"dyknow/robot/{robot_units[0]}/**", "--duration", "1.5", "--manager", "station")
            assert done.returncode == 1 and "it is a key of manager 'robot', and manager 'robot' is LOST since " in done.stderr, done.stderr
            done = dyknow("hz", REQUEST_KEY, "--duration", "1.5", "--manager", "station")
            assert done.returncode == 1, done.stderr
            assert f"it is the key of request {TRACK} of manager 'station', which is degraded: " in done.stderr, done.stderr
        finally:
            sites.close()
