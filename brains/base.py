"""The brain protocol: what every driving brain implements, whatever it is made of.

A brain turns camera images into (speed, yaw rate) commands. It knows nothing of the bus: the brain host
(``python -m brains``) feeds it observations and publishes its actions. It keeps no state between episodes
beyond what ``reset`` re-initialises, so episodes are independent and repeatable.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Observation:
    """What a brain sees at one control step.

    image_rgb: H x W x 3 uint8, RGB, row 0 at the top (the car's front camera, possibly perturbed).
    stamp_ns: simulated time of the frame in ns since the episode start.
    seq: frame number within the episode (0, 1, 2, ...).
    """

    image_rgb: np.ndarray
    stamp_ns: int
    seq: int


@dataclass(frozen=True)
class Action:
    """A driving command in the car frame.

    speed_mps: forward speed along the car's x axis, m/s.
    yaw_rate_radps: yaw rate, rad/s, positive = turning left (anticlockwise seen from above).
    """

    speed_mps: float
    yaw_rate_radps: float


@runtime_checkable
class Brain(Protocol):
    """Implemented by every brain. ``reset`` is called before the first frame of every episode."""

    def reset(self, *, seed: int) -> None:
        """Forget everything from the previous episode; seed any randomness from ``seed``."""

    def act(self, observation: Observation) -> Action:
        """The command answering ``observation``. Called once per frame, in frame order."""
