"""Recording units: attach a recorder to any stream, or replay a recording where a sensor is missing.

Their specs are in ``specs/recording.xml``::

    manager.spawn("recorder", "rec1", params={"path": "run.mcap"}, bindings={"in": "robot/**"})
    manager.spawn("replay(Recorded)", "cam", params={"file": "run.mcap", "topic": "robot/camera"})
"""

from __future__ import annotations

import math
import threading

from dyknow import Message, Unit
from dyknow.errors import RecordingError
from dyknow.recording import Player, RecordedMessage, Recorder

__all__ = ["RecorderUnit", "ReplaySource"]


class RecorderUnit(Unit):
    """Records every message arriving on ``in`` to the MCAP file ``path``.

    Bind ``in`` to any key expression, wildcards included; each key gets a channel of its own.
    Rebinding ``in`` at runtime records the new keys into the same file. The file is finalized
    when the unit is destroyed. A write that fails (a full disk, say) marks the unit failed with
    the recorder's error.
    """

    path_params = {"path": "write"}

    def setup(self) -> None:
        """Open the recording file named by the ``path`` param."""
        self.recorder = Recorder(
            (),
            str(self.params.get("path", "recording.mcap")),
            compression=str(self.params.get("compression", "zstd")),
            metadata={"unit": self.name},
        )

    def on_message(self, port: str, msg: Message) -> None:
        """Write the message to the file."""
        self.recorder.write(msg)

    def teardown(self) -> None:
        """Finish the file (summary and footer)."""
        self.recorder.close()


class ReplaySource(Unit):
    """Replays one topic of an MCAP recording on ``out``, with the origin timestamps of the file.

    Params: ``file``; ``topic`` (may be left empty when the file has one topic); ``rate`` (1.0
    is the original pace, 0 as fast as possible); ``loop``; ``recover`` (replay what is valid in
    a damaged file). Payloads are decoded as :class:`dyknow.recording.Player` does: images arrive
    as numpy arrays.
    """

    path_params = {"file": "read"}

    def setup(self) -> None:
        """Open the file and select its topic."""
        topic = str(self.params.get("topic", "")).strip()
        rate = float(self.params.get("rate", 1.0))
        if rate < 0:
            raise RecordingError(
                f"got {rate}", where=f"param 'rate' of {self.name!r}", expected="a positive number, or 0 for as fast as possible"
            )
        self.player = Player(
            str(self.params["file"]),
            rate=rate or math.inf,
            loop=bool(self.params.get("loop", False)),
            topics=[topic] if topic else (),
            recover=bool(self.params.get("recover", False)),
        )
        if len(self.player.channels) != 1:
            self.player.close()
            topics = ", ".join(repr(c.topic) for c in self.player.channels) or "none"
            # a hint, not an "expected" value: it stays at the end of ``what``, and the message reads as before
            raise RecordingError(
                f"replay unit {self.name!r} replays one topic, and {topic or 'no topic'!r} selects "
                f"{len(self.player.channels)}: {topics}; set param topic to one of them",
                where=str(self.params["file"]),
            )
        self.replayed = 0
        self.finished = threading.Event()

    def run(self, stop: threading.Event) -> None:
        """Replay until the file ends or the unit stops."""
        self.player.play(self._deliver, stop=stop)
        self.finished.set()

    def _deliver(self, msg: Message, record: RecordedMessage) -> None:
        self.publish("out", msg.payload, origin_ns=msg.origin_ns)
        self.replayed += 1

    def teardown(self) -> None:
        """Close the file."""
        self.player.close()
