"""Several managers, one system: each knows the others through Zenoh.

Every manager declares a liveliness token on ``@dyknow/<manager>`` and publishes its
:class:`Summary` (host, library, running units, measurements, load) on
``dyknow/<manager>/summary`` whenever it changes; a newcomer asks each manager it discovers
for its summary through the ``get_summary`` service. A :class:`Directory` keeps what the others
said: a manager that appears is noticed when its token does (at once on a reachable network), one
that dies or is cut off when its token goes (its links close, or Zenoh's lease expires). There
is no broker: Zenoh's peers, gossip and routers carry it all.

A summary arrives from the network, so it is hostile input: it is bounded in size, its specs are
XML read by the hardened spec reader, and nothing in it is ever imported or run here. A
manager's units are only ever spawned by that manager, through its own services and policy.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dyknow import keys
from dyknow.errors import DyKnowError, SpecError
from dyknow.planner import RunningUnit
from dyknow.spec import TransformationSpec, parse_specs

__all__ = ["GOODBYE", "MAX_SUMMARY_BYTES", "STOPPED", "Directory", "Summary", "SummaryUnit"]

log = logging.getLogger(__name__)

#: The largest summary a manager takes from another (about 10,000 specs).
MAX_SUMMARY_BYTES = 16 << 20

_MAX_ITEMS = 20_000
# A manager whose summary could not be fetched is asked again after 0.05 s, then twice as long
# each time up to 2 s: a fetch made as a manager's token appears can fail for a moment (its
# services not reachable yet, a watcher that has not yet seen the token), and a fixed 2 s made a
# healed partition wait for it (issue 43).
_RETRY_FIRST_S = 0.05
_RETRY_S = 2.0
#: What a manager publishes on its summary key as it stops, before its token goes: the others
#: then tell a manager that stopped from one that crashed or was cut off.
GOODBYE = b'{"stopping":true}'
_GOODBYE_S = 5.0  # a goodbye this recent explains a loss
_MAX_LOST = 1_000  # lost managers remembered (names come from the network: bounded)
#: Why a manager is lost, when it said goodbye.
STOPPED = "it stopped (it said goodbye)"
_VANISHED = "its liveliness token went away without a goodbye: it crashed, or its host was cut off past its lease"


@dataclass(frozen=True, slots=True)
class SummaryUnit:
    """A running unit as its manager's summary tells: what its outputs carry and where."""

    name: str
    label: str
    outputs: Mapping[str, str]
    tags: Mapping[str, tuple[str, ...]]
    healthy: bool
    owner: str | None = None  # the manager whose request spawned it, if another one

    def running(self, manager: str) -> RunningUnit:
        """The unit as the planner sees it, on ``manager``."""
        return RunningUnit(self.name, self.label, dict(self.outputs), dict(self.tags), self.healthy, manager)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form."""
        return {"name": self.name, "label": self.label, "outputs": dict(self.outputs), "tags": {p: list(t) for p, t in self.tags.items()},
                "healthy": self.healthy, "owner": self.owner}  # fmt: skip


@dataclass(frozen=True, slots=True)
class Summary:
    """What one manager offers the others: its library, its running units, its measurements."""

    manager: str
    host: str
    version: int
    library: str = ""  # changes when the library does (planners cache on it)
    specs: tuple[TransformationSpec, ...] = ()
    units: tuple[SummaryUnit, ...] = ()
    measurements: Mapping[str, float | str] = field(default_factory=dict)
    requests: int = 0
    clock: int = 0  # the manager's clock id (dyknow.message.CLOCK_ID of its process; 0: unknown)

    @property
    def load(self) -> int:
        """How busy the manager is: its running units."""
        return len(self.units)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form, specs as XML (what ``get_summary`` serves and the summary key carries)."""
        return {
            "manager": self.manager,
            "host": self.host,
            "version": self.version,
            "library": self.library,
            "specs": [s.to_xml() for s in self.specs],
            "units": [u.to_dict() for u in self.units],
            "measurements": dict(self.measurements),
            "requests": self.requests,
            "clock": self.clock,
        }

    @classmethod
    def from_json(cls, data: bytes, manager: str, previous: Summary | None = None) -> Summary:
        """A summary received from the network; :class:`DyKnowError` when it is malformed or too big.

        ``manager`` is who it must be about (the key or token it came with). The specs of
        ``previous`` (the last summary of that manager) are kept when its library has not changed,
        so a manager's every unit change does not mean reading its whole library again.
        """
        if len(data) > MAX_SUMMARY_BYTES:
            raise DyKnowError(f"a summary of {len(data)} bytes", where=f"manager {manager!r}", expected=f"at most {MAX_SUMMARY_BYTES}")
        try:
            raw = json.loads(data)
            if not isinstance(raw, dict) or raw.get("manager") != manager:
                raise ValueError("not the summary of this manager")
            specs_xml = raw.get("specs", [])
            units = raw.get("units", [])
            if len(specs_xml) > _MAX_ITEMS or len(units) > _MAX_ITEMS:
                raise ValueError("too many specs or units")
            library = str(raw.get("library", ""))[:128]
            specs: list[TransformationSpec] = []
            if previous is not None and library and previous.library == library:
                specs = list(previous.specs)
            else:
                for i, xml in enumerate(specs_xml):
                    specs.extend(parse_specs(str(xml), f"<summary of {manager}, spec {i}>", max_expansions=1))
            measurements = {
                str(k): v
                for k, v in dict(raw.get("measurements", {})).items()
                if isinstance(v, int | float | str) and not isinstance(v, bool)
            }
            return cls(
                manager=manager,
                host=str(raw.get("host", "")),
                version=int(raw.get("version", 0)),
                library=library,
                specs=tuple(specs),
                units=tuple(_unit(u, manager) for u in units),
                measurements=measurements,
                requests=int(raw.get("requests", 0)),
                clock=_clock(raw.get("clock", 0)),
            )
        except (ValueError, TypeError, KeyError, AttributeError, RecursionError, SpecError) as exc:
            raise DyKnowError(f"a malformed summary: {str(exc)[:200]}", where=f"manager {manager!r}") from exc


def _clock(raw: Any) -> int:
    """A clock id from a summary: a 32-bit unsigned integer."""
    if isinstance(raw, bool) or not isinstance(raw, int) or not 0 <= raw < 1 << 32:
        raise ValueError(f"clock {str(raw)[:40]!r} is not a 32-bit id")
    return raw


def _unit(raw: Any, manager: str) -> SummaryUnit:
    """A unit of ``manager``'s summary. Only its outputs on concrete keys of the manager's own key
    space (``dyknow/<manager>/...``) are kept: a summary may not offer another's stream, or a
    wildcard, as its own (a planner would wire whatever publishes there)."""
    own = keys.manager_prefix(manager)
    outputs = {str(p): str(k) for p, k in dict(raw["outputs"]).items()}
    kept = {p: k for p, k in outputs.items() if k.startswith(own) and "*" not in k and "@" not in k}  # '*': any wildcard
    if len(kept) < len(outputs):
        log.warning("summary of %r: outputs outside its key space %s** ignored: %s", manager, own, sorted(set(outputs) - set(kept))[:5])
    tags = {str(p): tuple(str(t) for t in ts) for p, ts in dict(raw["tags"]).items() if str(p) in kept}
    owner = raw.get("owner")
    return SummaryUnit(str(raw["name"]), str(raw["label"]), kept, tags, bool(raw["healthy"]), str(owner) if owner else None)


class Directory:
    """The other managers a manager can reach, and the last summary each published.

    ``fetch(name)`` asks a manager for its summary (the manager's client call, bytes back);
    ``on_change(kind, name)`` is told "found", "lost" or "changed", on the directory's thread.
    ``summarize()`` gives this manager's own summary, published by :meth:`changed` (debounced).
    """

    def __init__(
        self,
        session: Any,
        name: str,
        *,
        summarize: Callable[[], Summary],
        fetch: Callable[[str], bytes],
        on_change: Callable[[str, str], None],
        debounce_s: float = 0.05,
    ) -> None:
        self.name = name
        self._session = session
        self._summarize = summarize
        self._fetch = fetch
        self._on_change = on_change
        self._debounce_s = debounce_s
        self._publish_s = 0.0  # how long building and sending the last summary took
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._summaries: dict[str, Summary] = {}
        self._retry_at: dict[str, tuple[float, float]] = {}  # manager -> (when to ask again for its summary, the wait after)
        self._lost: dict[str, tuple[int, str]] = {}  # manager known, then lost -> (when, wall clock ns; why)
        self._goodbyes: dict[str, float] = {}  # manager -> when it said it was stopping (monotonic)
        self._todo: list[tuple[str, str, bytes | None]] = []  # (kind, manager, summary bytes)
        self._wake = threading.Event()
        self._dirty = threading.Event()
        self._settle = threading.Event()  # set only to cut a wait short at close (a timed wait, not time.sleep)
        self._closed = False
        self._said_goodbye = False
        self._thread = threading.Thread(target=self._run, name=f"dyknow-{name}-directory", daemon=True)
        self._thread.start()
        self._token = session.declare_liveliness_token(keys.manager_token(name))
        self._summary_sub = session.declare_raw_subscriber(keys.summaries_pattern(), self._summary_sample)
        self._watch = session.declare_liveliness_subscriber(keys.managers_pattern(), self._liveliness)
        self.changed()

    # -- what is known

    def peers(self) -> dict[str, Summary]:
        """The reachable managers (this one excluded) whose summary is known, by name."""
        with self._lock:
            return {m: s for m, s in self._summaries.items() if m in self._alive}

    def alive(self) -> set[str]:
        """The names of the managers whose liveliness token is up (this one excluded)."""
        with self._lock:
            return set(self._alive)

    def lost(self) -> dict[str, tuple[int, str]]:
        """The managers this one knew and lost, and that have not come back: name -> (when, in
        wall-clock ns; why: stopped, or gone without a goodbye)."""
        with self._lock:
            return dict(self._lost)

    def changed(self) -> None:
        """This manager's summary changed: publish it soon (several changes, one publication)."""
        self._dirty.set()
        self._wake.set()

    def say_goodbye(self) -> None:
        """Tell the others this manager is stopping (once), before its token goes: they then tell
        it from a manager that crashed or was cut off. The owner says it as its close begins."""
        if self._said_goodbye:
            return
        self._said_goodbye = True
        try:
            self._session.put(keys.summary_key(self.name), GOODBYE)
        except DyKnowError as exc:
            log.debug("directory of %r: no goodbye: %s", self.name, exc)

    def close(self, timeout_s: float = 2.0) -> None:
        """Say goodbye, stop watching and withdraw this manager's token; safe twice."""
        if self._closed:
            return
        self._closed = True
        self._settle.set()
        self.say_goodbye()
        for entity in (self._watch, self._summary_sub, self._token):
            entity.undeclare()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    # -- Zenoh callbacks (quick: the work happens on the directory's thread)

    def _liveliness(self, key: str, alive: bool) -> None:
        manager = keys.manager_of_token(key)
        if manager is None or manager == self.name:
            return
        self._queue("found" if alive else "lost", manager, None)

    def _summary_sample(self, key: str, payload: bytes) -> None:
        manager = key.split("/")[1] if key.count("/") == 2 else None
        if manager is None or manager == self.name:
            return
        if payload == GOODBYE:
            with self._lock:
                self._goodbyes[manager] = time.monotonic()
                while len(self._goodbyes) > _MAX_LOST:
                    del self._goodbyes[next(iter(self._goodbyes))]
                if manager in self._lost:  # its token's end came first
                    self._lost[manager] = (self._lost[manager][0], STOPPED)
            return
        self._queue("summary", manager, payload)

    def _queue(self, kind: str, manager: str, data: bytes | None) -> None:
        with self._lock:
            self._todo.append((kind, manager, data))
        self._wake.set()

    # -- the directory's thread

    def _run(self) -> None:
        while not self._closed:
            with self._lock:
                due = min((at for at, _ in self._retry_at.values()), default=None)
            self._wake.wait(1.0 if due is None else min(1.0, max(0.0, due - time.monotonic())))
            self._wake.clear()
            if self._closed:
                return
            now = time.monotonic()
            with self._lock:
                todo, self._todo = self._todo, []
                # alive, but no summary yet (its fetch failed): ask again, sooner at first
                for m in sorted(self._alive - set(self._summaries)):
                    at, _ = self._retry_at.setdefault(m, (now + _RETRY_S, _RETRY_S))
                    if at <= now and not any(t[1] == m for t in todo):
                        todo.append(("retry", m, None))
                for m in [m for m in self._retry_at if m not in self._alive or m in self._summaries]:
                    del self._retry_at[m]
            for kind, manager, data in todo:
                try:
                    self._handle(kind, manager, data)
                except Exception:
                    log.exception("directory of %r: cannot handle %s of %r", self.name, kind, manager)
            if self._dirty.is_set():
                # let a burst of changes settle into one summary; a big manager's summary costs
                # more to build, so it is built less often (at most a fifth of the thread's time)
                self._settle.wait(max(self._debounce_s, 4 * self._publish_s))
                self._dirty.clear()
                started = time.perf_counter()
                self._publish()
                self._publish_s = time.perf_counter() - started

    def _handle(self, kind: str, manager: str, data: bytes | None) -> None:
        if kind != "retry":
            log.info("directory of %r: %s %r", self.name, kind, manager)
        if kind == "lost":
            with self._lock:
                known = manager in self._alive
                self._alive.discard(manager)
                self._summaries.pop(manager, None)  # a manager that comes back starts afresh
                self._retry_at.pop(manager, None)
                if known:
                    said = self._goodbyes.pop(manager, None)
                    stopped = said is not None and time.monotonic() - said < _GOODBYE_S
                    self._lost[manager] = (time.time_ns(), STOPPED if stopped else _VANISHED)
                    while len(self._lost) > _MAX_LOST:
                        del self._lost[next(iter(self._lost))]
            if known:
                self._on_change("lost", manager)
            return
        if kind in ("found", "retry"):
            with self._lock:
                self._lost.pop(manager, None)
                new = manager not in self._alive or (kind == "retry" and manager not in self._summaries)
                self._alive.add(manager)
            if not new:
                return
            data = self._fetch_summary(manager)
            if data is None:
                return
            kind = "found"
        assert data is not None
        try:
            with self._lock:
                previous = self._summaries.get(manager)
            summary = Summary.from_json(data, manager, previous)
        except DyKnowError as exc:
            log.warning("directory of %r: %s", self.name, exc)
            if kind == "found":  # fetched: ask again later, not at once
                self._retry_later(manager)
            return
        with self._lock:
            old = self._summaries.get(manager)
            if old is not None and old.version > summary.version and kind == "summary":
                return  # an older publication overtaken by a fetch
            self._summaries[manager] = summary
            alive = manager in self._alive
        if alive:
            self._on_change("found" if kind == "found" else "changed", manager)

    def _fetch_summary(self, manager: str) -> bytes | None:
        try:
            return self._fetch(manager)
        except DyKnowError as exc:
            wait = self._retry_later(manager)
            # (the first failures are expected as a manager appears: said only once it persists)
            log.log(logging.WARNING if wait >= _RETRY_S else logging.DEBUG, "directory of %r: no summary from %r yet: %s", self.name, manager, exc)
            return None

    def _retry_later(self, manager: str) -> float:
        """Ask ``manager`` for its summary again later: soon after a first failure, then twice as
        late each time (see ``_RETRY_FIRST_S``); returns the wait."""
        with self._lock:
            previous = self._retry_at.get(manager)
            wait = _RETRY_FIRST_S if previous is None else min(2 * previous[1], _RETRY_S)
            self._retry_at[manager] = (time.monotonic() + wait, wait)
        return wait

    def _publish(self) -> None:
        try:
            self._session.put(keys.summary_key(self.name), json.dumps(self._summarize().to_dict()))
        except DyKnowError as exc:
            log.warning("directory of %r: cannot publish the summary: %s", self.name, exc)


def running_units(peers: Mapping[str, Summary]) -> list[RunningUnit]:
    """Every unit running on the given managers, as the planner sees them."""
    return [u.running(m) for m, s in sorted(peers.items()) for u in s.units]


def peer_specs(peers: Mapping[str, Summary]) -> dict[str, Sequence[TransformationSpec]]:
    """Each manager's library, by manager."""
    return {m: s.specs for m, s in peers.items()}
