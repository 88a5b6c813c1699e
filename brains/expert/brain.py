"""The privileged expert: pure pursuit on the circuit's centre line from the car's ground-truth pose.

It never looks at the image, so it drives any world the same way: no line, white road, no walls, a moved camera, a
noisy camera. That is what a domain-randomised dataset needs, since the explicit brain follows the red line's pixels
and cannot label a world without one (CARLA's autopilot plays the same role from the map). The brain host gives it
the pose the simulator published for each frame (``needs_ground_truth``); it is for collecting data and for upper
bounds in matrices, not a vision brain.

Per frame:
1. Project the car onto the centre line (tracking its previous projection, so hairpins never confuse it).
2. Speed: ``sqrt(lateral_accel_mps2 / curvature)`` for the tightest curvature within the braking distance ahead,
   clipped to ``[min_speed_mps, max_speed_mps]``, and changed by at most ``accel_mps2`` per second.
3. Yaw rate: pure pursuit towards the centre-line point ``lookahead_s * v`` (at least ``min_lookahead_m``) ahead:
   ``w = 2 v sin(alpha) / L``, ``alpha`` the bearing of that point in the car frame.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from brains.base import Action, GroundTruth, Observation

CURVATURE_WINDOW_M = 4.0  # curvature is smoothed over this much centre line (its points are 0.25 m apart)


@lru_cache(maxsize=8)
def _route(circuit: str, direction: str):
    """The circuit in the driven direction and its smoothed curvature (1/m) at each centre-line point."""
    from circuits import load_circuit

    track = load_circuit(circuit, direction=direction)
    centreline = track.centreline
    headings = centreline.headings_rad()
    turn = np.angle(np.exp(1j * (np.roll(headings, -1) - headings)))  # heading change per segment, wrapped
    step_m = centreline.length_m / len(centreline)
    width = max(1, int(round(CURVATURE_WINDOW_M / step_m)))
    kernel = np.ones(width) / width
    padded = np.concatenate([turn[-width:], turn, turn[:width]])
    curvature = np.abs(np.convolve(padded, kernel, mode="same")[width:-width]) / step_m
    return centreline, curvature, step_m


class ExpertBrain:
    """Pure pursuit on ground truth (see the module docstring); every constant is a keyword option.

    max_speed_mps / min_speed_mps: speed limits; lateral_accel_mps2: the grip the speed rule allows in a curve;
    accel_mps2: the most the speed changes per second; braking_distance_m: how far ahead curves slow it down;
    lookahead_s / min_lookahead_m: pure pursuit's look-ahead distance, as time at the current speed and a floor.
    """

    needs_ground_truth = True

    def __init__(
        self,
        *,
        max_speed_mps: float = 12.0,
        min_speed_mps: float = 4.0,
        lateral_accel_mps2: float = 5.0,
        accel_mps2: float = 4.0,
        braking_distance_m: float = 18.0,
        lookahead_s: float = 0.35,
        min_lookahead_m: float = 2.5,
    ):
        if not 0 < min_speed_mps <= max_speed_mps or lateral_accel_mps2 <= 0 or accel_mps2 <= 0:
            raise ValueError("need 0 < min_speed_mps <= max_speed_mps, lateral_accel_mps2 > 0 and accel_mps2 > 0")
        self.max_speed_mps, self.min_speed_mps = float(max_speed_mps), float(min_speed_mps)
        self.lateral_accel_mps2, self.accel_mps2 = float(lateral_accel_mps2), float(accel_mps2)
        self.braking_distance_m = float(braking_distance_m)
        self.lookahead_s, self.min_lookahead_m = float(lookahead_s), float(min_lookahead_m)
        self.reset(seed=0)

    def reset(self, *, seed: int) -> None:
        self._s_m: float | None = None
        self._speed_mps = self.min_speed_mps
        self._last_stamp_ns: int | None = None

    def act(self, observation: Observation) -> Action:
        truth = observation.ground_truth
        if truth is None:  # the host could not get this frame's pose (it logs why): hold the speed, steer straight
            return Action(speed_mps=self._speed_mps, yaw_rate_radps=0.0)
        centreline, curvature, step_m = _route(truth.circuit, truth.direction)
        s_m = centreline.project(truth.x_m, truth.y_m, near_s_m=self._s_m).s_m
        self._s_m = s_m
        dt_s = 0.05 if self._last_stamp_ns is None else max(1e-3, (observation.stamp_ns - self._last_stamp_ns) * 1e-9)
        self._last_stamp_ns = observation.stamp_ns
        self._speed_mps = self._next_speed(s_m, curvature, step_m, dt_s)
        return Action(speed_mps=self._speed_mps, yaw_rate_radps=self._yaw_rate(truth, centreline, s_m))

    def _next_speed(self, s_m: float, curvature: np.ndarray, step_m: float, dt_s: float) -> float:
        first = int(s_m / step_m)
        ahead = np.take(curvature, np.arange(first, first + int(self.braking_distance_m / step_m) + 1), mode="wrap")
        tightest = float(ahead.max())
        target = self.max_speed_mps if tightest <= 0 else math.sqrt(self.lateral_accel_mps2 / tightest)
        target = min(max(target, self.min_speed_mps), self.max_speed_mps)
        change = self.accel_mps2 * dt_s
        return min(max(target, self._speed_mps - 2 * change), self._speed_mps + change)  # brakes twice as hard

    def _yaw_rate(self, truth: GroundTruth, centreline, s_m: float) -> float:
        lookahead_m = max(self.min_lookahead_m, self.lookahead_s * self._speed_mps)
        x, y, _ = centreline.pose_at(s_m + lookahead_m)
        alpha = math.atan2(y - truth.y_m, x - truth.x_m) - truth.yaw_rad
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        distance_m = math.hypot(x - truth.x_m, y - truth.y_m)
        return 2.0 * self._speed_mps * math.sin(alpha) / max(distance_m, 1e-6)
