"""The report's comparison of brains with intervals (``reference/statistics.md``): per brain, the lap success rate
and normalised progress with 95 % stratified-bootstrap confidence intervals over training runs x conditions, their
IQM, the probability that one brain beats another on a random condition, and a performance profile with bands.

A brain compared over training seeds is a matrix entry whose weights were a glob (``group`` and ``training_seed``
in its results); any other brain is one training run, and the tables say "one training run: no interval" for it
rather than print a spread of zero width. Conditions are the episodes' keys without the brain (circuit, world,
perturbation, repetition): the statistics use only the conditions every run of every brain finished with a score,
so every comparison is paired, and they say how many that is.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations
from pathlib import Path

import numpy as np

from orchestrator.matrix.plan import part_of
from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.document import Plot, Section, Table
from orchestrator.report.statistics import (
    ONE_RUN,
    Interval,
    StatisticsError,
    iqm,
    mean,
    probability_of_improvement,
    profile_bands,
    stratified_bootstrap,
)
from protocol.messages import EndReason

PROFILE_TAUS = np.linspace(0.0, 1.0, 41)
PROFILE_FILE = "performance_profile.png"


@dataclass(frozen=True)
class BrainScores:
    """One brain's scores: rows are its training runs (by seed), columns the shared conditions."""

    brain: str
    seeds: tuple[int | None, ...]
    success: np.ndarray  # 1.0 where the episode reached its lap target
    progress: np.ndarray  # laps driven / lap target, capped at 1


def success_of(result: EpisodeResult) -> float:
    return 1.0 if result.score is not None and result.score.reason == EndReason.LAPS_COMPLETED else 0.0


def progress_of(result: EpisodeResult) -> float:
    if result.score is None:
        return 0.0
    return float(min(max(result.score.metrics.progress_laps / max(result.spec.laps, 1), 0.0), 1.0))


def condition_of(result: EpisodeResult) -> str:
    return result.key.split("/", 1)[1]


def brain_scores(results: list[EpisodeResult]) -> tuple[list[BrainScores], int, int]:
    """Each compared brain's score arrays over the conditions every run of every brain has a score for; also how
    many conditions there were in all and how many are shared."""
    runs: dict[str, dict[int | None, dict[str, EpisodeResult]]] = {}
    for r in results:
        if r.score is None:
            continue
        brain = str(r.brain_entry.get("group") or r.brain)
        runs.setdefault(brain, {}).setdefault(r.brain_entry.get("training_seed"), {})[condition_of(r)] = r
    every = {condition_of(r) for r in results}
    shared = sorted(set.intersection(*(set(c) for by_seed in runs.values() for c in by_seed.values())) if runs else [])
    scored = []
    for brain, by_seed in runs.items():
        seeds = tuple(sorted(by_seed, key=lambda seed: -1 if seed is None else seed))
        rows = [[by_seed[seed][c] for c in shared] for seed in seeds]
        scored.append(
            BrainScores(
                brain=brain,
                seeds=seeds,
                success=np.array([[success_of(r) for r in row] for row in rows]).reshape(len(seeds), len(shared)),
                progress=np.array([[progress_of(r) for r in row] for row in rows]).reshape(len(seeds), len(shared)),
            )
        )
    return scored, len(every), len(shared)


def comparison_section(results: list[EpisodeResult], *, plots_dir: Path, seed: int = 0) -> tuple[Section, Path | None]:
    """The "Comparison with intervals" section, and the performance-profile plot it shows (None when none)."""
    brains, total, shared = brain_scores(results)
    section = Section("Comparison with intervals")
    if not brains or shared == 0:
        section.blocks.append("No condition was finished with a score by every brain: nothing to compare.")
        return section, None
    section.blocks.append(
        f"Over the {shared} condition(s) every run of every brain finished with a score (of {total}): each figure "
        "rests on the training runs it names x those conditions. Intervals: 95 % stratified bootstrap over training "
        "runs within each condition (2,000 resamples); IQM: the mean of the middle 50 % of run x condition scores; "
        "normalised progress: laps driven / lap target, capped at 1."
    )
    section.blocks.append(_brain_table(brains, seed=seed))
    by_part = _part_table(results, seed=seed)
    if by_part is not None:
        section.blocks.append(by_part)
    if len(brains) > 1:
        section.blocks.append(_improvement_table(brains, seed=seed))
    plot = _profile_plot(brains, plots_dir=plots_dir, seed=seed)
    if plot is not None:
        section.blocks.append(plot)
    return section, plot.path if plot is not None else None


def _with_interval(scores: np.ndarray, statistic, *, seed: int) -> str:
    try:
        return str(stratified_bootstrap([scores], statistic, seed=seed))
    except StatisticsError as error:
        return f"{statistic(scores):.2f} ({error})"


def _brain_table(brains: list[BrainScores], *, seed: int) -> Table:
    rows = [
        [
            b.brain,
            _runs_text(b),
            str(b.success.shape[1]),
            _with_interval(b.success, mean, seed=seed),
            _with_interval(b.progress, mean, seed=seed),
            _with_interval(b.progress, iqm, seed=seed),
        ]
        for b in brains
    ]
    return Table(
        ["Brain", "Training runs", "Conditions", "Lap success rate", "Progress (mean)", "Progress (IQM)"],
        rows,
        numeric=[False, False, True, True, True, True],
        caption="Per brain: estimate [95 % CI]",
    )


def _part_table(results: list[EpisodeResult], *, seed: int) -> Table | None:
    """Per part and brain, over the part's own shared conditions: where a brain's overall figure comes from (a
    study's parts are its question's axes, e.g. the flat and the gazebo look). None for a matrix without parts."""
    parts: dict[str, list[EpisodeResult]] = {}
    for r in results:
        parts.setdefault(part_of(r.key), []).append(r)
    if len(parts) < 2:
        return None
    rows = []
    for part, part_results in parts.items():
        brains, _, shared = brain_scores(part_results)
        for b in brains:
            rows.append(
                [
                    part or "(top level)",
                    b.brain,
                    str(shared),
                    _with_interval(b.success, mean, seed=seed),
                    _with_interval(b.progress, mean, seed=seed),
                ]
            )
    return Table(
        ["Part", "Brain", "Conditions", "Lap success rate", "Progress (mean)"],
        rows,
        numeric=[False, False, True, True, True],
        caption="Per part: estimate [95 % CI] over the training runs x the part's shared conditions",
    )


def _runs_text(brain: BrainScores) -> str:
    if brain.seeds == (None,):
        return "1 (one training run)"
    return f"{len(brain.seeds)} (seeds {', '.join(str(s) for s in brain.seeds)})"


def _improvement_table(brains: list[BrainScores], *, seed: int) -> Table:
    rows = []
    for x, y in permutations(brains, 2):
        try:
            interval = stratified_bootstrap([x.progress, y.progress], probability_of_improvement, seed=seed)
            text, verdict = str(interval), _verdict(interval)
        except StatisticsError:
            text = f"{probability_of_improvement(x.progress, y.progress):.2f} ({ONE_RUN})"
            verdict = "cannot tell (no interval)"
        rows.append([x.brain, y.brain, text, verdict])
    return Table(
        ["X", "Y", "P(X > Y) [95 % CI]", "reading"],
        rows,
        numeric=[False, False, True, False],
        caption="Probability of improvement on normalised progress: the chance X drives further than Y on a random "
        "condition (ties a half); meaningful when the whole interval is on one side of 0.5",
    )


def _verdict(interval: Interval) -> str:
    if interval.low > 0.5:
        return "X better"
    if interval.high < 0.5:
        return "Y better"
    return "cannot tell (the interval straddles 0.5)"


def _profile_plot(brains: list[BrainScores], *, plots_dir: Path, seed: int) -> Plot | None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0), layout="constrained")
    for b in brains:
        try:
            profile, low, high = profile_bands(b.progress, PROFILE_TAUS, seed=seed)
            ax.fill_between(PROFILE_TAUS, low, high, alpha=0.2)
            label = f"{b.brain} ({len(b.seeds)} runs)"
        except StatisticsError:
            profile = np.array([(b.progress.ravel() > tau).mean() for tau in PROFILE_TAUS])
            label = f"{b.brain} (one run: no band)"
        ax.plot(PROFILE_TAUS, profile, lw=1.8, label=label)
    ax.set_xlabel("normalised progress τ (laps driven / lap target)")
    ax.set_ylabel("fraction of runs x conditions above τ")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(True, color="0.92")
    ax.legend(fontsize=8.5, frameon=False)
    plots_dir.mkdir(parents=True, exist_ok=True)
    path = plots_dir / PROFILE_FILE
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Plot(path, "Performance profile with 95 % bands over training runs (stratified bootstrap).")
