"""An episode's trajectory as the stack lived it: ground-truth poses and live metrics as received, written to
``trajectory.npz`` for the report's trajectory plots and progress curves (a matrix's episode executor keeps one per
episode)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from orchestrator.stack.launcher import LocalStack
from protocol import keys
from protocol.bus import Inbox, Subscription
from protocol.messages import LiveMetrics, Pose

SETTLE_S = 2.0  # the longest a trajectory waits for its last pose after the score came


class Trace:
    """An episode's ground-truth poses and live metrics, as received, for trajectory plots and progress curves."""

    def __init__(self) -> None:
        self._poses = Inbox()
        self._received: list[Pose] = []
        self._live: list[tuple[float, float, float]] = []
        self._subscription: Subscription | None = None

    def attach(self, stack: LocalStack) -> None:
        assert stack.bus is not None
        self._subscription = stack.bus.subscribe(keys.pose(stack.run_id), Pose, inbox=self._poses)

    def detach(self) -> None:
        """Stop receiving poses (a warm stack's bus outlives the episode; its subscriptions must not pile up)."""
        if self._subscription is not None:
            self._subscription.close()
            self._subscription = None

    def settle(self, *, last_seq: int, episode: int | None, timeout_s: float = SETTLE_S) -> None:
        """Wait (at most ``timeout_s``) for the episode's last pose, ``last_seq``: the score can overtake the last
        poses on a loaded machine, and a trajectory must not lose its end to that (seen: 3 of 61 poses)."""
        deadline = time.monotonic() + timeout_s
        while True:
            self._received.extend(p.message for p in self._poses.drain())
            if any(p.header.seq >= last_seq and episode in (None, p.header.episode) for p in self._received):
                return
            remaining_s = deadline - time.monotonic()
            if remaining_s <= 0:
                return
            arrived = self._poses.recv(timeout_s=min(remaining_s, 0.05))
            if arrived is not None:
                self._received.append(arrived.message)

    def add_live(self, live: LiveMetrics) -> None:
        self._live.append((live.sim_time_s, live.progress_laps, live.cross_track_m))

    def save(self, path: Path, *, episode: int | None = None) -> Path:
        """Write the trajectory; ``episode``: keep only that episode's poses (on a warm stack, a pose of the episode
        before may still trail in after this one's subscription began)."""
        received = self._received + [p.message for p in self._poses.drain()]
        if episode is not None:
            received = [pose for pose in received if pose.header.episode == episode]
        # The first pose of each frame: a lock-step resend of a frame nobody answered yet publishes its pose again
        # with the speed zeroed, and the trajectory must not depend on whether the brain was slow to its first answer.
        first: dict[int, Pose] = {}
        for pose in received:
            first.setdefault(pose.header.seq, pose)
        poses = sorted(first.items())
        rows = np.array(
            [(pose.header.stamp_ns / 1e9, pose.x_m, pose.y_m, pose.yaw_rad, pose.speed_mps) for _, pose in poses],
            dtype=np.float64,
        ).reshape(-1, 5)
        live = np.array(self._live, dtype=np.float64).reshape(-1, 3)
        np.savez_compressed(
            path,
            stamp_s=rows[:, 0],
            x_m=rows[:, 1],
            y_m=rows[:, 2],
            yaw_rad=rows[:, 3],
            speed_mps=rows[:, 4],
            live_sim_time_s=live[:, 0],
            live_progress_laps=live[:, 1],
            live_cross_track_m=live[:, 2],
        )
        return path


__all__ = ["SETTLE_S", "Trace"]
