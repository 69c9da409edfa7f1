"""Summary table and the paper's figures from a grid's results folder.

Reads ``OUT/grid.json`` and each run's ``episodes.csv`` and ``evaluation.json``; writes

* ``summary.md`` / ``summary.csv``: per task and method, the mean and 95% confidence
  interval (Student t) over seeds of the per-seed median test score, and the seed count;
* ``fig_summary``: bar summary of the scores (the paper's Fig. 3, ``sim_summary``);
* ``fig_learning``: learning curves per task, mean over seeds, 95% bands (Fig. 4, ``sim_learn``);
* ``fig_regularization``: trajectories of sigma*(rho - rho_dagger) (Fig. 5, ``sim_isr_diff``);

each figure as PNG and PDF. Unfinished or failed runs are left out and counted.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from scipy import stats

from ..io import atomic_savefig, atomic_write_text
from ..runs.logger import EpisodeRecord, read_records
from .figures import METHOD_COLORS, METHOD_LABELS, METHOD_STYLES

__all__ = ["Cell", "load_results", "mean_ci", "write_report"]


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


def mean_ci(values: list[float], level: float = 0.95) -> tuple[float, float, float]:
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


def load_results(out: str | Path) -> list[Cell]:
    """Collect every run of the grid in ``out`` into (task, method) cells."""
    root = Path(out)
    grid_file = root / "grid.json"
    if not grid_file.exists():
        raise ValueError(f"{root} holds no grid results (no grid.json); run `pporpe reproduce`")
    grid = json.loads(grid_file.read_text())
    cells: dict[tuple[str, str], Cell] = {}
    for run in grid["runs"]:
        key = (run["env"], run["method"])
        cell = cells.setdefault(key, Cell(run["env"], run["method"], {}, {}, []))
        run_dir = root / run["key"]
        if not (run_dir / "done.json").exists():
            cell.missing.append(run["seed"])
            continue
        cell.curves[run["seed"]] = read_records(run_dir / "episodes.csv")
        ev = run_dir / "evaluation.json"
        if ev.exists():
            cell.scores[run["seed"]] = float(json.loads(ev.read_text())["median"])
    return list(cells.values())


def _table_rows(cells: list[Cell]) -> list[dict[str, Any]]:
    rows = []
    for c in cells:
        mean, lo, hi = mean_ci(list(c.scores.values()))
        rows.append(
            {
                "task": c.env,
                "method": METHOD_LABELS.get(c.method, c.method),
                "mean_score": mean,
                "ci95_low": lo,
                "ci95_high": hi,
                "seeds": len(c.scores),
                "missing": len(c.missing),
            }
        )
    return rows


def _fmt(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{x:.1f}"


def summary_markdown(cells: list[Cell]) -> str:
    """The summary table as Markdown."""
    lines = [
        "| task | method | score (mean over seeds) | 95% CI | seeds | missing |",
        "| --- | --- | ---: | :---: | ---: | ---: |",
    ]
    for r in _table_rows(cells):
        ci = f"[{_fmt(r['ci95_low'])}, {_fmt(r['ci95_high'])}]"
        lines.append(
            f"| {r['task']} | {r['method']} | {_fmt(r['mean_score'])} | {ci} | "
            f"{r['seeds']} | {r['missing']} |"
        )
    note = (
        "\nScore of a run: median return of its test episodes. Mean and 95% confidence "
        "interval (Student t) over seeds.\n"
    )
    return "\n".join(lines) + "\n" + note


def summary_csv(cells: list[Cell]) -> str:
    """The summary table as CSV."""
    buf = io.StringIO()
    rows = _table_rows(cells)
    writer = csv.DictWriter(
        buf, fieldnames=list(rows[0]) if rows else ["task"], lineterminator="\n"
    )
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _envs(cells: list[Cell]) -> list[str]:
    return list(dict.fromkeys(c.env for c in cells))


def _band(curves: list[list[float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and 95% band over seeds, episode by episode (up to the shortest run)."""
    n = min(len(c) for c in curves)
    arr = np.asarray([c[:n] for c in curves], dtype=np.float64)
    mean = arr.mean(axis=0)
    if arr.shape[0] < 2:
        return mean, mean, mean
    half = stats.t.ppf(0.975, arr.shape[0] - 1) * arr.std(axis=0, ddof=1) / math.sqrt(arr.shape[0])
    return mean, mean - half, mean + half


def _smooth(x: list[float], window: int) -> list[float]:
    if window <= 1 or len(x) < 2:
        return list(x)
    out, acc = [], 0.0
    for i, v in enumerate(x):
        acc += v
        if i >= window:
            acc -= x[i - window]
        out.append(acc / min(i + 1, window))
    return out


def _curve_figure(cells: list[Cell], field: str, ylabel: str, title: str, smooth: int) -> Any:
    envs = _envs(cells)
    fig, axes = plt.subplots(1, len(envs), figsize=(4.2 * len(envs), 3.6), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=True):
        for c in (c for c in cells if c.env == env):
            curves = [
                _smooth([getattr(r, field) for r in recs], smooth)
                for recs in c.curves.values()
                if recs
            ]
            if not curves:
                continue
            mean, lo, hi = _band(curves)
            x = np.arange(1, mean.size + 1)
            color = METHOD_COLORS.get(c.method)
            ax.plot(
                x,
                mean,
                color=color,
                ls=METHOD_STYLES.get(c.method, "-"),
                lw=1.6,
                label=f"{METHOD_LABELS.get(c.method, c.method)} (n={len(curves)})",
            )
            ax.fill_between(x, lo, hi, color=color, alpha=0.2, lw=0)
        ax.set_title(env)
        ax.set_xlabel("episode")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    suffix = f"; moving average over {smooth} episodes" if smooth > 1 else ""
    fig.suptitle(f"{title} (mean over seeds, shaded: 95% CI{suffix})")
    fig.tight_layout()
    return fig


def _summary_figure(cells: list[Cell]) -> Any:
    envs = _envs(cells)
    fig, axes = plt.subplots(1, len(envs), figsize=(3.6 * len(envs), 3.6), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=True):
        row = [c for c in cells if c.env == env]
        for i, c in enumerate(row):
            scores = list(c.scores.values())
            mean, lo, hi = mean_ci(scores)
            color = METHOD_COLORS.get(c.method)
            if scores:
                err = None if math.isnan(lo) else [[mean - lo], [hi - mean]]
                ax.bar(i, mean, color=color, alpha=0.7, yerr=err, capsize=5)
                jitter = np.linspace(-0.15, 0.15, len(scores)) if len(scores) > 1 else [0.0]
                ax.scatter(i + np.asarray(jitter), scores, color="k", s=10, zorder=3)
        ax.set_xticks(range(len(row)), [METHOD_LABELS.get(c.method, c.method) for c in row])
        ax.set_title(env)
        ax.set_ylabel("median test return")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("Test score per seed (dots), mean and 95% CI over seeds (bars)")
    fig.tight_layout()
    return fig


def write_report(out: str | Path, smooth: int = 10) -> list[Path]:
    """Write the summary table and figures into ``out`` (the grid's results folder)."""
    if not (isinstance(smooth, int) and smooth >= 1):
        raise ValueError(f"smooth must be an int >= 1; got {smooth!r}")
    root = Path(out)
    cells = load_results(root)
    written = [
        atomic_write_text(root / "summary.md", summary_markdown(cells)),
        atomic_write_text(root / "summary.csv", summary_csv(cells)),
    ]
    figures = {
        "fig_summary": _summary_figure(cells),
        "fig_learning": _curve_figure(cells, "ret", "episode return", "Learning curves", smooth),
        "fig_regularization": _curve_figure(
            cells,
            "reg_amount",
            r"$\sigma(\rho - \rho^\dagger)$",
            "Amount of regularisation",
            smooth,
        ),
    }
    for name, fig in figures.items():
        for ext in ("png", "pdf"):
            written.append(atomic_savefig(fig, root / f"{name}.{ext}"))
        plt.close(fig)
    return written
