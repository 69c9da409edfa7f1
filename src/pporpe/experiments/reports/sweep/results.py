"""A sweep's results folder read into (task, method, setting) cells, and their statistics:
per task the rule's metric over seeds, pooled over tasks the rule's value of the min-max
normalised values (:mod:`.selection`), each method's selection, and each run's trust region
(its mean approximate KL and mean abs(rho - 1) over its updates, from ``updates.csv``).

Every number a report of a sweep shows is computed here once (:func:`sweep_statistics`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ....runs.logger import read_records, read_updates
from ...sweep_terms import Setting, cell_name, sweep_of
from ..batch.aggregate import normalised
from ..batch.results import last_return, step_mean_return
from ..results import DIAGNOSTICS, update_mean
from ..stats import Estimate, bootstrap_ci, stratified_iqm_ci
from .selection import Candidate, Rule, Selection, parse_rule, select

__all__ = [
    "TRUST_FIELDS",
    "PooledCell",
    "SweepCell",
    "SweepRun",
    "SweepStatistics",
    "load_sweep",
    "sweep_statistics",
    "task_best",
]

TRUST_FIELDS = ("approx_kl", "ratio_dev", "past_threshold")
"""The ``updates.csv`` columns averaged over a run's updates: its trust region."""


@dataclass(frozen=True)
class SweepRun:
    """The numbers of one finished run."""

    seed: int
    values: dict[str, float]
    """Each :data:`..batch.results.METRICS` key's value (NaN where the run has none)."""
    trust: dict[str, float]
    """Each of :data:`TRUST_FIELDS`, the mean over the run's updates (every update weighs
    the same) in its ``updates.csv``; for an online run (no ``updates.csv``) the mean of its
    episodes' diagnostics weighted by their lengths (one update per step), and no KL. NaN
    without a finite value."""


@dataclass(frozen=True)
class SweepCell:
    """The runs of one (task, method, setting) of a sweep."""

    env: str
    method: str
    setting: Setting
    runs: tuple[SweepRun, ...]
    """Finished runs, by seed."""
    missing: tuple[int, ...]
    """Seeds without a finished run (``done.json``)."""

    @property
    def name(self) -> str:
        """The cell's folder name (:func:`...sweep_terms.cell_name`)."""
        return cell_name(self.method, self.setting)

    def values(self, metric: str) -> dict[int, float]:
        """The finite values of ``metric`` by seed."""
        return {r.seed: v for r in self.runs if math.isfinite(v := r.values[metric])}


def _mean(values: Sequence[float]) -> float:
    vals = [v for v in values if math.isfinite(v)]
    return float(np.mean(vals)) if vals else math.nan


def _run(seed: int, run_dir: Path) -> SweepRun:
    records = read_records(run_dir / "episodes.csv")
    ev = run_dir / "evaluation.json"
    score = float(json.loads(ev.read_text())["median"]) if ev.exists() else math.nan
    values = {"score": score, "last100": last_return(records),
              "mean_return": step_mean_return(records)}  # fmt: skip
    path = run_dir / "updates.csv"
    if path.exists():
        updates = read_updates(path)
        trust = {f: _mean([u.values.get(f, math.nan) for u in updates]) for f in TRUST_FIELDS}
    else:  # an online run: one update per step, its episodes' diagnostics, no KL
        trust = {f: update_mean(records, f) if f in DIAGNOSTICS else math.nan
                 for f in TRUST_FIELDS}  # fmt: skip
    return SweepRun(seed, values, trust)


def load_sweep(root: Path) -> tuple[dict[str, Any], list[SweepCell]]:
    """The ``grid.json`` of the sweep in ``root`` and its cells, in the order of its runs
    (task, then method, then setting)."""
    grid = json.loads((root / "grid.json").read_text())
    if sweep_of(grid) is None:
        raise ValueError(f"{root}: not a sweep (its grid.json records no sweep)")
    found: dict[tuple[Any, ...], tuple[list[SweepRun], list[int]]] = {}
    for run in grid["runs"]:
        setting = tuple(run.get("setting", {}).items())
        runs, missing = found.setdefault((run["env"], run["method"], setting), ([], []))
        run_dir = root / run["key"]
        if (run_dir / "done.json").exists():
            runs.append(_run(int(run["seed"]), run_dir))
        else:
            missing.append(int(run["seed"]))
    cells = [
        SweepCell(env, method, setting, tuple(sorted(runs, key=lambda r: r.seed)),
                  tuple(sorted(missing)))
        for (env, method, setting), (runs, missing) in found.items()
    ]  # fmt: skip
    return grid, cells


@dataclass(frozen=True)
class PooledCell:
    """A (method, setting) over the tasks: the rule's value and its CI."""

    method: str
    setting: Setting
    value: Estimate | None
    """The rule's statistic of the normalised values pooled over tasks and seeds, with a
    bootstrap 95% CI (stratified by task for the IQM); None without a finished run."""
    runs: int
    """Finished runs pooled."""
    missing: int
    """Runs not finished."""
    trust: dict[str, float]
    """Each of :data:`TRUST_FIELDS`: the mean over its finished runs."""


@dataclass(frozen=True)
class SweepStatistics:
    """Every number of a sweep's report."""

    rule: Rule
    cells: tuple[SweepCell, ...]
    pooled: tuple[PooledCell, ...]
    """Per method and setting, in spec order."""
    selections: dict[str, Selection]
    """Per method, its selection; empty while a run of the sweep is unfinished."""

    @property
    def complete(self) -> bool:
        """Whether every run of the sweep has finished."""
        return not any(c.missing for c in self.cells)

    @property
    def tasks(self) -> list[str]:
        """The tasks, in spec order."""
        return list(dict.fromkeys(c.env for c in self.cells))


def _ranges(cells: Sequence[SweepCell], metric: str) -> dict[str, tuple[float, float]]:
    """Per task, the lowest and highest value of ``metric`` over all its finished runs."""
    out = {}
    for env in dict.fromkeys(c.env for c in cells):
        vals = [v for c in cells if c.env == env for v in c.values(metric).values()]
        if vals:
            out[env] = (min(vals), max(vals))
    return out


def _pooled(
    rule: Rule, group: list[SweepCell], ranges: dict[str, tuple[float, float]]
) -> PooledCell:
    strata = [[normalised(v, *ranges[c.env]) for v in c.values(rule.metric).values()]
              for c in group if c.values(rule.metric)]  # fmt: skip
    flat = [v for s in strata for v in s]
    est = None
    if flat:
        est = stratified_iqm_ci(strata) if rule.statistic == "iqm" else bootstrap_ci(flat)
        est = Estimate(rule.value(flat), est.low, est.high)
    runs = [r for c in group for r in c.runs]
    trust = {f: _mean([r.trust[f] for r in runs]) for f in TRUST_FIELDS}
    first = group[0]
    return PooledCell(first.method, first.setting, est, len(runs),
                      sum(len(c.missing) for c in group), trust)  # fmt: skip


def sweep_statistics(grid: dict[str, Any], cells: list[SweepCell]) -> SweepStatistics:
    """The pooled values of every (method, setting) and, once every run has finished, each
    method's selection by the sweep's rule."""
    rule = parse_rule((sweep_of(grid) or {}).get("select", "iqm:mean_return"))
    ranges = _ranges(cells, rule.metric)
    groups: dict[tuple[str, Setting], list[SweepCell]] = {}
    for c in cells:
        groups.setdefault((c.method, c.setting), []).append(c)
    pooled = tuple(_pooled(rule, g, ranges) for g in groups.values())
    selections: dict[str, Selection] = {}
    if not any(c.missing for c in cells):
        for method in dict.fromkeys(p.method for p in pooled):
            candidates = [Candidate(p.setting, p.value.value if p.value else math.nan, p.runs)
                          for p in pooled if p.method == method]  # fmt: skip
            if (chosen := select(method, candidates)) is not None:
                selections[method] = chosen
    return SweepStatistics(rule, tuple(cells), pooled, selections)


def task_best(cells: Sequence[SweepCell], env: str, method: str, metric: str) -> Setting | None:
    """The setting of ``method`` with the highest mean over seeds of ``metric`` on ``env``
    (the first listed among equals; None without a finished run)."""
    here = [(c.setting, _mean(list(c.values(metric).values())))
            for c in cells if c.env == env and c.method == method]  # fmt: skip
    here = [(s, v) for s, v in here if math.isfinite(v)]
    if not here:
        return None
    top = max(v for _, v in here)
    return next(s for s, v in here if v == top)
