"""The brain host process (``python -m brains --brain NAME``): camera frames in, commands out.

It keeps only the newest frame (a brain slower than the camera skips frames instead of lagging behind), calls the
brain, and publishes a Command stamped with the frame it answers and the inference time. A new episode number on
the frames resets the brain, seeded from the episode's spec. A frame it has already answered (the simulator
repeats a frame nobody answered) gets the same command again without calling the brain twice. A frame the noise
injector dropped gets the last command again (the car keeps doing what the brain last decided), stamped for the new
frame, without calling the brain.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import msgspec
from brains.base import Brain, Observation
from brains.registry import BrainOptionsError, UnknownBrainError, brain_names, make_brain
from protocol import keys
from protocol.bus import Bus, BusConfig, Traffic
from protocol.episodes import EpisodeStarts
from protocol.images import FrameReader
from protocol.messages import CameraFrame, Command, Header

log = logging.getLogger("drivebench.brain")


class BrainHostConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of one brain host process.

    brain: registered brain name (``explicit``, ``constant``, ...).
    name: this brain's name on the bus (its command key and liveliness token); defaults to ``brain``.
    options: keyword options for the brain's constructor (e.g. ``{speed_mps: 2.0}`` for ``constant``).
    camera: which stream to drive from: ``perturbed`` (after the noise injector, the default) or ``raw`` (straight
        from the simulator, for a stack without a noise injector).
    """

    bus: BusConfig = BusConfig()
    run_id: str = "default"
    brain: str = "explicit"
    name: str = ""
    options: dict[str, Any] = {}
    camera: str = "perturbed"

    def __post_init__(self) -> None:
        if self.camera not in ("raw", "perturbed"):
            raise ValueError(f"camera must be raw or perturbed, got {self.camera!r}")

    @property
    def bus_name(self) -> str:
        return self.name or self.brain


class BrainHost:
    def __init__(self, config: BrainHostConfig, bus: Bus, brain: Brain):
        self.config = config
        self.brain = brain
        self.name = keys.check_name(config.bus_name, what="brain name")
        run = config.run_id
        camera_key = keys.camera_raw(run) if config.camera == "raw" else keys.camera_perturbed(run)
        self._frames = bus.subscribe(camera_key, CameraFrame, keep_last=1)
        self._starts = EpisodeStarts(bus, run)
        self._commands = bus.publisher(keys.command(run, self.name), Command, Traffic.COMMANDS)
        self._episode = -1
        self._last: Command | None = None
        self._seq = 0
        self._reader = FrameReader(log)
        # Declared last: whoever sees this token can rely on the subscriptions above.
        bus.declare_alive(keys.alive(run, "brain", self.name))

    def serve_forever(self) -> None:
        log.info("brain %s (%s) ready on run %s", self.name, self.config.brain, self.config.run_id)
        while True:
            received = self._frames.recv(timeout_s=0.5)
            if received is not None:
                self.answer(received.message)

    def _seed_for(self, episode: int) -> int:
        spec = self._starts.spec(episode)
        if spec is None:
            log.warning("no start event for episode %d: resetting the brain with seed 0", episode)
            return 0
        return spec.seed

    def answer(self, frame: CameraFrame) -> None:
        h = frame.header
        if self._last is not None and (self._last.header.episode, self._last.frame_seq) == (h.episode, h.seq):
            self._commands.publish(self._last)  # a repeated frame: same answer, the brain sees each frame once
            return
        image = None if frame.dropped else self._reader.image(frame)
        if image is None and not frame.dropped:
            return
        if h.episode != self._episode:
            self._episode = h.episode
            self._last = None
            self.brain.reset(seed=self._seed_for(h.episode))
        if image is None:  # lost on the way: keep doing what the brain last decided
            speed_mps = self._last.speed_mps if self._last is not None else 0.0
            yaw_rate_radps = self._last.yaw_rate_radps if self._last is not None else 0.0
            inference_ns = 0
        else:
            started = time.perf_counter_ns()
            action = self.brain.act(Observation(image_rgb=image, stamp_ns=h.stamp_ns, seq=h.seq))
            inference_ns = time.perf_counter_ns() - started
            speed_mps, yaw_rate_radps = float(action.speed_mps), float(action.yaw_rate_radps)
        command = Command(
            header=Header(run_id=self.config.run_id, episode=h.episode, seq=self._seq, stamp_ns=h.stamp_ns),
            brain=self.name, frame_seq=h.seq, speed_mps=speed_mps, yaw_rate_radps=yaw_rate_radps,
            inference_ns=inference_ns)
        self._seq += 1
        self._commands.publish(command)
        self._last = command


def main(argv: list[str] | None = None) -> int:
    from protocol.runtime import UserError, load_service_config, log_config, run_service, service_parser

    parser = service_parser("drivebench brain host: camera frames in, driving commands out")
    parser.add_argument("--brain", help=f"brain to run ({', '.join(brain_names())})")
    parser.add_argument("--name", help="name on the bus (default: the brain's name)")
    parser.add_argument("--weights", metavar="CKPT",
                        help="neural brains: checkpoint or exported ONNX file (= --set options.weights=CKPT)")
    args = parser.parse_args(argv)

    def run() -> int:
        config = load_service_config(BrainHostConfig, args, extra={"brain": args.brain, "name": args.name,
                                                                   "options.weights": args.weights})
        log_config(config)
        try:
            brain = make_brain(config.brain, **config.options)
        except (UnknownBrainError, BrainOptionsError) as error:
            raise UserError(str(error)) from None
        except TypeError as error:
            raise UserError(f"bad options for brain {config.brain!r}: {error}") from None
        with Bus(config.bus, name=f"brain-{config.bus_name}") as bus:
            BrainHost(config, bus, brain).serve_forever()
        return 0

    return run_service("brain", run)
