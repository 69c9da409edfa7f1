"""The statistics of a batch report (:mod:`.batch.report`), computed once: per task and
method the three numbers of :data:`.batch.results.METRICS` over seeds, per task and rival
PPO-RPE's probability of improvement and difference of means with their verdicts, the
surrogate diagnostics by quarter of steps, and the aggregate over tasks (:mod:`.aggregate`);
and the report's CSV tables.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..figures import METHOD_LABELS
from ..results import QUARTERS
from ..stats import (
    Estimate,
    bootstrap_ci,
    common_seeds,
    iqm,
    mean_difference_ci,
    probability_of_improvement_ci,
)
from ..tables import QuarterRow
from ..verdicts import verdict
from .aggregate import Aggregate, aggregate
from .results import METRICS, QUARTER_FIELDS, BatchCell, batch_tasks

__all__ = [
    "BatchRow",
    "BatchStatistics",
    "Comparison",
    "MetricSummary",
    "batch_statistics",
    "comparisons",
    "quarter_rows",
    "runs_csv",
    "summary_csv",
]


@dataclass(frozen=True)
class MetricSummary:
    """One metric of one (task, method) over its seeds (None without a finite value)."""

    mean: Estimate | None
    """Mean over seeds, bootstrap (BCa) 95% CI."""
    iqm: Estimate | None
    """Interquartile mean over seeds, bootstrap (BCa) 95% CI."""


@dataclass(frozen=True)
class BatchRow:
    """A (task, method) of a batch grid: its seeds and each metric's summary."""

    task: str
    method: str
    seeds: int
    """Finished runs."""
    missing: int
    """Runs not finished."""
    metrics: tuple[MetricSummary, ...]
    """One per :data:`.batch.results.METRICS`, in their order."""


@dataclass(frozen=True)
class Comparison:
    """P(``method`` > ``rival``) of one metric on one task, and the difference of means."""

    metric: str
    task: str
    method: str
    rival: str
    n: tuple[int, int]
    """Seeds of ``method`` and of ``rival`` compared: those both have a finite value of."""
    left_out: int
    """Seeds of either left out because the other has no value there (a run unfinished or
    failed; :func:`.stats.common_seeds`)."""
    p: Estimate | None
    """P(method > rival) with its bootstrap 95% CI (None without data)."""
    diff: Estimate | None
    """mean(method) - mean(rival) with its bootstrap 95% CI (None without data)."""

    @property
    def verdict(self) -> str:
        """:func:`.verdicts.verdict` of the CI of ``p``."""
        low, high = (math.nan, math.nan) if self.p is None else (self.p.low, self.p.high)
        return verdict(low, high, self.n, self.left_out)


@dataclass(frozen=True)
class BatchStatistics:
    """Every number of a batch report, computed once."""

    rows: tuple[BatchRow, ...]
    comparisons: tuple[Comparison, ...]
    quarters: tuple[QuarterRow, ...]
    aggregate: Aggregate


def _summary(values: list[float]) -> MetricSummary:
    if not values:
        return MetricSummary(None, None)
    return MetricSummary(bootstrap_ci(values), bootstrap_ci(values, iqm))


def _row(c: BatchCell) -> BatchRow:
    metrics = tuple(_summary(list(c.values(m.key).values())) for m in METRICS)
    label = METHOD_LABELS.get(c.method, c.method)
    return BatchRow(c.env, label, len(c.runs), len(c.missing), metrics)


def comparisons(cells: list[BatchCell], of: str = "rpe") -> list[Comparison]:
    """Per metric, task and rival: P(``of`` > rival) and the difference of the means."""
    out = []
    for m in METRICS:
        for env in batch_tasks(cells):
            here = {c.method: c.values(m.key) for c in cells if c.env == env}
            if of not in here:
                continue
            for rival, theirs in here.items():
                if rival == of:
                    continue
                x, y, left_out = common_seeds(here[of], theirs)
                a, b = list(x.values()), list(y.values())
                p = probability_of_improvement_ci(a, b) if a and b else None
                diff = mean_difference_ci(a, b) if a and b else None
                n = (len(a), len(b))
                out.append(Comparison(m.key, env, of, rival, n, left_out, p, diff))
    return out


def _seed_mean(values: list[float]) -> float:
    vals = [v for v in values if math.isfinite(v)]
    return float(np.mean(vals)) if vals else math.nan


def quarter_rows(cells: list[BatchCell]) -> list[QuarterRow]:
    """Per (task, method): each of :data:`.batch.results.QUARTER_FIELDS` by quarter of
    steps, the mean over seeds of the runs' quarter means."""
    rows = []
    for c in cells:
        per_field = [
            tuple(_seed_mean([getattr(r.quarters, f)[k] for r in c.runs]) for k in range(QUARTERS))
            for f in QUARTER_FIELDS
        ]
        label = METHOD_LABELS.get(c.method, c.method)
        rows.append(QuarterRow(c.env, label, len(c.runs), *per_field))
    return rows


def batch_statistics(cells: list[BatchCell]) -> BatchStatistics:
    """The per-task rows, the comparisons, the quarters and the aggregate of ``cells``."""
    return BatchStatistics(
        tuple(_row(c) for c in cells),
        tuple(comparisons(cells)),
        tuple(quarter_rows(cells)),
        aggregate(cells),
    )


def summary_csv(stats: BatchStatistics) -> str:
    """A row per task and method: seeds, missing, and per metric its mean and IQM with
    their CIs (``<metric>_mean_value|low|high``, ``<metric>_iqm_value|low|high``)."""
    rows = []
    for r in stats.rows:
        row: dict[str, Any] = {"task": r.task, "method": r.method, "seeds": r.seeds,
                               "missing": r.missing}  # fmt: skip
        for m, s in zip(METRICS, r.metrics, strict=True):
            for name, est in (("mean", s.mean), ("iqm", s.iqm)):
                for part in ("value", "low", "high"):
                    row[f"{m.key}_{name}_{part}"] = math.nan if est is None else getattr(est, part)
        rows.append(row)
    return _csv(rows)


def runs_csv(cells: list[BatchCell]) -> str:
    """A row per finished run: task, method, seed, its training episodes and steps, and its
    three numbers."""
    rows = [
        {"task": c.env, "method": c.method, "seed": r.seed, "episodes": len(r.returns),
         "steps": r.steps[-1] if r.steps else 0, **{m.key: r.value(m.key) for m in METRICS}}
        for c in cells
        for r in c.runs
    ]  # fmt: skip
    return _csv(rows)


def _csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    names = list(rows[0]) if rows else ["task"]
    writer = csv.DictWriter(buf, fieldnames=names, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()
