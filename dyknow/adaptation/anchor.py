"""The request anchor: the relay unit owned by a request, whose output is the request's stable key;
adapting rebinds its input. The warm anchor also keeps the standby's latest message, forwarded at
once on a switch. :func:`spawn_anchor` gives a request its anchor.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping

from dyknow.adaptation.knowledge import Knowledge, Request
from dyknow.adaptation.runtime import Runtime
from dyknow.message import Message
from dyknow.spec import Port, TransformationSpec
from dyknow.unit import Unit

log = logging.getLogger("dyknow.adaptation")  # one name for the loop, whichever part logs

ANCHOR_LABEL = "dyknow-request-anchor"


# ---------------------------------------------------------------------------- the anchor unit


class RequestAnchor(Unit):
    """Relays a request's configuration onto the request's stable key; reports recoveries.

    After an adaptation the loop tells the anchor which key the new configuration publishes on;
    the first message from that key closes the adaptation with its recovery time.

    The anchor of a warm request (:data:`WARM_ANCHOR_SPEC`) also reads the standby's output on
    port ``standby`` and keeps only the latest message, since the port was last rebound. When
    ``in`` is rebound onto that key (the standby takes over), it forwards that message at once,
    with its own origin time, unless a newer one from that key was forwarded already.
    """

    def setup(self) -> None:
        """Wait for nothing yet."""
        self._waiting: tuple[str, Callable[[int], None]] | None = None
        self._latest: Message | None = None  # the standby's latest message

    def expect(self, key: str, on_first: Callable[[int], None]) -> None:
        """Call ``on_first(arrival_ns)`` for the next message arriving from ``key``."""
        self._waiting = (key, on_first)

    def on_message(self, port: str, msg: Message) -> None:
        """Relay the message onto the request's key; report the first one of a new configuration.

        A message on ``standby`` is only kept (the latest one), not relayed."""
        if port == "standby":
            self._latest = msg
            return
        latest = self._latest
        if latest is not None and latest.key == msg.key:
            self._latest = None  # its configuration is the active one now: this message is newer
        self._first(msg.key)  # before relaying it: see the recovery record (dyknow.adaptation.events.Recovery)
        self.publish("out", msg.payload)

    def on_reconfigure(self, changes: Mapping[str, str]) -> None:
        """When ``in`` moved onto the standby's key, forward the standby's latest message now."""
        latest = self._latest
        if "standby" in changes:
            self._latest = None  # a new standby (or none): what the old one said is not its
        key = changes.get("in")
        if key is not None and latest is not None and latest.key == key:
            self._latest = None
            self._first(key)
            self.publish("out", latest.payload, origin_ns=latest.origin_ns)

    def _first(self, key: str) -> None:
        waiting = self._waiting
        if waiting is not None and key == waiting[0]:
            self._waiting = None
            waiting[1](time.time_ns())


ANCHOR_SPEC = TransformationSpec(
    label=ANCHOR_LABEL,
    source="dyknow.adaptation:RequestAnchor",
    ports=(Port("in", "in", queue=64), Port("out", "out")),
    description="Relays a request's stream onto its stable key (internal to request()).",
)
"""The anchor of a request without a standby."""

WARM_ANCHOR_SPEC = TransformationSpec(
    label=ANCHOR_LABEL,
    source="dyknow.adaptation:RequestAnchor",
    ports=(Port("in", "in", queue=64), Port("standby", "in", queue=1), Port("out", "out")),
    description="Relays a request's stream onto its stable key, and keeps its warm standby's latest message (internal to request()).",
)
"""The anchor of a request with a warm standby: port ``standby`` reads the standby's output."""


# ---------------------------------------------------------------------------- a request's anchor


def anchor_name(runtime: Runtime, tag: str) -> str:
    """A name for the anchor of a request of ``tag`` that no running unit has."""
    base = "request-" + "".join(c if c.isalnum() or c in "_-." else "-" for c in tag).strip("-")
    name, n = base, 1
    while runtime.has_unit(name):
        n += 1
        name = f"{base}-{n}"
    return name


def spawn_anchor(runtime: Runtime, knowledge: Knowledge, request: Request, input_key: str) -> None:
    """Spawn ``request``'s anchor (:attr:`Request.anchor`) reading ``input_key``; a warm request's
    also reads its standby's output, when it has one."""
    bindings = {"in": input_key, "out": request.key}
    spec = ANCHOR_SPEC
    if request.standby_mode == "warm":
        spec = WARM_ANCHOR_SPEC
        if request.standby_key is not None:
            bindings["standby"] = request.standby_key
    runtime.spawn(spec, request.anchor, bindings=bindings)
    knowledge.managed.add(request.anchor)
