"""A consumer on one host of a namespace test: requests a stream and reports which camera feeds it.

Run as ``python -m tests.netns_observer ENDPOINT MANAGER TAG`` inside a host's namespace (the
test process cannot reach addresses inside the namespaces). It prints JSON lines: the request's
``key``, then a ``camera`` line each time the camera id in the frames changes; on a line
``adaptations`` or ``managers`` on its standard input it prints that list.
"""

from __future__ import annotations

import json
import sys
import threading
import time

from dyknow import Client, Message


def main() -> int:
    """Request, watch, answer questions until standard input closes."""
    endpoint, manager, tag = sys.argv[1:4]
    lock = threading.Lock()
    last: list[int] = []

    def say(data: dict[str, object]) -> None:
        with lock:
            print(json.dumps(data), flush=True)

    def on_message(msg: Message) -> None:
        camera = int(msg.payload["camera"])  # the tracker says which camera the frames came from
        if last != [camera]:
            last[:] = [camera]
            say({"event": "camera", "camera": camera, "t_ns": time.time_ns()})

    with Client(manager, connect=[endpoint], timeout_s=10.0, lease_ms=1000) as client:  # the managers' lease: see the cut as soon
        deadline = time.monotonic() + 30
        while True:
            try:
                key = client.request(tag)
                break
            except Exception as exc:  # the other managers may not be known yet
                if time.monotonic() > deadline:
                    raise
                say({"event": "waiting", "why": str(exc)[:200]})
                time.sleep(0.2)
        say({"event": "key", "key": key})
        with client.declare_subscriber(key, on_message):
            for line in sys.stdin:
                if line.strip() == "adaptations":
                    say({"event": "adaptations", "items": client.get_adaptations()})
                elif line.strip() == "managers":
                    say({"event": "managers", "items": client.managers()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
