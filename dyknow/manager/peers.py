"""The manager among the others: what it tells and asks them, the units it runs for them, their clocks.

:mod:`dyknow.federation` holds how managers find and follow each other; :class:`Peers` is one
manager's side of it: its :class:`~dyknow.federation.Summary`, the calls it makes on the others
for its requests (``spawn_on``, ...), the units it spawned for another manager's request (they
go when that manager is lost), and the clock offsets it estimates on demand (:mod:`dyknow.clocks`).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Collection, Mapping
from typing import Any

from dyknow import clocks, keys
from dyknow.adaptation import ANCHOR_LABEL, AdaptationLoop
from dyknow.client import Client
from dyknow.errors import DyKnowError, UnitError
from dyknow.federation import STOPPED, Directory, Summary, SummaryUnit
from dyknow.library import Library
from dyknow.manager.spawning import Spawner
from dyknow.message import CLOCK_ID
from dyknow.transport import Session

__all__ = ["Peers"]

log = logging.getLogger("dyknow.manager")  # one name for the manager, whichever part logs


class Peers:
    """Manager ``manager`` (on ``host``) among the others it reaches through ``session``.

    ``client`` makes its calls on them (signed with its certificate); ``spawner`` holds its
    units, ``library`` its specs, ``adaptation`` its requests and measurements. It shares the
    manager's ``lock``. It follows the others once :meth:`federate` is called (a manager that
    does not federate only answers their calls).
    """

    def __init__(
        self,
        manager: str,
        host: str,
        *,
        session: Session,
        client: Client,
        lock: threading.RLock,
        spawner: Spawner,
        library: Library,
        adaptation: AdaptationLoop,
    ) -> None:
        self._manager = manager
        self._host = host
        self._session = session
        self._client = client
        self._lock = lock
        self._spawner = spawner
        self._library = library
        self._adaptation = adaptation
        self._owners: dict[str, str] = {}  # unit -> the manager whose request it serves
        self._version = 0
        self._started_ns = time.time_ns()
        self._directory: Directory | None = None
        self._clocks: clocks.ClockTracker | None = None  # the peers' clock offsets (dyknow.clocks)
        self._clock_token: Any = None  # says whose clock this process's clock id is
        self._clocks_asked: dict[int, float] = {}  # unknown clock ids asked about -> when (monotonic)
        self._data_peers: set[str] = set()  # managers whose data reached this one: their clocks estimated until they go

    def federate(self) -> None:
        """Announce the manager and its summary, follow the others, and estimate their clocks."""
        # clocks on demand: those of the managers this one exchanges data or calls with (issue 40)
        self._clocks = clocks.ClockTracker(self._session, in_use=self.in_use, wanted=self._clock_peers)
        self._clock_token = self._session.declare_liveliness_token(keys.clock_token(CLOCK_ID, self._manager))
        self._directory = Directory(
            self._session,
            self._manager,
            summarize=self.summary,
            fetch=self._fetch_summary,
            on_change=self._peer_changed,
            in_use=self.in_use,
        )

    def say_goodbye(self) -> None:
        """Tell the others this manager stops (first, as it closes: it did not crash)."""
        if self._directory is not None:
            self._directory.say_goodbye()

    def close(self, timeout_s: float) -> None:
        """Stop following the others and estimating their clocks."""
        if self._directory is not None:
            self._directory.close(timeout_s)
        if self._clocks is not None:
            self._clocks.close()
        if self._clock_token is not None:
            self._clock_token.undeclare()

    @property
    def directory(self) -> Directory | None:
        """What this manager knows of the others (None when it does not federate)."""
        return self._directory

    def clock_estimates(self) -> dict[str, clocks.Estimate]:
        """The clock offsets estimated so far, by manager."""
        return self._clocks.estimates() if self._clocks is not None else {}

    # ------------------------------------------------------------------ the units it runs for the others

    def serves(self, unit: str, manager: str) -> None:
        """Unit ``unit`` was spawned for a request of ``manager``: it goes when that manager is lost."""
        self._owners[unit] = manager

    def unit_gone(self, unit: str) -> None:
        """Unit ``unit`` was destroyed."""
        self._owners.pop(unit, None)

    def owned(self) -> int:
        """How many units run for the others' requests."""
        return len(self._owners)

    # ------------------------------------------------------------------ what the others see

    def summary(self) -> Summary:
        """What this manager offers the others: host, library, running units, measurements."""
        stalled = self._adaptation.knowledge.stalled
        with self._lock:
            proxies = self._spawner.proxies()
            self._version += 1
            version = self._version
        units = tuple(
            SummaryUnit(
                p.name,
                p.label,
                {port.name: p.get_config()[port.name] for port in p.spec.outputs},
                {port.name: p.spec.tags_for(port.name) for port in p.spec.outputs},
                p.alive and p.name not in stalled,
                self._owners.get(p.name),
            )
            for p in proxies
            if p.label != ANCHOR_LABEL
        )
        library = f"{self._started_ns}.{self._library.version}"
        measurements = dict(self._adaptation.knowledge.measurements)
        return Summary(
            self._manager, self._host, version, library, self._library.specs(), units, measurements, len(self._adaptation.requests()), CLOCK_ID
        )

    def brief(self, health: bool = False) -> dict[str, Any]:
        """What a listing of the managers shows (``get_summary`` with ``brief``): counts, no
        library. ``health``: also the managers it lost (``{"manager", "since_ns", "why"}``) and its
        requests that are degraded (``{"tag", "key", "reason"}``), what a tool that cannot reach a
        manager, or finds a stream silent, asks (:mod:`dyknow.presence`)."""
        units = sum(1 for p in self._spawner.proxies() if p.label != ANCHOR_LABEL)
        requests = self._adaptation.requests()
        brief: dict[str, Any] = {
            "manager": self._manager,
            "host": self._host,
            "specs": len(self._library),
            "units": units,
            "requests": len(requests),
        }
        if health:
            lost = self._directory.lost() if self._directory is not None else {}
            brief["lost"] = [{"manager": m, "since_ns": since, "why": why} for m, (since, why) in sorted(lost.items())]
            brief["degraded"] = [{"tag": r.tag, "key": r.key, "reason": r.reason} for r in requests if r.state == "degraded"]
        return brief

    def changed(self) -> None:
        """The manager's model changed: the others hear of it (a summary, debounced)."""
        if self._directory is not None:
            self._directory.changed()
            # what the requests that ended needed (their candidates, the watches of their tags) is let go
            self._directory.keep({r.tag for r in list(self._adaptation.knowledge.requests.values())})
        if self._clocks is not None:
            self._clocks.reconcile()  # a manager may be in use now, or no longer

    # ------------------------------------------------------------------ the others

    def peers(self) -> dict[str, Summary]:
        """The other managers this one reaches, with their last summary (empty when not federated)."""
        return self._directory.peers() if self._directory is not None else {}

    def discover(self, wanted: Collection[tuple[str, tuple[str, ...]]], *, need: str | None = None) -> bool:
        """Find the managers that offer the tags ``wanted`` and follow them; True when one was added."""
        return self._directory.discover(wanted, need=need) if self._directory is not None else False

    def reachable(self) -> set[str]:
        """The names of the other managers whose liveliness token is up (followed or not)."""
        return self._directory.alive() if self._directory is not None else set()

    def follow(self, manager: str) -> None:
        """Follow ``manager`` now (it asked this one for a unit: its loss, or goodbye, is this one's concern)."""
        if self._directory is not None:
            self._directory.follow(manager, at_once=True)

    def in_use(self) -> set[str]:
        """The managers this one exchanges data and calls with: those whose units its requests
        use, and those whose requests its units serve."""
        used = set(self._owners.values())
        for info in self._adaptation.requests():
            used.update(ref.rpartition("@")[2] for ref in (*info.units, *info.standby) if "@" in ref)
        # and those where units it spawned still run (a request's, being taken down as it ends)
        used.update(ref.rpartition("@")[2] for ref in list(self._adaptation.knowledge.remote) if "@" in ref)
        return used

    def spawn_on(self, manager: str, label: str, name: str, *, bindings: Mapping[str, str]) -> None:
        """Spawn a unit on another manager, through its spawn service, for a request of this one."""
        info = self._client.call_manager(manager, "spawn", {"label": label, "name": name, "bindings": dict(bindings), "owner": self._manager})
        if info.get("state") == "failed":
            raise UnitError(f"failed at start: {info.get('error')}", where=f"unit {name!r} on manager {manager!r}")

    def destroy_on(self, manager: str, name: str) -> None:
        """Destroy a unit this manager spawned on another one."""
        self._client.call_manager(manager, "destroy", {"name": name})

    def set_config_on(self, manager: str, name: str, bindings: Mapping[str, str]) -> None:
        """Rebind ports of a unit on another manager."""
        self._client.call_unit(manager, name, "set_config", {"bindings": dict(bindings)})

    def _fetch_summary(self, manager: str) -> bytes:
        return json.dumps(self._client.call_manager(manager, "get_summary", {})).encode()

    def _clock_peers(self) -> dict[str, tuple[str, int]]:
        """The managers whose clocks to estimate (on demand, issue 40): those this one exchanges
        data or calls with, and those whose clocks stamp data it received with no offset known.
        Such a clock id of a manager not followed yet is looked up by its clock token (at most
        8 ids a second, each once in 10 s): its manager is then followed, and tracked next round."""
        directory = self._directory
        if directory is None:
            return {}
        peers = directory.peers()
        used = self.in_use()
        unknown = clocks.CLOCKS.unknown()
        for name, s in peers.items():  # whose data arrived: kept until it goes (once known, its data says no more)
            if s.clock in unknown and len(self._data_peers) < 256:
                self._data_peers.add(name)
        wanted = {
            name: (keys.clock_key(name), s.clock)
            for name, s in peers.items()
            if s.clock and s.clock != CLOCK_ID and (name in used or name in self._data_peers)  # one process, one clock: nothing to estimate
        }
        now = time.monotonic()
        for clock, at in list(self._clocks_asked.items()):
            if now - at > 10.0:
                del self._clocks_asked[clock]
        known = {s.clock for s in peers.values()}
        for clock in sorted(unknown - known)[:8]:
            if clock in self._clocks_asked or len(self._clocks_asked) >= 1024:
                continue
            self._clocks_asked[clock] = now

            def found(tokens: list[str], count: int, clock: int = clock) -> None:
                for token in tokens:
                    name = token.rpartition("/")[2]
                    if name != self._manager:
                        directory.follow(name)

            try:
                self._session.ask_alive(keys.clock_token(clock, "*"), timeout_s=1.0, limit=2, done=found)
            except DyKnowError as exc:
                log.debug("no answer about clock %08x: %s", clock, exc)
        return wanted

    def _peer_changed(self, kind: str, manager: str) -> None:
        if self._clocks is not None:
            if kind == "lost":
                self._data_peers.discard(manager)
                self._clocks.untrack(manager)
            else:
                self._clocks.reconcile()  # maybe one to estimate now
        if kind == "lost":
            with self._lock:
                orphans = [unit for unit, owner in self._owners.items() if owner == manager]
            destroyed = []
            for unit in orphans:  # units that served the lost manager's requests
                try:
                    self._spawner.destroy(unit)
                    destroyed.append(unit)
                except DyKnowError as exc:
                    log.debug("unit %r of lost manager %r: %s", unit, manager, exc)
            why = self._directory.lost().get(manager, (0, "it is gone"))[1] if self._directory is not None else "it is gone"
            # one line: a manager that stopped is no fault; one that vanished is
            log.log(
                logging.INFO if why == STOPPED else logging.WARNING,
                "manager %r was lost (%s)%s",
                manager,
                why,
                f"; destroyed the units it had asked for: {', '.join(destroyed)}" if destroyed else "",
            )
        self._adaptation.peer_changed(kind, manager)
