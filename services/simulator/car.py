"""The car: a kinematic unicycle integrated exactly, like Gazebo's planar_move plugin in Behavior Metrics.

The brain's (speed, yaw rate) command is realised exactly over a step: the car moves along the circular arc
(or the straight line) that a constant (v, w) traces. Pure and deterministic; no PyBullet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# Below this |yaw rate| (rad/s) the arc formula loses precision (v/w blows up): use the straight-line limit.
_STRAIGHT_YAW_RATE_RADPS = 1e-9


@dataclass(frozen=True)
class CarState:
    """Pose of the car, world_from_car.

    x_m, y_m: position of the car origin in the world frame, metres.
    yaw_rad: heading of the car's x axis, anticlockwise from the world x axis, in (-pi, pi].
    """

    x_m: float
    y_m: float
    yaw_rad: float


def wrap_angle(angle_rad: float) -> float:
    """``angle_rad`` wrapped into (-pi, pi]."""
    wrapped = math.remainder(angle_rad, math.tau)  # in [-pi, pi]
    return math.pi if wrapped == -math.pi else wrapped


def integrate_unicycle(state: CarState, *, speed_mps: float, yaw_rate_radps: float, dt_s: float) -> CarState:
    """The pose after driving at constant ``speed_mps`` (along the car's x) and ``yaw_rate_radps`` (anticlockwise)
    for ``dt_s`` seconds, integrated exactly along the arc."""
    v, w, theta = float(speed_mps), float(yaw_rate_radps), state.yaw_rad
    if abs(w) < _STRAIGHT_YAW_RATE_RADPS:
        x = state.x_m + v * dt_s * math.cos(theta)
        y = state.y_m + v * dt_s * math.sin(theta)
    else:
        theta_end = theta + w * dt_s
        radius = v / w
        x = state.x_m + radius * (math.sin(theta_end) - math.sin(theta))
        y = state.y_m - radius * (math.cos(theta_end) - math.cos(theta))
    return CarState(x_m=x, y_m=y, yaw_rad=wrap_angle(theta + w * dt_s))
