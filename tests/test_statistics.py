"""The statistics of brain comparisons on synthetic data whose answers are known (issue 28's definition of done)."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.report.statistics import (
    ONE_RUN,
    StatisticsError,
    iqm,
    mean,
    performance_profile,
    probability_of_improvement,
    profile_bands,
    stratified_bootstrap,
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
    interval = stratified_bootstrap([better, worse], probability_of_improvement, resamples=300)
    assert interval.low == interval.high == interval.estimate == 1.0


def test_probability_of_improvement_counts_pairs_of_runs_per_condition():
    x = np.array([[1.0, 0.0], [0.0, 0.0]])  # condition 0: runs 1, 0; condition 1: 0, 0
    y = np.array([[0.5, 0.0], [0.5, 1.0]])  # condition 0: 0.5, 0.5; condition 1: 0, 1
    # condition 0: (1 > 0.5) twice, (0 < 0.5) twice -> 0.5; condition 1: ties 0-0 twice (1.0), losses twice -> 0.25
    assert probability_of_improvement(x, y) == pytest.approx((0.5 + 0.25) / 2)


@pytest.mark.slow  # over 9 s: out of the quick tier
def test_the_95_percent_interval_covers_the_true_mean_in_93_to_97_percent_of_experiments():
    """1,000 synthetic experiments, each 30 training runs x 10 conditions of a known mean: the stratified bootstrap's
    percentile interval must cover that mean about 95 % of the time: 94.2 % here. (With 5 runs the same experiment
    covers 93.1 %: resampling n runs sees only a (n-1)/n share of their variance, so few seeds give slightly narrow
    intervals.)"""
    rng = np.random.default_rng(2026)
    condition_means = np.linspace(0.2, 0.8, 10)
    true_mean = condition_means.mean()
    experiments, covered = 1000, 0
    for experiment in range(experiments):
        scores = condition_means + rng.normal(0.0, 0.15, size=(30, 10))
        interval = stratified_bootstrap([scores], mean, resamples=1000, seed=experiment)
        covered += interval.low <= true_mean <= interval.high
    assert 0.93 <= covered / experiments <= 0.97, covered


def test_one_run_gives_no_interval_and_says_so():
    with pytest.raises(StatisticsError, match=ONE_RUN):
        stratified_bootstrap([np.ones((1, 4))], mean)
    with pytest.raises(StatisticsError, match=ONE_RUN):
        profile_bands(np.ones((1, 4)), np.linspace(0, 1, 5))


def test_bad_scores_are_one_line_errors():
    with pytest.raises(StatisticsError, match="runs x conditions"):
        stratified_bootstrap([np.ones(4)], mean)
    with pytest.raises(StatisticsError, match="not a finite number"):
        stratified_bootstrap([np.array([[1.0, np.nan], [0.0, 1.0]])], mean)
    with pytest.raises(StatisticsError, match="different numbers of conditions"):
        probability_of_improvement(np.ones((2, 3)), np.ones((2, 4)))


def test_performance_profile_and_its_band():
    scores = np.array([[0.0, 0.5, 1.0, 1.0], [0.25, 0.5, 0.75, 1.0]])
    taus = np.array([0.0, 0.5, 0.99])
    assert performance_profile(scores, taus).tolist() == [7 / 8, 4 / 8, 3 / 8]
    profile, low, high = profile_bands(scores, taus, resamples=200)
    assert profile.tolist() == [7 / 8, 4 / 8, 3 / 8]
    assert np.all(low <= profile) and np.all(profile <= high)


def test_the_interval_is_the_same_for_the_same_seed():
    scores = np.random.default_rng(1).random((5, 6))
    assert stratified_bootstrap([scores], iqm, seed=7) == stratified_bootstrap([scores], iqm, seed=7)
