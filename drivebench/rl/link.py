"""The environment's place in the stack: it takes the brain's part on the bus (frames in, commands out) and
listens to what it needs for rewards and ``info`` (poses, episode events, live metrics, scores).

It declares a brain's liveliness token under its own name, so the simulator drives with its commands in
lock-step: frame n goes out, the simulator waits for the command that answers frame n, steps, sends frame n+1.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from protocol import keys
from protocol.bus import Bus, Inbox, Subscription, Traffic
from protocol.images import frame_image
from protocol.messages import (
    CameraFrame,
    Command,
    EndReason,
    EpisodeEvent,
    EpisodeScore,
    EventKind,
    Header,
    LiveMetrics,
    Pose,
)

POLL_S = 0.2  # how often a wait checks that the stack still stands


@dataclass
class Transition:
    """What came back for one frame: its image (None at the episode's end), the pose and, at the end, the END."""

    image: np.ndarray | None
    pose: Pose
    seq: int
    end: EpisodeEvent | None = None


@dataclass
class _Episode:
    number: int
    images: dict[int, np.ndarray] = field(default_factory=dict)
    poses: dict[int, Pose] = field(default_factory=dict)
    end: EpisodeEvent | None = None


class BrainLink:
    """The brain's end of one run, on ``bus``: ``name`` is its bus name (the spec's ``active_brain``)."""

    def __init__(self, bus: Bus, *, run_id: str, name: str, perturbed: bool, check: Callable[[], None]):
        self.bus, self.run_id, self.name = bus, run_id, keys.check_name(name, what="brain name")
        self._check = check  # raises when the stack no longer stands
        self._inbox = Inbox()
        camera = keys.camera_perturbed(run_id) if perturbed else keys.camera_raw(run_id)
        self._subscriptions: list[Subscription] = [
            bus.subscribe(camera, CameraFrame, inbox=self._inbox),
            bus.subscribe(keys.pose(run_id), Pose, inbox=self._inbox),
            bus.subscribe(keys.events(run_id), EpisodeEvent, inbox=self._inbox),
        ]
        self._live = bus.subscribe(keys.live_metrics(run_id), LiveMetrics, keep_last=1)
        self._scores = bus.subscribe(keys.score(run_id), EpisodeScore)
        self._commands = bus.publisher(keys.command(run_id, self.name), Command, Traffic.COMMANDS)
        self._command_seq = 0
        self._episode: _Episode | None = None
        self._last_image: np.ndarray | None = None
        self._live_kept: LiveMetrics | None = None
        self._withdraw = bus.declare_alive(keys.alive(run_id, "brain", self.name))

    def follow(self, episode: int) -> None:
        """From now on collect the frames of ``episode`` (earlier ones are dropped)."""
        self._episode = _Episode(episode)
        self._last_image = None
        self._live_kept = None

    def ended(self) -> bool:
        return self._episode is not None and self._episode.end is not None

    def answer(self, seq: int, *, stamp_ns: int, speed_mps: float, yaw_rate_radps: float) -> None:
        """Publish the command that answers frame ``seq`` of the followed episode."""
        assert self._episode is not None
        header = Header(run_id=self.run_id, episode=self._episode.number, seq=self._command_seq, stamp_ns=stamp_ns)
        self._command_seq += 1
        self._commands.publish(
            Command(header=header, brain=self.name, frame_seq=seq, speed_mps=speed_mps, yaw_rate_radps=yaw_rate_radps)
        )

    def wait(self, seq: int, *, timeout_s: float) -> Transition:
        """Frame ``seq`` and its pose, or the episode's END and its last pose; TimeoutError after ``timeout_s``."""
        assert self._episode is not None
        episode = self._episode
        deadline = time.monotonic() + timeout_s
        next_check = 0.0
        while True:
            if seq in episode.images and seq in episode.poses:
                return Transition(image=episode.images[seq], pose=episode.poses[seq], seq=seq)
            if episode.end is not None and episode.end.last_pose_seq in episode.poses:
                last = episode.end.last_pose_seq
                return Transition(image=None, pose=episode.poses[last], seq=last, end=episode.end)
            now = time.monotonic()
            if now >= next_check:
                self._check()
                next_check = now + POLL_S
            if now > deadline:
                raise TimeoutError(f"no frame {seq} of episode {episode.number} after {timeout_s:.0f} s")
            received = self._inbox.recv(timeout_s=POLL_S)
            if received is not None:
                self._take(received.message, episode)

    def _take(self, message, episode: _Episode) -> None:
        if message.header.episode != episode.number:
            return  # another episode's (a stopped one's END, a frame that trailed in)
        if isinstance(message, CameraFrame):
            if message.header.seq not in episode.images:  # the simulator resends a frame nobody answered yet
                if not message.dropped:
                    image = np.array(frame_image(message))
                elif self._last_image is not None:  # lost by the noise injector: the last image stands
                    image = self._last_image
                else:
                    image = np.zeros((message.height_px, message.width_px, 3), np.uint8)
                episode.images[message.header.seq] = self._last_image = image
            episode.images.pop(message.header.seq - 2, None)
        elif isinstance(message, Pose):
            episode.poses[message.header.seq] = message
            episode.poses.pop(message.header.seq - 2, None)
        elif message.kind == EventKind.END:
            episode.end = message

    def wait_end(self, *, timeout_s: float) -> None:
        """Until the followed episode's END came (after a stop)."""
        assert self._episode is not None
        deadline = time.monotonic() + timeout_s
        while self._episode.end is None and time.monotonic() < deadline:
            received = self._inbox.recv(timeout_s=POLL_S)
            if received is not None:
                self._take(received.message, self._episode)
            self._check()
        if self._episode.end is None:
            raise TimeoutError(f"episode {self._episode.number} did not end within {timeout_s:.0f} s of a stop")

    def latest_live(self) -> LiveMetrics | None:
        """The newest live metrics of the followed episode, if any came."""
        received = None
        while (newer := self._live.recv(timeout_s=0)) is not None:
            received = newer
        if received is not None and self._episode is not None:
            if received.message.header.episode == self._episode.number:
                self._live_kept = received.message
        return self._live_kept

    def score(self, episode: int, *, timeout_s: float) -> EpisodeScore | None:
        """The scorer's score of ``episode``, waiting up to ``timeout_s``; None when none came."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            received = self._scores.recv(timeout_s=min(left, POLL_S))
            if received is not None and received.message.header.episode == episode:
                return received.message
        return None

    def close(self) -> None:
        self._withdraw()
        subscriptions: list[Subscription] = [*self._subscriptions, self._live, self._scores]
        for subscription in subscriptions:
            subscription.close()


TERMINAL_REASONS = (EndReason.CRASH, EndReason.OFF_TRACK, EndReason.LAPS_COMPLETED)


def ending(end: EpisodeEvent | None) -> tuple[bool, bool]:
    """(terminated, truncated) of an episode's END: a crash, leaving the road or the lap target end the task
    (terminated); the time limit, or anything else that cut it short (a stop, a timeout), truncates it."""
    if end is None:
        return False, False
    return (True, False) if end.reason in TERMINAL_REASONS else (False, True)
