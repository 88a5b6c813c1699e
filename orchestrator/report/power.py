"""Power before driving: what difference in lap success rate a study of R training runs x C conditions detects, by
simulation, from a pilot's results or from a given run-to-run spread (``reference/statistics.md``).

    drivebench matrix FILE --plan --power PILOT_DIR
    drivebench matrix FILE --plan --run-spread 0.3 [--base-rate 0.5]

The model is a logit-normal one: run r of a brain laps condition c with probability
``expit(L + a_r + b_c)``, a run effect ``a_r ~ N(0, run_sd)`` shared by every condition the run drives (one seed, one
network), a condition effect ``b_c ~ N(0, condition_sd)`` shared by every run of every brain (the design is paired).
A pilot gives the three by simulation too: for each of its brains with two runs or more, the (run_sd,
condition_sd) on a grid whose simulated pilots best match its spread of run means and of condition means, L set so
that the mean success rate is the pilot's. A given spread is the standard deviation of a run's success rate over
runs; the conditions are then taken alike (condition_sd 0).

A simulated study detects a difference when the report's interval of the difference in success rate ("these
conditions, new training runs": whole runs resampled, expanded percentile levels) lies on one side of 0. The
smallest difference detected in 80 % of the simulated studies is what the design can answer.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orchestrator.report.statistics import percentile_levels

POWER = 0.8
DIFFERENCES = tuple(round(0.05 * step, 2) for step in range(1, 11))  # 0.05 ... 0.50 in success rate
GRID_SD = np.arange(0.0, 4.01, 0.5)  # logit-scale spreads tried when fitting a pilot
_NODES, _WEIGHTS = np.polynomial.hermite_e.hermegauss(48)  # E[f(Z)], Z ~ N(0, 1), by Gauss-Hermite quadrature
_WEIGHTS = _WEIGHTS / _WEIGHTS.sum()


class PowerError(ValueError):
    """A pilot or a spread that cannot size a study: one line saying which."""


@dataclass(frozen=True)
class Spread:
    """What a study's scores vary with: ``base_rate`` (the mean lap success rate), ``run_sd`` and ``condition_sd``
    (logit-scale standard deviations of the run and condition effects), and where they come from (``source``)."""

    base_rate: float
    run_sd: float
    condition_sd: float
    source: str


@dataclass(frozen=True)
class PowerPoint:
    """The share of simulated studies (``power``) whose interval detected a difference of ``difference``."""

    difference: float
    power: float


def _expit(values: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-values))


def logit_for_rate(rate: float, *, total_sd: float) -> float:
    """The L for which the mean of expit(L + total_sd * Z) over Z ~ N(0, 1) is ``rate`` (bisection)."""
    low, high = -30.0, 30.0
    for _ in range(80):
        middle = (low + high) / 2.0
        if float(np.sum(_WEIGHTS * _expit(middle + total_sd * _NODES))) < rate:
            low = middle
        else:
            high = middle
    return (low + high) / 2.0


def spread_given(*, run_spread: float, base_rate: float) -> Spread:
    """A spread from the standard deviation of a run's success rate over runs (``run_spread``) at ``base_rate``."""
    if not 0.0 < base_rate < 1.0:
        raise PowerError(f"--base-rate must be between 0 and 1 (exclusive), got {base_rate}")
    if not 0.0 <= run_spread < 0.5:
        raise PowerError(f"--run-spread must be a standard deviation of a success rate in [0, 0.5), got {run_spread}")

    def rate_sd(run_sd: float) -> float:
        rates = _expit(logit_for_rate(base_rate, total_sd=run_sd) + run_sd * _NODES)
        return float(np.sqrt(np.sum(_WEIGHTS * (rates - base_rate) ** 2)))

    low, high = 0.0, 20.0
    if rate_sd(high) < run_spread:
        raise PowerError(f"--run-spread {run_spread} is more than a rate of {base_rate} can spread")
    for _ in range(60):
        middle = (low + high) / 2.0
        low, high = (middle, high) if rate_sd(middle) < run_spread else (low, middle)
    return Spread(
        base_rate=base_rate,
        run_sd=(low + high) / 2.0,
        condition_sd=0.0,
        source=f"given: runs' success rates spread by {run_spread:.2f} (sd) around {base_rate:.2f}; conditions alike",
    )


def simulate(
    spread: Spread,
    *,
    runs: int,
    conditions: int,
    studies: int,
    rng: np.random.Generator,
    shift: float = 0.0,
    condition_effects: np.ndarray | None = None,
) -> np.ndarray:
    """``studies`` simulated success arrays, (studies, runs, conditions), of a brain whose mean rate is the spread's
    base rate plus ``shift``; ``condition_effects`` (studies, conditions) to pair two brains on the same ones."""
    total = float(np.hypot(spread.run_sd, spread.condition_sd))
    level = logit_for_rate(min(max(spread.base_rate + shift, 1e-6), 1 - 1e-6), total_sd=total)
    if condition_effects is None:
        condition_effects = rng.normal(0.0, spread.condition_sd, (studies, conditions))
    run_effects = rng.normal(0.0, spread.run_sd, (studies, runs, 1))
    chance = _expit(level + run_effects + condition_effects[:, None, :])
    return (rng.random(chance.shape) < chance).astype(float)


def spread_of_results(folder: Path) -> Spread:
    """The spread a pilot's results folder shows, fitted by simulation (the module's docstring)."""
    from orchestrator.matrix.results import ResultsError, ResultStore
    from orchestrator.report.comparison import brain_scores

    try:
        with ResultStore.read_only(folder) as store:  # a pilot's folder may be committed results
            results = store.results()
    except ResultsError as error:
        raise PowerError(f"--power: {error}") from None
    brains, _, shared = brain_scores(results)
    pilots = [b for b in brains if b.success.shape[0] >= 2]
    if not pilots or shared < 2:
        raise PowerError(
            f"--power {folder}: the pilot needs a brain of two training runs or more on two shared conditions or "
            f"more (it has {max((b.success.shape[0] for b in brains), default=0)} run(s) x {shared} condition(s))"
        )
    fits = [_fit(b.success) for b in pilots]
    rate = float(np.mean([b.success.mean() for b in pilots]))
    described = ", ".join(f"{b.brain} ({b.success.shape[0]} runs)" for b in pilots)
    return Spread(
        base_rate=rate,
        run_sd=float(np.mean([run_sd for run_sd, _ in fits])),
        condition_sd=float(np.mean([condition_sd for _, condition_sd in fits])),
        source=f"pilot {folder}: {described} x {shared} conditions",
    )


def _spreads(success: np.ndarray) -> np.ndarray:
    """The standard deviations of run means and of condition means, for (..., runs, conditions) arrays."""
    return np.stack([success.mean(axis=-1).std(axis=-1, ddof=1), success.mean(axis=-2).std(axis=-1, ddof=1)], -1)


def _fit(success: np.ndarray, *, studies: int = 200, seed: int = 0) -> tuple[float, float]:
    """The (run_sd, condition_sd) on :data:`GRID_SD` whose simulated pilots' spreads best match ``success``'s."""
    runs, conditions = success.shape
    observed = _spreads(success)
    rate = float(success.mean())
    best, best_distance = (0.0, 0.0), np.inf
    for run_sd in GRID_SD:
        for condition_sd in GRID_SD:
            rng = np.random.default_rng(seed)
            spread = Spread(base_rate=rate, run_sd=float(run_sd), condition_sd=float(condition_sd), source="fit")
            simulated = _spreads(simulate(spread, runs=runs, conditions=conditions, studies=studies, rng=rng))
            distance = float(np.sum((simulated.mean(axis=0) - observed) ** 2))
            if distance < best_distance:
                best, best_distance = (float(run_sd), float(condition_sd)), distance
    return best


def power_curve(
    spread: Spread,
    *,
    runs: int,
    conditions: int,
    differences: tuple[float, ...] = DIFFERENCES,
    studies: int = 400,
    resamples: int = 1000,
    seed: int = 0,
) -> list[PowerPoint]:
    """For each difference in success rate, the share of simulated paired studies (``runs`` runs of each of two
    brains x ``conditions`` shared conditions) whose run-level interval of the difference excludes 0."""
    if runs < 2:
        raise PowerError(f"{runs} training run(s) per brain gives no interval, so no power: train 2 or more seeds")
    rng = np.random.default_rng(seed)
    # Towards the middle: from a base rate above one half, the better brain cannot be much better.
    sign = 1.0 if spread.base_rate <= 0.5 else -1.0
    low_level, high_level = percentile_levels(0.95, runs=runs)
    curve = []
    for shift in differences:
        if not 0.0 < spread.base_rate + sign * shift < 1.0:
            continue
        shared = rng.normal(0.0, spread.condition_sd, (studies, conditions))
        one = simulate(spread, runs=runs, conditions=conditions, studies=studies, rng=rng, condition_effects=shared)
        other = simulate(
            spread, runs=runs, conditions=conditions, studies=studies, rng=rng, shift=sign * shift,
            condition_effects=shared,
        )  # fmt: skip
        run_means = [other.mean(axis=2), one.mean(axis=2)]  # (studies, runs): a rate is the mean of run means
        draws = [rng.integers(0, runs, (studies, resamples, runs)) for _ in run_means]
        differences_drawn = np.stack(
            [np.take_along_axis(m[:, None, :], d, axis=2).mean(axis=2) for m, d in zip(run_means, draws)]
        )
        boot = differences_drawn[0] - differences_drawn[1]
        low, high = np.percentile(boot, [low_level, high_level], axis=1)
        detected = (low > 0.0) if sign > 0 else (high < 0.0)
        curve.append(PowerPoint(difference=shift, power=float(detected.mean())))
    return curve


def detectable(curve: list[PowerPoint], *, power: float = POWER) -> float | None:
    """The smallest difference detected with at least ``power``, or None when none of the curve's is."""
    return next((point.difference for point in curve if point.power >= power), None)


def power_report(spread: Spread, *, runs: int, conditions: int, curve: list[PowerPoint]) -> str:
    """What the design detects, in lines a user reads before driving."""
    smallest = detectable(curve)
    lines = [
        f"power of {runs} training runs per brain x {conditions} conditions (paired), from {spread.source}",
        f"  model: success rate {spread.base_rate:.2f}; logit-scale spread of runs {spread.run_sd:.2f}, of "
        f"conditions {spread.condition_sd:.2f}",
        "  difference in lap success rate -> share of simulated studies whose 95 % interval (these conditions, new "
        "training runs) excludes 0:",
        *(f"    {point.difference:.2f}  {point.power:.0%}" for point in curve),
    ]
    if smallest is None:
        lines.append(
            f"  no difference up to {curve[-1].difference if curve else 0:.2f} is detected with {POWER:.0%} power: "
            "more runs (or a question with larger effects) are needed before driving"
        )
    else:
        lines.append(f"  detects a difference of {smallest:.2f} or more in lap success rate with {POWER:.0%} power")
    return "\n".join(lines)
