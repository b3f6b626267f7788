"""What a manager offers the others: the tags of its summary (:func:`offered`), each announced as a
liveliness token (:func:`dyknow.keys.offer_token`) by its :class:`Offers`, so that a manager that
needs a tag finds its providers with one liveliness query, without following the whole fleet.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from dyknow import keys
from dyknow.errors import DyKnowError
from dyknow.federation.summary import Summary
from dyknow.tags import local_name, parse_term

log = logging.getLogger("dyknow.federation")  # one name for the federation, whichever part logs

#: The most tags a manager announces as offer tokens; the rest are found only through its summary.
MAX_OFFERS = 1_024


def offered(summary: Summary) -> set[tuple[str, tuple[str, ...]]]:
    """The tags a manager offers, ``(functor, args)`` by local names: those of its library's
    output ports and of its running units' outputs (what :func:`dyknow.keys.offer_token` announces)."""
    tags = [t for s in summary.specs for p in s.outputs for t in s.tags_for(p.name)]
    tags.extend(t for u in summary.units for ts in u.tags.values() for t in ts)
    found: set[tuple[str, tuple[str, ...]]] = set()
    for tag in tags:
        try:
            term = parse_term(tag)
        except DyKnowError:
            continue
        found.add((local_name(term.functor), tuple(local_name(a) for a in term.args)))
    return found


class Offers:
    """This manager's offer tokens: one per tag its summary offers (at most :data:`MAX_OFFERS`).

    ``lock`` is the directory's: as it closes, the directory takes every token back in the same
    locked step as its watches (:meth:`withdraw`), after which ``closed()`` is true and a token
    declared meanwhile is undeclared at once. ``bound(what, line)`` counts a refusal by a bound
    (the line logged once per kind).
    """

    def __init__(
        self, session: Any, name: str, *, lock: threading.Lock, closed: Callable[[], bool], bound: Callable[[str, str], None]
    ) -> None:
        self.name = name
        self._session = session
        self._lock = lock
        self._closed = closed
        self._bound = bound
        self._offers: dict[str, Any] = {}  # this manager's offer tokens, by key
        # and the index that answers which of them a query covers: an offer whose manager
        # answers is told from a token anyone could declare (issue 51)
        self._index: Any = None
        self._held: tuple[str, ...] = ()  # the keys of the tokens, replaced whole (read on Zenoh's thread, without the lock)

    def announce(self, summary: Summary) -> None:
        """Declare an offer token per tag this manager's summary offers (at most MAX_OFFERS), and
        withdraw those of tags it no longer offers."""
        wanted: set[str] = set()
        too_long = 0
        for functor, args in offered(summary):
            key = keys.offer_token(functor, args, self.name)
            if len(key.encode()) > keys.MAX_KEY_BYTES:
                too_long += 1
            else:
                wanted.add(key)
        if too_long:
            self._bound(
                "offer-too-long",
                f"manager {self.name!r}: {too_long} of its tags make offer keys over {keys.MAX_KEY_BYTES} bytes; not announced "
                "(other managers find them only once they follow this one)",
            )
        if len(wanted) > MAX_OFFERS:
            self._bound(
                "offers",
                f"manager {self.name!r} offers {len(wanted)} tags; announces {MAX_OFFERS} of them (MAX_OFFERS): the others are "
                "found only by the managers that follow it already",
            )
            wanted = set(sorted(wanted)[:MAX_OFFERS])
        with self._lock:
            gone = [self._offers.pop(k) for k in list(self._offers) if k not in wanted]
            add = sorted(wanted - set(self._offers))
            index = self._index is None and not self._closed()
            self._held = tuple(self._offers)
        if index:
            try:
                declared = self._session.declare_index(keys.offers_of(self.name), self.held)
            except DyKnowError as exc:
                log.warning("manager %r: cannot answer for its offers: %s", self.name, exc)
            else:
                with self._lock:
                    if self._closed() or self._index is not None:
                        gone.append(declared)
                    else:
                        self._index = declared
        for entity in gone:
            entity.undeclare()
        for key in add:
            try:
                token = self._session.declare_liveliness_token(key)
            except DyKnowError as exc:
                log.warning("manager %r: cannot announce its offer %s: %s", self.name, key, exc)
                continue
            with self._lock:
                if self._closed():
                    token.undeclare()
                    return
                self._offers[key] = token
                self._held = tuple(self._offers)

    def held(self) -> list[str]:
        """The keys of this manager's offer tokens now (what its index answers from)."""
        return list(self._held)

    def withdraw(self) -> list[Any]:
        """(Under the lock.) Forget every offer token and the index; returns them, to undeclare."""
        tokens = list(self._offers.values())
        if self._index is not None:
            tokens.append(self._index)
            self._index = None
        self._offers.clear()
        self._held = ()
        return tokens
