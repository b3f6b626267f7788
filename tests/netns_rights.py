"""What each certificate may do, through one endpoint, on a host of a namespace test.

Run as ``python -m tests.netns_rights ENDPOINT MANAGER CERTS NAME...`` inside a host's namespace
(the test process cannot reach addresses inside the namespaces). ``CERTS`` holds ``ca.pem`` and
``NAME.pem``/``NAME.key`` for each name and ``admin``. Through ``ENDPOINT`` (a router, or another
manager than ``MANAGER``), each name's client calls ``MANAGER``'s services, subscribes to its data
and publishes into a unit of it; one JSON line says what came of each::

    {"name": ..., "get_model": OUTCOME, "destroy": OUTCOME, "request": OUTCOME, "receives": bool, "publishes": bool}

An OUTCOME is ``reached`` (the manager answered: done, or refused for its own reasons such as an
unknown unit or tag), ``refused`` (the manager's check of the caller's role), ``dropped`` (an
access control on the way dropped the call) or ``nothing`` (no service visible at all).
"""

from __future__ import annotations

import functools
import json
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dyknow import AccessError, Client, DyKnowError, Message, ServiceError
from dyknow.access import TlsFiles
from dyknow.transport import Session, make_config

SOURCE, INBOX = "rights-ticks", "rights-inbox"


def _outcome(call: Callable[[], Any]) -> str:
    try:
        call()
    except AccessError:
        return "refused"
    except ServiceError as exc:
        reason = exc.details.get("reason") if exc.kind is None else None
        return "dropped" if reason == "dropped" else "nothing" if reason in ("no-role", "timeout", "unreachable") else f"error: {exc}"
    except DyKnowError:
        return "reached"
    return "reached"


def main() -> int:
    """Check every name; one JSON line each."""
    endpoint, manager, certs, *names = sys.argv[1:]

    def tls(name: str) -> TlsFiles:
        return TlsFiles(str(Path(certs) / "ca.pem"), str(Path(certs) / f"{name}.pem"), str(Path(certs) / f"{name}.key"))

    with Client(manager, connect=[endpoint], tls=tls("admin"), timeout_s=10) as admin:
        admin.spawn("periodic-source", SOURCE, params={"rate_hz": 50})
        admin.spawn("relay", INBOX, bindings={"in": "dyknow/ext/in"})

        def inbox() -> int:
            return int(admin.get_statistics(INBOX)["ports"]["in"]["messages"])

        for name in names:
            result: dict[str, Any] = {"name": name}
            with Client(manager, connect=[endpoint], tls=tls(name), timeout_s=3) as client:
                result["get_model"] = _outcome(client.get_model)
                result["destroy"] = _outcome(functools.partial(client.destroy, "no-such-unit"))
                result["request"] = _outcome(functools.partial(client.request, "NoSuchTag"))
                got = threading.Event()

                def seen(msg: Message, got: threading.Event = got) -> None:
                    got.set()

                with client.declare_subscriber(f"dyknow/{manager}/{SOURCE}/out", seen):
                    result["receives"] = got.wait(3)  # (50 messages a second: one comes within 3 s, if any may)
            before = inbox()
            # a leaf of the endpoint (a peer would find the manager through gossip and bypass it)
            with Session(make_config(connect=[endpoint], tls=tls(name), mode="client", listen=[])) as session:
                publisher = session.declare_publisher("dyknow/ext/in")
                for i in range(20):
                    publisher.put(Message({"i": i}, i, 0, 0, "dyknow/ext/in"))
                    threading.Event().wait(0.05)
                session.flush()
            # flush: the endpoint has it (and dropped it at its link, or passes it on); what it
            # passes on takes a moment more to reach the manager
            deadline = time.monotonic() + 5
            while not (arrived := inbox() > before) and time.monotonic() < deadline:
                threading.Event().wait(0.1)
            result["publishes"] = arrived
            print(json.dumps(result), flush=True)
        admin.destroy(INBOX)
        admin.destroy(SOURCE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
