"""The statistics of brain comparisons on synthetic data whose answers are known (issues 28 and 39)."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.report.statistics import (
    ONE_RUN,
    RUNS,
    RUNS_AND_CONDITIONS,
    Interval,
    StatisticsError,
    clopper_pearson,
    difference,
    iqm,
    mean,
    percentile_levels,
    performance_profile,
    probability_of_improvement,
    profile_bands,
    run_bootstrap,
    t_quantile,
)


def test_iqm_is_the_mean_of_the_middle_half_computed_by_hand():
    scores = np.array([[8.0, 1.0, 3.0, 100.0], [2.0, 7.0, 5.0, 6.0]])  # sorted: 1 2 3 5 6 7 8 100
    assert iqm(scores) == pytest.approx((3.0 + 5.0 + 6.0 + 7.0) / 4)
    # 10 scores: int(2.5) = 2 cut from each side, the middle six averaged.
    ten = np.arange(10.0).reshape(2, 5)
    assert iqm(ten) == pytest.approx(np.mean([2, 3, 4, 5, 6, 7]))


def test_a_brain_against_itself_has_probability_of_improvement_one_half():
    rng = np.random.default_rng(3)
    scores = rng.random((5, 12))
    assert probability_of_improvement(scores, scores) == 0.5
    ties = np.ones((4, 3))
    assert probability_of_improvement(ties, ties) == 0.5


def test_a_brain_better_on_every_condition_has_probability_one():
    rng = np.random.default_rng(4)
    worse = rng.random((5, 8))
    better = worse.max(axis=0) + 0.1 + rng.random((5, 8))  # above every run of the other, condition by condition
    assert probability_of_improvement(better, worse) == 1.0
    assert probability_of_improvement(worse, better) == 0.0
    interval = run_bootstrap([better, worse], probability_of_improvement, resamples=300)
    assert interval.low == interval.high == interval.estimate == 1.0 and not interval.has_width


def test_probability_of_improvement_counts_pairs_of_runs_per_condition():
    x = np.array([[1.0, 0.0], [0.0, 0.0]])  # condition 0: runs 1, 0; condition 1: 0, 0
    y = np.array([[0.5, 0.0], [0.5, 1.0]])  # condition 0: 0.5, 0.5; condition 1: 0, 1
    # condition 0: (1 > 0.5) twice, (0 < 0.5) twice -> 0.5; condition 1: ties 0-0 twice (1.0), losses twice -> 0.25
    assert probability_of_improvement(x, y) == pytest.approx((0.5 + 0.25) / 2)


def test_one_draw_of_runs_is_applied_to_every_condition():
    """Two runs, one that laps everything and one that laps nothing: a resample of whole runs can only give a
    success rate of 0, 0.5 or 1 (never a mix of one run's conditions with the other's), so with 2 runs the interval
    reaches both ends."""
    scores = np.array([[1.0] * 30, [0.0] * 30])
    interval = run_bootstrap([scores], mean, resamples=500, expanded=False)
    assert (interval.low, interval.estimate, interval.high) == (0.0, 0.5, 1.0)
    assert interval.covers == RUNS
    assert run_bootstrap([scores], mean, conditions=True, resamples=50).covers == RUNS_AND_CONDITIONS


def test_the_two_level_interval_is_wider_when_conditions_differ():
    rng = np.random.default_rng(5)
    scores = np.linspace(0.0, 1.0, 20) + rng.normal(0.0, 0.05, (6, 20))  # conditions differ, runs barely do
    runs = run_bootstrap([scores], mean)
    both = run_bootstrap([scores], mean, conditions=True)
    assert both.high - both.low > 3 * (runs.high - runs.low)


def test_a_paired_difference_resamples_each_brains_runs():
    rng = np.random.default_rng(6)
    x = rng.random((8, 25))
    interval = run_bootstrap([x + 0.2, x], difference(mean))
    assert interval.estimate == pytest.approx(0.2)
    assert interval.low < 0.2 < interval.high  # the two brains' runs are drawn independently: a spread remains


def test_expanded_levels_widen_for_few_runs_and_t_quantiles_are_right():
    assert t_quantile(0.975, degrees=4) == pytest.approx(2.7764, abs=1e-3)
    assert t_quantile(0.975, degrees=9) == pytest.approx(2.2622, abs=1e-3)
    assert percentile_levels(0.95, runs=5, expanded=False) == pytest.approx((2.5, 97.5))
    low5, _ = percentile_levels(0.95, runs=5)
    low10, _ = percentile_levels(0.95, runs=10)
    low100, _ = percentile_levels(0.95, runs=100)
    assert low5 < low10 < low100 < 2.5 and low100 > 2.0


def test_clopper_pearson_is_exact_and_never_of_zero_width():
    assert clopper_pearson(5, 5) == pytest.approx((0.025 ** (1 / 5), 1.0), abs=1e-9)
    assert clopper_pearson(0, 25) == pytest.approx((0.0, 1 - 0.025 ** (1 / 25)), abs=1e-9)
    assert clopper_pearson(3, 10) == pytest.approx((0.0667, 0.6525), abs=1e-4)  # the textbook values
    with pytest.raises(StatisticsError, match="binomial"):
        clopper_pearson(4, 3)


def test_an_interval_of_zero_width_is_never_printed_as_one():
    assert str(Interval(estimate=1.0, low=1.0, high=1.0)) == (
        "1.00 (every resample alike: no spread between runs, no interval)"
    )
    assert str(Interval(estimate=0.5, low=0.25, high=0.75)) == "0.50 [0.25, 0.75]"


def test_one_run_gives_no_interval_and_says_so():
    with pytest.raises(StatisticsError, match=ONE_RUN):
        run_bootstrap([np.ones((1, 4))], mean)
    with pytest.raises(StatisticsError, match=ONE_RUN):
        profile_bands(np.ones((1, 4)), np.linspace(0, 1, 5))


def test_bad_scores_are_one_line_errors():
    with pytest.raises(StatisticsError, match="runs x conditions"):
        run_bootstrap([np.ones(4)], mean)
    with pytest.raises(StatisticsError, match="not a finite number"):
        run_bootstrap([np.array([[1.0, np.nan], [0.0, 1.0]])], mean)
    with pytest.raises(StatisticsError, match="different numbers of conditions"):
        probability_of_improvement(np.ones((2, 3)), np.ones((2, 4)))
    with pytest.raises(StatisticsError, match="different numbers of conditions"):
        run_bootstrap([np.ones((2, 3)), np.ones((2, 4))], difference(mean))


def test_performance_profile_and_its_band():
    scores = np.array([[0.0, 0.5, 1.0, 1.0], [0.25, 0.5, 0.75, 1.0]])
    taus = np.array([0.0, 0.5, 0.99])
    assert performance_profile(scores, taus).tolist() == [7 / 8, 4 / 8, 3 / 8]
    profile, low, high = profile_bands(scores, taus, resamples=200)
    assert profile.tolist() == [7 / 8, 4 / 8, 3 / 8]
    assert np.all(low <= profile) and np.all(profile <= high)


def test_the_profile_band_equals_the_profiles_of_the_resamples_themselves():
    """profile_bands computes each resample's curve from the runs' own profiles; the same curves drawn the long way
    (every resampled run x condition score against every tau) give the same band."""
    scores = np.random.default_rng(5).random((5, 40))
    taus = np.linspace(0.0, 1.0, 11)
    rows = np.random.default_rng(9).integers(0, 5, size=(300, 5))
    direct = performance_profile(scores[rows], taus)
    levels = percentile_levels(0.95, runs=5)
    _, low, high = profile_bands(scores, taus, resamples=300, seed=9)
    assert np.allclose(low, np.percentile(direct, levels, axis=0)[0])
    assert np.allclose(high, np.percentile(direct, levels, axis=0)[1])


def test_aggregates_take_stacks_of_resamples():
    stack = np.random.default_rng(2).random((7, 4, 9))
    assert np.allclose(mean(stack), [mean(s) for s in stack])
    assert np.allclose(iqm(stack), [iqm(s) for s in stack])
    other = stack[::-1]
    assert np.allclose(
        probability_of_improvement(stack, other), [probability_of_improvement(a, b) for a, b in zip(stack, other)]
    )


def test_the_interval_is_the_same_for_the_same_seed():
    scores = np.random.default_rng(1).random((5, 6))
    assert run_bootstrap([scores], iqm, seed=7) == run_bootstrap([scores], iqm, seed=7)
