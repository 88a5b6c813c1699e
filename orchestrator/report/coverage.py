"""What the report's "95 %" intervals really cover, measured by simulation with a run effect shared by every
condition (one training seed gives one network, and that network drives every condition).

    python -m orchestrator.report.coverage [--experiments 1000] [--resamples 2000]

prints the table docs/statistics.md quotes; ``tests/test_coverage.py`` runs a smaller form of it.

The model (a probit, so that the true success rates are exact): episode r, c laps when
``mu + a_r + b_c + e_rc > 0``, with a run effect ``a_r ~ N(0, run_sd)`` shared by all of run r's conditions, a
condition effect ``b_c ~ N(0, condition_sd)`` shared by every run, and episode noise ``e_rc ~ N(0, episode_sd)``.
The truths:

* "these conditions, new training runs": the mean over this experiment's conditions of
  ``Phi((mu + b_c) / sqrt(run_sd^2 + episode_sd^2))``;
* "new conditions and new runs": ``Phi(mu / sqrt(run_sd^2 + condition_sd^2 + episode_sd^2))``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from orchestrator.report.statistics import (
    RUNS,
    RUNS_AND_CONDITIONS,
    Interval,
    mean,
    per_condition_bootstrap,
    run_bootstrap,
)

MU = 0.3
CONDITION_SD = 1.0
EPISODE_SD = 0.5


@dataclass(frozen=True)
class Design:
    """One simulated study: ``runs`` training runs x ``conditions`` conditions, the run effect's spread (probit)."""

    runs: int
    conditions: int
    run_sd: float


@dataclass(frozen=True)
class Method:
    """An interval as the report computes it, and the population whose truth it is held to."""

    name: str
    covers: str
    interval: Callable[[np.ndarray, int, int], Interval]  # (success scores, resamples, seed)


METHODS = (
    Method(
        "per condition (reports before issue 39)",
        RUNS,
        lambda scores, resamples, seed: per_condition_bootstrap([scores], mean, resamples=resamples, seed=seed),
    ),
    Method(
        "whole runs, plain percentile",
        RUNS,
        lambda scores, resamples, seed: run_bootstrap([scores], mean, resamples=resamples, seed=seed, expanded=False),
    ),
    Method(
        "whole runs, expanded (the report's)",
        RUNS,
        lambda scores, resamples, seed: run_bootstrap([scores], mean, resamples=resamples, seed=seed),
    ),
    Method(
        "runs and conditions, expanded (the report's)",
        RUNS_AND_CONDITIONS,
        lambda scores, resamples, seed: run_bootstrap([scores], mean, conditions=True, resamples=resamples, seed=seed),
    ),
)
DESIGNS = tuple(
    Design(runs=runs, conditions=conditions, run_sd=run_sd)
    for run_sd in (0.5, 1.5)
    for runs in (5, 10)
    for conditions in (20, 40)
)


def coverage(design: Design, *, experiments: int, resamples: int, seed: int = 0) -> dict[str, float]:
    """Per method's name, the share of ``experiments`` simulated studies whose interval held the truth."""
    rng = np.random.default_rng(seed)
    normal = NormalDist()
    within_sd = float(np.hypot(design.run_sd, EPISODE_SD))
    everywhere = normal.cdf(MU / float(np.sqrt(design.run_sd**2 + CONDITION_SD**2 + EPISODE_SD**2)))
    covered = dict.fromkeys((m.name for m in METHODS), 0)
    for experiment in range(experiments):
        condition_effects = rng.normal(0.0, CONDITION_SD, design.conditions)
        run_effects = rng.normal(0.0, design.run_sd, (design.runs, 1))
        noise = rng.normal(0.0, EPISODE_SD, (design.runs, design.conditions))
        scores = (MU + run_effects + condition_effects + noise > 0).astype(float)
        truths = {
            RUNS: float(np.mean([normal.cdf((MU + b) / within_sd) for b in condition_effects])),
            RUNS_AND_CONDITIONS: everywhere,
        }
        for method in METHODS:
            interval = method.interval(scores, resamples, experiment)
            covered[method.name] += interval.low <= truths[method.covers] <= interval.high
    return {name: count / experiments for name, count in covered.items()}


def coverage_table(*, experiments: int, resamples: int) -> str:
    """The Markdown table of every method's coverage over :data:`DESIGNS`."""
    lines = [
        "| run effect (probit sd) | runs x conditions | " + " | ".join(m.name for m in METHODS) + " |",
        "|---|---|" + "---:|" * len(METHODS),
    ]
    for design in DESIGNS:
        shares = coverage(design, experiments=experiments, resamples=resamples)
        cells = " | ".join(f"{shares[m.name]:.1%}" for m in METHODS)
        lines.append(f"| {design.run_sd} | {design.runs} x {design.conditions} | {cells} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", type=int, default=1000, help="simulated studies per design (default 1000)")
    parser.add_argument("--resamples", type=int, default=2000, help="bootstrap resamples per interval (default 2000)")
    args = parser.parse_args(argv)
    print(coverage_table(experiments=args.experiments, resamples=args.resamples))
    return 0


if __name__ == "__main__":
    sys.exit(main())
