"""The one table of metric columns: how every report shows each field of
:class:`~protocol.messages.EpisodeMetrics`.

:data:`METRIC_COLUMNS` has one :class:`MetricColumn` per field, in the order a person reads them. Three reports are
made from it, so a new metric is one row here (``tests/test_report_columns.py`` fails until it has one):

* the main table of a matrix report (:mod:`orchestrator.report.matrix`): the columns with a ``main`` header, in this
  order, each a mean ± std over the repetitions;
* one episode's table, printed by ``drivebench run`` (:mod:`orchestrator.report.episode`): a row per ``label``
  (columns that share a label are one row, written by the first one's ``text``); a column without a label is left
  out of it;
* the CSV and Parquet files (:mod:`orchestrator.report.export`): every column, in the struct's field order (the
  order files written before this table had), as :meth:`MetricColumn.cell` gives it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from protocol.messages import EpisodeMetrics


def first_lap_s(metrics: EpisodeMetrics) -> float | None:
    """The first-lap time: BM's ``bm_lap_seconds`` when BM counts the lap, else the first timed lap; None when the
    episode completed no lap."""
    if metrics.bm_lap_seconds is not None:
        return float(metrics.bm_lap_seconds)
    return float(metrics.lap_times_s[0]) if metrics.lap_times_s else None


def plain(value: Any, unit: str = "", digits: int = 2) -> str:
    """A value with its unit: floats to ``digits`` decimals, None as ``-``."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}{unit}"
    return f"{value}{unit}"


def lap_times_words(lap_times_s: list[float]) -> str:
    """The arc-length lap times, or that there are none (a bare "- s" read as a broken value)."""
    if not lap_times_s:
        return "no lap completed"
    return ", ".join(f"{t:.2f}" for t in lap_times_s) + " s"


def brains_own(value: float | None, *, scale: float, unit: str, digits: int) -> str:
    """A figure BM takes from the brain's own lists (its model's timings, its suddenness), or why there is none."""
    if value is None:
        return "not kept by the brain (BM reports none)"
    return f"{value * scale:.{digits}f}{unit}"


@dataclass(frozen=True, kw_only=True)
class MetricColumn:
    """How the reports show one field of :class:`~protocol.messages.EpisodeMetrics`.

    field: the struct's field. label: the episode table's row (None: the CSV only); columns sharing a label are one
    row. unit, digits: the episode table's plain text of the value. text: the episode table's text when the plain
    value says too little (the first column of a shared row writes the whole row). main: the main table's header
    (None: not in it), with ``main_digits`` decimals; ``main_value`` gives the figure averaged there (default: the
    field's value).
    """

    field: str
    label: str | None
    unit: str = ""
    digits: int = 2
    text: Callable[[EpisodeMetrics], str] | None = None
    main: str | None = None
    main_digits: int = 2
    main_value: Callable[[EpisodeMetrics], float | None] | None = None

    def value(self, metrics: EpisodeMetrics) -> Any:
        return getattr(metrics, self.field)

    def episode_text(self, metrics: EpisodeMetrics) -> str:
        """The episode table's text of this column (of its row, for the first column of a shared row)."""
        if self.text is not None:
            return self.text(metrics)
        return plain(self.value(metrics), self.unit, self.digits)

    def main_figure(self, metrics: EpisodeMetrics) -> float | None:
        """The figure the main table averages over an episode's repetitions (None: left out of the mean)."""
        if self.main_value is not None:
            return self.main_value(metrics)
        value = self.value(metrics)
        return None if value is None else float(value)

    def cell(self, metrics: EpisodeMetrics | None) -> Any:
        """The CSV's cell: the value, lists joined with ';' (full precision), "" when absent or unscored."""
        value = self.value(metrics) if metrics is not None else None
        if isinstance(value, list):
            return ";".join(repr(float(v)) for v in value) if value else ""
        return "" if value is None else value


def _progress(m: EpisodeMetrics) -> str:
    return f"{plain(m.progress_m, ' m', 1)} ({plain(m.progress_laps * 100, ' %', 1)})"


def _cross_track(m: EpisodeMetrics) -> str:
    return f"{m.cross_track_mean_m:.3f} / {m.cross_track_rms_m:.3f} / {m.cross_track_max_m:.3f} m"


def _brain_iterations(m: EpisodeMetrics) -> str:
    return (
        f"{m.brain_iterations_frequency_real_time_hz:.1f} / {m.brain_iterations_frequency_simulated_time_hz:.1f} "
        f"Hz (BM's wall-clock target {m.target_brain_iterations_simulated_time_hz:.1f} Hz)"
    )


def _latency(m: EpisodeMetrics) -> str:
    if m.command_latency_p50_ms is None:
        return "not measured"
    return f"{m.command_latency_p50_ms:.2f} / {m.command_latency_p95_ms:.2f} ms"


def _times(m: EpisodeMetrics) -> str:
    return f"{m.sim_time_s:.2f} s / {m.wall_time_s:.2f} s (RTF {m.real_time_factor:.2f}x)"


_CROSS_TRACK = "cross-track |e| mean / rms / max"
_ITERATIONS = "BM brain iterations real / sim time"
_LATENCY = "frame-to-command latency p50 / p95"
_TIMES = "sim time / wall time"

METRIC_COLUMNS: tuple[MetricColumn, ...] = (
    MetricColumn(field="completed_laps", label="completed laps"),
    MetricColumn(field="lap_times_s", label="lap times (arc length)", text=lambda m: lap_times_words(m.lap_times_s)),
    MetricColumn(field="bm_lap_seconds", label="BM lap seconds", unit=" s", main="Lap (s)", main_value=first_lap_s),
    MetricColumn(
        field="position_deviation_mae",
        label="BM position deviation (mean 1000^d)",
        digits=3,
        main="Position deviation (BM)",
    ),
    MetricColumn(field="position_deviation_total_err", label=None),
    MetricColumn(
        field="cross_track_mean_m", label=_CROSS_TRACK, text=_cross_track, main="Cross-track mean (m)", main_digits=3
    ),
    MetricColumn(field="cross_track_rms_m", label=_CROSS_TRACK),
    MetricColumn(field="cross_track_max_m", label=_CROSS_TRACK, main="Cross-track max (m)", main_digits=3),
    MetricColumn(field="cross_track_p95_m", label=None),
    MetricColumn(field="average_speed_mps", label="BM average speed", unit=" m/s", main="Avg speed (m/s)"),
    MetricColumn(
        field="percentage_completed",
        label="BM percentage completed",
        unit=" %",
        digits=1,
        main="Completed (%)",
        main_digits=1,
    ),
    MetricColumn(field="progress_m", label="progress", text=_progress),
    MetricColumn(field="progress_laps", label="progress"),
    MetricColumn(field="off_track_events", label="off-track events"),
    MetricColumn(field="completed_distance_m", label="BM completed distance", unit=" m", digits=1),
    MetricColumn(
        field="suddenness_distance",
        label="suddenness (from the commands)",
        text=lambda m: f"{m.suddenness_distance:.4f}",
    ),
    MetricColumn(
        field="bm_suddenness_distance",
        label="BM suddenness",
        text=lambda m: brains_own(m.bm_suddenness_distance, scale=1, unit="", digits=4),
    ),
    MetricColumn(
        field="mean_inference_time_s",
        label="brain step time (mean)",
        text=lambda m: f"{m.mean_inference_time_s * 1e3:.2f} ms",
    ),
    MetricColumn(
        field="bm_mean_inference_time_s",
        label="BM mean inference time",
        text=lambda m: brains_own(m.bm_mean_inference_time_s, scale=1e3, unit=" ms", digits=2),
    ),
    MetricColumn(field="inference_p50_ms", label=None),
    MetricColumn(field="inference_p95_ms", label=None),
    MetricColumn(
        field="circuit_diameter_m",
        label="BM circuit diameter",
        text=lambda m: "no lap completed" if m.circuit_diameter_m is None else f"{m.circuit_diameter_m:.1f} m",
    ),
    MetricColumn(field="frame_rate_hz", label="BM frame rate", text=lambda m: f"{m.frame_rate_hz:.1f} Hz"),
    MetricColumn(field="brain_iterations_frequency_real_time_hz", label=_ITERATIONS, text=_brain_iterations),
    MetricColumn(field="brain_iterations_frequency_simulated_time_hz", label=_ITERATIONS),
    MetricColumn(field="target_brain_iterations_simulated_time_hz", label=_ITERATIONS),
    MetricColumn(field="mean_brain_iterations_real_time_s", label=None),
    MetricColumn(field="mean_brain_iterations_simulated_time_s", label=None),
    MetricColumn(field="gpu_inference", label="BM GPU inference", text=lambda m: "yes" if m.gpu_inference else "no"),
    MetricColumn(field="command_rate_hz", label="command rate", unit=" Hz", digits=1),
    MetricColumn(field="command_latency_p50_ms", label=_LATENCY, text=_latency),
    MetricColumn(field="command_latency_p95_ms", label=_LATENCY),
    MetricColumn(field="sim_time_s", label=_TIMES, text=_times),
    MetricColumn(field="wall_time_s", label=_TIMES),
    MetricColumn(field="real_time_factor", label=_TIMES),
    MetricColumn(field="steps", label=None),
)

MAIN_COLUMNS: tuple[MetricColumn, ...] = tuple(c for c in METRIC_COLUMNS if c.main is not None)
# The CSV's order: the struct's own (files written before the table had it; pandas users may index by position).
CSV_COLUMNS: tuple[MetricColumn, ...] = tuple(
    sorted(METRIC_COLUMNS, key=lambda c: EpisodeMetrics.__struct_fields__.index(c.field))
)


def metric_rows(metrics: EpisodeMetrics) -> list[tuple[str, str]]:
    """The episode table's metric rows, one per label, in the table's order."""
    rows: dict[str, str] = {}
    for column in METRIC_COLUMNS:
        if column.label is not None and column.label not in rows:
            rows[column.label] = column.episode_text(metrics)
    return list(rows.items())
