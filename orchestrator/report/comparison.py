"""The report's comparison of brains with intervals (``reference/statistics.md``): per brain, the lap success rate
and normalised progress with 95 % bootstrap intervals that resample whole training runs, their IQM, every pair's
differences with their own intervals, the probability that one brain beats another, how each condition went, and a
performance profile with bands.

A brain compared over training seeds is a matrix entry whose weights were a glob (``group`` and ``training_seed``
in its results); any other brain is one training run, and the tables say "one training run: no interval" for it
rather than print a spread of zero width. A condition is an episode's key without the brain (part, circuit, world,
perturbation, repetition): the statistics use only the conditions every run of every brain finished with a usable
score, so every comparison is paired, and they say how many that is and which episodes were left out.

Every interval says what it covers: "these conditions, new training runs" (whole runs resampled) or "new conditions
and new runs" (runs and conditions resampled: the two-level bootstrap).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from itertools import combinations, permutations
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator.matrix.plan import part_of
from orchestrator.matrix.results import EpisodeResult
from orchestrator.report.document import Plot, Section, Table
from orchestrator.report.statistics import (
    RUNS,
    RUNS_AND_CONDITIONS,
    Interval,
    StatisticsError,
    clopper_pearson,
    difference,
    iqm,
    mean,
    probability_of_improvement,
    profile_bands,
    run_bootstrap,
)
from protocol.messages import EndReason

PROFILE_TAUS = np.linspace(0.0, 1.0, 41)
PROFILE_FILE = "performance_profile.png"
MAX_CONDITION_ROWS = 100  # rows of the per-condition table (the separating conditions first)


@dataclass(frozen=True)
class BrainScores:
    """One brain's scores: rows are its training runs (by seed), columns the shared conditions."""

    brain: str
    seeds: tuple[int | None, ...]
    success: np.ndarray  # 1.0 where the episode reached its lap target
    progress: np.ndarray  # laps driven / lap target, capped at 1
    conditions: tuple[str, ...] = ()  # the columns' condition keys


def success_of(result: EpisodeResult) -> float:
    return 1.0 if result.score is not None and result.score.reason == EndReason.LAPS_COMPLETED else 0.0


def progress_of(result: EpisodeResult) -> float:
    if result.score is None:
        return 0.0
    return float(min(max(result.score.metrics.progress_laps / max(result.spec.laps, 1), 0.0), 1.0))


def condition_of(result: EpisodeResult) -> str:
    """The episode's key without the brain, its part kept: two parts may differ only in limits, include or exclude,
    and each is a condition of its own."""
    part, rest = part_of(result.key), result.key.split("/", 1)[1]
    return f"{part}:{rest}" if part else rest


def unusable(result: EpisodeResult) -> str | None:
    """Why a scored episode's score cannot enter the statistics (None when it can)."""
    if result.score is not None and not math.isfinite(result.score.metrics.progress_laps):
        return f"episode {result.key}: progress_laps is not a finite number ({result.score.metrics.progress_laps})"
    return None


def brain_scores(results: list[EpisodeResult]) -> tuple[list[BrainScores], int, int]:
    """Each compared brain's score arrays over the conditions every run of every brain has a usable score for; also
    how many conditions there were in all and how many are shared."""
    runs: dict[str, dict[int | None, dict[str, EpisodeResult]]] = {}
    for r in results:
        if r.score is None or unusable(r) is not None:
            continue
        brain = r.brain_entry.group or r.brain
        runs.setdefault(brain, {}).setdefault(r.brain_entry.training_seed, {})[condition_of(r)] = r
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
                conditions=tuple(shared),
            )
        )
    return scored, len(every), len(shared)


def comparison_section(results: list[EpisodeResult], *, plots_dir: Path, seed: int = 0) -> tuple[Section, Path | None]:
    """The "Comparison with intervals" section, and the performance-profile plot it shows (None when none)."""
    brains, total, shared = brain_scores(results)
    section = Section("Comparison with intervals")
    left_out = [problem for problem in map(unusable, results) if problem is not None]
    if left_out:
        section.blocks.append(f"Left out of every figure below ({len(left_out)}): " + "; ".join(left_out) + ".")
    if not brains or shared == 0:
        section.blocks.append("No condition was finished with a score by every brain: nothing to compare.")
        return section, None
    section.blocks.append(
        f"Over the {shared} condition(s) every run of every brain finished with a score (of {total}): each figure "
        "rests on the training runs it names x those conditions. One training seed gives one network, and that "
        "network drives every condition, so the intervals resample whole training runs (one draw of run indices "
        "per resample, applied to every condition; 2,000 resamples, expanded percentile levels for few runs). "
        f"Each interval says what it covers: *{RUNS}* (the recipe trained again, on exactly these conditions) or "
        f"*{RUNS_AND_CONDITIONS}* (the conditions resampled too: a claim about conditions like these, beyond the "
        "set). IQM: the mean of the middle 50 % of run x condition scores; normalised progress: laps driven / lap "
        "target, capped at 1. docs/statistics.md gives the coverage these intervals reach in simulation."
    )
    section.blocks.append(_brain_table(brains, seed=seed))
    by_part = _part_table(results, seed=seed)
    if by_part is not None:
        section.blocks.append(by_part)
    if len(brains) > 1:
        section.blocks.append(_difference_table(brains, seed=seed))
        section.blocks.append(_improvement_table(brains, seed=seed))
        section.blocks.append(_condition_table(brains))
    plot = _profile_plot(brains, plots_dir=plots_dir, seed=seed)
    if plot is not None:
        section.blocks.append(plot)
    return section, plot.path if plot is not None else None


def _estimate(statistic: Callable[..., Any], scores: list[np.ndarray]) -> str:
    try:
        return f"{statistic(*scores):.2f}"
    except StatisticsError:
        return "–"


def _interval_text(
    scores: list[np.ndarray], statistic: Callable[..., Any], *, seed: int, conditions: bool = False
) -> str:
    """The estimate and its interval, or the estimate and why there is none; never an interval of zero width."""
    try:
        interval = run_bootstrap(scores, statistic, conditions=conditions, seed=seed)
    except StatisticsError as error:
        return f"{_estimate(statistic, scores)} ({error})"
    if not interval.has_width and len(scores) == 1:
        return _all_runs_alike(scores[0], interval)
    return str(interval)


def _all_runs_alike(scores: np.ndarray, interval: Interval) -> str:
    """A brain whose every run scored the same: "n of n runs", with an exact bound over runs where that score is an
    end of the scale (every run lapped every condition, or none lapped any)."""
    runs, count = scores.shape
    if np.all(scores == scores.flat[0]) and scores.flat[0] in (0.0, 1.0):
        low, high = clopper_pearson(runs, runs, confidence=interval.confidence)
        what = "scored 1 (lapped) on every one of" if scores.flat[0] == 1.0 else "scored 0 on every one of"
        return (
            f"{interval.estimate:.2f}: {runs} of {runs} runs {what} the {count} condition(s); a new run does so with "
            f"probability {low:.2f}-{high:.2f} (exact Clopper-Pearson 95 % over runs)"
        )
    return str(interval)


def _brain_table(brains: list[BrainScores], *, seed: int) -> Table:
    rows = [
        [
            b.brain,
            _runs_text(b),
            str(b.success.shape[1]),
            _interval_text([b.success], mean, seed=seed),
            _interval_text([b.success], mean, seed=seed, conditions=True),
            _interval_text([b.progress], mean, seed=seed),
            _interval_text([b.progress], iqm, seed=seed),
        ]
        for b in brains
    ]
    return Table(
        [
            "Brain",
            "Training runs",
            "Conditions",
            f"Lap success rate [95 % CI: {RUNS}]",
            f"Lap success rate [95 % CI: {RUNS_AND_CONDITIONS}]",
            f"Progress (mean) [95 % CI: {RUNS}]",
            f"Progress (IQM) [95 % CI: {RUNS}]",
        ],
        rows,
        numeric=[False, False, True, True, True, True, True],
        caption="Per brain: estimate [95 % CI over what the column names]",
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
                    _interval_text([b.success], mean, seed=seed),
                    _interval_text([b.progress], mean, seed=seed),
                ]
            )
    return Table(
        ["Part", "Brain", "Conditions", f"Lap success rate [95 % CI: {RUNS}]", f"Progress (mean) [95 % CI: {RUNS}]"],
        rows,
        numeric=[False, False, True, True, True],
        caption="Per part: estimate [95 % CI] over the training runs x the part's shared conditions",
    )


def _runs_text(brain: BrainScores) -> str:
    if brain.seeds == (None,):
        return "1 (one training run)"
    return f"{len(brain.seeds)} (seeds {', '.join(str(s) for s in brain.seeds)})"


def _difference_table(brains: list[BrainScores], *, seed: int) -> Table:
    """Every pair's paired differences, each with its own interval (each brain's runs resampled independently,
    the conditions, where resampled, jointly)."""
    rows = []
    for x, y in combinations(brains, 2):
        rate = _paired_interval([x.success, y.success], difference(mean), seed=seed)
        rows.append(
            [
                x.brain,
                y.brain,
                rate[1],
                _paired_interval([x.success, y.success], difference(mean), seed=seed, conditions=True)[1],
                _paired_interval([x.progress, y.progress], difference(mean), seed=seed)[1],
                _paired_interval([x.progress, y.progress], difference(iqm), seed=seed)[1],
                _reading(rate[0], no_effect=0.0),
            ]
        )
    return Table(
        [
            "X",
            "Y",
            f"X - Y lap success rate [95 % CI: {RUNS}]",
            f"X - Y lap success rate [95 % CI: {RUNS_AND_CONDITIONS}]",
            f"X - Y progress (mean) [95 % CI: {RUNS}]",
            f"X - Y progress (IQM) [95 % CI: {RUNS}]",
            "reading (lap success, these conditions)",
        ],
        rows,
        numeric=[False, False, True, True, True, True, False],
        caption="The difference of every pair of brains, with its own interval: a difference is read from its "
        "interval, never from two brains' intervals side by side",
    )


def _paired_interval(
    scores: list[np.ndarray], statistic: Callable[..., Any], *, seed: int, conditions: bool = False
) -> tuple[Interval | None, str]:
    try:
        interval = run_bootstrap(scores, statistic, conditions=conditions, seed=seed)
    except StatisticsError as error:
        return None, f"{_estimate(statistic, scores)} ({error})"
    return interval, str(interval)


def _reading(interval: Interval | None, *, no_effect: float) -> str:
    """Which brain the interval favours: X when it lies wholly above ``no_effect`` (0 for a difference, 0.5 for
    P(X > Y)), Y when wholly below, else that the data cannot tell."""
    if interval is None:
        return "cannot tell (no interval)"
    if not interval.has_width:
        return "cannot tell (no spread between runs)"
    if interval.low > no_effect:
        return "X better"
    if interval.high < no_effect:
        return "Y better"
    return "cannot tell (the interval straddles 0.5)" if no_effect == 0.5 else "cannot tell (the interval holds 0)"


def separating(x: BrainScores, y: BrainScores) -> np.ndarray:
    """The conditions (a boolean per column) where not every run of both brains reached the same progress: the
    others carry nothing about which is better and pull P(X > Y) towards 0.5."""
    both = np.concatenate([x.progress, y.progress])
    return np.any(both != both[:1], axis=0)


def _improvement_table(brains: list[BrainScores], *, seed: int) -> Table:
    rows = []
    for x, y in permutations(brains, 2):
        interval, text = _paired_interval([x.progress, y.progress], probability_of_improvement, seed=seed)
        columns = separating(x, y)
        if columns.any():
            _, among = _paired_interval(
                [x.progress[:, columns], y.progress[:, columns]], probability_of_improvement, seed=seed
            )
        else:
            among = "– (no condition separates them)"
        rows.append(
            [
                x.brain,
                y.brain,
                text,
                f"{int(columns.sum())} of {columns.size}",
                among,
                _reading(interval, no_effect=0.5),
            ]
        )
    return Table(
        [
            "X",
            "Y",
            f"P(X > Y), all conditions [95 % CI: {RUNS}]",
            "Conditions that separate them",
            f"P(X > Y), those conditions [95 % CI: {RUNS}]",
            "reading (all conditions)",
        ],
        rows,
        numeric=[False, False, True, True, True, False],
        caption="Probability of improvement on normalised progress: the chance X drives further than Y on one of "
        "these conditions (ties a half), whole runs resampled; meaningful when the whole interval is on one side of "
        "0.5. A condition separates two brains when not every run of both reached the same progress; the others "
        "pull P(X > Y) towards 0.5, so it is given over the separating conditions too",
    )


def _condition_table(brains: list[BrainScores]) -> Table:
    """Per condition, how many runs of each brain lapped, and whether the condition separates the brains at all."""
    success = np.concatenate([b.success for b in brains])
    separates = np.any(success != success[:1], axis=0)
    order = sorted(range(separates.size), key=lambda column: not separates[column])
    shown = order[:MAX_CONDITION_ROWS]
    rows = [
        [
            brains[0].conditions[column] if brains[0].conditions else str(column),
            *(f"{int(b.success[:, column].sum())} of {b.success.shape[0]}" for b in brains),
            "yes" if separates[column] else "no",
        ]
        for column in shown
    ]
    cut = f"; the first {len(shown)} shown, separating ones first" if len(shown) < separates.size else ""
    return Table(
        ["Condition", *(f"{b.brain}: runs that lapped" for b in brains), "separates the brains"],
        rows,
        numeric=[False, *([True] * len(brains)), False],
        caption=f"Per condition: {int(separates.sum())} of {separates.size} condition(s) separate the brains (not "
        f"every run of every brain lapped, nor every run failed){cut}",
    )


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
    return Plot(path, f"Performance profile with 95 % bands ({RUNS}: whole training runs resampled).")
