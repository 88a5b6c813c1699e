"""Circuit geometry: built-in circuits are closed and sane; projection is exact and keeps to its branch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.circuits import Centreline, CircuitError, circuit_names, load_circuit


def brute_force(centreline: Centreline, x: float, y: float) -> tuple[float, float]:
    """(distance, s) of the closest point over every segment."""
    p = centreline.points_m
    v = np.roll(p, -1, axis=0) - p
    t = np.clip(((x - p[:, 0]) * v[:, 0] + (y - p[:, 1]) * v[:, 1]) / (v ** 2).sum(axis=1), 0, 1)
    d = np.hypot(x - (p[:, 0] + t * v[:, 0]), y - (p[:, 1] + t * v[:, 1]))
    i = int(np.argmin(d))
    return float(d[i]), float(centreline.s_m[i] + t[i] * np.hypot(*v[i]))


def segments_cross(a, b, c, d) -> bool:
    def orient(p, q, r):
        return np.sign((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))
    return orient(a, b, c) != orient(a, b, d) and orient(c, d, a) != orient(c, d, b)


@pytest.mark.parametrize("name", circuit_names())
def test_builtin_circuit_is_closed_simple_and_at_behavior_metrics_scale(name):
    circuit = load_circuit(name)
    points = circuit.centreline.points_m
    steps = np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)
    assert steps.max() < 0.3 and steps.min() > 0.2  # resampled at ~0.25 m, closing gap included
    assert 400 < circuit.length_m < 1600
    assert circuit.road_half_width_m == pytest.approx(1.5)
    # Not self-intersecting: no two non-adjacent segments of a coarse copy cross.
    coarse = points[::8]
    n = len(coarse)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            assert not segments_cross(coarse[i], coarse[(i + 1) % n], coarse[j], coarse[(j + 1) % n]), (i, j)
    x, y, yaw = circuit.start_pose()
    assert (x, y) == tuple(points[0]) and -math.pi <= yaw <= math.pi


def test_simple_circuit_size_matches_behavior_metrics():
    circuit = load_circuit("simple")
    assert 430 < circuit.length_m < 460
    extent = np.ptp(circuit.centreline.points_m, axis=0)
    assert 100 < extent[0] < 120 and 100 < extent[1] < 120


def test_projection_matches_brute_force_and_tracking():
    centreline = load_circuit("simple").centreline
    rng = np.random.default_rng(0)
    s_prev = None
    for s in np.linspace(0, centreline.length_m, 400, endpoint=False):
        x, y, heading = centreline.pose_at(s)
        offset = rng.uniform(-1.4, 1.4)
        px, py = x - offset * math.sin(heading), y + offset * math.cos(heading)
        for near in (None, s_prev):
            projection = centreline.project(px, py, near_s_m=near)
            distance, _ = brute_force(centreline, px, py)
            assert abs(projection.lateral_m) == pytest.approx(distance, abs=1e-9)
        assert projection.lateral_m == pytest.approx(offset, abs=0.05)  # + is left
        s_prev = projection.s_m


def test_tracking_keeps_to_its_own_branch_where_two_run_close():
    # A hairpin: two straights 2.5 m apart, joined by half circles.
    half = np.linspace(-np.pi / 2, np.pi / 2, 40, endpoint=False)
    top = np.column_stack([np.linspace(0, 100, 400, endpoint=False), np.zeros(400)])
    right = np.column_stack([100 + 1.25 * np.cos(half), 1.25 + 1.25 * np.sin(half)])
    bottom = np.column_stack([np.linspace(100, 0, 400, endpoint=False), np.full(400, 2.5)])
    left = np.column_stack([-1.25 * np.cos(half), 1.25 - 1.25 * np.sin(half)])
    centreline = Centreline(np.vstack([top, right, bottom, left]))
    start = centreline.project(10.0, 0.0)
    # 1.4 m left of the first straight: nearer the other straight (1.1 m), but the car is still on its own.
    tracked = centreline.project(10.5, 1.4, near_s_m=start.s_m)
    assert tracked.lateral_m == pytest.approx(1.4)
    assert centreline.project(10.5, 1.4).lateral_m == pytest.approx(1.1)  # the global answer is the other branch


def test_unknown_circuit_names_the_known_ones():
    with pytest.raises(CircuitError, match=r"unknown circuit 'monza' \(known: .*simple"):
        load_circuit("monza")


def test_bad_centrelines_are_rejected():
    with pytest.raises(ValueError, match="N >= 3"):
        Centreline(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="finite"):
        Centreline(np.array([[0, 0], [1, np.nan], [2, 0]]))
    with pytest.raises(ValueError, match="repeated"):
        Centreline(np.array([[0, 0], [0, 0], [1, 1]]))
