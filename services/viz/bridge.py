"""The core of the live view: bus messages in, Foxglove WebSocket channels out. Knows nothing of Zenoh.

It serves a Foxglove WebSocket server (foxglove-sdk, subprotocol ``foxglove.sdk.v1``) and maps each bus message to
the channel a recording would hold for it (``protocol.mapping.recording``, ``protocol.mapping.views``), under the same
stable topics
(``protocol.mapping.topics``: ``/camera/truth``, ``/car/pose``, ``/tf``, ...), so one layout
(``docs/foxglove/drivebench-layout.json``) shows any recording and any live run:

* camera frames -> ``foxglove.CompressedImage`` (protobuf, JPEG; the recording's image schema with the run id,
  episode, sequence number and dropped flag as extra fields), one channel per camera key;
* poses -> the views ``/car/pose`` (``foxglove.PoseInFrame``) and ``/tf`` (``foxglove.FrameTransform``), and the
  episode's circuit as ``/circuit`` (``foxglove.SceneUpdate``), sent once per episode and again whenever a viewer
  subscribes to it; episode events also as ``/episode/log`` (``foxglove.Log``);
* poses themselves, commands (one channel per brain), live metrics, episode events and scores -> JSON with a JSON
  Schema.

Log times are simulated time: the first episode seen starts at 0 and each later one one second after the previous
one's last message (``protocol.mapping.recording.EpisodeClock``, as in recordings), so a viewer's clock never runs back.
The geometry messages carry that same time in their ``timestamp`` (a viewer looks transforms up at its clock).

A slow viewer costs bounded memory and nothing else: ``log()`` only queues, into a queue of ``backlog`` messages per
client that drops its oldest, and the simulator never waits for this process (see ``services.viz.service``). With
``max_viewers`` / ``backlog_bytes``, viewers come in through ``services.viz.gate``: a cap on their number, and each
one's queue bounded in bytes too.
"""

from __future__ import annotations

import logging
import queue
import re
import threading
from collections import Counter
from collections.abc import Iterable

import foxglove
import msgspec
from foxglove.websocket import ServerListener

from protocol import keys
from protocol.mapping.recording import EpisodeClock, Schema, channel_layout, to_record
from protocol.mapping.topics import RUN_ID_METADATA, VIEW_METADATA, VIEW_TOPICS
from protocol.mapping.views import ViewMaker, ViewMessage, protobuf_schema
from protocol.messages import CameraFrame, Command, EpisodeEvent, EpisodeScore, LiveMetrics, Pose, RunMessage
from services.viz.gate import ViewerGate

log = logging.getLogger("drivebench.viz")
_SDK_LOG = logging.getLogger("foxglove")  # foxglove-sdk's Rust log records arrive under it

SUBPROTOCOL = "foxglove.sdk.v1"
SDK_LOG_LEVEL = "WARNING"
JSON_MESSAGES = (Command, EpisodeEvent, LiveMetrics, EpisodeScore)


class BridgeError(RuntimeError):
    """The server could not start (port taken, bad host): one line."""


def view_topics() -> dict[str, str]:
    """Topics of the derived views by name: car pose, world -> car transform, track, episode log."""
    return dict(VIEW_TOPICS)


class _LostSubscriptions(logging.Handler):
    """Channels a viewer could not subscribe to, from foxglove-sdk 0.30's error log.

    A channel created while viewers are connected is advertised to them before the server knows it: a viewer that
    subscribes at once (our test client; Foxglove, for a topic its panels show) is refused ("attempted to subscribe to
    unknown channel: N") and is never told. Measured: 1 in ~200 new channels in an idle process, about every other
    one in a busy bridge. The bridge advertises such a channel again (``LiveBridge._readvertise_lost``).
    Runs on the SDK's threads: only queues the id.
    """

    _PATTERN = re.compile(r"subscribe to unknown channel: (\d+)")

    def __init__(self) -> None:
        super().__init__(level=logging.WARNING)
        self._ids: queue.SimpleQueue[int] = queue.SimpleQueue()

    def emit(self, record: logging.LogRecord) -> None:
        if (match := self._PATTERN.search(record.getMessage())) is not None:
            self._ids.put(int(match.group(1)))

    def drain(self) -> list[int]:
        ids = []
        while not self._ids.empty():
            ids.append(self._ids.get())
        return ids


class _Listener(ServerListener):
    """foxglove-sdk server callbacks (they run on the SDK's threads: only set flags here). The SDK calls every
    method of ``ServerListener`` (no-ops there), so it must be a subclass."""

    def __init__(self, bridge: LiveBridge):
        self._bridge = bridge

    def on_subscribe(self, client, channel) -> None:
        self._bridge._on_subscribe(client.id, channel.topic)


class LiveBridge:
    """One Foxglove WebSocket server for one run.

    host / port: where to listen (port 0: any free port, see :attr:`port`). backlog: messages queued per client
    before its oldest are dropped (``message_backlog_size``). jpeg_quality: 1-100.

    Thread use: :meth:`publish_frame` from any thread (one per camera key), :meth:`publish` and :meth:`maintain`
    from one thread.
    """

    def __init__(
        self,
        *,
        run_id: str,
        host: str,
        port: int,
        backlog: int,
        jpeg_quality: int = 90,
        name: str = "drivebench",
        brains: Iterable[str] = (),
        perturbed: bool = False,
        max_viewers: int | None = None,
        backlog_bytes: int | None = None,
    ):
        self.run_id = run_id
        self.jpeg_quality = jpeg_quality
        self.sent: Counter[str] = Counter()  # messages sent per topic (logged while some viewer subscribed)
        self.frames_skipped = 0  # frames not encoded: nobody subscribed to their channel
        self.bad_frames = 0
        self.readvertised = 0  # channels advertised again after a viewer's subscription to them was lost
        self._context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._channels_lock = threading.Lock()
        self._clock = EpisodeClock()
        self._clock_lock = threading.Lock()
        self._views = ViewMaker(run_id, track_resend_ns=None)  # a live viewer keeps the track: once per episode
        self._view_topics = view_topics()
        self._topics_of_keys: dict[str, str] = {}  # bus key -> stable topic
        self._track_wanted = threading.Event()
        self._last_log_time_ns = 0
        # The SDK hands its Rust log records to Python logging, taking the GIL from whichever thread logs, possibly
        # while holding its own locks. Keep that off the hot path ("outbox full" is logged from ``log()``): only
        # warnings and errors go through; a new viewer is logged here instead (``_on_subscribe``).
        foxglove.set_log_level(SDK_LOG_LEVEL)
        self._viewers: set[int] = set()
        self._ids: dict[int, str] = {}  # channel id -> topic
        self._lost = _LostSubscriptions()
        self._advertise_known_channels(brains=brains, perturbed=perturbed)
        self._advertise_views()
        self.gate: ViewerGate | None = None
        self._serve(
            name=name, host=host, port=port, backlog=backlog, max_viewers=max_viewers, backlog_bytes=backlog_bytes
        )

    def _advertise_known_channels(self, *, brains: Iterable[str], perturbed: bool) -> None:
        """The bus channels known before the server starts: camera, pose, events, metrics, score, each brain's
        commands and the perturbed camera when asked for."""
        # Every channel known now is created before the server starts, so a viewer meets them all in its first
        # advertisement. One created later races its viewers' subscriptions (see _LostSubscriptions): the perturbed
        # camera and each brain's commands when their process comes up later (``advertise_*``) or at their first
        # message.
        for key, message_type in (
            (keys.camera_raw(self.run_id), CameraFrame),
            (keys.pose(self.run_id), Pose),
            (keys.events(self.run_id), EpisodeEvent),
            (keys.live_metrics(self.run_id), LiveMetrics),
            (keys.score(self.run_id), EpisodeScore),
        ):
            self._bus_channel(key, message_type)
        for brain in brains:
            self.advertise_command(brain)
        if perturbed:
            self.advertise_perturbed_camera()

    def _advertise_views(self) -> None:
        """The derived views' channels (car pose, world -> car transform, track, episode log)."""
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.Log_pb2 import Log
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        for name_, message_class in (
            ("car_pose", PoseInFrame),
            ("world_from_car", FrameTransform),
            ("track", SceneUpdate),
            ("episode_log", Log),
        ):
            self._channel(
                self._view_topics[name_],
                "protobuf",
                protobuf_schema(message_class),
                {VIEW_METADATA: "1", RUN_ID_METADATA: self.run_id},
            )

    def _serve(
        self,
        *,
        name: str,
        host: str,
        port: int,
        backlog: int,
        max_viewers: int | None,
        backlog_bytes: int | None,
    ) -> None:
        """Start the SDK's WebSocket server, behind a :class:`ViewerGate` when viewers or their backlog are limited;
        :class:`BridgeError` (one line) when the address cannot be served."""
        _SDK_LOG.addHandler(self._lost)
        # With limits, viewers reach the SDK's server only through the gate (services.viz.gate), which listens on
        # the address asked for; the server itself then listens on a loopback port of its own.
        gated = max_viewers is not None or backlog_bytes is not None
        try:
            self._server = foxglove.start_server(
                name=name,
                host="127.0.0.1" if gated else host,
                port=0 if gated else port,
                context=self._context,
                message_backlog_size=backlog,
                server_listener=_Listener(self),
            )
        except RuntimeError as error:
            _SDK_LOG.removeHandler(self._lost)
            raise BridgeError(
                f"cannot serve Foxglove WebSocket on {host}:{port}: {str(error).removeprefix('FoxgloveError: ')}"
            ) from None
        if gated:
            try:
                self.gate = ViewerGate(
                    host=host,
                    port=port,
                    upstream_port=self._server.port,
                    max_viewers=max_viewers or 1_000_000,
                    backlog_bytes=backlog_bytes or 1 << 40,
                )
            except OSError as error:
                self.close()
                raise BridgeError(
                    f"cannot serve Foxglove WebSocket on {host}:{port}: {error.strerror or error}"
                ) from None

    @property
    def port(self) -> int:
        """The port viewers connect to (the actual one when started with port 0)."""
        return self.gate.port if self.gate is not None else self._server.port

    # -- channels --

    def _channel(
        self, topic: str, encoding: str, schema: Schema, metadata: dict[str, str] | None = None
    ) -> foxglove.Channel:
        with self._channels_lock:
            channel = self._channels.get(topic)
            if channel is None:
                channel = self._channels[topic] = foxglove.Channel(
                    topic,
                    message_encoding=encoding,
                    context=self._context,
                    metadata=metadata,
                    schema=foxglove.Schema(name=schema.name, encoding=schema.encoding, data=schema.data),
                )
                self._ids[channel.id()] = topic
            return channel

    def _readvertise_lost(self) -> None:
        """Advertise again, under a new id, each channel a viewer failed to subscribe to (it then subscribes again,
        as Foxglove does for the topics its panels show)."""
        for channel_id in self._lost.drain():
            with self._channels_lock:
                topic = self._ids.pop(channel_id, None)
                old = self._channels.pop(topic, None) if topic is not None else None
                if topic is None or old is None:
                    continue  # not ours, or already replaced
                schema, encoding, metadata = old.schema(), old.message_encoding, old.metadata()
                # Closed first: the SDK hands back the open channel of the same topic and schema, same id and all.
                old.close()
                new = self._channels[topic] = foxglove.Channel(
                    topic, message_encoding=encoding, context=self._context, schema=schema, metadata=metadata
                )
                self._ids[new.id()] = topic
            self.readvertised += 1
            log.info("advertised %s again: a viewer's subscription to it was lost", topic)

    def _bus_channel(self, key: str, message_type: type[msgspec.Struct]) -> foxglove.Channel:
        """The channel of bus key ``key`` (its layout is only worked out the first time)."""
        with self._channels_lock:
            topic = self._topics_of_keys.get(key)
            channel = self._channels.get(topic) if topic is not None else None
        if channel is not None:
            return channel
        layout = channel_layout(key, message_type, image_format="jpeg")  # the recording's, with JPEG images
        with self._channels_lock:
            self._topics_of_keys[key] = layout.topic
        return self._channel(layout.topic, layout.message_encoding, layout.schema, layout.metadata)

    def advertise_command(self, brain: str) -> None:
        """Advertise the command channel of ``brain`` before its first command (a viewer then misses none)."""
        self._bus_channel(keys.command(self.run_id, brain), Command)

    def advertise_perturbed_camera(self) -> None:
        """Advertise the perturbed camera (a noise injector is alive) before its first frame."""
        self._bus_channel(keys.camera_perturbed(self.run_id), CameraFrame)

    def topics(self) -> list[str]:
        with self._channels_lock:
            return sorted(self._channels)

    def _on_subscribe(self, client_id: int, topic: str) -> None:
        if client_id not in self._viewers:
            self._viewers.add(client_id)
            log.info("viewer %d subscribed (first to %s)", client_id, topic)
        if topic == self._view_topics["track"]:
            self._track_wanted.set()  # a new viewer: send it the circuit (from the publishing thread)

    # -- messages --

    def log_time_ns(self, message: RunMessage) -> int:
        header = message.header
        with self._clock_lock:
            return self._clock.log_time_ns(header.run_id, header.episode, header.stamp_ns)

    def publish_frame(self, key: str, frame: CameraFrame) -> bool:
        """Encode one camera frame as JPEG and send it; False when skipped (no viewer, dropped or bad frame)."""
        channel = self._bus_channel(key, CameraFrame)
        if not channel.has_sinks():
            self.frames_skipped += 1
            return False
        if frame.dropped or not frame.data:
            return False  # the noise injector lost it: nothing to show
        try:
            data = to_record(frame, image_format="jpeg", jpeg_quality=self.jpeg_quality)
        except ValueError as error:  # a payload of the wrong size
            self.bad_frames += 1
            if self.bad_frames == 1:
                log.warning("dropped bad camera frame on %s: %s (further ones are only counted)", key, error)
            return False
        channel.log(data, log_time=self.log_time_ns(frame))
        self.sent[key] += 1
        return True

    def publish(self, key: str, message: RunMessage) -> None:
        """Send one small bus message (command, metrics, event, score, pose) and the views it implies."""
        log_time = self.log_time_ns(message)
        self._last_log_time_ns = max(self._last_log_time_ns, log_time)
        if isinstance(message, (*JSON_MESSAGES, Pose)):
            channel = self._bus_channel(key, type(message))
            if channel.has_sinks():  # nobody subscribed: not even worth encoding
                channel.log(to_record(message), log_time=log_time)
                self.sent[key] += 1
        if isinstance(message, Pose):
            # The geometry is stamped with the viewer's clock (see the module docstring).
            message = msgspec.structs.replace(
                message, header=msgspec.structs.replace(message.header, stamp_ns=log_time)
            )
        if isinstance(message, (Pose, EpisodeEvent)):
            for view in self._views.on_message(message, log_time_ns=log_time):
                sent = self._publish_view(view, log_time)
                if sent and view.topic == self._view_topics["track"]:
                    self._track_wanted.clear()  # only once a viewer really got it (its sink may lag its subscribe)

    def maintain(self) -> None:
        """Periodic work (call a few times a second): advertise again the channels whose subscription was lost, send
        the track to a viewer that subscribed since."""
        self._readvertise_lost()
        if self._track_wanted.is_set() and (track := self._views.track) is not None:
            if self._publish_view(track, self._last_log_time_ns):
                self._track_wanted.clear()  # else the new viewer's sink is not there yet: again on the next call

    def _publish_view(self, view: ViewMessage, log_time: int) -> bool:
        """Send a view to its channel's viewers; False when it has none."""
        channel = self._channel(view.topic, "protobuf", view.schema)
        if not channel.has_sinks():
            return False
        channel.log(view.message.SerializeToString(), log_time=log_time)
        self.sent[view.topic] += 1
        return True

    def close(self) -> None:
        _SDK_LOG.removeHandler(self._lost)
        gate = getattr(self, "gate", None)  # None too when __init__ failed before setting it
        if gate is not None:
            gate.close()
        self._server.stop()
        with self._channels_lock:
            for channel in self._channels.values():
                channel.close()
