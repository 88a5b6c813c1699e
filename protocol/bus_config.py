"""How a process joins the bus: endpoints, mode, TLS and credentials from its config or the environment, checked
before Zenoh sees them (one-line :class:`BusError`), and the Zenoh config they make. ``protocol.bus`` re-exports
everything here; the sessions themselves are there.
"""

from __future__ import annotations

import json
import os
import re
import socket
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import msgspec
import zenoh

from protocol import environment

# Environment: how a process joins the bus when its config leaves a field empty (config > environment > default).
# Names, kinds, defaults and meanings: protocol.environment.
ROUTER_ENV = environment.ROUTER.name
MODE_ENV = environment.MODE.name
LISTEN_ENV = environment.LISTEN.name
TLS_ROOT_CA_ENV = environment.TLS_ROOT_CA.name
TLS_CERT_ENV = environment.TLS_CERT.name
TLS_KEY_ENV = environment.TLS_KEY.name
USER_ENV = environment.USER.name
PASSWORD_ENV = environment.PASSWORD.name
BUS_ENV = tuple(variable.name for variable in environment.BUS)

DEFAULT_ROUTER_LISTEN = ("tcp/[::]:7447",)
SECURE_CONNECT_TIMEOUT_MS = 10_000  # see BusConfig.connect_timeout_ms

_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
_SECURE_PROTOCOLS = ("tls", "quic")
_ZENOH_SOURCE = re.compile(r"\s+at /\S+?\.rs:\d+\.?")  # "... at /root/.cargo/.../orchestrator.rs:388."


class BusError(RuntimeError):
    """The bus could not be opened or used; the text says which endpoint and why."""


def _check_endpoint(endpoint: str, *, where: str) -> str:
    protocol, slash, address = endpoint.partition("/")
    if not slash or not address or protocol not in _PROTOCOLS:
        raise ValueError(
            f"{where}: {endpoint!r} is not an endpoint like tcp/HOST:PORT or tls/HOST:PORT "
            f"(protocols: {', '.join(_PROTOCOLS)})"
        )
    return endpoint


class BusConfig(msgspec.Struct, frozen=True, kw_only=True):
    """How a process joins the bus. Every empty field falls back to an environment variable, then to a default.

    mode: "peer" (data flows peer to peer, the router serves discovery), "client" (everything through the router) or
        "router"; empty = ``DRIVEBENCH_MODE`` (peer or client), else client when TLS or credentials are set
        (see below), else peer.
    connect: endpoints to connect to, e.g. ``["tcp/127.0.0.1:7447"]`` or ``["tls/router.lan:7447"]``; empty =
        ``DRIVEBENCH_ROUTER`` (comma separated).
    listen: endpoints to listen on; empty = ``DRIVEBENCH_LISTEN`` (comma separated), else a peer listens on an
        ephemeral port (loopback when it only connects to loopback) so others can open direct links to it, a
        router on ``tcp/[::]:7447``, and a client on nothing.
    lease_ms: how long a silent peer is kept before its liveliness tokens vanish.
    shared_memory: Zenoh's implicit shared memory for large puts between processes on one host.
    tls_root_ca: PEM file of the CA that signed the router's certificate (and, with mutual TLS, every process's);
        empty = ``DRIVEBENCH_TLS_ROOT_CA``.
    tls_cert, tls_key: this process's own certificate and private key (PEM): what a client shows a mutual-TLS
        router (its common name is its identity for access control), what a router shows its clients (its name
        must match the host name they connect to); empty = ``DRIVEBENCH_TLS_CERT`` / ``DRIVEBENCH_TLS_KEY``.
    user: user name for the router's user/password authentication; empty = ``DRIVEBENCH_USER``.
    password_file: file whose first line is the password; empty = the ``DRIVEBENCH_PASSWORD`` variable. There is no
        password field: configs are logged and written into recordings.
    connect_timeout_ms: how long opening the bus keeps trying the connect endpoints; -1 = forever (a process may
        start before its router); empty = forever, or 10 s when TLS or credentials are set, because a refused
        certificate or password is retried like an absent router and would otherwise hang the process silently.

    Security: with TLS or credentials set, a process that is not the router must be a client with no listener. The
    router enforces access control on what passes through it, and only on that: a peer would open direct (gossip)
    links to other peers, on plain TCP listeners, that bypass the router and its access control.
    """

    mode: str = ""
    connect: list[str] = []
    listen: list[str] = []
    lease_ms: int = 3000
    shared_memory: bool = True
    tls_root_ca: str = ""
    tls_cert: str = ""
    tls_key: str = ""
    user: str = ""
    password_file: str = ""
    connect_timeout_ms: int | None = None

    def __post_init__(self) -> None:
        if self.mode not in ("", "peer", "client", "router"):
            raise ValueError(f"mode must be peer, client or router, got {self.mode!r}")
        for endpoint in self.connect:
            _check_endpoint(endpoint, where="connect")
        for endpoint in self.listen:
            _check_endpoint(endpoint, where="listen")
        if self.connect_timeout_ms is not None and self.connect_timeout_ms < -1:
            raise ValueError(f"connect_timeout_ms must be -1 (forever) or >= 0, got {self.connect_timeout_ms}")


# The bus of processes that only observe a run (scorer, recorder): a client, whose one link, to the router, exists
# before any episode starts. As peers they would also open direct links to the other peers as gossip finds them,
# and a route that changes mid-episode has lost messages to them: once ~10 consecutive steps on every key of a
# recording, once the last pose of an episode at the scorer. The driving loop stays peer to peer (low latency),
# and lock-step re-sends a frame nobody answered, so a loss there costs a second, never a step.
OBSERVER_BUS = BusConfig(mode="client")


@dataclass(frozen=True)
class ResolvedBus:
    """A :class:`BusConfig` with the environment and the defaults applied and every file checked.

    ``password`` is the secret itself: never logged (``repr`` hides it).
    """

    mode: str
    connect: tuple[str, ...]
    listen: tuple[str, ...]
    lease_ms: int
    shared_memory: bool
    connect_timeout_ms: int
    tls_root_ca: str = ""
    tls_cert: str = ""
    tls_key: str = ""
    user: str = ""
    password: str = field(default="", repr=False)

    @property
    def secure(self) -> bool:
        """TLS or credentials are set: the process must then go through the router (see :class:`BusConfig`)."""
        return _is_secure(self.connect, self.tls_root_ca, self.tls_cert, self.user)

    def settings(self) -> dict[str, Any]:
        """Every setting, for the logged config: the password only as whether one is set."""
        fields = {name: getattr(self, name) for name in self.__dataclass_fields__ if name != "password"}
        return {**fields, "connect": list(self.connect), "listen": list(self.listen), "password": bool(self.password)}

    def describe(self) -> str:
        """One line for logs and errors (no secrets)."""
        parts = [self.mode, f"connect={list(self.connect)}", f"listen={list(self.listen)}"]
        if self.tls_cert or self.tls_root_ca:
            parts.append(f"tls(ca={self.tls_root_ca or '-'}, cert={self.tls_cert or '-'})")
        if self.user:
            parts.append(f"user={self.user}")
        return ", ".join(parts)


def _is_secure(connect: Iterable[str], *settings: str) -> bool:
    return any(settings) or any(e.split("/", 1)[0] in _SECURE_PROTOCOLS for e in connect)


def _endpoints_from_env(env: Mapping[str, str], name: str) -> list[str]:
    return [_check_endpoint(e.strip(), where=name) for e in env.get(name, "").split(",") if e.strip()]


def _readable_file(path: str, *, where: str) -> str:
    """``path`` when it is a readable file; else a BusError naming the field or variable and the path."""
    try:
        with open(path, "rb"):
            pass
    except OSError as error:
        raise BusError(f"{where}: cannot read {path}: {error.strerror}") from None
    return path


def resolve_bus(config: BusConfig, env: Mapping[str, str] | None = None) -> ResolvedBus:
    """Apply the environment (this process's bus variables by default) and the defaults to ``config``; check every file.

    Precedence, field by field: the config (file or ``--set``) > the environment variable > the default.
    Raises :class:`BusError` (one line naming the field or the variable) on a bad value, an unreadable file, or
    security settings on a process that is not a client.
    """
    env = environment.bus_settings() if env is None else env
    try:
        connect = list(config.connect) or ([] if config.mode == "router" else _endpoints_from_env(env, ROUTER_ENV))
        env_listen = _endpoints_from_env(env, LISTEN_ENV)
    except ValueError as error:
        raise BusError(str(error)) from None
    root_ca, cert, key = _tls_files(config, env)
    user, password = _credentials(config, env)
    secure = _is_secure(connect, root_ca, cert, user)
    mode, mode_from = _mode(config, env, secure=secure)
    listen = _listen(config, mode=mode, env_listen=env_listen, connect=connect)
    _check_secure_roles(mode=mode, mode_from=mode_from, listen=listen, secure=secure, cert=cert)
    if config.connect_timeout_ms is not None:
        timeout_ms = config.connect_timeout_ms
    else:
        timeout_ms = SECURE_CONNECT_TIMEOUT_MS if secure and mode != "router" else -1
    return ResolvedBus(
        mode=mode,
        connect=tuple(connect),
        listen=tuple(listen),
        lease_ms=config.lease_ms,
        shared_memory=config.shared_memory,
        connect_timeout_ms=timeout_ms,
        tls_root_ca=root_ca,
        tls_cert=cert,
        tls_key=key,
        user=user,
        password=password,
    )


def _setting(env: Mapping[str, str], value: str, *, name: str, variable: str) -> tuple[str, str]:
    """A bus field's value and where it came from (``bus.NAME`` or the variable): the config wins when set."""
    return (value, f"bus.{name}") if value else (env.get(variable, "").strip(), variable)


def _tls_files(config: BusConfig, env: Mapping[str, str]) -> tuple[str, str, str]:
    """The root CA, certificate and key paths (each readable, the last two set together); empty when unset."""
    root_ca, root_ca_from = _setting(env, config.tls_root_ca, name="tls_root_ca", variable=TLS_ROOT_CA_ENV)
    cert, cert_from = _setting(env, config.tls_cert, name="tls_cert", variable=TLS_CERT_ENV)
    key, key_from = _setting(env, config.tls_key, name="tls_key", variable=TLS_KEY_ENV)
    for path, where in ((root_ca, root_ca_from), (cert, cert_from), (key, key_from)):
        if path:
            _readable_file(path, where=where)
    if bool(cert) != bool(key):
        raise BusError(
            f"{cert_from if cert else key_from} is set but not its pair: a certificate needs its private "
            f"key (bus.tls_cert and bus.tls_key, or {TLS_CERT_ENV} and {TLS_KEY_ENV})"
        )
    return root_ca, cert, key


def _credentials(config: BusConfig, env: Mapping[str, str]) -> tuple[str, str]:
    """The user and password (both or neither); the password from bus.password_file's first line or the
    environment, never from the config itself (configs are logged and recorded)."""
    user, user_from = _setting(env, config.user, name="user", variable=USER_ENV)
    if config.password_file:
        _readable_file(config.password_file, where="bus.password_file")
        with open(config.password_file, encoding="utf-8", errors="replace") as file:
            password, password_from = file.readline().rstrip("\r\n"), "bus.password_file"
        if not password:
            raise BusError(f"bus.password_file: {config.password_file} has no password on its first line")
    else:
        password, password_from = env.get(PASSWORD_ENV, ""), PASSWORD_ENV
    if user and not password:
        raise BusError(f"{user_from} is set but no password: set {PASSWORD_ENV} or bus.password_file")
    if password and not user:
        raise BusError(f"{password_from} is set but no user: set {USER_ENV} or bus.user")
    return user, password


def _mode(config: BusConfig, env: Mapping[str, str], *, secure: bool) -> tuple[str, str]:
    """The session mode and where it came from; unset, a secure process is a client and any other a peer."""
    if config.mode:
        return config.mode, "bus.mode"
    mode = env.get(MODE_ENV, "").strip()
    if mode and mode not in ("peer", "client"):
        raise BusError(f"{MODE_ENV} must be peer or client, got {mode!r}")
    return mode or ("client" if secure else "peer"), MODE_ENV


def _listen(config: BusConfig, *, mode: str, env_listen: list[str], connect: list[str]) -> list[str]:
    """The listen endpoints: the config's, none for a client, the environment's, else a default by mode (a peer
    whose routers are all on this machine listens on loopback only)."""
    if config.listen:
        return list(config.listen)
    if mode == "client":
        return []  # a client never listens, whatever DRIVEBENCH_LISTEN says (it may be meant for the peers)
    if env_listen:
        return env_listen
    if mode == "router":
        return list(DEFAULT_ROUTER_LISTEN)
    local = all("127.0.0.1" in e or "localhost" in e for e in connect)
    return ["tcp/127.0.0.1:0"] if local else ["tcp/0.0.0.0:0"]


def _check_secure_roles(*, mode: str, mode_from: str, listen: list[str], secure: bool, cert: str) -> None:
    """A secure process is a client that does not listen; a router listening on TLS needs its certificate."""
    if secure and mode == "peer":
        raise BusError(
            f"{mode_from} is peer, but TLS or credentials are set: a secure process must be a client of "
            f"the router, which enforces access control; a peer's direct links to other peers would bypass "
            f"it (leave the mode empty: it is then client)"
        )
    if secure and mode == "client" and listen:
        raise BusError(
            f"bus.listen is {listen}, but TLS or credentials are set: a secure client must not listen "
            f"(everything goes through the router, which enforces access control)"
        )
    if mode == "router" and any(e.split("/", 1)[0] in _SECURE_PROTOCOLS for e in listen) and not cert:
        raise BusError(
            f"listening on {[e for e in listen if e.split('/', 1)[0] in _SECURE_PROTOCOLS]} needs the "
            f"router's certificate: bus.tls_cert and bus.tls_key (or {TLS_CERT_ENV} and {TLS_KEY_ENV})"
        )


def zenoh_settings(bus: ResolvedBus, *, name: str) -> dict[str, Any]:
    """The Zenoh config, as a JSON-able dict, of one process (``reference/transport.md`` §10 for each setting)."""
    settings: dict[str, Any] = {
        "mode": bus.mode,
        "connect": {"endpoints": list(bus.connect), "timeout_ms": bus.connect_timeout_ms},
        "listen": {"endpoints": list(bus.listen)},
        "scouting": {
            "multicast": {"enabled": False},
            "gossip": {"enabled": True},
        },
        "timestamping": {"enabled": True},
        "transport": {
            "link": {"tx": {"lease": bus.lease_ms}},
            "shared_memory": {"enabled": bus.shared_memory},
        },
        "metadata": {"name": name},
    }
    if bus.mode == "peer":
        settings["scouting"]["gossip"]["autoconnect_strategy"] = {
            "peer": {"to_router": "always", "to_peer": "greater-zid"}
        }
    tls: dict[str, Any] = {}
    if bus.tls_root_ca:
        tls["root_ca_certificate"] = bus.tls_root_ca
    if bus.tls_cert:
        # Measured (Zenoh 1.10): a connecting side shows its certificate only with enable_mtls; a router's own
        # enable_mtls (whether it demands clients' certificates) comes from the router config and overrides this.
        tls.update(connect_certificate=bus.tls_cert, connect_private_key=bus.tls_key, enable_mtls=True)
        if bus.mode == "router":
            tls.update(listen_certificate=bus.tls_cert, listen_private_key=bus.tls_key)
    if tls:
        settings["transport"]["link"]["tls"] = tls
    if bus.user:
        settings["transport"]["auth"] = {"usrpwd": {"user": bus.user, "password": bus.password}}
    return settings


def merge_settings(base: dict[str, Any], extra: Mapping[str, Any]) -> None:
    """Merge ``extra`` into ``base``; keys may be paths (``"transport/auth/usrpwd/dictionary_file"``)."""
    for path, value in extra.items():
        *parents, last = path.split("/")
        node = base
        for part in parents:
            node = node.setdefault(part, {})
        if isinstance(value, Mapping) and isinstance(node.get(last), dict):
            merge_settings(node[last], value)
        else:
            node[last] = value


def zenoh_config(
    config: BusConfig, *, name: str, extra: Mapping[str, Any] | None = None, env: Mapping[str, str] | None = None
) -> zenoh.Config:
    """The Zenoh config for one process; ``extra`` adds or replaces settings (the router's security)."""
    settings = zenoh_settings(resolve_bus(config, env), name=name)
    merge_settings(settings, extra or {})
    try:
        return zenoh.Config.from_json5(json.dumps(settings))
    except zenoh.ZError as error:
        raise BusError(f"invalid Zenoh config: {zenoh_message(error)}") from None


def zenoh_section(key: str, text: str) -> Any:
    """Zenoh's parse of one config section given as JSON5 text (``text`` may also be a whole config holding it), as
    plain JSON data; BusError with Zenoh's complaint when it does not parse."""
    config = zenoh.Config()
    try:
        config.insert_json5(key, text)
    except zenoh.ZError as error:
        try:
            config = zenoh.Config.from_json5(text)
        except zenoh.ZError:
            raise BusError(zenoh_message(error)) from None
    return json.loads(config.get_json(key))


_zenoh_log_started = False


def zenoh_log_from_env() -> None:
    """Zenoh's own (Rust) log on stderr, only when ``RUST_LOG`` asks for it (e.g. ``RUST_LOG=warn``): the one place a
    router says why it refused a link ("peer sent no certificates"); a client only ever sees a timeout."""
    global _zenoh_log_started
    if not _zenoh_log_started and os.environ.get("RUST_LOG"):
        _zenoh_log_started = True
        zenoh.init_log_from_env_or("warn")


def zenoh_message(error: Exception) -> str:
    """Zenoh's error text without the Rust source location it ends with."""
    return " ".join(_ZENOH_SOURCE.sub("", str(error)).split()).rstrip(". ") or type(error).__name__


def router_address(endpoint: str) -> tuple[str, int]:
    """(host, port) of a Zenoh endpoint like ``tcp/10.0.0.5:7447``, ``tls/localhost:7447`` or ``tcp/[::1]:7447``;
    an unspecified address (``0.0.0.0``, ``[::]``) is this machine's loopback."""
    _, _, address = endpoint.partition("/")
    host, _, port = address.split("#")[0].split("?")[0].rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"not a tcp/tls endpoint with a port: {endpoint!r}")
    host = host.strip("[]")
    return ("127.0.0.1" if host == "0.0.0.0" else "::1" if host == "::" else host), int(port)


def probe_router(endpoint: str, *, timeout_s: float = 2.0) -> None:
    """Raise :class:`BusError` unless the router's TCP port accepts connections. A client waits forever for a
    router that is not there; tools that must answer now (healthchecks, ``drivebench view``) ask this first."""
    try:
        host, port = router_address(endpoint)
    except ValueError as error:
        raise BusError(str(error)) from None
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as error:
        raise BusError(f"router {endpoint} not reachable: {error.strerror or error}") from None
