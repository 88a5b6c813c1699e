"""The brain host process (``python -m brains --brain NAME``): camera frames in, commands out.

In a real-time episode it takes only the newest frame (a brain slower than the camera skips frames instead of lagging
behind). In lock-step it answers every frame in order, up to ``FRAME_BACKLOG`` behind: the driving brain is never
behind (the simulator waits for it), and a shadow brain, which the simulator does not wait for, still sees the same
frames in the same order as the driver, which a brain with memory needs for its commands to be comparable. It calls
the brain, and publishes a Command stamped with the frame it answers and the inference time. A new episode number on
the frames resets the brain, seeded from the episode's START as brains are told it (``keys.brain_events``: the seed
and mode, none of the episode's conditions). A frame it has already answered (the simulator
repeats a frame nobody answered) gets the same command again without calling the brain twice. A frame the noise
injector dropped gets the last command again (the car keeps doing what the brain last decided), stamped for the new
frame, without calling the brain.

Each host serves its own control key (``keys.brain_control``): "status", and "stop", which makes it exit cleanly
(code 0), so a live brain swap can retire the old brain. A host that joins in the middle of an episode (it never saw
the START event) asks the simulator's read-only status (``keys.sim_status``, which every identity may query under
access control) for the running episode's spec, so it is seeded as the others were.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
import uuid
from typing import Any

import msgspec

from brains.base import Brain, GroundTruth, Observation
from brains.registry import BrainOptionsError, UnknownBrainError, brain_names, bus_name, make_brain
from brains.sandbox_exit import exit_for
from protocol import codec, keys
from protocol.bus import Bus, BusConfig, Inbox, Traffic
from protocol.deploy.runtime import stop_requested
from protocol.episode_spec import EpisodeSpec
from protocol.episodes import BrainStarts, EpisodeStarts, brain_event, running_spec, start_event
from protocol.images import FrameReader
from protocol.messages import (
    BrainEvent,
    CameraFrame,
    Command,
    ControlReply,
    ControlRequest,
    EventKind,
    Header,
    Pose,
    ReplyCode,
    ServerState,
    command_problem,
)

log = logging.getLogger("drivebench.brain")

FRAME_BACKLOG = 64  # lock-step: frames kept for a brain that lags (a shadow); older ones are skipped
STOP_LINGER_S = 0.2  # after a stop request: time for the reply to leave before the session closes
CAMERA_SOURCES = ("auto", "perturbed", "raw")
GROUND_TRUTH_WAIT_S = 2.0  # a privileged brain: how long a frame waits for its pose (published just after it)
POSES_KEPT = 256  # a privileged brain: poses kept, by (episode, seq), for frames still to come


class BrainHostConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of one brain host process.

    brain: registered brain name (``explicit``, ``constant``, ...).
    name: this brain's name on the bus (its command key and liveliness token); defaults to ``brain``.
    options: keyword options for the brain's constructor (e.g. ``{speed_mps: 2.0}`` for ``constant``).
    camera: which stream to drive from: ``auto`` (the default: per episode, the simulator's frames when the episode
        has no noise, else the noise injector's; identity noise forwards the same bytes, so this saves a hop and
        changes nothing the brain sees; once a frame of the episode came on its stream the other one is dropped
        unread until the episode's END), ``perturbed`` (always the noise injector's) or ``raw`` (always the
        simulator's, for a stack without a noise injector).
    orphan_timeout_s: exit (code 0) when the run has had no simulator for this long: nothing a stack or a swap
        starts outlives its stack. 0 (default): wait for a simulator forever (services started by hand, compose).
    shadow: started as a shadow (``drivebench run --shadow``, a matrix's ``shadows:``): its commands say so, and the
        score reports how far they were from the driver's. A brain that drives, or waits to be swapped in, is not.
    sandboxed: runs inside the launcher's sandbox (``orchestrator.stack.sandbox``): an error of the brain's that is
        the sandbox's wall (a limit, a refused write or connection) exits with its ``brains.sandbox_exit`` code, so
        that the launcher types the failure by the code.
    """

    bus: BusConfig = BusConfig()
    run_id: str = "default"
    brain: str = "explicit"
    name: str = ""
    options: dict[str, Any] = {}
    camera: str = "auto"
    orphan_timeout_s: float = 0.0
    shadow: bool = False
    sandboxed: bool = False

    def __post_init__(self) -> None:
        if self.orphan_timeout_s < 0:
            raise ValueError(f"orphan_timeout_s must be >= 0, got {self.orphan_timeout_s}")
        if self.camera not in CAMERA_SOURCES:
            raise ValueError(f"camera must be {', '.join(CAMERA_SOURCES)}, got {self.camera!r}")

    @property
    def bus_name(self) -> str:
        return self.name or bus_name(self.brain)


class BrainHost:
    def __init__(self, config: BrainHostConfig, bus: Bus, brain: Brain):
        self.config = config
        self.brain = brain
        self.bus = bus
        self.name = keys.check_name(config.bus_name, what="brain name")
        run = config.run_id
        self._frames = Inbox(keep_last=FRAME_BACKLOG)
        self._sources = {  # the camera streams it may drive from: "raw" (simulator) and "perturbed" (noise)
            source: bus.subscribe(key, CameraFrame, inbox=self._frames)
            for source, key in (("raw", keys.camera_raw(run)), ("perturbed", keys.camera_perturbed(run)))
            if config.camera in (source, "auto")
        }
        self._source_keys = {source: subscription.key for source, subscription in self._sources.items()}
        self._source = next(iter(self._sources))  # the stream of the current episode
        self._realtime = False  # the current episode's mode: real-time takes the newest frame only
        # Its seed and mode from the brains' events (keys.brain_events), which carry none of the episode's conditions:
        # a sandboxed brain may read nothing else.
        self._starts = BrainStarts(bus, run, on_event=self._on_event if config.camera == "auto" else None)
        self._commands = bus.publisher(keys.command(run, self.name), Command, Traffic.COMMANDS)
        self._episode = -1
        self._last: Command | None = None
        # This process, in every command: the scorer keeps two shadows of one name apart by it.
        self._host_id = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self._seq = 0
        self._reader = FrameReader(log)
        self._stop = threading.Event()
        # A privileged brain (the expert) gets the simulator's ground-truth pose of every frame, and the circuit and
        # direction of the episode's spec with it.
        privileged = getattr(brain, "needs_ground_truth", False)
        self._poses = bus.subscribe(keys.pose(run), Pose) if privileged else None
        self._specs = EpisodeStarts(bus, run) if privileged else None
        self._spec: EpisodeSpec | None = None
        self._pose_by_frame: dict[tuple[int, int], Pose] = {}
        bus.serve(keys.brain_control(run, self.name), self._on_control)
        self._simulators = bus.watch_alive(keys.alive_role(run, "simulator")) if config.orphan_timeout_s else None
        self._simulator_seen = time.monotonic()
        # Declared last: whoever sees this token can rely on the subscriptions above.
        bus.declare_alive(keys.alive(run, "brain", self.name))

    def _on_event(self, event: BrainEvent) -> None:
        """Callback thread: at the end of an episode let every stream in again, so that the next episode's first
        frame gets through whichever stream it drives from."""
        if event.kind == EventKind.END:
            for subscription in self._sources.values():
                subscription.open = True

    def _drive_only_from_source(self) -> None:
        """Main loop, once a frame of the current episode came on its stream: drop the other copies unread."""
        for name, subscription in self._sources.items():
            subscription.open = name == self._source

    def serve_forever(self) -> None:
        """Answer frames until a "stop" request (or, with ``orphan_timeout_s``, until the run has lost its simulator);
        then return (the process exits with code 0)."""
        log.info("brain %s (%s) ready on run %s", self.name, self.config.brain, self.config.run_id)
        while not self._stop.is_set() and not self._orphaned() and not stop_requested():
            received = self._frames.recv(timeout_s=0.1)
            if received is not None and self._realtime and (newer := self._frames.drain()):
                received = newer[-1]
            if received is not None and not self._stop.is_set():
                self.answer(received.message, key=received.key)
        time.sleep(STOP_LINGER_S)
        if self._stop.is_set():
            log.info("brain %s stopped on request", self.name)

    def _orphaned(self) -> bool:
        """Whether the run has had no simulator for ``orphan_timeout_s`` (only when that watch is on)."""
        if self._simulators is None:
            return False
        now = time.monotonic()
        if self._simulators.alive():
            self._simulator_seen = now
            return False
        if now - self._simulator_seen < self.config.orphan_timeout_s:
            return False
        log.info(
            "no simulator on run %s for %.0f s: its stack is gone, exiting",
            self.config.run_id,
            self.config.orphan_timeout_s,
        )
        return True

    def _on_control(self, payload: bytes) -> bytes:
        """The control queryable (Zenoh's callback thread: never block)."""
        request = codec.decode(payload, ControlRequest)
        if request.action == "status":
            return codec.encode(
                ControlReply(ok=True, state=ServerState.SERVING, episode=self._episode, active_brain=self.name)
            )
        if request.action == "stop":
            log.info("stop requested over the bus")
            self._stop.set()
            return codec.encode(ControlReply(ok=True, state=ServerState.STOPPING, episode=self._episode))
        return codec.encode(
            ControlReply(
                ok=False,
                code=ReplyCode.UNKNOWN_ACTION,
                detail=f"unknown action {request.action!r} (brain hosts know status and stop)",
                state=ServerState.SERVING,
                episode=self._episode,
            )
        )

    def _from_source(self, key: str) -> bool:
        """Whether a frame that came on ``key`` is on the current episode's stream ("" counts as on it)."""
        return not key or key == self._source_keys[self._source]

    def _seed_for(self, episode: int) -> int:
        """The episode's seed (and mode) from its START event, or from the simulator's status for a late joiner."""
        start = self._starts.start(episode)
        spec = self._specs.spec(episode) if self._specs is not None else None  # a privileged brain's: the conditions
        if start is None or (self._specs is not None and spec is None):
            # Missed (a late joiner): the simulator's status has it. A sandboxed brain may not ask: it gets seed 0.
            spec = running_spec(self.bus, self.config.run_id, episode)
            if start is None and spec is not None:
                start = brain_event(start_event(self.config.run_id, episode, spec))
        self._spec = spec if self._specs is not None else None
        if self.config.camera == "auto":
            self._source = source_of(start)
            self._sources[self._source].open = True  # in case its first frame was shut out: the resend gets in
        if start is None:
            log.warning("no start event for episode %d: resetting the brain with seed 0", episode)
            return 0
        self._realtime = start.realtime
        return start.seed

    def answer(self, frame: CameraFrame, *, key: str = "") -> None:
        """Answer one frame with a command; ``key``: the stream it came on ("" = the current episode's)."""
        h = frame.header
        if h.episode <= self._episode and not self._from_source(key):
            # The other copy of a frame (a late joiner lets both in until it knows the episode), or one of an earlier
            # episode that trailed in after the next one began (a noise injector running behind).
            return
        if self._last is not None and (self._last.header.episode, self._last.frame_seq) == (h.episode, h.seq):
            self._commands.publish(self._last)  # a repeated frame: same answer, the brain sees each frame once
            return
        image = None if frame.dropped else self._reader.image(frame)
        if image is None and not frame.dropped:
            return  # unreadable: ignored (logged by the reader), and no reason to start a new episode
        if h.episode != self._episode:
            self._episode = h.episode
            self._last = None
            self.brain.reset(seed=self._seed_for(h.episode))
            if not self._from_source(key):
                return
        if len(self._sources) > 1:
            self._drive_only_from_source()
        invalid = ""
        own: dict[str, Any] = {}  # what the brain measures itself (BM's inference_times, suddenness_distance)
        if image is None:  # lost on the way: keep doing what the brain last decided
            speed_mps = self._last.speed_mps if self._last is not None else 0.0
            yaw_rate_radps = self._last.yaw_rate_radps if self._last is not None else 0.0
            inference_ns = 0
        else:
            truth = self._ground_truth(h.episode, h.seq) if self._poses is not None else None
            started = time.perf_counter_ns()
            action = self.brain.act(Observation(image_rgb=image, stamp_ns=h.stamp_ns, seq=h.seq, ground_truth=truth))
            inference_ns = time.perf_counter_ns() - started
            speed_mps, yaw_rate_radps, invalid = self._checked(action, frame_seq=h.seq, episode=h.episode)
            own = _own_measures(action)
        command = Command(
            header=Header(run_id=self.config.run_id, episode=h.episode, seq=self._seq, stamp_ns=h.stamp_ns),
            brain=self.name,
            frame_seq=h.seq,
            speed_mps=speed_mps,
            yaw_rate_radps=yaw_rate_radps,
            inference_ns=inference_ns,
            invalid=invalid,
            shadow=self.config.shadow,
            host=self._host_id,
            gpu=bool(getattr(self.brain, "gpu_inference", False)),
            **own,
        )
        self._seq += 1
        self._commands.publish(command)
        self._last = command

    def _checked(self, action: Any, *, frame_seq: int, episode: int) -> tuple[float, float, str]:
        """(speed, yaw rate, "") of a command a car can take; else (0, 0, what was wrong), logged: the simulator
        ends the episode ``brain_invalid`` on it. Refused here, where the value enters: a NaN cannot even cross the
        bus (``protocol.codec``), and a huge finite value would overflow the physics or the metrics downstream."""
        try:
            speed_mps, yaw_rate_radps = float(action.speed_mps), float(action.yaw_rate_radps)
        except (TypeError, ValueError, OverflowError):
            problem = f"speed_mps={action.speed_mps!r}, yaw_rate_radps={action.yaw_rate_radps!r} (not numbers)"
        else:
            problem = command_problem(speed_mps=speed_mps, yaw_rate_radps=yaw_rate_radps)
            if not problem:
                return speed_mps, yaw_rate_radps, ""
        log.warning("brain %s answered frame %d of episode %d with %s: refused", self.name, frame_seq, episode, problem)
        return 0.0, 0.0, problem

    def _ground_truth(self, episode: int, seq: int) -> GroundTruth | None:
        """The pose of frame (episode, seq), waiting up to GROUND_TRUTH_WAIT_S for it; None (logged) without it."""
        if self._poses is None:
            return None
        deadline = time.monotonic() + GROUND_TRUTH_WAIT_S
        while (episode, seq) not in self._pose_by_frame:
            received = self._poses.recv(timeout_s=max(0.0, deadline - time.monotonic()))
            if received is None:
                log.warning("no ground-truth pose for frame %d of episode %d", seq, episode)
                return None
            pose = received.message
            self._pose_by_frame[(pose.header.episode, pose.header.seq)] = pose
            while len(self._pose_by_frame) > POSES_KEPT:
                self._pose_by_frame.pop(next(iter(self._pose_by_frame)))
        pose = self._pose_by_frame[(episode, seq)]
        spec = self._spec or EpisodeSpec()
        return GroundTruth(
            x_m=pose.x_m, y_m=pose.y_m, yaw_rad=pose.yaw_rad, circuit=spec.circuit, direction=spec.direction
        )


def source_of(start: BrainEvent | None) -> str:
    """The camera stream an ``auto`` brain drives from in an episode: the simulator's when it has no noise (the
    noise injector would forward the same bytes), else the noise injector's; the latter when the start is unknown."""
    return "raw" if start is not None and not start.perturbed else "perturbed"


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import load_service_config, log_config, run_service, service_parser

    parser = service_parser("drivebench brain host: camera frames in, driving commands out")
    parser.add_argument("--brain", help=f"brain to run ({', '.join(brain_names())})")
    parser.add_argument("--name", help="name on the bus (default: the brain's name)")
    parser.add_argument(
        "--weights",
        metavar="CKPT",
        help="neural brains: checkpoint or exported ONNX file (= --set options.weights=CKPT; empty: "
        "the shipped weights of that network, if any)",
    )
    args = parser.parse_args(argv)

    def run() -> int:
        config = load_service_config(
            BrainHostConfig,
            args,
            extra={"brain": args.brain, "name": args.name, "options.weights": args.weights or None},
        )
        log_config(config)
        try:
            return _host(config)
        except Exception as error:
            wall = exit_for(error) if config.sandboxed else None
            if wall is None:
                raise
            # The brain's own code met the sandbox's wall: say which by the exit code, the traceback in the log.
            log.error("brain %s stopped by the sandbox (%s)", config.bus_name, wall.name.lower(), exc_info=error)
            return int(wall)

    return run_service("brain", run)


def _host(config: BrainHostConfig) -> int:
    """Make the brain, then serve it on the bus until stopped (exit code 0)."""
    from protocol.deploy.runtime import UserError

    try:
        brain = make_brain(config.brain, **config.options)
    except (UnknownBrainError, BrainOptionsError) as error:
        raise UserError(str(error)) from None
    except TypeError as error:
        raise UserError(f"bad options for brain {config.brain!r}: {error}") from None
    with Bus(config.bus, name=f"brain-{config.bus_name}") as bus:
        join_bus = getattr(brain, "join_bus", None)
        if callable(join_bus):  # a brain that talks on the bus itself (ros2: a ROS 2 node)
            join_bus(bus)
        BrainHost(config, bus, brain).serve_forever()
    return 0


def _own_measures(action: Any) -> dict[str, Any]:
    """The Command fields of what the brain measured itself (optional ``Action`` fields): a value that is not a
    finite non-negative number is left out (it would not cross the bus, and it is the brain's own bookkeeping, not
    its command)."""
    own: dict[str, Any] = {}
    inference_s = getattr(action, "model_inference_s", None)
    if isinstance(inference_s, int | float) and math.isfinite(inference_s) and inference_s >= 0:
        own["model_inference_ns"] = max(1, round(inference_s * 1e9))
    suddenness = getattr(action, "suddenness", None)
    if isinstance(suddenness, int | float) and math.isfinite(suddenness) and suddenness >= 0:
        own["suddenness"] = float(suddenness)
    return own
