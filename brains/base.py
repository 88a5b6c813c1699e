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
class GroundTruth:
    """Privileged facts about the car when a frame was taken, for brains that declare ``needs_ground_truth``
    (experts that label data; never a vision brain under test).

    x_m, y_m, yaw_rad: world_from_car, metres and radians (yaw anticlockwise from world x).
    circuit: the episode's circuit name; direction: "forward" or "reverse" (``EpisodeSpec.direction``).
    """

    x_m: float
    y_m: float
    yaw_rad: float
    circuit: str
    direction: str = "forward"


@dataclass(frozen=True)
class Observation:
    """What a brain sees at one control step.

    image_rgb: H x W x 3 uint8, RGB, row 0 at the top (the car's front camera, possibly perturbed).
    stamp_ns: simulated time of the frame in ns since the episode start.
    seq: frame number within the episode (0, 1, 2, ...).
    ground_truth: the car's true pose, only for a brain whose class sets ``needs_ground_truth = True``.
    """

    image_rgb: np.ndarray
    stamp_ns: int
    seq: int
    ground_truth: GroundTruth | None = None


@dataclass(frozen=True)
class Action:
    """A driving command in the car frame.

    speed_mps: forward speed along the car's x axis, m/s.
    yaw_rate_radps: yaw rate, rad/s, positive = turning left (anticlockwise seen from above).
    model_inference_s: optional, the brain's own timing of its model for this command (Behavior Metrics' brains
        keep one, ``inference_times``, around the network's predict only), s; None = it keeps none. The host times
        all of ``act`` regardless; BM's ``mean_inference_time`` is the mean of the brain's own timings.
    suddenness: optional, the brain's own suddenness value for this command (BM's brains append
        ‖(v, w)_t − (v, w)_{t−1}‖ of their normalised outputs to ``suddenness_distance``); None = it keeps none.
    """

    speed_mps: float
    yaw_rate_radps: float
    model_inference_s: float | None = None
    suddenness: float | None = None


@runtime_checkable
class Brain(Protocol):
    """Implemented by every brain. ``reset`` is called before the first frame of every episode.

    A brain may also set ``needs_ground_truth = True`` (class attribute): its host then waits for the simulator's
    pose of every frame and passes it as ``Observation.ground_truth``.
    """

    def reset(self, *, seed: int) -> None:
        """Forget everything from the previous episode; seed any randomness from ``seed``."""

    def act(self, observation: Observation) -> Action:
        """The command answering ``observation``. Called once per frame, in frame order."""
