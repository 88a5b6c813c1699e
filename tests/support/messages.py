"""One set of example messages shared by the message tests."""

from __future__ import annotations

from protocol.messages import (
    EpisodeMetrics,
)

METRICS = EpisodeMetrics(
    sim_time_s=1.0,
    wall_time_s=0.5,
    real_time_factor=2.0,
    steps=20,
    completed_distance_m=7.0,
    average_speed_mps=7.0,
    percentage_completed=1.5,
    bm_lap_seconds=None,
    position_deviation_mae=1.2,
    position_deviation_total_err=12.0,
    suddenness_distance=0.01,
    mean_inference_time_s=0.002,
    progress_m=7.0,
    progress_laps=0.016,
    completed_laps=0,
    lap_times_s=[],
    cross_track_mean_m=0.01,
    cross_track_rms_m=0.02,
    cross_track_max_m=0.05,
    cross_track_p95_m=0.04,
    off_track_events=0,
    command_rate_hz=20.0,
    command_latency_p50_ms=1.0,
    command_latency_p95_ms=2.0,
    inference_p50_ms=2.0,
    inference_p95_ms=3.0,
)
