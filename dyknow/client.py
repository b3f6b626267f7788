"""The client: calls a manager's services from another process over Zenoh.

Every method mirrors the manager's, takes JSON-friendly arguments and returns the manager's JSON
reply (plain dicts and lists). A refused request raises the same exception class the manager
raised (``UnitError``, ``BindingError``, ``SpecError``, ...); a manager that does not answer raises
:class:`~dyknow.errors.ServiceError`, whose ``details["reason"]`` says why, as far as it can be
told (:mod:`dyknow.reach`): ``refused``, ``unreachable``, ``silent``, ``tls-listener``,
``tls-untrusted``, ``tls-rejected`` (the endpoint), ``no-such-manager`` (others are there:
``details["managers"]``), ``no-manager`` (linked, and no manager is there at all), ``no-role``
(linked, but nothing visible), ``dropped`` (an access control on the way), ``gone`` (its token
went away), ``lost`` (it went before this client started, and the managers up remember it:
since when, why, who saw it; :mod:`dyknow.presence`) or ``timeout`` (with ``details["link"]``:
``"cut"`` when not even its clock exchange answers, ``"up"`` when it does: busy or stuck).

A manager that is not there is said after a grace of at most a second, not after the timeout:
the client's own session is a Zenoh client, whose router answers the client's first question
(which managers' liveliness tokens are up) whole, tokens and then the end of them. A call to a
manager not among them, nor heard of since, is sent once anyway (to a manager that announces no
token, ``--alone``, it goes through); when it reaches nothing and the grace is over (a manager
whose "ready" was printed a moment ago may not be heard of yet), it ends, naming the managers
that are there.

Usage::

    with Client("robot", connect=["tcp/127.0.0.1:7447"]) as client:
        client.spawn("relay", "relay1")
        print(client.get_model()["units"])
"""

from __future__ import annotations

import fnmatch
import json
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dyknow import keys, reach, replies
from dyknow.access import ROLES, AccessControl, TlsFiles
from dyknow.errors import DyKnowError, ServiceError, SpecError, SpecIssue, TransportError, did_you_mean
from dyknow.message import CLOCK_ID, Message
from dyknow.presence import MAX_GONE, Loss, Presence, recall
from dyknow.transport import (
    DEFAULT_ENDPOINT,
    MAX_ALIVE_KEYS,
    LivelinessToken,
    Session,
    Subscriber,
    check_key_expr,
    make_config,
)

if TYPE_CHECKING:
    from dyknow.clocks import Estimate

# (dyknow.service, dyknow.clocks and dyknow.model are imported where they are
# needed: a command that fails at once, or reads a model, does not pay for the services' checks,
# the formula parser they pull in, or the clock estimates: the dyknow command starts faster)

__all__ = ["Client"]

log = logging.getLogger(__name__)

_MAX_PAGES = 100_000  # of one model: far past any manager's (each page holds at least one entry)
#: How long a call waits for a manager never seen while others are up, before it says so: a
#: manager's token and its services come to a client together, so this is ample.
_ABSENT_S = 1.0
#: How long a call that finds no service at once waits for the answer to the client's first
#: question, which managers are up (a round trip; it is looked at again while the call waits).
_ASKED_S = 0.05
_DIAL_MS = 2000  # how long a client that could not connect at once gives each new attempt (TCP and TLS handshakes)


def _clock_id(raw: Any) -> int | None:
    """A clock id as a model shows it (8 hex digits), or None."""
    if not isinstance(raw, str) or len(raw) != 8:
        return None
    try:
        return int(raw, 16)
    except ValueError:
        return None


def _number(value: Any) -> float | None:
    """A finite number of a model (under 10^15: µs of years), or None."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and abs(value) < 1e15:
        return float(value)
    return None


class _Answer:
    """The answer to a liveliness query: the keys of the tokens that are up, once the whole answer
    came (None until then, and for good when Zenoh's timeout ended it, or it held too many)."""

    def __init__(self) -> None:
        self.keys: list[str] | None = None
        self.ended = threading.Event()
        self._late = False

    def timed_out(self) -> None:
        self._late = True

    def done(self, keys: list[str], count: int) -> None:
        if not self._late and count <= len(keys):
            self.keys = keys
        self.ended.set()


class ClockView:
    """The clock offsets a manager estimates (:meth:`Client.clocks`), kept current by a thread of
    its own (a clock drifts; a peer appears): a process that reads messages from other hosts
    corrects their times by it. A context manager (:meth:`Client.follow_clocks`).

    This host's clock is taken as the manager's (a client beside its manager shares its clock).
    """

    def __init__(self, client: Client, manager: str, every_s: float = 5.0) -> None:
        self.manager = manager
        self.every_s = every_s
        self.fetched = threading.Event()  # set once the first look is over (found or not)
        self.found: bool | None = None  # whether the manager was reachable at the latest look
        self.reachable: list[str] = []  # the managers reachable then
        from dyknow.clocks import Estimate

        self._client = client
        self._estimates: dict[int, Estimate] = {CLOCK_ID: Estimate(CLOCK_ID, 0, 0, 0.0, 0, 0)}  # swapped whole
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._follow, name="dyknow-clock-view", daemon=True)
        self._thread.start()

    def __enter__(self) -> ClockView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop following; safe twice."""
        self._done.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=self._client.timeout_s + 2.0)

    def corrected(self, clock: int, t_ns: int, now_ns: int | None = None) -> tuple[int, int] | None:
        """``t_ns`` of clock ``clock`` (a header's ``origin_clock``) on this host's clock, and its
        uncertainty (ns); None when the manager does not know that clock (yet)."""
        estimate = self._estimates.get(clock)
        if estimate is None:
            return None
        offset, uncertainty = estimate.carried(time.time_ns() if now_ns is None else now_ns)
        return t_ns - offset, uncertainty

    def _follow(self) -> None:
        from dyknow.clocks import Estimate

        client = self._client
        while True:
            try:  # (a manager that is not there would hold each look up for the client's timeout)
                self.reachable = client.manager_names(timeout_s=min(client.timeout_s, 1.0))
                self.found = self.manager in self.reachable
                if self.found:
                    found = client.clocks(self.manager)
                    self._estimates = {CLOCK_ID: Estimate(CLOCK_ID, 0, 0, 0.0, 0, 0), **{e.clock: e for e in found.values()}}
            except DyKnowError as exc:
                log.debug("no clock offsets from %r: %s", self.manager, exc)
            self.fetched.set()
            if self._done.wait(self.every_s):
                return


class Client:
    """A connection to one manager's services. A context manager; ``close()`` is safe twice.

    ``lease_ms``: Zenoh's lease for the client's own session; give it the managers' lease (see
    :func:`~dyknow.transport.make_config`), so that a host cut off is dropped by every process alike.

    Its own session (without ``zenoh_config``) only connects: it is a Zenoh *client* of the
    endpoints it connects to when one answers at once (the process there, a manager or a router,
    carries its calls and its streams), else a peer without a listener that keeps trying. It
    never listens, so clients do not mesh with each other: as listening peers, 32 clients on one
    machine connected to each other and spent 1.4 cores on each other's declarations
    (``benchmarks/load.py``).
    """

    def __init__(
        self,
        manager: str,
        *,
        connect: Sequence[str] = (DEFAULT_ENDPOINT,),
        zenoh_config: str | os.PathLike[str] | None = None,
        timeout_s: float = 5.0,
        session: Session | None = None,
        tls: TlsFiles | None = None,
        lease_ms: int | None = None,
    ) -> None:
        self.manager = manager
        self.timeout_s = timeout_s
        self._own_session = session is None
        self._connect = [] if session is not None and tuple(connect) == (DEFAULT_ENDPOINT,) else list(connect)
        self._tls = tls.check() if tls is not None else None  # (files that do not belong together: said here, naming them)
        tls = self._tls
        # with a certificate, every call carries its caller's signature (a manager with --acl
        # checks it, whichever routers or managers carry the call): dyknow.identity
        self._signer = None
        if tls is not None:  # (cryptography's x509 is imported only for a client with a certificate: the command starts faster)
            from dyknow.identity import Signer

            self._signer = Signer(tls)
        # whether the session is a Zenoh client, whose router answers a liveliness query for the
        # network and says when it is done (a peer answers from what it heard so far: 1 of 120
        # fresh peer sessions asked just after their link came up heard nothing)
        self._routed = False
        # set when the session could not connect at once: what probing each endpoint found
        # (None: connected, or nothing to probe), so a call that cannot work fails saying why
        self._findings: list[reach.Finding] | None = None
        self._found_at = 0.0  # when they were found (time.monotonic())
        self._no_session = False  # TCP went through at the start, but Zenoh opened no session (a full router)
        # the timeout counts from here for what the client does before it ever reached anything
        # (a command's whole wait for a silent host is its --timeout: issue 43)
        self._started = time.monotonic()
        if session is None and zenoh_config is None:
            reach.check_endpoints(self._connect, tls)
        if session is None:
            if self._connect and zenoh_config is None:
                session = self._open_leaf(lease_ms)
            else:
                session = Session(make_config(connect=self._connect, config_file=zenoh_config, tls=tls, lease_ms=lease_ms))
        self._session = session
        # Which managers are up, asked before the watch below begins: while a watch's first
        # tokens are on their way, Zenoh answers such a question from what the session heard so
        # far (nothing, in 19 of 30 fresh sessions), and asked first, the router answers it whole
        # (50 of 50). A call to a manager not among them (nor heard of since) is sent once and,
        # when it reaches nothing, ends at once (see _call).
        self._first = self._ask_managers()
        self._presence = Presence(session)
        # the requests this client holds (dyknow.holders): key -> (references, the token that says it is alive)
        self._holder = os.urandom(8).hex()  # (what secrets.token_hex does, without importing it)
        if self._signer is not None:  # a manager with roles takes only ids of the certificate's own scope (dyknow.holders)
            self._holder = keys.holder_scope(self._signer.common_name) + self._holder
        self._held: dict[str, tuple[int, LivelinessToken]] = {}
        self._held_lock = threading.Lock()
        self._recalling = threading.Lock()  # held while asking the managers about one not there (never nested)

    def _open_leaf(self, lease_ms: int | None) -> Session:
        """A session that only connects: a Zenoh client of the endpoints when one answers now,
        else a peer without a listener that keeps trying. What the first try found about each
        endpoint (:mod:`dyknow.reach`) is kept: a call made while every endpoint refuses for a
        reason no manager starting there would change (nothing listens, TLS refused) fails at
        once, saying why; otherwise calls wait for the manager (it may be starting), together no
        longer than ``timeout_s`` from here, and then say what the endpoints did."""
        # (Zenoh's client would wait up to its open timeout, 10 s, for a host that does not answer)
        found = reach.dial(self._connect, timeout_s=min(1.0, self.timeout_s))
        if any(f.kind == "ok" for f in found):
            # (a busy router is tried again within the timeout: a peer's liveliness queries are
            # answered from what it heard itself, so a client fallen back to one lists nothing)
            opened = reach.open_patiently(
                lambda: Session(make_config(connect=self._connect, tls=self._tls, lease_ms=lease_ms, mode="client", listen=[])),
                self._connect,
                patience_s=self.timeout_s,
                who=f"client of {', '.join(self._connect)}",
            )
            if opened is not None:
                self._routed = True
                return opened
            found = []  # TCP went through but Zenoh did not: its TLS is probed at the first call
            self._no_session = True
        self._findings, self._found_at = found, time.monotonic()
        # each attempt to dial bounded (closing the session ends one under way: Session.close)
        return Session(make_config(connect=self._connect, tls=self._tls, lease_ms=lease_ms, listen=[], open_timeout_ms=_DIAL_MS))

    def _fresh_findings(self) -> list[reach.Finding] | None:
        """What probing the endpoints found, when the session has no link: the last findings while
        they are younger than the timeout, else the endpoints probed again; None once linked."""
        if self._findings is None or self._session.linked():
            return None
        if not self._findings or time.monotonic() - self._found_at > self.timeout_s:
            self._findings = reach.probe_all(self._connect, self._tls, timeout_s=min(1.0, self.timeout_s))
            self._found_at = time.monotonic()
        if self._no_session:  # (what went through to a Zenoh that opened no session, as tried at the start)
            return [reach.no_session(f.endpoint) if f.kind == "ok" else f for f in self._findings]
        return self._findings

    def _budget(self, timeout_s: float) -> float:
        """``timeout_s``, or less while the session never reached anything and the client's own
        timeout, counted from its start, ends sooner (at least 50 ms)."""
        if self._findings is None or self._session.linked():
            return timeout_s
        left = self._started + self.timeout_s - time.monotonic()
        return max(0.05, min(timeout_s, left)) if left > 0 else timeout_s

    def _probe(self) -> None:
        """When the session never connected and has no link now: raise at once when each endpoint
        fails for good (refused, unreachable, TLS refused either way)."""
        findings = self._fresh_findings()
        if findings and all(f.definite for f in findings):
            raise self._unlinked_error(findings)

    def unreachable(self) -> ServiceError | None:
        """Why this client reaches nothing, when its session has no link: each endpoint probed
        (:mod:`dyknow.reach`; findings younger than the timeout are not probed again); None when
        it has a link (or nothing was found wrong)."""
        if self._session.linked() or not self._connect:
            return None
        findings = self._fresh_findings()
        if findings is None:
            findings = reach.probe_all(self._connect, self._tls, timeout_s=min(1.0, self.timeout_s))
        return self._unlinked_error(findings, "any manager") if any(f.kind not in ("ok", "unknown") for f in findings) else None

    def _unlinked_error(self, findings: Sequence[reach.Finding], who: str | None = None) -> ServiceError:
        failed = [f for f in findings if f.kind not in ("ok", "unknown")] or list(findings)
        what = "; ".join(f.what or f"no link to {f.endpoint}" for f in failed)
        expected = "; or ".join(dict.fromkeys(f.expected for f in failed if f.expected)) or self._expected(self.manager)
        who = who or f"manager {self.manager!r}"
        return ServiceError(f"cannot reach {who}: {what}", expected=expected, details={"reason": failed[0].kind})

    def _ask_managers(self) -> _Answer | None:
        """Ask which managers' tokens are up, when the answer will be whole (the client's own
        session, a Zenoh client, linked now); else None. Returns at once: the answer comes to the
        :class:`_Answer` a round trip later."""
        if not self._routed or not self._session.linked():
            return None
        answer = _Answer()
        try:
            self._session.ask_alive(
                keys.managers_pattern(), timeout_s=self.timeout_s, limit=MAX_GONE, done=answer.done, timed_out=answer.timed_out
            )
        except TransportError as exc:
            log.debug("no first look at the managers: %s", exc)
            return None
        return answer

    def _known_up(self, wait_s: float) -> list[str] | None:
        """The managers up as the network said at first (whole), with those heard of since and
        without those gone, sorted; None when that is not known (not asked, not answered within
        ``wait_s`` more, not whole, or the session has no link now)."""
        first = self._first
        if first is None or not first.ended.wait(wait_s) or first.keys is None or not self._session.linked():
            return None
        came, went = self._presence.heard()
        names = {m for m in (keys.manager_of_token(k) for k in first.keys) if m is not None}
        return sorted((names | came) - went)

    def _expected(self, manager: str) -> str:
        expected = f"a running manager (dyknow manager --name {manager})"
        if self._tls is not None or any(e.startswith("tls/") for e in self._connect):
            expected += " whose CA signed this client's certificate (and whose --acl, if any, gives it a role)"
        return expected

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the client's own session (not one it was given); safe twice. The requests it
        holds are released by their manager a grace period later (:mod:`dyknow.holders`)."""
        with self._held_lock:
            tokens = [token for _, token in self._held.values()]
            self._held.clear()
        for token in tokens:
            token.undeclare()
        self._presence.close()
        if self._own_session:
            self._session.close()

    @property
    def session(self) -> Session:
        """The Zenoh session the client calls through."""
        return self._session

    # ------------------------------------------------------------------ calls

    def _call(self, key: str, request: Mapping[str, Any], what: str, manager: str | None = None) -> Any:
        manager = manager or self.manager
        where = f"manager {manager!r}" + (f" at {', '.join(self._connect)}" if self._connect else "")
        self._probe()
        # a manager never heard of is said absent only after this grace: one that started a
        # moment ago (its "ready" printed) may not be heard of yet, its token on its way
        grace_over = time.monotonic() + min(_ABSENT_S, self.timeout_s / 2)
        started = time.monotonic()
        known: list[list[str]] = []  # the managers up, once absent() found the manager not among them
        waited = [False]

        def gone() -> str | None:
            why = self._presence.why_gone(manager)
            if why is None and time.monotonic() > grace_over:
                why = self._presence.why_absent(manager)
            return why

        def absent() -> str | None:  # (while the service is not found)
            if time.monotonic() < grace_over:
                return None
            names = self._known_up(0.0 if waited[0] else _ASKED_S)
            waited[0] = True
            if names is None or manager in names:
                return None
            known[:] = [names]  # (Session.call sends the request once more: a manager --alone announces no token)
            return f"no manager {manager!r} is there (no liveliness token of it is up, and the call reached nothing)"

        try:
            reply = self._session.call(
                key,
                json.dumps(request).encode(),
                timeout_s=self.timeout_s,
                reachable_within_s=self._budget(self.timeout_s),
                what=f"{what} of {where}",
                sign=self._signer.sign if self._signer is not None else None,
                gone=gone,
                absent=absent,
            )
        except ServiceError as exc:
            reason = exc.details.get("reason") if exc.kind is None else None
            if reason == "absent" and known:
                raise self._unanswered(manager, where, known[0]) from exc  # (naming those there)
            if reason == "gone" and self._presence.why_absent(manager) is not None:
                raise self._unanswered(manager, where) from exc  # (with the close match)
            if reason == "unreachable":
                raise self._unanswered(manager, where) from exc
            if reason == "dropped" and self._signer is not None:
                chunks = key.split("/")
                unit = len(chunks) == 5 and chunks[2] == "unit"  # @dyknow/<manager>/unit/<name>/<service>
                roles = [r for r in AccessControl().roles_for_call(what, unit=unit) if r in ROLES]  # (manager: not a person's)
                raise ServiceError(
                    f"{where} dropped the call to {what!r} without a reply: the manager's --acl does not let this client's "
                    f"certificate (common name {self._signer.common_name!r}, --tls-cert {self._tls.cert if self._tls else ''}) call it",
                    expected=f"a certificate whose common name has a role that may call {what!r} in the manager's --acl file "
                    f"({' or '.join(roles) or 'none of the built-in roles'}, or a role its define lists it in)",
                    details={"reason": "dropped"},
                ) from exc
            if exc.kind is None and (str(exc) == "Timeout" or (reason is None and str(exc).endswith(f"within {self.timeout_s:g} s"))):
                raise self._timed_out(what, where, time.monotonic() - started, manager) from None
            from dyknow import service

            replies.check_error(exc.details, manager, what)  # (a refusal's fields: another process's word, as a reply is)
            raise service.raise_remote(exc) from None
        return replies.check_reply(replies.decode_reply(reply, manager, what), manager, what)

    def _timed_out(self, what: str, where: str, waited_s: float, manager: str) -> ServiceError:
        """A call that reached the manager's service and got no answer in time (Zenoh says only
        "Timeout"): busy or stuck, or cut off, told apart by its clock exchange, which a manager
        answers at once on Zenoh's thread however busy it is (:meth:`answers_at_once`)."""
        from dyknow import service

        check = "" if what in service.READ_ONLY_SERVICES else "; before calling again, check whether it was done (dyknow model)"
        if what in service.READ_ONLY_SERVICES:
            done = "it only reads, so nothing was changed"
            busy = "a longer --timeout (timeout_s) if the manager is busy, or a manager that is not stuck (its log says why)"
        else:
            done = "the request was sent to it and may still be carried out"
            busy = "a longer --timeout (timeout_s) if the manager is busy (planning, spawning, a slow unit's setup)"
        answers = self.answers_at_once(manager)
        cut = (
            "the link to its host back (across sites: the link between the gateways' routers, which log it going and coming back); "
            "a manager cut off still seems there until its lease expires, then dyknow managers shows it LOST"
        )
        if answers is False:
            cause, expected, link = (
                "nothing of it answers now, not even its clock exchange (answered at once, however busy it is): the link to it is "
                "cut, or its host stalled",
                cut,
                "cut",
            )
        elif answers is True:
            cause, expected, link = "its clock exchange answers at once, so the link is up: it is busy or stuck", busy, "up"
        else:
            cause, expected, link = "it is busy or stuck, or the link to it is cut", f"{busy}; or {cut}", "unknown"
        return ServiceError(
            f"no answer from {where} to {what!r} within {self.timeout_s:g} s (waited {waited_s:.1f} s; --timeout): its service "
            f"is there, and did not answer in time: {cause}; {done}",
            expected=expected + check,
            details={"reason": "timeout", "call": what, "waited_s": round(waited_s, 3), "may_have_run": what not in service.READ_ONLY_SERVICES,
                     "link": link},
        )  # fmt: skip

    def answers_at_once(self, manager: str, timeout_s: float = 1.0) -> bool | None:
        """Whether ``manager`` answers a clock exchange within ``timeout_s``: a manager answers
        one at once on Zenoh's thread, however busy its services are, so no answer says the link
        to it is down (or its host stalled) while its token, up until its lease expires, says it
        is there. None when the question could not be sent."""
        from dyknow import clocks

        ended = threading.Event()
        answered = [False]

        def done(got: tuple[bytes, int, int, int] | None) -> None:
            answered[0] = got is not None
            ended.set()

        try:
            self._session.exchange(keys.clock_key(manager), clocks.request(time.time_ns()), timeout_s=timeout_s, done=done)
        except TransportError as exc:
            log.debug("no clock exchange with %r: %s", manager, exc)
            return None
        return answered[0] if ended.wait(timeout_s + 1.0) else None

    def _unanswered(self, manager: str, where: str, known: list[str] | None = None) -> ServiceError:
        """Why nothing answered within the timeout, or (``known``: the managers that are there,
        as the network said) why nothing will, as far as it can be told (see :mod:`dyknow.reach`)."""
        findings = self._fresh_findings()
        if findings is not None:
            return self._unlinked_error(findings)
        waited = known is None
        if known is not None:
            names = known
        else:
            try:
                names = self.manager_names(timeout_s=0.5)
            except ServiceError:
                names = []
            if not names:  # (a query slow to answer, under load: the tokens heard say who is there)
                came, went = self._presence.heard()
                names = sorted(came - went)
        if manager not in names and self._recalling.acquire(blocking=False):
            try:  # (a manager that anyone remembers as lost is said so, never a misspelling)
                loss = self.recall_lost(names).get(manager)
            finally:
                self._recalling.release()
            if loss is not None:
                return loss.error(where.split(" at ", 1)[-1] if self._connect else None)
        if names and manager not in names:
            return ServiceError(
                f"no manager {manager!r} among those reachable ({', '.join(names)})",
                where=where.split(" at ", 1)[-1] if self._connect else None,
                expected=f"--manager one of {', '.join(names)}{did_you_mean(manager, names)}",
                details={"reason": "no-such-manager", "managers": names},
            )
        expected = self._expected(manager)
        within = f" within {self.timeout_s:g} s" if waited else ""
        if not names and self._signer is not None:
            return ServiceError(
                f"no answer from {where}{within}: linked, but no manager is visible from here",
                expected=f"a running manager (dyknow manager --name {manager}) whose --acl gives this client's certificate "
                f"(common name {self._signer.common_name!r}) a role: without one, it shows the client nothing",
                details={"reason": "no-role"},
            )
        if not waited and manager not in names:
            linked = f"linked to {', '.join(self._connect)}" if self._connect else "linked"
            return ServiceError(
                f"cannot reach manager {manager!r}: {linked}, but no manager is there (no manager's liveliness token is up)",
                expected=f"{expected} that this endpoint reaches (--connect); or --wait S for one that is starting",
                details={"reason": "no-manager", "managers": []},
            )
        return ServiceError(f"no answer from {where}{within}", expected=expected, details={"reason": "timeout"})

    def _manager(self, service_name: str, request: Mapping[str, Any]) -> Any:
        return self.call_manager(self.manager, service_name, request)

    def _unit(self, name: str, service_name: str, request: Mapping[str, Any]) -> Any:
        return self.call_unit(self.manager, name, service_name, request)

    def call_manager(self, manager: str, service_name: str, request: Mapping[str, Any]) -> Any:
        """Call service ``service_name`` of ``manager`` (any manager reachable) with a JSON request."""
        return self._call(keys.manager_service_key(manager, service_name), request, service_name, manager)

    def call_unit(self, manager: str, unit: str, service_name: str, request: Mapping[str, Any]) -> Any:
        """Call proxy service ``service_name`` of ``unit`` on ``manager``."""
        return self._call(keys.unit_service_key(manager, unit, service_name), request, service_name, manager)

    def add_transformation(self, xml_or_path: str | os.PathLike[str]) -> list[str]:
        """Send a spec (XML text, or a file's path) to the manager; returns the labels added."""
        text = str(xml_or_path)
        path = "<client>"
        if isinstance(xml_or_path, os.PathLike) or not text.lstrip().startswith("<"):
            file = Path(text)
            try:
                text = file.read_text(encoding="utf-8")
            except OSError as exc:
                raise SpecError([SpecIssue(str(file), 0, f"cannot read: {exc.strerror or exc}")]) from exc
            path = str(file)
        return list(self._manager("add_transformation", {"xml": text, "path": path})["labels"])

    def remove_transformation(self, label: str) -> bool:
        """Ask the manager to forget the spec ``label``; returns whether it had one."""
        return bool(self._manager("remove_transformation", {"label": label})["removed"])

    def spawn(
        self,
        label: str,
        name: str,
        *,
        protected: bool = False,
        params: Mapping[str, Any] | None = None,
        bindings: Mapping[str, str] | None = None,
    ) -> dict[str, Any]:
        """Start a unit of ``label`` named ``name`` on the manager; returns its model entry."""
        request = {"label": label, "name": name, "protected": protected, "params": dict(params or {}), "bindings": dict(bindings or {})}
        return dict(self._manager("spawn", request))

    def destroy(self, name: str, *, force: bool = False) -> None:
        """Stop unit ``name`` on the manager; a protected unit only with ``force`` (an admin's call
        when the manager has roles)."""
        self._manager("destroy", {"name": name, "force": True} if force else {"name": name})

    def monitor(
        self, formula: str, *, reorder_ms: float = 0.0, keep: bool = False, bindings: Mapping[str, str] | None = None, robustness: bool = False
    ) -> str:
        """Ask the manager to monitor a temporal formula; the key of its verdicts (see
        :meth:`dyknow.manager.Manager.monitor`). :meth:`release` of the key takes it down.
        ``bindings`` bind terms to what exists, with no spec: ``{"Odom(r1)": "ros2:/r1/odom"}``,
        ``ros2dds:/TOPIC`` or a Zenoh key (:mod:`dyknow.reasoning.bindings`). ``robustness``: each
        change of the verdict also says each subformula's robustness (``"robustness_of"``).

        The client holds the monitor as it holds a request: once the client is gone, the manager
        releases it a grace period later (``keep=True``: it runs until released)."""
        request: dict[str, Any] = {"formula": formula, "reorder_ms": reorder_ms}
        if bindings:
            request["bindings"] = dict(bindings)
        if robustness:
            request["robustness"] = True
        if not keep:
            request["holder"] = self._holder
        key = str(self._manager("monitor", request)["key"])
        if not keep:
            self._hold(key)
        return key

    def get_model(self, manager: str | None = None) -> dict[str, Any]:
        """The model of the manager (or of ``manager``): units, specs and requests (the JSON form
        of :class:`~dyknow.model.Model`). A large model comes in pages (each at most the
        manager's ``max_reply_bytes``); this gathers them."""
        name = manager or self.manager
        model = dict(self.call_manager(name, "get_model", {}))
        for _ in range(_MAX_PAGES):
            after = model.pop("next", None)
            if not after:
                break
            page = dict(self.call_manager(name, "get_model", {"page": after}))  # (each page's shape checked: dyknow.replies)
            if page.get("next") and not (page["next"]["units"] > after["units"] or page["next"]["specs"] > after["specs"]):
                raise ServiceError("a model page that does not move on", where=f"manager {name!r}", expected="a manager that pages its model")
            model["units"] += page["units"]
            model["specs"] += page["specs"]
            model["requests"] = page.get("requests", [])
            model["next"] = page.get("next")
        model.pop("next", None)
        model.pop("total", None)
        return model

    def clocks(self, manager: str | None = None, *, model: Mapping[str, Any] | None = None) -> dict[str, Estimate]:
        """Every manager's clock as the manager (or ``manager``) estimates it, from its model:
        manager name -> :class:`~dyknow.clocks.Estimate`, its offset that clock minus the
        manager's (ns), at ``at_ns`` (when the model was read; :meth:`Estimate.carried` carries it
        on by its drift). The manager itself is there too, with offset and uncertainty 0; a
        manager whose offset it does not know yet is not. Offsets are from the manager's clock: a
        client on the manager's host shares it (one host, one clock), so ``origin_ns`` of a
        message stamped by the clock of an estimate reads ``origin_ns - offset`` on this host's
        clock; elsewhere, add how far this host's clock is from the manager's host's. Entries that
        do not parse (a model is another process's word) are left out. ``model``: that manager's
        model, read already (it is not asked again)."""
        from dyknow.clocks import DRIFT_BOUND_PPM, Estimate

        name = manager or self.manager
        raw = (model if model is not None else self.get_model(name)).get("clocks", {})
        now = time.time_ns()
        found: dict[str, Estimate] = {}
        if not isinstance(raw, dict):
            return found
        own = _clock_id(raw.get("clock"))
        if own is not None:
            found[name] = Estimate(own, 0, 0, 0.0, 0, now)
        for peer, entry in raw.items():
            if peer == "clock" or not isinstance(entry, dict):
                continue
            clock = _clock_id(entry.get("clock"))
            offset, uncertainty = _number(entry.get("offset_us")), _number(entry.get("uncertainty_us"))
            if clock is None or offset is None or uncertainty is None or uncertainty < 0:
                continue
            samples = entry.get("samples", 0)
            drift, growth = _number(entry.get("drift_ppm")) or 0.0, _number(entry.get("growth_ppm"))
            found[str(peer)] = Estimate(
                clock,
                round(offset * 1000),
                round(uncertainty * 1000),
                drift,
                samples if isinstance(samples, int) else 0,
                now,
                abs(growth) if growth is not None else DRIFT_BOUND_PPM + abs(drift),  # (a manager that does not say: the bound)
            )
        return found

    def follow_clocks(self, manager: str | None = None, every_s: float = 5.0) -> ClockView:
        """The clock offsets ``manager`` (default: the client's) estimates, looked up every
        ``every_s`` (see :class:`ClockView`); close it (or use it in ``with``) when done."""
        return ClockView(self, manager or self.manager, every_s)

    def get_config(self, name: str) -> dict[str, str]:
        """Port -> key bindings of unit ``name``."""
        return dict(self._unit(name, "get_config", {}))

    def set_config(self, name: str, bindings: Mapping[str, str]) -> dict[str, str]:
        """Rebind ports of unit ``name`` atomically; returns the new bindings."""
        return dict(self._unit(name, "set_config", {"bindings": dict(bindings)}))

    def get_statistics(self, name: str) -> dict[str, Any]:
        """Uptime, reconfigurations and per-port statistics of unit ``name``."""
        return dict(self._unit(name, "get_statistics", {}))

    def request(self, tag: str, *, standby: str | None = None, require: Sequence[str] = (), keep: bool = False) -> str:
        """Ask the manager for a stream of ``tag``; returns its key (PlanningError when nothing fits).

        ``standby="warm"`` keeps the next-best configuration running beside it (see
        :meth:`dyknow.manager.Manager.request`); an unknown mode is refused as a UnitError naming the
        field and the allowed values, before anything is sent. ``require``: formulas the stream
        must satisfy (a false verdict makes it adapt).

        The client holds the request: once it is gone (closed, crashed, cut off), the manager
        releases it a grace period later (:mod:`dyknow.holders`). ``keep=True`` leaves it
        running until someone releases it (``dyknow request`` does).
        """
        request: dict[str, Any] = {"tag": tag}
        if require:
            request["require"] = list(require)
        if standby is not None:
            from dyknow.model import check_standby

            request["standby"] = check_standby(standby)
        if not keep:
            request["holder"] = self._holder
        key = str(self._manager("request", request)["key"])
        if not keep:
            self._hold(key)
        return key

    def _hold(self, key: str) -> None:
        """One more reference held on ``key``: its token says this client is there while it holds any."""
        with self._held_lock:
            references, token = self._held.get(key) or (0, None)
            if token is None:
                token = self._session.declare_liveliness_token(keys.holder_token(key, self._holder))
            self._held[key] = (references + 1, token)

    def release(self, key: str, *, force: bool = False) -> int:
        """Give back a request made with :meth:`request` (or a monitor); returns how many
        references to it remain (another client's, or an earlier request of the same tag): it
        runs on while any does. A client gives back only what it (or, on a manager with roles,
        its certificate's name) requested; ``force`` gives back every reference, whoever took
        it (an admin's call on a manager with roles)."""
        with self._held_lock:
            held = key in self._held
        request: dict[str, Any] = {"key": key, "holder": self._holder} if held else {"key": key}
        if force:
            request["force"] = True
        reply = self._manager("release", request)
        with self._held_lock:
            references, was = self._held.get(key) or (0, None)
            if references > 1 and was is not None and not force:
                self._held[key] = (references - 1, was)
            elif was is not None:
                del self._held[key]
                was.undeclare()
        remaining = reply.get("references", 0) if isinstance(reply, dict) else 0
        return remaining if isinstance(remaining, int) else 0

    def measure(self, name: str, value: float | str) -> None:
        """Record a measurement on the manager (constraints are checked against it)."""
        self._manager("measure", {"name": name, "value": value})

    def get_adaptations(self) -> list[dict[str, Any]]:
        """Every adaptation the manager made so far, oldest first (JSON form of its events)."""
        return list(self._manager("get_adaptations", {}))

    def get_load(self) -> dict[str, Any]:
        """How the manager keeps up: its lanes (threads), their units and how busy each is, and
        its overload state (see :meth:`dyknow.manager.Manager.load`)."""
        return dict(self._manager("get_load", {}))

    # ------------------------------------------------------------------ every manager

    def manager_names(self, timeout_s: float = 1.0, *, match: str | Sequence[str] = "*") -> list[str]:
        """The names of the managers reachable now (their liveliness tokens), sorted; ``match``:
        only those whose names match one of these globs (``robot-*``), asked of Zenoh as such.

        One liveliness query per glob: a name each (tens of bytes), however many managers there
        are; their summaries and models are read a page at a time (:meth:`managers_page`)."""
        globs = [match] if isinstance(match, str) else list(match)
        found: set[str] = set()
        for glob in globs or ["*"]:
            pattern = keys.managers_matching(glob)
            names = (keys.manager_of_token(k) for k in self._session.alive(pattern, timeout_s=self._budget(timeout_s)))
            found.update(m for m in names if m is not None and fnmatch.fnmatchcase(m, glob))
        return sorted(found)

    def answering_managers(self, timeout_s: float = 1.0, *, match: str | Sequence[str] = "*") -> set[str]:
        """The managers (of those whose names match ``match``) that answer for their names: each
        manager answers a query on its token's key. A liveliness token alone, which anyone may
        declare without TLS, does not: thousands of tokens of names that run no manager are told
        from the managers that are there (issue 51). Empty when none answered (or the query is
        not allowed: an ACL lets a client that is no manager query services only)."""
        globs = [match] if isinstance(match, str) else list(match)
        found: set[str] = set()
        for glob in globs or ["*"]:
            answers: list[list[str]] = []
            done = threading.Event()

            def answered(found_keys: list[str], count: int, answers: list[list[str]] = answers, done: threading.Event = done) -> None:
                answers.append(found_keys)
                done.set()

            try:
                self._session.ask_index(keys.managers_matching(glob), timeout_s=self._budget(timeout_s), limit=MAX_ALIVE_KEYS, done=answered)
            except DyKnowError:
                continue
            done.wait(timeout_s + 0.5)
            names = (keys.manager_of_token(k) for k in (answers[0] if answers else []))
            found.update(m for m in names if m is not None and fnmatch.fnmatchcase(m, glob))
        return found

    def wait_for_managers(self, names: Sequence[str], timeout_s: float = 10.0) -> list[str]:
        """Wait until every manager in ``names`` is reachable, then return :meth:`manager_names`.

        A manager that has just started, or just connected to this one, is listed once its
        liveliness token has reached this client's network: a script that starts managers and
        lists them at once should wait for them here. Raises :class:`ServiceError` after
        ``timeout_s`` naming the managers still missing and those that are reachable."""
        wanted = set(names)
        deadline = time.monotonic() + timeout_s
        delay = 0.02
        while True:
            reachable = self.manager_names(timeout_s=min(1.0, max(0.25, deadline - time.monotonic())))  # (shorter missed some)
            missing = sorted(wanted.difference(reachable))
            if not missing:
                return reachable
            if time.monotonic() >= deadline:
                raise ServiceError(
                    f"{', '.join(missing)} not reachable after {timeout_s:g} s",
                    where="wait_for_managers",
                    expected=f"the managers reachable now: {', '.join(reachable) or 'none'}; check that each is running and "
                    "connected (dyknow doctor), or wait longer (timeout_s)",
                )
            time.sleep(min(delay, max(0.0, deadline - time.monotonic())))
            delay = min(0.25, delay * 2)

    def managers_page(
        self, timeout_s: float = 1.0, *, match: str | Sequence[str] = "*", limit: int = 100, after: str | None = None
    ) -> dict[str, Any]:
        """One page of :meth:`managers`: ``{"managers": [...], "next": name or None, "total": n}``.

        The managers matching ``match`` whose names sort after ``after`` (a previous page's
        ``next``), at most ``limit`` of them; ``next`` is the name to pass as ``after`` for the
        following page (None on the last), ``total`` how many match in all. Only the page's
        managers are asked for their summaries (8 at once, each a brief one: counts, no library).
        A manager whose summary is not a manager's (:mod:`dyknow.replies`) is left out, and
        ``"refused"`` says why: ``{name: message}``."""
        if limit < 1:
            raise ServiceError(f"a page of {limit} managers", where="managers_page", expected="a limit of at least 1")
        names = self.manager_names(timeout_s, match=match)
        silent: set[str] = set()
        if len(names) > limit:
            # more than a page: the managers that answer for their names first, and the names
            # that do not (tokens with nobody behind them, maybe) listed after them without a
            # call each: a flood of tokens made the listing ask only those and say "no manager
            # reachable" (issue 51). (None answered: the query is not allowed, ask them all.)
            answering = self.answering_managers(timeout_s, match=match)
            if answering:
                silent = {n for n in names if n not in answering}
                names = sorted(n for n in names if n in answering) + sorted(silent)
        rest = names[names.index(after) + 1 :] if after in names else [n for n in names if after is None or n > after]
        page = rest[:limit]
        refused: dict[str, str] = {}

        def brief(name: str) -> dict[str, Any] | None:
            if name in silent:
                return {"manager": name, "host": "", "specs": 0, "units": 0, "requests": 0, "silent": True}
            try:
                try:
                    summary = self.call_manager(name, "get_summary", {"brief": True})
                except ServiceError as exc:
                    if "unknown field 'brief'" not in str(exc):
                        raise
                    summary = self.call_manager(name, "get_summary", {})  # an older manager: its whole summary
            except ServiceError as exc:
                if exc.details.get("reason") == replies.MALFORMED:
                    refused[name] = str(exc)
                return None  # it vanished while asked (or answered no manager's summary): left out
            if not isinstance(summary, dict):
                return None

            def count(field: str) -> int:
                value = summary.get(field, 0)
                return len(value) if isinstance(value, list) else value if isinstance(value, int) and not isinstance(value, bool) else 0

            return {"manager": name, "host": str(summary.get("host", ""))[:256], "specs": count("specs"), "units": count("units"),
                    "requests": count("requests")}  # fmt: skip

        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(8, max(1, len(page)))) as pool:
            listed = [m for m in pool.map(brief, page) if m is not None]
        return {"managers": listed, "next": page[-1] if len(rest) > limit else None, "total": len(names), "refused": refused}

    def managers(
        self, timeout_s: float = 1.0, *, match: str | Sequence[str] = "*", limit: int | None = None, after: str | None = None
    ) -> list[dict[str, Any]]:
        """Every manager reachable (matching ``match``): ``{"manager", "host", "specs", "units",
        "requests"}``, by name. With ``limit``, one page (see :meth:`managers_page`, which also
        says where the next one starts). A manager that vanishes while asked is left out."""
        if limit is not None:
            return list(self.managers_page(timeout_s, match=match, limit=limit, after=after)["managers"])
        listed: list[dict[str, Any]] = []
        cursor = after
        while True:  # (a page at a time: a fleet of 1,000 is read in ten)
            page = self.managers_page(timeout_s, match=match, limit=100, after=cursor)
            listed.extend(page["managers"])
            cursor = page["next"]
            if cursor is None:
                return listed

    def lost_managers(self, manager: str | None = None, *, model: Mapping[str, Any] | None = None) -> list[dict[str, Any]]:
        """The managers the manager (or ``manager``) knew and lost, and that have not come back:
        ``{"manager", "since_ns" (wall clock), "why"}`` each, from its model (or ``model``, read
        already). Entries that do not parse (a model is another process's word) are left out."""
        raw = (model if model is not None else self.get_model(manager or self.manager)).get("lost", [])
        found = []
        for entry in raw if isinstance(raw, list) else []:
            if not isinstance(entry, dict):
                continue
            name, since, why = entry.get("manager"), entry.get("since_ns"), entry.get("why")
            if keys.manager_of_token(keys.manager_token(str(name))) == name and isinstance(since, int) and not isinstance(since, bool) \
                    and 0 <= since < 1 << 63 and isinstance(why, str):  # fmt: skip
                found.append({"manager": name, "since_ns": since, "why": why[:512]})
        return found

    def recall_lost(self, names: Sequence[str] | None = None) -> dict[str, Loss]:
        """The managers lost and not back, by name (:class:`dyknow.presence.Loss`: since when, why,
        who saw it): those this client saw go, and those the managers up (``names``, else those
        reachable now; a few of them asked) remember. A tool started after a loss learns it here."""
        return recall(self, self.manager_names(timeout_s=0.5) if names is None else list(names))

    def seen_lost(self) -> list[dict[str, Any]]:
        """The managers this client saw leave since it started, and that are not back:
        ``{"manager", "since_ns" (wall clock), "why"}`` each, sorted by name. A client watches
        every manager's token and goodbye (a manager lists only the losses of those it follows:
        :meth:`lost_managers`), so a tool that stays up, such as the web page, sees every loss."""
        return self._presence.lost()

    def get_federated_model(
        self, timeout_s: float = 1.0, *, match: str | Sequence[str] = "*", limit: int | None = None, after: str | None = None
    ) -> dict[str, Any]:
        """The model of every manager reachable (matching ``match``): ``{"managers": [model, ...],
        "next": name or None}``, each as :meth:`get_model`. With ``limit``, one page of at most
        that many managers after ``after``; ``next`` is where the following page starts (None on
        the last). Only the page's managers are asked. A manager whose model is not a manager's
        (:mod:`dyknow.replies`) is left out, and ``"refused"`` says why: ``{name: message}``."""
        if limit is not None and limit < 1:
            raise ServiceError(f"a page of {limit} managers", where="get_federated_model", expected="a limit of at least 1")
        names = [n for n in self.manager_names(timeout_s, match=match) if after is None or n > after]
        page = names if limit is None else names[:limit]
        models = []
        refused: dict[str, str] = {}
        for name in page:
            try:
                models.append(self.get_model(name))
            except ServiceError as exc:
                if exc.details.get("reason") == replies.MALFORMED:
                    refused[name] = str(exc)
                continue
        return {"managers": models, "next": page[-1] if limit is not None and len(names) > limit else None, "refused": refused}

    # ------------------------------------------------------------------ streams

    def declare_subscriber(self, key_expr: str, callback: Callable[[Message], None]) -> Subscriber:
        """Receive the messages published on ``key_expr`` (wildcards allowed) by other sessions.

        ``callback(msg)`` runs on a Zenoh thread; undeclare the returned subscriber (or use it as
        a context manager) to stop.
        """
        check_key_expr(key_expr, what="subscription")
        return self._session.declare_subscriber(key_expr, callback)
