"""The simulator process: wires :class:`EpisodeSim` to the bus.

Publishes camera frames (ground truth), poses and episode events; applies the active brain's commands; answers run
control queries (start / stop / status). Lock-step by default: publish frame n, wait for the active brain's command
for frame n, step. A brain that does not answer in time, or whose liveliness token vanishes, ends the episode with
a typed reason; nothing stalls silently.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import msgspec

from protocol import codec, keys
from protocol.bus import Bus, BusConfig, Inbox, Traffic
from protocol.images import image_frame
from protocol.messages import (
    CameraFrame, Command, ControlReply, ControlRequest, EndReason, EpisodeEvent, EpisodeSpec, EventKind, Header, Pose,
)
from services.circuits import Circuit, CircuitError, load_circuit
from services.simulator.episode import EpisodeSim, SceneCache, StepResult

log = logging.getLogger("drivebench.simulator")

# Lock-step: if a frame has had no answer for this long, publish it again (same seq). It covers a brain whose
# subscription was not yet known to this session when the frame went out; brain hosts answer a repeated frame
# with the command they already computed.
RESEND_AFTER_S = 1.0


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
        self._commands = Inbox()
        bus.subscribe(keys.commands_all(run), Command, inbox=self._commands)
        self._alive_brains: set[str] = set()
        self._alive_lock = threading.Lock()
        bus.watch_alive(keys.alive_all(run), self._on_liveliness)
        self._requests: queue.Queue[tuple[EpisodeSpec, Circuit]] = queue.Queue()
        self._state = "idle"
        self._episode = -1
        self._stop_requested = threading.Event()
        self._scenes = SceneCache()
        bus.serve(keys.sim_control(run), self._on_control)
        bus.declare_alive(keys.alive(run, "simulator", config.name))

    # -- callbacks (Zenoh's callback thread: never block) --

    def _on_liveliness(self, key: str, alive: bool) -> None:
        try:
            _, role, name = keys.parse_alive(key)
        except ValueError:
            return
        if role != "brain":
            return
        with self._alive_lock:
            (self._alive_brains.add if alive else self._alive_brains.discard)(name)

    def _brain_alive(self, name: str) -> bool:
        with self._alive_lock:
            return name in self._alive_brains

    def _on_control(self, payload: bytes) -> bytes:
        request = codec.decode(payload, ControlRequest)
        if request.action == "status":
            return codec.encode(ControlReply(ok=True, state=self._state, episode=self._episode))
        if request.action == "stop":
            self._stop_requested.set()
            return codec.encode(ControlReply(ok=True, state=self._state, episode=self._episode))
        if request.action != "start":
            return codec.encode(ControlReply(ok=False, detail=f"unknown action {request.action!r}"))
        if request.spec is None:
            return codec.encode(ControlReply(ok=False, detail="start needs a spec"))
        if self._state != "idle" or not self._requests.empty():
            return codec.encode(ControlReply(ok=False, detail=f"busy ({self._state})", state=self._state))
        try:
            circuit = load_circuit(request.spec.circuit)  # checked here so a bad name is refused, not run
        except CircuitError as error:
            return codec.encode(ControlReply(ok=False, detail=str(error)))
        if not self._brain_alive(request.spec.active_brain):
            return codec.encode(ControlReply(ok=False, detail=f"brain {request.spec.active_brain!r} is not alive"))
        self._state = "starting"
        self._requests.put((request.spec, circuit))
        return codec.encode(ControlReply(ok=True, state="starting", episode=self._episode + 1))

    # -- main loop --

    def serve_forever(self) -> None:
        log.info("simulator ready on run %s", self.config.run_id)
        while True:
            try:
                spec, circuit = self._requests.get(timeout=0.5)
            except queue.Empty:
                continue
            self._episode += 1
            self._stop_requested.clear()
            self._state = "running"
            try:
                self.run_episode(spec, circuit)
            finally:
                self._state = "idle"

    def run_episode(self, spec: EpisodeSpec, circuit: Circuit | None = None) -> EndReason:
        episode = self._episode
        sim = EpisodeSim(spec, scenes=self._scenes, circuit=circuit)
        self._frames = self._frames_latest if spec.realtime else self._frames_lossless
        self._wait_for_subscribers()
        self._commands.drain()  # answers to an earlier episode are stale
        event_seq = 0

        def header(seq: int, stamp_ns: int) -> Header:
            return Header(run_id=self.config.run_id, episode=episode, seq=seq, stamp_ns=stamp_ns)

        self._events.publish(EpisodeEvent(header=header(event_seq, 0), kind=EventKind.START, spec=spec))
        log.info("episode %d started: %s", episode, codec.to_json(spec))
        wall_start = time.monotonic_ns()
        stepper = self._realtime_steps if spec.realtime else self._lockstep_steps
        reason = EndReason.STOPPED
        for result in stepper(sim, header):
            if result.lap:
                event_seq += 1
                self._events.publish(EpisodeEvent(header=header(event_seq, result.stamp_ns), kind=EventKind.LAP,
                                                  lap=result.lap))
            if result.end is not None:
                reason = result.end
                break
        wall_ns = time.monotonic_ns() - wall_start
        event_seq += 1
        self._events.publish(EpisodeEvent(header=header(event_seq, sim.stamp_ns), kind=EventKind.END, reason=reason,
                                          last_pose_seq=sim.seq, wall_elapsed_ns=wall_ns))
        log.info("episode %d ended: %s after %.2f s sim, %.2f s wall", episode, reason, sim.stamp_ns / 1e9,
                 wall_ns / 1e9)
        return reason

    def _wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + self.config.subscriber_wait_s
        while time.monotonic() < deadline:
            if self._frames.has_subscribers() and self._events.has_subscribers():
                return
            time.sleep(0.01)
        log.warning("starting without a subscriber to camera frames or events")

    def _publish_observation(self, sim: EpisodeSim, header, *, speed_mps: float, yaw_rate_radps: float,
                             latency_ns: int, frame: bool = True) -> int:
        """Publish frame (optional) and pose of the current step; return when the frame went out (monotonic ns)."""
        h = header(sim.seq, sim.stamp_ns)
        if frame:
            self._frames.publish(image_frame(h, sim.render()))
        sent_ns = time.monotonic_ns()
        self._poses.publish(Pose(header=h, x_m=sim.car.x_m, y_m=sim.car.y_m, yaw_rad=sim.car.yaw_rad,
                                 speed_mps=speed_mps, yaw_rate_radps=yaw_rate_radps, command_latency_ns=latency_ns))
        return sent_ns

    def _lockstep_steps(self, sim: EpisodeSim, header):
        spec = sim.spec
        speed, yaw_rate, latency_ns = 0.0, 0.0, 0
        while True:
            frame_sent_ns = self._publish_observation(sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate,
                                                      latency_ns=latency_ns)
            command, ending = self._await_command(sim, header, spec, frame_sent_ns)
            if ending is not None:
                yield StepResult(car=sim.car, stamp_ns=sim.stamp_ns, seq=sim.seq, lateral_m=0.0, lap=0, end=ending)
                return
            latency_ns = command.arrival_ns - frame_sent_ns
            speed, yaw_rate = command.message.speed_mps, command.message.yaw_rate_radps
            result = sim.step(speed_mps=speed, yaw_rate_radps=yaw_rate)
            if result.end is not None:  # the last pose, without a frame nobody would answer
                self._publish_observation(sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate,
                                          latency_ns=latency_ns, frame=False)
            yield result

    def _await_command(self, sim: EpisodeSim, header, spec: EpisodeSpec, frame_sent_ns: int):
        """(command for the current frame, None) or (None, the reason the episode must end)."""
        deadline = frame_sent_ns + int(spec.brain_timeout_s * 1e9)
        resend_at = frame_sent_ns + int(RESEND_AFTER_S * 1e9)
        while True:
            if self._stop_requested.is_set():
                return None, EndReason.STOPPED
            if not self._brain_alive(spec.active_brain):
                return None, EndReason.BRAIN_LOST
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
            if (command.brain == spec.active_brain and command.header.episode == self._episode
                    and command.frame_seq == sim.seq):
                return received, None

    def _realtime_steps(self, sim: EpisodeSim, header):
        """Free-running: one step per ``step_s`` of wall time with the latest command of the active brain."""
        spec = sim.spec
        speed, yaw_rate = 0.0, 0.0
        last_command_ns = time.monotonic_ns()
        next_tick = time.monotonic()
        while True:
            self._publish_observation(sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate, latency_ns=0)
            next_tick += spec.step_s
            if (delay := next_tick - time.monotonic()) > 0:
                time.sleep(delay)
            for received in self._commands.drain():
                command: Command = received.message
                if command.brain == spec.active_brain and command.header.episode == self._episode:
                    speed, yaw_rate = command.speed_mps, command.yaw_rate_radps
                    last_command_ns = received.arrival_ns
            ending = None
            if self._stop_requested.is_set():
                ending = EndReason.STOPPED
            elif not self._brain_alive(spec.active_brain):
                ending = EndReason.BRAIN_LOST
            elif time.monotonic_ns() - last_command_ns > spec.brain_timeout_s * 1e9:
                ending = EndReason.BRAIN_TIMEOUT
            if ending is not None:
                yield StepResult(car=sim.car, stamp_ns=sim.stamp_ns, seq=sim.seq, lateral_m=0.0, lap=0, end=ending)
                return
            result = sim.step(speed_mps=speed, yaw_rate_radps=yaw_rate)
            if result.end is not None:
                self._publish_observation(sim, header, speed_mps=speed, yaw_rate_radps=yaw_rate, latency_ns=0,
                                          frame=False)
            yield result

    def close(self) -> None:
        self._scenes.close()


def main(argv: list[str] | None = None) -> int:
    from protocol.runtime import service_main

    return service_main("simulator", "drivebench simulator: PyBullet world, camera frames, poses, episode events",
                        SimulatorConfig, SimulatorService, argv)


__all__ = ["SimulatorConfig", "SimulatorService", "main"]
