"""Procedural circuits: ``random_circuit(seed)``, loaded by name as ``random:SEED``.

A candidate is a periodic cubic spline through 7-14 control points scattered around a circle: the points are
taken in clockwise order at evenly spaced angles with a random jitter, at random distances from the centre (so the
circle becomes bays, bulges, S-bends and the odd hairpin). A candidate is kept when

* its lap is 400-1500 m,
* it never turns tighter than :data:`MIN_RADIUS_M`,
* :func:`~services.circuits.library.check_track` passes with a :data:`MIN_GAP_M` centre-to-centre clearance (no
  crossing, and the walls of two parts of the track never come close),

otherwise the next candidate is drawn from a seed derived from ``(seed, attempt)``. Everything is drawn from
NumPy's PCG64 generator seeded by ``[seed, attempt]``, so a seed always gives the same circuit. The start is moved
to the straightest stretch of the lap (the point whose surroundings, :data:`START_WINDOW_M` either way, bend least).
Road, line and walls are at Behavior Metrics' scale (3 m, 0.10 m, 0.5 m).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import maximum_filter1d

from services.circuits.centreline import Centreline
from services.circuits.library import (
    RANDOM_PREFIX,
    RESAMPLE_STEP_M,
    Circuit,
    CircuitError,
    check_track,
    closed_spline,
    min_turn_radius_m,
    signed_area_m2,
    turn_radii_m,
)

ROAD_WIDTH_M = 3.0
LINE_WIDTH_M = 0.10
WALL_HEIGHT_M = 0.5
MIN_LENGTH_M = 400.0
MAX_LENGTH_M = 1500.0
MIN_RADIUS_M = 8.0
MIN_GAP_M = 8.0
START_WINDOW_M = 15.0
MAX_ATTEMPTS = 200


def random_circuit(seed: int) -> Circuit:
    """The procedural circuit of ``seed`` (a non-negative integer), named ``random:SEED``; see the module doc."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise CircuitError(f"a random circuit's seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, attempt])
        points = _candidate(rng)
        if points is not None:
            return Circuit(
                name=f"{RANDOM_PREFIX}{seed}",
                description=f"procedural circuit of seed {seed} (candidate {attempt})",
                source="drivebench procedural generator (services.circuits.generator)",
                centreline=Centreline(points),
                road_half_width_m=ROAD_WIDTH_M / 2,
                line_width_m=LINE_WIDTH_M,
                wall_height_m=WALL_HEIGHT_M,
            )
    raise CircuitError(f"no valid random circuit for seed {seed} in {MAX_ATTEMPTS} attempts")  # pragma: no cover


def _candidate(rng: np.random.Generator) -> np.ndarray | None:
    """A clockwise centreline resampled every RESAMPLE_STEP_M, starting on its straightest stretch; None if the
    draw fails a test."""
    count = int(rng.integers(7, 15))
    target_length = rng.uniform(450.0, 1350.0)
    # Scattered radii make the lap longer than the circle's circumference; 1.15 is the typical ratio.
    mean_radius = target_length / (2 * math.pi * 1.15)
    spacing = 2 * math.pi / count
    angles = -spacing * np.arange(count) + rng.uniform(-0.3, 0.3, count) * spacing  # clockwise
    radii = mean_radius * rng.uniform(0.55, 1.25, count)
    control = np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
    points = closed_spline(control, step_m=RESAMPLE_STEP_M)
    length = float(np.sum(np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)))
    if not MIN_LENGTH_M <= length <= MAX_LENGTH_M or signed_area_m2(points) >= 0:
        return None
    if min_turn_radius_m(points) < MIN_RADIUS_M:
        return None
    try:
        check_track(points, ROAD_WIDTH_M / 2, min_gap_m=MIN_GAP_M)
    except CircuitError:
        return None
    curvature = 1.0 / turn_radii_m(points)
    window = 2 * round(START_WINDOW_M / RESAMPLE_STEP_M) + 1
    worst_nearby = maximum_filter1d(curvature, size=window, mode="wrap")
    start = int(np.argmin(worst_nearby))
    return np.roll(points, -start, axis=0)
