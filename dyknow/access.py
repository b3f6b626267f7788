"""Who may reach a manager: TLS with mutual authentication, and access control by role.

:class:`TlsFiles` names the PEM files of a session: the CA that signs every certificate of the
deployment, and this process's certificate and key. With them, Zenoh's TLS transport requires and
verifies the peer's certificate on every link (mutual TLS); ``dyknow certs`` writes development
ones.

:class:`AccessControl` maps certificate common names to roles, read from a JSON5 file
(``dyknow manager --acl FILE``, and ``dyknow router --acl FILE``)::

    { roles: { viewer: ["dashboard"], operator: ["robot-ui"], admin: ["alice"],
               manager: ["robot", "station"], router: ["hub"] } }

People and tools (each role may what the ones before it may):

- **viewer**: read the model, configs, statistics, adaptations and summaries; subscribe to data,
  watch liveliness and see which managers are up; see the ROS 2 graph and read other ROS 2
  nodes' lifecycle state, parameters and mode (below);
- **operator**: also spawn, destroy, set_config, request, release and measure; publish data;
  manage other ROS 2 nodes (the right ``manage``, below);
- **admin**: also add and remove transformations, and destroy protected units.

The processes of the system:

- **manager**: another manager of the system. Its certificate's common name must be its manager
  name: it may announce itself, publish its summary and serve services *under that name only*
  (``@dyknow/<name>``, ``@dyknow/<name>/**``), publish data and the liveliness of its ports, and
  call this manager's services as an operator would (its requests span managers). It also carries
  the calls of the clients connected to it;
- **router**: a Zenoh router of the system (``dyknow router``): it carries everyone's traffic, so
  every message may pass its link, and it enforces the same file at its own links. The robot's
  ROS 2 side (rmw_zenoh's router, ``rmw_zenohd``, run with TLS and a certificate of the CA) links
  under this role too: it carries the nodes' topics, services and graph.

**Other ROS 2 nodes: the right** ``manage``. Calling the lifecycle, parameter and mode services of
nodes dyknow did not spawn (over rmw_zenoh: queries on ``<domain>/<node>/<service>/<type>/<hash>``,
:mod:`dyknow.ros2.names`) is governed by the service's last name, whatever the node and the type:

- :data:`ROS2_READ_SERVICES` (``get_state``, ``get_parameters``, ``list_parameters``,
  ``get_mode``, ...): every role may call them (a viewer, and a role of the file's own that is
  ``like`` one or has ``manage``), and see the graph (``@ros2_lv/**``) to find them, declaring
  its own node's and clients' tokens only;
- :data:`ROS2_MANAGE_SERVICES` (``change_state``, ``set_parameters``,
  ``set_parameters_atomically``, ``change_mode``, as a node and the ``system_modes`` mode
  manager serve them): only with the right :data:`MANAGE`, which operators, admins, managers and
  a role of the file's own whose ``calls`` name ``manage`` (or that is ``like`` an operator)
  have (:meth:`AccessControl.may_manage`);
- anything else of ROS 2 (topics, other services, serving) is carried by no role but a router.

The transport enforces it at the first link a query crosses (rmw_zenoh's calls carry no dyknow
signature, as data does not: give every manager and router the same file). A manager also refuses
a managed node's unit (a spec's ``<node>``) to a caller without ``manage``, as it refuses spawn to a
viewer. Over DDS (``ros2dds:``, ``--dds``) there is no Zenoh link to judge: dyknow's roles do
not govern it.

Roles of the file's own, for what these do not fit: ``define`` gives each the built-in role it
starts from (``like``, optional) and besides it the services it may call (``calls``, names of
:data:`SERVICES`, or the right :data:`MANAGE`) and the key expressions under ``dyknow/`` it may
``publish`` and ``subscribe`` to; a mistake is located (``FILE:LINE: define.ROLE.calls[1]:
unknown service ...``)::

    { roles: { requester: ["robot-ui"], tuner: ["field-laptop"] },
      define: { requester: { like: "viewer", calls: ["request", "release"] },
                tuner: { like: "viewer", calls: ["manage"] } } }

It becomes the session's Zenoh ``access_control`` configuration (:meth:`AccessControl.zenoh`):
default deny, one subject per role (by certificate common name), one allow rule per role and
message kind, for each manager one subject and rules of its own name, and for each name that may
``request`` or ``monitor`` one subject that lets it declare the holder tokens of its own clients
only (:mod:`dyknow.holders`; no other role but managers and routers, which carry them, may
declare holder tokens, unless a role of the file's own ``publish``-es on their keys). So the transport
refuses what a link may not carry, before any handler sees it: a refused query gets no reply.
Zenoh judges a message by the link it came by, that is by the neighbour; so a manager with an ACL
also checks every service call's own signature and its caller's role (:mod:`dyknow.identity`,
with :meth:`AccessControl.may_call`): a call keeps its caller's rights through routers and
other managers. Without an ACL everything is allowed (local use).
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dyknow import keys
from dyknow.errors import AccessError, DyKnowError, did_you_mean

__all__ = [
    "MANAGE",
    "PEER_ROLES",
    "ROLES",
    "ROS2_MANAGE_SERVICES",
    "ROS2_READ_SERVICES",
    "SERVICES",
    "AccessControl",
    "RoleDefinition",
    "TlsFiles",
    "ros2_right",
]

#: The roles of people and tools, each allowed what the ones before it are.
ROLES: tuple[str, ...] = ("viewer", "operator", "admin")
#: The roles of the system's own processes (see the module documentation).
PEER_ROLES: tuple[str, ...] = ("manager", "router")

_DATA = f"{keys.DATA_ROOT}/**"
_SERVICES = f"{keys.SERVICE_ROOT}/**"
_MANAGERS = keys.managers_pattern()
_SUMMARIES = keys.summaries_pattern()
_OFFERS = f"{keys.SERVICE_ROOT}/{keys.OFFERS}/**"  # (dyknow.keys.offer_token: what the managers offer)
_CLOCKS = keys.clocks_of("*")  # (dyknow.keys.clock_token: whose clock an id is)
_GOODBYES = keys.goodbye_token("*")
_HOLDERS = keys.holders_pattern()  # (dyknow.holders: <request or monitor key>/holders/<client>)
# The services each role may call, besides those of the roles before it (any manager, any unit).
_SERVICES_OF = {
    "viewer": ["get_model", "get_summary", "get_metrics", "get_adaptations", "get_load", "clock", "unit/*/get_config", "unit/*/get_statistics"],
    "operator": ["spawn", "destroy", "unit/*/set_config", "request", "release", "measure", "monitor"],
    "admin": ["add_transformation", "remove_transformation"],
}
# What a manager may call as itself: what its requests across managers need.
_MANAGER_CALLS = [*_SERVICES_OF["viewer"], *_SERVICES_OF["operator"]]
#: Every service a role may be given (``calls`` of a defined role), as the ACL file names them:
#: a unit's services by their own name (``get_config`` is ``unit/*/get_config``).
SERVICES: tuple[str, ...] = tuple(sorted(s.removeprefix("unit/*/") for r in ROLES for s in _SERVICES_OF[r]))
_UNIT_SERVICES = frozenset(s.removeprefix("unit/*/") for r in ROLES for s in _SERVICES_OF[r] if s.startswith("unit/*/"))
_DEFINE_FIELDS = ("like", "calls", "publish", "subscribe")

#: The right to manage other ROS 2 nodes (``calls`` of a defined role may name it beside the
#: services): to call their :data:`ROS2_MANAGE_SERVICES`, and to spawn a managed node's unit.
MANAGE = "manage"
#: The ROS 2 services every role may call (by the last part of the service's name, whatever the
#: node and the type): they read a node's lifecycle state, parameters and mode.
ROS2_READ_SERVICES: tuple[str, ...] = (
    "get_state", "get_available_states", "get_available_transitions", "get_transition_graph",  # lifecycle_msgs
    "get_parameters", "get_parameter_types", "list_parameters", "describe_parameters",  # rcl_interfaces
    "get_mode", "get_available_modes",  # system_modes
    "get_type_description",  # type_description_interfaces
)  # fmt: skip
#: The ROS 2 services that need the right :data:`MANAGE`: they change a node's lifecycle state,
#: parameters or mode.
ROS2_MANAGE_SERVICES: tuple[str, ...] = ("change_state", "set_parameters", "set_parameters_atomically", "change_mode")
# The roles of people that may manage nodes, besides the roles of the file's own that call manage.
_MANAGERS_OF_NODES = ("operator", "admin")


@dataclass(frozen=True, slots=True)
class RoleDefinition:
    """A role the ACL file defines (``define: { NAME: {...} }``): what a built-in role may
    (``like``, or nothing) and besides it the services it may ``calls`` and the key expressions
    under ``dyknow/`` it may ``publish`` and ``subscribe`` to."""

    name: str
    like: str | None = None
    calls: tuple[str, ...] = ()
    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()

    @property
    def manages(self) -> bool:
        """Whether it may manage ROS 2 nodes (:data:`MANAGE`): it calls ``manage``, or is ``like`` an operator or admin."""
        return MANAGE in self.calls or self.like in _MANAGERS_OF_NODES

    def services(self) -> set[str]:
        """The services it may call, as :data:`_SERVICES_OF` names them (``unit/*/...``)."""
        found = {f"unit/*/{c}" if c in _UNIT_SERVICES else c for c in self.calls if c != MANAGE}
        if self.like is not None:
            found.update(s for r in ROLES[: ROLES.index(self.like) + 1] for s in _SERVICES_OF[r])
        return found


@dataclass(frozen=True, slots=True)
class TlsFiles:
    """The PEM files of a TLS session: the CA's certificate, this process's certificate and key."""

    ca: str
    cert: str
    key: str

    def check(self) -> TlsFiles:
        """This, once the files are known to work together; else :class:`AccessError` naming the
        file: one that is not readable, a CA file without a certificate, a certificate or key that
        does not load, a key that is not the certificate's, a certificate its CA did not sign
        (every peer would refuse it)."""
        for option, path in (("--tls-ca", self.ca), ("--tls-cert", self.cert), ("--tls-key", self.key)):
            if not os.path.isfile(path) or not os.access(path, os.R_OK):
                raise AccessError(
                    f"{path!r} is not a readable file", where=option, expected="a PEM file (dyknow certs DIR writes development ones)"
                )
        import ssl  # (here, json5 and cryptography where they are used: a command without TLS or an ACL starts faster)

        context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        try:
            context.load_verify_locations(self.ca)
        except (ssl.SSLError, ValueError) as exc:
            raise AccessError(
                f"{self.ca} holds no CA certificate ({exc})", where="--tls-ca", expected="the PEM certificate of the CA"
            ) from exc
        try:
            context.load_cert_chain(self.cert, self.key)
        except ssl.SSLError as exc:
            if "KEY_VALUES_MISMATCH" in str(exc):
                raise AccessError(
                    f"the key in {self.key} is not the key of the certificate {self.cert}",
                    where="--tls-key",
                    expected="the private key the certificate was issued for (NAME.key beside NAME.pem)",
                ) from exc
            raise AccessError(
                f"{self.cert} and {self.key} do not load as a certificate and its key ({exc})",
                where="--tls-cert/--tls-key",
                expected="a PEM certificate and its unencrypted PEM private key",
            ) from exc
        if not _issued_by(Path(self.cert).read_bytes(), Path(self.ca).read_bytes()):
            raise AccessError(
                f"the certificate {self.cert} is not signed by the CA of {self.ca}: every peer that trusts that CA would refuse it",
                where="--tls-cert",
                expected="a certificate issued by the CA of --tls-ca (dyknow certs DIR writes both in DIR), or the CA file that issued it",
            )
        return self

    @classmethod
    def from_options(cls, ca: str | None, cert: str | None, key: str | None) -> TlsFiles | None:
        """The files given on a command line: all three, or none (None: no TLS)."""
        given = {"--tls-ca": ca, "--tls-cert": cert, "--tls-key": key}
        if not any(given.values()):
            return None
        missing = [name for name, value in given.items() if not value]
        if missing:
            raise AccessError(f"{', '.join(missing)} missing", where="TLS options", expected="--tls-ca, --tls-cert and --tls-key together")
        return cls(str(ca), str(cert), str(key)).check()


def _issued_by(cert_pem: bytes, ca_pem: bytes) -> bool:
    """Whether a certificate of the file ``cert_pem`` (the leaf, or a chain's intermediate) is a CA
    of ``ca_pem`` or was signed by one."""
    from cryptography import x509
    from cryptography.exceptions import InvalidSignature

    try:
        chain, cas = x509.load_pem_x509_certificates(cert_pem), x509.load_pem_x509_certificates(ca_pem)
    except ValueError:
        return True  # (ssl loaded them: a form this check does not read; the handshake judges)
    for cert in chain:
        for ca in cas:
            if cert == ca:
                return True
            try:
                cert.verify_directly_issued_by(ca)
                return True
            except (ValueError, TypeError, InvalidSignature):
                continue
    return False


@dataclass(frozen=True, slots=True)
class AccessControl:
    """Certificate common names by role (see the module documentation)."""

    roles: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    #: The roles the file defines, by name (see :class:`RoleDefinition`).
    defined: Mapping[str, RoleDefinition] = field(default_factory=dict)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> AccessControl:
        """Read an ACL file (JSON5); :class:`AccessError` naming the file and the field when malformed."""
        import json5

        where = os.fspath(path)
        try:
            data = json5.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise AccessError(f"cannot read the ACL file: {exc.strerror or exc}", where=where) from exc
        except ValueError as exc:
            # (the json5 reader names no file: "<string>:LINE what"; the file's own name instead)
            found = re.match(r"<string>:(\d+) (.*)", str(exc), re.DOTALL)
            raise AccessError(
                f"not JSON5: {found.group(2) if found else exc}",
                where=f"{where}:{found.group(1)}" if found else where,
                expected='{ roles: { viewer: ["CN", ...], operator: [...], admin: [...] } }',
            ) from exc
        return cls.from_dict(data, where, text=Path(path).read_text(encoding="utf-8"))

    @classmethod
    def from_dict(cls, data: Any, where: str = "<acl>", *, text: str | None = None) -> AccessControl:
        """The ACL from its parsed form; :class:`AccessError` naming the field when malformed
        (``FILE:LINE: field`` when the file's ``text`` is given)."""
        shape = "{ roles: { viewer: [...], operator: [...], admin: [...], manager: [...], router: [...], ROLE: [...] }, define: { ROLE: {...} } }"
        if not isinstance(data, dict) or "roles" not in data or not set(data) <= {"roles", "define"} or not isinstance(data["roles"], dict):
            raise AccessError(
                "the file must hold the field roles (and, to define roles, define), nothing else", where=where, expected=shape
            )
        defined = _definitions(data.get("define", {}), where, text)
        roles: dict[str, tuple[str, ...]] = {}
        for role, names in data["roles"].items():
            if role not in ROLES + PEER_ROLES and role not in defined:
                known = [*ROLES, *PEER_ROLES, *defined]
                raise AccessError(
                    f"unknown role {role!r}",
                    where=_at(where, text, f"roles.{role}", role),
                    expected=f"one of {', '.join(known)}, or a role of define{did_you_mean(role, known)}",
                )
            if not isinstance(names, list) or not all(isinstance(n, str) and n.strip() for n in names):
                raise AccessError(
                    f"got {names!r}", where=_at(where, text, f"roles.{role}", role), expected="a list of certificate common names"
                )
            roles[role] = tuple(n.strip() for n in names)
        for name in roles.get("manager", ()):
            try:
                keys.check_name(name, "manager name")
            except DyKnowError as exc:
                raise AccessError(
                    f"{name!r} cannot be a manager's name", where=f"{where}: roles.manager",
                    expected="the common names of the managers' certificates, each its manager's --name",
                ) from exc  # fmt: skip
        return cls(roles, defined)

    def role_of(self, common_name: str) -> str | None:
        """The role of a certificate's common name: its highest of viewer, operator and admin,
        else manager or router; None when it has none."""
        found = [role for role in ROLES + PEER_ROLES if common_name in self.roles.get(role, ())]
        people = [role for role in found if role in ROLES]
        if people:
            return people[-1]
        own = [role for role in self.defined if common_name in self.roles.get(role, ())]
        if own:
            return own[0]
        return found[0] if found else None

    def may_call(self, common_name: str, service: str, *, unit: bool = False) -> bool:
        """Whether the holder of ``common_name`` may call ``service`` (a unit's service when
        ``unit``) on this manager, whichever link the call came by."""
        wanted = f"unit/*/{service}" if unit else service
        allowed: set[str] = set()
        for level, role in enumerate(ROLES):
            if common_name in self.roles.get(role, ()):
                allowed.update(s for r in ROLES[: level + 1] for s in _SERVICES_OF[r])
        if common_name in self.roles.get("manager", ()):
            allowed.update(_MANAGER_CALLS)
        for role, definition in self.defined.items():
            if common_name in self.roles.get(role, ()):
                allowed.update(definition.services())
        return wanted in allowed

    def may_manage(self, common_name: str) -> bool:
        """Whether the holder of ``common_name`` has the right :data:`MANAGE` here: to call other
        ROS 2 nodes' :data:`ROS2_MANAGE_SERVICES` and to spawn a managed node's unit (an
        operator, an admin, a manager, or a role of the file's own that calls ``manage`` or is
        ``like`` an operator or admin)."""
        if any(common_name in self.roles.get(role, ()) for role in (*_MANAGERS_OF_NODES, "manager")):
            return True
        return any(common_name in self.roles.get(role, ()) and definition.manages for role, definition in self.defined.items())

    def roles_for_manage(self) -> list[str]:
        """The roles that have the right :data:`MANAGE` (for messages that say who may)."""
        return [*_MANAGERS_OF_NODES, *(role for role, definition in self.defined.items() if definition.manages), "manager"]

    def may_read(self, common_name: str, key: str) -> bool:
        """Whether the holder of ``common_name`` may subscribe to the data on ``key`` (a concrete
        key under ``dyknow/``): the built-in roles, managers and routers may read all data; a
        role of the file's own what its ``like`` may and the key expressions it may
        ``subscribe`` to. A monitor or a requirement reads only what its caller may read."""
        if any(common_name in self.roles.get(role, ()) for role in (*ROLES, *PEER_ROLES)):
            return keys.includes(_DATA, key)
        for role, definition in self.defined.items():
            if common_name not in self.roles.get(role, ()):
                continue
            if definition.like is not None and keys.includes(_DATA, key):
                return True
            if any(keys.includes(expr, key) for expr in definition.subscribe):
                return True
        return False

    def roles_for_read(self, key: str) -> list[str]:
        """The roles that may read the data on ``key`` (for messages that say who may)."""
        found = [*ROLES, *PEER_ROLES] if keys.includes(_DATA, key) else []
        found += [
            role
            for role, definition in self.defined.items()
            if (definition.like is not None and keys.includes(_DATA, key)) or any(keys.includes(e, key) for e in definition.subscribe)
        ]
        return found

    def roles_for_call(self, service: str, *, unit: bool = False) -> list[str]:
        """The roles that may call ``service`` (for messages that say who may)."""
        wanted = f"unit/*/{service}" if unit else service
        found = [role for level, role in enumerate(ROLES) if any(wanted in _SERVICES_OF[r] for r in ROLES[: level + 1])]
        found += [role for role, definition in self.defined.items() if wanted in definition.services()]
        return found + (["manager"] if wanted in _MANAGER_CALLS else [])

    def _holding_names(self) -> list[str]:
        """The common names that may take references a client holds (may call ``request`` or
        ``monitor``), sorted: each gets its own holder tokens (:mod:`dyknow.holders`)."""
        named = {name for names in self.roles.values() for name in names}
        return sorted(name for name in named if self.may_call(name, "request") or self.may_call(name, "monitor"))

    def zenoh(self) -> dict[str, Any]:
        """The Zenoh ``access_control`` configuration that enforces these roles at every link."""
        rules: list[dict[str, Any]] = []
        subjects: list[dict[str, Any]] = []
        policies: list[dict[str, Any]] = []
        for level, role in enumerate(ROLES):
            names = self.roles.get(role, ())
            if not names:
                continue
            subjects.append({"id": role, "cert_common_names": list(names)})
            granted = [name for r in ROLES[: level + 1] for name in _rules_of(r)]
            policies.append({"id": f"{role}-policy", "rules": granted, "subjects": [role]})
        for role in ROLES:
            rules.extend(_RULES[role])
        rules.extend(rule for role in ROLES for rule in _ros2_rules().get(role, []))
        if self.roles.get("router"):
            rules.extend(_RULES["router"])
            rules.extend(_ros2_rules()["router"])
            subjects.append({"id": "router", "cert_common_names": list(self.roles["router"])})
            policies.append({"id": "router-policy", "rules": _rules_of("router"), "subjects": ["router"]})
        for i, (role, definition) in enumerate(self.defined.items()):
            names = self.roles.get(role, ())
            if not names:
                continue
            subject = f"defined-{i}"  # (the file's names are not Zenoh ids)
            own = _defined_rules(subject, definition)
            rules.extend(own)
            subjects.append({"id": subject, "cert_common_names": list(names)})
            base = [name for r in ROLES[: ROLES.index(definition.like) + 1] for name in _rules_of(r)] if definition.like else []
            if definition.manages:  # (the viewer's sight of the ROS 2 graph, and the operator's calls)
                base += [r["id"] for role in ("viewer", "operator") for r in _ros2_rules()[role] if r["id"] not in base]
            policies.append({"id": f"{subject}-policy", "rules": [*base, *(r["id"] for r in own)], "subjects": [subject]})
        for i, name in enumerate(self._holding_names()):
            # what it requests, it holds: its client's liveliness token says it is still there,
            # and it may declare the tokens of its own clients only (dyknow.holders)
            subject = f"holder-{i}"
            rules.append(_rule(f"{subject}-holds", "ingress", ["liveliness_token"], [keys.holder_tokens_of(name)]))
            subjects.append({"id": subject, "cert_common_names": [name]})
            policies.append({"id": f"{subject}-policy", "rules": [f"{subject}-holds"], "subjects": [subject]})
        managers = self.roles.get("manager", ())
        if managers:
            rules.extend(_RULES["manager"])
            rules.extend(_ros2_rules()["manager"])
        for i, name in enumerate(managers):
            # each manager its own subject: it serves and announces under its own name only
            subject = f"manager-{i}"
            own = _own_rules(subject, name)
            rules.extend(own)
            subjects.append({"id": subject, "cert_common_names": [name]})
            policies.append({"id": f"{subject}-policy", "rules": [*_rules_of("manager"), *(r["id"] for r in own)], "subjects": [subject]})
        return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


# Every data key of 2 to 5 chunks or of 7 and more: all but the 6 of a holder token
# (dyknow/<manager>/<kind>/<name>/holders/<client>). Zenoh's deny rules win over any subject's
# allow (eclipse-zenoh 1.10), so holder tokens are left out of the allow rules instead.
_TOKENS_BUT_HOLDERS = [f"{keys.DATA_ROOT}{'/*' * n}" for n in range(1, 5)] + [f"{keys.DATA_ROOT}{'/*' * 6}/**"]


def _services(role: str) -> list[str]:
    return [f"{keys.SERVICE_ROOT}/*/{service}" for service in _SERVICES_OF[role]]


# Every key dyknow uses: '**' does not reach verbatim chunks such as @dyknow, so they are named too.
_EVERYTHING = ["**", _SERVICES]
_ALL_MESSAGES = [
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
]  # fmt: skip

_RULES: dict[str, list[dict[str, Any]]] = {
    "viewer": [
        _rule("viewer-calls", "ingress", ["query"], _services("viewer")),
        _rule(
            "viewer-subscribes",
            "ingress",
            ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            [_DATA, _MANAGERS, _SUMMARIES, _OFFERS, _CLOCKS, _GOODBYES],
        ),
        _rule("viewer-receives", "egress", ["put", "delete", "liveliness_token"], [_DATA, _MANAGERS, _SUMMARIES, _OFFERS, _CLOCKS, _GOODBYES]),
        _rule("viewer-sees-services", "egress", ["declare_queryable", "reply"], [_SERVICES]),
    ],
    "operator": [
        _rule("operator-calls", "ingress", ["query"], _services("operator")),
        _rule("operator-publishes", "ingress", ["put", "delete"], [_DATA]),
        # a client's holder token is its certificate's own (dyknow.holders): liveliness tokens on
        # every data key but holder tokens (a subject per name allows those of its own clients)
        _rule("operator-declares", "ingress", ["liveliness_token"], _TOKENS_BUT_HOLDERS),
        _rule("operator-reaches-subscribers", "egress", ["declare_subscriber", "declare_liveliness_subscriber"], [_DATA]),
    ],
    "admin": [_rule("admin-calls", "ingress", ["query"], _services("admin"))],
    # Another manager: it calls services (its own calls, and those of its clients, each signed
    # by its caller and checked by the manager called), publishes data and its ports'
    # liveliness, watches the others; this manager sends it everything. What it may serve and
    # announce is in its own rules (_own_rules), under its own name.
    "manager": [
        _rule("manager-calls", "ingress", ["query"], [_SERVICES]),
        _rule("manager-publishes", "ingress", ["put", "delete", "liveliness_token"], [_DATA]),
        _rule(
            "manager-subscribes",
            "ingress",
            ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            [_DATA, _MANAGERS, _SUMMARIES, _OFFERS, _CLOCKS, _GOODBYES],
        ),
        _rule("manager-receives", "egress", _ALL_MESSAGES, _EVERYTHING),
    ],
    # A router carries everyone's messages both ways (it enforces the same roles at its own links).
    "router": [
        _rule("router-carries", "ingress", _ALL_MESSAGES, _EVERYTHING),
        _rule("router-delivers", "egress", _ALL_MESSAGES, _EVERYTHING),
    ],
}


def _own_rules(subject: str, manager: str) -> list[dict[str, Any]]:
    """What only the manager named ``manager`` may do: serve, announce and summarise under its name."""
    return [
        _rule(f"{subject}-serves", "ingress", ["declare_queryable", "reply"], [keys.services_pattern(manager)]),
        # (and answers for its name and its offers: the indexes of a manager that is there, dyknow.federation)
        _rule(f"{subject}-answers-for-itself", "ingress", ["declare_queryable", "reply"], [keys.manager_token(manager), keys.offers_of(manager)]),
        _rule(f"{subject}-announces", "ingress", ["liveliness_token"], [keys.manager_token(manager), keys.offers_of(manager), keys.clocks_of(manager), keys.goodbye_token(manager)]),
        _rule(f"{subject}-summarises", "ingress", ["put"], [keys.summary_key(manager)]),
    ]


def _rules_of(role: str) -> list[str]:
    return [rule["id"] for rule in (*_RULES[role], *_ros2_rules().get(role, []))]


@functools.cache
def _ros2_rules() -> dict[str, list[dict[str, Any]]]:
    """The rules over other ROS 2 nodes on rmw_zenoh (their keys are outside dyknow's, laid out by
    :mod:`dyknow.ros2.names`): a viewer sees the graph, declares its own node's and clients'
    tokens and calls the read services; an operator also the manage services; a manager what an
    operator may. Everything else of ROS 2 (topics, other services, servers) is left to the
    default deny: a role carries it only as a router."""
    # (imported here: importing dyknow.ros2 imports the transport, which imports this module)
    from dyknow.ros2.names import EntityKind, every_service, every_token

    reads = [every_service(s) for s in ROS2_READ_SERVICES]
    manages = [every_service(s) for s in ROS2_MANAGE_SERVICES]
    graph = [every_token()]
    own = [every_token(EntityKind.NODE), every_token(EntityKind.CLIENT)]

    def sees(prefix: str) -> list[dict[str, Any]]:
        return [
            _rule(f"{prefix}-sees-ros2-graph", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], graph),
            _rule(f"{prefix}-receives-ros2-graph", "egress", ["liveliness_token"], graph),
            _rule(f"{prefix}-joins-ros2-graph", "ingress", ["liveliness_token"], own),
            _rule(f"{prefix}-reads-ros2-nodes", "ingress", ["query"], reads),
            _rule(f"{prefix}-hears-ros2-nodes", "egress", ["declare_queryable", "reply"], reads + manages),
        ]

    return {
        "viewer": sees("viewer"),
        "operator": [_rule("operator-manages-ros2-nodes", "ingress", ["query"], manages)],
        "manager": [*sees("manager"), _rule("manager-manages-ros2-nodes", "ingress", ["query"], manages)],
        # ('**' does not reach the verbatim @ros2_lv: a router carries the graph by name)
        "router": [_rule("router-carries-ros2-graph", "ingress", _ALL_MESSAGES, graph), _rule("router-delivers-ros2-graph", "egress", _ALL_MESSAGES, graph)],
    }


def ros2_right(service: str) -> str | None:
    """The right a call of the ROS 2 service ``service`` (``/camera_top/change_state``) needs on a
    link with roles: :data:`MANAGE` for one of :data:`ROS2_MANAGE_SERVICES`, ``"viewer"`` (any
    role) for one of :data:`ROS2_READ_SERVICES`; None for any other service, which no role but a
    router's carries."""
    last = service.rstrip("/").rsplit("/", 1)[-1]
    if last in ROS2_MANAGE_SERVICES:
        return MANAGE
    return "viewer" if last in ROS2_READ_SERVICES else None


def _defined_rules(subject: str, role: RoleDefinition) -> list[dict[str, Any]]:
    """The Zenoh rules of a defined role, besides those of the built-in role it is ``like``."""
    rules = []
    own_calls = sorted(
        role.services() - {s for r in ROLES[: ROLES.index(role.like) + 1] for s in _SERVICES_OF[r]} if role.like else role.services()
    )
    if own_calls:
        rules.append(_rule(f"{subject}-calls", "ingress", ["query"], [f"{keys.SERVICE_ROOT}/*/{c}" for c in own_calls]))
        rules.append(_rule(f"{subject}-sees-services", "egress", ["declare_queryable", "reply"], [_SERVICES]))
    if role.subscribe:
        rules.append(_rule(f"{subject}-subscribes", "ingress", ["declare_subscriber"], list(role.subscribe)))
        rules.append(_rule(f"{subject}-receives", "egress", ["put", "delete"], list(role.subscribe)))
    if role.publish:
        rules.append(_rule(f"{subject}-publishes", "ingress", ["put", "delete", "liveliness_token"], list(role.publish)))
        rules.append(_rule(f"{subject}-reaches-subscribers", "egress", ["declare_subscriber"], list(role.publish)))
    return rules


def _at(where: str, text: str | None, field_path: str, needle: str, after: str | None = None) -> str:
    """``FILE:LINE: field`` for a value of the file (the first line holding ``needle``, after the
    first holding ``after``), or ``FILE: field`` when the line cannot be told."""
    if text is None:
        return f"{where}: {field_path}"
    lines = text.splitlines()
    start = 0
    if after is not None:
        start = next((i for i, line in enumerate(lines) if after in line), 0)
    line = next((i for i in range(start, len(lines)) if needle in lines[i]), None)
    return f"{where}:{line + 1}: {field_path}" if line is not None else f"{where}: {field_path}"


def _definitions(raw: Any, where: str, text: str | None) -> dict[str, RoleDefinition]:
    """The ``define`` field: role name -> definition, each checked (located errors)."""
    shape = '{ define: { requester: { like: "viewer", calls: ["request", "release"], publish: [], subscribe: [] } } }'
    if not isinstance(raw, dict):
        raise AccessError(f"got {raw!r}", where=_at(where, text, "define", "define"), expected=shape)
    defined: dict[str, RoleDefinition] = {}
    for name, spec in raw.items():
        at = _at(where, text, f"define.{name}", str(name), "define")
        if name in ROLES + PEER_ROLES:
            raise AccessError(
                f"{name!r} is a built-in role",
                where=at,
                expected="another name: the built-in roles stay as they are (use like: to start from one)",
            )
        try:
            keys.check_name(str(name), "role name")
        except DyKnowError as exc:
            raise AccessError(f"{name!r} cannot be a role's name", where=at, expected="letters, digits, '_', '-' and '.'") from exc
        if not isinstance(spec, dict) or not set(spec) <= set(_DEFINE_FIELDS):
            unknown = sorted(set(spec) - set(_DEFINE_FIELDS)) if isinstance(spec, dict) else []
            raise AccessError(
                f"unknown field {unknown[0]!r}{did_you_mean(unknown[0], _DEFINE_FIELDS)}" if unknown else f"got {spec!r}",
                where=_at(where, text, f"define.{name}", unknown[0] if unknown else str(name), "define"),
                expected=f"an object of {', '.join(_DEFINE_FIELDS)}",
            )
        like = spec.get("like")
        if like is not None and like not in ROLES:
            raise AccessError(
                f"like {like!r}", where=_at(where, text, f"define.{name}.like", f"{like}", str(name)),
                expected=f"one of the built-in roles {', '.join(ROLES)}{did_you_mean(str(like), ROLES)}",
            )  # fmt: skip
        lists: dict[str, tuple[str, ...]] = {}
        for kind in ("calls", "publish", "subscribe"):
            values = spec.get(kind, [])
            if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
                raise AccessError(
                    f"got {values!r}", where=_at(where, text, f"define.{name}.{kind}", kind, str(name)), expected="a list of strings"
                )
            for i, value in enumerate(values):
                problem = _check_call(value) if kind == "calls" else _check_key_expr(value)
                if problem is not None:
                    raise AccessError(
                        problem[0], where=_at(where, text, f"define.{name}.{kind}[{i}]", f"{value}", str(name)), expected=problem[1]
                    )
            lists[kind] = tuple(values)
        defined[str(name)] = RoleDefinition(str(name), like, lists["calls"], lists["publish"], lists["subscribe"])
    return defined


def _check_call(service: str) -> tuple[str, str] | None:
    if service in SERVICES or service == MANAGE:
        return None
    known = [*SERVICES, MANAGE]
    return (
        f"unknown service {service!r}",
        f"one of {', '.join(SERVICES)}, or {MANAGE} (the right to manage ROS 2 nodes){did_you_mean(service, known)}",
    )


def _check_key_expr(key_expr: str) -> tuple[str, str] | None:
    chunks = key_expr.split("/")
    if chunks[0] != keys.DATA_ROOT or len(chunks) < 2 or any(not c or c.startswith("@") or any(ch in c for ch in "?#$") for c in chunks):
        return (
            f"{key_expr!r} is not a key expression under {keys.DATA_ROOT}/",
            f"chunks under {keys.DATA_ROOT}/, such as dyknow/robot/** or dyknow/*/requests/**",
        )
    return None
