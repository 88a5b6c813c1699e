"""The noise injector process: ground-truth camera frames in, perturbed frames out (what brains see).

Per episode it builds the spec's noise pipeline, seeded from the spec, so the same spec twice perturbs the same
frames the same way. The scorer and the recorder keep reading ground truth on the simulator's key.
With no noise configured the received bytes are forwarded as they are (no decode/encode), for recordings, datasets
and viewers of the brain's camera; brain hosts then drive from the simulator's own frames and do not wait for this
process, so in lock-step it keeps every frame queued, however far behind it falls, and forwards the rest at stop.
A frame the simulator sends again (lock-step resend, byte for byte the same) gets the same output again; the
pipeline sees it once.
"""

from __future__ import annotations

import logging
import time

import msgspec

from protocol import codec, keys
from protocol.bus import Bus, BusConfig, Received, Traffic
from protocol.deploy.runtime import stop_requested
from protocol.episodes import EpisodeStarts
from protocol.images import FrameReader, image_frame
from protocol.messages import CameraFrame, EpisodeEvent, EventKind
from services.noise.models import NoisePipeline

log = logging.getLogger("drivebench.noise")

# Real time: frames kept waiting to be perturbed (newest win). In lock-step every frame is kept: a brain that drives
# from the simulator's own frames (an episode without noise) does not wait for this process, yet the recorder and
# datasets need every perturbed frame.
REALTIME_FRAME_BACKLOG = 8
# At a stop, frames still on their way are forwarded: every frame of a lock-step episode whose END came, then
# whatever comes until none has for STOP_QUIET_S; all within STOP_DRAIN_MAX_S (inside the launcher's 5 s grace).
# STOP_LINGER_S then lets the last ones leave before the session closes.
STOP_QUIET_S = 0.2
STOP_DRAIN_MAX_S = 4.0
STOP_LINGER_S = 0.2


class NoiseConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of the noise injector process (the perturbations themselves come with each episode's spec)."""

    bus: BusConfig = BusConfig()
    run_id: str = "default"
    name: str = "noise"


class NoiseService:
    def __init__(self, config: NoiseConfig, bus: Bus):
        self.config = config
        run = config.run_id
        self._frames = bus.subscribe(keys.camera_raw(run), CameraFrame)
        self._starts = EpisodeStarts(bus, run, on_event=self._on_event)
        self._last_frame_seq: dict[int, int] = {}  # lock-step episodes that ended: the seq of their last frame
        self._lockstep = False  # the current episode's mode
        self._forwarded_seq = -1  # the highest seq of the current episode dealt with
        self._out_latest = bus.publisher(keys.camera_perturbed(run), CameraFrame, Traffic.FRAMES)
        self._out_lossless = bus.publisher(keys.camera_perturbed(run), CameraFrame, Traffic.FRAMES_LOSSLESS)
        self._out = self._out_lossless  # as the simulator: lossless in lock-step, latest-wins in real time
        self._episode = -1
        self._pipeline: NoisePipeline | None = None  # None: pass frames through as they are
        self._unknown_episodes: set[int] = set()
        self._last_input = b""  # the last frame's wire bytes, to recognise a resend
        self._last_payload = b""
        self._reader = FrameReader(log)
        bus.declare_alive(keys.alive(run, "noise", config.name))

    def serve_forever(self) -> None:
        log.info("noise injector ready on run %s", self.config.run_id)
        while not stop_requested():
            received = self._frames.recv(timeout_s=0.5)
            if received is not None:
                self.perturb(received)
        self._forward_the_rest()

    def _on_event(self, event: EpisodeEvent) -> None:
        """Callback thread: note where each episode ends (END names its last pose; the last frame is one before)."""
        if event.kind == EventKind.END and event.last_pose_seq >= 0:
            self._last_frame_seq[event.header.episode] = event.last_pose_seq - 1

    def _owes_frames(self) -> bool:
        """Whether the current lock-step episode has ended and frames of it are still to be forwarded."""
        last = self._last_frame_seq.get(self._episode)
        return self._lockstep and last is not None and self._forwarded_seq < last

    def _forward_the_rest(self) -> None:
        """Forward what is still queued or on its way: an episode's last steps, which the recorder (stopped after us)
        must still get, when a brain that drives from the simulator's frames let this process fall behind. Only what
        Python had already received was forwarded before: a test that froze the injector and stopped it lost up to
        56 of an episode's 60 frames, still in transit to it when the session closed."""
        forwarded = 0
        deadline = time.monotonic() + STOP_DRAIN_MAX_S
        while time.monotonic() < deadline:
            received = self._frames.recv(timeout_s=0.05 if self._owes_frames() else STOP_QUIET_S)
            if received is None and not self._owes_frames():
                break
            if received is not None:
                self.perturb(received)
                forwarded += 1
        if self._owes_frames():
            log.warning(
                "stopping without frames %d..%d of episode %d (never came)",
                self._forwarded_seq + 1,
                self._last_frame_seq[self._episode],
                self._episode,
            )
        if forwarded:
            log.info("forwarded the %d frames still on their way at stop", forwarded)
            time.sleep(STOP_LINGER_S)

    def _start_episode(self, episode: int) -> bool:
        """Build the episode's pipeline; False (and pass the frame through) when its START was never seen."""
        spec = self._starts.spec(episode)
        if spec is None:
            if episode not in self._unknown_episodes:
                self._unknown_episodes.add(episode)
                log.warning("no start event for episode %d: passing its frames through unperturbed", episode)
            return False
        self._episode = episode
        self._lockstep, self._forwarded_seq = not spec.realtime, -1
        self._out = self._out_latest if spec.realtime else self._out_lossless
        self._frames.inbox.keep_last(REALTIME_FRAME_BACKLOG if spec.realtime else None)
        self._pipeline = NoisePipeline(list(spec.noise)) if spec.noise else None
        if self._pipeline is not None:
            self._pipeline.reset(seed=spec.seed)
        log.info("episode %d: noise %s", episode, codec.to_json(list(spec.noise)) if spec.noise else "none")
        return True

    def perturb(self, received: Received[CameraFrame]) -> None:
        frame = received.message
        if received.payload == self._last_input:  # a lock-step resend: same output, the pipeline sees it once
            self._out.publish_bytes(self._last_payload)
            return
        if frame.header.episode != self._episode and not self._start_episode(frame.header.episode):
            self._out.publish_bytes(received.payload)
            return
        self._forwarded_seq = max(self._forwarded_seq, frame.header.seq)  # dealt with (an unreadable one too)
        if self._pipeline is None:
            payload = received.payload
        else:
            image = self._reader.image(frame)
            if image is None:
                return
            perturbed = self._pipeline.apply(image)
            if perturbed is None:
                out = CameraFrame(
                    header=frame.header, width_px=frame.width_px, height_px=frame.height_px, data=b"", dropped=True
                )
            else:
                out = image_frame(frame.header, perturbed)
            payload = codec.encode(out)
        self._out.publish_bytes(payload)
        self._last_input, self._last_payload = received.payload, payload


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import service_main

    return service_main(
        "noise",
        "drivebench noise injector: ground-truth camera in, perturbed camera out",
        NoiseConfig,
        NoiseService,
        argv,
    )
