"""A matrix's episodes as a flat table (one row per episode: its coordinates, outcome and metrics) for CSV and, where
pyarrow is installed, Parquet: what people load into pandas or a spreadsheet."""

from __future__ import annotations

import csv
import importlib.util
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.columns import CSV_COLUMNS


def episode_rows(results: Sequence[EpisodeResult]) -> list[dict[str, Any]]:
    """One flat dict per episode: conditions, status, timings, every metric column
    (:data:`~orchestrator.report.columns.CSV_COLUMNS`), files."""
    rows = []
    for r in results:
        row: dict[str, Any] = {
            "key": r.key,
            "brain": r.brain,
            # A training run of a brain compared over seeds: the brain it is a run of, and its training seed.
            "brain_group": r.brain_entry.group or r.brain,
            "training_seed": "" if r.brain_entry.training_seed is None else r.brain_entry.training_seed,
            "circuit": r.circuit,
            "variation": r.variation,
            "perturbation": r.perturbation,
            "repetition": r.repetition,
            "seed": r.spec.seed,
            "laps_target": r.spec.laps,
            "status": r.status,
            "reason": r.reason or "",
            "failure": str(r.failure or ""),
            "wall_s": round(r.wall_s, 3),
        }
        metrics = r.score.metrics if r.score is not None else None
        for column in CSV_COLUMNS:
            row[column.field] = column.cell(metrics)
        row.update(
            {
                "recording": r.recording or "",
                "trajectory": r.trajectory or "",
                "logs": r.logs or "",
                "node": r.node or "",
                "lost_attempts": len(r.lost_attempts),
            }
        )
        rows.append(row)
    return rows


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def write_parquet(rows: list[dict[str, Any]], path: Path) -> Path | None:
    if importlib.util.find_spec("pyarrow") is None:
        return None
    import pyarrow as pa
    import pyarrow.parquet as pq

    # Empty strings of unscored episodes become nulls, so numeric columns keep a numeric type.
    columns = {name: [None if row[name] == "" else row[name] for row in rows] for name in rows[0]}
    pq.write_table(pa.table(columns), path)
    return path
