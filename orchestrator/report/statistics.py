"""Interval estimates for comparing brains over training seeds and conditions (``reference/statistics.md``).

The methods of rliable (Agarwal et al., NeurIPS 2021, "Deep RL at the edge of the statistical precipice"),
written here on numpy alone: rliable itself pins ``arch < 8`` and pulls seaborn, pandas and absl for these few
functions, and its definitions are short enough to hold to tests with known answers (``tests/test_statistics.py``).

Scores are arrays of shape ``(runs, conditions)``: one row per training run (seed) of a brain, one column per
condition every brain met alike (circuit x world x perturbation x repetition: a paired design). A score is a number
per episode, success (0/1) or normalised progress in [0, 1].

* :func:`stratified_bootstrap`: a percentile confidence interval of any aggregate, resampling runs with replacement
  within each condition (the stratified bootstrap), 2,000 resamples by default.
* :func:`iqm`: the interquartile mean of all run x condition scores (the mean of the middle 50 %).
* :func:`probability_of_improvement`: P(X > Y), the chance that brain X beats brain Y on a random condition, from
  the Mann-Whitney U statistic over runs (ties count a half), averaged over conditions.
* :func:`performance_profile`: the fraction of run x condition scores above each threshold tau.

One run gives no interval: :func:`stratified_bootstrap` refuses it and the reports say "one training run: no
interval" rather than print a spread of zero width.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

DEFAULT_RESAMPLES = 2000
DEFAULT_CONFIDENCE = 0.95
ONE_RUN = "one training run: no interval"


class StatisticsError(ValueError):
    """Scores that cannot be compared (wrong shape, different conditions, one run): one line saying which."""


@dataclass(frozen=True)
class Interval:
    """A point estimate and its confidence interval (``low`` <= ``high``), at ``confidence`` (0.95: 95 %)."""

    estimate: float
    low: float
    high: float
    confidence: float = DEFAULT_CONFIDENCE

    def __str__(self) -> str:
        return f"{self.estimate:.2f} [{self.low:.2f}, {self.high:.2f}]"


def as_scores(scores: np.ndarray | Sequence[Sequence[float]], *, what: str = "scores") -> np.ndarray:
    """``scores`` as a finite float array of shape (runs, conditions), or :class:`StatisticsError`."""
    array = np.asarray(scores, dtype=float)
    if array.ndim != 2 or array.shape[0] < 1 or array.shape[1] < 1:
        raise StatisticsError(f"{what} must be runs x conditions (a 2-D array), got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise StatisticsError(f"{what} hold a value that is not a finite number")
    return array


def iqm(scores: np.ndarray) -> float:
    """The interquartile mean of every run x condition score: sorted, the lowest and highest ``int(0.25 * n)`` cut,
    the rest averaged (scipy.stats.trim_mean with 0.25, as rliable computes it)."""
    values = np.sort(np.asarray(scores, dtype=float).ravel())
    cut = int(0.25 * values.size)
    return float(np.mean(values[cut : values.size - cut]))


def mean(scores: np.ndarray) -> float:
    """The mean of every run x condition score (success rate for 0/1 scores)."""
    return float(np.mean(scores))


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """P(X > Y): for each condition, the fraction of (run of X, run of Y) pairs where X scores higher, ties a half
    (the Mann-Whitney U statistic over n_x * n_y); then the mean over conditions. 0.5 for a brain against itself."""
    x, y = as_scores(x, what="scores of X"), as_scores(y, what="scores of Y")
    if x.shape[1] != y.shape[1]:
        raise StatisticsError(f"X and Y met different numbers of conditions ({x.shape[1]} and {y.shape[1]})")
    # pairs[c, i, j] compares run i of X with run j of Y on condition c.
    pairs = x.T[:, :, None] - y.T[:, None, :]
    wins = (pairs > 0).mean(axis=(1, 2)) + 0.5 * (pairs == 0).mean(axis=(1, 2))
    return float(wins.mean())


def performance_profile(scores: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """The fraction of run x condition scores strictly above each tau."""
    values = np.asarray(scores, dtype=float).ravel()
    return np.array([(values > tau).mean() for tau in np.asarray(taus, dtype=float)])


def stratified_bootstrap(
    scores: Sequence[np.ndarray],
    statistic: Callable[..., float],
    *,
    resamples: int = DEFAULT_RESAMPLES,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
) -> Interval:
    """``statistic(*scores)`` with a percentile interval from the stratified bootstrap: in every resample, each
    brain's runs are drawn with replacement within each condition (column), independently per brain.

    ``scores``: one (runs, conditions) array per brain that ``statistic`` takes. Raises :class:`StatisticsError`
    when a brain has a single run (there is nothing to resample: "one training run: no interval")."""
    arrays = [as_scores(array) for array in scores]
    if any(array.shape[0] < 2 for array in arrays):
        raise StatisticsError(ONE_RUN)
    if not 0.0 < confidence < 1.0:
        raise StatisticsError(f"confidence must be between 0 and 1, got {confidence}")
    rng = np.random.default_rng(seed)
    samples = [_resamples_within_conditions(array, rng, resamples) for array in arrays]
    estimates = np.array([statistic(*(sample[index] for sample in samples)) for index in range(resamples)])
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(estimates, [tail, 100.0 - tail])
    return Interval(estimate=statistic(*arrays), low=float(low), high=float(high), confidence=confidence)


def _resamples_within_conditions(array: np.ndarray, rng: np.random.Generator, resamples: int) -> np.ndarray:
    """``resamples`` copies of ``array`` (runs, conditions), each column's runs drawn with replacement from that
    column alone: shape (resamples, runs, conditions)."""
    runs, conditions = array.shape
    rows = rng.integers(0, runs, size=(resamples, runs, conditions))
    return array[rows, np.arange(conditions)]


def profile_bands(
    scores: np.ndarray,
    taus: np.ndarray,
    *,
    resamples: int = DEFAULT_RESAMPLES,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A performance profile and its pointwise confidence band: (profile, low, high), each one value per tau."""
    array = as_scores(scores)
    if array.shape[0] < 2:
        raise StatisticsError(ONE_RUN)
    rng = np.random.default_rng(seed)
    curves = np.stack(
        [performance_profile(sample, taus) for sample in _resamples_within_conditions(array, rng, resamples)]
    )
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(curves, [tail, 100.0 - tail], axis=0)
    return performance_profile(array, taus), low, high
