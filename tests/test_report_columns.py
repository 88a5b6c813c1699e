"""The one table of metric columns (orchestrator/report/columns.py): every field of EpisodeMetrics has one row, and
the main table, one episode's table and the CSV are all made from it."""

from __future__ import annotations

from orchestrator.report.columns import CSV_COLUMNS, MAIN_COLUMNS, METRIC_COLUMNS, metric_rows
from protocol.messages import EpisodeMetrics


def _metrics(**overrides) -> EpisodeMetrics:
    values = dict.fromkeys(EpisodeMetrics.__struct_fields__, 0.0)
    values.update(
        steps=10,
        completed_laps=1,
        off_track_events=0,
        lap_times_s=[57.93],
        bm_lap_seconds=57.2,
        command_latency_p50_ms=None,
        command_latency_p95_ms=None,
        circuit_diameter_m=None,
        bm_mean_inference_time_s=None,
        bm_suddenness_distance=None,
        gpu_inference=False,
    )
    values.update(overrides)
    return EpisodeMetrics(**values)


def test_every_metric_field_has_exactly_one_column():
    fields = [c.field for c in METRIC_COLUMNS]
    assert sorted(fields) == sorted(EpisodeMetrics.__struct_fields__), (
        "a field of EpisodeMetrics without a row in METRIC_COLUMNS (orchestrator/report/columns.py), or a row of a "
        "field that is gone"
    )


def test_the_csv_keeps_the_structs_order_and_every_column():
    assert [c.field for c in CSV_COLUMNS] == list(EpisodeMetrics.__struct_fields__)


def test_the_main_table_is_the_columns_with_a_header_in_table_order():
    assert [c.main for c in MAIN_COLUMNS] == [
        "Lap (s)",
        "Position deviation (BM)",
        "Cross-track mean (m)",
        "Cross-track max (m)",
        "Avg speed (m/s)",
        "Completed (%)",
    ]


def test_an_episode_row_per_label_written_by_its_first_column():
    metrics = _metrics(cross_track_mean_m=0.1234, cross_track_rms_m=0.2, cross_track_max_m=0.5)
    rows = dict(metric_rows(metrics))
    labels = list(dict.fromkeys(c.label for c in METRIC_COLUMNS if c.label is not None))
    assert list(rows) == labels
    assert rows["cross-track |e| mean / rms / max"] == "0.123 / 0.200 / 0.500 m"
    assert rows["lap times (arc length)"] == "57.93 s"
    assert rows["frame-to-command latency p50 / p95"] == "not measured"


def test_a_csv_cell_joins_lists_and_leaves_none_and_unscored_empty():
    by_field = {c.field: c for c in METRIC_COLUMNS}
    metrics = _metrics(lap_times_s=[1.5, 2.0])
    assert by_field["lap_times_s"].cell(metrics) == "1.5;2.0"
    assert by_field["circuit_diameter_m"].cell(metrics) == ""
    assert by_field["steps"].cell(None) == ""
    assert by_field["gpu_inference"].cell(metrics) is False
