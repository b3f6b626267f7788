"""The :class:`Recorder`: dyknow streams to MCAP files that Foxglove and other MCAP tools can read.

A recorder subscribes to key expressions (or a unit feeds it messages) and writes each message to
an MCAP file, through the ``mcap`` library's writer. Every key gets its own channel; a key whose
payloads change kind (JSON, then bytes, say) gets one channel per kind, all with the key as
topic. How payloads are stored is :mod:`dyknow.recording.codecs`' table. The message header goes
into the MCAP message: ``log_time`` is the origin timestamp, ``publish_time`` the send timestamp
and ``sequence`` the sequence number. An origin stamped by another process's clock stays as
stamped, and the offset of that clock the recorder knew is recorded beside it, so that a replay
can correct it (:mod:`dyknow.recording.offsets`); a recorder with subscriptions of its own
estimates the offsets of the managers it finds (:meth:`dyknow.clocks.ClockTracker.follow`). The file is chunked and compressed (zstd by default, or lz4
or none) and has a summary with statistics and chunk, message and metadata indexes::

    from dyknow.recording import Recorder

    with Recorder(["robot/**"], "run.mcap", connect=["tcp/127.0.0.1:7447"]) as rec:
        rec.wait(10.0)        # wait for max_messages, or do something else, then close
    print(rec.count, rec.topics)

Nothing is lost on the way to the disk. A Zenoh callback only puts the message on a queue, and a
writer thread of its own encodes and writes it. Chunks are handed to the operating system as they
fill, and at least every ``flush_interval_s``. So a recorder killed with SIGKILL leaves a file
whose complete chunks a recovering reader (``Player(..., recover=True)``, ``dyknow replay
--recover``) still replays. :meth:`Recorder.close` writes the summary and the footer. A write
that fails, for example on a full disk, stops the recorder with a :class:`RecordingError` that
names the file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import queue
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from importlib import metadata as _metadata
from typing import Any

from mcap.writer import CompressionType, IndexType, Writer

from dyknow.access import TlsFiles
from dyknow.clocks import CLOCKS, ClockTable, ClockTracker
from dyknow.errors import ClosedError, RecordingError
from dyknow.message import CLOCK_ID, Message
from dyknow.recording.codecs import PAYLOAD_METADATA, PROTOBUF_SCHEMAS, encode, json_schema
from dyknow.recording.offsets import CLOCK_METADATA, CLOCKS_SCHEMA, CLOCKS_TOPIC, OffsetLog
from dyknow.transport import Session, Subscriber, check_key_expr, make_config

__all__ = ["COMPRESSIONS", "Recorder"]

log = logging.getLogger(__name__)

#: The chunk compressions :class:`Recorder` accepts.
COMPRESSIONS: tuple[str, ...] = ("zstd", "lz4", "none")

_COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

_STOP = object()


class _Output:
    """The file under the MCAP writer: every write goes to the operating system at once.

    The writer writes a whole chunk (and its message indexes) per call, so flushing each write
    costs little and a process killed at any moment leaves every complete chunk on disk.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self._file = open(path, "wb")  # noqa: SIM115 (closed by close())
        self.written = 0

    def write(self, data: bytes) -> int:
        count = self._file.write(data)
        self._file.flush()
        self.written += len(data)
        return count

    def tell(self) -> int:
        return self._file.tell()

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def _write_error(path: str, exc: OSError, what: str) -> RecordingError:
    reason = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return RecordingError(f"cannot write the file: {reason} (the disk is full); {what}", where=path)
    return RecordingError(f"cannot write the file: {reason}; {what}", where=path)


def _library() -> str:
    try:
        version = _metadata.version("dyknow")
    except _metadata.PackageNotFoundError:
        version = "dev"
    return f"dyknow {version}"


class Recorder:
    """Records dyknow streams to an MCAP file. A context manager; ``close()`` finalizes the file.

    ``key_exprs``: key expressions to subscribe to (wildcards allowed). They are received through
    ``session``, or through a session of the recorder's own connected to ``connect`` (or set up
    by ``zenoh_config``). Zenoh delivers a session only what *other* sessions publish, so pass a
    session other than the publishers'. With no key expressions the recorder takes messages
    through :meth:`write` only, which is how the ``recorder`` unit feeds it.

    ``compression`` is one of :data:`COMPRESSIONS`. ``chunk_size`` is the uncompressed size at
    which a chunk is written. ``flush_interval_s`` bounds how long a message stays in memory
    before its chunk goes to disk. ``max_messages`` stops the recording after that many messages
    (:meth:`wait` returns then). ``metadata`` goes into an MCAP metadata record named ``dyknow``.
    ``track_clocks``: with subscriptions, estimate the clock offsets of the managers found (for a
    recorder in a manager's process, that manager's estimates are used in any case).

    Raises :class:`RecordingError` when the file cannot be created or written.
    """

    def __init__(
        self,
        key_exprs: Sequence[str] | str = (),
        path: str | os.PathLike[str] = "recording.mcap",
        *,
        session: Session | None = None,
        connect: Iterable[str] = (),
        zenoh_config: str | os.PathLike[str] | None = None,
        tls: TlsFiles | None = None,
        compression: str = "zstd",
        chunk_size: int = 1024 * 1024,
        flush_interval_s: float = 1.0,
        max_messages: int | None = None,
        metadata: Mapping[str, str] | None = None,
        track_clocks: bool = True,
    ) -> None:
        keys = [key_exprs] if isinstance(key_exprs, str) else list(key_exprs)
        for key in keys:
            check_key_expr(key, what="key expression to record")
        if compression not in _COMPRESSIONS:
            raise RecordingError(f"got {compression!r}", where="compression", expected=f"one of {', '.join(COMPRESSIONS)}")
        if chunk_size < 1:
            raise RecordingError(f"got {chunk_size}", where="chunk_size", expected="a positive number of bytes")
        if not flush_interval_s > 0:
            raise RecordingError(f"got {flush_interval_s}", where="flush_interval_s", expected="a positive number of seconds")
        if max_messages is not None and max_messages < 1:
            raise RecordingError(f"got {max_messages}", where="max_messages", expected="a positive number")
        self.path = os.fspath(path)
        self.key_exprs: tuple[str, ...] = tuple(keys)
        self.max_messages = max_messages
        self._flush_interval_s = flush_interval_s
        self._lock = threading.Lock()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._done = threading.Event()
        self._closed = False
        self._accepted = 0
        self._count = 0
        self._dropped = 0
        self._topics: dict[str, int] = {}
        self._error: RecordingError | None = None
        self._subscribers: list[Subscriber] = []
        self._session: Session | None = None
        self._own_session = False
        try:
            self._out = _Output(self.path)
        except OSError as exc:
            hint = " (does the folder exist?)" if isinstance(exc, FileNotFoundError) else ""
            raise RecordingError(f"cannot create the file: {exc.strerror or exc}{hint}", where=self.path) from exc
        try:
            self._writer = Writer(
                self._out,  # type: ignore[arg-type]
                chunk_size=chunk_size,
                compression=_COMPRESSIONS[compression],
                index_types=IndexType.ALL,
                repeat_channels=True,
                repeat_schemas=True,
                use_chunking=True,
                use_statistics=True,
                use_summary_offsets=True,
                enable_crcs=True,
            )
            self._writer.start(profile="", library=_library())
            info = {"key_exprs": json.dumps(list(keys)), "started_ns": str(time.time_ns())}
            self._writer.add_metadata("dyknow", {**info, **dict(metadata or {})})
        except OSError as exc:
            with contextlib.suppress(OSError):  # the same error again, flushing what the failed write left
                self._out.close()
            raise _write_error(self.path, exc, "nothing was recorded") from exc
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[tuple[str, str, str, str, int], int] = {}
        self._offsets = OffsetLog(CLOCK_ID)
        self._clock_table: ClockTable | None = None  # the offsets of this recorder's own tracker, if it has one
        self._tracker: ClockTracker | None = None
        self._thread = threading.Thread(target=self._run, name=f"dyknow-recorder:{os.path.basename(self.path)}", daemon=True)
        self._thread.start()
        if keys:
            try:
                if session is None:
                    session = Session(make_config(connect=list(connect), config_file=zenoh_config, tls=tls))
                    self._own_session = True
                self._session = session
                if track_clocks:
                    self._clock_table = ClockTable()
                    self._tracker = ClockTracker(session, self._clock_table)
                    self._tracker.follow()
                for key in keys:
                    self._subscribers.append(session.declare_subscriber(key, self.write, self._on_error))
            except BaseException:
                self.close()
                with contextlib.suppress(OSError):
                    os.remove(self.path)  # nothing was recorded: leave no empty file behind
                raise
        log.info("recording %s to %s", ", ".join(keys) or "(fed by write())", self.path)

    # ------------------------------------------------------------------ state

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "recording"
        return f"Recorder({self.path!r}, {state}, {self._count} messages)"

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    @property
    def count(self) -> int:
        """Messages written to the file so far (all of them once closed)."""
        return self._count

    @property
    def topics(self) -> dict[str, int]:
        """Messages written so far per key."""
        return dict(self._topics)

    @property
    def dropped(self) -> int:
        """Messages that arrived but are not in the file: after a write error, or at a close that timed out."""
        return self._dropped

    @property
    def error(self) -> RecordingError | None:
        """The error that stopped the recording, if any."""
        return self._error

    @property
    def bytes_written(self) -> int:
        """Bytes handed to the file so far (its size once closed)."""
        return self._out.written

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait up to ``timeout_s`` seconds (None: for ever) until ``max_messages`` were received
        or the recording failed; True if so."""
        return self._done.wait(timeout_s)

    # ------------------------------------------------------------------ recording

    def write(self, msg: Message) -> None:
        """Record one message (any thread). Its key names the channel.

        Raises :class:`ClosedError` after close and the recording's error after a failed write.
        """
        with self._lock:
            if self._closed:
                raise ClosedError("the recorder is closed; start a new one", where=self.path)
            if self._error is not None:
                raise self._error
            if self.max_messages is not None and self._accepted >= self.max_messages:
                return
            self._accepted += 1
            self._queue.put(msg)
            if self._accepted == self.max_messages:
                self._done.set()

    def _on_error(self, exc: BaseException) -> None:
        # After a failed write or during close every message raises the same error: say it once.
        if exc is not self._error and not isinstance(exc, ClosedError):
            log.warning("recorder %s: %s", self.path, exc)

    def _run(self) -> None:
        """The writer thread: encodes and writes messages, flushes chunks that get old."""
        interval = self._flush_interval_s
        deadline = time.monotonic() + interval
        pending = False
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            if item is not None:
                if self._error is not None:
                    self._dropped += 1
                else:
                    self._write(item)
                    pending = True
            if time.monotonic() >= deadline:
                if pending and self._error is None:
                    try:
                        self._writer.flush()
                    except OSError as exc:
                        self._fail(exc)
                    pending = False
                deadline = time.monotonic() + interval

    def _write(self, msg: Message) -> None:
        try:
            kind, encoding, schema_name, data = encode(msg.payload, msg.origin_ns)
        except RecordingError as exc:
            self._dropped += 1
            log.warning("recorder %s: message on %s not recorded: %s", self.path, msg.key, exc)
            return
        try:
            clock = self._offsets.clock_of(msg.origin_clock)
            if clock != CLOCK_ID:
                self._clock_records(clock)
            channel = self._channel(msg.key, kind, encoding, schema_name, msg.payload, clock)
            self._writer.add_message(
                channel_id=channel,
                log_time=max(0, msg.origin_ns),
                publish_time=max(0, msg.send_ns),
                sequence=msg.seq & 0xFFFFFFFF,
                data=data,
            )
        except OSError as exc:
            self._dropped += 1
            self._fail(exc)
            return
        self._count += 1
        self._topics[msg.key] = self._topics.get(msg.key, 0) + 1

    def _fail(self, exc: OSError) -> None:
        with self._lock:
            if self._error is None:
                what = f"recording stopped after {self._count} messages; the complete chunks before it are readable"
                self._error = _write_error(self.path, exc, what)
                self._error.__cause__ = exc
                log.error("%s", self._error)
        self._done.set()

    def _clock_records(self, clock: int) -> None:
        """Write what the recording needs to know of ``clock`` (another's) before its next message."""
        tables = [t for t in (self._clock_table, CLOCKS) if t is not None]
        offset = next((o for o in (t.offset(clock) for t in tables) if o is not None), None)
        uncertainty = next((t.uncertainty(clock) for t in tables if t.offset(clock) is not None), None)
        for record in self._offsets.note(clock, offset, uncertainty, time.time_ns()):
            channel = self._channels.get((CLOCKS_TOPIC, "json", "json", CLOCKS_TOPIC, CLOCK_ID))
            if channel is None:
                schema_id = self._writer.register_schema(CLOCKS_TOPIC, "jsonschema", json.dumps(CLOCKS_SCHEMA).encode())
                channel = self._writer.register_channel(CLOCKS_TOPIC, "json", schema_id, {PAYLOAD_METADATA: "json"})
                self._channels[(CLOCKS_TOPIC, "json", "json", CLOCKS_TOPIC, CLOCK_ID)] = channel
            self._writer.add_message(channel_id=channel, log_time=max(0, record.at_ns), publish_time=max(0, record.at_ns), sequence=0, data=record.to_json())

    def _channel(self, key: str, kind: str, encoding: str, schema_name: str, payload: Any, clock: int = CLOCK_ID) -> int:
        signature = (key, kind, encoding, schema_name, clock)
        channel = self._channels.get(signature)
        if channel is not None:
            return channel
        schema_id = 0
        if encoding == "json":
            schema = (key, "jsonschema", json.dumps({"title": key, **json_schema(payload)}).encode())
        elif encoding == "protobuf":
            schema = (schema_name, "protobuf", PROTOBUF_SCHEMAS[schema_name])
        else:
            schema = None
        if schema is not None:
            schema_id = self._schemas.get(schema, 0)
            if not schema_id:
                schema_id = self._schemas[schema] = self._writer.register_schema(*schema)
        metadata = {PAYLOAD_METADATA: kind} if clock == CLOCK_ID else {PAYLOAD_METADATA: kind, CLOCK_METADATA: f"{clock:08x}"}
        channel = self._channels[signature] = self._writer.register_channel(key, encoding, schema_id, metadata)
        return channel

    # ------------------------------------------------------------------ closing

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop receiving, write what is queued, then the summary and footer. Safe to call twice.

        Waits up to ``timeout_s`` seconds for the queue to drain; what is still queued then is
        dropped (and counted in :attr:`dropped`) so that close never hangs. Raises the
        recording's :class:`RecordingError` if a write failed.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for sub in reversed(self._subscribers):
            sub.undeclare()
        self._subscribers.clear()
        if self._tracker is not None:
            self._tracker.close()
        if self._own_session and self._session is not None:
            self._session.close()
        self._session = None
        self._queue.put(_STOP)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            # Too much queued: keep what is written, drop the rest, and still finalize the file.
            with self._lock:
                if self._error is None:
                    self._error = RecordingError(f"writing did not finish within {timeout_s:g} s; the rest was dropped", where=self.path)
            self._thread.join(2.0)
        if self._thread.is_alive():
            log.error("recorder %s: the writer thread is stuck; the file is left without its summary", self.path)
            self._done.set()
            raise RecordingError(
                "cannot finish the file: its writer is stuck (a hung disk?); the complete chunks are readable", where=self.path
            )
        while True:
            try:
                if self._queue.get_nowait() is not _STOP:
                    self._dropped += 1
            except queue.Empty:
                break
        self._done.set()
        error = self._error
        try:
            self._writer.finish()
        except OSError as exc:
            if error is None:
                error = _write_error(self.path, exc, "the file has no summary; its complete chunks are readable")
        finally:
            try:
                self._out.close()
            except OSError as exc:
                if error is None:
                    error = _write_error(self.path, exc, "the file may be incomplete")
        self._error = error
        log.info("recorded %d messages to %s", self._count, self.path)
        if error is not None:
            raise error
