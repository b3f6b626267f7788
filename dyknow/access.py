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
  watch liveliness and see which managers are up;
- **operator**: also spawn, destroy, set_config, request, release and measure; publish data;
- **admin**: also add and remove transformations, and destroy protected units.

The processes of the system:

- **manager**: another manager of the system. Its certificate's common name must be its manager
  name: it may announce itself, publish its summary and serve services *under that name only*
  (``@dyknow/<name>``, ``@dyknow/<name>/**``), publish data and the liveliness of its ports, and
  call this manager's services as an operator would (its requests span managers). It also carries
  the calls of the clients connected to it;
- **router**: a Zenoh router of the system (``dyknow router``): it carries everyone's traffic, so
  every message may pass its link, and it enforces the same file at its own links.

It becomes the session's Zenoh ``access_control`` configuration (:meth:`AccessControl.zenoh`):
default deny, one subject per role (by certificate common name), one allow rule per role and
message kind, and for each manager one subject and rules of its own name. So the transport
refuses what a link may not carry, before any handler sees it: a refused query gets no reply.
Zenoh judges a message by the link it came by, that is by the neighbour; so a manager with an ACL
also checks every service call's own signature and its caller's role (:mod:`dyknow.identity`,
with :meth:`AccessControl.may_call`): a call keeps its caller's rights through routers and
other managers. Without an ACL everything is allowed (local use).
"""

from __future__ import annotations

import os
import ssl
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import json5
from cryptography.exceptions import InvalidSignature

from dyknow import keys
from dyknow.errors import AccessError, DyKnowError

__all__ = ["PEER_ROLES", "ROLES", "AccessControl", "TlsFiles"]

#: The roles of people and tools, each allowed what the ones before it are.
ROLES: tuple[str, ...] = ("viewer", "operator", "admin")
#: The roles of the system's own processes (see the module documentation).
PEER_ROLES: tuple[str, ...] = ("manager", "router")

_DATA = f"{keys.DATA_ROOT}/**"
_SERVICES = f"{keys.SERVICE_ROOT}/**"
_MANAGERS = keys.managers_pattern()
_SUMMARIES = keys.summaries_pattern()
# The services each role may call, besides those of the roles before it (any manager, any unit).
_SERVICES_OF = {
    "viewer": ["get_model", "get_summary", "get_adaptations", "clock", "unit/*/get_config", "unit/*/get_statistics"],
    "operator": ["spawn", "destroy", "unit/*/set_config", "request", "release", "measure", "monitor"],
    "admin": ["add_transformation", "remove_transformation"],
}
# What a manager may call as itself: what its requests across managers need.
_MANAGER_CALLS = [*_SERVICES_OF["viewer"], *_SERVICES_OF["operator"]]


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

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> AccessControl:
        """Read an ACL file (JSON5); :class:`AccessError` naming the file and the field when malformed."""
        where = os.fspath(path)
        try:
            data = json5.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise AccessError(f"cannot read the ACL file: {exc.strerror or exc}", where=where) from exc
        except ValueError as exc:
            raise AccessError(
                f"not JSON5: {exc}", where=where, expected='{ roles: { viewer: ["CN", ...], operator: [...], admin: [...] } }'
            ) from exc
        return cls.from_dict(data, where)

    @classmethod
    def from_dict(cls, data: Any, where: str = "<acl>") -> AccessControl:
        """The ACL from its parsed form; :class:`AccessError` naming the field when malformed."""
        shape = "{ roles: { viewer: [...], operator: [...], admin: [...], manager: [...], router: [...] } }"
        if not isinstance(data, dict) or set(data) != {"roles"} or not isinstance(data["roles"], dict):
            raise AccessError("the file must hold exactly one field, roles", where=where, expected=shape)
        roles: dict[str, tuple[str, ...]] = {}
        for role, names in data["roles"].items():
            if role not in ROLES + PEER_ROLES:
                raise AccessError(
                    f"unknown role {role!r}", where=f"{where}: roles", expected=f"one of {', '.join(ROLES + PEER_ROLES)}"
                )
            if not isinstance(names, list) or not all(isinstance(n, str) and n.strip() for n in names):
                raise AccessError(f"got {names!r}", where=f"{where}: roles.{role}", expected="a list of certificate common names")
            roles[role] = tuple(n.strip() for n in names)
        for name in roles.get("manager", ()):
            try:
                keys.check_name(name, "manager name")
            except DyKnowError as exc:
                raise AccessError(
                    f"{name!r} cannot be a manager's name", where=f"{where}: roles.manager",
                    expected="the common names of the managers' certificates, each its manager's --name",
                ) from exc  # fmt: skip
        return cls(roles)

    def role_of(self, common_name: str) -> str | None:
        """The role of a certificate's common name: its highest of viewer, operator and admin,
        else manager or router; None when it has none."""
        found = [role for role in ROLES + PEER_ROLES if common_name in self.roles.get(role, ())]
        people = [role for role in found if role in ROLES]
        if people:
            return people[-1]
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
        return wanted in allowed

    def roles_for_call(self, service: str, *, unit: bool = False) -> list[str]:
        """The roles that may call ``service`` (for messages that say who may)."""
        wanted = f"unit/*/{service}" if unit else service
        found = [role for level, role in enumerate(ROLES) if any(wanted in _SERVICES_OF[r] for r in ROLES[: level + 1])]
        return found + (["manager"] if wanted in _MANAGER_CALLS else [])

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
        if self.roles.get("router"):
            rules.extend(_RULES["router"])
            subjects.append({"id": "router", "cert_common_names": list(self.roles["router"])})
            policies.append({"id": "router-policy", "rules": _rules_of("router"), "subjects": ["router"]})
        managers = self.roles.get("manager", ())
        if managers:
            rules.extend(_RULES["manager"])
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
            [_DATA, _MANAGERS, _SUMMARIES],
        ),
        _rule("viewer-receives", "egress", ["put", "delete", "liveliness_token"], [_DATA, _MANAGERS, _SUMMARIES]),
        _rule("viewer-sees-services", "egress", ["declare_queryable", "reply"], [_SERVICES]),
    ],
    "operator": [
        _rule("operator-calls", "ingress", ["query"], _services("operator")),
        _rule("operator-publishes", "ingress", ["put", "delete", "liveliness_token"], [_DATA]),
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
            [_DATA, _MANAGERS, _SUMMARIES],
        ),
        _rule("manager-receives", "egress", _ALL_MESSAGES, _EVERYTHING),
    ],
    # A router carries everyone's messages both ways (it enforces the same roles at its own links).
    "router": [_rule("router-carries", "ingress", _ALL_MESSAGES, _EVERYTHING), _rule("router-delivers", "egress", _ALL_MESSAGES, _EVERYTHING)],
}


def _own_rules(subject: str, manager: str) -> list[dict[str, Any]]:
    """What only the manager named ``manager`` may do: serve, announce and summarise under its name."""
    return [
        _rule(f"{subject}-serves", "ingress", ["declare_queryable", "reply"], [keys.services_pattern(manager)]),
        _rule(f"{subject}-announces", "ingress", ["liveliness_token"], [keys.manager_token(manager)]),
        _rule(f"{subject}-summarises", "ingress", ["put"], [keys.summary_key(manager)]),
    ]


def _rules_of(role: str) -> list[str]:
    return [rule["id"] for rule in _RULES[role]]
