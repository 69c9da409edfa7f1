"""Statistics over seeds that researchers trust (Agarwal et al. 2021, "Deep RL at the Edge
of the Statistical Precipice"): the mean and the interquartile mean (IQM) of per-seed
scores, the probability of improvement and the difference of two methods' means, each
with a bootstrap 95% confidence interval.

The bootstrap is scipy's (:func:`scipy.stats.bootstrap`: BCa, 10,000 resamples, a fixed
generator so that a report is reproducible; percentile intervals where BCa is degenerate,
e.g. with ties). Per task the seeds are one stratum, so the stratified bootstrap of
rliable reduces to resampling seeds; the probability of improvement and the mean difference
resample the two methods' seeds independently.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

__all__ = [
    "N_RESAMPLES",
    "Estimate",
    "average_probability_of_improvement_ci",
    "bootstrap_ci",
    "common_seeds",
    "iqm",
    "mean_ci",
    "mean_difference",
    "mean_difference_ci",
    "probability_of_improvement",
    "probability_of_improvement_ci",
    "stratified_iqm_ci",
]

N_RESAMPLES = 10_000
"""Bootstrap resamples of every interval."""


@dataclass(frozen=True)
class Estimate:
    """A point estimate and the two ends of its confidence interval."""

    value: float
    low: float
    high: float

    def as_dict(self) -> dict[str, float]:
        """``{"value", "low", "high"}``."""
        return {"value": self.value, "low": self.low, "high": self.high}

    def __str__(self) -> str:
        return f"{self.value:.1f} [{self.low:.1f}, {self.high:.1f}]"


def mean_ci(values: Sequence[float], level: float = 0.95) -> tuple[float, float, float]:
    """Mean and the two ends of its Student-t confidence interval (NaN ends for n < 2)."""
    arr = np.asarray(values, dtype=np.float64)
    n = arr.size
    if n == 0:
        return math.nan, math.nan, math.nan
    mean = float(arr.mean())
    if n < 2:
        return mean, math.nan, math.nan
    half = float(stats.t.ppf(0.5 + level / 2, n - 1) * arr.std(ddof=1) / math.sqrt(n))
    return mean, mean - half, mean + half


def iqm(x: Any, axis: int = -1) -> Any:
    """Interquartile mean: the mean of the middle 50% (``scipy.stats.trim_mean``, 25% a side)."""
    return stats.trim_mean(x, 0.25, axis=axis)


def _bootstrap(
    data: tuple[np.ndarray, ...], statistic: Callable[..., Any], level: float, seed: int
) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    kw = {"n_resamples": N_RESAMPLES, "confidence_level": level, "vectorized": True}
    try:
        with warnings.catch_warnings():  # a degenerate BCa is handled below
            warnings.simplefilter("ignore")
            res = stats.bootstrap(data, statistic, method="BCa", rng=rng, **kw)
        lo, hi = res.confidence_interval
    except Exception:  # BCa needs a non-degenerate jackknife
        lo = hi = float("nan")
    if not (np.isfinite(lo) and np.isfinite(hi)):
        rng = np.random.default_rng(seed)
        res = stats.bootstrap(data, statistic, method="percentile", rng=rng, **kw)
        lo, hi = res.confidence_interval
    return float(lo), float(hi)


def bootstrap_ci(
    values: Sequence[float],
    statistic: Callable[..., Any] = np.mean,
    level: float = 0.95,
    seed: int = 0,
) -> Estimate:
    """``statistic(values)`` and its bootstrap confidence interval over the values (seeds).

    ``statistic`` must take an ``axis`` keyword (``np.mean``, :func:`iqm`). With fewer
    than two values, or all values equal, the interval is the point itself.
    """
    data = np.asarray(values, dtype=np.float64)
    if data.ndim != 1 or data.size == 0:
        raise ValueError(f"values must be a non-empty 1-D sequence; got shape {data.shape}")
    point = float(statistic(data, axis=-1))
    if data.size < 2 or np.all(data == data[0]):
        return Estimate(point, point, point)
    lo, hi = _bootstrap((data,), statistic, level, seed)
    return Estimate(point, lo, hi)


def probability_of_improvement(x: Any, y: Any, axis: int = -1) -> Any:
    """P(X > Y) + P(X = Y) / 2 for a random seed of X against a random seed of Y.

    The Mann-Whitney U statistic over the number of pairs: 1 when every score of ``x``
    beats every score of ``y``, 0.5 when neither method is ahead. Vectorised over leading
    axes (for the bootstrap); ``axis`` must be the last.
    """
    if axis not in (-1, np.ndim(x) - 1):
        raise ValueError(f"axis must be the last axis; got {axis}")
    a = np.asarray(x, dtype=np.float64)[..., :, None]
    b = np.asarray(y, dtype=np.float64)[..., None, :]
    wins = np.count_nonzero(a > b, axis=(-1, -2))  # counted as ints: no float copy of every
    ties = np.count_nonzero(a == b, axis=(-1, -2))  # pair, and the same exact sum as before
    return (wins + 0.5 * ties) / (a.shape[-2] * b.shape[-1])


def probability_of_improvement_ci(
    x: Sequence[float], y: Sequence[float], level: float = 0.95, seed: int = 0
) -> Estimate:
    """:func:`probability_of_improvement` with a bootstrap CI (seeds of ``x`` and ``y``
    resampled independently)."""
    a, b = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if a.ndim != 1 or b.ndim != 1 or a.size == 0 or b.size == 0:
        raise ValueError("x and y must be non-empty 1-D sequences of scores")
    point = float(probability_of_improvement(a, b))
    if a.size < 2 or b.size < 2 or np.all(np.concatenate([a, b]) == a[0]):
        return Estimate(point, point, point)
    lo, hi = _bootstrap((a, b), probability_of_improvement, level, seed)
    return Estimate(point, lo, hi)


def mean_difference(x: Any, y: Any, axis: int = -1) -> Any:
    """mean(x) - mean(y) along ``axis`` (vectorised over leading axes, for the bootstrap)."""
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


def mean_difference_ci(
    x: Sequence[float], y: Sequence[float], level: float = 0.95, seed: int = 0
) -> Estimate:
    """:func:`mean_difference` of two samples with a bootstrap CI (the seeds of ``x`` and of
    ``y`` resampled independently, as for :func:`probability_of_improvement_ci`). With fewer
    than two values in either sample, or each sample constant, the interval is the point."""
    a, b = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if a.ndim != 1 or b.ndim != 1 or a.size == 0 or b.size == 0:
        raise ValueError("x and y must be non-empty 1-D sequences of values")
    point = float(mean_difference(a, b))
    if a.size < 2 or b.size < 2 or (np.all(a == a[0]) and np.all(b == b[0])):
        return Estimate(point, point, point)
    lo, hi = _bootstrap((a, b), mean_difference, level, seed)
    return Estimate(point, lo, hi)


def average_probability_of_improvement_ci(
    pairs: Sequence[tuple[Sequence[float], Sequence[float]]], level: float = 0.95, seed: int = 0
) -> Estimate:
    """The mean over tasks of :func:`probability_of_improvement`, with a bootstrap CI.

    ``pairs`` holds one ``(x, y)`` per task (scores of X and of Y on that task); every
    task weighs the same whatever its number of seeds (Agarwal et al. 2021's average
    probability of improvement). The seeds of every sample are resampled independently.
    """
    samples = [np.asarray(v, dtype=np.float64) for pair in pairs for v in pair]
    if not pairs or any(v.ndim != 1 or v.size == 0 for v in samples):
        raise ValueError("pairs must hold one (x, y) pair of non-empty 1-D score sequences")

    def average(*data: Any, axis: int = -1) -> Any:
        per_task = [
            probability_of_improvement(data[i], data[i + 1], axis=axis)
            for i in range(0, len(data), 2)
        ]
        return np.mean(per_task, axis=0)

    point = float(average(*samples))
    if any(v.size < 2 for v in samples) or np.all(np.concatenate(samples) == samples[0][0]):
        return Estimate(point, point, point)
    lo, hi = _bootstrap(tuple(samples), average, level, seed)
    return Estimate(point, lo, hi)


def stratified_iqm_ci(
    strata: Sequence[Sequence[float]], level: float = 0.95, seed: int = 0
) -> Estimate:
    """The :func:`iqm` of the values of every stratum pooled, with a stratified bootstrap CI.

    ``strata`` holds one sample per task (a method's per-seed normalised scores on it); a
    resample draws each task's seeds with replacement from that task alone, so that every
    resample keeps each task's number of runs (Agarwal et al. 2021's stratified bootstrap).
    With fewer than two values in every stratum, or all values equal, the CI is the point.
    """
    samples = [np.asarray(v, dtype=np.float64) for v in strata]
    if not samples or any(v.ndim != 1 or v.size == 0 for v in samples):
        raise ValueError("strata must hold non-empty 1-D sequences of values")

    def pooled_iqm(*data: Any, axis: int = -1) -> Any:
        """The IQM over the last axis of the strata side by side (leading axes broadcast:
        scipy's resamples and jackknife)."""
        lead = np.broadcast_shapes(*(np.shape(d)[:-1] for d in data))
        pooled = [np.broadcast_to(d, (*lead, np.shape(d)[-1])) for d in data]
        return iqm(np.concatenate(pooled, axis=-1), axis=-1)

    point = float(pooled_iqm(*samples))
    flat = np.concatenate(samples)
    if all(v.size < 2 for v in samples) or np.all(flat == flat[0]):
        return Estimate(point, point, point)
    lo, hi = _bootstrap(tuple(samples), pooled_iqm, level, seed)
    return Estimate(point, lo, hi)


def common_seeds(
    x: Mapping[int, float], y: Mapping[int, float]
) -> tuple[dict[int, float], dict[int, float], int]:
    """``x`` and ``y`` (values by seed) restricted to the seeds both have, so that two
    methods are compared on the same seeds while a grid runs or after a run failed, and how
    many seeds of either were left out."""
    both = set(x) & set(y)
    a = {s: v for s, v in x.items() if s in both}
    b = {s: v for s, v in y.items() if s in both}
    return a, b, len(x) + len(y) - 2 * len(both)
