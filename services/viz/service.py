"""The live view process (``python -m services.viz``): one run's bus traffic served to Foxglove over WebSocket.

It joins as an observer (a Zenoh client, like the scorer and the recorder) and declares the liveliness token
``drivebench/alive/<run>/viz/<name>``. Open it in Foxglove with Open connection -> Foxglove WebSocket ->
``ws://HOST:PORT`` (see ``docs/live-view.md``; channels in ``services.viz.bridge``).

Why a slow viewer never slows the simulation:
  * the Zenoh callbacks only decode and queue (``protocol.bus``), so this process drains the bus at once;
  * camera frames wait in a queue of ``frame_queue`` frames, newest wins, and one thread per camera key encodes
    them to JPEG (only while a viewer is subscribed to that camera);
  * the small messages (poses, commands, metrics, events, scores) wait in a queue of at most ``PENDING_LIMIT``;
  * the Foxglove server queues at most ``backlog`` messages per client and drops the oldest, and the gate in front
    of it (``services.viz.gate``) at most ``backlog_bytes`` per viewer and serves at most ``max_viewers``, so a
    client that never reads costs bounded memory and no waiting.
"""

from __future__ import annotations

import faulthandler
import logging
import queue
import sys
import threading
import time

import msgspec

from protocol import keys
from protocol.bus import OBSERVER_BUS, Bus, BusConfig, Inbox, Subscription
from protocol.deploy.runtime import UserError, stop_requested
from protocol.episodes import running_spec, start_event
from protocol.messages import CameraFrame, Command, EpisodeEvent, EpisodeScore, EventKind, LiveMetrics, Pose, RunMessage
from services.viz.bridge import BridgeError, LiveBridge

log = logging.getLogger("drivebench.viz")

PENDING_LIMIT = 10_000  # small messages waiting for the publishing thread (far more than it ever falls behind)
DEFAULT_PORT = 8765
STALL_DUMP_S = 20.0


class VizConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of the live view process.

    host: address the Foxglove WebSocket server binds to ("0.0.0.0": every interface, as compose does).
    port: its TCP port (0: any free port; the log says which).
    backlog: messages queued per viewer before its oldest are dropped (foxglove-sdk ``message_backlog_size``,
        whose default of 1024 is ~1 GB of raw frames per slow viewer; 30-60 suits a pure image stream). One step
        of a run is up to ~6 messages here (two cameras, pose, its two views, a command), so 120 holds ~20 steps
        (~1 s at 20 Hz): a few MB of JPEG per viewer at most.
    max_viewers: viewers served at once; one more is refused (HTTP 503, logged) until one leaves
        (``services.viz.gate``): each viewer costs socket writes and up to ``backlog_bytes`` of memory.
    backlog_bytes: bytes queued per viewer before its newest messages are dropped (whole messages, never the
        channel advertisements), on top of the ``backlog`` bound in messages: a slow viewer of big noisy JPEGs holds
        at most this much (plus the kernel's socket buffer).
    jpeg_quality: 1-100, of the camera images sent (JPEG: ~1/13 of raw frames' bandwidth).
    frame_queue: camera frames waiting per camera to be encoded; when encoding falls behind, the newest win.
    perturbed: also serve the perturbed camera of a noise injector (``<run>/noise/camera``).
    bus: a Zenoh client by default (see ``protocol.bus.OBSERVER_BUS``).
    """

    bus: BusConfig = OBSERVER_BUS
    run_id: str = "default"
    name: str = "viz"
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    backlog: int = 120
    max_viewers: int = 4
    backlog_bytes: int = 4_000_000
    jpeg_quality: int = 90
    frame_queue: int = 2
    perturbed: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be within 0..65535, got {self.port}")
        if not 1 <= self.backlog <= 100_000:
            raise ValueError(f"backlog must be within 1..100000 messages, got {self.backlog}")
        if not 1 <= self.max_viewers <= 1000:
            raise ValueError(f"max_viewers must be within 1..1000, got {self.max_viewers}")
        if not 10_000 <= self.backlog_bytes <= 10_000_000_000:
            raise ValueError(f"backlog_bytes must be within 10000..10000000000, got {self.backlog_bytes}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be 1-100, got {self.jpeg_quality}")
        if not 1 <= self.frame_queue <= 100:
            raise ValueError(f"frame_queue must be within 1..100 frames, got {self.frame_queue}")


def viewer_url(host: str, port: int) -> str:
    """Where to point Foxglove (an address that listens on every interface is shown as this machine's loopback)."""
    shown = "127.0.0.1" if host in ("", "0.0.0.0", "::") else host
    return f"ws://[{shown}]:{port}" if ":" in shown else f"ws://{shown}:{port}"


class _CameraPump(threading.Thread):
    """Encodes and sends the frames of one camera key, newest first when behind (off the Zenoh callback thread)."""

    def __init__(self, bridge: LiveBridge, inbox: Inbox, stop: threading.Event, key: str):
        super().__init__(name=f"viz-camera-{key.rsplit('/', 2)[-2]}", daemon=True)
        self.bridge, self.inbox, self.stop, self.key = bridge, inbox, stop, key
        self.handled = 0

    def run(self) -> None:
        while not self.stop.is_set():
            received = self.inbox.recv(timeout_s=0.2)
            if received is not None:
                self.handled += 1
                try:
                    self.bridge.publish_frame(received.key, received.message)
                except Exception:  # one bad frame must not end the camera stream
                    log.exception("could not send a camera frame on %s", received.key)


class VizService:
    def __init__(self, config: VizConfig, bus: Bus):
        self.config = config
        run = config.run_id
        # The processes alive now, so that their channels exist before the first viewer connects.
        alive = [keys.parse_alive(key)[1:] for key in bus.alive_now(keys.alive_all(run))]
        try:
            self.bridge = LiveBridge(
                run_id=run,
                host=config.host,
                port=config.port,
                backlog=config.backlog,
                jpeg_quality=config.jpeg_quality,
                name=f"drivebench {run}",
                brains=[name for role, name in alive if role == "brain"],
                perturbed=config.perturbed and any(role == "noise" for role, _ in alive),
                max_viewers=config.max_viewers,
                backlog_bytes=config.backlog_bytes,
            )
        except BridgeError as error:
            raise UserError(str(error)) from None
        self._bus = bus
        self._stop = threading.Event()
        self._inbox = Inbox(keep_last=PENDING_LIMIT)
        self._subscriptions: list[Subscription] = [
            bus.subscribe(keys.events(run), EpisodeEvent, inbox=self._inbox),
            bus.subscribe(keys.pose(run), Pose, inbox=self._inbox),
            bus.subscribe(keys.commands_all(run), Command, inbox=self._inbox),
            bus.subscribe(keys.live_metrics(run), LiveMetrics, inbox=self._inbox),
            bus.subscribe(keys.score(run), EpisodeScore, inbox=self._inbox),
        ]
        self._pumps: list[_CameraPump] = []
        for key in [keys.camera_raw(run)] + ([keys.camera_perturbed(run)] if config.perturbed else []):
            inbox = Inbox(keep_last=config.frame_queue)
            self._subscriptions.append(bus.subscribe(key, CameraFrame, inbox=inbox))
            pump = _CameraPump(self.bridge, inbox, self._stop, key)
            pump.start()
            self._pumps.append(pump)
        # Channels that appear with processes: each brain's commands, the perturbed camera. Advertised as soon as
        # the process is alive (from the liveliness callback, handled in the publishing thread), not at its first
        # message, so a viewer subscribed in time misses none of them.
        self._appeared: queue.SimpleQueue[str] = queue.SimpleQueue()
        self._watch = bus.watch_alive(keys.alive_all(run), self._on_alive)
        self._started: set[int] = set()  # episodes whose START was sent
        self._asked: set[int] = set()  # episodes whose missed START we asked the simulator for
        bus.declare_alive(keys.alive(run, "viz", config.name))
        log.info(
            "serving run %s to Foxglove at %s (at most %d viewers; backlog %d messages, %d bytes per viewer)",
            run,
            viewer_url(config.host, self.bridge.port),
            config.max_viewers,
            config.backlog,
            config.backlog_bytes,
        )

    @property
    def port(self) -> int:
        return self.bridge.port

    def serve_forever(self) -> None:
        rearmed = 0.0
        try:
            sys.stderr.fileno()
        except (OSError, ValueError, AttributeError):  # stderr is no file (embedded, captured): no stall dumps
            rearmed = float("inf")
        try:
            while not stop_requested():
                self.poll(timeout_s=0.1)
                if (now := time.monotonic()) - rearmed > 1.0:
                    # A stalled publishing loop (it never should) prints every thread's stack to the log, from a C
                    # thread that needs no GIL: what a hang needs to be understood.
                    faulthandler.dump_traceback_later(STALL_DUMP_S, exit=False)
                    rearmed = now
        finally:
            faulthandler.cancel_dump_traceback_later()

    def _on_alive(self, key: str, alive: bool) -> None:
        if alive:
            self._appeared.put(key)

    def _advertise_appeared(self) -> None:
        while not self._appeared.empty():
            _, role, name = keys.parse_alive(self._appeared.get())
            if role == "brain":
                self.bridge.advertise_command(name)
            elif role == "noise" and self.config.perturbed:
                self.bridge.advertise_perturbed_camera()

    def poll(self, *, timeout_s: float) -> None:
        self._advertise_appeared()
        received = self._inbox.recv(timeout_s)
        while received is not None:
            self._handle(received.key, received.message)
            received = self._inbox.try_recv()
        self.bridge.maintain()

    def _handle(self, key: str, message: RunMessage) -> None:
        episode = message.header.episode
        start = message.spec if isinstance(message, EpisodeEvent) and message.kind == EventKind.START else None
        is_start = start is not None
        if is_start and episode in self._started:
            return  # recovered from the simulator before it arrived
        if not is_start and episode not in self._started | self._asked:
            self._recover_start(episode)
        self.bridge.publish(key, message)
        if start is not None:
            self._started.add(episode)
            log.info("episode %d started on %s", episode, start.circuit)
        if isinstance(message, EpisodeEvent) and message.kind == EventKind.END:
            self._log_episode_end(episode)

    def _recover_start(self, episode: int) -> None:
        """Messages of an episode whose START we missed (joined late): its spec, for the track, comes from the
        simulator's status, and the very START it published goes out as if we had seen it."""
        self._asked.add(episode)
        spec = running_spec(self._bus, self.config.run_id, episode)
        if spec is not None:
            self._handle(keys.events(self.config.run_id), start_event(self.config.run_id, episode, spec))

    def _log_episode_end(self, episode: int) -> None:
        sent = self.bridge.sent
        cameras = ", ".join(
            f"{p.key.rsplit('/', 2)[-2]}: {p.inbox.received} in, {p.handled} taken, {sent[p.key]} sent"
            for p in self._pumps
        )
        log.info(
            "episode %d ended; so far: %d messages sent; camera frames %s; %d not encoded (no viewer)",
            episode,
            sum(sent.values()),
            cameras,
            self.bridge.frames_skipped,
        )
        if (gate := self.bridge.gate) is not None:
            stats = gate.stats
            log.info(
                "viewers: %d connected, %d served, %d refused (max %d); %d messages (%d bytes) dropped for "
                "slow viewers; peak backlog %d bytes (limit %d)",
                stats.viewers,
                stats.served,
                stats.refused,
                gate.max_viewers,
                stats.dropped_messages,
                stats.dropped_bytes,
                stats.peak_backlog_bytes,
                gate.backlog_bytes,
            )

    def close(self) -> None:
        self._stop.set()
        self._watch.close()
        for subscription in self._subscriptions:
            subscription.close()
        for pump in self._pumps:
            pump.join(timeout=2.0)
        self.bridge.close()


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import service_main

    return service_main(
        "viz",
        "drivebench viz: a run's camera, pose, commands and metrics live in Foxglove (WebSocket)",
        VizConfig,
        VizService,
        argv,
    )
