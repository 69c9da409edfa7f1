"""A grid of batch runs (``kind = "batch"``) read into per-run numbers.

A batch run (:mod:`pporpe.batch`) collects rollouts, then updates on them, so its report
measures it as CleanRL and rliable do, by environment steps rather than by episodes:

* the **test score**: the median return of its deterministic test episodes
  (``evaluation.json``), as for the online grids;
* the **last-100 return**: the mean return of its last :data:`LAST_EPISODES` training
  episodes (CleanRL's metric of its published runs);
* the **mean training return**: the mean over the run's environment steps of the return of
  the episode each step belongs to (each training episode weighted by its length), the
  area under the learning curve over steps divided by the steps: sample efficiency;
* per quarter of training *by steps* (:func:`quarters_by_steps`), from ``updates.csv``:
  the share of samples past the threshold, the mean abs(rho - 1) and the approximate KL of
  the updates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ....run_files import read_grid, read_json
from ....runs.logger import EpisodeRecord, LoggedUpdate, read_updates
from ..results import QUARTERS, Cell, load_results

__all__ = [
    "LAST_EPISODES",
    "METRICS",
    "QUARTER_FIELDS",
    "BatchCell",
    "BatchRun",
    "Metric",
    "QuarterDiagnostics",
    "batch_tasks",
    "is_batch_grid",
    "last_return",
    "load_batch",
    "quarters_by_steps",
    "step_mean_return",
]

LAST_EPISODES = 100
"""Training episodes of the last-episodes return (CleanRL's metric)."""

QUARTER_FIELDS = ("past_threshold", "ratio_dev", "approx_kl")
"""The ``updates.csv`` columns averaged per quarter of training."""


@dataclass(frozen=True)
class Metric:
    """A per-run number that the report compares between methods."""

    key: str
    """The :class:`BatchRun` attribute that holds it."""
    name: str
    """Its name in the tables (the ``claim`` column of the verdicts)."""
    what: str
    """What it is, for the legend."""


METRICS: tuple[Metric, ...] = (
    Metric("score", "test score", "median return of the run's deterministic test episodes"),
    Metric(
        "last100",
        f"last {LAST_EPISODES} episodes",
        f"mean return of the run's last {LAST_EPISODES} training episodes (CleanRL's metric)",
    ),
    Metric(
        "mean_return",
        "mean training return",
        "mean training return over the run's steps (each training episode weighted by its "
        "length: the area under the learning curve over steps, per step; sample efficiency)",
    ),
)
"""The three per-run numbers of a batch report, in the order of its tables."""


@dataclass(frozen=True)
class QuarterDiagnostics:
    """Per quarter of a run's steps, the mean over its updates of each of
    :data:`QUARTER_FIELDS` (NaN for a quarter without a finite value)."""

    past_threshold: tuple[float, ...]
    """Share of the update's samples whose ratio rho was past the threshold (a fraction)."""
    ratio_dev: tuple[float, ...]
    """Mean abs(rho - 1) over the update's samples."""
    approx_kl: tuple[float, ...]
    """The update's approximate KL divergence of the new policy from the old (CleanRL's
    ``(rho - 1) - log rho`` estimator)."""


@dataclass(frozen=True)
class BatchRun:
    """The numbers of one finished batch run."""

    seed: int
    score: float
    """Median return of the run's test episodes (NaN without ``evaluation.json``)."""
    last100: float
    """Mean return of the run's last :data:`LAST_EPISODES` training episodes."""
    mean_return: float
    """Mean training return over the run's steps (:func:`step_mean_return`)."""
    steps: tuple[int, ...]
    """Environment steps taken by the run at the end of each training episode."""
    returns: tuple[float, ...]
    """Return of each training episode."""
    quarters: QuarterDiagnostics
    """Surrogate diagnostics by quarter of the run's steps."""

    def value(self, metric: str) -> float:
        """The run's number ``metric`` (a :data:`METRICS` key)."""
        return float(getattr(self, metric))


@dataclass(frozen=True)
class BatchCell:
    """The finished runs of one (task, method) of a batch grid."""

    env: str
    method: str
    runs: tuple[BatchRun, ...]
    """Finished runs, by seed."""
    missing: tuple[int, ...]
    """Seeds without a finished run."""

    def values(self, metric: str) -> dict[int, float]:
        """The finite values of ``metric`` by seed."""
        return {r.seed: v for r in self.runs if math.isfinite(v := r.value(metric))}


def batch_tasks(cells: list[BatchCell]) -> list[str]:
    """The tasks of ``cells`` in their first order."""
    return list(dict.fromkeys(c.env for c in cells))


def last_return(records: list[EpisodeRecord], episodes: int = LAST_EPISODES) -> float:
    """Mean return of a run's last ``episodes`` training episodes (all of them if it has
    fewer; NaN without any)."""
    rets = [r.ret for r in records[-episodes:]] if episodes > 0 else []
    return float(np.mean(rets)) if rets else math.nan


def step_mean_return(records: list[EpisodeRecord]) -> float:
    """Mean over a run's environment steps of the return of the episode each step belongs
    to: sum(return * length) / sum(length) over its training episodes (NaN without any)."""
    pairs = [(r.ret, r.length) for r in records if r.length > 0]
    if not pairs:
        return math.nan
    return float(sum(g * n for g, n in pairs) / sum(n for _, n in pairs))


def quarters_by_steps(updates: list[LoggedUpdate], field: str) -> tuple[float, ...]:
    """The mean of ``field`` over the updates in each quarter of a run's steps.

    With ``T`` the run's steps at its last update, an update made when the run had taken
    ``s`` steps falls in quarter ``k`` (from 0) where ``k T / 4 < s <= (k + 1) T / 4``;
    every update weighs the same (each learns from one rollout of the same size). NaN for
    a quarter without a finite value of ``field`` (fewer than 4 updates, or a column the
    run did not log).
    """
    bins: list[list[float]] = [[] for _ in range(QUARTERS)]
    total = updates[-1].total_steps if updates else 0
    for u in updates:
        k = -(-u.total_steps * QUARTERS // total) - 1 if total > 0 else 0
        value = u.values.get(field, math.nan)
        if math.isfinite(value):
            bins[min(max(k, 0), QUARTERS - 1)].append(value)
    return tuple(float(np.mean(b)) if b else math.nan for b in bins)


def _run_config(run_dir: Path) -> dict[str, object]:
    path = run_dir / "config.json"
    data = read_json(path) if path.exists() else {}
    return data if isinstance(data, dict) else {}


def is_batch_grid(out: str | Path) -> bool:
    """Whether the grid in ``out`` holds batch runs: a run folder's ``config.json`` says
    ``"kind": "batch"`` (the first run folder that has one decides)."""
    grid = read_grid(out)
    for run in grid["runs"]:
        cfg = _run_config(Path(out) / run["key"])
        if cfg:
            return cfg.get("kind") == "batch"
    return False


def _batch_run(seed: int, run_dir: Path, records: list[EpisodeRecord], score: float) -> BatchRun:
    path = run_dir / "updates.csv"
    updates = read_updates(path) if path.exists() else []
    quarters = QuarterDiagnostics(*(quarters_by_steps(updates, f) for f in QUARTER_FIELDS))
    return BatchRun(
        seed=seed,
        score=score,
        last100=last_return(records),
        mean_return=step_mean_return(records),
        steps=tuple(r.total_steps for r in records),
        returns=tuple(r.ret for r in records),
        quarters=quarters,
    )


def load_batch(out: str | Path) -> tuple[list[Cell], list[BatchCell]]:
    """The grid in ``out`` as the online report's cells (:func:`.results.load_results`) and
    as :class:`BatchCell` (one per (task, method), the same order)."""
    root = Path(out)
    cells = load_results(root)
    keys = {(r["env"], r["method"], r["seed"]): r["key"]
            for r in read_grid(root)["runs"]}  # fmt: skip
    batch = []
    for c in cells:
        runs = tuple(
            _batch_run(seed, root / keys[(c.env, c.method, seed)], recs, score)
            for seed, recs in sorted(c.curves.items())
            for score in [c.scores.get(seed, math.nan)]
        )
        batch.append(BatchCell(c.env, c.method, runs, tuple(sorted(c.missing))))
    return cells, batch
