"""Unit tests of the scorer's pure core (services/scorer/metrics.py): synthetic trajectories with known answers."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest
from scipy.interpolate import CubicSpline
from scipy.optimize import fmin

from circuits import Centreline, Circuit, load_circuit
from protocol.messages import EpisodeMetrics
from services.scorer.metrics import (
    EpisodeScorer,
    average_speed_mps,
    bm_lap_seconds,
    bm_nearest_checkpoint,
    bm_percentage_completed,
    bm_position_deviation,
    completed_distance_m,
    count_off_track_events,
    cross_track_stats,
    lap_crossing_times_s,
    lap_times_s,
    mean_inference_time_s,
    percentiles_ms,
    suddenness_distance,
)

STEP_S = 0.05
STEP_NS = 50_000_000


# --- synthetic circuits ------------------------------------------------------------------------------------------


def make_circuit(points: np.ndarray, half_width: float = 1.5) -> Circuit:
    return Circuit(
        name="synthetic",
        description="",
        source="",
        centreline=Centreline(points),
        road_half_width_m=half_width,
        line_width_m=0.1,
        wall_height_m=0.5,
    )


def circle_points(radius: float, spacing: float = 0.25) -> np.ndarray:
    """Anticlockwise circle starting at (radius, 0)."""
    count = round(2 * math.pi * radius / spacing)
    angles = np.arange(count) * 2 * math.pi / count
    return np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])


def stadium_points(straight: float, radius: float, spacing: float = 0.25) -> np.ndarray:
    """Anticlockwise stadium: the bottom straight y = -radius from x = -straight/2 to +straight/2 heading +x,
    a semicircle up on the right, the top straight heading -x, a semicircle down on the left."""
    half = straight / 2
    points = []
    n_straight = round(straight / spacing)
    n_arc = round(math.pi * radius / spacing)
    for k in range(n_straight):
        points.append((-half + k * straight / n_straight, -radius))
    for k in range(n_arc):
        a = -math.pi / 2 + k * math.pi / n_arc
        points.append((half + radius * math.cos(a), radius * math.sin(a)))
    for k in range(n_straight):
        points.append((half - k * straight / n_straight, radius))
    for k in range(n_arc):
        a = math.pi / 2 + k * math.pi / n_arc
        points.append((-half + radius * math.cos(a), radius * math.sin(a)))
    return np.array(points)


def drive(
    scorer: EpisodeScorer,
    xy: np.ndarray,
    *,
    speed: float = 5.0,
    yaw_rate: float = 0.0,
    inference_ns: int = 0,
    latency_ns: int = 0,
) -> None:
    """Feed poses (one per step) and one lock-step command per pose."""
    for k, (x, y) in enumerate(np.asarray(xy).tolist()):
        scorer.add_pose(seq=k, stamp_ns=k * STEP_NS, x_m=x, y_m=y, yaw_rad=0.0, command_latency_ns=latency_ns)
        scorer.add_command(stamp_ns=k * STEP_NS, speed_mps=speed, yaw_rate_radps=yaw_rate, inference_ns=inference_ns)


def circle_trajectory(
    radius: float, speed: float, laps: float, *, start_rad: float = 0.0, direction: int = 1
) -> np.ndarray:
    steps = int(round(laps * 2 * math.pi * radius / speed / STEP_S))
    angles = start_rad + direction * speed * np.arange(steps + 1) * STEP_S / radius
    return np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])


# --- pure BM functions -------------------------------------------------------------------------------------------


def test_completed_distance_of_zig_zag_and_average_speed():
    zig_zag = np.array([[0, 0], [3, 4], [6, 0], [9, 4], [9, 4]], dtype=float)
    assert completed_distance_m(zig_zag) == pytest.approx(15.0)
    assert completed_distance_m(zig_zag[:1]) == 0.0
    assert completed_distance_m(np.zeros((0, 2))) == 0.0
    assert average_speed_mps(15.0, 3.0) == pytest.approx(5.0)
    assert average_speed_mps(15.0, 0.0) == 0.0


def test_suddenness_distance():
    assert suddenness_distance([10.0] * 50, [0.3] * 50) == 0.0
    # v from one end of [6.5, 24] to the other at constant w: distance 1 per step.
    assert suddenness_distance([6.5, 24.0, 6.5, 24.0], [0.0] * 4) == pytest.approx(1.0)
    # w over the full [-7.1, 7.1] range: also 1; both at once: sqrt(2).
    assert suddenness_distance([7.0, 7.0], [-7.1, 7.1]) == pytest.approx(1.0)
    assert suddenness_distance([6.5, 24.0], [-7.1, 7.1]) == pytest.approx(math.sqrt(2))
    # mean over steps: one jump of 0.5 among four steps.
    assert suddenness_distance([10, 10, 10, 18.75, 18.75], [0] * 5) == pytest.approx(0.5 / 4)
    assert suddenness_distance([10.0], [1.0]) == 0.0
    assert suddenness_distance([], []) == 0.0


def test_mean_inference_time_trims_ten_each_side():
    times = [1.0] * 10 + [0.01] * 10 + [1.0] * 10
    assert mean_inference_time_s(times) == pytest.approx(0.01)
    # 20 or fewer: all of them.
    assert mean_inference_time_s([0.1] * 10 + [0.3] * 10) == pytest.approx(0.2)
    assert mean_inference_time_s([0.1] * 10 + [0.3] * 11) == pytest.approx(0.3)  # [10:-10] keeps one
    assert mean_inference_time_s([]) == 0.0


def test_percentiles_ms():
    assert percentiles_ms([1_000_000, 2_000_000, 3_000_000]) == pytest.approx([2.0, 2.9])
    assert percentiles_ms([]) == [0.0, 0.0]


def test_bm_nearest_checkpoint_starts_at_100_m():
    q = circle_points(20.0)
    assert bm_nearest_checkpoint(q, (0.0, 21.0)) == int(np.argmin(np.hypot(q[:, 0], q[:, 1] - 21.0)))
    assert bm_nearest_checkpoint(q, (500.0, 500.0)) == 0  # nothing within 100 m


def test_bm_percentage_half_lap_has_no_lap():
    radius = 100.0
    q = circle_points(radius)
    p = circle_trajectory(radius, 6.0, 0.5)
    percentage, lap_checkpoint = bm_percentage_completed(p, q)
    length = 2 * math.pi * radius
    # Checkpoints up to 5 m ahead of the car are taken: 50 % plus at most 5 m / L.
    assert 50.0 < percentage <= 50.0 + 100 * 5.0 / length + 0.1
    assert lap_checkpoint is None
    assert bm_lap_seconds(np.arange(len(p)) * STEP_S, percentage, lap_checkpoint) is None


def test_bm_percentage_full_lap_completes_about_5_m_early():
    radius, speed = 20.0, 6.0
    q = circle_points(radius)
    p = circle_trajectory(radius, speed, 1.1)
    percentage, lap_checkpoint = bm_percentage_completed(p, q)
    assert percentage > 100.0
    assert lap_checkpoint is not None
    stamps = np.arange(len(p)) * STEP_S
    lap = bm_lap_seconds(stamps, percentage, lap_checkpoint)
    true_lap = 2 * math.pi * radius / speed
    assert true_lap - (5.0 + 0.25) / speed - STEP_S <= lap < true_lap - 4.5 / speed
    # Strictly above 100 is needed.
    assert bm_lap_seconds(stamps, 100.0, lap_checkpoint) is None
    assert bm_lap_seconds(stamps, 100.01, 3) == pytest.approx(3 * STEP_S)


def test_bm_percentage_counts_the_backward_direction_too():
    q = circle_points(20.0)
    p = circle_trajectory(20.0, 6.0, 1.1, direction=-1)
    percentage, lap_checkpoint = bm_percentage_completed(p, q)
    assert percentage > 100.0 and lap_checkpoint is not None


def test_bm_percentage_terminates_on_a_circuit_inside_the_radius():
    q = circle_points(1.0, spacing=0.1)  # every checkpoint within 5 m of every sample: BM would loop forever
    p = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]])
    percentage, lap_checkpoint = bm_percentage_completed(p, q)
    assert percentage > 100.0 and lap_checkpoint == 1
    assert bm_percentage_completed(p[:1], q) == (0.0, None)
    assert bm_percentage_completed(p, np.zeros((0, 2))) == (0.0, None)


def test_bm_position_deviation_on_the_centreline_is_one():
    circuit = load_circuit("simple")
    q = circuit.centreline.points_m
    for start in (0, 500):  # Q is rotated to the checkpoint nearest p0
        p = np.roll(q, -start, axis=0)
        mae, total = bm_position_deviation(p, q)
        assert mae == pytest.approx(1.0, abs=1e-3)
        count = total / mae
        assert len(q) - 3 <= count <= len(q)  # stops only when t* > n - 2


def test_bm_position_deviation_of_a_constant_offset():
    # Samples on a circle 0.1 m outside the checkpoints, at a spacing unrelated to theirs: d = 0.1 -> 1000**0.1.
    q = circle_points(30.0)
    p = circle_trajectory(30.1, 5.7, 1.0, start_rad=0.013)
    mae, total = bm_position_deviation(p, q)
    assert mae == pytest.approx(1000**0.1, abs=1e-3)
    assert mae == pytest.approx(1.995, abs=1e-3)
    assert total == pytest.approx(mae * round(total / mae))


def test_bm_position_deviation_stops_where_the_trajectory_ends():
    q = circle_points(30.0)
    p = circle_trajectory(30.0, 5.0, 0.5)
    mae, total = bm_position_deviation(p, q)
    assert mae == pytest.approx(1.0, abs=1e-3)
    assert 0.45 * len(q) < total / mae < 0.52 * len(q)
    # A car that stops halfway and sits there: the search ends (stall rule or end of samples), no hang.
    trapped = np.vstack([p, np.repeat(p[-1:], 300, axis=0)])
    mae_trapped, total_trapped = bm_position_deviation(trapped, q)
    assert 0.45 * len(q) < total_trapped / mae_trapped < 0.55 * len(q)


def _bm_reference_deviation(p: np.ndarray, q: np.ndarray) -> float:
    """BM's search as the reference describes it, with SciPy fmin (no global retries needed on this path except
    for the first 3 checkpoints, done here by brute force over [prev_t, prev_t + 100])."""
    n = len(p)
    spline = CubicSpline(np.arange(n), p, axis=0, bc_type="natural")
    q = np.roll(q, -bm_nearest_checkpoint(q, p[0]), axis=0)
    values, prev_t, stalls = [], 0.0, 0
    for k, point in enumerate(q):

        def distance(t, point=point):
            return float(np.hypot(*(spline(np.atleast_1d(t)[0]) - point)))

        t = float(fmin(distance, prev_t, disp=False, xtol=1e-8, ftol=1e-10)[0])
        if distance(t) > 1.0 or k < 3:
            grid = np.linspace(prev_t, min(prev_t + 100, n - 1), 20001)
            t = float(grid[np.argmin(np.hypot(*(spline(grid) - point).T))])
            t = float(fmin(distance, t, disp=False, xtol=1e-8, ftol=1e-10)[0])
        if t > n - 2:
            break
        if abs(t - prev_t) < 0.01:
            stalls += 1
            if stalls > 3:
                break
        else:
            stalls = 0
        values.append(1000 ** distance(t))
        prev_t = t
    return float(np.mean(values))


@pytest.mark.parametrize("offset_m", [0.0, 1.2])
def test_bm_position_deviation_matches_an_fmin_search(offset_m):
    # A weaving car along the stadium's bottom straight: well-behaved. With the 1.2 m offset every checkpoint is
    # more than 1 m away, so every one goes through the global search.
    q = stadium_points(60.0, 20.0)
    x = np.arange(-30.0, 29.0, 0.3)
    p = np.column_stack([x, -20.0 + offset_m + 0.4 * np.sin(x / 3.0)])
    mae, total = bm_position_deviation(p, q)
    reference = _bm_reference_deviation(p, q)
    assert mae == pytest.approx(reference, rel=1e-6)
    assert mae > 1000**offset_m * 1.5  # the weave is seen: a straight path would give 1000**offset


# --- beyond BM: pure functions -----------------------------------------------------------------------------------


def test_lap_crossings_are_interpolated_and_not_counted_twice():
    times = np.arange(6, dtype=float)
    progress = np.array([0, 5, 10, 9, 11, 21], dtype=float)
    assert lap_crossing_times_s(times, progress, 10.0) == pytest.approx([2.0, 4.9])
    assert lap_times_s(times, progress, 10.0) == pytest.approx([2.0, 2.9])
    # Backing over the line and crossing again is still one lap.
    assert lap_crossing_times_s(np.arange(5.0), np.array([0, 6, 11, 9, 12.0]), 10.0) == pytest.approx([1.8])
    assert lap_times_s(np.arange(3.0), np.array([0, -5, -12.0]), 10.0) == []
    assert lap_times_s(np.zeros(1), np.zeros(1), 10.0) == []


def test_cross_track_stats_and_off_track_events():
    lateral = np.array([0.0, 1.0, 1.6, 1.7, 1.6, 1.4, 1.6, 2.0, 1.0, -1.6, 0.0])
    assert count_off_track_events(lateral, 1.5) == 3  # out at 1.6, again after 1.4, again at -1.6
    assert count_off_track_events([1.6, 1.7, 0.0], 1.5) == 1  # starting outside counts
    assert count_off_track_events([1.5, -1.5], 1.5) == 0  # on the edge is on the road
    assert count_off_track_events([], 1.5) == 0
    mean, rms, peak, p95 = cross_track_stats([-3.0, 4.0])
    assert (mean, rms, peak) == pytest.approx((3.5, math.sqrt(12.5), 4.0))
    assert p95 == pytest.approx(3.95)
    assert cross_track_stats([]) == (0.0, 0.0, 0.0, 0.0)


# --- the scorer --------------------------------------------------------------------------------------------------


def test_straight_line_offset_gives_its_cross_track_error():
    circuit = make_circuit(stadium_points(60.0, 20.0))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    x = np.arange(-25.0, 25.0, 0.25)
    drive(scorer, np.column_stack([x, np.full_like(x, -20.0 + 0.5)]))
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.cross_track_mean_m == pytest.approx(0.5, abs=1e-9)
    assert metrics.cross_track_max_m == pytest.approx(0.5, abs=1e-9)
    assert metrics.cross_track_rms_m == pytest.approx(0.5, abs=1e-9)
    assert metrics.cross_track_p95_m == pytest.approx(0.5, abs=1e-9)
    assert metrics.off_track_events == 0
    assert metrics.progress_m == pytest.approx(x[-1] - x[0], abs=1e-9)
    assert scorer.live()["cross_track_m"] == pytest.approx(0.5)


def test_projection_lateral_is_signed_left_positive():
    centreline = make_circuit(stadium_points(60.0, 20.0)).centreline
    first = centreline.project(0.0, -19.7)
    assert first.lateral_m == pytest.approx(0.3)
    second = centreline.project(1.0, -20.4, near_s_m=first.s_m)
    assert second.lateral_m == pytest.approx(-0.4)
    assert second.s_m - first.s_m == pytest.approx(1.0)


def test_on_the_centreline_cross_track_zero_and_deviation_one():
    circuit = load_circuit("simple")
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    drive(scorer, circuit.centreline.points_m)  # 0.25 m per step: 5 m/s
    metrics = scorer.finish(wall_time_s=10.0)
    assert metrics.cross_track_max_m < 1e-9
    assert metrics.position_deviation_mae == pytest.approx(1.0, abs=1e-3)
    assert metrics.off_track_events == 0
    # The last point is one segment short of the start: almost a lap, not a lap.
    assert metrics.completed_laps == 0 and metrics.lap_times_s == []
    assert metrics.progress_m == pytest.approx(
        circuit.length_m - np.hypot(*(circuit.centreline.points_m[-1] - circuit.centreline.points_m[0]))
    )


def test_perfect_circle_lap_is_timed_to_better_than_a_step():
    radius, speed = 20.0, 6.0
    circuit = make_circuit(circle_points(radius))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    drive(scorer, circle_trajectory(radius, speed, 1.2), speed=speed, yaw_rate=speed / radius)
    metrics = scorer.finish(wall_time_s=2.0)
    true_lap = 2 * math.pi * radius / speed  # 20.94 s: not a multiple of the step
    assert metrics.completed_laps == 1
    assert len(metrics.lap_times_s) == 1
    assert metrics.lap_times_s[0] == pytest.approx(true_lap, abs=1e-4)
    assert metrics.percentage_completed > 100.0
    assert metrics.bm_lap_seconds is not None and metrics.bm_lap_seconds < true_lap
    assert metrics.progress_laps == pytest.approx(1.2, abs=0.01)
    assert metrics.suddenness_distance == 0.0
    assert metrics.average_speed_mps == pytest.approx(speed, rel=1e-3)
    assert metrics.position_deviation_mae == pytest.approx(1.0, abs=1e-3)
    assert metrics.command_rate_hz == pytest.approx(1 / STEP_S)


def test_several_laps_from_an_arbitrary_start():
    radius, speed = 15.0, 7.0
    circuit = make_circuit(circle_points(radius))
    scorer = EpisodeScorer(circuit=circuit, laps_target=2, step_s=STEP_S)
    drive(scorer, circle_trajectory(radius, speed, 2.5, start_rad=1.234), speed=speed)
    metrics = scorer.finish(wall_time_s=1.0)
    true_lap = 2 * math.pi * radius / speed
    assert metrics.completed_laps == 2
    assert metrics.lap_times_s == pytest.approx([true_lap, true_lap], abs=1e-3)
    assert scorer.live()["completed_laps"] == 2
    assert metrics.percentage_completed > 200.0


def test_half_lap_is_half_and_no_lap():
    radius = 100.0
    circuit = make_circuit(circle_points(radius))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    drive(scorer, circle_trajectory(radius, 6.0, 0.5))
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.progress_laps == pytest.approx(0.5, abs=1e-3)
    assert 50.0 < metrics.percentage_completed < 51.0
    assert metrics.completed_laps == 0
    assert metrics.lap_times_s == []
    assert metrics.bm_lap_seconds is None


def test_driving_backwards_is_negative_progress_but_a_bm_lap():
    circuit = make_circuit(circle_points(20.0))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    drive(scorer, circle_trajectory(20.0, 6.0, 1.1, direction=-1))
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.progress_laps == pytest.approx(-1.1, abs=0.01)
    assert metrics.completed_laps == 0 and metrics.lap_times_s == []
    assert metrics.percentage_completed > 100.0  # BM's backward pass counts the wrong way round


def test_off_track_excursions_counted_once_each():
    circuit = make_circuit(stadium_points(60.0, 20.0), half_width=1.5)
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    offsets = [0.0, 1.0, 1.6, 1.7, 1.8, 1.6, 1.4, 1.6, 2.0, 1.0, 0.0, -1.6, -1.7, 0.0]
    xy = [(-20.0 + 0.3 * k, -20.0 + lateral) for k, lateral in enumerate(offsets)]
    drive(scorer, np.array(xy))
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.off_track_events == 3
    assert metrics.cross_track_max_m == pytest.approx(2.0)


def test_tracking_matches_brute_force_and_counts_a_lap_off_centre():
    circuit = load_circuit("simple")
    centreline = circuit.centreline
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    xy, lateral = [], []
    for s in np.arange(0.0, centreline.length_m + 20.0, 0.31):
        x, y, heading = centreline.pose_at(s)
        offset = 0.5 * math.sin(s / 9.0)
        lateral.append(offset)
        xy.append((x - offset * math.sin(heading), y + offset * math.cos(heading)))
    drive(scorer, np.array(xy))
    metrics = scorer.finish(wall_time_s=1.0)
    # Brute force: distance to every segment.
    points = centreline.points_m
    vectors = np.roll(points, -1, axis=0) - points
    brute = []
    for x, y in xy:
        rel = np.array([x, y]) - points
        t = np.clip(np.einsum("ij,ij->i", rel, vectors) / np.einsum("ij,ij->i", vectors, vectors), 0, 1)
        brute.append(np.min(np.hypot(*(rel - t[:, None] * vectors).T)))
    assert metrics.cross_track_max_m == pytest.approx(max(brute), abs=1e-9)
    assert metrics.cross_track_mean_m == pytest.approx(float(np.mean(brute)), abs=1e-9)
    assert metrics.cross_track_max_m == pytest.approx(0.5, abs=0.01)
    assert metrics.completed_laps == 1
    assert metrics.progress_m == pytest.approx(centreline.length_m + 20.0, abs=0.5)


def centreline_drive(circuit: Circuit, *, start_m: float, distance_m: float, speed_mps: float) -> np.ndarray:
    """Positions one step apart of a car on the centre line from ``start_m`` for ``distance_m``, in driving order."""
    steps = int(round(distance_m / speed_mps / STEP_S))
    return np.array([circuit.centreline.pose_at(start_m + k * speed_mps * STEP_S)[:2] for k in range(steps + 1)])


@pytest.mark.parametrize("direction", ["forward", "reverse"])
def test_a_loop_from_a_start_along_the_circuit_is_a_lap_measured_from_there(direction):
    circuit = load_circuit("simple", direction=direction)
    length_m, speed_mps = circuit.length_m, 8.0
    scores = {}
    for start_m in (0.0, 300.0):
        scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
        drive(scorer, centreline_drive(circuit, start_m=start_m, distance_m=length_m + 10.0, speed_mps=speed_mps))
        scores[start_m] = scorer.finish(wall_time_s=1.0)
    along = scores[300.0]
    # The start line lies 143 m ahead of the car: crossing it is no lap, one length back to 300 m is.
    assert along.completed_laps == 1 and along.progress_m == pytest.approx(length_m + 10.0, abs=0.05)
    assert along.lap_times_s == pytest.approx([length_m / speed_mps], abs=0.01)
    assert along.percentage_completed > 100.0 and along.bm_lap_seconds is not None
    assert along.bm_lap_seconds == pytest.approx(length_m / speed_mps, abs=1.5)  # BM: ~5 m before the start point
    assert along.position_deviation_mae == pytest.approx(1.0, abs=0.01)
    # The same loop from the start line scores the same (the centre line's vertices fall elsewhere along each loop).
    line = scores[0.0]
    assert line.completed_laps == 1 and line.lap_times_s == pytest.approx(along.lap_times_s, abs=0.01)
    assert line.progress_m == pytest.approx(along.progress_m, abs=0.05)
    assert line.percentage_completed == pytest.approx(along.percentage_completed, abs=1.0)


def test_tracking_stays_on_its_branch_where_the_track_passes_close():
    # Two straights 2.5 m apart, joined by tight semicircles: a car 1.4 m left of the bottom straight is nearer
    # the top straight's centreline (1.1 m) than its own. Global nearest-point projection would jump branch.
    circuit = make_circuit(stadium_points(60.0, 1.25), half_width=1.5)
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    x = np.arange(-25.0, 25.0, 0.25)
    lateral = np.clip((x + 25.0) / 5.0, 0.0, 1.4)  # start on the centre line, then drift left
    drive(scorer, np.column_stack([x, -1.25 + lateral]))
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.progress_m == pytest.approx(x[-1] - x[0], abs=1e-6)
    assert metrics.cross_track_max_m == pytest.approx(1.4, abs=1e-9)
    assert scorer.live()["cross_track_m"] == pytest.approx(1.4)
    trap = circuit.centreline.project(0.0, -1.25 + 1.4)  # global nearest point: the other straight
    assert abs(trap.lateral_m) == pytest.approx(1.1)
    assert trap.s_m > 60.0


def test_real_time_factor_and_steps():
    circuit = make_circuit(circle_points(20.0))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    drive(scorer, circle_trajectory(20.0, 5.0, 0.0 + 50.0 / (2 * math.pi * 20.0)))  # 200 steps, 10 s
    metrics = scorer.finish(wall_time_s=4.0)
    assert metrics.steps == 200
    assert metrics.sim_time_s == pytest.approx(10.0)
    assert metrics.real_time_factor == pytest.approx(2.5)
    assert metrics.wall_time_s == 4.0
    assert scorer.finish(wall_time_s=0.0).real_time_factor == 0.0


def test_command_rate_latency_and_inference():
    circuit = make_circuit(circle_points(20.0))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    xy = circle_trajectory(20.0, 5.0, 0.1)
    n = len(xy)
    for k, (x, y) in enumerate(xy.tolist()):
        latency = 0 if k == 0 else (2_000_000 if k % 2 else 4_000_000)  # 0 = not measured (the start pose)
        scorer.add_pose(seq=k, stamp_ns=k * STEP_NS, x_m=x, y_m=y, yaw_rad=0.0, command_latency_ns=latency)
        # Warm-up and shutdown inference slow; in between 3 ms.
        inference = 50_000_000 if k < 10 or k >= n - 9 else 3_000_000
        scorer.add_command(stamp_ns=k * STEP_NS, speed_mps=5.0, yaw_rate_radps=0.25, inference_ns=inference)
    # A stray command from after the episode does not raise the rate.
    scorer.add_command(stamp_ns=(n + 5) * STEP_NS, speed_mps=5.0, yaw_rate_radps=0.25, inference_ns=50_000_000)
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.command_rate_hz == pytest.approx(20.0)
    assert metrics.command_latency_p50_ms == pytest.approx(3.0)
    assert metrics.command_latency_p95_ms == pytest.approx(4.0)
    assert metrics.inference_p50_ms == pytest.approx(3.0)
    assert metrics.inference_p95_ms == pytest.approx(3.0)
    assert metrics.mean_inference_time_s == pytest.approx(0.003)
    assert metrics.suddenness_distance == 0.0


def test_degenerate_episodes_do_not_raise():
    circuit = make_circuit(circle_points(20.0))
    empty = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    assert empty.live() == {
        "progress_laps": 0.0,
        "completed_laps": 0,
        "sim_time_s": 0.0,
        "cross_track_m": 0.0,
        "speed_mps": 0.0,
    }
    metrics = empty.finish(wall_time_s=0.0)
    assert metrics.steps == 0 and metrics.sim_time_s == 0.0 and metrics.real_time_factor == 0.0
    assert metrics.percentage_completed == 0.0 and metrics.bm_lap_seconds is None
    assert metrics.lap_times_s == [] and metrics.completed_laps == 0
    assert metrics.position_deviation_mae == 0.0 and metrics.command_rate_hz == 0.0
    assert metrics.inference_p95_ms == 0.0 and metrics.command_latency_p50_ms is None  # absent, never 0

    one = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    one.add_pose(seq=0, stamp_ns=0, x_m=20.3, y_m=0.0, yaw_rad=math.pi / 2)
    metrics = one.finish(wall_time_s=0.1)
    assert metrics.steps == 0 and metrics.completed_distance_m == 0.0
    assert metrics.percentage_completed == 0.0 and metrics.position_deviation_total_err == 0.0
    assert metrics.cross_track_max_m == pytest.approx(0.3, abs=1e-3)
    assert metrics.suddenness_distance == 0.0 and metrics.mean_inference_time_s == 0.0

    # Poses that never move, no commands.
    still = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    for k in range(30):
        still.add_pose(seq=k, stamp_ns=k * STEP_NS, x_m=20.0, y_m=0.0, yaw_rad=0.0)
    metrics = still.finish(wall_time_s=1.0)
    assert metrics.average_speed_mps == 0.0 and metrics.progress_m == 0.0
    assert metrics.command_rate_hz == 0.0 and metrics.suddenness_distance == 0.0
    assert metrics.percentage_completed < 10.0
    # The result is a valid, serialisable message.
    decoded = msgspec.json.decode(msgspec.json.encode(metrics), type=EpisodeMetrics)
    assert decoded == metrics


def test_live_values():
    circuit = make_circuit(stadium_points(60.0, 20.0))
    scorer = EpisodeScorer(circuit=circuit, laps_target=3, step_s=STEP_S)
    scorer.add_pose(seq=0, stamp_ns=0, x_m=-20.0, y_m=-19.7, yaw_rad=0.0)
    assert scorer.live()["speed_mps"] == 0.0
    scorer.add_command(stamp_ns=0, speed_mps=4.0, yaw_rate_radps=0.0, inference_ns=0)
    assert scorer.live()["speed_mps"] == 4.0  # one pose: the last command's speed
    for k in range(1, 11):
        scorer.add_pose(seq=k, stamp_ns=k * STEP_NS, x_m=-20.0 + 0.25 * k, y_m=-19.7, yaw_rad=0.0)
    live = scorer.live()
    assert live["sim_time_s"] == pytest.approx(0.5)
    assert live["speed_mps"] == pytest.approx(5.0)
    assert live["cross_track_m"] == pytest.approx(0.3)
    assert live["progress_laps"] == pytest.approx(2.5 / circuit.length_m)
    assert live["completed_laps"] == 0
    assert scorer.laps_target == 3


def test_duplicate_and_late_poses_are_dropped():
    circuit = make_circuit(stadium_points(60.0, 20.0))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    scorer.add_pose(seq=0, stamp_ns=0, x_m=-20.0, y_m=-20.0, yaw_rad=0.0)
    scorer.add_pose(seq=1, stamp_ns=STEP_NS, x_m=-19.75, y_m=-20.0, yaw_rad=0.0)
    scorer.add_pose(seq=1, stamp_ns=STEP_NS, x_m=-19.75, y_m=-20.0, yaw_rad=0.0)
    scorer.add_pose(seq=0, stamp_ns=0, x_m=-20.0, y_m=-20.0, yaw_rad=0.0)
    assert scorer.pose_count == 2 and scorer.dropped_poses == 2
    assert scorer.finish(wall_time_s=1.0).steps == 1


def test_long_episode_finishes():
    # ~3.4 laps of the simple circuit, 6000 poses, weaving within the road: the figures hang together.
    circuit = load_circuit("simple")
    centreline = circuit.centreline
    scorer = EpisodeScorer(circuit=circuit, laps_target=3, step_s=STEP_S)
    s_values = np.linspace(0.0, 1500.0, 6000)
    xy = []
    for s in s_values:
        x, y, heading = centreline.pose_at(s)
        offset = 0.6 * math.sin(s / 7.0)
        xy.append((x - offset * math.sin(heading), y + offset * math.cos(heading)))
    drive(scorer, np.array(xy))
    metrics = scorer.finish(wall_time_s=30.0)
    assert metrics.completed_laps == 3 and len(metrics.lap_times_s) == 3
    lap_s = centreline.length_m / (1500.0 / (5999 * STEP_S))
    assert metrics.lap_times_s == pytest.approx([lap_s] * 3, rel=1e-3)
    assert metrics.progress_m == pytest.approx(1500.0, abs=0.5)
    assert metrics.cross_track_max_m == pytest.approx(0.6, abs=0.01)
    assert 1.0 < metrics.position_deviation_mae < 1000**0.6
    assert metrics.percentage_completed > 300.0


def test_bm_runtime_keys_and_the_brains_own_lists_beside_drivebenchs():
    """BM's circuit_diameter (only with a completed lap), frame_rate, brain-iteration keys and gpu_inference; its
    mean_inference_time and suddenness_distance from the brain's own lists, beside drivebench's, which time the
    whole step and measure the commands."""
    radius, speed = 20.0, 6.0
    circuit = make_circuit(circle_points(radius))
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=STEP_S)
    xy = circle_trajectory(radius, speed, 1.2)
    for k, (x, y) in enumerate(xy.tolist()):
        scorer.add_pose(seq=k, stamp_ns=k * STEP_NS, x_m=x, y_m=y, yaw_rad=0.0)
        scorer.add_command(
            stamp_ns=k * STEP_NS,
            speed_mps=speed,
            yaw_rate_radps=speed / radius,
            inference_ns=20_000_000,  # the host's timing of the whole step: 20 ms (brain-side rain included)
            model_inference_ns=3_000_000 if k >= 5 else 0,  # the brain's own list, from its 6th frame: 3 ms
            suddenness=0.25 if k >= 5 else None,
            gpu=k == 7,
        )
    steps = len(xy) - 1
    metrics = scorer.finish(wall_time_s=steps * STEP_S / 2)  # RTF 2
    assert metrics.circuit_diameter_m == pytest.approx(circuit.centreline.length_m)
    assert metrics.frame_rate_hz == pytest.approx(1 / STEP_S)
    assert metrics.mean_brain_iterations_real_time_s == pytest.approx(0.020)
    assert metrics.brain_iterations_frequency_real_time_hz == pytest.approx(50.0)
    assert metrics.mean_brain_iterations_simulated_time_s == pytest.approx(steps * STEP_S / len(xy))
    assert metrics.target_brain_iterations_simulated_time_hz == pytest.approx(1 / STEP_S / 2)
    assert metrics.gpu_inference is True
    assert metrics.mean_inference_time_s == pytest.approx(0.020)
    assert metrics.bm_mean_inference_time_s == pytest.approx(0.003)
    assert metrics.suddenness_distance == 0.0 and metrics.bm_suddenness_distance == pytest.approx(0.25)


def test_bm_keys_a_brain_does_not_keep_are_none_and_no_lap_has_no_circuit_diameter():
    radius, speed = 20.0, 6.0
    scorer = EpisodeScorer(circuit=make_circuit(circle_points(radius)), laps_target=1, step_s=STEP_S)
    drive(scorer, circle_trajectory(radius, speed, 0.5), speed=speed, inference_ns=1_000_000)
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.circuit_diameter_m is None
    assert metrics.bm_mean_inference_time_s is None and metrics.bm_suddenness_distance is None
    assert metrics.gpu_inference is False
