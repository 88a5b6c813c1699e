"""The constant brain: same (speed, yaw rate) whatever it sees."""

from __future__ import annotations

from brains.base import Action, Observation


class ConstantBrain:
    """Always answers ``Action(speed_mps, yaw_rate_radps)``; ``delay_s`` sleeps before answering (timeout tests)."""

    def __init__(self, *, speed_mps: float = 1.0, yaw_rate_radps: float = 0.0, delay_s: float = 0.0):
        self._action = Action(speed_mps=float(speed_mps), yaw_rate_radps=float(yaw_rate_radps))
        self._delay_s = float(delay_s)

    def reset(self, *, seed: int) -> None:
        del seed  # nothing to forget

    def act(self, observation: Observation) -> Action:
        del observation
        if self._delay_s > 0:
            import time

            time.sleep(self._delay_s)
        return self._action
