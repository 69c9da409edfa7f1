"""The statistics a report prints, computed once: per-cell rows and PPO-RPE's improvements."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..figures import METHOD_LABELS
from ..results import (
    QUARTERS,
    Cell,
    early_return,
    mean_regularization,
    quarter_means,
    tasks_of,
    update_mean,
)
from ..stats import (
    Estimate,
    bootstrap_ci,
    common_seeds,
    iqm,
    mean_ci,
    mean_difference_ci,
    probability_of_improvement_ci,
)
from ..tables import QuarterRow

__all__ = [
    "Statistics",
    "cell_rows",
    "improvement_rows",
    "quarter_rows",
    "statistics",
]


@dataclass(frozen=True)
class Statistics:
    """Every statistic a report prints, computed once (the bootstraps are the slow part)."""

    rows: list[dict[str, Any]]
    """Per task and method: scores, early learning, regularisation, updates past the
    threshold and abs(rho - 1) (``summary.csv``)."""
    improvements: list[dict[str, Any]]
    """Per task and rival: the probabilities of improvement of PPO-RPE and the differences
    of the means."""
    quarters: list[QuarterRow]
    """Per task and method: the surrogate diagnostics by quarter of training."""


def statistics(cells: list[Cell]) -> Statistics:
    """The tables of a report: :func:`cell_rows`, :func:`improvement_rows` and
    :func:`quarter_rows`."""
    return Statistics(cell_rows(cells), improvement_rows(cells), quarter_rows(cells))


def _finite(values: list[float]) -> list[float]:
    return [v for v in values if math.isfinite(v)]


def _estimate(values: list[float], statistic: Any = np.mean) -> Estimate | None:
    vals = _finite(values)
    return bootstrap_ci(vals, statistic) if vals else None


def _put(row: dict[str, Any], name: str, est: Estimate | None) -> None:
    """``row[name_value|low|high]``: the estimate's three numbers (NaN without one)."""
    for part in ("value", "low", "high"):
        row[f"{name}_{part}"] = math.nan if est is None else getattr(est, part)


def cell_rows(cells: list[Cell]) -> list[dict[str, Any]]:
    """One row per cell: the mean score with its Student-t CI, then the bootstrap estimates
    (``<name>_value|low|high``) of the mean score (``boot``), its IQM, the first-50 return,
    the regularisation amount, the share of updates past the threshold and abs(rho - 1)."""
    rows = []
    for c in cells:
        scores = list(c.scores.values())
        mean, lo, hi = mean_ci(scores)
        row: dict[str, Any] = {
            "task": c.env,
            "method": METHOD_LABELS.get(c.method, c.method),
            "mean_score": mean,
            "ci95_low": lo,
            "ci95_high": hi,
            "seeds": len(c.scores),
            "missing": len(c.missing),
        }
        runs = list(c.curves.values())
        _put(row, "boot", _estimate(scores))
        _put(row, "iqm", _estimate(scores, iqm))
        _put(row, "first50", _estimate([early_return(r) for r in runs]))
        _put(row, "reg", _estimate([mean_regularization(r) for r in runs]))
        _put(row, "past", _estimate([update_mean(r, "past_threshold") for r in runs]))
        _put(row, "ratio_dev", _estimate([update_mean(r, "ratio_dev") for r in runs]))
        rows.append(row)
    return rows


def _seed_means(per_seed: list[tuple[float, ...]], quarter: int) -> float:
    """The mean over seeds of one quarter's values (NaN where no seed has a finite one)."""
    vals = _finite([q[quarter] for q in per_seed])
    return float(np.mean(vals)) if vals else math.nan


def quarter_rows(cells: list[Cell]) -> list[QuarterRow]:
    """One :class:`QuarterRow` per cell: ``past_threshold`` and ``ratio_dev`` by quarter of
    training, per run (:func:`.results.quarter_means`), then averaged over seeds."""
    rows = []
    for c in cells:
        by_field = []
        for field in ("past_threshold", "ratio_dev"):
            per_run = [quarter_means(r, field) for r in c.curves.values()]
            by_field.append(tuple(_seed_means(per_run, k) for k in range(QUARTERS)))
        past, dev = by_field
        label = METHOD_LABELS.get(c.method, c.method)
        rows.append(QuarterRow(c.env, label, len(c.curves), past, dev))
    return rows


def _per_seed(cell: Cell) -> dict[str, dict[int, float]]:
    """The per-seed numbers compared between methods (score, first-50 return,
    regularisation), by seed, finite values only."""
    numbers = {
        "score": dict(cell.scores),
        "first50": {s: early_return(r) for s, r in cell.curves.items()},
        "reg": {s: mean_regularization(r) for s, r in cell.curves.items()},
    }
    return {
        name: {s: v for s, v in sorted(by_seed.items()) if math.isfinite(v)}
        for name, by_seed in numbers.items()
    }


def _compare(row: dict[str, Any], name: str, x: dict[int, float], y: dict[int, float]) -> None:
    """``row``'s entries for one statistic on the seeds both methods finished
    (:func:`.stats.common_seeds`): P(x > y) (``name_value|low|high``), the difference of
    the means (``name_diff_*``), the numbers of seeds compared (``name_n``), the seeds
    (``name_seeds``) and how many were left out (``name_left_out``)."""
    x, y, left_out = common_seeds(x, y)
    a, b = list(x.values()), list(y.values())
    _put(row, name, probability_of_improvement_ci(a, b) if a and b else None)
    _put(row, f"{name}_diff", mean_difference_ci(a, b) if a and b else None)
    row[f"{name}_n"] = (len(a), len(b))
    row[f"{name}_seeds"] = (tuple(x), tuple(y))
    row[f"{name}_left_out"] = left_out


def improvement_rows(cells: list[Cell], of: str = "rpe") -> list[dict[str, Any]]:
    """Per task and rival method: P(``of`` > rival) of the scores, of the early returns and
    of the regularisation amount, and the differences of their means (``of`` minus rival),
    each with its bootstrap CI, with the seeds compared."""
    rows = []
    for env in tasks_of(cells):
        here = {c.method: c for c in cells if c.env == env}
        if of not in here:
            continue
        mine = _per_seed(here[of])
        for rival, theirs in here.items():
            if rival == of:
                continue
            row: dict[str, Any] = {"task": env, "method": of, "rival": rival}
            for name, y in _per_seed(theirs).items():
                _compare(row, name, mine[name], y)
            rows.append(row)
    return rows
