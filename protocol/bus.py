"""The bus: a thin wrapper over one Zenoh session (only ``protocol/`` imports ``zenoh``).

What it adds to Zenoh, and why:
  * sessions configured one way everywhere (multicast scouting off, one router endpoint, gossip for direct peer
    links, short lease so a hung process is noticed in ~2-3 s), see ``reference/transport.md`` §10;
  * typed publishers per traffic class (frames drop, commands and events never drop);
  * subscribers that decode into the expected type and hand messages to the caller's loop through a queue with a
    timeout (Zenoh's own channels have no ``recv(timeout)``); bad input is counted, logged with the field path
    (rate-limited per subscription and queryable: :class:`RejectCounter`), and dropped, so a malformed message can
    never crash a process;
  * liveliness tokens and watchers;
  * endpoints, mode, TLS and credentials from the config or the environment (``DRIVEBENCH_*``, see
    :class:`BusConfig` and ``docs/security.md``), checked before Zenoh sees them, with one-line errors
    (``protocol.bus_config``, re-exported here);
  * ``with Bus(...)`` always closes the session: a process with a live callback subscriber never exits otherwise.
"""

from __future__ import annotations

import collections
import enum
import json
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import msgspec
import zenoh

from protocol import codec
from protocol.bus_config import (
    BUS_ENV,
    DEFAULT_ROUTER_LISTEN,
    LISTEN_ENV,
    MODE_ENV,
    OBSERVER_BUS,
    PASSWORD_ENV,
    ROUTER_ENV,
    SECURE_CONNECT_TIMEOUT_MS,
    TLS_CERT_ENV,
    TLS_KEY_ENV,
    TLS_ROOT_CA_ENV,
    USER_ENV,
    BusConfig,
    BusError,
    ResolvedBus,
    merge_settings,
    probe_router,
    resolve_bus,
    router_address,
    zenoh_config,
    zenoh_log_from_env,
    zenoh_message,
    zenoh_section,
    zenoh_settings,
)
from protocol.trace import Tracer

# How to join the bus is protocol.bus_config's; its names are this module's too (the bus's one public face).
__all__ = [
    "BUS_ENV",
    "DEFAULT_ROUTER_LISTEN",
    "LISTEN_ENV",
    "MODE_ENV",
    "OBSERVER_BUS",
    "PASSWORD_ENV",
    "ROUTER_ENV",
    "SECURE_CONNECT_TIMEOUT_MS",
    "TLS_CERT_ENV",
    "TLS_KEY_ENV",
    "TLS_ROOT_CA_ENV",
    "USER_ENV",
    "Bus",
    "BusConfig",
    "BusError",
    "Inbox",
    "LivelinessWatch",
    "Publisher",
    "Received",
    "RejectCounter",
    "ResolvedBus",
    "Subscription",
    "Traffic",
    "probe_router",
    "resolve_bus",
    "router_address",
    "zenoh_config",
    "zenoh_section",
    "zenoh_settings",
]

log = logging.getLogger("drivebench.bus")

if TYPE_CHECKING:
    from typing_extensions import TypeForm  # a struct or a union of tagged structs: see protocol.codec.decode

T = TypeVar("T", bound=msgspec.Struct)


class Traffic(enum.Enum):
    """Traffic classes, each with its own QoS (``reference/transport.md`` §10)."""

    FRAMES = "frames"  # large, newest wins: never block a real-time simulator for a slow viewer
    FRAMES_LOSSLESS = "frames_lossless"  # large, every one must arrive: lock-step runs, where a lost frame is a
    # lost step for the recorder and the dataset (the simulator waits for the brain anyway)
    COMMANDS = "commands"  # small, must arrive, jump the queue ahead of frames
    EVENTS = "events"  # small, must arrive, in order (poses, episode events, scores)
    METRICS = "metrics"  # small, latest wins


_QOS: dict[Traffic, dict[str, Any]] = {
    Traffic.FRAMES: dict(congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA),
    Traffic.FRAMES_LOSSLESS: dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA),
    Traffic.COMMANDS: dict(
        congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME, express=True
    ),
    Traffic.EVENTS: dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA),
    Traffic.METRICS: dict(congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA_LOW),
}


class Publisher(Generic[T]):
    """Publishes messages of one type on one key."""

    def __init__(self, session: zenoh.Session, key: str, traffic: Traffic, tracer: Tracer):
        self.key = key
        self._publisher = session.declare_publisher(key, **_QOS[traffic])
        self._tracer = tracer

    def publish(self, message: T) -> None:
        payload = codec.encode(message)
        self._tracer.mark("put", self.key, message)
        self._publisher.put(payload)
        self._tracer.mark("sent", self.key, message)

    def publish_bytes(self, payload: bytes) -> None:
        """Put raw bytes (tests use this to send garbage; replay uses it for recorded wire bytes)."""
        self._tracer.mark("put", self.key)
        self._publisher.put(payload)
        self._tracer.mark("sent", self.key)

    def has_subscribers(self) -> bool:
        status: Any = self._publisher.matching_status  # a MatchingStatus (zenoh's stub says bool)
        return bool(status.matching)

    def close(self) -> None:
        self._publisher.undeclare()


@dataclass(frozen=True)
class Received(Generic[T]):
    """A decoded message, its wire bytes, the key it came on, and when it arrived (``time.monotonic_ns`` here)."""

    key: str
    message: T
    arrival_ns: int
    payload: bytes = b""


REJECT_LOG_INTERVAL_S = 10.0  # bad input: at most one log line per subscription (or queryable) this often


@dataclass
class _RejectLog:
    """What one subscription's (or queryable's) bad input has logged so far."""

    what: str  # "message" or "request"
    logged_at: float  # time.monotonic() of its last line
    since: str  # wall-clock time of that line, for the next one ("... since 16:04:05")
    unlogged: int = 0  # dropped since that line
    last: str = ""  # the last of those: its key and error


@dataclass
class RejectCounter:
    """Bad input (messages that do not decode, requests a handler refuses), counted per subscription or queryable.

    Logged per subscription's key expression, never per concrete key: the first in full (the key and the field path),
    then at most one line every ``interval_s`` with how many more were dropped since, and at :meth:`flush` (the bus's
    close) the ones not logged yet. A client sending 1,000 bad requests, or 2,000 junk keys under a wildcard, makes a
    few lines, not thousands, and the lines count every drop.
    """

    interval_s: float = REJECT_LOG_INTERVAL_S
    counts: dict[str, int] = field(default_factory=lambda: collections.defaultdict(int))  # by key expression
    _logs: dict[str, _RejectLog] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def reject(self, key: str, error: Exception, *, source: str = "", what: str = "message") -> None:
        """One bad ``what`` on ``key``, received by the subscription or queryable declared on ``source`` (default:
        ``key``)."""
        source = source or key
        now = time.monotonic()
        with self._lock:
            self.counts[source] += 1
            entry = self._logs.get(source)
            if entry is None:
                self._logs[source] = _RejectLog(what=what, logged_at=now, since=time.strftime("%H:%M:%S"))
            else:
                entry.unlogged += 1
                entry.last = f"{key}: {error}"
        if entry is None:
            log.warning(
                "dropped bad %s on %s: %s (more on %s are counted, and logged at most every %g s)",
                what, key, error, source, self.interval_s,
            )  # fmt: skip
        elif now - entry.logged_at >= self.interval_s:
            self._log_unlogged(source)

    def flush(self) -> None:
        """Log what was dropped since the last line, for every subscription and queryable."""
        for source in list(self._logs):
            self._log_unlogged(source)

    def _log_unlogged(self, source: str) -> None:
        with self._lock:
            entry = self._logs[source]
            count, since, last = entry.unlogged, entry.since, entry.last
            entry.unlogged, entry.logged_at, entry.since = 0, time.monotonic(), time.strftime("%H:%M:%S")
        if count:
            log.warning(
                "dropped %d more bad %s(s) on %s since %s (the last on %s)", count, entry.what, source, since, last
            )

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
        self.tracer: Tracer | None = None  # set by a subscription of a traced bus: marks when the loop takes each

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
            return self._taken(self._queue.popleft())

    def keep_last(self, count: int | None) -> None:
        """From now on keep only the newest ``count`` messages (None: keep everything); the newest queued stay."""
        with self._ready:
            self._queue = collections.deque(self._queue, maxlen=count)

    def try_recv(self) -> Received | None:
        with self._ready:
            return self._taken(self._queue.popleft()) if self._queue else None

    def drain(self) -> list[Received]:
        with self._ready:
            items = list(self._queue)
            self._queue.clear()
        for item in items:
            self._taken(item)
        return items

    def _taken(self, item: Received) -> Received:
        if self.tracer is not None:
            self.tracer.mark("taken", item.key, item.message)
        return item


class Subscription(Generic[T]):
    """Decodes messages of one type on one key expression into an :class:`Inbox`.

    ``open`` is a gate: while it is False, samples are dropped on arrival, before they are copied or decoded (a
    brain host that subscribes to two camera streams and drives from one per episode pays nothing for the other).
    ``on_message(received)``, if given, runs on the callback thread for each decoded message before it is queued:
    keep it short, and never block in it.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        message_type: TypeForm[T],
        rejects: RejectCounter,
        inbox: Inbox,
        on_message: Callable[[Received[T]], None] | None = None,
        tracer: Tracer | None = None,
    ):
        self.key = key
        self.inbox = inbox
        self._tracer = tracer if tracer is not None and tracer.on else None
        if self._tracer is not None:
            inbox.tracer = self._tracer
        self.open = True
        self._type = message_type
        self._rejects = rejects
        self._on_message = on_message
        # zenoh-python runs each subscription's Python callback on a thread of its own (no order across keys):
        # decode there (cheap, and bad input is rejected before it reaches the loop), then wake the loop.
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if not self.open:
            return
        arrived_ns = time.monotonic_ns()
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        try:
            message = codec.decode(payload, self._type)
        except codec.DecodeError as error:
            self._rejects.reject(key, error, source=self.key)
            return
        received = Received(key=key, message=message, arrival_ns=time.monotonic_ns(), payload=payload)
        if self._tracer is not None:
            self._tracer.mark("arrived", key, message, ns=arrived_ns)
            self._tracer.mark("decoded", key, message, ns=received.arrival_ns)
        if self._on_message is not None:
            self._on_message(received)
        self.inbox.put(received)

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


# How long a control or status query waits for its answer. The answer takes milliseconds; on a loaded machine the
# answering callback may wait seconds for its process's CPU and GIL, and Zenoh turns an answer later than the
# timeout into an error reply ("Timeout"), which no retry should follow (a late-accepted start would run twice). A
# query to a key nobody serves returns at once whatever this is.
ANSWER_TIMEOUT_S = 15.0


class Bus:
    """One process's connection to the bus. Use as a context manager: ``with Bus(config, name="sim") as bus:``.

    ``extra``: more Zenoh settings (key paths to values), e.g. a router's access control; ``env``: the environment
    the config's empty fields fall back to (``os.environ`` by default; ``{}`` for a self-contained local stack);
    ``resolved`` is the config with the environment applied.
    """

    def __init__(
        self,
        config: BusConfig,
        *,
        name: str,
        extra: Mapping[str, Any] | None = None,
        env: Mapping[str, str] | None = None,
    ):
        self.name = name
        self.config = config
        self.rejects = RejectCounter()
        self.resolved = resolve_bus(config, env)
        zenoh_log_from_env()
        settings = zenoh_settings(self.resolved, name=name)
        merge_settings(settings, extra or {})
        try:
            self.session = zenoh.open(zenoh.Config.from_json5(json.dumps(settings)))
        except zenoh.ZError as error:
            hint = ""
            if self.resolved.secure and self.resolved.mode != "router":
                # Zenoh reports a refused certificate or password exactly like an absent router: a timeout.
                hint = (
                    " - with TLS or credentials set, this is also what a refused or missing certificate, a "
                    "certificate name that does not match the endpoint's host, an unknown CA or a wrong "
                    "user/password look like (the router says which with RUST_LOG=warn)"
                )
            raise BusError(f"cannot open the bus ({self.resolved.describe()}): {zenoh_message(error)}{hint}") from None
        self._tokens: list[zenoh.LivelinessToken] = []
        self._queryables: list[zenoh.Queryable] = []
        self.tracer = Tracer(name)  # on only with $DRIVEBENCH_TRACE_DIR (protocol.trace)

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def publisher(self, key: str, message_type: type[T], traffic: Traffic) -> Publisher[T]:
        del message_type  # documents the type at the call site; the codec encodes any struct
        return Publisher(self.session, key, traffic, self.tracer)

    def subscribe(
        self,
        key: str,
        message_type: TypeForm[T],
        *,
        keep_last: int | None = None,
        inbox: Inbox | None = None,
        on_message: Callable[[Received[T]], None] | None = None,
    ) -> Subscription[T]:
        """Messages of ``message_type`` on ``key`` into ``inbox`` (a new one with ``keep_last`` if not given);
        ``on_message`` sees each one first, on the callback thread (see :class:`Subscription`)."""
        inbox = inbox or Inbox(keep_last=keep_last)
        return Subscription(self.session, key, message_type, self.rejects, inbox, on_message, self.tracer)

    def declare_alive(self, key: str) -> Callable[[], None]:
        """Declare a liveliness token, kept until the bus closes (or the process dies) or the returned function,
        which withdraws it, is called."""
        token = self.session.liveliness().declare_token(key)
        self._tokens.append(token)

        def withdraw() -> None:
            if token in self._tokens:
                self._tokens.remove(token)
                token.undeclare()

        return withdraw

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
            except Exception as error:  # a bad request must not kill the server
                self.rejects.reject(key, error, what="request")  # logged as bad input is: rate-limited, counted
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
            if reply.err is not None:
                errors.append(reply.err.payload.to_bytes().decode(errors="replace"))
        if errors:
            raise BusError(f"request to {key} failed: {errors[0]}")
        return None

    def close(self) -> None:
        if not self.session.is_closed():
            self.session.close()
        self.rejects.flush()  # bad input dropped since its last log line
        self.tracer.write()
