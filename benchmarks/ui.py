"""The interactive tool under load, in a real browser (Chromium driven by Selenium).

Four ``dyknow manager`` processes with 50 units each (200 in all: relays, one 10-hop chain fed at
50 Hz, a 640x480 synthetic camera at 30 Hz) and ``dyknow ui`` pointed at them. Measured:

- first draw: from the page's navigation start to the graph drawn with every unit (the page's own
  ``performance.now()``);
- a model change on screen: from a spawn through the client to its row on the page (polled);
- the image view's frame rate at 640x480 (the page's own count);
- the chain's end-to-end latency over its 10 hops, page closed against page open and watching it.

    python benchmarks/ui.py                  # prints each figure beside its target
    python benchmarks/ui.py --smoke --json out/ui.json
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from dyknow import Client, Message
from dyknow.resources import specs_dir
from dyknow.transport import Session, make_config

from harness import Proc, free_ports, machine, percentile, write_json

HOPS = 10


def start_managers(count: int, units: int) -> tuple[list[Proc], list[str]]:
    """``count`` manager processes, each with ``units`` units (the first with the chain and the camera)."""
    ports = free_ports(count)
    hub = f"tcp/127.0.0.1:{ports[0]}"
    procs, endpoints = [], []
    for i, port in enumerate(ports):
        endpoint = f"tcp/127.0.0.1:{port}"
        argv = [sys.executable, "-m", "dyknow.cli", "manager", "--name", f"m{i}", "--listen", endpoint, "--json",
                "--specs", str(specs_dir() / "generic.xml"), str(specs_dir() / "sources.xml"), *([] if i == 0 else ["--connect", hub])]  # fmt: skip
        proc = Proc(argv)
        proc.next_json(60, event="ready")
        procs.append(proc)
        endpoints.append(endpoint)
    with Client("m0", connect=[hub], timeout_s=10) as client:
        for i in range(count):
            made = 0
            if i == 0:
                client.spawn("periodic-source", "src", params={"rate_hz": 50.0})
                upstream = "dyknow/m0/src/out"
                for h in range(HOPS):
                    client.spawn("relay", f"hop{h}", bindings={"in": upstream})
                    upstream = f"dyknow/m0/hop{h}/out"
                client.spawn("synthetic-scene(ceiling)", "scene", params={"rate_hz": 30})
                made = HOPS + 2
            for n in range(made, units):
                client.call_manager(f"m{i}", "spawn", {"label": "relay", "name": f"idle{n}"})
    return procs, endpoints


class ChainLatency:
    """End-to-end latency of the chain's last key (origin at the source to arrival here), in ms."""

    def __init__(self, session: Session) -> None:
        self.samples: list[float] = []
        self.recording = False
        self._sub = session.declare_subscriber(f"dyknow/m0/hop{HOPS - 1}/out", self._on)

    def _on(self, msg: Message) -> None:
        if self.recording:
            self.samples.append((time.time_ns() - msg.origin_ns) / 1e6)

    def window(self, seconds: float) -> list[float]:
        """The samples of the next ``seconds``."""
        self.samples = []
        self.recording = True
        time.sleep(seconds)
        self.recording = False
        return list(self.samples)


def browser() -> Any:
    """Headless Chromium through chromedriver (Debian's packages)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    options = Options()
    options.binary_location = shutil.which("chromium") or "chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,900", "--disable-dev-shm-usage"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(shutil.which("chromedriver") or "chromedriver"), options=options)


def main() -> int:
    """Run the measurements and print each beside its target."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--managers", type=int, default=4)
    parser.add_argument("--units", type=int, default=50, help="units per manager (default 50)")
    parser.add_argument("--changes", type=int, default=10, help="spawns timed to the screen (default 10)")
    parser.add_argument("--window", type=float, default=10.0, help="seconds of chain latency per phase (default 10)")
    parser.add_argument("--smoke", action="store_true", help="2 managers x 15 units, 3 changes, 2 s windows")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.smoke:
        args.managers, args.units, args.changes, args.window = 2, 15, 3, 2.0
    total = args.managers * args.units
    procs, endpoints = start_managers(args.managers, args.units)
    ui = None
    driver = None
    try:
        ui = Proc([sys.executable, "-m", "dyknow.cli", "ui", "--connect", endpoints[0], "--port", "0", "--json"])
        url = str(ui.next_json(30, event="ready")["url"])
        with Session(make_config(connect=[endpoints[0]])) as session, Client("m0", connect=[endpoints[0]]) as client:
            chain = ChainLatency(session)
            time.sleep(1.0)
            closed = chain.window(args.window)

            driver = browser()
            driver.get(url)
            deadline = time.monotonic() + 30
            while driver.execute_script("return window.dyknowFirstDraw === undefined || cy.nodes('.unit').length") != total:
                if time.monotonic() > deadline:
                    raise RuntimeError("the page did not draw every unit within 30 s")
                time.sleep(0.01)
            first_draw_ms = float(driver.execute_script("return window.dyknowFirstDraw"))
            # the first draw may come before every unit is in: time to all units drawn, from navigation start
            all_drawn_ms = float(driver.execute_script("return performance.now()"))

            changes = []
            for n in range(args.changes):
                name = f"new{n}"
                start = time.monotonic()
                client.spawn("relay", name)
                while not driver.execute_script(f"return !!document.querySelector('tr[data-unit={name}]')"):
                    time.sleep(0.005)
                changes.append((time.monotonic() - start) * 1000)

            driver.find_element("css selector", "nav button[data-tab=view]").click()
            driver.find_element("id", "view-key").send_keys("dyknow/m0/scene/out")
            driver.find_element("css selector", "#view-form button[type=submit]").click()
            time.sleep(3.0)
            fps = float(driver.find_element("id", "view-stats").get_attribute("data-rate") or 0)

            driver.find_element("id", "view-key").clear()
            driver.find_element("id", "view-key").send_keys(f"dyknow/m0/hop{HOPS - 1}/out")
            driver.find_element("css selector", "#view-form button[type=submit]").click()
            time.sleep(1.0)
            opened = chain.window(args.window)
    finally:
        if driver is not None:
            driver.quit()
        for proc in [*([ui] if ui else []), *procs]:
            proc.close()

    closed_p50, opened_p50 = statistics.median(closed), statistics.median(opened)
    rise = (opened_p50 - closed_p50) / closed_p50 * 100
    rows = [
        {"figure": "graph drawn with every unit, from navigation start", "value_ms": round(all_drawn_ms, 1), "first_draw_ms": round(first_draw_ms, 1), "target": "<= 1500 ms", "met": all_drawn_ms <= 1500},
        {"figure": "a spawn on screen (p50 / p99)", "p50_ms": percentile(changes, 50, 1), "p99_ms": percentile(changes, 99, 1), "target": "<= 1000 ms", "met": max(changes) <= 1000},
        {"figure": "image view at 640x480", "frames_per_s": round(fps, 1), "target": ">= 15 frames/s", "met": fps >= 15},
        {"figure": f"{HOPS}-hop chain latency p50, page closed / open", "closed_ms": round(closed_p50, 3), "open_ms": round(opened_p50, 3),
         "rise_percent": round(rise, 1), "target": "rise <= 5 %", "met": rise <= 5},
    ]  # fmt: skip
    print(f"{args.managers} managers x {args.units} units ({total}); Chromium headless; {HOPS}-hop chain at 50 Hz; 640x480 camera at 30 Hz")
    print(f"graph drawn with all {total} units {all_drawn_ms:.0f} ms after navigation start (first draw {first_draw_ms:.0f} ms)   target <= 1500 ms: {'met' if rows[0]['met'] else 'NOT met'}")
    print(f"a spawn on screen: p50 {rows[1]['p50_ms']} ms, p99 {rows[1]['p99_ms']} ms over {len(changes)}   target <= 1000 ms: {'met' if rows[1]['met'] else 'NOT met'}")
    print(f"image view: {fps:.1f} frames/s at 640x480   target >= 15: {'met' if rows[2]['met'] else 'NOT met'}")
    print(f"chain end-to-end latency p50: {closed_p50:.3f} ms page closed ({len(closed)} messages), {opened_p50:.3f} ms page open ({len(opened)}): "
          f"{rise:+.1f} %   target <= +5 %: {'met' if rows[3]['met'] else 'NOT met'}")  # fmt: skip
    if args.json:
        write_json(args.json, {"machine": machine(), "results": rows})
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
