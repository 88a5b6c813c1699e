"""The bus: a thin wrapper over one Zenoh session. The only module of the project that imports ``zenoh``.

What it adds to Zenoh, and why:
  * sessions configured one way everywhere (multicast scouting off, one router endpoint, gossip for direct peer
    links, short lease so a hung process is noticed in ~2-3 s), see ``reference/transport.md`` §10;
  * typed publishers per traffic class (frames drop, commands and events never drop);
  * subscribers that decode into the expected type and hand messages to the caller's loop through a queue with a
    timeout (Zenoh's own channels have no ``recv(timeout)``); bad input is counted, logged once per key with the
    field path, and dropped, so a malformed message can never crash a process;
  * liveliness tokens and watchers;
  * endpoints, mode, TLS and credentials from the config or the environment (``DRIVEBENCH_*``, see
    :class:`BusConfig` and ``docs/security.md``), checked before Zenoh sees them, with one-line errors;
  * ``with Bus(...)`` always closes the session: a process with a live callback subscriber never exits otherwise.
"""

from __future__ import annotations

import collections
import enum
import json
import logging
import os
import re
import socket
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import msgspec
import zenoh

from protocol import codec

log = logging.getLogger("drivebench.bus")

T = TypeVar("T", bound=msgspec.Struct)

# Environment: how a process joins the bus when its config leaves a field empty (config > environment > default).
ROUTER_ENV = "DRIVEBENCH_ROUTER"  # connect endpoints, comma separated
MODE_ENV = "DRIVEBENCH_MODE"  # peer | client
LISTEN_ENV = "DRIVEBENCH_LISTEN"  # listen endpoints, comma separated (peers and routers; clients never listen)
TLS_ROOT_CA_ENV = "DRIVEBENCH_TLS_ROOT_CA"  # CA that signed the router's (and, mTLS, the clients') certificates
TLS_CERT_ENV = "DRIVEBENCH_TLS_CERT"  # this process's own certificate (PEM)
TLS_KEY_ENV = "DRIVEBENCH_TLS_KEY"  # its private key (PEM)
USER_ENV = "DRIVEBENCH_USER"  # user name for the router's user/password authentication
PASSWORD_ENV = "DRIVEBENCH_PASSWORD"  # its password (only ever from here or a file: configs are logged and recorded)
BUS_ENV = (ROUTER_ENV, MODE_ENV, LISTEN_ENV, TLS_ROOT_CA_ENV, TLS_CERT_ENV, TLS_KEY_ENV, USER_ENV, PASSWORD_ENV)

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
        raise ValueError(f"{where}: {endpoint!r} is not an endpoint like tcp/HOST:PORT or tls/HOST:PORT "
                         f"(protocols: {', '.join(_PROTOCOLS)})")
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
    """Apply the environment (``os.environ`` by default) and the defaults to ``config``; check every file.

    Precedence, field by field: the config (file or ``--set``) > the environment variable > the default.
    Raises :class:`BusError` (one line naming the field or the variable) on a bad value, an unreadable file, or
    security settings on a process that is not a client.
    """
    env = os.environ if env is None else env
    try:
        connect = list(config.connect) or ([] if config.mode == "router" else _endpoints_from_env(env, ROUTER_ENV))
        env_listen = _endpoints_from_env(env, LISTEN_ENV)
    except ValueError as error:
        raise BusError(str(error)) from None

    def setting(value: str, name: str, variable: str) -> tuple[str, str]:
        return (value, f"bus.{name}") if value else (env.get(variable, "").strip(), variable)

    root_ca, root_ca_from = setting(config.tls_root_ca, "tls_root_ca", TLS_ROOT_CA_ENV)
    cert, cert_from = setting(config.tls_cert, "tls_cert", TLS_CERT_ENV)
    key, key_from = setting(config.tls_key, "tls_key", TLS_KEY_ENV)
    user, user_from = setting(config.user, "user", USER_ENV)
    for path, where in ((root_ca, root_ca_from), (cert, cert_from), (key, key_from)):
        if path:
            _readable_file(path, where=where)
    if bool(cert) != bool(key):
        raise BusError(f"{cert_from if cert else key_from} is set but not its pair: a certificate needs its private "
                       f"key (bus.tls_cert and bus.tls_key, or {TLS_CERT_ENV} and {TLS_KEY_ENV})")
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

    secure = _is_secure(connect, root_ca, cert, user)
    mode, mode_from = config.mode, "bus.mode"
    if not mode:
        mode, mode_from = env.get(MODE_ENV, "").strip(), MODE_ENV
        if mode and mode not in ("peer", "client"):
            raise BusError(f"{MODE_ENV} must be peer or client, got {mode!r}")
        mode = mode or ("client" if secure else "peer")

    if config.listen:
        listen = list(config.listen)
    elif mode == "client":
        listen = []  # a client never listens, whatever DRIVEBENCH_LISTEN says (it may be meant for the peers)
    elif env_listen:
        listen = env_listen
    elif mode == "router":
        listen = list(DEFAULT_ROUTER_LISTEN)
    else:
        local = all("127.0.0.1" in e or "localhost" in e for e in connect)
        listen = ["tcp/127.0.0.1:0"] if local else ["tcp/0.0.0.0:0"]

    if secure and mode == "peer":
        raise BusError(f"{mode_from} is peer, but TLS or credentials are set: a secure process must be a client of "
                       f"the router, which enforces access control; a peer's direct links to other peers would bypass "
                       f"it (leave the mode empty: it is then client)")
    if secure and mode == "client" and listen:
        raise BusError(f"bus.listen is {listen}, but TLS or credentials are set: a secure client must not listen "
                       f"(everything goes through the router, which enforces access control)")
    if mode == "router" and any(e.split("/", 1)[0] in _SECURE_PROTOCOLS for e in listen) and not cert:
        raise BusError(f"listening on {[e for e in listen if e.split('/', 1)[0] in _SECURE_PROTOCOLS]} needs the "
                       f"router's certificate: bus.tls_cert and bus.tls_key (or {TLS_CERT_ENV} and {TLS_KEY_ENV})")
    if config.connect_timeout_ms is not None:
        timeout_ms = config.connect_timeout_ms
    else:
        timeout_ms = SECURE_CONNECT_TIMEOUT_MS if secure and mode != "router" else -1
    return ResolvedBus(mode=mode, connect=tuple(connect), listen=tuple(listen), lease_ms=config.lease_ms,
                       shared_memory=config.shared_memory, connect_timeout_ms=timeout_ms, tls_root_ca=root_ca,
                       tls_cert=cert, tls_key=key, user=user, password=password)


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


def _merge(base: dict[str, Any], extra: Mapping[str, Any]) -> None:
    """Merge ``extra`` into ``base``; keys may be paths (``"transport/auth/usrpwd/dictionary_file"``)."""
    for path, value in extra.items():
        *parents, last = path.split("/")
        node = base
        for part in parents:
            node = node.setdefault(part, {})
        if isinstance(value, Mapping) and isinstance(node.get(last), dict):
            _merge(node[last], value)
        else:
            node[last] = value


def zenoh_config(config: BusConfig, *, name: str, extra: Mapping[str, Any] | None = None,
                 env: Mapping[str, str] | None = None) -> zenoh.Config:
    """The Zenoh config for one process; ``extra`` adds or replaces settings (the router's security)."""
    settings = zenoh_settings(resolve_bus(config, env), name=name)
    _merge(settings, extra or {})
    try:
        return zenoh.Config.from_json5(json.dumps(settings))
    except zenoh.ZError as error:
        raise BusError(f"invalid Zenoh config: {_zenoh_message(error)}") from None


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
            raise BusError(_zenoh_message(error)) from None
    return json.loads(config.get_json(key))


_zenoh_log_started = False


def _zenoh_log_from_env() -> None:
    """Zenoh's own (Rust) log on stderr, only when ``RUST_LOG`` asks for it (e.g. ``RUST_LOG=warn``): the one place a
    router says why it refused a link ("peer sent no certificates"); a client only ever sees a timeout."""
    global _zenoh_log_started
    if not _zenoh_log_started and os.environ.get("RUST_LOG"):
        _zenoh_log_started = True
        zenoh.init_log_from_env_or("warn")


def _zenoh_message(error: Exception) -> str:
    """Zenoh's error text without the Rust source location it ends with."""
    return " ".join(_ZENOH_SOURCE.sub("", str(error)).split()).rstrip(". ") or type(error).__name__


class Traffic(enum.Enum):
    """Traffic classes, each with its own QoS (``reference/transport.md`` §10)."""

    FRAMES = "frames"  # large, newest wins: never block a real-time simulator for a slow viewer
    FRAMES_LOSSLESS = "frames_lossless"  # large, every one must arrive: lock-step runs, where a lost frame is a
    # lost step for the recorder and the dataset (the simulator waits for the brain anyway)
    COMMANDS = "commands"  # small, must arrive, jump the queue ahead of frames
    EVENTS = "events"  # small, must arrive, in order (poses, episode events, scores)
    METRICS = "metrics"  # small, latest wins


_QOS = {
    Traffic.FRAMES: dict(congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA),
    Traffic.FRAMES_LOSSLESS: dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA),
    Traffic.COMMANDS: dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME,
                           express=True),
    Traffic.EVENTS: dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA),
    Traffic.METRICS: dict(congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA_LOW),
}


class Publisher(Generic[T]):
    """Publishes messages of one type on one key."""

    def __init__(self, session: zenoh.Session, key: str, traffic: Traffic):
        self.key = key
        self._publisher = session.declare_publisher(key, **_QOS[traffic])

    def publish(self, message: T) -> None:
        self._publisher.put(codec.encode(message))

    def publish_bytes(self, payload: bytes) -> None:
        """Put raw bytes (tests use this to send garbage; replay uses it for recorded wire bytes)."""
        self._publisher.put(payload)

    def has_subscribers(self) -> bool:
        return bool(self._publisher.matching_status.matching)

    def close(self) -> None:
        self._publisher.undeclare()


@dataclass(frozen=True)
class Received(Generic[T]):
    """A decoded message, its wire bytes, the key it came on, and when it arrived (``time.monotonic_ns`` here)."""

    key: str
    message: T
    arrival_ns: int
    payload: bytes = b""


@dataclass
class RejectCounter:
    """Bad input per key: counted always, logged once per key (with the field path)."""

    counts: dict[str, int] = field(default_factory=lambda: collections.defaultdict(int))
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def reject(self, key: str, error: Exception) -> None:
        with self._lock:
            self.counts[key] += 1
            first = self.counts[key] == 1
        if first:
            log.warning("dropped bad message on %s: %s (further ones on this key are only counted)", key, error)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())


class Inbox:
    """A thread-safe queue of :class:`Received` messages that one or more subscriptions fill.

    ``keep_last=None``: a FIFO that keeps everything (commands, poses, events).
    ``keep_last=n``: keep only the newest n (camera frames: a slow consumer gets the latest frame, not a backlog).
    Give several subscriptions one inbox to handle their messages in one loop, in arrival order.
    """

    def __init__(self, *, keep_last: int | None = None):
        self._queue: collections.deque[Received] = collections.deque(maxlen=keep_last)
        self._ready = threading.Condition()
        self.received = 0

    def put(self, item: Received) -> None:
        with self._ready:
            self._queue.append(item)
            self.received += 1
            self._ready.notify()

    def recv(self, timeout_s: float | None = None) -> Received | None:
        """The oldest queued message; waits up to ``timeout_s`` (None = forever); None on timeout."""
        with self._ready:
            if not self._queue and not self._ready.wait_for(lambda: bool(self._queue), timeout=timeout_s):
                return None
            return self._queue.popleft()

    def try_recv(self) -> Received | None:
        with self._ready:
            return self._queue.popleft() if self._queue else None

    def drain(self) -> list[Received]:
        with self._ready:
            items = list(self._queue)
            self._queue.clear()
            return items


class Subscription(Generic[T]):
    """Decodes messages of one type on one key expression into an :class:`Inbox`."""

    def __init__(self, session: zenoh.Session, key: str, message_type: type[T], rejects: RejectCounter,
                 inbox: Inbox):
        self.key = key
        self.inbox = inbox
        self._type = message_type
        self._rejects = rejects
        # A Python callback runs on the session's one Python callback thread: decode there (cheap, and bad input
        # is rejected before it reaches the loop), then wake the loop.
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        try:
            message = codec.decode(payload, self._type)
        except codec.DecodeError as error:
            self._rejects.reject(key, error)
            return
        self.inbox.put(Received(key=key, message=message, arrival_ns=time.monotonic_ns(), payload=payload))

    def recv(self, timeout_s: float | None = None) -> Received[T] | None:
        return self.inbox.recv(timeout_s)

    def close(self) -> None:
        self._subscriber.undeclare()


class LivelinessWatch:
    """Which liveliness tokens under a key expression are alive now; calls ``on_change(key, alive)`` on changes."""

    def __init__(self, session: zenoh.Session, key: str, on_change: Callable[[str, bool], None] | None = None):
        self._alive: set[str] = set()
        self._lock = threading.Condition()
        self._on_change = on_change
        self._subscriber = session.liveliness().declare_subscriber(key, self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            (self._alive.add if alive else self._alive.discard)(key)
            self._lock.notify_all()
        if self._on_change is not None:
            self._on_change(key, alive)

    def alive(self) -> set[str]:
        with self._lock:
            return set(self._alive)

    def wait_for(self, keys: set[str], *, timeout_s: float, abort: Callable[[], str | None] | None = None) -> set[str]:
        """Wait until every key in ``keys`` is alive; return the missing ones (empty = all alive).

        ``abort`` is polled a few times a second; a non-None string stops the wait early.
        """
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                missing = keys - self._alive
                remaining = deadline - time.monotonic()
                if not missing or remaining <= 0 or (abort is not None and abort() is not None):
                    return missing
                self._lock.wait(timeout=min(remaining, 0.2))

    def close(self) -> None:
        self._subscriber.undeclare()


class Bus:
    """One process's connection to the bus. Use as a context manager: ``with Bus(config, name="sim") as bus:``.

    ``extra``: more Zenoh settings (key paths to values), e.g. a router's access control; ``env``: the environment
    the config's empty fields fall back to (``os.environ`` by default; ``{}`` for a self-contained local stack);
    ``resolved`` is the config with the environment applied.
    """

    def __init__(self, config: BusConfig, *, name: str, extra: Mapping[str, Any] | None = None,
                 env: Mapping[str, str] | None = None):
        self.name = name
        self.config = config
        self.rejects = RejectCounter()
        self.resolved = resolve_bus(config, env)
        _zenoh_log_from_env()
        settings = zenoh_settings(self.resolved, name=name)
        _merge(settings, extra or {})
        try:
            self.session = zenoh.open(zenoh.Config.from_json5(json.dumps(settings)))
        except zenoh.ZError as error:
            hint = ""
            if self.resolved.secure and self.resolved.mode != "router":
                # Zenoh reports a refused certificate or password exactly like an absent router: a timeout.
                hint = (" - with TLS or credentials set, this is also what a refused or missing certificate, a "
                        "certificate name that does not match the endpoint's host, an unknown CA or a wrong "
                        "user/password look like (the router says which with RUST_LOG=warn)")
            raise BusError(f"cannot open the bus ({self.resolved.describe()}): {_zenoh_message(error)}{hint}") from None
        self._tokens: list[zenoh.LivelinessToken] = []
        self._queryables: list[zenoh.Queryable] = []

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def publisher(self, key: str, message_type: type[T], traffic: Traffic) -> Publisher[T]:
        del message_type  # documents the type at the call site; the codec encodes any struct
        return Publisher(self.session, key, traffic)

    def subscribe(self, key: str, message_type: type[T], *, keep_last: int | None = None,
                  inbox: Inbox | None = None) -> Subscription[T]:
        """Messages of ``message_type`` on ``key`` into ``inbox`` (a new one with ``keep_last`` if not given)."""
        return Subscription(self.session, key, message_type, self.rejects, inbox or Inbox(keep_last=keep_last))

    def declare_alive(self, key: str) -> None:
        """Declare a liveliness token, kept until the bus closes (or the process dies)."""
        self._tokens.append(self.session.liveliness().declare_token(key))

    def watch_alive(self, key: str, on_change: Callable[[str, bool], None] | None = None) -> LivelinessWatch:
        return LivelinessWatch(self.session, key, on_change)

    def alive_now(self, key: str, *, timeout_s: float = 1.0) -> set[str]:
        """The liveliness tokens alive under ``key`` now (a liveliness query: no watch to keep)."""
        found = set()
        for reply in self.session.liveliness().get(key, timeout=timeout_s):
            if reply.ok is not None:
                found.add(str(reply.ok.key_expr))
        return found

    def serve(self, key: str, handler: Callable[[bytes], bytes]) -> None:
        """A queryable: ``handler(request payload) -> reply payload``; runs on the session's callback thread."""

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                reply = handler(payload)
            except Exception as error:  # noqa: BLE001 - a bad request must not kill the server
                log.warning("control request on %s failed: %s", key, error)
                query.reply_err(str(error).encode())
                return
            query.reply(key, reply)

        self._queryables.append(self.session.declare_queryable(key, on_query))

    def request(self, key: str, payload: bytes, *, timeout_s: float) -> bytes | None:
        """Send a query and return the first successful reply payload (None when nobody answered in time)."""
        errors = []
        for reply in self.session.get(key, payload=payload, timeout=timeout_s):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            errors.append(reply.err.payload.to_bytes().decode(errors="replace"))
        if errors:
            raise BusError(f"request to {key} failed: {errors[0]}")
        return None

    def close(self) -> None:
        if not self.session.is_closed():
            self.session.close()


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
