"""Episode metrics: the scorer's pure core (no bus).

Two families of figures, both computed from the ground-truth poses and the active brain's commands of one episode:

* **Behavior-Metrics-compatible** (``bm_*`` functions and the BM fields of :class:`EpisodeMetrics`): the same
  definitions as JdeRobot Behavior Metrics' Gazebo metrics, re-implemented from their description
  (``shared/reference/behavior-metrics.md`` §3), so numbers can be set beside the paper's. The circuit's
  centreline points play the role of BM's "perfect lap" checkpoints Q.
* **Beyond BM**: arc-length progress and lap counting, every lap timed at full time resolution, cross-track error
  in metres, de-duplicated off-track events, command rate, latency and inference percentiles, real-time factor.

Units: metres, seconds, radians; arrays of positions are ``(n, 2)`` world (x, y) in metres.

Where we differ from BM on purpose (all documented at the function):

* Time has full resolution (BM only reads the integer seconds of ``/clock``).
* The position-deviation search is a dense evaluation of the spline plus a continuous refinement instead of
  SciPy ``fmin`` / ``dual_annealing``; it gives the same t* on well-behaved paths, much faster (BM issue #264).
* ``bm_percentage_completed`` guards against BM's endless loop when one sample lies within 5 m of every checkpoint.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline

from circuits import Circuit
from protocol.messages import EpisodeMetrics

# --- Behavior Metrics constants (reference §3, §8) -------------------------------------------------------------
BM_CHECKPOINT_RADIUS_M = 5.0  # a checkpoint counts as reached within this distance (strict <)
BM_NEAREST_START_M = 100.0  # the search for the checkpoint nearest p0 starts at this distance
BM_DEVIATION_BASE = 1000.0  # position deviation values are BASE ** d
BM_DEVIATION_RETRY_M = 1.0  # a local search result farther than this is redone globally
BM_DEVIATION_GLOBAL_FIRST = 3  # the first checkpoints are always searched globally
BM_DEVIATION_WINDOW_SAMPLES = 100.0  # global search interval [prev_t, prev_t + WINDOW] (sample indices)
BM_DEVIATION_STALL_DT = 0.01  # |t* - prev_t| below this counts as a stall ...
BM_DEVIATION_MAX_STALLS = 3  # ... and more than this many stalls in a row stop the search
BM_SPEED_RANGE_MPS = (6.5, 24.0)  # normalisation of v for suddenness (the explicit brain's label range)
BM_YAW_RATE_RANGE_RADPS = (-7.1, 7.1)  # normalisation of w for suddenness
BM_INFERENCE_TRIM = 10  # mean inference time over inference_times[10:-10]

#: Dense spline evaluation points per sample interval in :func:`bm_position_deviation`.
DEVIATION_OVERSAMPLE = 8


# --- Behavior-Metrics-compatible metrics -------------------------------------------------------------------------


def completed_distance_m(positions_m: np.ndarray) -> float:
    """Path length of the trajectory: sum of ‖p_i − p_{i−1}‖ (BM ``completed_distance``).

    It is a path length, not progress along the track, so weaving inflates it. 0 for fewer than 2 samples.
    """
    p = _as_points(positions_m)
    if len(p) < 2:
        return 0.0
    return float(np.sum(np.hypot(*np.diff(p, axis=0).T)))


def average_speed_mps(distance_m: float, sim_time_s: float) -> float:
    """Completed distance over simulated time, m/s (BM ``average_speed``); 0 when the time is not positive.

    BM divides by whole clock seconds; we use the full-resolution simulated time.
    """
    return float(distance_m / sim_time_s) if sim_time_s > 0 else 0.0


def bm_nearest_checkpoint(checkpoints_m: np.ndarray, point_m: Sequence[float]) -> int:
    """Index of the checkpoint nearest ``point_m``, as BM finds it: a search that starts at 100 m, so 0 when
    no checkpoint is closer than that."""
    q = _as_points(checkpoints_m)
    if len(q) == 0:
        return 0
    distances = np.hypot(q[:, 0] - point_m[0], q[:, 1] - point_m[1])
    j = int(np.argmin(distances))
    return j if distances[j] < BM_NEAREST_START_M else 0


def bm_percentage_completed(
    positions_m: np.ndarray, checkpoints_m: np.ndarray, *, radius_m: float = BM_CHECKPOINT_RADIUS_M
) -> tuple[float, int | None]:
    """BM ``percentage_completed``: the share of in-order checkpoints reached, in percent, and the lap checkpoint.

    positions_m P: the trajectory (n, 2). checkpoints_m Q: one lap of checkpoints (N, 2) in driving order.

    j0 is the checkpoint nearest p0. The forward pass starts with ``reached = 1`` at sample i = 1 and checkpoint
    j0 + 1: while i < n, if ‖p_i − q_j‖ < radius, the checkpoint is reached (``reached += 1``, j advances,
    wrapping at N) and the same sample is tried again, so one sample can take several checkpoints; otherwise i
    advances.
    The sample at which ``reached`` becomes N is the lap checkpoint. The backward pass does the same with j
    decreasing from j0 − 1. The percentage is max(forward, backward) / N × 100; a lap is completed iff it is
    **strictly** above 100. Consequences worth knowing: checkpoints up to ``radius`` ahead are taken at once, so the
    percentage runs ahead of the car by about radius / lap length, and the "lap" is complete about ``radius`` before
    the point where the car started (j0: the start line, or ``EpisodeSpec.start_m`` along the circuit).

    Returns ``(percentage, lap_checkpoint)``: the lap checkpoint (a sample index into P) comes from the pass that
    gave the maximum (forward on ties), None when that pass never reached N. Fewer than 2 samples or no checkpoints
    give ``(0.0, None)`` (BM zeroes runs with ≤ 1 odometry sample).

    Difference from BM: BM loops forever when a sample lies within ``radius`` of every checkpoint (a circuit smaller
    than the radius); here a sample takes at most N checkpoints in a row.
    """
    p = _as_points(positions_m)
    q = _as_points(checkpoints_m)
    n, count = len(p), len(q)
    if n < 2 or count == 0:
        return 0.0, None
    j0 = bm_nearest_checkpoint(q, p[0])
    px, py = p[:, 0].tolist(), p[:, 1].tolist()
    qx, qy = q[:, 0].tolist(), q[:, 1].tolist()
    radius_sq = radius_m * radius_m
    best_reached, best_lap = -1, None
    for direction in (1, -1):
        reached, lap_checkpoint = 1, None
        i, j, taken_here = 1, (j0 + direction) % count, 0
        while i < n:
            dx, dy = px[i] - qx[j], py[i] - qy[j]
            if dx * dx + dy * dy < radius_sq and taken_here < count:
                reached += 1
                taken_here += 1
                j = (j + direction) % count
                if reached == count:
                    lap_checkpoint = i
            else:
                i += 1
                taken_here = 0
        if reached > best_reached:
            best_reached, best_lap = reached, lap_checkpoint
    return 100.0 * best_reached / count, best_lap


def bm_lap_seconds(stamps_s: np.ndarray, percentage: float, lap_checkpoint: int | None) -> float | None:
    """BM ``lap_seconds``: time from the first sample to the lap checkpoint, only when percentage > 100 (strict).

    BM reads it off ``/clock`` as ``C[⌊len(C)·lap_checkpoint/n⌋].secs − C[0].secs``: whole seconds, from a clock
    message mapped proportionally onto the odometry index. We take the simulated time of the lap-checkpoint sample
    itself, at full resolution (ns stamps), so it can be up to ~1 s larger or smaller than BM's figure. First lap
    only; note that the BM lap ends about 5 m before the start line (see :func:`bm_percentage_completed`).
    """
    if percentage <= 100.0 or lap_checkpoint is None:
        return None
    stamps = np.asarray(stamps_s, dtype=float)
    return float(stamps[lap_checkpoint] - stamps[0])


def bm_position_deviation(
    positions_m: np.ndarray, checkpoints_m: np.ndarray, *, oversample: int = DEVIATION_OVERSAMPLE
) -> tuple[float, float]:
    """BM ``position_deviation_mae`` and ``position_deviation_total_err``: mean and sum of 1000**d. Not metres.

    1. Natural cubic splines x(t), y(t) through P with t = sample index 0..n−1.
    2. Q rotated to start at the checkpoint nearest p0 (:func:`bm_nearest_checkpoint`).
    3. For each q in order, from prev_t = 0: t* = the spline parameter nearest q found by a local search started
       at prev_t; if that point is more than 1 m from q, or q is one of the first 3, t* is searched again globally
       on [prev_t, prev_t + 100]. Stop when t* > n − 2, or when |t* − prev_t| < 0.01 for more than 3 checkpoints
       in a row; otherwise append 1000**d with d = ‖q − (x(t*), y(t*))‖ and set prev_t = t*.

    So d = 0 gives 1, 0.1 m gives 2.0, 0.5 m gives 31.6, 1 m gives 1000. Returns (mae, total_err); (0.0, 0.0) when
    fewer than 2 samples or no checkpoints, or when the search stops before the first value.

    Difference from BM: BM's local search is SciPy ``fmin`` (Nelder-Mead) from prev_t and its global one
    ``dual_annealing`` — slow (BM issue #264) and stochastic. Here the spline is evaluated densely (``oversample``
    points per sample); the local search walks downhill from prev_t on that grid (forwards or backwards, as fmin
    may) to the first local minimum, the global search takes the grid minimum over the window, and both are
    refined on the continuous spline with a safeguarded Newton iteration. On well-behaved paths (distance to q
    unimodal near the car) this is the same t* as BM's, to ~1e-9; it differs where Nelder-Mead's simplex would jump
    over a small bump that the downhill walk stops at. t* is also kept within [0, n − 1] (BM lets fmin extrapolate
    the spline; such t* end the search anyway).
    """
    p = _as_points(positions_m)
    q = _as_points(checkpoints_m)
    n = len(p)
    if n < 2 or len(q) == 0:
        return 0.0, 0.0
    q = np.roll(q, -bm_nearest_checkpoint(q, p[0]), axis=0)
    search = _SplineNearest(p, oversample=oversample)
    values: list[float] = []
    prev_t, stalls = 0.0, 0
    for k, (qx, qy) in enumerate(q.tolist()):
        t, d = search.local(qx, qy, prev_t)
        if d > BM_DEVIATION_RETRY_M or k < BM_DEVIATION_GLOBAL_FIRST:
            t, d = search.global_(qx, qy, prev_t, prev_t + BM_DEVIATION_WINDOW_SAMPLES)
        if t > n - 2:
            break
        if abs(t - prev_t) < BM_DEVIATION_STALL_DT:
            stalls += 1
            if stalls > BM_DEVIATION_MAX_STALLS:
                break
        else:
            stalls = 0
        values.append(BM_DEVIATION_BASE**d)
        prev_t = t
    if not values:
        return 0.0, 0.0
    total = math.fsum(values)
    return total / len(values), total


def suddenness_distance(speeds_mps: Sequence[float], yaw_rates_radps: Sequence[float]) -> float:
    """BM ``suddenness_distance``: mean L2 distance between consecutive commands in normalised (v, w) space.

    v is normalised over [6.5, 24] m/s and w over [−7.1, 7.1] rad/s (the explicit brain's label ranges) without
    clipping, so one step from v = 6.5 to 24 at constant w is 1.0. 0 for fewer than 2 commands.
    """
    v = np.asarray(speeds_mps, dtype=float)
    w = np.asarray(yaw_rates_radps, dtype=float)
    if len(v) < 2:
        return 0.0
    v_lo, v_hi = BM_SPEED_RANGE_MPS
    w_lo, w_hi = BM_YAW_RATE_RANGE_RADPS
    v_hat = (v - v_lo) / (v_hi - v_lo)
    w_hat = (w - w_lo) / (w_hi - w_lo)
    return float(np.mean(np.hypot(np.diff(v_hat), np.diff(w_hat))))


def trimmed_inference_times(inference_times: Sequence[float]) -> np.ndarray:
    """``inference_times[10:-10]`` (drops warm-up and shutdown), or all of them when fewer than 21."""
    times = np.asarray(inference_times, dtype=float)
    if len(times) > 2 * BM_INFERENCE_TRIM:
        return times[BM_INFERENCE_TRIM:-BM_INFERENCE_TRIM]
    return times


def mean_inference_time_s(inference_times_s: Sequence[float]) -> float:
    """BM ``mean_inference_time``: mean of ``inference_times[10:-10]`` in seconds (all of them when fewer than 21;
    0 when there are none)."""
    times = trimmed_inference_times(inference_times_s)
    return float(np.mean(times)) if len(times) else 0.0


def bm_circuit_diameter_m(percentage_completed: float, *, lap_length_m: float) -> float | None:
    """BM ``circuit_diameter``: the lap's length (BM: its perfect lap's), reported only with a completed lap, i.e.
    BM's percentage strictly above 100; None otherwise."""
    return float(lap_length_m) if percentage_completed > 100 else None


# --- Beyond BM ---------------------------------------------------------------------------------------------------


def lap_crossing_times_s(times_s: np.ndarray, progress_m: np.ndarray, lap_length_m: float) -> list[float]:
    """Times at which arc-length progress first reaches k·L, k = 1, 2, ...; linearly interpolated between samples.

    A lap, once completed, stays completed: progress that falls back below k·L (reversing over the line) and
    crosses it again does not count a second time.
    """
    t = np.asarray(times_s, dtype=float)
    prog = np.asarray(progress_m, dtype=float)
    if len(prog) < 2 or not lap_length_m > 0:
        return []
    best = np.maximum.accumulate(prog)
    laps = int(math.floor(best[-1] / lap_length_m)) if best[-1] > 0 else 0
    crossings = []
    for k in range(1, laps + 1):
        target = k * lap_length_m
        i = int(np.searchsorted(best, target, side="left"))  # first sample with a new maximum >= target
        if i == 0:  # progress starts at 0, so only a degenerate lap length gets here
            crossings.append(float(t[0]))
            continue
        # best[i-1] < target <= best[i] and best rose at i, so prog[i] == best[i] and prog[i-1] < target.
        fraction = (target - prog[i - 1]) / (prog[i] - prog[i - 1])
        crossings.append(float(t[i - 1] + fraction * (t[i] - t[i - 1])))
    return crossings


def lap_times_s(times_s: np.ndarray, progress_m: np.ndarray, lap_length_m: float) -> list[float]:
    """Duration of every completed lap (s): lap k runs from the k−1-th crossing (the first sample for k = 1) to
    the k-th one (:func:`lap_crossing_times_s`)."""
    crossings = lap_crossing_times_s(times_s, progress_m, lap_length_m)
    if not crossings:
        return []
    return np.diff(np.concatenate([[float(np.asarray(times_s)[0])], crossings])).tolist()


def cross_track_stats(lateral_m: Sequence[float]) -> tuple[float, float, float, float]:
    """(mean, RMS, max, p95) of |lateral offset| in metres; zeros when empty. p95 interpolates linearly."""
    lat = np.abs(np.asarray(lateral_m, dtype=float))
    if len(lat) == 0:
        return 0.0, 0.0, 0.0, 0.0
    return (float(np.mean(lat)), float(np.sqrt(np.mean(lat**2))), float(np.max(lat)), float(np.percentile(lat, 95)))


def count_off_track_events(lateral_m: Sequence[float], half_width_m: float) -> int:
    """Number of excursions beyond the road edge: entries into |lateral| > half_width (the car's reference point,
    as the simulator's off-track test). An excursion counts once; the next only after coming back to
    |lateral| <= half_width. A trajectory that starts outside counts that as an excursion."""
    out = np.abs(np.asarray(lateral_m, dtype=float)) > half_width_m
    if len(out) == 0:
        return 0
    return int(out[0]) + int(np.count_nonzero(out[1:] & ~out[:-1]))


def percentiles_ms(durations_ns: Sequence[int] | np.ndarray, qs: Sequence[float] = (50, 95)) -> list[float]:
    """Percentiles (linear interpolation) of durations given in ns, in ms; zeros when empty."""
    d = np.asarray(durations_ns, dtype=float)
    if len(d) == 0:
        return [0.0 for _ in qs]
    return [float(v) / 1e6 for v in np.percentile(d, list(qs))]


# --- The accumulating scorer -------------------------------------------------------------------------------------


class EpisodeScorer:
    """Accumulates one episode and computes its :class:`EpisodeMetrics`.

    circuit: the circuit driven; its centreline gives arc length, cross-track error and BM's checkpoints.
    laps_target: the episode's lap target (kept for live reports; it does not change any metric).
    step_s: nominal simulation step (s), used only when two poses carry the same stamp.

    Feed ground-truth poses in order with :meth:`add_pose` (seq 0 is the start pose; a pose whose seq is not
    above the previous one is a duplicate or late and is dropped) and the active brain's commands with
    :meth:`add_command`. Each pose costs one windowed projection onto the centreline (tens of µs), so the scorer
    keeps up live; :meth:`finish` computes everything else.

    Everything is measured from the first pose, wherever on the circuit the car started (``EpisodeSpec.start_m``):
    progress is arc length driven from it, a lap is one circuit length driven back to it, and BM's checkpoints start
    at the one nearest it. So the scorer needs no start point, and a start at the start line scores as it always did.
    """

    def __init__(self, *, circuit: Circuit, laps_target: int, step_s: float):
        self.circuit = circuit
        self.laps_target = laps_target
        self.step_s = step_s
        self.lap_length_m = circuit.centreline.length_m
        self.dropped_poses = 0
        # Per pose.
        self._seq: list[int] = []
        self._stamp_ns: list[int] = []
        self._x: list[float] = []
        self._y: list[float] = []
        self._lateral: list[float] = []
        self._progress: list[float] = []
        self._latency_ns: list[int] = []
        # Running state.
        self._s_prev = 0.0
        self._best_progress = 0.0
        # Per command.
        self._cmd_stamp_ns: list[int] = []
        self._cmd_speed: list[float] = []
        self._cmd_yaw_rate: list[float] = []
        self._cmd_inference_ns: list[int] = []
        self._cmd_model_inference_ns: list[int] = []  # the brain's own timings (BM's inference_times), > 0 only
        self._cmd_suddenness: list[float] = []  # the brain's own suddenness values
        self._gpu = False

    # -- input ----------------------------------------------------------------------------------------------------

    def add_pose(
        self, *, seq: int, stamp_ns: int, x_m: float, y_m: float, yaw_rad: float, command_latency_ns: int = 0
    ) -> None:
        """Add one ground-truth pose (world frame, metres; stamp in simulated ns). ``yaw_rad`` is accepted for
        completeness; no metric needs it. ``command_latency_ns``: the Pose message's field, 0 = not measured."""
        if self._seq and seq <= self._seq[-1]:
            self.dropped_poses += 1
            return
        projection = self.circuit.centreline.project(
            float(x_m), float(y_m), near_s_m=self._s_prev if self._progress else None
        )
        s, lateral = projection.s_m, projection.lateral_m
        if self._progress:
            progress = self._progress[-1] + float(self.circuit.centreline.wrap_ds(s - self._s_prev))
        else:
            progress = 0.0
        self._s_prev = s
        self._best_progress = max(self._best_progress, progress)
        self._seq.append(int(seq))
        self._stamp_ns.append(int(stamp_ns))
        self._x.append(float(x_m))
        self._y.append(float(y_m))
        self._lateral.append(lateral)
        self._progress.append(progress)
        self._latency_ns.append(int(command_latency_ns))

    def add_command(
        self,
        *,
        stamp_ns: int,
        speed_mps: float,
        yaw_rate_radps: float,
        inference_ns: int,
        model_inference_ns: int = 0,
        suddenness: float | None = None,
        gpu: bool = False,
    ) -> None:
        """Add one command of the active brain. ``stamp_ns``: the sim stamp of the frame it answers;
        ``inference_ns``: wall time the brain spent on it, 0 = not measured. ``model_inference_ns`` /
        ``suddenness``: what the brain measured itself (0 / None: nothing); ``gpu``: its model runs on a GPU."""
        self._cmd_stamp_ns.append(int(stamp_ns))
        self._cmd_speed.append(float(speed_mps))
        self._cmd_yaw_rate.append(float(yaw_rate_radps))
        self._cmd_inference_ns.append(int(inference_ns))
        if model_inference_ns > 0:
            self._cmd_model_inference_ns.append(int(model_inference_ns))
        if suddenness is not None:
            self._cmd_suddenness.append(float(suddenness))
        self._gpu = self._gpu or bool(gpu)

    # -- output ---------------------------------------------------------------------------------------------------

    @property
    def pose_count(self) -> int:
        return len(self._seq)

    @property
    def command_count(self) -> int:
        return len(self._cmd_speed)

    def sim_time_s(self) -> float:
        """Simulated time from the first to the last pose, s."""
        return (self._stamp_ns[-1] - self._stamp_ns[0]) / 1e9 if self._stamp_ns else 0.0

    def live(self) -> dict:
        """Running figures: progress_laps, completed_laps, sim_time_s, cross_track_m (|lateral| of the latest
        pose), speed_mps (from the last two poses; the last command's when there is only one pose; else 0)."""
        progress = self._progress[-1] if self._progress else 0.0
        return {
            "progress_laps": progress / self.lap_length_m,
            "completed_laps": self._completed_laps(),
            "sim_time_s": self.sim_time_s(),
            "cross_track_m": abs(self._lateral[-1]) if self._lateral else 0.0,
            "speed_mps": self._latest_speed_mps(),
        }

    def finish(self, *, wall_time_s: float) -> EpisodeMetrics:
        """Every metric of the episode. ``wall_time_s``: wall-clock duration of the episode (for the RTF)."""
        n = len(self._seq)
        sim_time = self.sim_time_s()
        stamps_s = (np.asarray(self._stamp_ns, dtype=np.int64) - (self._stamp_ns[0] if n else 0)) / 1e9
        positions = np.column_stack([self._x, self._y]) if n else np.zeros((0, 2))
        checkpoints = self.circuit.centreline.points_m

        if n >= 2:  # BM zeroes everything with <= 1 odometry sample
            distance = completed_distance_m(positions)
            percentage, lap_checkpoint = bm_percentage_completed(positions, checkpoints)
            lap_s = bm_lap_seconds(stamps_s, percentage, lap_checkpoint)
            deviation_mae, deviation_total = bm_position_deviation(positions, checkpoints)
        else:
            distance, percentage, lap_s, deviation_mae, deviation_total = 0.0, 0.0, None, 0.0, 0.0

        progress = self._progress[-1] if n else 0.0
        ct_mean, ct_rms, ct_max, ct_p95 = cross_track_stats(self._lateral)

        # Commands answering frames in [first pose, last pose): exactly 1/step in lock-step.
        if n >= 2 and sim_time > 0:
            t0, t1 = self._stamp_ns[0], self._stamp_ns[-1]
            in_episode = sum(1 for stamp in self._cmd_stamp_ns if t0 <= stamp < t1)
            command_rate = in_episode / sim_time
        else:
            command_rate = 0.0
        measured_latency = [v for v in self._latency_ns if v > 0]
        latency_p50, latency_p95 = percentiles_ms(measured_latency) if measured_latency else (None, None)
        measured_inference = [v for v in self._cmd_inference_ns if v > 0]
        inference_p50, inference_p95 = percentiles_ms(trimmed_inference_times(measured_inference))
        bm_runtime = self._bm_runtime(
            sim_time_s=sim_time, wall_time_s=wall_time_s, steps=max(0, n - 1), inference_ns=measured_inference
        )

        return EpisodeMetrics(
            sim_time_s=float(sim_time),
            wall_time_s=float(wall_time_s),
            real_time_factor=float(sim_time / wall_time_s) if wall_time_s > 0 else 0.0,
            steps=max(0, n - 1),
            completed_distance_m=float(distance),
            average_speed_mps=average_speed_mps(distance, sim_time),
            percentage_completed=float(percentage),
            bm_lap_seconds=lap_s,
            position_deviation_mae=float(deviation_mae),
            position_deviation_total_err=float(deviation_total),
            suddenness_distance=suddenness_distance(self._cmd_speed, self._cmd_yaw_rate),
            mean_inference_time_s=mean_inference_time_s([v / 1e9 for v in measured_inference]),
            progress_m=float(progress),
            progress_laps=float(progress / self.lap_length_m),
            completed_laps=self._completed_laps(),
            lap_times_s=[float(v) for v in lap_times_s(stamps_s, np.asarray(self._progress), self.lap_length_m)],
            cross_track_mean_m=ct_mean,
            cross_track_rms_m=ct_rms,
            cross_track_max_m=ct_max,
            cross_track_p95_m=ct_p95,
            off_track_events=count_off_track_events(self._lateral, self.circuit.road_half_width_m),
            command_rate_hz=float(command_rate),
            command_latency_p50_ms=latency_p50,
            command_latency_p95_ms=latency_p95,
            inference_p50_ms=inference_p50,
            inference_p95_ms=inference_p95,
            circuit_diameter_m=bm_circuit_diameter_m(percentage, lap_length_m=self.lap_length_m),
            **bm_runtime,
        )

    def _bm_runtime(
        self, *, sim_time_s: float, wall_time_s: float, steps: int, inference_ns: list[int]
    ) -> dict[str, Any]:
        """BM's runtime keys, by BM's definitions, from what drivebench measures (see :class:`EpisodeMetrics`)."""
        commands = len(self._cmd_speed)
        real_s = float(np.mean(inference_ns)) / 1e9 if inference_ns else 0.0
        simulated_s = sim_time_s / commands if commands else 0.0
        rtf = round(sim_time_s / wall_time_s, 2) if wall_time_s > 0 else 0.0
        own_times = [v / 1e9 for v in self._cmd_model_inference_ns]
        return {
            "frame_rate_hz": steps / sim_time_s if sim_time_s > 0 else 0.0,
            "mean_brain_iterations_real_time_s": real_s,
            "brain_iterations_frequency_real_time_hz": 1 / real_s if real_s > 0 else 0.0,
            "mean_brain_iterations_simulated_time_s": simulated_s,
            "brain_iterations_frequency_simulated_time_hz": 1 / simulated_s if simulated_s > 0 else 0.0,
            # BM: 1000 / PilotTimeCycle / round(RTF, 2), PilotTimeCycle in ms; here the step is the cycle
            "target_brain_iterations_simulated_time_hz": 1 / self.step_s / rtf if rtf > 0 else 0.0,
            "gpu_inference": self._gpu,
            "bm_mean_inference_time_s": mean_inference_time_s(own_times) if own_times else None,
            "bm_suddenness_distance": float(np.mean(self._cmd_suddenness)) if self._cmd_suddenness else None,
        }

    # -- internals ------------------------------------------------------------------------------------------------

    def _completed_laps(self) -> int:
        # Laps completed so far: the best progress, so reversing over the line does not take a lap back.
        return max(0, int(math.floor(self._best_progress / self.lap_length_m)))

    def _latest_speed_mps(self) -> float:
        if len(self._seq) >= 2:
            dt_s = (self._stamp_ns[-1] - self._stamp_ns[-2]) / 1e9
            if dt_s <= 0:
                dt_s = (self._seq[-1] - self._seq[-2]) * self.step_s
            return math.hypot(self._x[-1] - self._x[-2], self._y[-1] - self._y[-2]) / dt_s
        if self._cmd_speed:
            return self._cmd_speed[-1]
        return 0.0


class _SplineNearest:
    """Nearest point of the natural cubic spline (x(t), y(t)) through P (t = sample index) to a query point,
    searched on a dense grid and refined on the continuous spline. Helper of :func:`bm_position_deviation`."""

    def __init__(self, positions_m: np.ndarray, *, oversample: int):
        n = len(positions_m)
        self.n = n
        self.h = 1.0 / oversample
        self.oversample = oversample
        spline = CubicSpline(np.arange(n, dtype=float), positions_m, axis=0, bc_type="natural")
        grid_t = np.arange((n - 1) * oversample + 1) / oversample
        self._grid = spline(grid_t)
        self._gx = self._grid[:, 0].tolist()
        self._gy = self._grid[:, 1].tolist()
        c = spline.c  # (4, n-1, 2): cubic, quadratic, linear, constant coefficient per interval
        self._cx = [c[k, :, 0].tolist() for k in range(4)]
        self._cy = [c[k, :, 1].tolist() for k in range(4)]

    def local(self, qx: float, qy: float, t0: float) -> tuple[float, float]:
        """Downhill walk on the grid from t0 to the first local minimum of the distance, then refinement."""
        gx, gy = self._gx, self._gy
        last = len(gx) - 1
        i = min(last, max(0, round(t0 * self.oversample)))
        best = (gx[i] - qx) ** 2 + (gy[i] - qy) ** 2
        for step in (1, -1):
            moved = False
            while 0 <= i + step <= last:
                d = (gx[i + step] - qx) ** 2 + (gy[i + step] - qy) ** 2
                if d >= best:
                    break
                i, best, moved = i + step, d, True
            if moved:
                break
        return self._refine(qx, qy, i)

    def global_(self, qx: float, qy: float, t_lo: float, t_hi: float) -> tuple[float, float]:
        """Grid minimum of the distance over [t_lo, t_hi] (within [0, n-1]), then refinement."""
        last = len(self._gx) - 1
        lo = min(last, max(0, math.ceil(t_lo * self.oversample - 1e-9)))
        hi = min(last, max(lo, math.floor(t_hi * self.oversample + 1e-9)))
        window = self._grid[lo : hi + 1]
        d_sq = (window[:, 0] - qx) ** 2 + (window[:, 1] - qy) ** 2
        return self._refine(qx, qy, lo + int(np.argmin(d_sq)))

    def _refine(self, qx: float, qy: float, i: int) -> tuple[float, float]:
        """Minimise the squared distance on [t_i - h, t_i + h] ∩ [0, n-1] by safeguarded Newton on its derivative;
        returns (t*, distance). Never worse than the grid point."""
        t_grid = i * self.h
        a = max(0.0, t_grid - self.h)
        b = min(self.n - 1.0, t_grid + self.h)
        t = t_grid
        for _ in range(40):
            f, g, curvature = self._distance_sq_derivatives(qx, qy, t)
            if g > 0:
                b = t
            elif g < 0:
                a = t
            else:
                break
            t_new = t - g / curvature if curvature > 0 else 0.5 * (a + b)
            if not a < t_new < b:
                t_new = 0.5 * (a + b)
            if abs(t_new - t) < 1e-12:
                t = t_new
                break
            t = t_new
        f_best = self._distance_sq_derivatives(qx, qy, t)[0]
        f_grid = (self._gx[i] - qx) ** 2 + (self._gy[i] - qy) ** 2
        if f_grid < f_best:
            return t_grid, math.sqrt(f_grid)
        return t, math.sqrt(max(0.0, f_best))

    def _distance_sq_derivatives(self, qx: float, qy: float, t: float) -> tuple[float, float, float]:
        """f = |S(t) - q|^2 and its first and second derivatives in t."""
        k = min(self.n - 2, max(0, int(t)))
        u = t - k
        cx, cy = self._cx, self._cy
        x = ((cx[0][k] * u + cx[1][k]) * u + cx[2][k]) * u + cx[3][k]
        y = ((cy[0][k] * u + cy[1][k]) * u + cy[2][k]) * u + cy[3][k]
        dx = (3 * cx[0][k] * u + 2 * cx[1][k]) * u + cx[2][k]
        dy = (3 * cy[0][k] * u + 2 * cy[1][k]) * u + cy[2][k]
        ddx = 6 * cx[0][k] * u + 2 * cx[1][k]
        ddy = 6 * cy[0][k] * u + 2 * cy[1][k]
        ex, ey = x - qx, y - qy
        return (ex * ex + ey * ey, 2 * (ex * dx + ey * dy), 2 * (dx * dx + dy * dy + ex * ddx + ey * ddy))


def _as_points(array: np.ndarray) -> np.ndarray:
    points = np.asarray(array, dtype=float)
    if points.size == 0:
        return np.zeros((0, 2))
    return points.reshape(-1, 2)
