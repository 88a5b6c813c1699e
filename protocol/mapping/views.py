"""Channels derived for viewers: the car pose as a Foxglove pose and transform, the circuit as a Foxglove scene,
the episode events as Foxglove log lines.

They make a recording useful in Foxglove's 3D panel (the car moving on the track) and Log panel without a plugin.
They are views only: replay and datasets read the bus channels and skip these
(``protocol.mapping.recording.is_bus_channel``).
Their topics are stable (``protocol.mapping.topics``: ``/car/pose``, ``/tf``, ``/circuit``, ``/episode/log``); the run
id is in :attr:`ViewMessage.run_id` (channel metadata, for the writer and the live view).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

from google.protobuf import descriptor_pb2
from google.protobuf.message import Message

from protocol.episode_spec import EpisodeSpec
from protocol.mapping.recording import Schema
from protocol.mapping.topics import view_topic
from protocol.messages import EndReason, EpisodeEvent, EventKind, Pose

WORLD_FRAME = "world"
CAR_FRAME = "car"
TRACK_RESEND_NS = 1_000_000_000  # a seek lands within 1 s of a scene update, so the track is always drawn
_LINE_RGBA = {"red": (0.85, 0.05, 0.05, 1.0), "white": (1.0, 1.0, 1.0, 1.0)}


@dataclass(frozen=True)
class ViewMessage:
    topic: str  # stable (protocol.mapping.topics)
    schema: Schema
    message: Message
    log_time_ns: int
    run_id: str = ""


@functools.cache
def protobuf_schema(message_class: type[Message]) -> Schema:
    """A stock protobuf class as an MCAP schema: its file and every file it depends on, dependencies first."""
    files: list[descriptor_pb2.FileDescriptorProto] = []
    seen: set[str] = set()

    def add(file_descriptor) -> None:
        if file_descriptor.name in seen:
            return
        seen.add(file_descriptor.name)
        for dependency in file_descriptor.dependencies:
            add(dependency)
        proto = descriptor_pb2.FileDescriptorProto()
        file_descriptor.CopyToProto(proto)
        files.append(proto)

    add(message_class.DESCRIPTOR.file)
    return Schema(
        name=message_class.DESCRIPTOR.full_name,
        encoding="protobuf",
        data=descriptor_pb2.FileDescriptorSet(file=files).SerializeToString(),
    )


class ViewMaker:
    """Turns recorded bus messages into view messages (call :meth:`on_message` for each, in recording order).

    track_resend_ns: how often (log time) the track goes out again; a recording needs it every second so a seek
        finds it, a live view (``services.viz``) only once per episode (None), as a live viewer keeps scene entities.
    """

    def __init__(self, run_id: str, *, track_resend_ns: int | None = TRACK_RESEND_NS):
        self.run_id = run_id
        self._track: object | None = None  # the SceneUpdate of the current episode's circuit
        self._track_sent_ns: int | None = None
        self._track_resend_ns = track_resend_ns

    @property
    def track(self) -> ViewMessage | None:
        """The current episode's track as a view message (log time 0), None before the first START."""
        return None if self._track is None else self._view("track", self._track, 0)

    def on_message(self, message: object, *, log_time_ns: int) -> list[ViewMessage]:
        views: list[ViewMessage] = []
        if isinstance(message, EpisodeEvent) and message.kind == EventKind.START and message.spec is not None:
            self._track = _track_scene(message.spec)
            self._track_sent_ns = None
        if isinstance(message, Pose):
            views += self._pose_views(message, log_time_ns)
        if isinstance(message, EpisodeEvent):
            views.append(self._view("episode_log", _event_log(message, log_time_ns=log_time_ns), log_time_ns))
        if self._track is not None and (
            self._track_sent_ns is None
            or (self._track_resend_ns is not None and log_time_ns - self._track_sent_ns >= self._track_resend_ns)
        ):
            self._track_sent_ns = log_time_ns
            views.append(self._view("track", self._track, log_time_ns))
        return views

    def _pose_views(self, pose: Pose, log_time_ns: int) -> list[ViewMessage]:
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

        seconds, nanos = divmod(pose.header.stamp_ns, 1_000_000_000)
        qz, qw = math.sin(pose.yaw_rad / 2), math.cos(pose.yaw_rad / 2)
        in_frame = PoseInFrame(frame_id=WORLD_FRAME)
        transform = FrameTransform(parent_frame_id=WORLD_FRAME, child_frame_id=CAR_FRAME)
        for message in (in_frame, transform):
            message.timestamp.seconds, message.timestamp.nanos = seconds, nanos
        in_frame.pose.position.x, in_frame.pose.position.y = pose.x_m, pose.y_m
        in_frame.pose.orientation.z, in_frame.pose.orientation.w = qz, qw
        transform.translation.x, transform.translation.y = pose.x_m, pose.y_m
        transform.rotation.z, transform.rotation.w = qz, qw
        return [self._view("car_pose", in_frame, log_time_ns), self._view("world_from_car", transform, log_time_ns)]

    def _view(self, name: str, message: Message, log_time_ns: int) -> ViewMessage:
        schema = protobuf_schema(type(message))  # type: ignore[arg-type]  # protobuf's stub: classes unhashable
        return ViewMessage(
            topic=view_topic(name), schema=schema, message=message, log_time_ns=log_time_ns, run_id=self.run_id
        )


def _event_log(event: EpisodeEvent, *, log_time_ns: int):
    """One line of the episode log (Foxglove's Log panel) for an episode event, stamped with the viewer's clock."""
    from foxglove_schemas_protobuf.Log_pb2 import Log

    detail = ""
    if event.kind == EventKind.START and event.spec is not None:
        detail = f"circuit {event.spec.circuit}, brain {event.spec.active_brain}, seed {event.spec.seed}"
    elif event.kind == EventKind.LAP:
        detail = f"lap {event.lap}"
    elif event.kind == EventKind.BRAIN_SWITCH:
        detail = f"to brain {event.brain}"
    elif event.kind == EventKind.END and event.reason is not None:
        detail = f"reason {event.reason}"
    text = " ".join(part for part in (f"episode {event.header.episode}: {event.kind}", detail, event.detail) if part)
    # An episode that did not reach its lap target stands out in the log.
    failed = event.kind == EventKind.END and event.reason not in (None, EndReason.LAPS_COMPLETED)
    log = Log(level=Log.WARNING if failed else Log.INFO, message=text, name=f"drivebench/{event.header.run_id}")
    log.timestamp.seconds, log.timestamp.nanos = divmod(log_time_ns, 1_000_000_000)
    return log


def _track_scene(spec: EpisodeSpec):
    """The circuit of an episode: road edges and centre line in the world frame, a box for the car."""
    from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    from circuits.library import CircuitError, load_circuit

    update = SceneUpdate()
    try:
        circuit = load_circuit(spec.circuit, direction=spec.direction)
    except CircuitError:
        return update  # a circuit only the simulator's machine has: record without the track
    points = circuit.centreline.points_m[:: max(1, len(circuit.centreline) // 2000)]
    normals = circuit.centreline.left_normals()[:: max(1, len(circuit.centreline) // 2000)]
    track = update.entities.add(id="track", frame_id=WORLD_FRAME)
    lines = [(points + side * circuit.road_half_width_m * normals, (0.2, 0.2, 0.2, 1.0), 0.05) for side in (-1, 1)]
    if spec.world.line in _LINE_RGBA:
        lines.append((points, _LINE_RGBA[spec.world.line], circuit.line_width_m))
    for line_points, rgba, thickness in lines:
        line = track.lines.add(type=LinePrimitive.LINE_LOOP, thickness=thickness, scale_invariant=False)
        line.pose.orientation.w = 1.0
        line.color.r, line.color.g, line.color.b, line.color.a = rgba
        for x, y in line_points:
            line.points.add(x=float(x), y=float(y), z=0.01)
    car = update.entities.add(id="car", frame_id=CAR_FRAME, frame_locked=True)
    cube = car.cubes.add()
    cube.pose.orientation.w = 1.0
    cube.pose.position.z = 0.1
    cube.size.x, cube.size.y, cube.size.z = 0.5, 0.3, 0.2
    cube.color.r, cube.color.g, cube.color.b, cube.color.a = 0.1, 0.4, 0.9, 1.0
    return update
