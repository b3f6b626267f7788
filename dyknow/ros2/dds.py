"""ROS 2 over DDS (its default middleware), through Cyclone DDS's Python binding.

ROS 2's DDS conventions (rmw_fastrtps and rmw_cyclonedds alike): a topic ``/chatter`` is the DDS
topic ``rt/chatter``; its type is named ``std_msgs::msg::dds_::String_``; samples are the same
CDR (XCDR1, with the encapsulation header) as on rmw_zenoh. The DDS types are built on the fly
from the definitions of :class:`~dyknow.ros2.types.TypeSupport` (one ``IdlStruct`` per ROS type,
nested types included), and a sample is handed over as its CDR bytes, so one codec
(:mod:`dyknow.ros2.types`) reads and writes both middlewares.

Discovery stays on loopback unless told otherwise (dyknow's default): a participant uses
:data:`LOOPBACK_CONFIG` (unicast to 127.0.0.1, no multicast), which ROS 2 nodes reach with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; give a Cyclone XML configuration to join a network.
DDS has no rmw_zenoh attachment: a received sample's :class:`Received` carries the DDS source
timestamp, sequence number 0 and a zero GID.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from dyknow.errors import BindingError, ClosedError, DyKnowError, ServiceError
from dyknow.ros2.attachment import Attachment
from dyknow.ros2.names import (
    DEFAULT_QOS,
    Durability,
    QoS,
    Reliability,
    check_topic,
    dds_reply_topic,
    dds_request_topic,
    dds_type_name,
    ros_type_name,
)
from dyknow.ros2.node import DEFAULT_MAX_MESSAGE_BYTES, UNTYPED_MAX_MESSAGE_BYTES, Received
from dyknow.ros2.services import DEFAULT_MAX_REQUEST_BYTES, as_message
from dyknow.ros2.types import MAX_CDR_BYTES, TypeSupport

__all__ = ["FASTDDS_PROFILE", "LOOPBACK_CONFIG", "DdsClient", "DdsNode", "DdsPublisher", "DdsService", "DdsSubscription", "unicast_config"]

log = logging.getLogger(__name__)

#: A Fast DDS profile for the ROS 2 nodes that talk to dyknow over DDS
#: (``FASTDDS_DEFAULT_PROFILES_FILE``): it turns Fast DDS's type propagation off. Fast DDS 3
#: sends type objects for sequences of plain types (an Image's ``data``) that Cyclone 11 refuses
#: ("invalid type object"), and then such a topic never matches; without type objects it matches
#: by type name, as ROS 2 names types. Strings and other types without such sequences need it not.
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_profile.xml")

#: The most publications and subscriptions :meth:`DdsNode.topics` reads.
MAX_DISCOVERED = 10_000

#: Cyclone DDS on loopback only: unicast discovery to 127.0.0.1 (participant indices 0 to 30), and
#: datagrams of up to 64 kB (loopback's MTU; Cyclone's default 14 kB made a 640x480 image some 700
#: datagrams, and cost the relay of benchmarks/ros2.py about 0.4 ms more CPU per frame). A
#: configuration for a real network keeps Cyclone's defaults there (an Ethernet MTU is 1,500).
LOOPBACK_CONFIG = (
    '<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
    "<AllowMulticast>false</AllowMulticast><MaxMessageSize>65500B</MaxMessageSize><FragmentSize>64000B</FragmentSize></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    '<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
)


def unicast_config(address: str, peers: Sequence[str]) -> str:
    """A Cyclone configuration for a network without multicast (or where it is not wanted): this
    host's interface of ``address``, discovery by unicast to ``peers`` (the hosts of the ROS 2
    nodes; ``ROS_STATIC_PEERS`` is their side of it). Raises :class:`BindingError` for an
    address that is not IPv4 or IPv6."""
    import ipaddress

    for where, text in (("address", address), *(("peers", peer) for peer in peers)):
        try:
            ipaddress.ip_address(text)
        except ValueError:
            raise BindingError(f"{where} {text!r}", where="DDS unicast configuration", expected="an IPv4 or IPv6 address") from None
    found = "".join(f'<Peer address="{peer}"/>' for peer in peers)
    return (
        f'<CycloneDDS><Domain Id="any"><General><Interfaces><NetworkInterface address="{address}"/></Interfaces>'
        "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
        f"<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex><Peers>{found}</Peers></Discovery></Domain></CycloneDDS>"
    )


@functools.cache
def _raw_entities() -> tuple[Any, Any]:
    """Cyclone's DataWriter and DataReader with a raw CDR write and take: what ``write`` and
    ``take`` do around the ``IdlStruct`` (de)serialization they skip, through the same C layer.
    An ``IdlStruct`` costs a Python int per byte of an image (15 ms a 640x480 frame).

    The write calls ``dds_write`` through ctypes, which lets go of the interpreter lock for the
    call, with the sample container the binding's own write builds (a pointer and a size; the
    binding's serdata copies it and touches no Python object). The binding's ``ddspy_write``
    keeps the lock while Cyclone writes, and a reliable write may wait there: for room in the
    writer's history, or for a lock that Cyclone's receive thread holds while it waits for the
    interpreter lock to run a listener. Neither then moves, and the whole process froze
    (services, timers and SIGTERM included; seen beside CPU hogs, the ``/diagnostics`` thread
    stuck in ``ddspy_write``)."""
    import ctypes

    from cyclonedds._clayer import ddspy_take  # type: ignore[import-not-found]  # (Cyclone's C layer ships no stubs)
    from cyclonedds.core import InstanceState, SampleState, ViewState
    from cyclonedds.internal import load_cyclonedds
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader

    class Container(ctypes.Structure):  # the binding's ddspy_sample_container_t
        _fields_ = (("usample", ctypes.c_void_p), ("usample_size", ctypes.c_size_t))

    # a foreign function of its own (ctypes.CDLL: the lock is released during the call), so
    # the binding's prototype of dds_write is left as it is
    dds_write = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_int32, ctypes.POINTER(Container))(("dds_write", load_cyclonedds()))

    class RawWriter(DataWriter):  # type: ignore[misc]
        def write_cdr(self, data: bytes) -> int:
            padded = data.ljust((len(data) + 3) & ~3, b"\0")
            buffer = ctypes.c_char_p(padded)  # points into ``padded`` (kept alive by this frame)
            container = Container(ctypes.cast(buffer, ctypes.c_void_p), len(padded))
            return int(dds_write(self._ref, ctypes.byref(container)))

    class RawReader(DataReader):  # type: ignore[misc]
        def take_cdr(self, n: int) -> list[tuple[bytes, Any]]:
            taken = ddspy_take(self._ref, SampleState.Any | ViewState.Any | InstanceState.Any, n)
            return [] if isinstance(taken, int) else [(bytes(data), info) for data, info in taken]

    return RawWriter, RawReader


# Cyclone configures a domain once per process: every participant of it shares that configuration
_domains: dict[int, tuple[str, Any]] = {}
_domains_lock = threading.Lock()


def _domain(domain: int, config: str) -> Any:
    from cyclonedds.domain import Domain

    with _domains_lock:
        found = _domains.get(domain)
        if found is None:
            found = _domains[domain] = (config, Domain(domain, config))
        elif found[0] != config:
            raise BindingError(
                f"DDS domain {domain} is configured already in this process, otherwise",
                where="DDS participant",
                expected="the same Cyclone configuration for every manager of this process on that domain",
            )
        return found[1]


def _qos(qos: QoS) -> Any:
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    return Qos(
        Policy.Reliability.Reliable(duration(seconds=1)) if qos.reliability is Reliability.RELIABLE else Policy.Reliability.BestEffort,
        Policy.Durability.TransientLocal if qos.durability is Durability.TRANSIENT_LOCAL else Policy.Durability.Volatile,
        Policy.History.KeepAll if qos.keep_all else Policy.History.KeepLast(qos.depth),
        # XCDR1, as ROS 2's DDS middlewares write; and match by type name when the peer's type
        # object cannot be read (Cyclone refuses Fast DDS's for sequences of plain types)
        Policy.DataRepresentation(use_cdrv0_representation=True),
        Policy.TypeConsistency.AllowTypeCoercion(force_type_validation=False),
    )


class DdsPublisher:
    """Writes one ROS 2 topic of one type. A context manager; ``close()`` is safe twice."""

    def __init__(self, node: DdsNode, topic: str, ros_type: str, qos: QoS) -> None:
        raw_writer, _ = _raw_entities()
        self.topic = check_topic(topic)
        self.ros_type = node.types.check(ros_type)
        self._types = node.types
        self._writer: Any = raw_writer(node.participant, node.dds_topic(topic, ros_type), qos=_qos(qos))
        self._node = node

    def publish(self, message: Any) -> None:
        """Serialize and write a message object."""
        self.publish_cdr(self._types.serialize(message, self.ros_type))

    def publish_cdr(self, data: bytes) -> None:
        """Write CDR bytes (with their encapsulation header) as they are."""
        writer = self._writer
        if writer is None:
            raise ClosedError("the writer is closed", where=f"DDS writer on rt{self.topic}", expected="a new publisher")
        ret = writer.write_cdr(data)
        if ret < 0:
            raise BindingError(f"Cyclone DDS returned {ret}", where=f"writing rt{self.topic}")

    def close(self) -> None:
        """Delete the writer; safe twice."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.__del__()  # Cyclone deletes an entity there (idempotent); dropping the reference may not
        self._node.forget(self)

    def __enter__(self) -> DdsPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DdsSubscription:
    """Reads one ROS 2 topic of one type: ``on_message(Received)`` for each sample; samples that
    do not decode, or are over ``max_bytes`` (dropped before they are decoded), are counted in
    ``refused``. ``publishers`` is the number of matched writers; ``on_publishers(count)`` is
    called when it changes. With ``call_soon`` (a unit's), Cyclone's thread only says that data
    is there and the samples are taken and decoded where ``call_soon`` runs them; without, on
    Cyclone's thread."""

    def __init__(
        self,
        node: DdsNode,
        topic: str,
        ros_type: str,
        qos: QoS,
        on_message: Callable[[Received], None],
        on_publishers: Callable[[int], None] | None = None,
        *,
        max_bytes: int | None = None,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
    ) -> None:
        from cyclonedds.core import Listener

        _, raw_reader = _raw_entities()

        self.topic = check_topic(topic)
        self.ros_type = node.types.check(ros_type)
        self.max_bytes = node.max_message_bytes if max_bytes is None else max_bytes
        if not 0 < self.max_bytes <= MAX_CDR_BYTES:
            raise BindingError(
                f"max_bytes {self.max_bytes}", where=f"DDS subscription on {self.topic}", expected=f"from 1 to {MAX_CDR_BYTES}"
            )
        self.received = 0
        self.refused = 0
        self.oversized = 0
        self.last_refusal: str | None = None
        self.publishers = 0
        self._types = node.types
        self._on_message = on_message
        self._lock = threading.Lock()
        self._pending = False
        key = "rt" + topic
        subscription = self

        def take() -> None:
            with subscription._lock:
                subscription._pending = False
            reader = subscription._reader
            if reader is not None:
                subscription._take(reader, key)

        class _Listener(Listener):  # type: ignore[misc]
            def on_data_available(self, reader: Any) -> None:
                if call_soon is None:
                    if reader is None:  # Cyclone calls the listener of a reader being deleted (close) with no reader
                        return
                    subscription._take(reader, key)
                    return
                with subscription._lock:
                    schedule = not subscription._pending
                    subscription._pending = True
                if schedule:
                    call_soon(take)

            def on_subscription_matched(self, reader: Any, status: Any) -> None:
                subscription.publishers = int(status.current_count)
                if on_publishers is not None:
                    on_publishers(subscription.publishers)

        self._reader: Any = raw_reader(node.participant, node.dds_topic(topic, ros_type), qos=_qos(qos), listener=_Listener())
        self._node = node

    def _refuse(self, why: str, *, oversized: bool = False) -> None:
        with self._lock:
            self.refused += 1
            self.oversized += oversized
            self.last_refusal = why
            count = self.refused
        if count <= 3 or count % 100 == 0:  # a stream of bad samples must not flood the log
            log.warning("DDS subscription on %s refused a sample (%d so far): %s", self.topic, count, why)

    def _take(self, reader: Any, key: str) -> None:
        while True:
            taken = reader.take_cdr(64)  # raw CDR: the one codec reads it
            if not taken:
                return
            for data, info in taken:
                arrival = time.time_ns()
                try:
                    if not info.valid_data:
                        continue
                    if len(data) > self.max_bytes:
                        self._refuse(
                            f"a sample of {len(data)} bytes, over the limit of {self.max_bytes} (raise it with max_bytes= in the binding)",
                            oversized=True,
                        )
                        continue
                    message = self._types.deserialize(data, self.ros_type)
                except BindingError as exc:
                    self._refuse(str(exc))
                    continue
                except Exception as exc:  # the binding's own errors: counted the same way
                    self._refuse(f"{type(exc).__name__}: {exc}")
                    continue
                with self._lock:
                    self.received += 1
                try:
                    self._on_message(Received(message, self.ros_type, Attachment(0, int(info.source_timestamp), bytes(16)), arrival, key))
                except Exception:
                    log.exception("DDS subscription on %s: on_message failed", self.topic)
            if len(taken) < 64:
                return

    def close(self) -> None:
        """Delete the reader; safe twice."""
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.__del__()  # as DdsPublisher.close
        self._node.forget(self)

    def __enter__(self) -> DdsSubscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# A DDS reader takes data only from writers it has discovered, and that a writer matched a reader
# says nothing of whether the reader's side discovered the writer yet: a request written at once
# was lost (seen with rclpy's client and a Cyclone server, tests/test_ros2_services.py). So a
# client whose first server was matched during a call gives the server's side this long first.
_SETTLE_S = 0.5


class _Matched:
    """Counts the peers matched with a reader or a writer, and wakes who waits for a change."""

    def __init__(self) -> None:
        self.count = 0
        self.changed = threading.Condition()

    def set(self, count: int) -> None:
        """Take the new count (a listener's) and wake the waiters."""
        with self.changed:
            self.count = count
            self.changed.notify_all()


class DdsClient:
    """Calls the ROS 2 service ``service`` of type ``srv_type`` over DDS: requests written on
    ``rq<service>Request``, responses read from ``rr<service>Reply`` (:mod:`~dyknow.ros2.names`),
    the payloads CDR as rmw_fastrtps writes them (no request header in the payload).

    rmw_fastrtps tells which request a response answers only in RTPS's inline QoS (the response's
    *related sample identity*: the request writer's GUID and the request's sequence number), which
    Cyclone DDS neither sends nor shows to its readers. So a client cannot tell its responses from
    those to other clients of the same service: it makes one call at a time (a second call waits
    for the first), takes the first response that arrives after its request was written, and a
    response the server writes to another client's concurrent request (or a late response to
    its own earlier call that timed out) may be taken for its own.
    A context manager; ``close()`` is safe twice.
    """

    def __init__(self, node: DdsNode, service: str, srv_type: str, *, max_bytes: int = DEFAULT_MAX_REQUEST_BYTES) -> None:
        self.service = check_topic(service, "ROS 2 service")
        self.srv_type = srv_type
        self.where = f"DDS client of {self.service}"
        self.request_type, self.response_type = node.types.service(srv_type)
        if not 0 < max_bytes <= MAX_CDR_BYTES:
            raise BindingError(f"max_bytes {max_bytes}", where=self.where, expected=f"from 1 to {MAX_CDR_BYTES}")
        self.max_bytes = max_bytes
        self._types = node.types
        self._node = node
        self._closed = False
        self._call_lock = threading.Lock()
        self._data = threading.Event()
        self._readers, self._writers = _Matched(), _Matched()  # the servers' request readers and reply writers
        self._reader: Any = None
        self._writer: Any = None
        self._open()

    def _open(self) -> None:
        """Make the request writer and the reply reader (anew after a call went unanswered: see
        :meth:`call`), with counters of their matches of their own."""
        from cyclonedds.core import Listener

        raw_writer, raw_reader = _raw_entities()
        readers, writers, data = _Matched(), _Matched(), self._data

        class _WriterListener(Listener):  # type: ignore[misc]
            def on_publication_matched(self, writer: Any, status: Any) -> None:
                readers.set(int(status.current_count))

        class _ReaderListener(Listener):  # type: ignore[misc]
            def on_data_available(self, reader: Any) -> None:
                data.set()

            def on_subscription_matched(self, reader: Any, status: Any) -> None:
                writers.set(int(status.current_count))

        node = self._node
        qos = _qos(DEFAULT_QOS)  # rmw_qos_profile_services_default: reliable, volatile, keep last 10
        self._readers, self._writers = readers, writers
        self._reader = raw_reader(node.participant, node.named_topic(dds_reply_topic(self.service), self.response_type), qos=qos, listener=_ReaderListener())
        self._writer = raw_writer(node.participant, node.named_topic(dds_request_topic(self.service), self.request_type), qos=qos, listener=_WriterListener())

    def _delete(self) -> None:
        writer, self._writer = self._writer, None
        reader, self._reader = self._reader, None
        for entity in (writer, reader):
            if entity is not None:
                entity.__del__()  # as DdsPublisher.close

    @property
    def servers(self) -> int:
        """How many servers are matched both ways (their request readers and reply writers)."""
        return min(self._readers.count, self._writers.count)

    def _wait_matched(self, deadline: float) -> bool:
        if self.servers:
            return True
        for matched in (self._readers, self._writers):
            with matched.changed:
                while matched.count == 0:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return False
                    matched.changed.wait(left)
        return True

    def call(self, request: Any, timeout_s: float = 5.0, *, resend_s: float | None = None) -> Any:
        """Send ``request`` (a request message or a dict of its fields) and return the response
        message; waits up to ``timeout_s`` in all (for a server to be matched both ways, for the
        calls before it, for the answer). Raises :class:`~dyknow.errors.ServiceError` naming the
        service and the time waited when nothing answers.

        A call that goes unanswered deletes the client's writer and reader and makes new ones:
        its request stayed in the writer's history unacknowledged, and a node that restarted
        meanwhile was given it (and a cleanup of the rollback then took the answer to that
        replayed activation for its own: the restarted node ended active, reported rolled back).

        ``resend_s``: write the request again each ``resend_s`` seconds while no answer came, for
        a service whose call changes nothing (:data:`dyknow.ros2.services.READ_ONLY_SERVICES`). A response is lost
        when the server's reply writer has not yet matched this client's reader (discovery runs
        both ways, and only this side's is seen); beside CPU hogs that took longer than
        :data:`_SETTLE_S`, and a new client's ``get_parameters`` waited its whole timeout. Never
        for a call that changes something: a second ``change_state`` would be refused, or done
        twice."""
        if not 0 < timeout_s <= 3600:
            raise BindingError(f"timeout {timeout_s} s", where=self.where, expected="from 0 to 3600 s")
        if resend_s is not None and not 0.05 <= resend_s <= 3600:
            raise BindingError(f"resend every {resend_s} s", where=self.where, expected="from 0.05 to 3600 s, or None")
        data = self._types.serialize(as_message(request, self.request_type, self._types, self.where), self.request_type)
        started = time.monotonic()
        deadline = started + timeout_s
        if not self._call_lock.acquire(timeout=timeout_s):
            raise self._no_answer(time.monotonic() - started, "the calls before it took the time")
        try:
            matched_before = self.servers > 0
            if not self._wait_matched(deadline):
                raise self._no_answer(time.monotonic() - started, "no server matched")
            if not matched_before:  # see _SETTLE_S
                time.sleep(min(_SETTLE_S, max(0.0, deadline - time.monotonic())))
            reader, writer = self._reader, self._writer
            if reader is None or writer is None:
                raise ClosedError("the client is closed", where=self.where, expected="a new client")
            self._data.clear()
            reader.take_cdr(64)  # what came before the request answers another (an earlier call's late answer)
            ret = writer.write_cdr(data)
            if ret < 0:
                raise ServiceError(f"Cyclone DDS returned {ret} writing the request", where=self.where)
            resend_at = time.monotonic() + resend_s if resend_s is not None else math.inf
            while True:
                now = time.monotonic()
                if now >= resend_at and resend_s is not None:
                    if writer.write_cdr(data) < 0:
                        raise ServiceError("Cyclone DDS refused to write the request again", where=self.where)
                    resend_at = now + resend_s
                left = deadline - now
                if left <= 0:
                    servers = self.servers
                    self._reopen()  # see the docstring: nothing of this call reaches or answers a later one
                    raise self._no_answer(now - started, f"{servers} server(s) matched")
                if not self._data.wait(min(left, max(0.0, resend_at - now))):
                    continue
                self._data.clear()
                for payload, info in reader.take_cdr(64):
                    if not info.valid_data:
                        continue
                    if len(payload) > self.max_bytes:
                        log.warning("%s: a response of %d bytes, over the limit of %d, dropped", self.where, len(payload), self.max_bytes)
                        continue
                    return self._types.deserialize(payload, self.response_type)
        finally:
            self._call_lock.release()

    def _no_answer(self, waited_s: float, why: str) -> ServiceError:
        return ServiceError(
            f"no answer in {waited_s:.1f} s ({why})",
            where=f"ROS 2 service {self.service} ({self.srv_type}) over DDS",
            expected="a server of this name and type that answers (dyknow ros2 list --dds shows the services), or a longer timeout",
        )

    def _reopen(self) -> None:
        """A writer and a reader anew, unless closed meanwhile."""
        self._delete()
        if not self._closed:
            self._open()

    def close(self) -> None:
        """Delete the writer and the reader; safe twice."""
        self._closed = True
        self._delete()
        self._node.forget(self)

    def __enter__(self) -> DdsClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DdsService:
    """Serves the ROS 2 service ``service`` of type ``srv_type`` over DDS: reads requests from
    ``rq<service>Request``, calls ``handler(request) -> response`` (a message object or a dict
    of its fields) where ``call_soon`` runs it (default: Cyclone's thread), and writes the
    response on ``rr<service>Reply``. A request over ``max_bytes`` or that does not decode is
    dropped (``refused``); an exception of the handler answers nothing and is logged (``failed``), as an answer Cyclone DDS could not write.

    **rmw_fastrtps clients (rclpy on Fast DDS) do not take these answers**: they take a response
    only when its related sample identity (RTPS inline QoS) names their request, and Cyclone DDS
    cannot write one. rmw_cyclonedds clients expect a request header in the payload, which this
    service neither reads nor writes. So it answers dyknow's :class:`DdsClient` only; serve
    ROS 2 nodes over rmw_zenoh (:meth:`~dyknow.ros2.node.Ros2Node.create_service`). A context
    manager; ``close()`` is safe twice.
    """

    def __init__(
        self,
        node: DdsNode,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        *,
        max_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
    ) -> None:
        from cyclonedds.core import Listener

        raw_writer, raw_reader = _raw_entities()
        self.service = check_topic(service, "ROS 2 service")
        self.srv_type = srv_type
        self.where = f"DDS service {self.service}"
        self.request_type, self.response_type = node.types.service(srv_type)
        if not 0 < max_bytes <= MAX_CDR_BYTES:
            raise BindingError(f"max_bytes {max_bytes}", where=self.where, expected=f"from 1 to {MAX_CDR_BYTES}")
        self.max_bytes = max_bytes
        self.received = 0
        self.answered = 0
        self.refused = 0
        self.failed = 0
        self._types = node.types
        self._handler = handler
        self._node = node
        self._lock = threading.Lock()
        self._pending = False
        server = self

        def take() -> None:
            with server._lock:
                server._pending = False
            server._take()

        class _Listener(Listener):  # type: ignore[misc]
            def on_data_available(self, reader: Any) -> None:
                if call_soon is None:
                    server._take()
                    return
                with server._lock:
                    schedule = not server._pending
                    server._pending = True
                if schedule:
                    call_soon(take)

        qos = _qos(DEFAULT_QOS)
        self._writer: Any = raw_writer(node.participant, node.named_topic(dds_reply_topic(self.service), self.response_type), qos=qos)
        self._reader: Any = raw_reader(
            node.participant, node.named_topic(dds_request_topic(self.service), self.request_type), qos=qos, listener=_Listener()
        )

    def _take(self) -> None:
        reader = self._reader
        while reader is not None:
            taken = reader.take_cdr(64)
            for payload, info in taken:
                if info.valid_data:
                    self._serve(payload)
            if len(taken) < 64:
                return

    def _serve(self, payload: bytes) -> None:
        with self._lock:
            self.received += 1
        try:
            if len(payload) > self.max_bytes:
                raise BindingError(f"a request of {len(payload)} bytes", where=self.where, expected=f"at most {self.max_bytes}")
            request = self._types.deserialize(payload, self.request_type)
        except BindingError as exc:
            with self._lock:
                self.refused += 1
            log.warning("%s refused a request: %s", self.where, exc)
            return
        try:
            response = self._handler(request)
            data = self._types.serialize(as_message(response, self.response_type, self._types, self.where), self.response_type)
        except Exception as exc:  # the handler's: answer nothing, say why in the log
            with self._lock:
                self.failed += 1
            log.log(logging.WARNING if isinstance(exc, DyKnowError) else logging.ERROR, "%s: the handler failed, answered nothing", self.where, exc_info=True)
            return
        writer = self._writer
        written = writer.write_cdr(data) if writer is not None else None
        with self._lock:
            if written is not None and written >= 0:
                self.answered += 1
            elif written is not None:
                self.failed += 1
        if written is not None and written < 0:
            log.warning("%s: Cyclone DDS returned %d writing an answer: not sent", self.where, written)

    def close(self) -> None:
        """Delete the reader and the writer; safe twice."""
        reader, self._reader = self._reader, None
        writer, self._writer = self._writer, None
        for entity in (reader, writer):
            if entity is not None:
                entity.__del__()  # as DdsPublisher.close
        self._node.forget(self)

    def __enter__(self) -> DdsService:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DdsNode:
    """A DDS domain participant for ROS 2 topics of ROS domain ``domain``.

    ``config``: a Cyclone DDS XML configuration (default :data:`LOOPBACK_CONFIG`);
    ``max_message_bytes``: the largest sample a subscription decodes unless told otherwise.
    """

    def __init__(
        self,
        *,
        domain: int = 0,
        config: str | None = None,
        types: TypeSupport | None = None,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    ) -> None:
        try:
            from cyclonedds.domain import DomainParticipant
        except ImportError as exc:
            raise BindingError(
                "Cyclone DDS's Python binding is not installed", where="ros2dds binding", expected="pip install 'dyknow[ros2]'"
            ) from exc
        if not 0 <= int(domain) <= 232:
            raise BindingError(f"domain {domain}", where="DDS participant", expected="a ROS_DOMAIN_ID from 0 to 232")
        self.domain = int(domain)
        self.types = types or TypeSupport()
        self.max_message_bytes = max_message_bytes  # what a subscription takes unless told otherwise
        self._domain = _domain(self.domain, config or LOOPBACK_CONFIG)
        self.participant: Any = DomainParticipant(self.domain)
        self._classes: dict[str, Any] = {}
        self._topics: dict[tuple[str, str], Any] = {}
        self._entities: list[Any] = []  # publishers, subscriptions, clients and services
        self._lock = threading.RLock()
        self._closed = False

    def idl_type(self, ros_type: str) -> Any:
        """The Cyclone ``IdlStruct`` class of ``ros_type`` (built once, nested types first)."""
        from cyclonedds.idl import make_idl_struct
        from cyclonedds.idl import types as t
        from rosbags.interfaces import Nodetype

        with self._lock:
            cls = self._classes.get(ros_type)
            if cls is not None:
                return cls
            base = {
                "bool": bool,
                "byte": t.byte,
                "char": t.uint8,
                "int8": t.int8,
                "uint8": t.uint8,
                "int16": t.int16,
                "uint16": t.uint16,
                "int32": t.int32,
                "uint32": t.uint32,
                "int64": t.int64,
                "uint64": t.uint64,
                "float32": t.float32,
                "float64": t.float64,
                "string": str,
            }

            def field_type(desc: Any) -> Any:
                node, rest = desc
                if node == Nodetype.NAME:
                    return self.idl_type(rest)
                if node == Nodetype.BASE:
                    if rest[0] == "string" and rest[1]:
                        return t.bounded_str[rest[1]]  # type: ignore[misc]  # (cyclonedds's IDL types are generic at run time; its stubs do not say so)
                    if rest[0] not in base:
                        raise BindingError(f"field type {rest[0]}", where=f"type {ros_type}", expected="a type DDS can carry here")
                    return base[rest[0]]
                inner, count = rest
                if node == Nodetype.ARRAY:
                    return t.array[field_type(inner), count]  # type: ignore[misc]  # (cyclonedds's IDL types are generic at run time; its stubs do not say so)
                return t.sequence[field_type(inner), count] if count else t.sequence[field_type(inner)]  # type: ignore[misc]  # (cyclonedds's IDL types are generic at run time; its stubs do not say so)

            fields = {name: field_type(desc) for name, desc in self.types.field_definitions(ros_type)} or {
                "structure_needs_at_least_one_member": t.uint8
            }
            name = ros_type.rsplit("/", 1)[1] + "_"
            cls = make_idl_struct(name, dds_type_name(ros_type), fields)
            self._classes[ros_type] = cls
            return cls

    def dds_topic(self, topic: str, ros_type: str) -> Any:
        """The DDS topic ``rt<topic>`` of ``ros_type`` (one per name and type)."""
        return self.named_topic("rt" + check_topic(topic), ros_type)

    def named_topic(self, name: str, ros_type: str) -> Any:
        """The DDS topic ``name`` (``rt/...``, ``rq/...Request``, ``rr/...Reply``) of ``ros_type``
        (one per name and type)."""
        from cyclonedds.topic import Topic

        with self._lock:
            if self._closed:
                raise ClosedError("the DDS participant is closed", where="ros2dds", expected="a new participant")
            found = self._topics.get((name, ros_type))
            if found is None:
                found = self._topics[(name, ros_type)] = Topic(self.participant, name, self.idl_type(ros_type))
            return found

    def topics(self, *, wait_s: float = 1.0) -> dict[str, list[str]]:
        """The ROS 2 topics the DDS writers and readers of this domain carry (``rt/`` topics with
        ROS type names), topic -> types, after discovery had ``wait_s`` to bring them."""
        return self.discover(wait_s=wait_s)[0]

    def discover(self, *, wait_s: float = 1.0) -> tuple[dict[str, list[str]], dict[str, dict[str, Any]]]:
        """``(topics, services)`` of this domain after discovery had ``wait_s`` to bring them:
        :meth:`topics`'s, and service -> ``{"types", "servers", "clients"}`` from the request
        topics (``rq/<service>Request``: a server reads it, a client writes it)."""
        from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription

        with self._lock:
            if self._closed:
                raise ClosedError("the DDS participant is closed", where="ros2dds", expected="a new participant")
            readers = [BuiltinDataReader(self.participant, t) for t in (BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription)]
        time.sleep(wait_s)  # DDS discovery has no "done": what came within the wait
        found: dict[str, set[str]] = {}
        services: dict[str, dict[str, Any]] = {}
        for reader, role in zip(readers, ("clients", "servers"), strict=True):
            for sample in reader.read(N=MAX_DISCOVERED):
                name, type_name = str(getattr(sample, "topic_name", "")), str(getattr(sample, "type_name", ""))
                try:
                    if name.startswith("rt/"):
                        found.setdefault(check_topic(name[2:]), set()).add(ros_type_name(type_name))
                    elif name.startswith("rq/") and name.endswith("Request") and type_name.endswith("_Request_"):
                        service = check_topic(name[2 : -len("Request")], "ROS 2 service")
                        entry = services.setdefault(service, {"types": set(), "servers": 0, "clients": 0})
                        entry["types"].add(ros_type_name(type_name[: -len("Request_")]))
                        entry[role] += 1
                    # (rr/ topics mirror rq/ ones; others are not ROS's)
                except BindingError:
                    log.debug("ignoring DDS topic %r of type %r", name[:200], type_name[:200])
            reader.__del__()  # as DdsPublisher.close
        topics = {topic: sorted(types) for topic, types in sorted(found.items())}
        return topics, {name: {**entry, "types": sorted(entry["types"])} for name, entry in sorted(services.items())}

    def create_publisher(self, topic: str, ros_type: str, qos: QoS = DEFAULT_QOS) -> DdsPublisher:
        """A writer of ``ros_type`` on ``topic``."""
        pub = DdsPublisher(self, topic, ros_type, qos)
        with self._lock:
            self._entities.append(pub)
        return pub

    def create_subscription(
        self,
        topic: str,
        ros_type: str | None,
        on_message: Callable[[Received], None],
        qos: QoS = DEFAULT_QOS,
        on_publishers: Callable[[int], None] | None = None,
        *,
        max_bytes: int | None = None,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
    ) -> DdsSubscription:
        """A reader of ``topic``; ``ros_type`` None: the one known type its writers announce
        (discovery is given 2 s), else :class:`BindingError`. ``max_bytes`` and ``call_soon``:
        as :class:`DdsSubscription` takes them."""
        if ros_type is None:
            announced = [t for t in self.topics(wait_s=2.0).get(check_topic(topic), []) if self.types.known(t)]
            if len(announced) != 1:
                raise BindingError(
                    f"ros2dds:{topic} names no type, and its DDS writers announced {announced or 'none'} within 2 s",
                    where="DDS subscription",
                    expected=f"ros2dds:{topic}?type=pkg/msg/Type",
                )
            ros_type = announced[0]
            if max_bytes is None:  # the writers chose the type: the tighter bound
                max_bytes = min(self.max_message_bytes, UNTYPED_MAX_MESSAGE_BYTES)
        sub = DdsSubscription(self, topic, ros_type, qos, on_message, on_publishers, max_bytes=max_bytes, call_soon=call_soon)
        with self._lock:
            self._entities.append(sub)
        return sub

    def create_client(self, service: str, srv_type: str, *, max_bytes: int = DEFAULT_MAX_REQUEST_BYTES) -> DdsClient:
        """A client of the service ``service`` of type ``srv_type`` over DDS (see :class:`DdsClient`)."""
        client = DdsClient(self, service, srv_type, max_bytes=max_bytes)
        with self._lock:
            self._entities.append(client)
        return client

    def create_service(
        self,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        *,
        max_bytes: int = DEFAULT_MAX_REQUEST_BYTES,
        call_soon: Callable[[Callable[[], None]], None] | None = None,
    ) -> DdsService:
        """Serve the service ``service`` of type ``srv_type`` over DDS (see :class:`DdsService`:
        rmw_fastrtps clients do not take its answers)."""
        server = DdsService(self, service, srv_type, handler, max_bytes=max_bytes, call_soon=call_soon)
        with self._lock:
            self._entities.append(server)
        return server

    def forget(self, entity: Any) -> None:
        """Called by an entity that closed itself."""
        with self._lock:
            if entity in self._entities:
                self._entities.remove(entity)

    def close(self) -> None:
        """Close every reader, writer, client and service (the latest first), then the participant;
        safe twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = list(reversed(self._entities))
        for entity in entities:
            entity.close()
        self._topics.clear()
        participant, self.participant = self.participant, None
        participant.__del__()  # deletes what is left under it

    def __enter__(self) -> DdsNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
