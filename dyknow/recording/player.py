"""The :class:`Player`: replaying a recording into dyknow streams, and which key each topic replays on.

A player replays in log-time order at the original pace, scaled by ``rate``, or as fast as
possible (``rate=math.inf``); once or in a loop; limited to some topics and a time window, with
topics remapped to other keys::

    from dyknow.recording import Player

    with Player("run.mcap", rate=2.0, topics=["/camera/image"], remap={"/camera/image": "replay/image"}) as player:
        player.publish(connect=["tcp/127.0.0.1:7447"])    # into Zenoh, until the end of the file

Each replayed :class:`~dyknow.message.Message` carries the file's sequence number, the message's
``log_time`` as its origin timestamp (it stays as in the file, also when looping) and the replay
time as its send timestamp. An origin stamped by another clock than the recorder's is corrected
by the offset recorded beside it (:mod:`dyknow.recording.offsets`), a time of the recording's
clock; one whose clock's offset the recorder did not know stays as stamped, with origin clock 0
(unknown: a consumer leaves it out of its figures). The pace follows the corrected times; the
order stays the file's (by stamped time). The clock records themselves are not replayed. A topic replays on the key :func:`key_for_topic` gives, such as
``camera/image`` for ``/camera/image``, unless it is remapped. Payloads are decoded from the
file's encodings as :mod:`dyknow.recording.codecs` says; ``decode=False`` delivers every message
as the bytes stored in the file.

A truncated or corrupt file raises :class:`~dyknow.errors.RecordingError` naming the file and
the offset of the damage. With ``recover=True`` the valid part is replayed, with a warning
(``problem`` says what was skipped). A file whose writer was killed, so it has no summary,
replays every complete chunk this way.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any

from dyknow.access import TlsFiles
from dyknow.errors import BindingError, ClosedError, RecordingError, did_you_mean
from dyknow.message import CLOCK_ID, Message
from dyknow.recording.codecs import Decoders
from dyknow.recording.offsets import CLOCK_METADATA, CLOCKS_TOPIC, ClockRecord, Offsets
from dyknow.recording.reader import ChannelInfo, ReadLimits, RecordedMessage, Recording, RecordingInfo
from dyknow.transport import Session, check_key_expr, is_wild, key_exprs_intersect, make_config

__all__ = ["Player", "key_for_topic"]

_INT64_MAX = 2**63 - 1


# --------------------------------------------------------------------------- topics and keys


def key_for_topic(topic: str) -> str:
    """The Zenoh key a recorded topic replays on, unless remapped.

    Leading, trailing and doubled slashes go (ROS's ``/camera/image`` becomes ``camera/image``)
    and characters Zenoh keys cannot hold (``* $ ? #``) become ``_``.

    >>> key_for_topic("/camera/image")
    'camera/image'
    """
    chunks = [c for c in topic.split("/") if c]
    return "/".join(c.translate(_KEY_UNSAFE) for c in chunks)


_KEY_UNSAFE = str.maketrans({c: "_" for c in "*$?#"})


def _matches(pattern: str, topic: str) -> bool:
    """Whether a ``topics`` entry selects ``topic``: the topic itself, its key, or a key expression."""
    if pattern == topic:
        return True
    key = key_for_topic(topic)
    if not key:
        return False
    if pattern.strip("/") == key:
        return True
    if is_wild(pattern):
        try:
            return key_exprs_intersect(pattern.strip("/"), key)
        except Exception:
            return False
    return False


def _remapped(remap: Mapping[str, str], topic: str) -> str | None:
    key = key_for_topic(topic)
    for source, target in remap.items():
        if source == topic or (key and source.strip("/") == key):
            return target
    for source, target in remap.items():  # prefixes: "robot/**=replay/**"
        if source.endswith("/**") and target.endswith("/**"):
            prefix = source[:-3].strip("/")
            if key == prefix or key.startswith(prefix + "/"):
                return target[:-3] + key[len(prefix) :]
    return None


# --------------------------------------------------------------------------- the player


_Sink = Callable[[Message, RecordedMessage], None]


class Player:
    """Replays an MCAP recording. A context manager; ``close()`` is safe twice and stops a replay.

    ``rate`` scales the pace (2.0: twice as fast; ``math.inf``: as fast as possible). ``loop``
    starts over at the end. ``start_s``/``end_s`` select a window in seconds from the first
    message. ``topics`` selects topics: a topic name, its key, or a key expression such as
    ``camera/**``. ``remap`` maps a topic (or a ``prefix/**``) to the key it replays on.
    ``recover`` reads what is valid in a damaged file. ``decode=False`` delivers the stored bytes.
    ``correct_clocks=False`` leaves every origin of another clock as stamped (and marked unknown).
    ``limits`` bound what reading the file holds in memory (:class:`~dyknow.recording.ReadLimits`).

    Raises :class:`RecordingError` for a file that cannot be read, a topic or remap that matches
    nothing, or a topic that cannot be a Zenoh key (remap it).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        rate: float = 1.0,
        loop: bool = False,
        start_s: float | None = None,
        end_s: float | None = None,
        topics: Sequence[str] = (),
        remap: Mapping[str, str] | None = None,
        recover: bool = False,
        decode: bool = True,
        correct_clocks: bool = True,
        limits: ReadLimits | None = None,
    ) -> None:
        if not (isinstance(rate, (int, float)) and rate > 0):
            raise RecordingError(
                f"got {rate!r}", where="rate", expected="a positive number (2.0 is twice as fast; math.inf as fast as possible)"
            )
        if start_s is not None and not start_s >= 0:
            raise RecordingError(f"got {start_s!r}", where="start", expected="seconds from the first message, 0 or more")
        if end_s is not None and not end_s >= (start_s or 0.0):
            raise RecordingError(
                f"got {end_s!r}", where="end", expected=f"seconds from the first message, not before start ({start_s or 0.0:g})"
            )
        self.rate = float(rate)
        self.loop = loop
        self.decode = decode
        self._stop = threading.Event()
        self._playing = threading.Lock()
        #: After :meth:`publish`: per key, the messages put while no subscriber matched it (delivered to no one).
        self.unmatched: dict[str, int] = {}
        self.recording = Recording(path, recover=recover, limits=limits)
        try:
            self._select(list(topics), dict(remap or {}), start_s, end_s)
            self._offsets = self._read_offsets() if correct_clocks else Offsets(())
        except BaseException:
            self.recording.close()
            raise
        self._decoders = Decoders(self.recording.path)

    def _select(self, topics: list[str], remap: dict[str, str], start_s: float | None, end_s: float | None) -> None:
        path = self.recording.path
        everything = [c for c in self.recording.channels if c.topic != CLOCKS_TOPIC]  # (bookkeeping, not a stream)
        names = sorted({c.topic for c in everything})
        for pattern in topics:
            if not any(_matches(pattern, c.topic) for c in everything):
                listing = ", ".join(map(repr, names)) or "none"
                raise RecordingError(
                    f"no topic matches {pattern!r}", where=path, expected=f"one of its topics {listing}{did_you_mean(pattern, names)}"
                )
        chosen = [c for c in everything if not topics or any(_matches(p, c.topic) for p in topics)]
        for source, target in remap.items():
            if not any(_remapped({source: target}, c.topic) is not None for c in chosen):
                listing = ", ".join(repr(c.topic) for c in chosen) or "none"
                raise RecordingError(
                    f"no replayed topic of {path} is {source!r}",
                    where=f"remap {source}={target}",
                    expected=f"one of {listing}{did_you_mean(source, names)}",
                )
        self._keys: dict[int, str] = {}
        self._bad_keys: list[str] = []  # only publish() needs valid keys; reading and play() do not
        for channel in chosen:
            key = _remapped(remap, channel.topic)
            if key is None:
                key = key_for_topic(channel.topic)
            try:
                check_key_expr(key, what=f"the key for topic {channel.topic!r}", concrete=True)
            except BindingError as exc:
                self._bad_keys.append(f"{exc}; remap the topic to a key, e.g. --remap '{channel.topic}=replay/topic'")
            self._keys[channel.id] = key
        self.channels: tuple[ChannelInfo, ...] = tuple(chosen)
        first = self.recording.info.start_ns or 0
        self._start_ns = None if start_s is None else first + round(start_s * 1e9)
        self._end_ns = None if end_s is None else first + round(end_s * 1e9)

    def __enter__(self) -> Player:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Player({self.recording.path!r}, {len(self.channels)} topics, rate={self.rate:g})"

    @property
    def info(self) -> RecordingInfo:
        """The recording's summary (all its channels, not only the selected ones)."""
        return self.recording.info

    @property
    def problem(self) -> str | None:
        """What is damaged in the file, when it was opened with ``recover``."""
        return self.recording.problem

    @property
    def keys(self) -> dict[str, str]:
        """The key each replayed topic is published on."""
        return {c.topic: self._keys[c.id] for c in self.channels}

    def stop(self) -> None:
        """Make a running :meth:`play` return soon (any thread)."""
        self._stop.set()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop a running replay (waiting up to ``timeout_s`` seconds for it) and close the file; safe twice."""
        self._stop.set()
        if self._playing.acquire(timeout=timeout_s):
            self._playing.release()
        self.recording.close()

    # ------------------------------------------------------------------ reading

    def messages(self) -> Iterator[RecordedMessage]:
        """The selected messages once, in log-time order, without pacing (``dyknow mcap cat``)."""
        if self.recording.closed:
            raise ClosedError("the player is closed; open a new one", where=self.recording.path)
        return self.recording.messages(self._keys, self._start_ns, self._end_ns)

    def _read_offsets(self) -> Offsets:
        """The recording's clock records, if any of the selected channels needs them."""
        if not any(CLOCK_METADATA in c.metadata for c in self.channels):
            return Offsets(())
        ids = [c.id for c in self.recording.channels if c.topic == CLOCKS_TOPIC]
        where = f"{self.recording.path}: {CLOCKS_TOPIC}"
        records: list[ClockRecord] = []
        for message in self.recording.messages(ids):
            try:
                records.append(ClockRecord.from_json(message.data, f"{where} #{len(records) + 1}"))
            except RecordingError:
                if not self.recording.problem:  # (read with recover: what is valid is used)
                    raise
        return Offsets(records)

    def corrected_origin(self, record: RecordedMessage) -> int | None:
        """The message's origin time on the recording's clock: its log time when the recorder's own
        clock stamped it, corrected by the recorded offset when another did, None when that
        clock's offset was not known (or ``correct_clocks`` is off)."""
        clock = record.channel.metadata.get(CLOCK_METADATA)
        if clock is None:
            return record.log_time_ns
        try:
            found = self._offsets.corrected(int(clock, 16), record.log_time_ns)
        except ValueError:
            return None
        return None if found is None else found[0]

    def payload(self, record: RecordedMessage) -> Any:
        """The dyknow payload of a recorded message (its bytes with ``decode=False``)."""
        return self._decoders.payload(record.channel, record.data) if self.decode else record.data

    # ------------------------------------------------------------------ replaying

    def play(self, sink: _Sink, *, stop: threading.Event | None = None) -> int:
        """Replay at the set pace, calling ``sink(message, record)`` for each message.

        ``message`` is the dyknow :class:`~dyknow.message.Message` a publisher would send (the
        decoded payload, the file's sequence number, log time as origin, now as send time, the
        replay key); ``record`` is the message as stored. Returns how many were delivered, when
        the file ends (without ``loop``), ``stop`` is set, or :meth:`stop`/:meth:`close` is called.
        """
        with self._playing:
            if self.recording.closed:
                raise ClosedError("the player is closed; open a new one", where=self.recording.path)
            self._stop.clear()  # stop() and close() end the replay running when they are called
            count = 0
            while True:
                delivered = 0
                first: tuple[int, int] | None = None
                for record in self.messages():
                    if self._stopped(stop):
                        return count
                    key = self._keys[record.channel.id]
                    payload = self.payload(record)
                    corrected = self.corrected_origin(record)
                    at = record.log_time_ns if corrected is None else corrected
                    if self.rate != math.inf:
                        if first is None:
                            first = (at, time.monotonic_ns())
                        due = first[1] + int((at - first[0]) / self.rate)
                        while (now := time.monotonic_ns()) < due:  # never early, even if a wait wakes up early
                            if self._wait((due - now) / 1e9, stop):
                                return count
                    origin = min(max(at, -_INT64_MAX), _INT64_MAX)
                    clock = CLOCK_ID if corrected is not None else 0  # (0: a clock whose offset is not known)
                    sink(Message(payload, record.sequence, origin, time.time_ns(), key, origin_clock=clock), record)
                    count += 1
                    delivered += 1
                if not self.loop or not delivered or self._stopped(stop):
                    return count

    def _stopped(self, stop: threading.Event | None) -> bool:
        return self._stop.is_set() or (stop is not None and stop.is_set())

    def _wait(self, seconds: float, stop: threading.Event | None) -> bool:
        """Sleep ``seconds`` unless stopped first; True if stopped."""
        if stop is None:
            return self._stop.wait(seconds)
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return self._stopped(stop)
            if stop.wait(min(left, 0.05)) or self._stop.is_set():
                return True

    def publish(
        self,
        session: Session | None = None,
        *,
        connect: Iterable[str] = (),
        zenoh_config: str | os.PathLike[str] | None = None,
        tls: TlsFiles | None = None,
        stop: threading.Event | None = None,
        wait_s: float = 0.0,
    ) -> int:
        """Replay into Zenoh: each topic on its key, through ``session`` or a session of its own.

        ``wait_s``: first wait up to that long for every key to have a subscriber (Zenoh's
        matching status: through routers and other managers too), so that consumers that are
        starting up get the first messages; it starts at once when they all have. Returns how many
        were published; :attr:`unmatched` then says, per key, how many of them were put while no
        subscriber matched it (delivered to no one). Raises :class:`RecordingError` when a topic
        cannot be a Zenoh key (remap it).
        """
        if self._bad_keys:
            raise RecordingError(self._bad_keys[0], where=self.recording.path)
        if self.recording.closed:
            raise ClosedError("the player is closed; open a new one", where=self.recording.path)
        self._stop.clear()
        own = session is None
        if session is None:
            session = Session(make_config(connect=list(connect), config_file=zenoh_config, tls=tls))
        publishers = {}
        try:
            for key in dict.fromkeys(self._keys.values()):
                publishers[key] = session.declare_publisher(key, reliable=True)  # a replay loses nothing
            deadline = time.monotonic() + wait_s
            while not all(p.matched for p in publishers.values()) and time.monotonic() < deadline:
                if self._wait(min(0.02, max(0.0, deadline - time.monotonic())), stop):
                    return 0

            unmatched = self.unmatched = dict.fromkeys(publishers, 0)

            def send(msg: Message, record: RecordedMessage) -> None:
                publisher = publishers[msg.key]
                if not publisher.matched:
                    unmatched[msg.key] += 1
                publisher.put(msg)

            sent = self.play(send, stop=stop)
            session.flush()  # what is still queued must reach the subscribers before we close
            return sent
        finally:
            for publisher in reversed(publishers.values()):
                publisher.undeclare()
            if own:
                session.close()
