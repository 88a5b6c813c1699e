"""Security of a stack that leaves one machine: the router's TLS, user/password and access-control settings.

The router is the only place that enforces anything: every other process of a secure stack is a client of it
(``protocol.bus``), so each message passes it once, and the router lets it through or drops it silently by the
identity of the link it came on (the common name of the client's certificate under mutual TLS, the user name under
user/password) and by key expression. :func:`build_access_control` writes Zenoh's ``access_control`` section from a
map of drivebench roles to identities; ``docs/security.md`` shows a whole secure deployment.

What Zenoh 1.10's access control does, measured with a Python router and clients while writing this (the effects
on a whole stack are pinned by ``tests/test_security.py``):
  * a message is checked at the router on the way in (``ingress``, against the sender's identity) and on the way
    out (``egress``, against the receiver's): ``put`` in from the publisher and out to each subscriber;
    ``declare_subscriber`` in from the subscriber and out to the publishers (without it a publisher never learns
    of the subscriber and sends nothing: no data, no matching status); ``query`` in from the querier and out to the
    queryable's owner; ``declare_queryable`` in; ``reply`` in from the queryable's owner and out to the querier;
    ``liveliness_token`` in from the declarer and out to liveliness subscribers and queriers;
    ``declare_liveliness_subscriber`` and ``liveliness_query`` in;
  * a key expression must be *included* in an allowed one: a put or query on a wildcard that merely intersects an
    allowed key (``drivebench/**``, ``.../sim/*``) is dropped;
  * a subject listing both a certificate common name and a user name matches only a link that has both;
  * a denied message is dropped without an error to its sender; a denied query ends at once with no reply.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import msgspec
import yaml

from protocol import keys
from protocol.deploy import graph
from protocol.deploy.config import ConfigError
from protocol.deploy.graph import NAME, RUN, wildcard

EVERYTHING = f"{keys.ROOT}/**"
ALL_ALIVE = f"{keys.ROOT}/alive/**"

# (flow, messages, key expressions) a role may use. Everything else is denied (the default permission).
Grant = tuple[str, tuple[str, ...], tuple[str, ...]]

# Every identity named in any role: subscribe to anything of drivebench, watch and query liveliness, read the
# simulator's status; and receive what it subscribed to, the declarations of subscribers (so that its own
# publishers send), replies to its queries and liveliness tokens.
COMMON: tuple[Grant, ...] = (
    ("ingress", ("declare_subscriber",), (EVERYTHING,)),
    ("ingress", ("declare_liveliness_subscriber", "liveliness_query"), (ALL_ALIVE,)),
    ("ingress", ("query",), (wildcard(keys.sim_status(RUN)),)),
    ("egress", ("put", "declare_subscriber", "reply"), (EVERYTHING,)),
    ("egress", ("liveliness_token",), (ALL_ALIVE,)),
)


def grants_of(row: graph.Role) -> tuple[Grant, ...]:
    """What one row of the process graph may do beyond :data:`COMMON`: put what it publishes, declare and answer
    what it serves, ask what it queries, declare its own liveliness token."""
    grants: tuple[Grant, ...] = ()
    if row.publishes:
        grants += (("ingress", ("put",), tuple(map(wildcard, row.publishes))),)
    if row.serves:
        served = tuple(map(wildcard, row.serves))
        grants += (("ingress", ("declare_queryable", "reply"), served), ("egress", ("query",), served))
    if row.queries:
        grants += (("ingress", ("query",), tuple(map(wildcard, row.queries))),)
    if row.token is not None:
        grants += (("ingress", ("liveliness_token",), (wildcard(keys.alive(RUN, row.token_role, NAME)),)),)
    if row.claims:
        grants += (("ingress", ("liveliness_token",), tuple(map(wildcard, row.claims))),)
    return grants


def _roles_from_graph() -> dict[str, tuple[Grant, ...]]:
    roles = {row.name: grants_of(row) for row in graph.ROLES if row.name != "router" and row.on_bus}
    for group in sorted({row.group for row in graph.ROLES if row.group}):
        roles[group] = tuple(grant for row in graph.ROLES if row.group == group for grant in grants_of(row))
    roles["observer"] = ()  # read-only: what every identity may do, and nothing more
    return roles


# The access-control roles: one per row of the process graph (``protocol.deploy.graph``), each group role ("service":
# one certificate for a machine running several services) and "observer".
ROLES: dict[str, tuple[Grant, ...]] = _roles_from_graph()


class Identity(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Who a client is to the router: the common name (CN) of its certificate (mutual TLS) and/or the user name it
    authenticates with (user/password). With both given, a link must show both."""

    cert_common_name: str = ""
    username: str = ""

    def __post_init__(self) -> None:
        if not (self.cert_common_name or self.username):
            raise ValueError("an identity needs a cert_common_name, a username or both")


# In a roles map, a plain string is a name that matches a certificate common name *or* a user name.
RoleMap = Mapping[str, Iterable["str | Identity"]]


def _subjects_of(identity: str | Identity) -> list[dict[str, Any]]:
    if isinstance(identity, str):
        if not identity:
            raise ConfigError("roles: an identity name is empty")
        return [{"cert_common_names": [identity]}, {"usernames": [identity]}]
    subject: dict[str, Any] = {}
    if identity.cert_common_name:
        subject["cert_common_names"] = [identity.cert_common_name]
    if identity.username:
        subject["usernames"] = [identity.username]
    return [subject]


def build_access_control(roles: RoleMap) -> dict[str, Any]:
    """Zenoh's ``access_control`` section for a map of drivebench roles (:data:`ROLES`) to identities.

    Default deny: an identity gets what its roles grant plus :data:`COMMON`; an identity in no role (a certificate
    signed by the CA but not named here) gets nothing at all.
    """
    unknown = sorted(set(roles) - set(ROLES))
    if unknown:
        raise ConfigError(f"roles: unknown role(s) {', '.join(map(repr, unknown))} (roles: {', '.join(sorted(ROLES))})")
    subjects: list[dict[str, Any]] = []
    subject_ids: dict[str, str] = {}  # canonical JSON of a subject -> its id (one subject per distinct identity)
    role_subjects: dict[str, list[str]] = {}
    for role, identities in roles.items():
        ids = role_subjects.setdefault(role, [])
        for identity in identities:
            for subject in _subjects_of(identity):
                canonical = json.dumps(subject, sort_keys=True)
                if canonical not in subject_ids:
                    subject_ids[canonical] = f"identity-{len(subject_ids) + 1}"
                    subjects.append({"id": subject_ids[canonical], **subject})
                if subject_ids[canonical] not in ids:
                    ids.append(subject_ids[canonical])
    rules: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def add_rules(name: str, grants: Iterable[Grant]) -> list[str]:
        ids = []
        for index, (flow, messages, key_exprs) in enumerate(grants):
            rule_id = f"{name}-{index}"
            rules.append(
                {
                    "id": rule_id,
                    "messages": list(messages),
                    "flows": [flow],
                    "permission": "allow",
                    "key_exprs": list(key_exprs),
                }
            )
            ids.append(rule_id)
        return ids

    everyone = [subject["id"] for subject in subjects]
    if everyone:
        policies.append({"id": "every-identity", "rules": add_rules("common", COMMON), "subjects": everyone})
    for role, ids in role_subjects.items():
        if ids and ROLES[role]:
            policies.append({"id": f"role-{role}", "rules": add_rules(role, ROLES[role]), "subjects": ids})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def check_users_file(path: str) -> str:
    """``path`` when it is a readable ``user:password`` file as Zenoh reads it; else one line saying where not."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as error:
        raise ConfigError(f"users_file: cannot read {path}: {error.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"users_file: {path} is not UTF-8 text") from None
    users = 0
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue  # Zenoh skips blank lines; it refuses comments and lines without ':'
        user, colon, _ = line.partition(":")
        if not colon or not user or line.startswith("#"):
            raise ConfigError(f"users_file: {path}:{number}: expected user:password (no comments)")
        users += 1
    if not users:
        raise ConfigError(f"users_file: {path} names no user")
    return path


def load_access_control_file(path: str) -> dict[str, Any]:
    """A hand-written Zenoh ``access_control`` section (or a whole Zenoh config that has one): YAML, JSON or JSON5."""
    from protocol.bus import BusError, zenoh_section

    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as error:
        raise ConfigError(f"access_control_file: cannot read {path}: {error.strerror}") from None
    if Path(path).suffix in (".yaml", ".yml"):
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise ConfigError(f"access_control_file: {path}: not valid YAML: {error}") from None
        if isinstance(data, dict) and "access_control" in data:
            data = data["access_control"]
        text = json.dumps(data)
    try:
        section = zenoh_section("access_control", text)
    except BusError as error:
        raise ConfigError(f"access_control_file: {path}: {error}") from None
    if not isinstance(section, dict) or not section.get("enabled"):
        raise ConfigError(f"access_control_file: {path}: access control is not enabled (enabled: true)")
    return section


def router_settings(
    *,
    mtls: bool,
    tls_root_ca: str,
    tls_cert: str,
    listen: Iterable[str],
    users_file: str,
    roles: RoleMap,
    access_control_file: str,
) -> dict[str, Any]:
    """The Zenoh settings a secure router adds to its bus (``protocol.bus.Bus(extra=...)``); {} for a plain one.

    ``tls_root_ca`` and ``tls_cert``: the router bus's resolved ones (the environment applied). Raises ConfigError
    (one line, naming the field) for settings that cannot work together.
    """
    settings: dict[str, Any] = {}
    secure_listeners = [e for e in listen if e.split("/", 1)[0] in ("tls", "quic")]
    if mtls:
        if not tls_root_ca:
            raise ConfigError(
                "mtls: true needs the CA that signed the clients' certificates: bus.tls_root_ca "
                "(or DRIVEBENCH_TLS_ROOT_CA)"
            )
        if not secure_listeners:
            raise ConfigError(f"mtls: true needs a tls/ or quic/ endpoint in bus.listen, got {list(listen)}")
    if tls_cert:
        # Always explicit: the router bus sets enable_mtls for its outgoing links (to other routers) whenever it
        # has a certificate, and on a router that flag also decides whether clients must show one.
        settings["transport/link/tls/enable_mtls"] = bool(mtls)
    if users_file:
        settings["transport/auth/usrpwd/dictionary_file"] = check_users_file(users_file)
    if roles and access_control_file:
        raise ConfigError("roles and access_control_file are alternatives: give one")
    if roles:
        if not (mtls or users_file):
            raise ConfigError(
                "roles need identities to match: set mtls: true (certificate common names) and/or "
                "users_file (user names)"
            )
        settings["access_control"] = build_access_control(roles)
    elif access_control_file:
        settings["access_control"] = load_access_control_file(access_control_file)
    return settings
