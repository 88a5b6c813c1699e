"""The reward of ``drivebench/LaneFollow-v0``, computed from the simulator's ground-truth poses (pure, no bus).

Per step (one lock-step step, ``step_s`` of simulated time):

    reward = progress_m * max(0, 1 - |lateral_m| / road_half_width_m)
             - smoothness * ||action - previous_action||^2
             - crash_penalty   (only on the step that ends the episode by a crash or by leaving the road)

``progress_m`` is the signed arc length the car's projection on the centreline advanced (metres: driving
backwards is negative), ``lateral_m`` its distance from the centreline after the step, so a car on the line earns
its full progress and one at the road edge nothing. The smoothness term penalises jerky commands (actions are in
[-1, 1]^2, so the term is at most 8 x ``smoothness``). One lap of ``simple`` driven on the line earns ~440.
The projection is the simulator's own (``circuits.centreline``, searched near the previous arc length), so
progress here is the progress that ends the episode at the lap target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from circuits import Circuit


@dataclass(frozen=True)
class RewardTerms:
    """One step's reward and its parts (all in reward units but ``lateral_m``)."""

    reward: float
    progress_m: float
    lateral_m: float
    smoothness_penalty: float
    crash_penalty: float


class ProgressReward:
    """Tracks the car along ``circuit``'s centreline and scores each step (see the module docstring)."""

    def __init__(self, circuit: Circuit, *, smoothness: float, crash_penalty: float, start_m: float = 0.0):
        self.circuit = circuit
        self.smoothness = smoothness
        self.crash_penalty = crash_penalty
        self.reset(start_m=start_m)

    def reset(self, *, start_m: float = 0.0) -> None:
        """A new episode whose car starts ``start_m`` along the circuit (``EpisodeSpec.start_m``)."""
        self._s_m = start_m  # where the first projection searches from, as the simulator counts it
        self.progress_m = 0.0

    def step(self, *, x_m: float, y_m: float, action: np.ndarray, previous_action: np.ndarray, crashed: bool):
        """The terms of the step that brought the car to (x_m, y_m) with ``action`` after ``previous_action``."""
        centreline = self.circuit.centreline
        projection = centreline.project(x_m, y_m, near_s_m=self._s_m)
        progress_m = float(centreline.wrap_ds(projection.s_m - self._s_m))
        self._s_m = projection.s_m
        self.progress_m += progress_m
        centring = max(0.0, 1.0 - abs(projection.lateral_m) / self.circuit.road_half_width_m)
        jerk = float(np.sum((np.asarray(action, np.float64) - np.asarray(previous_action, np.float64)) ** 2))
        smoothness_penalty = self.smoothness * jerk
        crash_penalty = self.crash_penalty if crashed else 0.0
        return RewardTerms(
            reward=progress_m * centring - smoothness_penalty - crash_penalty,
            progress_m=progress_m,
            lateral_m=float(projection.lateral_m),
            smoothness_penalty=smoothness_penalty,
            crash_penalty=crash_penalty,
        )
