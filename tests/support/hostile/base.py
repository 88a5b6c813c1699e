"""What every hostile brain shares: it drives straight when its attack lets it drive at all."""

from __future__ import annotations

from brains.base import Action, Observation


class Driving:
    def reset(self, *, seed: int) -> None:
        del seed

    def act(self, observation: Observation) -> Action:
        del observation
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)
