"""A flood of liveliness tokens through a router without TLS (issue 51): does a manager still serve?

A ``dyknow router`` and two ``dyknow manager`` processes behind it: ``provider`` (its library
offers the tag ``Wanted``) and ``station`` (nothing of its own). This process then declares, as
one client with no role, ``--tokens`` manager tokens and as many offer tokens of ``Wanted`` in
names that run no manager (names sorting before the real ones), and measures what the station
does meanwhile: its ``request`` of ``Wanted`` (answered? planned on the real provider?), its
``get_model``, the listing of the managers (``Client.managers_page``: are the real ones on the
first page?), and the station's threads and memory before and after. Found by the fourth
security review: 5,000-10,000 of each left ``request`` without an answer for 30 s, ``get_model``
at 3-4 s, 21 -> 82 threads, +56 MiB, and the listing said "no manager reachable".

    python benchmarks/token_flood.py                  # 5,000 of each
    python benchmarks/token_flood.py --tokens 500 --json out/token_flood.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from dyknow import Client, keys
from dyknow.transport import Session, make_config

from harness import Proc, free_ports, machine, memory_mib, write_json

OFFERING = """<transformations><transformation><label>offer-wanted</label><source>dyknow.testing:Source</source>
  <ports><port type="out">out</port></ports><tags><tag port="out">Wanted</tag></tags></transformation></transformations>"""


def threads_of(pid: int) -> int:
    """The threads of process ``pid`` (``/proc/<pid>/status``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Threads:"):
            return int(line.split()[1])
    return 0


def timed(what: dict[str, Any], name: str, call: Any) -> Any:
    """Call ``call()``; its time in ms (or its error) under ``what[name]``."""
    started = time.perf_counter()
    try:
        result = call()
    except Exception as exc:  # (the figure is that it failed: said, not raised)
        what[name] = {"ms": round((time.perf_counter() - started) * 1000, 1), "error": str(exc)[:300]}
        return None
    what[name] = {"ms": round((time.perf_counter() - started) * 1000, 1)}
    return result


def measure(hub: str, station_pid: int) -> dict[str, Any]:
    """What the station does now: request, model, listing, threads, memory."""
    out: dict[str, Any] = {"threads": threads_of(station_pid), "rss_mib": round(memory_mib(station_pid)["rss"], 1)}
    with Client("station", connect=[hub], timeout_s=30.0) as client:
        key = timed(out, "request", lambda: client.request("Wanted"))
        if key is not None:
            model = client.get_model()
            units = [u for r in model["requests"] if r["key"] == key for u in r["labels"]]
            out["request"]["provider"] = next((str(u).rpartition("@")[2] for u in units if "@" in str(u)), None)
            client.release(key)
        timed(out, "get_model", lambda: client.get_model())
        page = timed(out, "managers_page", lambda: client.managers_page(timeout_s=2.0, limit=10))
        if page is not None:
            out["managers_page"]["first"] = [m["manager"] for m in page["managers"] if not m.get("silent")]
            out["managers_page"]["total"] = page["total"]
    return out


def main() -> int:
    """Start the router and the managers, measure before, during and after the flood, print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tokens", type=int, default=5000, help="manager tokens, and as many offer tokens (default 5,000)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    (port,) = free_ports(1)
    hub = f"tcp/127.0.0.1:{port}"
    procs: list[Proc] = []
    with tempfile.TemporaryDirectory() as tmp:
        spec = Path(tmp) / "wanted.xml"
        spec.write_text(OFFERING)
        try:
            router = Proc([sys.executable, "-m", "dyknow", "router", "--listen", hub, "--json"])
            procs.append(router)
            router.next_json(30, event="ready")
            provider = Proc([sys.executable, "-m", "dyknow", "manager", "--name", "provider", "--router", hub, "--specs", str(spec), "--json"])
            station = Proc([sys.executable, "-m", "dyknow", "manager", "--name", "station", "--router", hub, "--json"])
            procs += [provider, station]
            provider.next_json(60, event="ready")
            station.next_json(60, event="ready")
            with Client("station", connect=[hub], timeout_s=10.0) as client:
                client.wait_for_managers(["provider", "station"], timeout_s=30)
            before = measure(hub, station.proc.pid)
            with Session(make_config(connect=[hub])) as attacker:
                names = [f"a{i:05d}" for i in range(args.tokens)]
                started = time.perf_counter()
                held = [attacker.declare_liveliness_token(keys.manager_token(n)) for n in names]
                held += [attacker.declare_liveliness_token(keys.offer_token("Wanted", (), n)) for n in names]
                declared_s = time.perf_counter() - started
                time.sleep(2.0)  # (the tokens reach the station: its session hears them all)
                during = measure(hub, station.proc.pid)
                for token in held:
                    token.undeclare()
            time.sleep(2.0)
            after = measure(hub, station.proc.pid)
        finally:
            for proc in reversed(procs):
                proc.close()
    rows = [("before the flood", before), (f"during {args.tokens} + {args.tokens} tokens", during), ("after they went", after)]
    print(f"token flood through a router: {args.tokens} manager tokens and {args.tokens} offers of Wanted, declared in {declared_s:.1f} s")
    print("(found before the fix, 5,000-10,000 of each: no answer to request in 30 s, get_model 3-4 s, 21 -> 82 threads, +56 MiB,")
    print(" 'no manager reachable')")
    for label, row in rows:
        request = row["request"]
        print(
            f"{label:<32} request {request['ms']:>8.1f} ms ({request.get('error') or 'on ' + str(request.get('provider'))}); "
            f"get_model {row['get_model']['ms']:>7.1f} ms; listing {row['managers_page']['ms']:>7.1f} ms, first "
            f"{row['managers_page'].get('first')} of {row['managers_page'].get('total')}; threads {row['threads']}, RSS {row['rss_mib']} MiB"
        )
    if args.json:
        write_json(args.json, {"machine": machine(), "tokens": args.tokens, "declared_s": declared_s,
                               "results": [{"phase": label, **row} for label, row in rows]})  # fmt: skip
    ok = all(row["request"].get("provider") == "provider" for _, row in rows)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
