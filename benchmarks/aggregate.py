"""Aggregate scores over tasks × seeds as the field reports them (Agarwal et al., 2021, "Deep RL at the
edge of the statistical precipice"; the ``rliable`` package): interquartile mean (IQM) and mean, with
stratified-bootstrap confidence intervals, and performance profiles.

Scores are a ``[runs, tasks]`` array, one normalized score per run (seed) and task. The definitions follow
``rliable``'s: the IQM is the mean of the middle 50 % of all runs × tasks (``scipy.stats.trim_mean(x, 0.25)``:
``floor(n / 4)`` scores cut from each end); the stratified bootstrap resamples runs with replacement
within each task, so every resample keeps each task's weight; intervals are percentile intervals; a
performance profile is the fraction of runs × tasks scoring above each threshold τ.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["iqm", "mean", "stratified_bootstrap_ci", "performance_profile"]


def _scores(scores) -> np.ndarray:
    array = np.asarray(scores, dtype=np.float64)
    if array.ndim != 2 or array.size == 0:
        raise ValueError(f"scores must be a non-empty [runs, tasks] array, got shape {array.shape}.")
    if not np.isfinite(array).all():
        raise ValueError("scores hold NaN or inf.")
    return array


def iqm(scores) -> float:
    """Interquartile mean of all runs × tasks: ``floor(n/4)`` scores cut from each end, the rest averaged."""
    flat = np.sort(_scores(scores).reshape(-1))
    cut = int(0.25 * flat.size)
    return float(flat[cut: flat.size - cut].mean())


def mean(scores) -> float:
    return float(_scores(scores).mean())


def stratified_bootstrap_ci(scores, statistic: Callable[[np.ndarray], float], *, reps: int = 2000,
                            confidence: float = 0.95, seed: int = 0) -> tuple[float, float, float]:
    """``(point, low, high)``: the statistic and its percentile interval over ``reps`` resamples that draw
    each task's runs with replacement from that task's own runs."""
    array = _scores(scores)
    runs, tasks = array.shape
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, runs, size=(reps, runs, tasks))
    resampled = np.take_along_axis(array[None], rows, axis=1)  # [reps, runs, tasks], column t from task t
    values = np.array([statistic(sample) for sample in resampled])
    tail = (1.0 - confidence) / 2 * 100
    low, high = np.percentile(values, [tail, 100 - tail])
    return statistic(array), float(low), float(high)


def performance_profile(scores, taus) -> np.ndarray:
    """Fraction of runs × tasks with a score above each τ."""
    flat = _scores(scores).reshape(-1)
    return np.array([(flat > tau).mean() for tau in np.asarray(taus, dtype=np.float64)])
