"""The noisy driver: another brain's commands with seeded steering disturbances, to collect recovery data.

A network trained only on a perfect driver never sees the car off the line, so it never learns to come back
(covariate shift). DART-style collection fixes that: this brain drives with short bursts of extra yaw rate that push
the car off the line, while the undisturbed expert (the same base brain, as a second brain host) answers the same
frames; the dataset is labelled with the expert's commands (``drivebench dataset collect --recovery-noise``).
"""

from __future__ import annotations

import numpy as np

from brains.base import Action, Observation


class NoisyBrain:
    """Base brain ``base`` (built with ``base_options``) plus bursts of extra yaw rate.

    steering_noise_radps: peak size of a disturbance, rad/s (each burst draws 0.5-1x of it, either sign).
    burst_probability: chance per frame that a burst starts when none is running.
    burst_steps: (shortest, longest) burst length in frames.
    Bursts are drawn from ``seed`` (``reset``), so an episode is repeatable.
    """

    def __init__(
        self,
        *,
        base: str = "explicit",
        base_options: dict | None = None,
        steering_noise_radps: float = 0.5,
        burst_probability: float = 0.03,
        burst_steps: tuple[int, int] = (3, 8),
    ):
        from brains.registry import make_brain

        if base == "noisy":
            raise ValueError("the noisy brain cannot wrap itself")
        if steering_noise_radps < 0 or not 0 <= burst_probability <= 1 or not 1 <= burst_steps[0] <= burst_steps[1]:
            raise ValueError("need steering_noise_radps >= 0, 0 <= burst_probability <= 1, 1 <= shortest <= longest")
        self.base = make_brain(base, **(base_options or {}))
        self.steering_noise_radps = float(steering_noise_radps)
        self.burst_probability = float(burst_probability)
        self.burst_steps = (int(burst_steps[0]), int(burst_steps[1]))
        self.reset(seed=0)

    @property
    def needs_ground_truth(self) -> bool:
        """A privileged base (the expert) needs the pose through this wrapper too."""
        return bool(getattr(self.base, "needs_ground_truth", False))

    def reset(self, *, seed: int) -> None:
        self.base.reset(seed=seed)
        self._rng = np.random.default_rng(seed)
        self._burst_left = 0
        self._burst_radps = 0.0

    def act(self, observation: Observation) -> Action:
        action = self.base.act(observation)
        return Action(speed_mps=action.speed_mps, yaw_rate_radps=action.yaw_rate_radps + self._disturbance())

    def _disturbance(self) -> float:
        if self._burst_left == 0 and self._rng.random() < self.burst_probability:
            self._burst_left = int(self._rng.integers(self.burst_steps[0], self.burst_steps[1] + 1))
            self._burst_radps = float(
                self._rng.choice((-1.0, 1.0)) * self._rng.uniform(0.5, 1.0) * self.steering_noise_radps
            )
        if self._burst_left == 0:
            return 0.0
        self._burst_left -= 1
        return self._burst_radps
