"""A small feature vector of the centre line, measured in the camera image: what the RL policy drives from.

Behavior Metrics' own RL brains learn from a line-centre feature rather than pixels (``reference/gymnasium.md``):
a few hundred thousand steps from raw pixels are beyond two CPU cores, a dozen numbers are not. The features are
computed from the image alone, so a brain can compute them exactly as the environment did during training.

For each look-ahead distance ``d`` in ``LOOKAHEAD_M`` the image row that sees the ground ``d`` metres ahead (a level
pinhole camera ``CAMERA_HEIGHT_M`` above a flat road: row = centre + f h / d) is searched for line pixels (HSV
saturation >= 110 and value >= 15, the explicit brain's mask: the red line, not the grey road, the walls or the
sky). Their mean column gives the tangent of the line's bearing, ``(centre - x) / f`` (positive: the line is to the
left), clipped to [-1, 1]; a row without line pixels gives 0 and its "seen" flag 0. The vector is

    [tan bearing at each distance] + [seen flag at each distance] + [previous action (2 values in [-1, 1])]

all in [-1, 1]. The camera is assumed to be drivebench's default mount (0.10 m high, level, 90 deg field of view);
any size works, but below ~160 px wide the far rows merge (at 96 x 96 they are a pixel apart).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

LOOKAHEAD_M = (1.0, 2.0, 3.5, 6.0)
CAMERA_HEIGHT_M = 0.10  # CameraSpec's default mount
CAMERA_HFOV_RAD = 1.57
SATURATION_MIN = 110
VALUE_MIN = 15
BAND_ROWS = 1  # rows searched either side of each look-ahead row
FEATURES = 2 * len(LOOKAHEAD_M) + 2


def line_rows(*, height_px: int, width_px: int, hfov_rad: float = CAMERA_HFOV_RAD) -> list[int]:
    """The image row that sees the ground at each look-ahead distance (clipped to the image)."""
    focal_px = (width_px / 2.0) / math.tan(hfov_rad / 2.0)
    centre_row = (height_px - 1) / 2.0
    return [min(height_px - 1, round(centre_row + focal_px * CAMERA_HEIGHT_M / d)) for d in LOOKAHEAD_M]


def line_features(image_rgb: np.ndarray, *, previous_action: np.ndarray) -> np.ndarray:
    """The feature vector (float32, ``FEATURES`` values in [-1, 1]) of one H x W x 3 uint8 RGB image."""
    height_px, width_px = image_rgb.shape[:2]
    focal_px = (width_px / 2.0) / math.tan(CAMERA_HFOV_RAD / 2.0)
    centre_col = (width_px - 1) / 2.0
    bearings, seen = [], []
    for row in line_rows(height_px=height_px, width_px=width_px):
        band = image_rgb[max(0, row - BAND_ROWS) : row + BAND_ROWS + 1]
        hsv = cv2.cvtColor(np.ascontiguousarray(band), cv2.COLOR_RGB2HSV)
        columns = np.nonzero((hsv[..., 1] >= SATURATION_MIN) & (hsv[..., 2] >= VALUE_MIN))[1]
        if columns.size:
            bearings.append(float(np.clip((centre_col - columns.mean()) / focal_px, -1.0, 1.0)))
            seen.append(1.0)
        else:
            bearings.append(0.0)
            seen.append(0.0)
    previous = np.clip(np.asarray(previous_action, dtype=np.float64).reshape(2), -1.0, 1.0)
    return np.array([*bearings, *seen, *previous], dtype=np.float32)


def scaled(value: float, low: float, high: float) -> float:
    """``value`` in [-1, 1] mapped linearly onto [low, high]: how the environment turns an action into a command,
    and so how the policy brain does."""
    return low + (float(np.clip(value, -1.0, 1.0)) + 1.0) * 0.5 * (high - low)
