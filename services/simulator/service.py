"""The simulator process: wires :class:`EpisodeSim` to the bus.

Publishes camera frames (ground truth), poses and episode events; applies the active brain's commands; answers run
control queries (start / stop / status / switch), and status queries on a read-only key of their own. Lock-step by
default: publish frame n, wait for the active brain's command for frame n, step. A brain that does not answer in
time, or whose liveliness token vanishes, ends the episode with a typed reason; nothing stalls silently. So does a
command no car can take (``Command.problem``: a brain host's refusal, or a huge value from any client), as
``brain_invalid``, before it reaches the physics.

Live brain switch: "switch" makes another alive brain the active one at once; the command for the frame being
waited for (lock-step) or applied next (real-time) comes from it, even when it arrived before the switch (the
commands of the current frame are kept per brain). A BRAIN_SWITCH event with that frame's stamp records it, so no
step is lost and the episode goes on.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import msgspec

from circuits import Circuit, CircuitError, load_circuit
from protocol import codec, keys
from protocol.bus import Bus, BusConfig, Inbox, Received, Traffic
from protocol.deploy.runtime import stop_requested
from protocol.episode_spec import EpisodeSpec
from protocol.episodes import brain_event
from protocol.images import image_frame
from protocol.messages import (
    BrainEvent,
    CameraFrame,
    Command,
    ControlReply,
    ControlRequest,
    EndReason,
    EpisodeEvent,
    EventKind,
    Header,
    Pose,
    ReplyCode,
    ServerState,
)
from services.simulator.episode import EpisodeSim, SceneCache, StepResult
from services.simulator.gl_scene import egl_unavailable_reason
from services.simulator.renderers import resolve_spec

log = logging.getLogger("drivebench.simulator")

# Lock-step: if a frame has had no answer for this long, publish it again (same seq). It covers a brain whose
# subscription was not yet known to this session when the frame went out; brain hosts answer a repeated frame
# with the command they already computed.
RESEND_AFTER_S = 1.0
DRIVER_GRACE_S = 1.5  # an episode's driver gone this long ends it (slack for its token to reach us at the start)
REALTIME_LATENCY_FRAMES = 200  # real time: frames remembered for matching late commands (10 s at 20 Hz)


class SimulatorConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of the simulator process.

    run_id: the run this simulator serves (every key carries it).
    name: this process's name in its liveliness token.
    subscriber_wait_s: at episode start, how long to wait for someone to subscribe to the camera and the events.
    """

    bus: BusConfig = BusConfig()
    run_id: str = "default"
    name: str = "sim"
    subscriber_wait_s: float = 10.0


class SimulatorService:
    def __init__(self, config: SimulatorConfig, bus: Bus):
        self.config = config
        self.bus = bus
        run = config.run_id
        self._frames_latest = bus.publisher(keys.camera_raw(run), CameraFrame, Traffic.FRAMES)
        self._frames_lossless = bus.publisher(keys.camera_raw(run), CameraFrame, Traffic.FRAMES_LOSSLESS)
        self._frames = self._frames_lossless
        self._poses = bus.publisher(keys.pose(run), Pose, Traffic.EVENTS)
        self._events = bus.publisher(keys.events(run), EpisodeEvent, Traffic.EVENTS)
        self._brain_events = bus.publisher(keys.brain_events(run), BrainEvent, Traffic.EVENTS)
        self._commands = Inbox()
        bus.subscribe(keys.commands_all(run), Command, inbox=self._commands)
        self._alive_brains: set[str] = set()
        self._alive_drivers: set[str] = set()
        self._driver = ""  # the running episode's driver (ControlRequest.driver), "" = not watched
        self._driver_missing_since: float | None = None
        self._alive_lock = threading.Lock()  # guards the alive brains, the active brain and its switches
        self._active_brain = ""
        self._switches: list[tuple[str, str]] = []  # (from, to) accepted, not yet announced by an event
        self._spec: EpisodeSpec | None = None
        self._event_seq = 0
        self._end_detail = ""  # the END event's detail of the running episode (brain_invalid: the refused answer)
        bus.watch_alive(keys.alive_all(run), self._on_liveliness)
        self._requests: queue.Queue[tuple[EpisodeSpec, Circuit, str]] = queue.Queue()
        self._state = ServerState.IDLE
        self._episode = -1
        self._stop_requested = threading.Event()
        self._scenes = SceneCache()
        bus.serve(keys.sim_control(run), self._on_control)
        # Status alone on its own key: access control lets every process read it (a late-joining brain host, scorer
        # or recorder) while only the orchestrator may use sim/control; "status" there still works too.
        bus.serve(keys.sim_status(run), self._on_status)
        # Whether --renderer gl can run here, probed now in the thread that will render (a GL context is bound to
        # its thread), before the liveliness token says we are ready: a start asking for gl is refused with the
        # reason rather than accepted and failed.
        self._gl_unavailable = egl_unavailable_reason()
        bus.declare_alive(keys.alive(run, "simulator", config.name))

    # -- callbacks (Zenoh's callback thread: never block) --

    def _on_liveliness(self, key: str, alive: bool) -> None:
        try:
            _, role, name = keys.parse_alive(key)
        except ValueError:
            return
        if role not in ("brain", "driver"):
            return
        with self._alive_lock:
            names = self._alive_brains if role == "brain" else self._alive_drivers
            (names.add if alive else names.discard)(name)

    def _driver_lost(self) -> bool:
        """Whether the running episode's driver has been gone (or never seen) for ``DRIVER_GRACE_S``."""
        if not self._driver:
            return False
        with self._alive_lock:
            present = self._driver in self._alive_drivers
        now = time.monotonic()
        if present:
            self._driver_missing_since = None
            return False
        if self._driver_missing_since is None:
            self._driver_missing_since = now
        return now - self._driver_missing_since > DRIVER_GRACE_S

    def _on_own_key(self, received: Received) -> bool:
        """Whether a command came on its own brain's key: a brain allowed to publish on its key (access control
        works on keys) must not answer for another brain by naming it in the message."""
        if keys.brain_of_command_key(received.key) == received.message.brain:
            return True
        self.bus.rejects.reject(
            received.key,
            ValueError(f"command names brain {received.message.brain!r}, not the brain of its key"),
            source=keys.commands_all(self.config.run_id),  # logged per subscription, as undecodable ones are
        )
        return False

    def _brain_alive(self, name: str) -> bool:
        with self._alive_lock:
            return name in self._alive_brains

    def _active(self) -> str:
        with self._alive_lock:
            return self._active_brain

    def _active_alive(self) -> bool:
        """Whether the active brain is alive; read together, so a switch never races a brain's departure."""
        with self._alive_lock:
            return self._active_brain in self._alive_brains

    def _status(self) -> ControlReply:
        running = self._state == ServerState.RUNNING
        return ControlReply(
            ok=True,
            state=self._state,
            episode=self._episode,
            active_brain=self._active(),
            spec=self._spec if running else None,
        )

    def _refuse(self, code: ReplyCode, detail: str, *, active_brain: str = "") -> ControlReply:
        """A refusal: its code for processes to decide on, its detail for people."""
        return ControlReply(
            ok=False, code=code, detail=detail, state=self._state, episode=self._episode, active_brain=active_brain
        )

    def _switch(self, brain: str) -> ControlReply:
        """Make ``brain`` the active brain from the frame whose command is awaited next (callback thread)."""
        if self._state != ServerState.RUNNING:
            detail = f"no episode is running (simulator {self._state})"
            return self._refuse(ReplyCode.NOT_RUNNING, detail, active_brain=self._active())
        if not brain:
            return self._refuse(ReplyCode.BAD_REQUEST, "switch needs a brain name")
        with self._alive_lock:
            previous = self._active_brain
            refusal: tuple[ReplyCode, str] | None = None
            if brain not in self._alive_brains:
                refusal = ReplyCode.NOT_ALIVE, f"brain {brain!r} is not alive"
            elif brain == previous:
                refusal = ReplyCode.ALREADY_ACTIVE, f"brain {brain!r} is already the active brain"
            else:
                self._active_brain = brain
                self._switches.append((previous, brain))
        if refusal is not None:
            return self._refuse(*refusal, active_brain=previous)
        log.info("switch requested: %s -> %s", previous, brain)
        return ControlReply(
            ok=True,
            detail=f"{previous} -> {brain} from the next frame",
            state=self._state,
            episode=self._episode,
            active_brain=brain,
        )

    def _on_status(self, payload: bytes) -> bytes:
        """The read-only status queryable (``keys.sim_status``): any payload, the status reply."""
        del payload
        return codec.encode(self._status())

    def _on_control(self, payload: bytes) -> bytes:
        request = codec.decode(payload, ControlRequest)
        if request.action == "status":
            return codec.encode(self._status())
        if request.action == "switch":
            return codec.encode(self._switch(request.brain))
        if request.action == "stop":
            self._stop_requested.set()
            return codec.encode(ControlReply(ok=True, state=self._state, episode=self._episode))
        if request.action != "start":
            return codec.encode(self._refuse(ReplyCode.UNKNOWN_ACTION, f"unknown action {request.action!r}"))
        return codec.encode(self._start(request))

    def _start(self, request: ControlRequest) -> ControlReply:
        """Accept a start (the main loop runs it) or refuse it with its code (callback thread: never block)."""
        spec = request.spec
        if spec is None:
            return self._refuse(ReplyCode.BAD_REQUEST, "start needs a spec")
        if self._state != ServerState.IDLE or not self._requests.empty():
            return self._refuse(ReplyCode.BUSY, f"busy ({self._state})")
        if spec.renderer == "gl" and self._gl_unavailable:
            return self._refuse(ReplyCode.RENDERER_UNAVAILABLE, f"renderer gl: {self._gl_unavailable}")
        try:
            # Loaded here, so that a bad name, or a start beyond the circuit's length, is refused rather than run.
            circuit = load_circuit(spec.circuit, direction=spec.direction)
            circuit.check_start_m(spec.start_m)
        except CircuitError as error:
            return self._refuse(ReplyCode.BAD_CIRCUIT, str(error))
        if not self._brain_alive(spec.active_brain):
            return self._refuse(ReplyCode.NOT_ALIVE, f"brain {spec.active_brain!r} is not alive")
        self._state = ServerState.STARTING
        self._requests.put((spec, circuit, request.driver))
        return ControlReply(ok=True, state=ServerState.STARTING, episode=self._episode + 1)

    # -- main loop --

    def _stopping(self) -> bool:
        """Whether the running episode must end ``stopped``: run control asked, or the process got SIGTERM."""
        return self._stop_requested.is_set() or stop_requested()

    def serve_forever(self) -> None:
        log.info("simulator ready on run %s", self.config.run_id)
        while not stop_requested():
            try:
                spec, circuit, driver = self._requests.get(timeout=0.5)
            except queue.Empty:
                continue
            self._episode += 1
            self._driver, self._driver_missing_since = driver, None
            self._stop_requested.clear()
            with self._alive_lock:  # before "running": a switch accepted from now on applies to this episode
                self._active_brain = spec.active_brain
                self._switches.clear()
            self._spec = spec = resolve_spec(spec)  # "auto" resolved before anyone can read the running spec
            self._state = ServerState.RUNNING
            try:
                self.run_episode(spec, circuit)
            finally:
                self._state = ServerState.IDLE

    def run_episode(self, spec: EpisodeSpec, circuit: Circuit | None = None) -> EndReason:
        episode = self._episode
        # "auto" becomes the renderer this process can run (probed in the thread that renders); the START event and
        # the status carry the resolved spec, so the score and the recording name the renderer that drew the frames.
        self._spec = spec = resolve_spec(spec)
        sim = EpisodeSim(spec, scenes=self._scenes, circuit=circuit)
        self._frames = self._frames_latest if spec.realtime else self._frames_lossless
        if self._state != ServerState.RUNNING:  # called directly (tests, benchmarks), not through serve_forever
            with self._alive_lock:
                self._active_brain = spec.active_brain
                self._switches.clear()
        self._wait_for_subscribers()
        self._commands.drain()  # answers to an earlier episode are stale
        self._event_seq = -1
        self._end_detail = ""

        def header(seq: int, stamp_ns: int) -> Header:
            return Header(run_id=self.config.run_id, episode=episode, seq=seq, stamp_ns=stamp_ns)

        self._publish_event(header, EventKind.START, 0, spec=spec)
        log.info("episode %d started: %s", episode, codec.to_json(spec))
        wall_start = time.monotonic_ns()
        stepper = self._realtime_steps if spec.realtime else self._lockstep_steps
        reason = EndReason.STOPPED
        for result in stepper(sim, header):
            if result.lap:
                self._publish_event(header, EventKind.LAP, result.stamp_ns, lap=result.lap)
            if result.end is not None:
                reason = result.end
                break
        wall_ns = time.monotonic_ns() - wall_start
        self._announce_switches(sim, header)  # one accepted after the last frame: the score names the brain
        self._publish_event(
            header,
            EventKind.END,
            sim.stamp_ns,
            reason=reason,
            last_pose_seq=sim.seq,
            wall_elapsed_ns=wall_ns,
            detail=self._end_detail,
        )
        log.info(
            "episode %d ended: %s after %.2f s sim, %.2f s wall%s",
            episode,
            reason,
            sim.stamp_ns / 1e9,
            wall_ns / 1e9,
            f" ({self._end_detail})" if self._end_detail else "",
        )
        return reason

    def _publish_event(self, header, kind: EventKind, stamp_ns: int, **fields) -> None:
        self._event_seq += 1
        event = EpisodeEvent(header=header(self._event_seq, stamp_ns), kind=kind, **fields)
        self._events.publish(event)
        if (for_brains := brain_event(event)) is not None:  # before the first frame too: brains seed from it
            self._brain_events.publish(for_brains)

    def _announce_switches(self, sim: EpisodeSim, header) -> bool:
        """Publish a BRAIN_SWITCH event, stamped with the current frame, for each switch accepted since the last
        call; True when there was one."""
        with self._alive_lock:
            switches, self._switches = self._switches, []
        for previous, brain in switches:
            self._publish_event(header, EventKind.BRAIN_SWITCH, sim.stamp_ns, brain=brain, detail=previous)
            log.info("episode %d: %s drives from frame %d on (was %s)", self._episode, brain, sim.seq, previous)
        return bool(switches)

    def _wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + self.config.subscriber_wait_s
        while time.monotonic() < deadline:
            if self._frames.has_subscribers() and self._events.has_subscribers():
                return
            time.sleep(0.01)
        log.warning("starting without a subscriber to camera frames or events")

    def _publish_observation(
        self, sim: EpisodeSim, header, *, speed_mps: float, yaw_rate_radps: float, latency_ns: int, frame: bool = True
    ) -> int:
        """Publish frame (optional) and pose of the current step; return when the frame went out (monotonic ns)."""
        h = header(sim.seq, sim.stamp_ns)
        if frame:
            self._frames.publish(image_frame(h, sim.render()))
        sent_ns = time.monotonic_ns()
        self._poses.publish(
            Pose(
                header=h,
                x_m=sim.car.x_m,
                y_m=sim.car.y_m,
                yaw_rad=sim.car.yaw_rad,
                speed_mps=speed_mps,
                yaw_rate_radps=yaw_rate_radps,
                command_latency_ns=latency_ns,
            )
        )
        return sent_ns

    def _lockstep_steps(self, sim: EpisodeSim, header):
        spec = sim.spec
        speed, yaw_rate, latency_ns = 0.0, 0.0, 0
        while True:
            frame_sent_ns = self._publish_observation(
                sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate, latency_ns=latency_ns
            )
            command, ending = self._await_command(sim, header, spec, frame_sent_ns)
            if ending is not None:
                yield StepResult(car=sim.car, stamp_ns=sim.stamp_ns, seq=sim.seq, lateral_m=0.0, lap=0, end=ending)
                return
            latency_ns = command.arrival_ns - frame_sent_ns
            speed, yaw_rate = command.message.speed_mps, command.message.yaw_rate_radps
            result = sim.step(speed_mps=speed, yaw_rate_radps=yaw_rate)
            if result.end is not None:  # the last pose, without a frame nobody would answer
                self._publish_observation(
                    sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate, latency_ns=latency_ns, frame=False
                )
            yield result

    def _await_command(self, sim: EpisodeSim, header, spec: EpisodeSpec, frame_sent_ns: int):
        """(command for the current frame, None) or (None, the reason the episode must end).

        Every brain's answer to the current frame is kept, so a switch while waiting takes the new brain's answer
        even if it came first. A switch restarts the timeout: the new brain gets the full time to answer.
        """
        timeout_ns = int(spec.brain_timeout_s * 1e9)
        deadline = frame_sent_ns + timeout_ns
        resend_at = frame_sent_ns + int(RESEND_AFTER_S * 1e9)
        answers: dict[str, Received] = {}
        while True:
            if self._announce_switches(sim, header):
                deadline = max(deadline, time.monotonic_ns() + timeout_ns)
            if (answer := answers.get(self._active())) is not None:
                return (None, EndReason.BRAIN_INVALID) if self._refused(answer.message, sim) else (answer, None)
            if self._stopping():
                return None, EndReason.STOPPED
            if not self._active_alive():
                return None, EndReason.BRAIN_LOST
            if self._driver_lost():
                return None, EndReason.DRIVER_LOST
            now = time.monotonic_ns()
            if now >= deadline:
                return None, EndReason.BRAIN_TIMEOUT
            if now >= resend_at:
                log.debug("no answer to frame %d yet: sending it again", sim.seq)
                self._publish_observation(sim, header, speed_mps=0.0, yaw_rate_radps=0.0, latency_ns=0)
                resend_at = now + int(RESEND_AFTER_S * 1e9)
            received = self._commands.recv(timeout_s=min(0.05, (deadline - now) / 1e9))
            if received is None:
                continue
            command: Command = received.message
            if command.header.episode == self._episode and command.frame_seq == sim.seq and self._on_own_key(received):
                answers.setdefault(command.brain, received)  # a repeated answer to a resent frame changes nothing

    def _refused(self, command: Command, sim: EpisodeSim) -> bool:
        """Whether the driving brain's command is one no car can take (from a brain host that refused its brain's
        answer, or from any client: NaN never gets past decoding, huge finite values get here); then the episode
        ends ``brain_invalid`` and END's detail says what it was."""
        problem = command.problem()
        if problem:
            self._end_detail = f"brain {command.brain!r} answered frame {command.frame_seq} with {problem}"
            log.warning("episode %d: %s", self._episode, self._end_detail)
        return bool(problem)

    def _realtime_steps(self, sim: EpisodeSim, header):
        """Free-running: one step per ``step_s`` of wall time with the latest command of the active brain.

        The latest command of every brain is kept, so a newly switched-in brain drives at once with its own latest
        answer; the timeout counts from its latest command or from the switch, whichever is later.
        """
        spec = sim.spec
        speed, yaw_rate, latency_ns = 0.0, 0.0, 0
        latest: dict[str, Received] = {}
        sent_ns: dict[int, int] = {}  # frame seq -> when it went out, for the latency of the command answering it
        active_since_ns = time.monotonic_ns()
        next_tick = time.monotonic()
        while True:
            sent_ns[sim.seq] = self._publish_observation(
                sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate, latency_ns=latency_ns
            )
            sent_ns.pop(sim.seq - REALTIME_LATENCY_FRAMES, None)
            latency_ns = 0
            next_tick += spec.step_s
            if (delay := next_tick - time.monotonic()) > 0:
                time.sleep(delay)
            for received in self._commands.drain():
                if received.message.header.episode == self._episode and self._on_own_key(received):
                    latest[received.message.brain] = received
                    if received.message.brain == self._active() and received.message.frame_seq in sent_ns:
                        latency_ns = received.arrival_ns - sent_ns.pop(received.message.frame_seq)
            if self._announce_switches(sim, header):
                active_since_ns = time.monotonic_ns()
            last_command_ns = active_since_ns
            if (current := latest.get(self._active())) is not None:
                speed, yaw_rate = current.message.speed_mps, current.message.yaw_rate_radps
                last_command_ns = max(last_command_ns, current.arrival_ns)
            ending = None
            if current is not None and self._refused(current.message, sim):
                ending = EndReason.BRAIN_INVALID
            elif self._stopping():
                ending = EndReason.STOPPED
            elif not self._active_alive():
                ending = EndReason.BRAIN_LOST
            elif self._driver_lost():
                ending = EndReason.DRIVER_LOST
            elif time.monotonic_ns() - last_command_ns > spec.brain_timeout_s * 1e9:
                ending = EndReason.BRAIN_TIMEOUT
            if ending is not None:
                yield StepResult(car=sim.car, stamp_ns=sim.stamp_ns, seq=sim.seq, lateral_m=0.0, lap=0, end=ending)
                return
            result = sim.step(speed_mps=speed, yaw_rate_radps=yaw_rate)
            if result.end is not None:
                self._publish_observation(
                    sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate, latency_ns=0, frame=False
                )
            yield result

    def close(self) -> None:
        self._scenes.close()


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import service_main

    return service_main(
        "simulator",
        "drivebench simulator: PyBullet world, camera frames, poses, episode events",
        SimulatorConfig,
        SimulatorService,
        argv,
    )


__all__ = ["SimulatorConfig", "SimulatorService", "main"]
