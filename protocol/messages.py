"""Every message that crosses the bus, as one frozen, keyword-only msgspec struct per type.

Conventions (all messages):
  * SI units and radians; the unit is in the field name (``speed_mps``, ``yaw_rad``, ``stamp_ns``).
  * Poses are ``world_from_car``: x forward / y left of the car, yaw anticlockwise from the world x axis.
  * ``Header.stamp_ns`` is *simulated* time in integer nanoseconds since the episode started; wall-clock figures are
    named ``wall_*``.
  * Every top-level message carries a versioned tag in its ``type`` field (``"drivebench.Pose.v1"``), so a payload of
    the wrong type on a key fails to decode instead of being misread.

The wire format is plain MessagePack maps (see ``protocol.codec``), readable by any msgpack client.
"""

from __future__ import annotations

import enum

import msgspec

TAG_FIELD = "type"


class Header(msgspec.Struct, frozen=True, kw_only=True):
    """Common header of every bus message.

    run_id: the run this message belongs to (also part of its key).
    episode: episode number within the run, from 0; ``seq`` restarts at 0 each episode.
    seq: sequence number of this message on its key within the episode.
    stamp_ns: simulated time of the message in ns since the episode start.
    """

    run_id: str
    episode: int
    seq: int
    stamp_ns: int


class EndReason(enum.StrEnum):
    """Why an episode ended. Every episode ends with exactly one of these."""

    LAPS_COMPLETED = "laps_completed"  # the lap target was reached
    TIME_LIMIT = "time_limit"  # max_sim_seconds of simulated time passed
    OFF_TRACK = "off_track"  # left the road (no walls): |lateral offset| beyond the road edge
    CRASH = "crash"  # touched a wall
    BRAIN_TIMEOUT = "brain_timeout"  # lock-step: the active brain did not answer a frame in time
    BRAIN_LOST = "brain_lost"  # the active brain's liveliness token vanished
    STOPPED = "stopped"  # stopped by run control (user, orchestrator)


class EventKind(enum.StrEnum):
    START = "start"
    LAP = "lap"
    BRAIN_SWITCH = "brain_switch"
    END = "end"


class CameraSpec(msgspec.Struct, frozen=True, kw_only=True):
    """The front camera, mounted on the car (car frame: x forward, y left, z up; metres, radians).

    Defaults follow Behavior Metrics' F1 car: 0.45 m ahead of the car origin, 0.10 m high, level, 90 deg horizontal
    field of view, clip planes 0.1-15 m. The vertical field of view follows from the aspect ratio.
    """

    width_px: int = 320
    height_px: int = 240
    hfov_rad: float = 1.57
    forward_m: float = 0.45
    lateral_offset_m: float = 0.0
    height_m: float = 0.10
    pitch_down_rad: float = 0.0
    near_m: float = 0.1
    far_m: float = 15.0

    def __post_init__(self) -> None:
        if not (8 <= self.width_px <= 4096 and 8 <= self.height_px <= 4096):
            raise ValueError(f"camera size must be 8..4096 px per side, got {self.width_px}x{self.height_px}")
        if not 0.1 <= self.hfov_rad <= 3.0:
            raise ValueError(f"hfov_rad must be within 0.1..3.0, got {self.hfov_rad}")
        if not 0 < self.near_m < self.far_m:
            raise ValueError(f"need 0 < near_m < far_m, got {self.near_m} and {self.far_m}")


class EpisodeSpec(msgspec.Struct, frozen=True, kw_only=True):
    """Everything that defines one episode; the same spec twice gives identical messages (lock-step).

    circuit: circuit name (``drivebench circuits list``).
    laps: lap target; the episode ends when it is reached.
    max_sim_seconds: simulated-time limit.
    step_s: simulation and control period (Behavior Metrics: 0.05 s, 20 Hz).
    seed: seeds every random generator of the episode.
    realtime: False = lock-step (wait for the brain's answer to every frame); True = free-running at wall-clock
        rate with the latest command.
    active_brain: name of the brain whose commands drive the car.
    brain_timeout_s: lock-step: wall seconds to wait for the answer to one frame before ending the episode.
    """

    circuit: str = "simple"
    laps: int = 1
    max_sim_seconds: float = 300.0
    step_s: float = 0.05
    seed: int = 0
    realtime: bool = False
    camera: CameraSpec = CameraSpec()
    active_brain: str = "explicit"
    brain_timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if self.laps < 1:
            raise ValueError(f"laps must be >= 1, got {self.laps}")
        if not self.max_sim_seconds > 0:
            raise ValueError(f"max_sim_seconds must be > 0, got {self.max_sim_seconds}")
        if not 0.001 <= self.step_s <= 1.0:
            raise ValueError(f"step_s must be within 0.001..1.0, got {self.step_s}")
        if not self.brain_timeout_s > 0:
            raise ValueError(f"brain_timeout_s must be > 0, got {self.brain_timeout_s}")

    @property
    def step_ns(self) -> int:
        return round(self.step_s * 1e9)


class CameraFrame(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.CameraFrame.v1", tag_field=TAG_FIELD):
    """One camera image. ``data`` is row-major ``height_px x width_px x 3`` uint8 in ``encoding`` (rgb8)."""

    header: Header
    width_px: int
    height_px: int
    encoding: str = "rgb8"
    data: bytes


class Pose(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.Pose.v1", tag_field=TAG_FIELD):
    """Ground-truth pose of the car (world_from_car) when frame ``header.seq`` was taken.

    speed_mps / yaw_rate_radps: the command applied over the step that *led* to this pose (0 at seq 0).
    command_latency_ns: wall time from publishing the previous frame to receiving the command that answered it
        (lock-step), 0 when not measured.
    """

    header: Header
    x_m: float
    y_m: float
    yaw_rad: float
    speed_mps: float = 0.0
    yaw_rate_radps: float = 0.0
    command_latency_ns: int = 0


class Command(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.Command.v1", tag_field=TAG_FIELD):
    """A brain's answer to one camera frame.

    header.seq: the brain's own message counter; header.stamp_ns: the sim stamp of the frame it answers.
    frame_seq: ``header.seq`` of the camera frame this command answers.
    speed_mps: forward speed along the car's x axis; yaw_rate_radps: anticlockwise yaw rate.
    inference_ns: wall time the brain spent computing this command.
    """

    header: Header
    brain: str
    frame_seq: int
    speed_mps: float
    yaw_rate_radps: float
    inference_ns: int = 0


class EpisodeEvent(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.EpisodeEvent.v1", tag_field=TAG_FIELD):
    """Episode life cycle, published by the simulator.

    START carries the spec. LAP carries ``lap`` (1-based). BRAIN_SWITCH carries ``brain``.
    END carries ``reason``, ``last_pose_seq`` (so a scorer knows when it has every pose) and ``wall_elapsed_ns``.
    """

    header: Header
    kind: EventKind
    spec: EpisodeSpec | None = None
    reason: EndReason | None = None
    lap: int = 0
    brain: str = ""
    detail: str = ""
    last_pose_seq: int = -1
    wall_elapsed_ns: int = 0


class LiveMetrics(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.LiveMetrics.v1", tag_field=TAG_FIELD):
    """Running figures of the current episode, published by the scorer a few times per second."""

    header: Header
    progress_laps: float
    laps_target: int
    completed_laps: int
    sim_time_s: float
    real_time_factor: float
    cross_track_m: float
    speed_mps: float


class EpisodeMetrics(msgspec.Struct, frozen=True, kw_only=True):
    """Final metrics of one episode.

    Behavior-Metrics-compatible (same definitions as BM's Gazebo metrics, see docs): ``completed_distance_m``,
    ``average_speed_mps``, ``percentage_completed`` (5 m in-order checkpoints), ``bm_lap_seconds``,
    ``position_deviation_mae`` / ``position_deviation_total_err`` (mean / sum of 1000**d, not metres),
    ``suddenness_distance``, ``mean_inference_time_s``.
    Beyond BM: true cross-track error in metres, every lap timed at full time resolution, arc-length progress,
    off-track events, command rate and latency, real-time factor.
    """

    sim_time_s: float
    wall_time_s: float
    real_time_factor: float
    steps: int
    completed_distance_m: float
    average_speed_mps: float
    percentage_completed: float
    bm_lap_seconds: float | None
    position_deviation_mae: float
    position_deviation_total_err: float
    suddenness_distance: float
    mean_inference_time_s: float
    progress_m: float
    progress_laps: float
    completed_laps: int
    lap_times_s: list[float]
    cross_track_mean_m: float
    cross_track_rms_m: float
    cross_track_max_m: float
    cross_track_p95_m: float
    off_track_events: int
    command_rate_hz: float
    command_latency_p50_ms: float
    command_latency_p95_ms: float
    inference_p50_ms: float
    inference_p95_ms: float


class EpisodeScore(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.EpisodeScore.v1", tag_field=TAG_FIELD):
    """The one final score of an episode, published by the scorer."""

    header: Header
    spec: EpisodeSpec
    reason: EndReason
    brain: str
    metrics: EpisodeMetrics


class ControlRequest(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.ControlRequest.v1",
                     tag_field=TAG_FIELD):
    """Run control, sent as a query to the simulator.

    action: "start" (needs ``spec``), "stop", or "status".
    """

    action: str
    spec: EpisodeSpec | None = None


class ControlReply(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.ControlReply.v1", tag_field=TAG_FIELD):
    ok: bool
    detail: str = ""
    episode: int = -1
    state: str = ""


BUS_MESSAGES: tuple[type[msgspec.Struct], ...] = (
    CameraFrame, Pose, Command, EpisodeEvent, LiveMetrics, EpisodeScore, ControlRequest, ControlReply,
)
