"""Human-readable views of scores: one episode's table, printed by ``drivebench run``."""

from __future__ import annotations

import collections

from orchestrator.report.columns import metric_rows
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EpisodeScore


def episode_words(spec: EpisodeSpec, *, brain: str) -> str:
    """What an episode is, in the words its run's first line and its metrics table share: the brain, the circuit,
    the direction, where it starts (``from 0 m`` too: a run's start is a choice worth seeing), the world's look,
    the laps and the seed."""
    direction = " (reverse)" if spec.direction == "reverse" else ""
    return (
        f"{brain} on {spec.circuit}{direction} from {spec.start_m:g} m along, look {spec.world.look}, "
        f"{spec.laps} lap(s), seed {spec.seed}"
    )


def metrics_table(score: EpisodeScore) -> str:
    """The episode's metrics as an aligned two-column table (Behavior-Metrics-compatible rows marked BM): what the
    episode was and how it ended, then one row per label of :data:`~orchestrator.report.columns.METRIC_COLUMNS`."""
    rows = [
        ("episode", episode_words(score.spec, brain=score.brain)),
        ("ended by", f"{score.reason} ({score.detail})" if score.detail else str(score.reason)),
        *metric_rows(score.metrics),
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
