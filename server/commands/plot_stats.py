"""Statistics of learning curves over seeds: the mean, median or interquartile mean (IQM) of
the seeds at each point, and a 95% percentile-bootstrap confidence interval around it.

Why the percentile bootstrap and not a Student-t interval: our benchmarks have 2–5 seeds, and
with so few the t quantile (12.7 for 2 seeds, 2.78 for 5) stretches the band past every seed
and past what the metric can be (a success rate above 1, a CartPole return above 500). Every
bootstrap resample's mean, median or IQM lies between the smallest and the largest seed, so
the percentile interval never leaves the data's range. Its known cost: with few seeds it is
too narrow (for the mean of 5 normal samples it covers ≈ 85%, of 20 ≈ 93%), so the figures
say how many seeds each curve has.

The bootstrap is stratified as in Agarwal et al. (2021, "Deep RL at the edge of the
statistical precipice"): with several tasks (strata), runs are resampled within each task and
the statistic is taken over all of them. The IQM is theirs too: the mean after dropping the
lowest and highest ⌊n/4⌋ scores (``scipy.stats.trim_mean(x, 0.25)``). Their library, rliable
1.2.0, installs with our pins but fails on import (arch 7.2 calls a pandas 3 helper with an
old signature) and brings ~500 MB of scipy, pandas, statsmodels, seaborn and arch for what is
a few lines of numpy here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATS = ("mean", "median", "iqm")
STAT_NAMES = {"mean": "mean", "median": "median", "iqm": "IQM"}
LEVEL = 0.95
RESAMPLES = 2000
_CHUNK = 250  # resamples per step: bounds memory for long curves of many runs


def iqm(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Interquartile mean along ``axis``: the mean of what is left after dropping the lowest
    and the highest ⌊n/4⌋ values (all of them for n < 4)."""
    n = values.shape[axis]
    cut = n // 4
    ordered = np.sort(values, axis=axis)
    return np.take(ordered, np.arange(cut, n - cut), axis=axis).mean(axis=axis)


def aggregate(values: np.ndarray, stat: str, axis: int = 0) -> np.ndarray:
    if stat == "mean":
        return np.mean(values, axis=axis)
    if stat == "median":
        return np.median(values, axis=axis)
    if stat == "iqm":
        return iqm(values, axis=axis)
    raise ValueError(f"unknown statistic {stat!r}; one of {', '.join(STATS)}")


def stratified_bootstrap_ci(
    scores: np.ndarray,
    stat: str,
    *,
    level: float = LEVEL,
    resamples: int = RESAMPLES,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Percentile-bootstrap interval of ``stat`` for ``scores`` shaped (runs, tasks, *points):
    each resample draws ``runs`` runs with replacement for every task separately, pools the
    runs × tasks scores and takes ``stat`` over them, independently at every point."""
    scores = np.asarray(scores, dtype=float)
    if scores.ndim < 2:
        raise ValueError("scores must be shaped (runs, tasks, ...)")
    runs, tasks = scores.shape[:2]
    rng = np.random.default_rng(seed)
    estimates = []
    for start in range(0, resamples, _CHUNK):
        count = min(_CHUNK, resamples - start)
        rows = rng.integers(0, runs, size=(count, runs, tasks))
        drawn = scores[rows, np.arange(tasks)]  # (count, runs, tasks, *points)
        pooled = drawn.reshape(count, runs * tasks, *scores.shape[2:])
        estimates.append(aggregate(pooled, stat, axis=1))
    alpha = (1.0 - level) / 2.0
    low, high = np.quantile(np.concatenate(estimates), [alpha, 1.0 - alpha], axis=0)
    return low, high


@dataclass(frozen=True)
class Band:
    """One curve over seeds: the statistic at each x and its confidence interval."""

    x: np.ndarray
    centre: np.ndarray
    low: np.ndarray
    high: np.ndarray
    seeds: int


def band_over_seeds(
    curves: list[tuple[np.ndarray, np.ndarray]], stat: str = "mean", *, seed: int = 0
) -> Band:
    """The seeds' (x, y) curves on a common grid (the first curve's x values inside the range
    every curve covers: never extrapolated), their ``stat`` and its bootstrap interval; one
    seed has no interval (low = high = its curve)."""
    if not curves:
        raise ValueError("no curves")
    start = max(float(x[0]) for x, _ in curves)
    end = min(float(x[-1]) for x, _ in curves)
    first = np.asarray(curves[0][0], dtype=float)
    grid = first[(first >= start) & (first <= end)]
    if grid.size == 0:  # no x of the first curve inside the common range: take its ends
        grid = np.array([start, end]) if end > start else np.array([start])
    values = np.stack([np.interp(grid, x, y) for x, y in curves])  # (seeds, points)
    centre = aggregate(values, stat, axis=0)
    if len(curves) < 2:
        return Band(grid, centre, centre, centre, 1)
    low, high = stratified_bootstrap_ci(values[:, None, :], stat, seed=seed)
    # In exact arithmetic both already lie in the seeds' range; the mean of n equal floats
    # can exceed them by a rounding step, which would put a band past a bound like 500.
    smallest, largest = values.min(axis=0), values.max(axis=0)
    low, high = np.clip(low, smallest, largest), np.clip(high, smallest, largest)
    return Band(grid, centre, low, high, len(curves))


def caption(stat: str, level: float = LEVEL, *, seeds: int = 2) -> str:
    """What a curve and its band are, for the figure's legend title; ``seeds``: the most any
    curve has (one seed: a run's own curve, no band)."""
    if seeds <= 1:
        return "one seed per curve: no band"
    return (
        f"{STAT_NAMES[stat]} over seeds; band: {level:.0%} percentile-bootstrap CI "
        f"({RESAMPLES:,} resamples)"
    )
