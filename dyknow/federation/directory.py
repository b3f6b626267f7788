"""The directory of the other managers: a :class:`Directory` follows the managers a manager needs
(the providers of the tags its plans need, those in use), their liveliness and their summaries,
and lets them go when nothing needs them any more, within bounds whatever the fleet announces.
"""

from __future__ import annotations

import concurrent.futures
import functools
import json
import logging
import random
import threading
import time
from collections import Counter
from collections.abc import Callable, Collection, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from dyknow import keys
from dyknow.errors import DyKnowError
from dyknow.federation.offers import Offers
from dyknow.federation.summary import Summary

log = logging.getLogger("dyknow.federation")  # one name for the federation, whichever part logs

#: The directory's own random numbers (which unknown candidates to sample): never the global
#: ``random`` state, which the program around a manager may have seeded for its own sequence.
_RANDOM = random.Random()

# A manager whose summary could not be fetched is asked again after 0.05 s, then twice as long
# each time up to 2 s: a fetch made as a manager's token appears can fail for a moment (its
# services not reachable yet, a watcher that has not yet seen the token), and a fixed 2 s made a
# healed partition wait for it (issue 43).
_RETRY_FIRST_S = 0.05
_RETRY_S = 2.0
#: What a manager publishes on its summary key as it stops, before its token goes: the others
#: then tell a manager that stopped from one that crashed or was cut off.
GOODBYE = b'{"stopping":true}'
_MAX_LOST = 1_000  # lost managers remembered (names come from the network: bounded)
# What a manager keeps of a fleet is bounded whatever the others announce (issue 40):
_MAX_ALIVE = 10_000  # managers listed by alive() (a name each)
_ALIVE_S = 1.0  # alive() asks who is up at most this often (a liveliness query; the answer before meanwhile)
_MAX_FOLLOWED = 256  # managers whose summaries are followed (candidates, managers in use)
_MAX_OFFER_KEYS = 1_024  # tags whose providers are watched
_MAX_HELD = 64  # providers of a tag whose comings and goings are held while discover() chooses (4 x MAX_CANDIDATES)
_MAX_TODO = 100_000  # changes waiting for the directory's thread
_DISCOVER_TIMEOUT_S = 1.0
#: How much longer a plan waits for a tag none of whose candidates' summaries came within
#: _DISCOVER_TIMEOUT_S: a real provider on a loaded host, or with a large library, may take longer
#: (beside CPU hogs, a library of 1,500 tags did); it ends at the first summary read. A tag offered
#: only by names with nobody behind them is held up this long once, and then planned without them.
_PATIENT_S = 5.0
_FETCHERS = 8  # summaries fetched at once
_DOUBTERS = 2  # summaries of managers that never answered, asked again at once
_GIVE_UP_ASKS, _GIVE_UP_S = 10, 30.0  # a manager followed that gives no summary for that long is let go (followed again if it restarts)
#: The most providers of one tag whose summaries a planner reads.
MAX_CANDIDATES = 16
#: Why a manager is lost, when it said goodbye.
STOPPED = keys.LOSS_STOPPED
_VANISHED = keys.LOSS_VANISHED


class Directory:
    """The other managers a manager plans with, and the last summary each published.

    A manager follows only the managers it needs, so what it pays does not grow with the fleet
    (issue 40). It announces each tag it offers as a liveliness token
    (:func:`dyknow.keys.offer_token`); :meth:`discover` finds the providers of the tags a plan
    needs with one liveliness query per tag, reads the summaries of those candidates only, and
    follows them from then on (their summary key, and new offers of those tags). Only the
    managers followed have their liveliness tokens (and goodbyes) watched, each on its own key: a
    manager joining or leaving the fleet costs nothing to those that do not follow it, so joins
    cost the fleet N, not N x N. A manager followed is a candidate of a plan, or one ``in_use()``
    names (it runs units for this one, or this one for it), or one :meth:`follow` was asked for.
    What a request needed is let go when it ends (:meth:`keep`): the providers' watches of its
    tags, and the candidates no other need, use or follow keeps. :meth:`alive` lists the whole
    fleet reachable by a liveliness query, on demand.

    ``fetch(name)`` asks a manager for its summary (the manager's client call, bytes back);
    ``on_change(kind, name)`` is told "found", "lost" or "changed" about managers followed, on
    the directory's thread. ``summarize()`` gives this manager's own summary, published by
    :meth:`changed` (debounced) with its offers.
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
        in_use: Callable[[], Collection[str]] | None = None,
    ) -> None:
        self.name = name
        self._session = session
        self._summarize = summarize
        self._fetch = fetch
        self._on_change = on_change
        self._in_use = in_use
        self._debounce_s = debounce_s
        self._publish_s = 0.0  # how long building and sending the last summary took
        self._lock = threading.Lock()
        self._offers = Offers(session, name, lock=self._lock, closed=lambda: self._closed, bound=self._bound)  # this manager's offer tokens
        self._up = threading.Condition(self._lock)  # told when a manager followed is seen up
        self._alive: set[str] = set()  # managers followed whose token is up
        self._reachable: set[str] | None = None  # every manager's token up, at the last query (alive())
        self._asked_at = -_ALIVE_S
        self._asking = False
        self._answered = threading.Event()
        self._received: Counter[str] = Counter()  # liveliness changes this directory's watches delivered, by kind
        self._summaries: dict[str, Summary] = {}
        # manager -> what watches it: its summary subscriber, its token's and its goodbye's (oldest use first)
        self._followed: dict[str, list[Any]] = {}
        self._pinned: dict[str, None] = {}  # managers follow() was asked for (not let go when a request ends)
        self._needs: dict[str, set[str]] = {}  # offers pattern -> the needs (requests' tags) discover() was asked for it by
        self._open: set[str] = set()  # the needs open at the last keep()
        self._ended: set[str] = set()  # needs that ended, to let go on the directory's thread
        self._lingering: set[str] = set()  # candidates of needs that ended, kept while in use
        self._sweep = False
        self._to_follow: set[str] = set()  # managers follow() was asked for, not followed yet
        self._fetching: set[str] = set()  # managers asked for their summaries now (on a fetcher)
        self._failures: dict[str, tuple[int, float]] = {}  # manager -> (asks in vain in a row, since when)
        self._offer_watch: dict[str, Any] = {}  # offers pattern -> its liveliness subscriber (oldest use first)
        self._candidates: dict[str, set[str]] = {}  # offers pattern -> the providers seen
        self._discovering: set[str] = set()  # offers patterns discover() is choosing the providers of now
        # offers pattern -> manager -> up: what their watches said while discover() chose (replayed after)
        self._held: dict[str, dict[str, bool]] = {}
        self._refused: Counter[str] = Counter()  # what the directory refused, by reason (bounds)
        self._said: set[str] = set()  # the bounds already logged (one line each)
        self._pool: ThreadPoolExecutor | None = None
        self._doubt_pool: ThreadPoolExecutor | None = None  # asks again the managers that never answered
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
        self._offers.announce(summarize())  # its offers before its token: whoever sees it can find what it offers
        self._token = session.declare_liveliness_token(keys.manager_token(name))
        # and answers for its name: a token alone, which anyone may declare without TLS, does not
        # (a listing of the managers puts those that answer first: Client.managers_page, issue 51)
        token_key = keys.manager_token(name)
        self._index = session.declare_index(token_key, lambda: [token_key])
        self._goodbye: Any = None  # this manager's goodbye token, as it stops
        self.changed()

    # -- what is known

    def peers(self) -> dict[str, Summary]:
        """The reachable managers followed (this one excluded) whose summary is known, by name."""
        with self._lock:
            return {m: s for m, s in self._summaries.items() if m in self._alive}

    def alive(self) -> set[str]:
        """The names of the managers whose liveliness token is up (this one excluded; at most
        10,000). Asked of Zenoh when called (a liveliness query, a name each), at most once a
        second: meanwhile the answer before, with the managers followed as their watches tell
        (those are watched; the others are not). The first call waits for its answer (up to 1 s)."""
        now = time.monotonic()
        with self._lock:
            ask = not self._asking and now - self._asked_at >= _ALIVE_S and not self._closed
            if ask:
                self._asking, self._asked_at = True, now
        if ask:
            try:
                self._session.ask_alive(keys.managers_pattern(), timeout_s=_ALIVE_S, limit=_MAX_ALIVE, done=self._reached)
            except DyKnowError as exc:
                log.debug("directory of %r: cannot ask who is up: %s", self.name, exc)
                with self._lock:
                    self._asking = False
        if self._reachable is None and ask:
            self._answered.wait(_ALIVE_S + 0.5)
        with self._lock:
            followed_down = set(self._followed) - self._alive
            return ((self._reachable or set()) - followed_down) | self._alive

    def _reached(self, tokens: list[str], count: int) -> None:
        """The answer of :meth:`alive`'s query (on a Zenoh thread)."""
        names = {m for m in map(keys.manager_of_token, tokens) if m is not None and m != self.name}
        with self._lock:
            self._reachable, self._asking = names, False
        self._answered.set()
        if count > _MAX_ALIVE:
            self._bound("alive", f"directory of {self.name!r}: {count} manager tokens up; listing {_MAX_ALIVE} of them")

    def received(self) -> dict[str, int]:
        """How many liveliness changes this directory's watches delivered, by kind ("manager
        tokens", "goodbyes", "offers"): what the fleet's comings and goings cost it. Only the
        managers followed, and the providers of the tags its plans need, are watched."""
        with self._lock:
            return dict(self._received)

    def watched(self) -> set[str]:
        """The offers patterns whose providers are watched (the tags the plans of open requests need)."""
        with self._lock:
            return set(self._offer_watch)

    def followed(self) -> set[str]:
        """The managers whose summaries this one follows (candidates of its plans, managers in use)."""
        with self._lock:
            return set(self._followed)

    def refused(self) -> dict[str, int]:
        """What the directory refused to keep, by reason (a flood of tokens, too many offers)."""
        with self._lock:
            return dict(self._refused)

    def follow(self, manager: str, *, at_once: bool = False) -> bool:
        """Follow ``manager``'s summary from now on (fetched soon, on the directory's thread);
        True when it was not followed yet. For a manager in use that was no candidate: the owner
        of a unit this one runs. ``at_once``: subscribe to its summary key (and its token and
        goodbye) before returning; not on a Zenoh thread (the subscription is a call into Zenoh).
        A manager followed so stays followed when requests end (least recently used ones make way
        beyond 256), unless it gives no summary (:data:`_GIVE_UP_S`)."""
        if manager == self.name or keys.manager_of_token(keys.manager_token(manager)) != manager:
            return False
        if at_once:
            new = self._follow(manager, pin=True)
            if new:
                self._queue("offer", manager, None)
            return new
        with self._lock:  # (followed on the directory's thread: this may be called on Zenoh's)
            if manager in self._followed:
                self._pin(manager)
                return False
            if manager in self._to_follow or len(self._to_follow) >= _MAX_FOLLOWED:
                return False
            self._to_follow.add(manager)
        self._queue("follow", manager, None)
        return True

    def _pin(self, manager: str) -> None:
        """(Under the lock.) ``manager`` was asked for by :meth:`follow`."""
        self._pinned[manager] = None
        while len(self._pinned) > _MAX_FOLLOWED:
            del self._pinned[next(iter(self._pinned))]

    def discover(
        self, wanted: Iterable[tuple[str, tuple[str, ...]]], timeout_s: float = _DISCOVER_TIMEOUT_S, *, need: str | None = None
    ) -> bool:
        """Find the providers of the tags ``wanted`` (``(functor, args)`` by local names), read
        the summaries of those not followed yet, and follow them; True when a summary was added.

        One liveliness query per tag not asked about before (:func:`dyknow.keys.offers_pattern`),
        all at once; a tag asked about stays watched (new providers are noticed as they appear),
        up to 1,024 tags. At most :data:`MAX_CANDIDATES` providers per tag are taken (a log line
        says when there were more: those already followed first, then a random choice, so names
        chosen to sort first do not crowd out the others). Called on the planner's thread: it
        waits for the answers, at most ``timeout_s`` for the query and as long for the summaries
        (and for the tokens of the managers it follows so, which say they are up).

        ``need``: what asks (a request's tag): when no open request has it any more
        (:meth:`keep`), the watches of these tags and the candidates no other need keeps are let go.
        """
        patterns = sorted({keys.offers_pattern(f, a) for f, a in wanted})
        with self._lock:
            for p in patterns:
                if p in self._offer_watch:
                    self._offer_watch[p] = self._offer_watch.pop(p)  # used: the last to go
                if need is not None:
                    self._needs.setdefault(p, set()).add(need)
            new = [p for p in patterns if p not in self._offer_watch]
            # watched already, with a provider that never answered among them: the managers that
            # answer for the tag are asked again (tokens anyone may declare must not hide them)
            doubtful = [
                p for p in patterns if p in self._offer_watch and any(m not in self._summaries for m in self._candidates.get(p, ()))
            ]
        if (not new and not doubtful) or self._closed:
            return False
        if len(new) > _MAX_OFFER_KEYS:
            self._bound("tags", f"directory of {self.name!r}: a plan needs {len(new)} tags; watching the providers of {_MAX_OFFER_KEYS}")
            new = new[:_MAX_OFFER_KEYS]
        answers: dict[str, tuple[list[str], int]] = {}
        answering: dict[str, set[str]] = {}
        done = threading.Event()

        pending = [2 * len(new) + len(new) + len(doubtful)]

        def arrived() -> None:  # (the lock held)
            pending[0] -= 1
            if pending[0] == 0:
                done.set()

        def answered(pattern: str, found: list[str], count: int) -> None:
            with self._lock:
                before, counted = answers.get(pattern, ([], 0))
                answers[pattern] = (sorted({*before, *found}), max(counted, count))
                arrived()

        index_pending = [len(new) + len(doubtful)]
        index_done = threading.Event()

        def indexed(pattern: str, found: list[str], count: int) -> None:
            with self._lock:
                answering.setdefault(pattern, set()).update(
                    m for m in map(keys.manager_of_offer, found) if m is not None and m != self.name
                )
                index_pending[0] -= 1
                if index_pending[0] == 0:
                    index_done.set()
                arrived()

        def ask() -> None:
            for p in new:
                try:
                    self._session.ask_alive(p, timeout_s=timeout_s, limit=4 * MAX_CANDIDATES, done=functools.partial(answered, p))
                except DyKnowError as exc:
                    log.warning("directory of %r: cannot ask who offers %s: %s", self.name, p, exc)
                    answered(p, [], 0)

        def ask_index() -> None:
            for p in [*new, *doubtful]:
                try:
                    # (it ends once every manager answered: the longer bound is waited for only
                    # when more managers offer a tag than are followed, see _discover)
                    self._session.ask_index(p, timeout_s=timeout_s + _PATIENT_S, limit=MAX_CANDIDATES, done=functools.partial(indexed, p))
                except DyKnowError as exc:
                    log.warning("directory of %r: cannot ask which managers answer for %s: %s", self.name, p, exc)
                    indexed(p, [], 0)

        # asked before the watch and again after it, the answers together: a Zenoh client's
        # liveliness query just after a liveliness subscriber on the same key expression finds
        # nothing (a manager behind a router planned nothing), and a provider that appears
        # between the first query and the watch is found by the second
        with self._lock:
            self._discovering.update(new)  # (their watches' first news: the answers to these queries)
        try:
            return self._discover(new, doubtful, ask, ask_index, answers, answering, (done, index_done), timeout_s)
        finally:
            with self._lock:
                self._discovering.difference_update(new)
                held = [(p, self._held.pop(p)) for p in new if p in self._held]
            # what the watches said meanwhile: a provider that came after the last query's answer
            # (while the candidates' summaries were read, seconds under load) is told only now;
            # dropped, it was never seen (a plan said 'nothing provides' for minutes)
            for p, changes in held:
                for manager, up in changes.items():
                    self._offer_seen(p, manager, up, replayed=True)

    def _discover(self, new: list[str], doubtful: list[str], ask: Callable[[], None], ask_index: Callable[[], None],
                  answers: dict[str, tuple[list[str], int]], answering: dict[str, set[str]],
                  events: tuple[threading.Event, threading.Event], timeout_s: float) -> bool:  # fmt: skip
        """:meth:`discover` once its questions are ready: ask them, watch the new tags, choose and
        read the candidates. ``events``: every answer came, and every index answer came."""
        done, index_done = events
        ask()
        ask_index()
        for p in new:
            try:
                watch = self._session.declare_liveliness_subscriber(p, functools.partial(self._offer_change, p), inline=True)
            except DyKnowError as exc:
                log.warning("directory of %r: cannot watch the providers of %s: %s", self.name, p, exc)
                continue
            evicted: list[Any] = []
            with self._lock:
                self._offer_watch[p] = watch
                self._candidates.setdefault(p, set())
                while len(self._offer_watch) > _MAX_OFFER_KEYS:
                    gone = next(iter(self._offer_watch))
                    evicted.append(self._offer_watch.pop(gone))
                    self._candidates.pop(gone, None)
                    self._needs.pop(gone, None)
            for entity in evicted:
                entity.undeclare()
        ask()
        done.wait(timeout_s + 0.5)
        with self._lock:
            crowded = any(count > MAX_CANDIDATES or len(found) > MAX_CANDIDATES for found, count in answers.values())
        if crowded:
            # more managers offer a tag than are followed: those that answer for their offers are
            # chosen first, so a slow answer (a busy host) is waited for, up to _PATIENT_S more;
            # else a random choice may leave the real provider out (tokens anyone may declare)
            index_done.wait(_PATIENT_S)
        with self._lock:
            got = {p: answers.get(p, ([], 0)) for p in new}
            answer = {p: set(ms) for p, ms in answering.items()}
            followed = set(self._followed)
        candidates: set[str] = set()
        for p in doubtful:  # the managers that answer join those of the tokens seen before
            with self._lock:
                self._candidates.setdefault(p, set()).update(answer.get(p, set()))
            candidates.update(answer.get(p, set()))
        for p, (found, count) in sorted(got.items()):
            names = sorted({m for m in map(keys.manager_of_offer, found) if m is not None and m != self.name} | answer.get(p, set()))
            if count > MAX_CANDIDATES or len(names) > MAX_CANDIDATES:
                # those that answer first, then those followed already, then a random choice: names
                # chosen to sort or to arrive first do not crowd out the others
                first = sorted(answer.get(p, set()))[:MAX_CANDIDATES]
                known = [m for m in names if m in followed and m not in first]
                rest = [m for m in names if m not in followed and m not in first]
                chosen = first + known[: MAX_CANDIDATES - len(first)]
                chosen += _RANDOM.sample(rest, max(0, min(len(rest), MAX_CANDIDATES - len(chosen))))
                names = sorted(chosen)
                self._bound(
                    f"candidates {p}",
                    f"directory of {self.name!r}: {max(count, len(names))} managers offer {p}; planning with {len(names)} of them "
                    f"(MAX_CANDIDATES), those that answer for their offers first",
                )
            candidates.update(names)
            with self._lock:
                self._candidates.setdefault(p, set()).update(names)
        answering_any: set[str] = set().union(*answer.values()) if answer else set()
        with self._lock:
            # those that answer for their offers first: a fetcher is not held by a silent name before them
            todo = sorted((m for m in candidates if m not in self._summaries), key=lambda m: (m not in answering_any, m))
        if not todo:
            return False
        for m in todo:
            self._follow(m)
        added: list[str] = []
        # those that did not answer for their offers, when others did, are asked on the fetchers
        # of the managers that never answered: they cannot hold up the fetch of one that did
        futures = [
            (self._doubters() if answering_any and m not in answering_any else self._fetchers()).submit(self._fetch_quietly, m)
            for m in todo
        ]
        # waited for at most timeout_s: a name with a token and nobody behind it holds a call for
        # the client's whole timeout (a flood of them held the request service for 30 s, issue 51);
        # what comes later reaches the directory's thread as a fetch of its own would
        finished, _ = concurrent.futures.wait(futures, timeout=timeout_s)
        finished = self._patiently([*new, *doubtful], dict(zip(todo, futures, strict=True)), set(finished))
        fetched: list[bytes | None] = []
        for m, future in zip(todo, futures, strict=True):
            if future in finished:
                fetched.append(future.result())
            else:
                fetched.append(None)
                future.add_done_callback(functools.partial(self._fetched_late, m))
        for m, data, future in zip(todo, fetched, futures, strict=True):
            if future not in finished:
                continue
            if data is None:
                self._retry_later(m)
                continue
            summary = self._parse(m, data)
            if summary is None:
                self._retry_later(m)
                continue
            with self._lock:
                if m not in self._followed:
                    continue
                self._summaries[m] = summary  # (planned with once its token is up: peers())
            added.append(m)
        # planned with once their tokens are seen (watched from _follow on): it answered, so its
        # token is up, on its way on the watch declared a round trip ago
        with self._up:
            self._up.wait_for(lambda: self._closed or all(m in self._alive or m not in self._followed for m in added), timeout_s)
        return bool(added)

    def _patiently(
        self, patterns: list[str], fetching: dict[str, concurrent.futures.Future[bytes | None]], finished: set[Any]
    ) -> set[Any]:
        """``finished`` (the fetches done within the first wait), and those done while a tag of
        ``patterns`` none of whose candidates has a summary yet waits for one of them, up to
        :data:`_PATIENT_S` more: a tag with a candidate read plans at once."""
        deadline = time.monotonic() + _PATIENT_S

        def read(manager: str) -> bool:
            future = fetching.get(manager)
            return future is not None and future in finished and future.result() is not None

        while not self._closed:
            with self._lock:
                unread = [self._candidates.get(p, set()) for p in patterns]
                unread = [c for c in unread if not any(m in self._summaries or read(m) for m in c)]
            waiting = {fetching[m] for c in unread for m in c if m in fetching and fetching[m] not in finished}
            left = deadline - time.monotonic()
            if not waiting or left <= 0:
                break
            done, _ = concurrent.futures.wait(waiting, timeout=left, return_when=concurrent.futures.FIRST_COMPLETED)
            finished |= done
        return finished

    def keep(self, needs: Collection[str]) -> None:
        """The needs (requests' tags, see :meth:`discover`) open now: those open before and no
        longer are let go, on the directory's thread: the providers' watches of the tags only they
        needed, and the managers followed as their candidates that no open need, use
        (``in_use()``) or :meth:`follow` keeps. Call it as requests come and go."""
        with self._lock:
            ended = self._open - set(needs)
            self._open = set(needs)
            if not ended and not self._lingering:
                return
            self._ended |= ended
            self._sweep = True
        self._wake.set()

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
            self._goodbye = self._session.declare_liveliness_token(keys.goodbye_token(self.name))  # for every manager
            self._session.put(keys.summary_key(self.name), GOODBYE)  # (and for those following it, as before)
        except DyKnowError as exc:
            log.debug("directory of %r: no goodbye: %s", self.name, exc)

    def close(self, timeout_s: float = 2.0) -> None:
        """Say goodbye, stop watching and withdraw this manager's token; safe twice."""
        if self._closed:
            return
        self._closed = True
        self._settle.set()
        self.say_goodbye()
        with self._lock:
            entities = [*(e for es in self._followed.values() for e in es), *self._offer_watch.values(), *self._offers.withdraw(),
                        self._index, self._token, self._goodbye]  # fmt: skip
            self._followed.clear()
            self._offer_watch.clear()
            self._up.notify_all()
        for entity in entities:
            if entity is not None:
                entity.undeclare()
        self._wake.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        for pool in (self._pool, self._doubt_pool):
            if pool is not None:
                pool.shutdown(wait=False, cancel_futures=True)

    # -- following managers

    def _follow(self, manager: str, *, pin: bool = False) -> bool:
        """Follow ``manager``: its summary key, its token and its goodbye token watched, each on
        its own key (no watch of every manager: see the class). The least recently used manager
        not in use makes way beyond 256. True when it was not followed. ``pin``: asked for by
        :meth:`follow` (not let go when a request ends)."""
        with self._lock:
            if pin:
                self._pin(manager)
            if manager in self._followed:
                self._followed[manager] = self._followed.pop(manager)
                return False
            if self._closed:
                return False
            # followed before its watches exist: what they tell at once (its token, up) is kept
            self._followed[manager] = []
            full = len(self._followed) > _MAX_FOLLOWED
        used = set(self._in_use()) if full and self._in_use is not None else set()
        entities: list[Any] = []
        try:
            # on Zenoh's thread: each callback only queues (a thread per watch was three threads a
            # manager followed: 20 -> 435 threads after a flood of tokens, issue 51)
            entities.append(self._session.declare_raw_subscriber(keys.summary_key(manager), self._summary_sample, inline=True))
            entities.append(self._session.declare_liveliness_subscriber(keys.manager_token(manager), self._liveliness, inline=True))
            entities.append(self._session.declare_liveliness_subscriber(keys.goodbye_token(manager), self._goodbye_token, inline=True))
        except DyKnowError as exc:
            log.warning("directory of %r: cannot follow %r: %s", self.name, manager, exc)
        evicted: list[Any] = []
        with self._lock:
            if self._followed.get(manager) != [] or self._closed:
                evicted.extend(entities)  # let go meanwhile (or closed)
            else:
                self._followed[manager] = entities
                while len(self._followed) > _MAX_FOLLOWED:
                    idle = next((m for m in self._followed if m not in used and m != manager), None)
                    if idle is None:
                        break
                    evicted.extend(self._unfollow(idle))
        for entity in evicted:
            entity.undeclare()
        return True

    def _unfollow(self, manager: str) -> list[Any]:
        """(Under the lock.) Forget ``manager`` (not lost: no longer followed); its watches, to undeclare."""
        entities = self._followed.pop(manager, None) or []
        self._summaries.pop(manager, None)
        self._alive.discard(manager)
        self._retry_at.pop(manager, None)
        self._failures.pop(manager, None)
        self._pinned.pop(manager, None)
        return entities

    def _let_go_needs(self, ended: set[str]) -> None:
        """Let go of what only the needs ``ended`` needed (see :meth:`keep`)."""
        used = set(self._in_use()) if self._in_use is not None else set()
        with self._lock:
            freed: list[str] = []
            for p, needs in list(self._needs.items()):
                needs -= ended
                if not needs:
                    del self._needs[p]
                    freed.append(p)
            entities = [self._offer_watch.pop(p) for p in freed if p in self._offer_watch]
            was = set(self._lingering)
            for p in freed:
                was |= self._candidates.pop(p, set())
            kept = set(self._pinned) | self._to_follow
            for providers in self._candidates.values():
                kept |= providers
            # (one still in use, the units of the request that ended being destroyed there, say: let go once it is not)
            self._lingering = {m for m in was & used - kept if m in self._followed}
            gone = sorted(m for m in was - kept - used if m in self._followed)
            for m in gone:
                entities.extend(self._unfollow(m))
        for entity in entities:
            entity.undeclare()
        if freed or gone:
            log.info(
                "directory of %r: %s ended: no longer watching the providers of %d tags%s",
                self.name, ", ".join(sorted(ended)[:5]), len(freed), f", nor following {', '.join(gone[:10])}" if gone else "",
            )  # fmt: skip

    def _fetchers(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(_FETCHERS, thread_name_prefix=f"dyknow-{self.name}-fetch")
        return self._pool

    def _doubters(self) -> ThreadPoolExecutor:
        if self._doubt_pool is None:
            self._doubt_pool = ThreadPoolExecutor(_DOUBTERS, thread_name_prefix=f"dyknow-{self.name}-refetch")
        return self._doubt_pool

    def _fetched_late(self, manager: str, future: concurrent.futures.Future[bytes | None]) -> None:
        """A summary :meth:`discover` did not wait for: to the directory's thread, as a fetch."""
        data = None if future.cancelled() or future.exception() is not None else future.result()
        with self._lock:
            self._todo.append(("fetched", manager, data))  # (one per candidate: bounded as they are)
        self._wake.set()

    def _fetch_quietly(self, manager: str) -> bytes | None:
        try:
            return self._fetch(manager)
        except DyKnowError as exc:
            log.debug("directory of %r: no summary from %r yet: %s", self.name, manager, exc)
            return None

    def _bound(self, what: str, line: str) -> None:
        """Count a refusal by a bound; its log line once per kind of refusal."""
        with self._lock:
            first = self._count_refusal(what)
        if first:
            log.warning("%s", line)

    def _count_refusal(self, what: str) -> bool:
        """Count a refusal by a bound (the lock held); whether it is the first of its kind."""
        self._refused[what.split(" ")[0]] += 1
        first = what not in self._said and len(self._said) < _MAX_LOST
        self._said.add(what)
        return first

    # -- Zenoh callbacks (quick: the work happens on the directory's thread)

    def _liveliness(self, key: str, alive: bool) -> None:
        manager = keys.manager_of_token(key)
        with self._lock:
            self._received["manager tokens"] += 1
        if manager is None or manager == self.name:
            return
        self._queue("found" if alive else "lost", manager, None)

    def _offer_change(self, pattern: str, key: str, alive: bool) -> None:
        manager = keys.manager_of_offer(key)
        with self._lock:
            self._received["offers"] += 1
        if manager is None or manager == self.name:
            return
        self._offer_seen(pattern, manager, alive)

    def _offer_seen(self, pattern: str, manager: str, alive: bool, *, replayed: bool = False) -> None:
        """A provider of ``pattern`` appeared or went (``replayed``: told by discover() once it chose)."""
        with self._lock:
            providers = self._candidates.get(pattern)
            if providers is None:
                return
            if pattern in self._discovering:  # discover() chooses among those there now; the rest is told after
                held = self._held.setdefault(pattern, {})
                if manager in held or len(held) < _MAX_HELD:
                    held[manager] = alive
                return
            if replayed and alive and manager in providers:
                return  # chosen by discover() already
            if not alive:
                providers.discard(manager)
                return
            full = manager not in providers and len(providers) >= MAX_CANDIDATES
            if not full:
                providers.add(manager)
        if full:
            self._bound(f"candidates {pattern}", f"directory of {self.name!r}: more than {MAX_CANDIDATES} managers offer {pattern}; "
                        f"not following {manager!r} (MAX_CANDIDATES)")  # fmt: skip
            return
        self._queue("offer", manager, None)

    def _goodbye_token(self, key: str, alive: bool) -> None:
        manager = key.rpartition("/")[2]
        with self._lock:
            self._received["goodbyes"] += 1
        if alive and manager != self.name and keys.manager_of_token(keys.manager_token(manager)) == manager:
            self._said_goodbye_by(manager)

    def _said_goodbye_by(self, manager: str) -> None:
        with self._lock:
            self._goodbyes[manager] = time.monotonic()
            while len(self._goodbyes) > _MAX_LOST:
                del self._goodbyes[next(iter(self._goodbyes))]
            if manager in self._lost:  # its token's end came first
                self._lost[manager] = (self._lost[manager][0], STOPPED)

    def _summary_sample(self, key: str, payload: bytes) -> None:
        manager = key.split("/")[1] if key.count("/") == 2 else None
        if manager is None or manager == self.name:
            return
        if payload == GOODBYE:
            self._said_goodbye_by(manager)
            return
        self._queue("summary", manager, payload)

    def _queue(self, kind: str, manager: str, data: bytes | None) -> None:
        with self._lock:
            if len(self._todo) >= _MAX_TODO:
                full = True
            else:
                full = False
                self._todo.append((kind, manager, data))
        if full:
            self._bound("backlog", f"directory of {self.name!r}: {_MAX_TODO} changes waiting; dropping {kind} of {manager!r} (a flood of tokens?)")
            return
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
                ended, self._ended = self._ended, set()
                sweep, self._sweep = self._sweep, False
            if sweep:
                try:
                    self._let_go_needs(ended)
                except Exception:
                    log.exception("directory of %r: cannot let go of what %s needed", self.name, sorted(ended)[:5])
            with self._lock:
                # alive, but no summary yet (its fetch failed): ask again, sooner at first
                for m in sorted((self._alive & set(self._followed)) - set(self._summaries)):
                    at, _ = self._retry_at.setdefault(m, (now + _RETRY_S, _RETRY_S))
                    if at <= now and m not in self._fetching and not any(t[1] == m for t in todo):
                        todo.append(("retry", m, None))
                for m in [m for m in self._retry_at if m not in self._alive or m in self._summaries or m not in self._followed]:
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
        with self._lock:
            followed = manager in self._followed
        if kind not in ("retry", "fetched") and (followed or kind == "lost"):
            log.log(logging.INFO if followed else logging.DEBUG, "directory of %r: %s %r", self.name, kind, manager)
        if kind == "lost":
            with self._lock:
                known = manager in self._alive  # (every manager seen is remembered when lost: a name each, at most 1,000)
                self._alive.discard(manager)
                self._summaries.pop(manager, None)  # a manager that comes back starts afresh
                self._retry_at.pop(manager, None)
                said = self._goodbyes.pop(manager, None)
                if known:
                    stopped = said is not None and time.monotonic() - said < keys.GOODBYE_S
                    self._lost[manager] = (time.time_ns(), STOPPED if stopped else _VANISHED)
                    while len(self._lost) > _MAX_LOST:
                        del self._lost[next(iter(self._lost))]
            if known and followed:  # (only a manager followed is watched: a late word of one let go changes nothing)
                self._on_change("lost", manager)
            return
        if kind in ("offer", "follow"):  # a provider of a tag this manager plans with, or a manager in use: follow it
            self._follow(manager, pin=kind == "follow")
            with self._lock:
                self._to_follow.discard(manager)
            kind = "retry"  # fetched below if its token is up (else when its token comes)
        if kind in ("found", "retry"):
            with self._lock:
                followed = manager in self._followed
                if kind == "found" and followed:  # only its token says a manager is up (and only one followed is watched)
                    self._lost.pop(manager, None)
                    self._alive.add(manager)
                    self._up.notify_all()
                # a manager that came back starts afresh (its summary went when it was lost); one
                # asked again, if it has no summary yet
                wanted = followed and manager in self._alive and manager not in self._summaries
            if not wanted:
                return  # not followed, or not up
            self._fetch_soon(manager)  # on a fetcher: a manager slow to answer holds up no other
            return
        if kind == "fetched":
            with self._lock:
                self._fetching.discard(manager)
            if data is None:
                self._failed(manager)
                return
            kind = "found"
        assert data is not None
        with self._lock:
            if manager not in self._followed or manager not in self._alive:
                return  # not followed any more (a summary on its way when it was let go), or gone
        summary = self._parse(manager, data)
        if summary is None:
            if kind == "found":  # fetched, and refused: asked again later (not at once), let go if it persists
                self._retry_later(manager)
                self._failed(manager)
            return
        with self._lock:
            self._failures.pop(manager, None)
            old = self._summaries.get(manager)
            if old is not None and old.version > summary.version and kind == "summary":
                return  # an older publication overtaken by a fetch
            self._summaries[manager] = summary
            alive = manager in self._alive
        if alive:
            self._on_change("found" if kind == "found" or old is None else "changed", manager)

    def _failed(self, manager: str) -> None:
        """No summary (or none worth keeping) came from ``manager`` when asked: counted; let go
        after :data:`_GIVE_UP_ASKS` such asks in a row over :data:`_GIVE_UP_S`."""
        now = time.monotonic()
        with self._lock:
            count, first = self._failures.get(manager, (0, now))
            self._failures[manager] = (count + 1, first)
        if count + 1 >= _GIVE_UP_ASKS and now - first >= _GIVE_UP_S:
            self._let_go(manager)

    def _let_go(self, manager: str) -> None:
        """Stop following a manager that never gave its summary (a token with no manager behind
        it, say), unless it is in use: its place among the candidates is free again. If it
        starts anew (its offers go and come back on the watches of the tags it offers), or a plan
        or :meth:`follow` asks for it again, it is followed again."""
        used = set(self._in_use()) if self._in_use is not None else set()
        if manager in used:
            return
        with self._lock:
            entities = self._unfollow(manager)
            for providers in self._candidates.values():
                providers.discard(manager)
            first = self._count_refusal(f"silent {manager}")  # with the unfollowing: who sees it let go sees it counted
        for entity in entities:
            entity.undeclare()
        if first:
            log.warning(
                "directory of %r: not following %r any more: no summary after %d asks in %g s (its tokens say it offers "
                "what a plan needs; nothing answers for it)",
                self.name, manager, _GIVE_UP_ASKS, _GIVE_UP_S,
            )  # fmt: skip

    def _fetch_soon(self, manager: str) -> None:
        """Ask ``manager`` for its summary on a fetcher thread; the answer comes back to the
        directory's thread as a "fetched" change (None: no answer, asked again later)."""
        with self._lock:
            if manager in self._fetching or self._closed:
                return
            self._fetching.add(manager)
            silent = manager in self._failures  # asked in vain before: a token with nobody behind it, maybe
        try:
            # the managers that never answered are asked again on fetchers of their own: a flood of
            # names nobody answers for cannot hold the fetchers of those that do (issue 51)
            (self._doubters() if silent else self._fetchers()).submit(self._fetch_job, manager)
        except RuntimeError:  # (closed meanwhile)
            with self._lock:
                self._fetching.discard(manager)

    def _fetch_job(self, manager: str) -> None:
        data = self._fetch_summary(manager)
        with self._lock:
            self._todo.append(("fetched", manager, data))  # (not bounded by _MAX_TODO: one per manager followed)
        self._wake.set()

    def _fetch_summary(self, manager: str) -> bytes | None:
        try:
            return self._fetch(manager)
        except DyKnowError as exc:
            wait = self._retry_later(manager)
            # (the first failures are expected as a manager appears: said only once it persists)
            log.log(logging.WARNING if wait >= _RETRY_S else logging.DEBUG, "directory of %r: no summary from %r yet: %s", self.name, manager, exc)
            return None

    def _parse(self, manager: str, data: bytes) -> Summary | None:
        """``manager``'s summary from what it sent (reusing what is unchanged since the last
        one), or None, said in the log, when it is not one."""
        with self._lock:
            previous = self._summaries.get(manager)
        try:
            return Summary.from_json(data, manager, previous)
        except DyKnowError as exc:
            with self._lock:
                self._refused["summary"] += 1
            log.warning("directory of %r: %s", self.name, exc)
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
        summary = self._summarize()
        try:
            self._session.put(keys.summary_key(self.name), json.dumps(summary.to_dict()))
        except DyKnowError as exc:
            log.warning("directory of %r: cannot publish the summary: %s", self.name, exc)
        self._offers.announce(summary)
