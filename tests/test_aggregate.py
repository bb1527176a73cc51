"""The aggregate statistics of benchmarks/aggregate.py against hand computations."""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.aggregate import iqm, mean, performance_profile, stratified_bootstrap_ci


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
