"""The scorer process: ground-truth poses, commands and episode events in; live metrics and one score out.

It scores only the simulator's ground truth (poses), never a camera stream, so noise cannot leak into the score.
Exactly one EpisodeScore per episode: after the END event, once every pose up to the END's ``last_pose_seq`` has
arrived (or after a short grace period if some never do, which the score's log line reports).

Every brain's commands are matched by frame (``services.scorer.shadows``): the driving brain's feed the metrics, and
the others are shadows whose distance to the driver the score reports. BRAIN_SWITCH events say who drove which
frame; the score names the brain driving at the end and lists the switches.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Annotated

import msgspec

from circuits import CircuitError, load_circuit
from protocol import keys
from protocol.bus import OBSERVER_BUS, Bus, BusConfig, Inbox, Traffic
from protocol.deploy.runtime import stop_requested
from protocol.episode_spec import EpisodeSpec
from protocol.episodes import running_spec
from protocol.messages import (
    BrainSwitch,
    Command,
    EndReason,
    EpisodeEvent,
    EpisodeScore,
    EventKind,
    Header,
    LiveMetrics,
    Pose,
)
from services.scorer.metrics import EpisodeScorer
from services.scorer.shadows import CommandMatcher

log = logging.getLogger("drivebench.scorer")

MAX_POSITION_M = 1e6  # 1000 km from the world's origin: beyond any circuit, and far below what overflows the metrics
# After END, how long to wait for poses still in flight before scoring what arrived.
POSE_GRACE_S = 2.0


class ScorerConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of the scorer process. live_rate_hz: how often live metrics are published (wall clock).

    bus: a Zenoh client by default (see ``protocol.bus.OBSERVER_BUS``): everything it reads comes through the router.
    """

    bus: BusConfig = OBSERVER_BUS
    run_id: str = "default"
    name: str = "scorer"
    live_rate_hz: Annotated[float, msgspec.Meta(gt=0)] = 4.0  # 0 would divide by zero at the first frame


@dataclass
class _Episode:
    number: int
    spec: EpisodeSpec
    scorer: EpisodeScorer
    commands: CommandMatcher
    active_brain: str
    wall_start: float = field(default_factory=time.monotonic)
    last_pose_seq: int = -1
    end: EpisodeEvent | None = None
    end_arrival: float = 0.0


class ScorerService:
    def __init__(self, config: ScorerConfig, bus: Bus):
        self.config = config
        run = config.run_id
        self._inbox = Inbox()
        bus.subscribe(keys.events(run), EpisodeEvent, inbox=self._inbox)
        bus.subscribe(keys.pose(run), Pose, inbox=self._inbox)
        bus.subscribe(keys.commands_all(run), Command, inbox=self._inbox)
        self._bus = bus
        self._live = bus.publisher(keys.live_metrics(run), LiveMetrics, Traffic.METRICS)
        self._scores = bus.publisher(keys.score(run), EpisodeScore, Traffic.EVENTS)
        self._episode: _Episode | None = None
        self._scored: set[int] = set()
        self._live_seq = 0
        self._next_live = 0.0
        self._ignored_episodes: set[int] = set()
        # The brain hosts of the run: in lock-step every one answers every frame (shadows and swap candidates too),
        # so a score waits for their answers to the last frame, not only the driver's (see _maybe_finish).
        self._brains = bus.watch_alive(keys.alive_role(run, "brain"))
        bus.declare_alive(keys.alive(run, "scorer", config.name))

    def serve_forever(self) -> None:
        log.info("scorer ready on run %s", self.config.run_id)
        while not stop_requested():
            self.poll(timeout_s=0.1)

    def poll(self, *, timeout_s: float) -> None:
        received = self._inbox.recv(timeout_s=timeout_s)
        if received is not None:
            message = received.message
            if isinstance(message, Pose):
                self._on_pose(message, key=received.key)
            elif isinstance(message, Command):
                self._on_command(message, key=received.key)
            elif isinstance(message, EpisodeEvent):
                self._on_event(message)
        self._maybe_finish()
        self._maybe_publish_live()

    def _current(self, episode: int) -> _Episode | None:
        current = self._episode
        if current is not None and current.number == episode:
            return current
        if episode not in self._scored and episode not in self._ignored_episodes:
            self._ignored_episodes.add(episode)  # ask once
            # Its START went out before our subscription reached the simulator (or we joined late).
            if (spec := running_spec(self._bus, self.config.run_id, episode)) is not None:
                self._begin(episode, spec)
                return self._episode
            log.warning("ignoring messages of episode %d: its start event was not seen", episode)
        return None

    def _on_event(self, event: EpisodeEvent) -> None:
        number = event.header.episode
        if event.kind == EventKind.START and event.spec is not None:
            if not (self._episode is not None and self._episode.number == number):  # not already recovered
                self._begin(number, event.spec)
            return
        current = self._current(number)
        if current is None:
            return
        if event.kind == EventKind.BRAIN_SWITCH and event.brain:
            self._on_switch(current, event)
        elif event.kind == EventKind.END:
            current.end = event
            current.end_arrival = time.monotonic()

    @staticmethod
    def _on_switch(current: _Episode, event: EpisodeEvent) -> None:
        # The event's stamp is that of the first frame the new brain drove.
        seq = round(event.header.stamp_ns / current.spec.step_ns)
        current.commands.add_switch(
            BrainSwitch(stamp_ns=event.header.stamp_ns, seq=seq, from_brain=event.detail, to_brain=event.brain)
        )
        current.active_brain = event.brain
        log.info("episode %d: %s drives from frame %d on (was %s)", current.number, event.brain, seq, event.detail)

    def _begin(self, number: int, spec: EpisodeSpec) -> None:
        try:
            circuit = load_circuit(spec.circuit, direction=spec.direction)
        except CircuitError as error:
            log.warning("cannot score episode %d: %s", number, error)
            return
        scorer = EpisodeScorer(circuit=circuit, laps_target=spec.laps, step_s=spec.step_s)
        commands = CommandMatcher(first_driver=spec.active_brain, on_driver=_driver_feed(scorer))
        self._episode = _Episode(
            number=number, spec=spec, scorer=scorer, commands=commands, active_brain=spec.active_brain
        )

    def _on_pose(self, pose: Pose, *, key: str) -> None:
        if not (abs(pose.x_m) <= MAX_POSITION_M and abs(pose.y_m) <= MAX_POSITION_M):
            # Finite, so it decoded, but no car of any circuit is there, and squared it overflows the metrics.
            self._bus.rejects.reject(
                key, ValueError(f"pose at ({pose.x_m}, {pose.y_m}) m: beyond +-{MAX_POSITION_M:g} m")
            )
            return
        current = self._current(pose.header.episode)
        if current is None or pose.header.seq <= current.last_pose_seq:
            return
        current.last_pose_seq = pose.header.seq
        current.scorer.add_pose(
            seq=pose.header.seq,
            stamp_ns=pose.header.stamp_ns,
            x_m=pose.x_m,
            y_m=pose.y_m,
            yaw_rad=pose.yaw_rad,
            command_latency_ns=pose.command_latency_ns,
        )

    def _on_command(self, command: Command, *, key: str) -> None:
        if problem := command.problem():
            # It drove nothing (the simulator ends the episode on it, or it came from a shadow), and a huge finite
            # value would overflow the metrics: dropped, said once per key.
            self._bus.rejects.reject(key, ValueError(problem))
            return
        current = self._current(command.header.episode)
        if current is not None:
            current.commands.add_command(command)

    def _brains_behind(self, current: _Episode, frame_seq: int) -> list[str]:
        """The brain hosts alive on the run that have not yet answered frame ``frame_seq`` of ``current``."""
        alive = sorted(keys.parse_alive(key)[2] for key in self._brains.alive())
        return [name for name in alive if not current.commands.answered(name, frame_seq)]

    def _maybe_finish(self) -> None:
        current = self._episode
        if current is None or current.end is None:
            return
        poses_in = current.last_pose_seq >= current.end.last_pose_seq
        # Lock-step: the driver answered every frame before the last pose, and its commands come straight from the
        # brain, not with END: wait for the last one too, or the score would depend on which arrived first.
        last_answered_frame = current.end.last_pose_seq - 1
        driver_gone = current.end.reason == EndReason.BRAIN_LOST  # its last command may have died with it
        commands_in = current.spec.realtime or driver_gone or current.commands.driver_answered(last_answered_frame)
        # A shadow's answers come on its own time (it never holds the simulator up): scored as soon as the driver's
        # were in, a shadow that was a moment behind (a busy machine) was missing from the score altogether.
        behind = [] if current.spec.realtime or not commands_in else self._brains_behind(current, last_answered_frame)
        complete = poses_in and commands_in and not behind
        if not complete and time.monotonic() - current.end_arrival < POSE_GRACE_S:
            return
        if behind:
            log.warning(
                "episode %d: scoring without the answers of %s to frame %d",
                current.number,
                ", ".join(behind),
                last_answered_frame,
            )
        if not poses_in:
            log.warning(
                "episode %d: scoring without poses %d..%d (never arrived)",
                current.number,
                current.last_pose_seq + 1,
                current.end.last_pose_seq,
            )
        if not commands_in:
            log.warning(
                "episode %d: scoring without the driver's answer to frame %d", current.number, last_answered_frame
            )
        wall_time_s = current.end.wall_elapsed_ns / 1e9 or (time.monotonic() - current.wall_start)
        shadows = current.commands.finish()  # first: it hands the last driver commands to the metrics
        metrics = current.scorer.finish(wall_time_s=wall_time_s)
        score = EpisodeScore(
            header=Header(
                run_id=self.config.run_id, episode=current.number, seq=0, stamp_ns=current.end.header.stamp_ns
            ),
            spec=current.spec,
            reason=current.end.reason or EndReason.STOPPED,
            brain=current.active_brain,
            metrics=metrics,
            switches=list(current.commands.switches),
            shadows=shadows,
            detail=current.end.detail,
        )
        self._scores.publish(score)
        self._scored.add(current.number)
        self._episode = None
        log.info(
            "episode %d scored: %s, %.1f %% of a lap, %d laps",
            current.number,
            score.reason,
            metrics.percentage_completed,
            metrics.completed_laps,
        )

    def _maybe_publish_live(self) -> None:
        current = self._episode
        now = time.monotonic()
        if current is None or now < self._next_live:
            return
        self._next_live = now + 1.0 / self.config.live_rate_hz
        live = current.scorer.live()
        wall_s = now - current.wall_start
        self._live.publish(
            LiveMetrics(
                header=Header(
                    run_id=self.config.run_id,
                    episode=current.number,
                    seq=self._live_seq,
                    stamp_ns=int(live["sim_time_s"] * 1e9),
                ),
                progress_laps=live["progress_laps"],
                laps_target=current.spec.laps,
                completed_laps=live["completed_laps"],
                sim_time_s=live["sim_time_s"],
                real_time_factor=live["sim_time_s"] / wall_s if wall_s > 0 else 0.0,
                cross_track_m=live["cross_track_m"],
                speed_mps=live["speed_mps"],
            )
        )
        self._live_seq += 1


def _driver_feed(scorer: EpisodeScorer):
    """The driving brain's commands, as the metrics take them."""

    def feed(command: Command) -> None:
        scorer.add_command(
            stamp_ns=command.header.stamp_ns,
            speed_mps=command.speed_mps,
            yaw_rate_radps=command.yaw_rate_radps,
            inference_ns=command.inference_ns,
            model_inference_ns=command.model_inference_ns,
            suddenness=command.suddenness,
            gpu=command.gpu,
        )

    return feed


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import service_main

    return service_main(
        "scorer", "drivebench scorer: live metrics and one final score per episode", ScorerConfig, ScorerService, argv
    )
