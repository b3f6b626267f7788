"""Who may reach a manager: TLS with mutual authentication, and access control by role.

:class:`TlsFiles` names the PEM files of a session: the CA that signs every certificate of the
deployment, and this process's certificate and key. With them, Zenoh's TLS transport requires and
verifies the peer's certificate on every link (mutual TLS); ``dyknow certs`` writes development
ones.

:class:`AccessControl` maps certificate common names to three roles, read from a JSON5 file
(``dyknow manager --acl FILE``)::

    { roles: { viewer: ["dashboard"], operator: ["robot-ui"], admin: ["alice"] } }

- **viewer**: read the model, configs, statistics, adaptations and summaries; subscribe to data,
  watch liveliness and see which managers are up;
- **operator**: also spawn, destroy, set_config, request, release and measure; publish data;
  announce itself as a manager, publish its summary and serve its services to this one (give the
  other managers of a system this role);
- **admin**: also add and remove transformations.

It becomes the session's Zenoh ``access_control`` configuration (:meth:`AccessControl.zenoh`):
default deny, one subject per role (by certificate common name), one allow rule per role and
message kind. So the transport refuses what a role may not do, before any handler sees it: a
refused query gets no reply. Without an ACL everything is allowed (local use).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import json5

from dyknow import keys
from dyknow.errors import AccessError

__all__ = ["ROLES", "AccessControl", "TlsFiles"]

#: The roles, each allowed what the ones before it are.
ROLES: tuple[str, ...] = ("viewer", "operator", "admin")

_DATA = f"{keys.DATA_ROOT}/**"
_SERVICES = f"{keys.SERVICE_ROOT}/**"
_MANAGERS = keys.managers_pattern()
_SUMMARIES = keys.summaries_pattern()
# The services each role may call, besides those of the roles before it (any manager, any unit).
_SERVICES_OF = {
    "viewer": ["get_model", "get_summary", "get_adaptations", "unit/*/get_config", "unit/*/get_statistics"],
    "operator": ["spawn", "destroy", "unit/*/set_config", "request", "release", "measure"],
    "admin": ["add_transformation", "remove_transformation"],
}


@dataclass(frozen=True, slots=True)
class TlsFiles:
    """The PEM files of a TLS session: the CA's certificate, this process's certificate and key."""

    ca: str
    cert: str
    key: str

    def check(self) -> TlsFiles:
        """This, once every file is known to be readable; :class:`AccessError` naming the one that is not."""
        for option, path in (("--tls-ca", self.ca), ("--tls-cert", self.cert), ("--tls-key", self.key)):
            if not os.path.isfile(path) or not os.access(path, os.R_OK):
                raise AccessError(
                    f"{path!r} is not a readable file", where=option, expected="a PEM file (dyknow certs DIR writes development ones)"
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
        if not isinstance(data, dict) or set(data) != {"roles"} or not isinstance(data["roles"], dict):
            raise AccessError(
                "the file must hold exactly one field, roles",
                where=where,
                expected="{ roles: { viewer: [...], operator: [...], admin: [...] } }",
            )
        roles: dict[str, tuple[str, ...]] = {}
        for role, names in data["roles"].items():
            if role not in ROLES:
                raise AccessError(f"unknown role {role!r}", where=f"{where}: roles", expected=f"one of {', '.join(ROLES)}")
            if not isinstance(names, list) or not all(isinstance(n, str) and n.strip() for n in names):
                raise AccessError(f"got {names!r}", where=f"{where}: roles.{role}", expected="a list of certificate common names")
            roles[role] = tuple(n.strip() for n in names)
        return cls(roles)

    def role_of(self, common_name: str) -> str | None:
        """The highest role of a certificate's common name, or None."""
        found = [role for role in ROLES if common_name in self.roles.get(role, ())]
        return found[-1] if found else None

    def zenoh(self) -> dict[str, Any]:
        """The Zenoh ``access_control`` configuration that enforces these roles."""
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
        return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


def _services(role: str) -> list[str]:
    return [f"{keys.SERVICE_ROOT}/*/{service}" for service in _SERVICES_OF[role]]


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
        # a peer manager is an operator: it announces itself and publishes its summary
        _rule("operator-announces", "ingress", ["liveliness_token"], [_MANAGERS]),
        _rule("operator-publishes-summary", "ingress", ["put"], [_SUMMARIES]),
        _rule("operator-reaches-subscribers", "egress", ["declare_subscriber", "declare_liveliness_subscriber"], [_DATA, _MANAGERS, _SUMMARIES]),
        # and it serves: this manager calls its services (get_summary, spawn, ...) and hears the replies
        _rule("operator-serves", "ingress", ["declare_queryable", "reply"], [_SERVICES]),
        _rule("operator-is-called", "egress", ["query", "liveliness_query"], [_SERVICES, _MANAGERS]),
    ],
    "admin": [_rule("admin-calls", "ingress", ["query"], _services("admin"))],
}


def _rules_of(role: str) -> list[str]:
    return [rule["id"] for rule in _RULES[role]]
