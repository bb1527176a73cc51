"""Aggregate statistics of normalized scores, as the field reports them (Agarwal et al., 2021, "Deep RL at the
edge of the statistical precipice"; the ``rliable`` package): interquartile mean (IQM) and mean, with
stratified-bootstrap confidence intervals, and performance profiles.

Scores are a ``[runs, tasks]`` array, one normalized score per run (seed) and task. The definitions follow
``rliable``'s: the IQM is the mean of the middle 50 % of all runs × tasks (``scipy.stats.trim_mean(x, 0.25)``:
``floor(n / 4)`` scores cut from each end); the stratified bootstrap resamples runs with replacement
within each task, so every resample keeps each task's weight; intervals are percentile intervals; a
performance profile is the fraction of runs × tasks scoring above each threshold τ.

One method on one task, over a handful of seeds, gets a Student-t interval instead (:func:`t_interval`): with
three seeds a bootstrap can only draw among ten distinct resamples, and its percentile interval stays inside
the seeds' range, understating how little three seeds pin down.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["interval_cell", "iqm", "mean", "performance_profile", "stratified_bootstrap_ci", "t_interval", "t_quantile"]


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


def _t_central_probability(t: float, df: int) -> float:
    """P(−t < T < t) for Student's t with an integer ``df``, in closed form (Abramowitz & Stegun 26.7.3-4)."""
    theta = math.atan(t / math.sqrt(df))
    cos2 = math.cos(theta) ** 2
    if df % 2:  # odd: (2/π)(θ + sinθ (cosθ + 2/3 cos³θ + … + (2·4···(df−3))/(1·3···(df−2)) cos^(df−2)θ))
        if df == 1:
            return 2 * theta / math.pi
        term = total = math.cos(theta)
        for k in range(1, (df - 1) // 2):
            term *= 2 * k / (2 * k + 1) * cos2
            total += term
        return 2 / math.pi * (theta + math.sin(theta) * total)
    term = total = 1.0  # even: sinθ (1 + 1/2 cos²θ + … + (1·3···(df−3))/(2·4···(df−2)) cos^(df−2)θ)
    for k in range(1, df // 2):
        term *= (2 * k - 1) / (2 * k) * cos2
        total += term
    return math.sin(theta) * total


def t_quantile(probability: float, df: int) -> float:
    """The ``probability`` quantile (above 0.5) of Student's t with an integer ``df`` ≥ 1, by bisection on its
    closed-form distribution function (no scipy)."""
    if not 0.5 < probability < 1 or df < 1 or int(df) != df:
        raise ValueError(f"need 0.5 < probability < 1 and an integer df >= 1, got {probability}, {df}")
    central = 2 * probability - 1
    low, high = 0.0, 1.0
    while _t_central_probability(high, df) < central:
        low, high = high, 2 * high
    for _ in range(200):
        middle = (low + high) / 2
        low, high = (middle, high) if _t_central_probability(middle, df) < central else (low, middle)
    return (low + high) / 2


def t_interval(values: Sequence[float], confidence: float = 0.95) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean of ``values`` (one score per seed) and its Student-t interval, mean ±
    t(1 − (1 − confidence)/2, n − 1) · s / √n with s the sample standard deviation; low and high are NaN for
    fewer than two values, which give no spread to measure."""
    scores = np.asarray(values, dtype=np.float64)
    if scores.ndim != 1 or scores.size == 0 or not np.isfinite(scores).all():
        raise ValueError(f"values must be a non-empty 1-d array of finite scores, got {values!r}")
    centre = float(scores.mean())
    if scores.size < 2:
        return centre, math.nan, math.nan
    half = t_quantile(1 - (1 - confidence) / 2, scores.size - 1) * float(scores.std(ddof=1)) / math.sqrt(scores.size)
    return centre, centre - half, centre + half


def interval_cell(values: Sequence[float], note: str = "") -> str:
    """A markdown table cell: the mean in bold, its 95 % t-interval (:func:`t_interval`) and n, with ``note``
    after n; the value and n=1 for one value; "no runs" for none."""
    if not len(values):
        return "no runs"
    centre, low, high = t_interval(values)
    extra = f"; {note}" if note else ""
    if len(values) == 1:
        return f"**{centre:.1f}** (n=1{extra})"
    return f"**{centre:.1f}** [{low:.1f}, {high:.1f}] (n={len(values)}{extra})"
