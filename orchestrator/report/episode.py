"""Human-readable views of scores."""

from __future__ import annotations

import collections

from protocol.messages import EpisodeScore, EpisodeSpec


def _fmt(value, unit: str = "", digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def episode_words(spec: EpisodeSpec, *, brain: str) -> str:
    """What an episode is, in the words its run's first line and its metrics table share: the brain, the circuit,
    the direction, where it starts (``from 0 m`` too: a run's start is a choice worth seeing), the world's look,
    the laps and the seed."""
    direction = " (reverse)" if spec.direction == "reverse" else ""
    return (
        f"{brain} on {spec.circuit}{direction} from {spec.start_m:g} m along, look {spec.world.look}, "
        f"{spec.laps} lap(s), seed {spec.seed}"
    )


def lap_times_words(lap_times_s: list[float]) -> str:
    """The arc-length lap times, or that there are none (a bare "- s" read as a broken value)."""
    if not lap_times_s:
        return "no lap completed"
    return ", ".join(f"{t:.2f}" for t in lap_times_s) + " s"


def _own(value: float | None, *, scale: float, unit: str, digits: int) -> str:
    """A figure BM takes from the brain's own lists (its model's timings, its suddenness), or why there is none."""
    if value is None:
        return "not kept by the brain (BM reports none)"
    return f"{value * scale:.{digits}f}{unit}"


def metrics_table(score: EpisodeScore) -> str:
    """The episode's metrics as an aligned two-column table (Behavior-Metrics-compatible rows marked BM)."""
    m = score.metrics
    rows = [
        ("episode", episode_words(score.spec, brain=score.brain)),
        ("ended by", f"{score.reason} ({score.detail})" if score.detail else str(score.reason)),
        ("completed laps", _fmt(m.completed_laps)),
        ("lap times (arc length)", lap_times_words(list(m.lap_times_s))),
        ("progress", f"{_fmt(m.progress_m, ' m', 1)} ({_fmt(m.progress_laps * 100, ' %', 1)})"),
        (
            "cross-track |e| mean / rms / max",
            f"{m.cross_track_mean_m:.3f} / {m.cross_track_rms_m:.3f} / {m.cross_track_max_m:.3f} m",
        ),
        ("off-track events", _fmt(m.off_track_events)),
        ("BM percentage completed", _fmt(m.percentage_completed, " %", 1)),
        ("BM lap seconds", _fmt(m.bm_lap_seconds, " s")),
        ("BM completed distance", _fmt(m.completed_distance_m, " m", 1)),
        ("BM average speed", _fmt(m.average_speed_mps, " m/s")),
        ("BM position deviation (mean 1000^d)", _fmt(m.position_deviation_mae, "", 3)),
        ("suddenness (from the commands)", f"{m.suddenness_distance:.4f}"),
        ("BM suddenness", _own(m.bm_suddenness_distance, scale=1, unit="", digits=4)),
        ("brain step time (mean)", f"{m.mean_inference_time_s * 1e3:.2f} ms"),
        ("BM mean inference time", _own(m.bm_mean_inference_time_s, scale=1e3, unit=" ms", digits=2)),
        (
            "BM circuit diameter",
            "no lap completed" if m.circuit_diameter_m is None else f"{m.circuit_diameter_m:.1f} m",
        ),
        ("BM frame rate", f"{m.frame_rate_hz:.1f} Hz"),
        (
            "BM brain iterations real / sim time",
            f"{m.brain_iterations_frequency_real_time_hz:.1f} / {m.brain_iterations_frequency_simulated_time_hz:.1f} "
            f"Hz (BM's wall-clock target {m.target_brain_iterations_simulated_time_hz:.1f} Hz)",
        ),
        ("BM GPU inference", "yes" if m.gpu_inference else "no"),
        ("command rate", _fmt(m.command_rate_hz, " Hz", 1)),
        (
            "frame-to-command latency p50 / p95",
            "not measured"
            if m.command_latency_p50_ms is None
            else f"{m.command_latency_p50_ms:.2f} / {m.command_latency_p95_ms:.2f} ms",
        ),
        ("sim time / wall time", f"{m.sim_time_s:.2f} s / {m.wall_time_s:.2f} s (RTF {m.real_time_factor:.2f}x)"),
    ]
    rows += switch_rows(score) + shadow_rows(score)
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def switch_rows(score: EpisodeScore) -> list[tuple[str, str]]:
    """One row per live brain switch: who took over from whom, at which frame and sim time."""
    return [
        (
            "brain switch",
            f"{switch.from_brain} -> {switch.to_brain} at frame {switch.seq} ({switch.stamp_ns / 1e9:.2f} s)",
        )
        for switch in score.switches
    ]


def shadow_rows(score: EpisodeScore) -> list[tuple[str, str]]:
    """One row per shadow brain host: its distance to the driving brain's commands over the frames both answered
    (two hosts of one name are told apart by their process)."""
    names = collections.Counter(shadow.brain for shadow in score.shadows)
    return [
        (
            f"shadow {shadow.brain}{f' ({shadow.host})' if names[shadow.brain] > 1 else ''} vs driver",
            f"|dv| mean {shadow.speed_mae_mps:.3f} m/s, |dw| mean / rms / max {shadow.yaw_rate_mae_radps:.3f} / "
            f"{shadow.yaw_rate_rmse_radps:.3f} / {shadow.yaw_rate_max_abs_radps:.3f} rad/s over {shadow.frames} "
            f"frames",
        )
        for shadow in score.shadows
    ]
