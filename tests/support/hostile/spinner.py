"""Loops forever in ``act``."""

from __future__ import annotations

from brains.base import Action, Observation
from support.hostile.base import Driving


class SpinnerBrain(Driving):
    def act(self, observation: Observation) -> Action:
        while True:
            pass
