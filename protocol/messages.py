"""Every message that crosses the bus, as one frozen, keyword-only msgspec struct per type (the episode spec that
several of them carry, with its camera, world and noise stages, is ``protocol.episode_spec``).

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
import math

import msgspec

from protocol.episode_spec import EpisodeSpec

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
    BRAIN_INVALID = "brain_invalid"  # the active brain answered a command no car can take (see command_problem)
    DRIVER_LOST = "driver_lost"  # the process that started the episode (its driver) went away: nobody collects it
    STOPPED = "stopped"  # stopped by run control (user, orchestrator)


class EventKind(enum.StrEnum):
    START = "start"
    LAP = "lap"
    BRAIN_SWITCH = "brain_switch"
    END = "end"


class CameraFrame(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.CameraFrame.v1", tag_field=TAG_FIELD):
    """One camera image. ``data`` is row-major ``height_px x width_px x 3`` uint8 in ``encoding`` (rgb8).

    dropped: the noise injector lost this frame (``data`` is empty): a brain host answers it with its last command,
        as a real brain keeps acting on what it last saw, so lock-step goes on.
    """

    header: Header
    width_px: int
    height_px: int
    encoding: str = "rgb8"
    data: bytes
    dropped: bool = False


class Pose(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.Pose.v1", tag_field=TAG_FIELD):
    """Ground-truth pose of the car (world_from_car) when frame ``header.seq`` was taken.

    speed_mps / yaw_rate_radps: the command applied over the step that *led* to this pose (0 at seq 0).
    command_latency_ns: wall time from publishing a frame to receiving the driving brain's command that answered it
        (lock-step: the previous frame; real time: the newest command that arrived since the previous pose), 0 = none
        (lock-step), 0 when not measured.
    """

    header: Header
    x_m: float
    y_m: float
    yaw_rad: float
    speed_mps: float = 0.0
    yaw_rate_radps: float = 0.0
    command_latency_ns: int = 0


# The largest command a car takes, either sign: far beyond any car here (F1 cars drive up to ~24 m/s), so an answer
# in km/h or degrees still drives (``brains check`` flags those), while NaN-like garbage such as 1e300 ends the
# episode ``brain_invalid`` instead of overflowing the physics or the metrics.
MAX_COMMAND_SPEED_MPS = 100.0
MAX_COMMAND_YAW_RATE_RADPS = 100.0


def command_problem(*, speed_mps: float, yaw_rate_radps: float) -> str:
    """Why no car can take this command (``"speed_mps=nan (not a finite number)"``), or "" when it can."""
    for name, value, limit, unit in (
        ("speed_mps", speed_mps, MAX_COMMAND_SPEED_MPS, "m/s"),
        ("yaw_rate_radps", yaw_rate_radps, MAX_COMMAND_YAW_RATE_RADPS, "rad/s"),
    ):
        if not math.isfinite(value):
            return f"{name}={value} (not a finite number)"
        if abs(value) > limit:
            return f"{name}={value} (beyond +-{limit:g} {unit})"
    return ""


class Command(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.Command.v1", tag_field=TAG_FIELD):
    """A brain's answer to one camera frame.

    header.seq: the brain's own message counter; header.stamp_ns: the sim stamp of the frame it answers.
    frame_seq: ``header.seq`` of the camera frame this command answers.
    speed_mps: forward speed along the car's x axis; yaw_rate_radps: anticlockwise yaw rate; each within
        +-MAX_COMMAND_SPEED_MPS / +-MAX_COMMAND_YAW_RATE_RADPS (:func:`command_problem`).
    inference_ns: wall time the brain spent computing this command.
    model_inference_ns: the brain's own timing of its model for this command (``Action.model_inference_s``, BM's
        ``inference_times``), 0 = the brain keeps none.
    suddenness: the brain's own suddenness value for this command (``Action.suddenness``), None = it keeps none.
    gpu: the brain runs its model on a GPU (its ``gpu_inference`` attribute; BM's ``gpu_inference``).
    invalid: non-empty when the brain's answer was one no car can take (NaN, infinite, beyond the limits): what it
        was, e.g. ``"speed_mps=nan (not a finite number)"``. Its speed and yaw rate are then 0 and mean nothing;
        the brain host sends it so that the simulator ends the episode ``brain_invalid`` at once, with the value,
        instead of waiting for an answer that never comes (a NaN cannot cross the bus).
    shadow: whether its brain host was started as a shadow (to be compared with the driver, never to drive).
    host: the identity of the brain host process that sent it (two processes of one name are two hosts).
    """

    header: Header
    brain: str
    frame_seq: int
    speed_mps: float
    yaw_rate_radps: float
    inference_ns: int = 0
    shadow: bool = False
    host: str = ""
    invalid: str = ""
    model_inference_ns: int = 0
    suddenness: float | None = None
    gpu: bool = False

    def problem(self) -> str:
        """Why this command cannot drive a car ("" when it can), whoever sent it."""
        return self.invalid or command_problem(speed_mps=self.speed_mps, yaw_rate_radps=self.yaw_rate_radps)


class EpisodeEvent(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.EpisodeEvent.v1", tag_field=TAG_FIELD):
    """Episode life cycle, published by the simulator.

    START carries the spec. LAP carries ``lap`` (1-based). BRAIN_SWITCH carries the new driving ``brain`` and the
    previous one in ``detail``; its stamp is that of the first frame whose command comes from the new brain.
    END carries ``reason``, ``last_pose_seq`` (so a scorer knows when it has every pose) and ``wall_elapsed_ns``;
    with reason ``brain_invalid``, ``detail`` names the brain and its refused answer.
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


class BrainEvent(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.BrainEvent.v1", tag_field=TAG_FIELD):
    """What a brain host is told of an episode's life cycle (``keys.brain_events``), published by the simulator beside
    each START and END of ``keys.events``.

    Enough to reset a brain as every other brain of the run was and to pick the camera stream it drives from; nothing
    of the conditions it is scored on. The START of ``keys.events`` carries the whole spec (the circuit's name, and so
    a drawn circuit's generator seed; the world, the start, the direction, the noise), which a challenge's hidden
    part must keep from the brains it scores: a sandboxed brain may read this key and not that one.

    START carries ``seed`` (what the brain's ``reset`` gets), ``realtime`` (lock-step or free-running) and
    ``perturbed`` (a noise injector perturbs the frames: an ``auto`` brain drives from its stream). END says the
    episode is over (frames of it may still trail in).
    """

    header: Header
    kind: EventKind  # START or END
    seed: int = 0
    realtime: bool = False
    perturbed: bool = False


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
    ``command_latency_*_ms``: wall time from a frame going out to the arrival of the driving brain's command that
    answers it (both modes; in real time only commands that name their frame count); None when none was measured.

    BM's other keys, by BM's definitions: ``circuit_diameter_m`` (the lap length, only when BM's percentage says a
    lap was completed, else None); ``frame_rate_hz`` (frames / simulated seconds); ``mean_brain_iterations_real_time_s``
    (mean wall time of the brain's step, as the host times it) and its inverse ``..._frequency_real_time_hz``;
    ``mean_brain_iterations_simulated_time_s`` (simulated seconds per command) and its inverse; ``target_...`` (BM's
    ``1000 / PilotTimeCycle / round(RTF, 2)`` with the step as PilotTimeCycle: what BM's wall-clock pacing would aim
    at; drivebench's lock-step does not pace by it); ``gpu_inference`` (the driver ran its model on a GPU).
    Where drivebench's definition differs from BM's, BM's is beside it: ``mean_inference_time_s`` and the
    ``inference_p*`` time the brain's whole step (a BM brain's own rain or crop included), ``bm_mean_inference_time_s``
    is BM's mean of the brain's own ``inference_times[10:-10]`` (None when the brain keeps none);
    ``suddenness_distance`` is computed from the commands, ``bm_suddenness_distance`` is the mean of the brain's own
    list (BM's brains append one value per step from their normalised outputs; None when it keeps none).
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
    command_latency_p50_ms: float | None  # None: not measured (no command matched to its frame)
    command_latency_p95_ms: float | None
    inference_p50_ms: float
    inference_p95_ms: float
    # Behavior Metrics' keys drivebench measured no other way (defaults: a score written before them still reads).
    circuit_diameter_m: float | None = None
    frame_rate_hz: float = 0.0
    mean_brain_iterations_real_time_s: float = 0.0
    brain_iterations_frequency_real_time_hz: float = 0.0
    mean_brain_iterations_simulated_time_s: float = 0.0
    brain_iterations_frequency_simulated_time_hz: float = 0.0
    target_brain_iterations_simulated_time_hz: float = 0.0
    gpu_inference: bool = False
    bm_mean_inference_time_s: float | None = None
    bm_suddenness_distance: float | None = None


class BrainSwitch(msgspec.Struct, frozen=True, kw_only=True):
    """One live switch of the driving brain within an episode (from a BRAIN_SWITCH event).

    stamp_ns: sim stamp of the first frame whose command came from ``to_brain``.
    seq: that frame's sequence number (camera frame and pose ``header.seq``).
    from_brain / to_brain: bus names of the brain that drove before and of the one that drives from ``seq`` on.
    """

    stamp_ns: int
    seq: int
    from_brain: str
    to_brain: str


class ShadowDistance(msgspec.Struct, frozen=True, kw_only=True):
    """How far a shadow brain's commands were from the driving brain's, over the frames both answered.

    A shadow is a brain host started as one (``--shadow``, a matrix's ``shadows:``): it receives the same frames as
    the driver and publishes commands that drive nothing. Brains swapped in or out are not shadows.

    brain: the shadow's bus name. host: its process (``Command.host``): two shadows of one name are two entries.
    frames: frames both the shadow and the driver answered.
    speed_mae_mps: mean |v_shadow - v_driver|. yaw_rate_mae_radps / yaw_rate_rmse_radps / yaw_rate_max_abs_radps:
        mean, root-mean-square and largest |w_shadow - w_driver|. All 0.0 when ``frames`` is 0.
    """

    brain: str
    frames: int
    speed_mae_mps: float
    yaw_rate_mae_radps: float
    yaw_rate_rmse_radps: float
    yaw_rate_max_abs_radps: float
    host: str = ""


class EpisodeScore(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.EpisodeScore.v1", tag_field=TAG_FIELD):
    """The one final score of an episode, published by the scorer.

    brain: the brain driving at the end of the episode. switches: live brain switches, in order. shadows: one
    entry per shadow brain host (see :class:`ShadowDistance`). detail: what the reason alone does not say (the
    END event's: for ``brain_invalid``, the brain and its refused answer), else "".
    """

    header: Header
    spec: EpisodeSpec
    reason: EndReason
    brain: str
    metrics: EpisodeMetrics
    switches: list[BrainSwitch] = []
    shadows: list[ShadowDistance] = []
    detail: str = ""


class ControlRequest(
    msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.ControlRequest.v1", tag_field=TAG_FIELD
):
    """Run control, sent as a query to the simulator (``keys.sim_control``) or to one brain host
    (``keys.brain_control``).

    action, simulator: "start" (needs ``spec``), "stop", "status", or "switch" (needs ``brain``: make that alive
        brain the driving one from the next frame on). Brain host: "status" or "stop" (the host exits cleanly).
    driver: with "start": the name of the starting process's liveliness token (``keys.alive(run, "driver",
        driver)``); when it is gone for ``DRIVER_GRACE_S`` the simulator ends the episode ``driver_lost`` (a dead
        man's switch: an episode whose driver died would otherwise run to its time limit and block the next one).
        Empty: no watch.
    Recorder (``keys.recorder_control``): "status"; "open" (needs ``output``, an absolute ``.mcap`` path; ``attach``:
        text files stored in its metadata) starts writing the run into a new file; "close" finishes the file being
        written (what is still on its way, until quiet, then summary and index) and records nothing until the next
        "open". Both are carried out by the recorder's writing thread: poll "status" until ``output`` says it is done.
    """

    action: str
    spec: EpisodeSpec | None = None
    brain: str = ""
    driver: str = ""
    output: str = ""
    attach: list[str] = []


class ServerState(enum.StrEnum):
    """The state of the process that answers run control, as a :class:`ControlReply` reports it."""

    IDLE = "idle"  # simulator: no episode, ready to start one; recorder: between two files
    STARTING = "starting"  # simulator: a start was accepted, the episode's START is not out yet
    RUNNING = "running"  # simulator: an episode runs
    SERVING = "serving"  # brain host: answering frames; recorder: writing a file
    STOPPING = "stopping"  # brain host: asked to stop, exiting cleanly


class ReplyCode(enum.StrEnum):
    """Why a :class:`ControlReply` is what it is: ``ok``, or the reason a request was refused. Processes decide on
    this code, never on ``detail`` (human text that may be reworded)."""

    OK = "ok"  # accepted
    BUSY = "busy"  # start: the simulator is starting or running another episode (retry later)
    NOT_ALIVE = "not_alive"  # start, switch: the named brain has no liveliness token (yet: it may be on its way)
    NOT_RUNNING = "not_running"  # switch: no episode is running
    ALREADY_ACTIVE = "already_active"  # switch: the named brain already drives
    BAD_CIRCUIT = "bad_circuit"  # start: the spec's circuit is unknown or cannot be loaded, or start_m is not on it
    RENDERER_UNAVAILABLE = "renderer_unavailable"  # start: the spec's renderer cannot run on this simulator
    BAD_REQUEST = "bad_request"  # the request lacks what its action needs (start without spec, switch without brain)
    UNKNOWN_ACTION = "unknown_action"  # the server does not know the action


class ControlReply(msgspec.Struct, frozen=True, kw_only=True, tag="drivebench.ControlReply.v1", tag_field=TAG_FIELD):
    """Answer to a :class:`ControlRequest`.

    ok: the request was accepted. code: ``ok``, or why it was refused (:class:`ReplyCode`: decide on this, never on
    ``detail``). detail: human text only (what the code alone does not say: which brain, which circuit). state: the
    server's state (:class:`ServerState`). episode: the current (or next) episode number, -1 before the first.
    active_brain: the brain driving now (simulator). spec: the running episode's spec (simulator "status" while an
    episode runs), so a process that joined mid-episode can set up as the episode's START told the others.
    output: recorder: the file being written now ("" between a "close" and the next "open").
    """

    ok: bool
    state: ServerState
    # Defaults to ok so that a brain host written before codes existed still decodes (it only ever refuses
    # unknown actions, and nothing decides on a brain host's refusal beyond ``ok``).
    code: ReplyCode = ReplyCode.OK
    detail: str = ""
    episode: int = -1
    active_brain: str = ""
    spec: EpisodeSpec | None = None
    output: str = ""


# A message published on a run's keys, with its header: what the recorder records and the live view shows. A
# static union, so that code taking one reads ``.header`` checked (msgspec decodes the same union by its tags).
RunMessage = CameraFrame | Pose | Command | EpisodeEvent | LiveMetrics | EpisodeScore
# Everything published on a run's keys (what a subscription to ``keys.run_all`` decodes): the recorded messages and
# the brains' copy of the episode events, which is derived from ``sim/events`` and so not recorded.
AnyRunMessage = RunMessage | BrainEvent

BUS_MESSAGES: tuple[type[msgspec.Struct], ...] = (
    CameraFrame,
    Pose,
    Command,
    EpisodeEvent,
    BrainEvent,
    LiveMetrics,
    EpisodeScore,
    ControlRequest,
    ControlReply,
)
