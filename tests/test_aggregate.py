"""The aggregate statistics of torchrl_tels.stats against hand computations."""
from __future__ import annotations

import numpy as np
import pytest

from torchrl_tels.stats import (interval_cell, iqm, mean, performance_profile, stratified_bootstrap_ci, t_interval,
                                t_quantile)


def test_iqm_cuts_a_quarter_from_each_end():
    scores = np.array([[1.0, 100.0], [2.0, 3.0], [4.0, -50.0], [5.0, 6.0]])  # 8 scores: cut 2 each end
    # sorted: -50, 1, 2, 3, 4, 5, 6, 100 -> middle four 2, 3, 4, 5
    assert iqm(scores) == pytest.approx(3.5)
    assert mean(scores) == pytest.approx(71.0 / 8)
    # 6 scores: floor(1.5) = 1 cut from each end, as scipy.stats.trim_mean(x, 0.25)
    assert iqm(np.array([[0.0, 10.0, 1.0], [2.0, 3.0, 4.0]])) == pytest.approx((1 + 2 + 3 + 4) / 4)


def test_bootstrap_keeps_each_task_whole():
    # Task A scores 0 in every run, task B 10: a stratified resample always holds both halves, so the
    # mean's interval is the single point 5; an unstratified one would wander.
    scores = np.array([[0.0, 10.0]] * 5)
    point, low, high = stratified_bootstrap_ci(scores, mean, reps=500)
    assert point == low == high == 5.0


def test_bootstrap_interval_brackets_the_point_and_is_reproducible():
    rng = np.random.default_rng(1)
    scores = rng.normal(50, 10, size=(5, 4))
    first = stratified_bootstrap_ci(scores, iqm, reps=400, seed=3)
    assert first == stratified_bootstrap_ci(scores, iqm, reps=400, seed=3)
    point, low, high = first
    assert low < point < high
    # with one run per task there is nothing to resample: the interval collapses
    single = scores[:1]
    assert stratified_bootstrap_ci(single, mean, reps=50)[1:] == (mean(single), mean(single))


def test_performance_profile_counts_scores_above_tau():
    scores = np.array([[10.0, 50.0], [30.0, 70.0]])
    np.testing.assert_allclose(performance_profile(scores, [0, 10, 40, 70]), [1.0, 0.75, 0.5, 0.0])


def test_bad_scores_are_refused():
    with pytest.raises(ValueError, match=r"\[runs, tasks\] array"):
        iqm([1.0, 2.0])
    with pytest.raises(ValueError, match="NaN or inf"):
        mean([[1.0, float("nan")]])


@pytest.mark.parametrize("df, quantile", [(1, 12.7062), (2, 4.3027), (3, 3.1824), (4, 2.7764), (9, 2.2622),
                                          (30, 2.0423)])
def test_t_quantile_matches_the_printed_tables(df, quantile):
    assert t_quantile(0.975, df) == pytest.approx(quantile, abs=1e-4)


def test_t_quantile_approaches_the_normal_and_refuses_what_it_cannot_compute():
    assert t_quantile(0.975, 400) == pytest.approx(1.9659, abs=1e-4)
    assert t_quantile(0.95, 1) == pytest.approx(6.3138, abs=1e-4)
    for probability, df in ((0.5, 3), (1.0, 3), (0.975, 0), (0.975, 2.5)):
        with pytest.raises(ValueError):
            t_quantile(probability, df)


def test_t_interval_is_the_mean_plus_minus_t_times_the_standard_error():
    centre, low, high = t_interval([40.0, 44.0, 48.0])  # mean 44, sample std 4, n 3
    half = 4.3027 * 4.0 / np.sqrt(3)
    assert centre == 44.0 and low == pytest.approx(44.0 - half, abs=1e-3) and high == pytest.approx(44.0 + half, abs=1e-3)
    single = t_interval([7.0])
    assert single[0] == 7.0 and np.isnan(single[1]) and np.isnan(single[2])


def test_interval_cell_prints_the_scipy_interval_and_n():
    from scipy import stats as scipy_stats

    values = [10.0, 14.0, 21.0]
    low, high = scipy_stats.t.interval(0.95, df=2, loc=np.mean(values), scale=scipy_stats.sem(values))
    assert interval_cell(values) == f"**15.0** [{low:.1f}, {high:.1f}] (n=3)"
    assert interval_cell(values, "success 0.50") == f"**15.0** [{low:.1f}, {high:.1f}] (n=3; success 0.50)"
    assert interval_cell([7.25]) == "**7.2** (n=1)"
    assert interval_cell([]) == "no runs"
