"""Which managers are there, and what is known of those that are not.

A manager a tool cannot reach is one of three things: never there (a misspelled name, said with
the names that are there), gone a moment ago (its token went while the tool watched), or lost
before the tool started: its token went while the other managers watched, and each of them
remembers it until it comes back (:meth:`dyknow.federation.Directory.lost`). A one-shot command
starts after the loss, so it asks: a manager that anyone still remembers as lost is said LOST,
since when, why and who saw it, never called a misspelling.

- :class:`Presence`: what a client saw come and go since it started (every manager's token and
  goodbye).
- :func:`health`: what managers know (``get_summary`` with ``health``): those they lost, and
  their requests that are degraded, with why.
- :func:`recall`: the losses this client saw and those the managers asked remember, merged into
  one :class:`Loss` per manager.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from dyknow import keys
from dyknow.errors import DyKnowError, ServiceError, TransportError
from dyknow.transport import LivelinessSubscriber, Session

__all__ = ["MAX_ASKED", "Health", "Loss", "Presence", "health", "recall"]

log = logging.getLogger(__name__)

MAX_GONE = 10_000  # managers remembered as gone (names come from the network: bounded)
#: The most managers a tool asks what they know of the others (in parallel): every manager
#: remembers every manager it saw and lost, so a few of them know as much as all.
MAX_ASKED = 8
#: Who saw a loss, when it was this process (a tool that watched the token go).
THIS_CLIENT = "this client"


class Asker(Protocol):
    """What :func:`health` and :func:`recall` use of a :class:`dyknow.Client`."""

    def call_manager(self, manager: str, service_name: str, request: Mapping[str, Any]) -> Any: ...

    def seen_lost(self) -> list[dict[str, Any]]: ...


@dataclass(frozen=True, slots=True)
class Loss:
    """A manager lost and not back: since when (wall clock, ns), why, and who remembers it."""

    manager: str
    since_ns: int
    why: str
    seen_by: tuple[str, ...]

    @property
    def stopped(self) -> bool:
        """Whether it said goodbye (stopped on purpose), rather than vanished."""
        return self.why == keys.LOSS_STOPPED

    def said(self, now_ns: int | None = None) -> str:
        """The loss as people read it: ``manager 'robot' is LOST since 18:22:03 (12.3 s ago, as
        station saw it): why``."""
        when = time.strftime("%H:%M:%S", time.localtime(self.since_ns / 1e9))
        ago = max(0.0, ((time.time_ns() if now_ns is None else now_ns) - self.since_ns) / 1e9)
        who = self.seen_by[0] if len(self.seen_by) == 1 else f"{', '.join(self.seen_by[:-1])} and {self.seen_by[-1]}"
        if len(self.seen_by) > 3:
            who = f"{', '.join(self.seen_by[:2])} and {len(self.seen_by) - 2} others"
        return f"manager {self.manager!r} is LOST since {when} ({ago:.1f} s ago, as {who} saw it): {self.why}"

    def fix(self) -> str:
        """What brings it back."""
        if self.stopped:
            return f"start it again (dyknow manager --name {self.manager}) if it should run; its requests moved or are degraded"
        return (
            "its host, or the link to it, back: a crashed manager restarted, or the network between here and its host "
            "(across sites, the link between the gateways' routers: each router logs its links to the others going and coming "
            "back); it is listed again within a lease of its return, and its requests move back by themselves"
        )

    def error(self, where: str | None = None) -> ServiceError:
        """The error of a call to the lost manager (``details["reason"]`` ``"lost"``)."""
        return ServiceError(self.said(), where=where, expected=self.fix(), details={"reason": "lost", **self.to_dict()})

    def to_dict(self) -> dict[str, Any]:
        """The JSON form: ``{"manager", "since_ns", "why", "seen_by"}``."""
        return {"manager": self.manager, "since_ns": self.since_ns, "why": self.why, "seen_by": list(self.seen_by)}


@dataclass(frozen=True, slots=True)
class Health:
    """What one manager knows (``get_summary`` with ``health``): the managers it lost
    (``{"manager", "since_ns", "why"}`` each) and its requests that are degraded (``{"tag", "key",
    "reason"}`` each)."""

    manager: str
    lost: tuple[Mapping[str, Any], ...]
    degraded: tuple[Mapping[str, Any], ...]


def health(client: Asker, names: Sequence[str], *, limit: int = MAX_ASKED) -> dict[str, Health]:
    """What each of the first ``limit`` of ``names`` knows, asked in parallel; a manager that
    does not answer (or is older, and knows no ``health``) is left out."""
    found: dict[str, Health] = {}

    def ask(name: str) -> Health | None:
        try:
            reply = client.call_manager(name, "get_summary", {"brief": True, "health": True})
        except DyKnowError as exc:
            log.debug("no health from %r: %s", name, exc)
            return None
        lost, degraded = reply.get("lost"), reply.get("degraded")
        if not isinstance(lost, list) or not isinstance(degraded, list):  # (an older manager: its brief summary alone)
            return None
        return Health(name, tuple(lost), tuple(degraded))

    def keep(name: str) -> None:
        known = ask(name)
        if known is not None:
            found[name] = known  # (one key per thread: no lock needed)

    asked = list(dict.fromkeys(names))[:limit]
    # (threads of its own, not concurrent.futures: a command that fails at once imports no more than it needs)
    threads = [threading.Thread(target=keep, args=(name,), name="dyknow-health", daemon=True) for name in asked[1:]]
    for thread in threads:
        thread.start()
    if asked:
        keep(asked[0])
    for thread in threads:
        thread.join()
    return {name: found[name] for name in asked if name in found}


def merge(reports: Iterable[tuple[str, Iterable[Mapping[str, Any]]]], up: Iterable[str] = ()) -> dict[str, Loss]:
    """One :class:`Loss` per manager from what each reporter (``(who, entries)``) remembers, the
    earliest loss first, without the managers ``up`` (back by now), by name."""
    back = set(up)
    found: dict[str, Loss] = {}
    for who, entries in reports:
        for entry in entries:
            name, since, why = entry["manager"], entry["since_ns"], entry["why"]
            if name in back:
                continue
            known = found.get(name)
            if known is None:
                found[name] = Loss(name, since, why, (who,))
            elif who not in known.seen_by:
                first = since < known.since_ns
                found[name] = Loss(name, since if first else known.since_ns, why if first else known.why, (*known.seen_by, who))
    return dict(sorted(found.items()))


def recall(client: Asker, names: Sequence[str], *, healths: Mapping[str, Health] | None = None) -> dict[str, Loss]:
    """The managers lost and not back, as this client saw them go and as ``names`` (the managers
    up; :data:`MAX_ASKED` of them asked, unless ``healths`` already holds their word) remember."""
    known = health(client, names) if healths is None else healths
    return merge([(THIS_CLIENT, client.seen_lost()), *((h.manager, h.lost) for h in known.values())], up=names)


class Presence:
    """Which managers have left: their liveliness tokens went away (stopped, crashed, or cut off
    past their lease). A call to one of them ends at once, saying so, instead of waiting for its
    service to come back. And which are up: a call to a manager never seen, while others are,
    ends after a second (a misspelled name), listing those there.

    A client is a tool (a command, the web page), so it watches every manager's token and
    goodbye, as no manager does (a manager watches only those it follows: :mod:`dyknow.federation`);
    :meth:`lost` is what it saw leave since it started."""

    def __init__(self, session: Session) -> None:
        self._lock = threading.Lock()
        self._gone: dict[str, float] = {}  # manager -> time.monotonic() when its token went
        self._lost: dict[str, tuple[int, str]] = {}  # manager -> (wall-clock ns when its token went, why)
        self._goodbyes: dict[str, float] = {}  # manager -> time.monotonic() of its goodbye
        self._up: set[str] = set()
        self._watches: list[LivelinessSubscriber] = []
        try:
            self._watches.append(session.declare_liveliness_subscriber(keys.managers_pattern(), self._change, inline=True))
            self._watches.append(session.declare_liveliness_subscriber(keys.goodbye_token("*"), self._goodbye, inline=True))
        except TransportError as exc:  # a closed session, say: calls just wait as before
            log.debug("no watch of the managers' liveliness: %s", exc)

    def _change(self, key: str, alive: bool) -> None:
        name = keys.manager_of_token(key)
        if name is None:
            return
        with self._lock:
            self._gone.pop(name, None)
            self._lost.pop(name, None)
            if alive and len(self._up) < MAX_GONE:
                self._up.add(name)
            if not alive:
                self._up.discard(name)
                now = time.monotonic()
                self._gone[name] = now
                said = self._goodbyes.pop(name, None)
                stopped = said is not None and now - said < keys.GOODBYE_S
                self._lost[name] = (time.time_ns(), keys.LOSS_STOPPED if stopped else keys.LOSS_VANISHED)
                for kept in (self._gone, self._lost):
                    while len(kept) > MAX_GONE:
                        del kept[next(iter(kept))]

    def _goodbye(self, key: str, alive: bool) -> None:
        name = key.rpartition("/")[2]
        if not alive or keys.manager_of_token(keys.manager_token(name)) != name:
            return
        with self._lock:
            if name in self._lost:  # (its token's end came first)
                self._lost[name] = (self._lost[name][0], keys.LOSS_STOPPED)
                return
            self._goodbyes[name] = time.monotonic()
            while len(self._goodbyes) > MAX_GONE:
                del self._goodbyes[next(iter(self._goodbyes))]

    def heard(self) -> tuple[set[str], set[str]]:
        """The managers whose tokens came since the watch began, and those whose tokens went."""
        with self._lock:
            return set(self._up), set(self._gone)

    def lost(self) -> list[dict[str, Any]]:
        """The managers whose tokens went since the watch began and that are not back, by name:
        ``{"manager", "since_ns" (wall clock), "why"}`` each."""
        with self._lock:
            return [{"manager": m, "since_ns": since, "why": why} for m, (since, why) in sorted(self._lost.items())]

    def why_absent(self, manager: str) -> str | None:
        """Why ``manager`` is not there when others are and it was never seen, or None."""
        with self._lock:
            if not self._up or manager in self._up or manager in self._gone:
                return None
            return f"no manager {manager!r} among those reachable ({', '.join(sorted(self._up)[:20])})"

    def why_gone(self, manager: str) -> str | None:
        """Why ``manager`` is known to be gone, or None (it is up, or was never seen)."""
        with self._lock:
            since = self._gone.get(manager)
        if since is None:
            return None
        return (
            f"manager {manager!r} is gone: its liveliness token went away {time.monotonic() - since:.1f} s ago "
            "(it stopped, crashed, or its host was cut off past its lease)"
        )

    def close(self) -> None:
        for watch in self._watches:
            watch.undeclare()
        self._watches.clear()


