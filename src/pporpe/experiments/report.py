"""``pporpe report``: REPORT.md, the summary tables and the figures of a grid's results.

Reads ``OUT/grid.json`` and each run's ``episodes.csv`` and ``evaluation.json``
(:mod:`.results`); writes

* ``REPORT.md``: what ran, the tables below, and each claim of the paper (final score,
  early learning on the pendulum tasks, strength of regularisation) against the data, as
  a probability of improvement with its CI, the difference of the means with its CI, and
  a verdict (:mod:`.verdicts`: supported, contradicted, equivalent or cannot tell; none
  from fewer than 5 seeds or different seeds); a hand-written ``notes.md`` in the folder
  goes at its top;
* ``summary.md`` / ``summary.csv`` (:mod:`.tables`, from :mod:`.summary`): per task and
  method, over seeds of the per-seed median test score: the mean and the IQM with
  bootstrap 95% CIs (:mod:`.stats`; the CSV also has the Student-t interval), the mean
  return of the first 50 training episodes, the mean regularisation amount; how often the
  ratio was past the threshold and how far it was from 1 (how much the surrogates can
  differ), over the run and by quarter of training; then P(PPO-RPE > rival) for the
  first three;
* ``fig_summary``: bar summary of the scores (the paper's Fig. 3, ``sim_summary``);
* ``fig_learning``: learning curves per task, mean over seeds, 95% bands (Fig. 4, ``sim_learn``);
* ``fig_regularization``: trajectories of sigma*(rho - rho_dagger) (Fig. 5, ``sim_isr_diff``);

each figure as PNG and PDF (:mod:`.report_figures`). Unfinished or failed runs are left
out and counted. A grid of batch runs (``kind = "batch"``) gets its own report, by steps
and over tasks (:mod:`.batch_report`); a sweep's tuning stage its sensitivity report, and
its evaluation stage its grid's report with the sweep's sections (:mod:`.sweep_report`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..io import atomic_savefig, atomic_write_text
from .batch_report import write_batch_report
from .batch_results import is_batch_grid
from .report_figures import curve_figure, summary_figure
from .results import (
    EARLY_EPISODES,
    Cell,
    compute_line,
    early_return,
    load_results,
    mean_regularization,
    tasks_of,
    update_mean,
)
from .stats import mean_ci
from .summary import Statistics, improvement_rows, statistics
from .sweep_report import evaluation_sections, sweep_stage, write_tuning_report
from .tables import report_head, summary_csv, summary_markdown
from .verdicts import claims_markdown

__all__ = [
    "EARLY_EPISODES",
    "Cell",
    "Statistics",
    "early_return",
    "improvement_rows",
    "load_results",
    "mean_ci",
    "mean_regularization",
    "report_markdown",
    "statistics",
    "update_mean",
    "write_report",
]


def _run_budget(cfg: dict[str, Any]) -> Any:
    """A run's length in its config: episodes or steps (online), total_steps (batch)."""
    return cfg.get("episodes") or cfg.get("steps") or cfg.get("total_steps")


def _budget_lines(grid: dict[str, Any], cells: list[Cell]) -> list[str]:
    """Per task: the training budget of its runs and how many of them finished."""
    lines = []
    for env in tasks_of(cells):
        runs = [r for r in grid["runs"] if r["env"] == env]
        budgets = sorted({_run_budget(r["config"]) for r in runs}, key=str)
        unit = "episodes" if runs and runs[0]["config"].get("episodes") else "steps"
        here = [c for c in cells if c.env == env]
        done = sum(len(c.curves) for c in here)
        lengths = [len(recs) for c in here for recs in c.curves.values()]
        ran = f"; episodes run per finished run: {min(lengths)}-{max(lengths)}" if lengths else ""
        lines.append(
            f"- {env}: {', '.join(map(str, budgets))} training {unit} per run, "
            f"{done}/{len(runs)} runs finished{ran}"
        )
    return lines


def _compute(root: Path, grid: dict[str, Any]) -> list[str]:
    """The grid's compute line (:func:`.results.compute_line`), if its runs record one."""
    line = compute_line(root, grid)
    return [line] if line else []


def report_markdown(root: Path, cells: list[Cell], stats: Statistics | None = None) -> str:
    """REPORT.md: what ran, the tables, the paper's claims against the data, the figures,
    and the folder's hand-written ``notes.md`` (if any) at the top."""
    stats = statistics(cells) if stats is None else stats
    grid = json.loads((root / "grid.json").read_text())
    parts = report_head(root, grid)
    parts += [
        "## What ran\n",
        "\n".join(_budget_lines(grid, cells) + _compute(root, grid)) + "\n",
        "## Scores, early learning, regularisation\n",
        summary_markdown(cells, stats),
        "## The paper's claims against these data\n",
        claims_markdown(cells, stats),
        "## Figures\n",
        "- Test scores per seed and their mean: ![summary](fig_summary.png)\n"
        "- Learning curves (mean over seeds, 95% band): ![learning](fig_learning.png)\n"
        "- Regularisation amount sigma*(rho - rho_dagger): "
        "![regularisation](fig_regularization.png)\n",
        f"Regenerated from the run folders by `pporpe report` on this folder ({root.name}/).\n",
    ]
    return "\n".join(parts)


def write_report(out: str | Path, smooth: int = 10) -> list[Path]:
    """Write the summary table and figures into ``out`` (the grid's results folder); a grid
    of batch runs gets the batch report (:func:`.batch_report.write_batch_report`)."""
    if not (isinstance(smooth, int) and smooth >= 1):
        raise ValueError(f"smooth must be an int >= 1; got {smooth!r}")
    root = Path(out)
    stage = sweep_stage(root)
    if stage == 1:
        return write_tuning_report(root)
    written = _write_grid_report(root, smooth)
    if stage == 2:  # a sweep's evaluation: its settings and trust regions after the verdicts
        extra, files = evaluation_sections(root)
        report = root / "REPORT.md"
        atomic_write_text(report, report.read_text().rstrip("\n") + "\n\n" + extra)
        written += files
    return written


def _write_grid_report(root: Path, smooth: int) -> list[Path]:
    """The report of a grid (of batch runs: :func:`.batch_report.write_batch_report`)."""
    if (root / "grid.json").exists() and is_batch_grid(root):
        return write_batch_report(root, smooth)
    cells = load_results(root)
    stats = statistics(cells)  # once for the three files
    written = [
        atomic_write_text(root / "REPORT.md", report_markdown(root, cells, stats)),
        atomic_write_text(root / "summary.md", summary_markdown(cells, stats)),
        atomic_write_text(root / "summary.csv", summary_csv(cells, stats)),
    ]
    regularization = r"$\sigma(\rho - \rho^\dagger)$"
    figures = {
        "fig_summary": summary_figure(cells),
        "fig_learning": curve_figure(cells, "ret", "episode return", "Learning curves", smooth),
        "fig_regularization": curve_figure(
            cells, "reg_amount", regularization, "Amount of regularisation", smooth
        ),
    }
    for name, fig in figures.items():
        for ext in ("png", "pdf"):
            written.append(atomic_savefig(fig, root / f"{name}.{ext}"))
    return written
