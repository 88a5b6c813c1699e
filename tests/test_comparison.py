"""The report's comparison of brains (orchestrator/report/comparison.py) on results built in memory: the conditions
it pairs, what it says when a score cannot be used, and the tables it prints (issue 39)."""

from __future__ import annotations

import math

import msgspec
import pytest

from orchestrator.matrix.plan import BrainEntry
from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.comparison import brain_scores, comparison_section
from orchestrator.report.document import Table
from orchestrator.report.statistics import ONE_RUN, RUNS, RUNS_AND_CONDITIONS
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EndReason, EpisodeMetrics, EpisodeScore, Header


def metrics_with(progress_laps: float) -> EpisodeMetrics:
    fields = {name: 0.0 for name in EpisodeMetrics.__struct_fields__}
    fields.update(
        steps=100, completed_laps=int(progress_laps >= 1.0), lap_times_s=[], off_track_events=0,
        bm_lap_seconds=None, progress_laps=progress_laps, gpu_inference=False,
    )  # fmt: skip
    return msgspec.convert(fields, EpisodeMetrics)


def episode(
    label: str, *, circuit: str = "simple", part: str = "", progress: float = 1.0, group: str = "", seed: int = 0
) -> EpisodeResult:
    """One scored episode of brain ``label`` (a training run of ``group`` when given), keyed as a matrix keys it."""
    spec = EpisodeSpec(circuit=circuit, laps=1, seed=0, active_brain=label)
    # msgspec.convert refuses a non-finite float from JSON-like input: build the metrics, then replace the value.
    metrics = msgspec.structs.replace(metrics_with(1.0 if math.isfinite(progress) else 0.0), progress_laps=progress)
    reason = EndReason.LAPS_COMPLETED if progress >= 1.0 else EndReason.CRASH
    score = EpisodeScore(
        header=Header(run_id="r", episode=0, seq=0, stamp_ns=0), spec=spec, reason=reason, brain=label, metrics=metrics
    )
    entry = {"label": label, "brain": "x", "weights": None, "options": {}}
    if group:
        entry.update(group=group, training_seed=seed)
    prefix = f"{part}:" if part else ""
    return EpisodeResult(
        key=f"{prefix}{label}/{circuit}/default/none/r0", index=0, brain=label, circuit=circuit,
        variation="default", perturbation="none", repetition=0, spec=spec, brain_entry=BrainEntry.from_dict(entry),
        status="done", run_id="r", started_at=0.0, ended_at=1.0, reason=str(reason), score=score,
    )  # fmt: skip


def runs_of(group: str, seeds, **kwargs) -> list[EpisodeResult]:
    return [episode(f"{group}-s{seed}", group=group, seed=seed, **kwargs) for seed in seeds]


def tables_of(section) -> list[Table]:
    return [block for block in section.blocks if isinstance(block, Table)]


def text_of(section) -> str:
    parts = []
    for block in section.blocks:
        if isinstance(block, Table):
            parts.append(" | ".join(block.columns) + " " + block.caption)
            parts.extend(" | ".join(row) for row in block.rows)
        elif isinstance(block, str):
            parts.append(block)
    return "\n".join(parts)


def test_two_parts_that_differ_only_in_limits_are_two_conditions():
    """The condition key kept the part's name out: two parts with the same circuit, world, perturbation and
    repetition (they differ in limits, include or exclude) collided, one silently overwriting the other."""
    results = []
    for part in ("short", "long"):
        results += [episode("explicit", part=part), *runs_of("tiny", (0, 1), part=part)]
    assert len(results) == 6
    brains, total, shared = brain_scores(results)
    assert (total, shared) == (2, 2)
    assert {b.brain: b.success.shape for b in brains} == {"explicit": (1, 2), "tiny": (2, 2)}


def test_a_score_that_is_not_a_number_is_left_out_and_named_not_called_one_run(tmp_path):
    """Every StatisticsError was labelled "one training run", and the fallback then raised on the non-finite
    progress itself: one bad score stopped the whole report."""
    results = runs_of("tiny", (0, 1, 2)) + runs_of("big", (0, 1, 2))
    results += runs_of("tiny", (0, 1, 2), circuit="many_curves") + runs_of("big", (0, 1), circuit="many_curves")
    results.append(episode("big-s2", group="big", seed=2, circuit="many_curves", progress=math.nan))
    section, _ = comparison_section(results, plots_dir=tmp_path)
    text = text_of(section)
    assert ONE_RUN not in text, text
    assert "big-s2/many_curves/default/none/r0" in text and "not a finite number" in text, text
    brains, _, shared = brain_scores(results)
    assert shared == 1 and all(b.success.shape[0] == 3 for b in brains)


def test_every_interval_says_what_it_covers_and_differences_have_intervals(tmp_path):
    results = []
    for circuit, tiny_laps in (("simple", (1.0, 1.0, 0.4)), ("many_curves", (1.0, 0.3, 0.2)), ("monaco", (1.0,) * 3)):
        results += [
            episode(f"tiny-s{seed}", group="tiny", seed=seed, circuit=circuit, progress=progress)
            for seed, progress in enumerate(tiny_laps)
        ]
        results += runs_of("big", (0, 1, 2), circuit=circuit)
    section, _ = comparison_section(results, plots_dir=tmp_path)
    text = text_of(section)
    assert RUNS in text and RUNS_AND_CONDITIONS in text, text
    difference = next(t for t in tables_of(section) if t.columns[:2] == ["X", "Y"] and "difference" in t.caption)
    assert any("[" in cell for row in difference.rows for cell in row[2:]), difference.rows
    # big laps every condition with every run: never "1.00 [1.00, 1.00]", but the count of runs and an exact bound.
    assert "1.00 [1.00, 1.00]" not in text
    assert "3 of 3 runs" in text and "Clopper-Pearson" in text, text
    # monaco: every run of both brains lapped: it cannot separate them, and the report says so.
    assert "2 of 3" in text, text


@pytest.mark.parametrize("separating", [True, False])
def test_the_per_condition_table_counts_the_runs_that_lapped(tmp_path, separating):
    results = runs_of("tiny", (0, 1)) + runs_of("big", (0, 1))
    results += [
        episode("tiny-s0", group="tiny", seed=0, circuit="monaco", progress=0.5 if separating else 1.0),
        episode("tiny-s1", group="tiny", seed=1, circuit="monaco"),
        *runs_of("big", (0, 1), circuit="monaco"),
    ]
    section, _ = comparison_section(results, plots_dir=tmp_path)
    table = next(t for t in tables_of(section) if t.columns[0] == "Condition")
    rows = {row[0]: row for row in table.rows}
    monaco = next(row for key, row in rows.items() if "monaco" in key)
    assert monaco[1:] == (["1 of 2", "2 of 2", "yes"] if separating else ["2 of 2", "2 of 2", "no"])
