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

import msgspec

from protocol import codec, keys
from protocol.bus import Bus, BusConfig, Received, Traffic
from protocol.deploy.runtime import stop_requested
from protocol.episodes import EpisodeStarts
from protocol.images import FrameReader, image_frame
from protocol.messages import CameraFrame
from services.noise.models import NoisePipeline

log = logging.getLogger("drivebench.noise")

# Real time: frames kept waiting to be perturbed (newest win). In lock-step every frame is kept: a brain that drives
# from the simulator's own frames (an episode without noise) does not wait for this process, yet the recorder and
# datasets need every perturbed frame.
REALTIME_FRAME_BACKLOG = 8


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
        self._starts = EpisodeStarts(bus, run)
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
        # Frames still queued are an episode's last steps, which the recorder (stopped after us) must still get: a
        # brain that drives from the simulator's frames lets this process fall behind on a busy machine.
        backlog = self._frames.inbox.drain()
        for received in backlog:
            self.perturb(received)
        if backlog:
            log.info("forwarded the %d frames still queued at stop", len(backlog))

    def _start_episode(self, episode: int) -> bool:
        """Build the episode's pipeline; False (and pass the frame through) when its START was never seen."""
        spec = self._starts.spec(episode)
        if spec is None:
            if episode not in self._unknown_episodes:
                self._unknown_episodes.add(episode)
                log.warning("no start event for episode %d: passing its frames through unperturbed", episode)
            return False
        self._episode = episode
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
