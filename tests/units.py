"""Units used by the tests (their specs are in tests/units.xml); the generic stand-ins are in dyknow.testing."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any, ClassVar

from dyknow import Message, Unit
from dyknow.testing import Camera


class Counter(Unit):
    """Keeps state across messages and reconfigurations: publishes a running count."""

    def setup(self) -> None:
        self.count = 0
        self.reconfigured: list[dict[str, str]] = []
        self.reconfigured_event = threading.Event()

    def on_message(self, port: str, msg: Message) -> None:
        self.count += 1
        self.publish("out", {"count": self.count, "payload_seq": msg.seq})

    def on_reconfigure(self, changes: Any) -> None:
        self.reconfigured.append(dict(changes))
        self.reconfigured_event.set()


class Failing(Unit):
    """Raises on the message number given by param fail_at."""

    def setup(self) -> None:
        self.seen = 0

    def on_message(self, port: str, msg: Message) -> None:
        self.seen += 1
        if self.seen >= int(self.params.get("fail_at", 1)):
            raise RuntimeError(f"boom at message {self.seen}")
        self.publish("out", msg.payload)


class SetupFails(Unit):
    def setup(self) -> None:
        raise ValueError("cannot open the device")


class ConstructorFails(Unit):
    def __init__(self) -> None:
        raise RuntimeError("constructor exploded")


class Slow(Unit):
    """Sleeps in every callback (param delay_s)."""

    def setup(self) -> None:
        self.handled = 0
        self.started = threading.Event()

    def on_message(self, port: str, msg: Message) -> None:
        self.started.set()
        time.sleep(float(self.params.get("delay_s", 0.2)))
        self.handled += 1


class SelfDestroying(Unit):
    """Destroys itself on its first message."""

    def on_message(self, port: str, msg: Message) -> None:
        self.destroy()
        self.after_destroy_call = True


class Forwarder(Unit):
    """Publishes whatever it receives, from any input, on out."""

    def on_message(self, port: str, msg: Message) -> None:
        self.publish("out", msg.payload)


class Looping(Unit):
    """A source with a blocking run() loop (like a camera reader)."""

    def setup(self) -> None:
        self.stopped_cleanly = False

    def run(self, stop: threading.Event) -> None:
        n = 0
        while not stop.wait(0.005):
            n += 1
            self.publish("out", {"n": n})
        self.stopped_cleanly = True


class TornDown(Unit):
    """Records teardown in a class attribute the test can read after destroy."""

    torn_down: list[str] = []

    def teardown(self) -> None:
        TornDown.torn_down.append(self.name)


class StuckInTeardown(Unit):
    """Never returns from teardown() (a driver that hangs on close, say)."""

    def teardown(self) -> None:
        threading.Event().wait()


NOT_A_UNIT = 42


class NotAUnit:
    """A class that is not a Unit."""


class Picky(Unit):
    """Accepts only 2-D arrays; rejects anything else and keeps running."""

    def setup(self) -> None:
        self.accepted = 0

    def on_message(self, port: str, msg: Message) -> None:
        payload = msg.payload
        if not hasattr(payload, "ndim") or payload.ndim != 2:
            self.reject(port, f"expected a 2-D array; got {type(payload).__name__}")
            return
        self.accepted += 1
        if self.has_subscribers("out"):
            self.publish("out", payload)


class SlowSetup(Unit):
    """Takes ``setup_s`` seconds to set up (a detector building its model, say); records when.
    With the param ``fail``, its setup then fails (a device that times out)."""

    log_lock = threading.Lock()
    setups: ClassVar[list[tuple[str, str]]] = []  # (unit, "begin" | "end"), in order

    def setup(self) -> None:
        with SlowSetup.log_lock:
            SlowSetup.setups.append((self.name, "begin"))
        time.sleep(float(self.params.get("setup_s", 1.0)))
        with SlowSetup.log_lock:
            SlowSetup.setups.append((self.name, "end"))
        if self.params.get("fail"):
            raise RuntimeError("the device did not answer")

    def on_message(self, port: str, msg: Message) -> None:
        self.publish("out", msg.payload)


class HangingCamera(Camera):
    """A camera that starts publishing, then says so (it creates the file ``marker``) and holds
    its setup for ``hang_s`` (default 60): the spawn that started it is in flight that long, for
    a test to kill its manager meanwhile."""

    def setup(self) -> None:
        super().setup()
        Path(str(self.params["marker"])).touch()
        time.sleep(float(self.params.get("hang_s", 60.0)))


class TurnsSlow(Unit):
    """Quick, except that a message whose payload is "slow" takes ``delay_s`` to handle."""

    def setup(self) -> None:
        self.handled = 0

    def on_message(self, port: str, msg: Message) -> None:
        if msg.payload == "slow":
            time.sleep(float(self.params.get("delay_s", 0.5)))
        self.handled += 1


class TickingRelay(Unit):
    """Forwards every input to out (dyknow does it), and publishes "tick" on out from a timer."""

    forward_to = "out"

    def setup(self) -> None:
        self.create_timer(0.01, lambda: self.publish("out", "tick"))


class ForwardsAndHandles(Unit):
    """Asks dyknow to forward its inputs and also overrides on_message: refused at spawn."""

    forward_to = "out"

    def on_message(self, port: str, msg: Message) -> None:
        self.publish("out", msg.payload)


class Level(Unit):
    """Publishes ``{"value": value, "n": n}`` on out at ``rate_hz``: a reading of a sensor."""

    def setup(self) -> None:
        self.n = 0
        self.create_timer(1.0 / float(self.params.get("rate_hz", 20.0)), self.tick)

    def tick(self) -> None:
        self.n += 1
        self.publish("out", {"value": float(self.params.get("value", 1.0)), "n": self.n})


class Reading(Unit):
    """Publishes ``{"id": id, "n": n}`` on out at ``rate_hz``: a producer whose ``id`` (param, and
    attribute: a test may change it while it runs, as a repair would) a requirement can check."""

    def setup(self) -> None:
        self.n = 0
        self.id = int(self.params.get("id", 1))
        self.create_timer(1.0 / float(self.params.get("rate_hz", 20.0)), self.tick)

    def tick(self) -> None:
        self.n += 1
        self.publish("out", {"id": self.id, "n": self.n})


class Relapsing(Reading):
    """A :class:`Reading` that sends ``id`` 2 for ``fail_after_s`` after each start, then 1: a
    provider that relapses after every start (a requirement ``id == 2`` turns false), until a
    test sets :attr:`fixed` (every start from then on keeps sending 2)."""

    fixed = False

    def setup(self) -> None:
        super().setup()
        self.id = 2
        self.fail_at = time.monotonic() + float(self.params.get("fail_after_s", 8.0))

    def tick(self) -> None:
        if not Relapsing.fixed and time.monotonic() >= self.fail_at:
            self.id = 1
        super().tick()
