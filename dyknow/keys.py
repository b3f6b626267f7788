"""The key scheme: every Zenoh key dyknow uses, built in one place.

Data (streams, events, measurements) lives under ``dyknow/``; services live under ``@dyknow/``
(``@dyknow`` is a verbatim chunk, so a data subscription such as ``**`` or ``dyknow/**`` never
matches a service)::

    dyknow/<manager>/<unit>/<port>            a port's default binding (default_key)
    dyknow/<manager>/requests/<tag>           the stable key of a request (request_key)
    dyknow/<manager>/events/<kind>            the manager's events, e.g. adaptation (event_key)
    dyknow/<manager>/monitors/<n>             the verdicts of a monitored formula (monitor_key)
    <request or monitor key>/holders/<client> a client holds it (holder_token; dyknow.holders)
    dyknow/measurements/<name>                a measurement for every manager (measurement_key)
    dyknow/<manager>/measurements/<name>      a measurement for one manager
    @dyknow/<manager>                         a manager's liveliness token: it is alive (manager_token)
    @dyknow/offers/<functor>/<args>/<manager> a manager offers a tag (offer_token; dyknow.federation)
    @dyknow/clocks/<clock id>/<manager>       whose clock an id is (clock_token; dyknow.clocks)
    @dyknow/goodbye/<manager>                 a manager is stopping (goodbye_token)
    @dyknow/<manager>/summary                 what a manager offers the others (summary_key)
    @dyknow/<manager>/clock                   a manager's clock exchanges (clock_key; dyknow.clocks)
    @dyknow/<manager>/<service>               a manager's services (manager_service_key)
    @dyknow/<manager>/unit/<unit>/<service>   a unit's proxy services (unit_service_key)

Liveliness: every output port declares a liveliness token on its own key (:func:`port_token`),
so whoever consumes a stream can watch its producer with the same key expression; every manager
declares one on ``@dyknow/<manager>`` (:func:`manager_token`), so the managers following it notice
it come and go (each watches the tokens of those it follows, one key each), and a listing finds it
by a liveliness query.

Manager, unit and measurement names become key chunks, so :func:`check_name` admits only
letters, digits, ``_``, ``-`` and ``.`` (not first). Transformation labels are shown and typed
back by people, so :func:`label_problem` admits visible text only: no control or formatting
characters (a U+202E would show one label as another), no spaces at either end, at most
:data:`MAX_LABEL_BYTES`. These two are the one validation of names and labels everywhere.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from dyknow.errors import BindingError, LibraryError, UnitError

__all__ = [
    "DATA_ROOT",
    "MAX_LABEL_BYTES",
    "MAX_KEY_BYTES",
    "MAX_NAME_BYTES",
    "ROS2_SCHEMES",
    "SERVICE_ROOT",
    "ServiceAddress",
    "check_data_key",
    "check_label",
    "check_name",
    "clock_key",
    "clock_token",
    "clocks_of",
    "goodbye_token",
    "GOODBYE_S",
    "HOLDER_SCOPE_DIGITS",
    "holder_scope",
    "holder_token",
    "holders_pattern",
    "holder_tokens_of",
    "LOSS_STOPPED",
    "LOSS_VANISHED",
    "default_key",
    "event_key",
    "label_problem",
    "manager_of_token",
    "manager_prefix",
    "manager_service_key",
    "manager_of_offer",
    "OFFERS",
    "offer_token",
    "offers_of",
    "offers_pattern",
    "manager_token",
    "managers_matching",
    "managers_pattern",
    "measurement_key",
    "measurement_patterns",
    "monitor_key",
    "includes",
    "parse_service_key",
    "port_token",
    "request_key",
    "services_pattern",
    "summaries_pattern",
    "summary_key",
    "unit_prefix",
    "unit_service_key",
]

#: The first chunk of every data key.
DATA_ROOT = "dyknow"
#: The first chunk of every service key (verbatim: wildcards in data subscriptions never reach it).
SERVICE_ROOT = "@dyknow"

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")

#: The longest manager or unit name (bytes). Names become key chunks.
MAX_NAME_BYTES = 128
#: The longest key expression dyknow declares (bytes). Zenoh's transport cannot send a
#: declaration larger than one batch (about 65 kB) and panics when asked to, so keys stay small.
MAX_KEY_BYTES = 1024
#: The longest transformation label (bytes).
MAX_LABEL_BYTES = 256
_UNSAFE_IN_CHUNK = "/*$?#@ "
#: The prefixes of bindings to ROS 2 topics instead of keys: rmw_zenoh's, then DDS's
#: (:mod:`dyknow.ros2.binding`). A manager wires them; as a key, ``ros2:/chatter`` would be a
#: Zenoh key no ROS 2 node reads, so :func:`check_data_key` refuses them.
ROS2_SCHEMES = ("ros2:", "ros2dds:")


def check_name(name: object, what: str) -> str:
    """Return ``name`` if it can be a manager or unit name (a key chunk); else raise :class:`UnitError`.

    ``what`` says which name it is, for the message ("unit name", "manager name").
    """
    if isinstance(name, str) and len(name.encode()) > MAX_NAME_BYTES:
        raise UnitError(f"{what} of {len(name.encode())} bytes is too long", expected=f"at most {MAX_NAME_BYTES} bytes")
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise UnitError(
            f"{what} {name!r} is not a valid name",
            expected="letters, digits, '_', '-' or '.', not starting with '-' or '.' (it becomes part of Zenoh keys)",
        )
    return name


def check_data_key(key: str, what: str) -> str:
    """Return ``key`` if a port may bind to it; else raise :class:`BindingError` naming ``what``.

    Ports carry data: a key with a verbatim chunk (one starting with ``@``) is dyknow's services,
    liveliness and summaries (``@dyknow/...``) or Zenoh's admin space (``@/...``), and an output
    bound there would pose as a manager (its port token would be a manager's token).
    """
    if key.startswith(ROS2_SCHEMES):
        raise BindingError(
            f"{key[:200]!r} is a ROS 2 binding, not a key",
            where=what,
            expected="a manager's spawn or set_config for ros2: bindings (a unit's own set_config takes keys only)",
        )
    if any(chunk.startswith("@") for chunk in key.split("/")):
        raise BindingError(
            f"{key[:200]!r} has a chunk starting with '@', which is for services and Zenoh's admin space, not data",
            where=what,
            expected="a data key without '@', like 'robot/camera/image'",
        )
    return key


def label_problem(label: object) -> tuple[str, str] | None:
    """Why ``label`` cannot be a transformation label, as ``(got, expected)``; None when it can."""
    expected = (
        f"visible text of 1 to {MAX_LABEL_BYTES} bytes without spaces at either end, control or formatting "
        "characters, like 'undistort(robot)'"
    )
    if not isinstance(label, str):
        return f"got a {type(label).__name__}", expected
    size = len(label.encode(errors="replace"))
    if size == 0 or size > MAX_LABEL_BYTES:
        return f"a label of {size} bytes", expected
    if label != label.strip():
        return f"{label!r} has spaces at an end", expected
    bad = next((c for c in label if not c.isprintable()), None)
    if bad is not None:
        return f"{label!r} holds the character U+{ord(bad):04X}", expected
    return None


def check_label(label: object, what: str = "label") -> str:
    """Return ``label`` if it can be a transformation label; else raise :class:`LibraryError` naming ``what``."""
    problem = label_problem(label)
    if problem is not None:
        raise LibraryError(problem[0], where=what, expected=problem[1])
    assert isinstance(label, str)
    return label


def clock_key(manager: str) -> str:
    """Where a manager answers clock exchanges: ``@dyknow/<manager>/clock`` (see :mod:`dyknow.clocks`)."""
    return f"{SERVICE_ROOT}/{manager}/clock"


def default_key(manager: str, unit: str, port: str) -> str:
    """Where a port is bound unless told otherwise: ``dyknow/<manager>/<unit>/<port>``."""
    return f"{DATA_ROOT}/{manager}/{unit}/{port}"


def manager_prefix(manager: str) -> str:
    """The prefix of a manager's own data keys: ``dyknow/<manager>/`` (its units' default
    bindings, its requests, its events: what its summary may offer)."""
    return f"{DATA_ROOT}/{manager}/"


def unit_prefix(manager: str, unit: str) -> str:
    """The prefix of a unit's default port keys: ``dyknow/<manager>/<unit>/``."""
    return f"{DATA_ROOT}/{manager}/{unit}/"


def includes(key_expr: str, key: str) -> bool:
    """Whether the key expression ``key_expr`` matches the concrete ``key``, as Zenoh matches them.

    ``*`` stands for one chunk, ``**`` for any number of chunks (none too), ``$*`` for any text
    inside a chunk; neither wildcard reaches a verbatim chunk (one starting with ``@``), which
    only the same chunk matches. Walked without recursion (the ACL's data rights use it on keys
    callers choose).
    """
    pattern, chunks = key_expr.split("/"), key.split("/")
    here = {0}  # how many chunks of the key the pattern's chunks so far can have matched
    for part in pattern:
        after: set[int] = set()
        if part == "**":
            for start in sorted(here):
                after.add(start)
                for end in range(start, len(chunks)):
                    if chunks[end].startswith("@"):
                        break
                    after.add(end + 1)
        else:
            after = {i + 1 for i in here if i < len(chunks) and _chunk_matches(part, chunks[i])}
        here = after
        if not here:
            return False
    return len(chunks) in here


def _chunk_matches(part: str, chunk: str) -> bool:
    if part == chunk:
        return True
    if chunk.startswith("@"):
        return False
    if part == "*":
        return True
    pieces = part.split("$*")
    if len(pieces) == 1:
        return False
    if not chunk.startswith(pieces[0]) or not chunk.endswith(pieces[-1]) or len(chunk) < len(pieces[0]) + len(pieces[-1]):
        return False
    at, end = len(pieces[0]), len(chunk) - len(pieces[-1])
    for piece in pieces[1:-1]:
        found = chunk.find(piece, at, end)
        if found < 0:
            return False
        at = found + len(piece)
    return True


def request_key(manager: str, tag: str) -> str:
    """The stable key of a request: ``dyknow/<manager>/requests/<tag>`` (unsafe characters as ``_``)."""
    chunk = "".join(c if c not in _UNSAFE_IN_CHUNK else "_" for c in tag) or "_"
    return f"{DATA_ROOT}/{manager}/requests/{chunk}"


def members_key(manager: str, n: int, k: int) -> str:
    """Where the members of a parameterized term of the ``n``-th monitor are relayed to it (its
    ``k``-th family): ``dyknow/<manager>/members/<n>/<k>`` (:mod:`dyknow.reasoning.members`)."""
    return f"{DATA_ROOT}/{manager}/members/{n}/{k}"


def monitor_key(manager: str, n: int) -> str:
    """Where the verdicts of the ``n``-th formula a manager monitors are published:
    ``dyknow/<manager>/monitors/<n>`` (see :mod:`dyknow.reasoning.monitors`)."""
    return f"{DATA_ROOT}/{manager}/monitors/{n}"


#: The hexadecimal digits of a caller's scope, which start its client ids on a manager with roles.
HOLDER_SCOPE_DIGITS = 16


def holder_token(key: str, holder: str) -> str:
    """The liveliness token a client declares while it holds the request or monitor on ``key``:
    ``<key>/holders/<holder>`` (a quantified monitor's key without its ``/*``, one per variable:
    ``monitors/4/*/*`` is held on ``monitors/4/holders/<holder>``; :mod:`dyknow.holders`)."""
    while key.endswith("/*"):  # (only one was taken off: a nested forall's holder was never seen, and its monitors went after the grace)
        key = key[:-2]
    return f"{key}/holders/{holder}"


def holders_pattern(manager: str = "*") -> str:
    """The holder tokens of every request and monitor of ``manager`` (default: of every manager)."""
    return f"{DATA_ROOT}/{manager}/*/*/holders/*"


def holder_scope(common_name: str) -> str:
    """What starts the client ids of the caller whose certificate's common name is
    ``common_name``, on a manager with roles: the first :data:`HOLDER_SCOPE_DIGITS` hexadecimal
    digits of its SHA-256 (:mod:`dyknow.holders`)."""
    import hashlib  # (here: only a client with a certificate, or a manager with roles, needs it; dyknow starts faster)

    return hashlib.sha256(common_name.encode()).hexdigest()[:HOLDER_SCOPE_DIGITS]


def holder_tokens_of(common_name: str) -> str:
    """The holder tokens of the clients of ``common_name``'s certificate, on every manager: those
    whose client id starts with its :func:`holder_scope` (what the ACL lets it declare)."""
    return f"{DATA_ROOT}/*/*/*/holders/{holder_scope(common_name)}$*"


def event_key(manager: str, kind: str) -> str:
    """Where a manager publishes its events of ``kind``: ``dyknow/<manager>/events/<kind>``."""
    return f"{DATA_ROOT}/{manager}/events/{kind}"


def measurement_key(name: str, manager: str | None = None) -> str:
    """Where a measurement is published: ``dyknow/measurements/<name>`` for every manager, or
    ``dyknow/<manager>/measurements/<name>`` for one."""
    if manager is None:
        return f"{DATA_ROOT}/measurements/{name}"
    return f"{DATA_ROOT}/{manager}/measurements/{name}"


def measurement_patterns(manager: str) -> tuple[str, str]:
    """The key expressions a manager takes measurements from (for every manager, and its own)."""
    return measurement_key("*"), measurement_key("*", manager)


def summary_key(manager: str) -> str:
    """Where a manager publishes its summary (library, units, load): ``@dyknow/<manager>/summary``.

    Under ``@dyknow``, so recording or subscribing to ``dyknow/**`` takes data only.
    """
    return f"{SERVICE_ROOT}/{manager}/summary"


def summaries_pattern() -> str:
    """The key expression of every manager's summary."""
    return summary_key("*")


def manager_token(manager: str) -> str:
    """The liveliness token that says a manager is alive: ``@dyknow/<manager>``."""
    return f"{SERVICE_ROOT}/{manager}"


def managers_pattern() -> str:
    """The key expression of every manager's liveliness token."""
    return manager_token("*")


_GLOB = re.compile(r"[A-Za-z0-9_.*?\[\]!-]+")


def managers_matching(glob: str) -> str:
    """The key expression of the liveliness tokens of the managers whose names match ``glob``
    (``*`` any text, ``?`` one character, ``[...]`` a set, as in a shell): ``robot-*`` asks Zenoh
    for ``@dyknow/robot-$*`` only. ``?`` and sets are matched by the caller (:func:`fnmatch.fnmatchcase`)
    within what the key expression finds. :class:`UnitError` for a glob that cannot match a name."""
    if not _GLOB.fullmatch(glob) or len(glob.encode()) > MAX_NAME_BYTES:
        raise UnitError(
            f"manager pattern {glob[:200]!r} cannot match a manager name",
            expected="letters, digits, '_', '-', '.', and the wildcards '*', '?' and '[...]', like 'robot-*'",
        )
    if "?" in glob or "[" in glob:
        return managers_pattern()  # (Zenoh has no one-character wildcard: filtered after)
    if glob == "*":
        return managers_pattern()
    return manager_token(re.sub(r"\*+", "$*", glob))


def manager_of_token(key: str) -> str | None:
    """The manager a liveliness token names, or None for another key, and for a token whose last
    chunk is no manager name (:func:`check_name`): anyone may declare ``@dyknow/<any text>``, a
    terminal escape say, and no manager has such a name."""
    prefix = f"{SERVICE_ROOT}/"
    rest = key[len(prefix) :] if key.startswith(prefix) else ""
    return rest if _NAME.fullmatch(rest) and len(rest.encode()) <= MAX_NAME_BYTES else None


#: The chunk under which managers announce the tags they offer (see :func:`offer_token`).
OFFERS = "offers"


def _offer_chunk(text: str) -> str:
    return "".join(c if c not in _UNSAFE_IN_CHUNK else "_" for c in text) or "_"


def _offer_args(args: tuple[str, ...]) -> str:
    return "(" + ",".join(_offer_chunk(a) for a in args) + ")"


def offer_token(functor: str, args: tuple[str, ...], manager: str) -> str:
    """The liveliness token by which ``manager`` says it offers streams tagged ``functor(args)``:
    ``@dyknow/offers/<functor>/(<arg>,...)/<manager>``, functor and arguments by their local names
    (unsafe characters as ``_``). An index, not the truth: a planner that finds a manager here
    reads its summary, and plans on what the summary says. The arguments' chunk starts with ``(``,
    which no unit name does, so no offer is ever a service key of a manager named ``offers``."""
    return f"{SERVICE_ROOT}/{OFFERS}/{_offer_chunk(functor)}/{_offer_args(args)}/{manager}"


def offers_pattern(functor: str, args: tuple[str, ...]) -> str:
    """The key expression of every manager's offer of ``functor(args)`` (one Zenoh query finds them)."""
    return offer_token(functor, args, "*")


def clock_token(clock: int, manager: str) -> str:
    """The liveliness token by which ``manager`` says whose clock ``clock`` (a 32-bit id) is:
    ``@dyknow/clocks/<id, 8 hex digits>/<manager>``. A manager that receives data stamped by a
    clock it does not know asks who has it, and estimates that manager's clock (:mod:`dyknow.clocks`)."""
    return f"{SERVICE_ROOT}/clocks/{clock:08x}/{manager}"


#: How recent a goodbye must be to explain a manager's token going (s).
GOODBYE_S = 5.0
#: Why a manager is lost, when it said goodbye (:func:`goodbye_token`) as it stopped.
LOSS_STOPPED = "it stopped (it said goodbye)"
#: Why a manager is lost, when its liveliness token went with no goodbye.
LOSS_VANISHED = "its liveliness token went away without a goodbye: it crashed, or its host was cut off past its lease"


def goodbye_token(manager: str) -> str:
    """The liveliness token a manager declares as it stops, before its others go:
    ``@dyknow/goodbye/<manager>``. Whoever sees it tells a manager that stopped from one that
    crashed or was cut off, without following its summary."""
    return f"{SERVICE_ROOT}/goodbye/{manager}"


def clocks_of(manager: str) -> str:
    """The key expression of ``manager``'s clock token, whatever its clock."""
    return f"{SERVICE_ROOT}/clocks/*/{manager}"


def offers_of(manager: str) -> str:
    """The key expression of every offer ``manager`` may announce: ``@dyknow/offers/*/*/<manager>``."""
    return f"{SERVICE_ROOT}/{OFFERS}/*/*/{manager}"


def manager_of_offer(key: str) -> str | None:
    """The manager an offer token names, or None for another key."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != SERVICE_ROOT or parts[1] != OFFERS or not _NAME.fullmatch(parts[4]):
        return None
    return parts[4]


def port_token(key: str) -> str:
    """The liveliness token an output port bound to ``key`` declares: the key itself."""
    return key


def manager_service_key(manager: str, service: str) -> str:
    """A manager's service: ``@dyknow/<manager>/<service>``."""
    return f"{SERVICE_ROOT}/{manager}/{service}"


def unit_service_key(manager: str, unit: str, service: str) -> str:
    """A unit's proxy service: ``@dyknow/<manager>/unit/<unit>/<service>``."""
    return f"{SERVICE_ROOT}/{manager}/unit/{unit}/{service}"


def services_pattern(manager: str) -> str:
    """The key expression that holds every service of a manager: ``@dyknow/<manager>/**``."""
    return f"{SERVICE_ROOT}/{manager}/**"


@dataclass(frozen=True, slots=True)
class ServiceAddress:
    """A service key taken apart: the ``service`` name and, for a unit's service, the ``unit``."""

    service: str
    unit: str | None = None


def parse_service_key(manager: str, key: str) -> ServiceAddress | None:
    """The service a key under ``@dyknow/<manager>/`` addresses, or None if it has the wrong shape."""
    prefix = f"{SERVICE_ROOT}/{manager}/"
    if not key.startswith(prefix):
        return None
    path = key[len(prefix) :].split("/")
    if len(path) == 1 and path[0]:
        return ServiceAddress(path[0])
    if len(path) == 3 and path[0] == "unit" and path[1] and path[2]:
        return ServiceAddress(path[2], path[1])
    return None
