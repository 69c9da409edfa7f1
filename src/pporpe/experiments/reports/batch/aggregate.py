"""The aggregate over the tasks of a batch grid, as rliable computes it (Agarwal et al. 2021).

For each of :data:`.batch.results.METRICS`:

* **normalisation per task** (:func:`task_ranges`): a run's value ``x`` on a task becomes
  ``(x - lo) / (hi - lo)``, with ``lo`` and ``hi`` the lowest and highest value of that
  task over every finished run of the grid (all methods, all seeds): 0 is the task's worst
  run, 1 its best. Unlike a random-policy and a reference score it needs no number from
  outside the grid (none is published for every metric here, nor for the small tasks of a
  test grid), and being affine per task it leaves every per-task comparison unchanged; the
  range is fixed from the data, not re-estimated in the bootstrap;
* **IQM** of the normalised values of a method, its runs on every task pooled, with a
  stratified bootstrap CI (:func:`~.stats.stratified_iqm_ci`: seeds resampled within each
  task);
* **P(PPO-RPE > rival) pooled over tasks**: the mean over tasks of the per-task probability
  of improvement, each task weighing the same, with a stratified bootstrap CI
  (:func:`~.stats.average_probability_of_improvement_ci`: each method's seeds resampled
  within each task), and a verdict by the per-task rules (:func:`.verdicts.verdict`).
  Normalisation does not change it (it is a comparison of ranks within a task).
"""

from __future__ import annotations

from dataclasses import dataclass

from ..stats import (
    Estimate,
    average_probability_of_improvement_ci,
    common_seeds,
    stratified_iqm_ci,
)
from ..verdicts import verdict
from .results import METRICS, BatchCell, batch_tasks

__all__ = [
    "Aggregate",
    "AggregateIQM",
    "PooledImprovement",
    "aggregate",
    "normalised",
    "pooled_improvement",
    "task_ranges",
]


@dataclass(frozen=True)
class AggregateIQM:
    """A method's IQM over tasks of one metric's normalised values."""

    metric: str
    method: str
    tasks: int
    """Tasks with at least one finished run of the method."""
    runs: int
    """Runs pooled (over those tasks)."""
    iqm: Estimate
    """IQM of the normalised values, with its stratified bootstrap 95% CI."""


@dataclass(frozen=True)
class PooledImprovement:
    """P(``method`` > rival) of one metric, averaged over tasks."""

    metric: str
    method: str
    rival: str
    tasks: int
    """Tasks where both methods have finished runs (those averaged)."""
    n: tuple[int, int]
    """The fewest seeds of ``method`` and of the rival on any of those tasks."""
    left_out: int
    """Seeds of either method left out over those tasks: each task compares the seeds both
    have finished (:func:`.stats.common_seeds`)."""
    p: Estimate
    """The mean over tasks of P(method > rival), with its stratified bootstrap 95% CI."""

    @property
    def verdict(self) -> str:
        """:func:`.verdicts.verdict` of the CI."""
        return verdict(self.p.low, self.p.high, self.n, self.left_out)


@dataclass(frozen=True)
class Aggregate:
    """The aggregate of a batch grid: per metric, the IQMs and the pooled comparisons."""

    iqms: tuple[AggregateIQM, ...]
    improvements: tuple[PooledImprovement, ...]


def task_ranges(cells: list[BatchCell], metric: str) -> dict[str, tuple[float, float]]:
    """Per task, the lowest and highest finite value of ``metric`` over all its runs."""
    ranges = {}
    for env in batch_tasks(cells):
        vals = [v for c in cells if c.env == env for v in c.values(metric).values()]
        if vals:
            ranges[env] = (min(vals), max(vals))
    return ranges


def normalised(value: float, lo: float, hi: float) -> float:
    """``(value - lo) / (hi - lo)``; 0.5 where every run of the task has the same value."""
    return 0.5 if hi == lo else (value - lo) / (hi - lo)


def _method_iqm(cells: list[BatchCell], metric: str, method: str) -> AggregateIQM | None:
    ranges = task_ranges(cells, metric)
    strata = [
        [normalised(v, *ranges[c.env]) for v in c.values(metric).values()]
        for c in cells
        if c.method == method and c.values(metric)
    ]
    if not strata:
        return None
    runs = sum(len(s) for s in strata)
    return AggregateIQM(metric, method, len(strata), runs, stratified_iqm_ci(strata))


def pooled_improvement(
    cells: list[BatchCell], metric: str, rival: str, of: str = "rpe"
) -> PooledImprovement | None:
    """P(``of`` > ``rival``) of ``metric`` averaged over the tasks where both have finished
    runs (None where there is none)."""
    pairs, left_out = [], 0
    for env in batch_tasks(cells):
        here = {c.method: c.values(metric) for c in cells if c.env == env}
        x, y, dropped = common_seeds(here.get(of, {}), here.get(rival, {}))
        if x and y:
            pairs.append((list(x.values()), list(y.values())))
            left_out += dropped
    if not pairs:
        return None
    n = (min(len(a) for a, _ in pairs), min(len(b) for _, b in pairs))
    est = average_probability_of_improvement_ci(pairs)
    return PooledImprovement(metric, of, rival, len(pairs), n, left_out, est)


def aggregate(cells: list[BatchCell], of: str = "rpe") -> Aggregate:
    """Every metric's IQM per method and P(``of`` > rival) per rival."""
    methods = list(dict.fromkeys(c.method for c in cells))
    iqms = [_method_iqm(cells, m.key, method) for m in METRICS for method in methods]
    pooled = [
        pooled_improvement(cells, m.key, rival, of)
        for m in METRICS
        for rival in methods
        if rival != of
    ]
    return Aggregate(
        tuple(x for x in iqms if x is not None), tuple(p for p in pooled if p is not None)
    )
