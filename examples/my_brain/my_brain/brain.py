"""MyBrain: a look-ahead line follower that slows down before bends, as a user's own brain would be written.

It implements drivebench's brain protocol (``brains.base.Brain``): ``reset(*, seed)`` and ``act(observation)``. It
looks for the red centre line in two bands of the image, near (what the car is on now) and far (what comes next):
the near band's offset steers, and the angle between the two bands says a bend is coming, which lowers the speed.
"""

from __future__ import annotations

import numpy as np

from brains.base import Action, Observation


class MyBrain:
    """Options (keyword-only, all optional): ``top_speed_mps``, ``bend_speed_mps``, ``steer_gain_radps``,
    ``damping_radps``: the speed on a straight and in a bend (m/s), and the PD gains on the line's normalised
    offset (rad/s for an offset of the whole half image)."""

    def __init__(
        self,
        *,
        top_speed_mps: float = 10.0,
        bend_speed_mps: float = 6.0,
        steer_gain_radps: float = 2.5,
        damping_radps: float = 3.0,
    ):
        self.top_speed_mps, self.bend_speed_mps = top_speed_mps, bend_speed_mps
        self.steer_gain_radps, self.damping_radps = steer_gain_radps, damping_radps
        self.reset(seed=0)

    def reset(self, *, seed: int) -> None:
        del seed  # deterministic
        self._previous_offset = 0.0

    def act(self, observation: Observation) -> Action:
        image = observation.image_rgb.astype(np.int16)
        height = image.shape[0]
        red = (image[..., 0] > 80) & (image[..., 0] > 2 * image[..., 1]) & (image[..., 0] > 2 * image[..., 2])
        near = _offset(red[height * 3 // 4 :])
        far = _offset(red[height // 2 : height * 5 // 8])
        offset = self._previous_offset if near is None else near
        bend = far is not None and near is not None and abs(far - near) > 0.15
        yaw_rate = self.steer_gain_radps * offset + self.damping_radps * (offset - self._previous_offset)
        self._previous_offset = offset
        return Action(
            speed_mps=self.bend_speed_mps if bend or near is None else self.top_speed_mps,
            yaw_rate_radps=float(yaw_rate),
        )


def _offset(mask: np.ndarray) -> float | None:
    """Where the line is across the band: -1 (right edge) .. 1 (left edge), positive left; None when not seen."""
    columns = np.nonzero(mask)[1]
    if columns.size == 0:
        return None
    half_width = mask.shape[1] / 2.0
    return float((half_width - columns.mean()) / half_width)
