"""A grid's results folder read into (task, method) cells, and per-run numbers from them."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from ...evaluation import summarize_returns
from ...run_files import read_done, read_evaluation, read_grid
from ...runs.kinds import SurrogateDiagnostics
from ...runs.logger import EpisodeRecord, read_records

__all__ = [
    "DIAGNOSTICS",
    "EARLY_EPISODES",
    "QUARTERS",
    "Cell",
    "compute_line",
    "diagnostic",
    "early_return",
    "load_results",
    "mean_regularization",
    "quarter_means",
    "record_value",
    "tasks_of",
    "update_mean",
]

EARLY_EPISODES = 50
"""Training episodes of the early-learning comparison (the paper's pendulum claim)."""

QUARTERS = 4
"""Parts of training that :func:`quarter_means` splits a run's episodes into."""

DIAGNOSTICS: tuple[str, ...] = tuple(f.name for f in fields(SurrogateDiagnostics))
"""The names of a record's surrogate diagnostics (:func:`diagnostic`)."""


@dataclass
class Cell:
    """Results of one (task, method) over seeds."""

    env: str
    method: str
    scores: dict[int, float]
    """Per-seed median test return."""
    curves: dict[int, list[EpisodeRecord]]
    """Per-seed training records."""
    missing: list[int]
    """Seeds without a finished run."""


def load_results(out: str | Path) -> list[Cell]:
    """Collect every run of the grid in ``out`` into (task, method) cells."""
    root = Path(out)
    grid_file = root / "grid.json"
    if not grid_file.exists():
        raise ValueError(f"{root} holds no grid results (no grid.json); run `pporpe reproduce`")
    grid = read_grid(root)
    cells: dict[tuple[str, str], Cell] = {}
    for run in grid["runs"]:
        key = (run["env"], run["method"])
        cell = cells.setdefault(key, Cell(run["env"], run["method"], {}, {}, []))
        run_dir = root / run["key"]
        if not (run_dir / "done.json").exists():
            cell.missing.append(run["seed"])
            continue
        cell.curves[run["seed"]] = read_records(run_dir / "episodes.csv")
        if (run_dir / "evaluation.json").exists():
            ev = read_evaluation(run_dir)
            median = ev["median"] if "median" in ev else summarize_returns(ev["returns"]).median
            cell.scores[run["seed"]] = float(median)
    return list(cells.values())


def compute_line(root: Path, grid: dict[str, Any]) -> str | None:
    """What the grid's finished runs record of their compute in ``done.json``: the CPU hours
    of training (``cpu_time``: each run's share of its process's CPU time) and of the test
    episodes (``eval_cpu_time``), summed over the runs that record them (not their wall
    times: a population's members share theirs); None when no finished run records CPU
    time (runs finished before pporpe recorded it). Work lost to a kill (since the last
    checkpoint) is not counted, nor the CPU time of a run before it resumed from a
    checkpoint without the record (``cpu_time_since`` > 0: counted as part-way)."""
    done = [root / r["key"] / "done.json" for r in grid["runs"]]
    stats = [read_done(f.parent) for f in done if f.exists()]
    timed = [d for d in stats if "cpu_time" in d]
    if not timed:
        return None
    train = sum(float(d["cpu_time"]) for d in timed) / 3600
    test = sum(float(d.get("eval_cpu_time", 0.0)) for d in timed) / 3600
    older = len(stats) - len(timed)
    partial = sum(int(d.get("cpu_time_since", 0)) > 0 for d in timed)
    notes = [f"{train:.2f} training, {test:.2f} test episodes"]
    if partial:
        notes.append(f"{partial} of these runs counted from a resume part-way, their earlier "
                     "CPU time unrecorded")  # fmt: skip
    if older:
        notes.append(f"{older} other finished run{'s' if older > 1 else ''} without the record")
    return (
        f"- Compute: {train + test:.2f} CPU hours over the {len(timed)} finished runs that "
        f"record it ({'; '.join(notes)}). "
        "A run's CPU time is its share of its process's: a population's split evenly between "
        "its busy members."
    )


def tasks_of(cells: list[Cell]) -> list[str]:
    """The tasks of ``cells`` in their first order."""
    return list(dict.fromkeys(c.env for c in cells))


def early_return(records: list[EpisodeRecord], episodes: int = EARLY_EPISODES) -> float:
    """Mean return of a run's first ``episodes`` training episodes (NaN without any)."""
    rets = [r.ret for r in records[:episodes]]
    return float(np.mean(rets)) if rets else math.nan


def diagnostic(record: EpisodeRecord, name: str) -> float:
    """A record's surrogate diagnostic ``name`` (a field of
    :class:`~pporpe.runs.kinds.SurrogateDiagnostics`); NaN where the record has none (a
    batch run's ``trace_decay``, a learner that reports no diagnostics)."""
    if name not in DIAGNOSTICS:
        raise ValueError(f"name must be one of {list(DIAGNOSTICS)}; got {name!r}")
    value = None if record.diagnostics is None else getattr(record.diagnostics, name)
    return math.nan if value is None else float(value)


def record_value(record: EpisodeRecord, name: str) -> float:
    """A record's number by its ``episodes.csv`` column: one of its own (``ret``,
    ``length``, ...) or of its diagnostics (:func:`diagnostic`: NaN where it has none)."""
    return diagnostic(record, name) if name in DIAGNOSTICS else float(getattr(record, name))


def mean_regularization(records: list[EpisodeRecord]) -> float:
    """Mean over a run's training episodes of sigma*(rho - rho_dagger) (NaN without any)."""
    vals = [v for r in records if math.isfinite(v := diagnostic(r, "reg_amount"))]
    return float(np.mean(vals)) if vals else math.nan


def update_mean(records: list[EpisodeRecord], field: str) -> float:
    """Mean over a run's updates of a per-episode mean diagnostic ``field``
    (``past_threshold``, ``ratio_dev``, ``trace_decay``): episodes weighted by their length,
    since an online run makes one update per step (NaN without any finite value: a batch
    run's ``trace_decay``)."""
    pairs = [(diagnostic(r, field), r.length) for r in records]
    pairs = [(v, n) for v, n in pairs if math.isfinite(v) and n > 0]
    if not pairs:
        return math.nan
    return float(sum(v * n for v, n in pairs) / sum(n for _, n in pairs))


def quarter_means(records: list[EpisodeRecord], field: str) -> tuple[float, ...]:
    """:func:`update_mean` of ``field`` over each quarter of a run's training episodes:
    quarter ``k`` holds ``records[k * n // 4 : (k + 1) * n // 4]`` of ``n`` (episodes, not
    steps, are split; within a quarter episodes weigh by their length, one update per
    step). NaN for a quarter without a finite value (fewer than 4 episodes)."""
    n = len(records)
    edges = [k * n // QUARTERS for k in range(QUARTERS + 1)]
    return tuple(update_mean(records[a:b], field) for a, b in pairwise(edges))
