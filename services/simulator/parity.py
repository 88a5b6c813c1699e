"""How alike two renderers' frames are: mean absolute difference, SSIM, and the poses to compare them at.

Pure NumPy. Used by ``benchmarks/renderer_parity.py`` (every circuit and variation) and by the parity test (a few
poses, loose thresholds).

SSIM is Wang et al. (2004): Gaussian window (sigma 1.5, 11 taps), ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2`` with
``L = 255``, on the luma (BT.601) of each image, averaged over the valid window positions (no padding).
"""

from __future__ import annotations

import math

import numpy as np

from circuits import Circuit
from services.simulator.car import CarState

_SIGMA = 1.5
_RADIUS = 5  # 11 taps
_C1 = (0.01 * 255) ** 2
_C2 = (0.03 * 255) ** 2


def mean_absolute_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Mean over pixels and channels of |a - b|, in 8-bit grey levels (0..255)."""
    _check_pair(a, b)
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))


def differing_fraction(a: np.ndarray, b: np.ndarray, *, tolerance: int = 8) -> float:
    """The fraction of pixels where some channel differs by more than ``tolerance`` grey levels."""
    _check_pair(a, b)
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2) > tolerance))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean structural similarity of two H x W x 3 uint8 RGB images (1.0: identical), on their luma."""
    _check_pair(a, b)
    if min(a.shape[:2]) < 2 * _RADIUS + 1:
        raise ValueError(f"images of at least {2 * _RADIUS + 1} px per side needed, got {a.shape[1]}x{a.shape[0]}")
    x, y = _luma(a), _luma(b)
    mu_x, mu_y = _blur(x), _blur(y)
    var_x = _blur(x * x) - mu_x**2
    var_y = _blur(y * y) - mu_y**2
    cov = _blur(x * y) - mu_x * mu_y
    index = ((2 * mu_x * mu_y + _C1) * (2 * cov + _C2)) / ((mu_x**2 + mu_y**2 + _C1) * (var_x + var_y + _C2))
    return float(index.mean())


def _check_pair(a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"need two H x W x 3 images of one size, got {a.shape} and {b.shape}")


def _luma(image: np.ndarray) -> np.ndarray:
    return image.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def _blur(image: np.ndarray) -> np.ndarray:
    """Separable Gaussian filter, valid positions only."""
    taps = np.exp(-0.5 * (np.arange(-_RADIUS, _RADIUS + 1) / _SIGMA) ** 2)
    taps /= taps.sum()
    rows = np.apply_along_axis(np.convolve, 1, image, taps, mode="valid")
    return np.apply_along_axis(np.convolve, 0, rows, taps, mode="valid")


def parity_poses(circuit: Circuit, *, count: int, seed: int = 0) -> list[CarState]:
    """``count`` car poses spread evenly round ``circuit``: on the road, up to 40 % of the half width off the centre
    line and up to 0.25 rad off the track heading (drawn from ``seed``), as a driving car sees it."""
    rng = np.random.default_rng([seed, 0xFA11])
    poses = []
    for index in range(count):
        s_m = (index + 0.5) * circuit.length_m / count
        x, y, heading = circuit.centreline.pose_at(s_m)
        lateral = float(rng.uniform(-0.4, 0.4)) * circuit.road_half_width_m
        turn = float(rng.uniform(-0.25, 0.25))
        poses.append(CarState(x - lateral * math.sin(heading), y + lateral * math.cos(heading), heading + turn))
    return poses
