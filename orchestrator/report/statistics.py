"""Interval estimates for comparing brains over training runs and conditions (``reference/statistics.md``).

The aggregates of rliable (Agarwal et al., NeurIPS 2021, "Deep RL at the edge of the statistical precipice"),
written here on numpy alone: rliable itself pins ``arch < 8`` and pulls seaborn, pandas and absl for these few
functions, and its definitions are short enough to hold to tests with known answers (``tests/test_statistics.py``).

Scores are arrays of shape ``(runs, conditions)``: one row per training run (seed) of a brain, one column per
condition every brain met alike (circuit x world x perturbation x repetition: a paired design). A score is a number
per episode, success (0/1) or normalised progress in [0, 1]. Every aggregate here also takes a stack of such arrays
(``(..., runs, conditions)``) and gives one value per leading index, so a bootstrap computes thousands at once.

**The unit of resampling is the training run.** One seed gives one network and that network drives every
condition: a seed that learned badly is bad everywhere. So :func:`run_bootstrap` draws run indices once per resample
and applies them to every condition (rliable's stratified bootstrap draws them per condition, which treats one
network's episodes as independent draws: its "95 %" interval covered the truth 46-69 % of the time in
``tests/test_coverage.py``; :func:`per_condition_bootstrap` keeps it for that measurement only).

* :func:`run_bootstrap`: a confidence interval of any aggregate that resamples whole training runs, each brain's
  independently; with ``conditions=True`` it resamples the conditions too (jointly for every brain: paired), the
  two-level bootstrap for claims about conditions beyond the set. Each :class:`Interval` says what it covers.
* :func:`iqm`, :func:`mean`, :func:`probability_of_improvement` (P(X > Y) from the Mann-Whitney U statistic over
  runs, averaged over conditions), :func:`performance_profile`, :func:`profile_bands`.
* :func:`clopper_pearson`: the exact binomial interval, for "k of n runs" where a bootstrap has no spread.

A percentile bootstrap over n runs sees only an (n - 1)/n share of their variance and a normal tail where a t tail
belongs, so with 5-10 runs it under-covers. The intervals here are *expanded* percentile intervals (Hesterberg,
"What teachers should know about the bootstrap", 2015): the percentile levels are widened so that a normal
quantile becomes ``sqrt(n / (n - 1)) * t(n - 1)``'s. ``benchmarks/interval_coverage.py`` measures what they cover.

One run gives no interval: :func:`run_bootstrap` refuses it and the reports say "one training run: no interval"
rather than print a spread of zero width.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np

DEFAULT_RESAMPLES = 2000
DEFAULT_CONFIDENCE = 0.95
ONE_RUN = "one training run: no interval"
# What an interval covers: the population a new experiment would draw from.
RUNS = "these conditions, new training runs"
RUNS_AND_CONDITIONS = "new conditions and new runs"
# Scores per chunk of resamples: bounds the memory of a bootstrap over many runs and conditions.
_CHUNK_VALUES = 4_000_000


class StatisticsError(ValueError):
    """Scores that cannot be compared (wrong shape, different conditions, one run): one line saying which."""


@dataclass(frozen=True)
class Interval:
    """A point estimate and its confidence interval (``low`` <= ``high``), at ``confidence`` (0.95: 95 %), over the
    population ``covers`` names (:data:`RUNS` or :data:`RUNS_AND_CONDITIONS`)."""

    estimate: float
    low: float
    high: float
    confidence: float = DEFAULT_CONFIDENCE
    covers: str = RUNS

    @property
    def has_width(self) -> bool:
        return self.high > self.low

    def __str__(self) -> str:
        # A zero-width interval claims a certainty the runs do not give: say what was seen instead.
        if not self.has_width:
            return f"{self.estimate:.2f} (every resample alike: no spread between runs, no interval)"
        return f"{self.estimate:.2f} [{self.low:.2f}, {self.high:.2f}]"


def as_scores(scores: np.ndarray | Sequence[Sequence[float]], *, what: str = "scores") -> np.ndarray:
    """``scores`` as a finite float array of shape (runs, conditions), or :class:`StatisticsError`."""
    array = np.asarray(scores, dtype=float)
    if array.ndim != 2 or array.shape[0] < 1 or array.shape[1] < 1:
        raise StatisticsError(f"{what} must be runs x conditions (a 2-D array), got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise StatisticsError(f"{what} hold a value that is not a finite number")
    return array


def _scalar_or_array(values: np.ndarray) -> Any:
    return float(values) if np.ndim(values) == 0 else values


def iqm(scores: np.ndarray) -> Any:
    """The interquartile mean of every run x condition score: sorted, the lowest and highest ``int(0.25 * n)`` cut,
    the rest averaged (scipy.stats.trim_mean with 0.25, as rliable computes it). One value per leading index."""
    array = np.asarray(scores, dtype=float)
    if array.ndim < 2:
        array = array.reshape(1, -1)
    values = np.sort(array.reshape(*array.shape[:-2], -1), axis=-1)
    cut = int(0.25 * values.shape[-1])
    return _scalar_or_array(np.mean(values[..., cut : values.shape[-1] - cut], axis=-1))


def mean(scores: np.ndarray) -> Any:
    """The mean of every run x condition score (success rate for 0/1 scores). One value per leading index."""
    return _scalar_or_array(np.mean(np.asarray(scores, dtype=float), axis=(-2, -1)))


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> Any:
    """P(X > Y): for each condition, the fraction of (run of X, run of Y) pairs where X scores higher, ties a half
    (the Mann-Whitney U statistic over n_x * n_y); then the mean over conditions. 0.5 for a brain against itself."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.ndim == 2 or y.ndim == 2:
        x, y = as_scores(x, what="scores of X"), as_scores(y, what="scores of Y")
    if x.shape[-1] != y.shape[-1]:
        raise StatisticsError(f"X and Y met different numbers of conditions ({x.shape[-1]} and {y.shape[-1]})")
    # pairs[..., i, j, c] compares run i of X with run j of Y on condition c.
    pairs = x[..., :, None, :] - y[..., None, :, :]
    wins = (pairs > 0).mean(axis=(-3, -2)) + 0.5 * (pairs == 0).mean(axis=(-3, -2))
    return _scalar_or_array(wins.mean(axis=-1))


def difference(statistic: Callable[[np.ndarray], Any]) -> Callable[[np.ndarray, np.ndarray], Any]:
    """``statistic(x) - statistic(y)``: the paired difference of two brains' aggregates, as one statistic."""

    def of(x: np.ndarray, y: np.ndarray) -> Any:
        return statistic(x) - statistic(y)

    of.__name__ = f"difference of {getattr(statistic, '__name__', 'statistic')}"
    return of


def performance_profile(scores: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """The fraction of run x condition scores strictly above each tau (one row per leading index)."""
    array = np.asarray(scores, dtype=float)
    values = array.reshape(*array.shape[:-2], -1) if array.ndim >= 2 else array
    return (values[..., None] > np.asarray(taus, dtype=float)).mean(axis=-2)


def run_bootstrap(
    scores: Sequence[np.ndarray],
    statistic: Callable[..., Any],
    *,
    conditions: bool = False,
    resamples: int = DEFAULT_RESAMPLES,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
    expanded: bool = True,
) -> Interval:
    """``statistic(*scores)`` with a bootstrap interval that resamples whole training runs: in every resample, one
    draw of each brain's run indices (with replacement, independently per brain) applied to every condition. With
    ``conditions``, the conditions are drawn with replacement too, once per resample for every brain (paired).

    ``scores``: one (runs, conditions) array per brain that ``statistic`` takes; ``statistic`` must take stacks
    (``(resamples, runs, conditions)``) as the aggregates of this module do. ``expanded``: the expanded percentile
    levels for the fewest runs (the module's docstring says why); False: plain percentiles. Raises
    :class:`StatisticsError` when a brain has a single run ("one training run: no interval")."""
    arrays = _checked(scores, confidence)
    rng = np.random.default_rng(seed)
    count = arrays[0].shape[1]
    per_resample = max(a.shape[0] for a in arrays) ** 2 * count * len(arrays)
    chunk = max(1, min(resamples, _CHUNK_VALUES // max(per_resample, 1)))
    estimates = []
    for start in range(0, resamples, chunk):
        size = min(chunk, resamples - start)
        columns = rng.integers(0, count, size=(size, 1, count)) if conditions else None
        samples = []
        for array in arrays:
            rows = rng.integers(0, array.shape[0], size=(size, array.shape[0], 1))
            samples.append(array[rows, columns if columns is not None else np.arange(count)])
        estimates.append(np.asarray(statistic(*samples), dtype=float).reshape(size))
    runs = min(a.shape[0] for a in arrays)
    low, high = np.percentile(np.concatenate(estimates), percentile_levels(confidence, runs=runs, expanded=expanded))
    return Interval(
        estimate=float(statistic(*arrays)),
        low=float(low),
        high=float(high),
        confidence=confidence,
        covers=RUNS_AND_CONDITIONS if conditions else RUNS,
    )


def per_condition_bootstrap(
    scores: Sequence[np.ndarray],
    statistic: Callable[..., Any],
    *,
    resamples: int = DEFAULT_RESAMPLES,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
) -> Interval:
    """The interval the reports printed before issue 39 (rliable's stratified bootstrap): each condition's runs drawn
    with replacement from that condition alone, plain percentiles. Kept to measure its coverage
    (``tests/test_coverage.py``): with a run effect shared by every condition it is far too narrow."""
    arrays = _checked(scores, confidence)
    rng = np.random.default_rng(seed)
    samples = []
    for array in arrays:
        runs, count = array.shape
        samples.append(array[rng.integers(0, runs, size=(resamples, runs, count)), np.arange(count)])
    estimates = np.asarray(statistic(*samples), dtype=float).reshape(resamples)
    low, high = np.percentile(estimates, percentile_levels(confidence, runs=2, expanded=False))
    return Interval(estimate=float(statistic(*arrays)), low=float(low), high=float(high), confidence=confidence)


def _checked(scores: Sequence[np.ndarray], confidence: float) -> list[np.ndarray]:
    arrays = [as_scores(array) for array in scores]
    if any(array.shape[0] < 2 for array in arrays):
        raise StatisticsError(ONE_RUN)
    if not 0.0 < confidence < 1.0:
        raise StatisticsError(f"confidence must be between 0 and 1, got {confidence}")
    if len({array.shape[1] for array in arrays}) > 1:
        raise StatisticsError(f"the brains met different numbers of conditions ({[a.shape[1] for a in arrays]})")
    return arrays


def percentile_levels(confidence: float, *, runs: int, expanded: bool = True) -> tuple[float, float]:
    """The two percentile levels (0-100) of a bootstrap interval at ``confidence``: plain (2.5, 97.5 at 95 %), or
    expanded for ``runs`` so that the normal quantile z becomes sqrt(n / (n - 1)) * t(1 - alpha / 2, n - 1)."""
    tail = (1.0 - confidence) / 2.0
    if expanded and runs >= 2:
        widened = math.sqrt(runs / (runs - 1)) * t_quantile(1.0 - tail, degrees=runs - 1)
        tail = NormalDist().cdf(-widened)
    return 100.0 * tail, 100.0 * (1.0 - tail)


def t_quantile(probability: float, *, degrees: int) -> float:
    """The ``probability`` quantile (above 0.5) of Student's t with ``degrees`` degrees of freedom: bisection on
    its CDF, the density integrated numerically (numpy only; scipy is an optional extra here)."""
    scale = math.exp(math.lgamma((degrees + 1) / 2) - math.lgamma(degrees / 2)) / math.sqrt(degrees * math.pi)

    def cdf(t: float) -> float:
        grid = np.linspace(0.0, t, 4001)
        density = scale * (1.0 + grid**2 / degrees) ** (-(degrees + 1) / 2)
        return 0.5 + float(np.sum((density[1:] + density[:-1]) * np.diff(grid)) / 2.0)

    low, high = 0.0, 1.0
    while cdf(high) < probability:
        low, high = high, high * 2.0
    for _ in range(60):
        middle = (low + high) / 2.0
        low, high = (middle, high) if cdf(middle) < probability else (low, middle)
    return (low + high) / 2.0


def clopper_pearson(successes: int, trials: int, *, confidence: float = DEFAULT_CONFIDENCE) -> tuple[float, float]:
    """The exact (Clopper-Pearson) interval of a binomial probability after ``successes`` of ``trials``: never of
    zero width, and 0 or 1 at an end only where the count is 0 or all."""
    if not 0 <= successes <= trials or trials < 1:
        raise StatisticsError(f"{successes} successes of {trials} trials is not a binomial count")
    tail = (1.0 - confidence) / 2.0
    # The upper bound of k of n is one minus the lower bound of the n - k failures.
    lower = 0.0 if successes == 0 else _lower_bound(successes, trials, tail)
    upper = 1.0 if successes == trials else 1.0 - _lower_bound(trials - successes, trials, tail)
    return lower, upper


def _lower_bound(successes: int, trials: int, tail: float) -> float:
    """The p at which P(X >= successes | p) = tail (it rises with p): bisection."""

    def at_least(p: float) -> float:
        return sum(math.comb(trials, k) * p**k * (1.0 - p) ** (trials - k) for k in range(successes, trials + 1))

    low, high = 0.0, 1.0
    for _ in range(60):
        middle = (low + high) / 2.0
        low, high = (middle, high) if at_least(middle) < tail else (low, middle)
    return (low + high) / 2.0


def profile_bands(
    scores: np.ndarray,
    taus: np.ndarray,
    *,
    resamples: int = DEFAULT_RESAMPLES,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A performance profile and its pointwise confidence band over training runs (whole runs resampled, as in
    :func:`run_bootstrap`): (profile, low, high), each one value per tau."""
    array = as_scores(scores)
    if array.shape[0] < 2:
        raise StatisticsError(ONE_RUN)
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, array.shape[0], size=(resamples, array.shape[0]))
    # Every run has the same conditions, so a resample's profile is the mean of its drawn runs' own profiles: one
    # (runs, taus) table, not a (resamples, runs x conditions, taus) comparison (1e9 values at 1,000 conditions).
    per_run = performance_profile(array[:, None, :], taus)
    curves = per_run[rows].mean(axis=1)
    low, high = np.percentile(curves, percentile_levels(confidence, runs=array.shape[0]), axis=0)
    return performance_profile(array, taus), low, high
