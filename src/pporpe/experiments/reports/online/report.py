"""``pporpe report`` on a grid of online runs: REPORT.md, the summary tables and the figures.

Reads ``OUT/grid.json`` and each run's ``episodes.csv`` and ``evaluation.json``
(:mod:`..results`); writes

* ``REPORT.md``: what ran, the tables below, and each claim of the paper (final score,
  early learning on the pendulum tasks, strength of regularisation) against the data, as
  a probability of improvement with its CI, the difference of the means with its CI, and
  a verdict (:mod:`.claims`, :mod:`..verdicts`: supported, contradicted, equivalent or
  cannot tell; none from fewer than 5 seeds or different seeds); a hand-written
  ``notes.md`` in the folder goes at its top;
* ``summary.md`` / ``summary.csv`` (:mod:`.tables`, from :mod:`.summary`): per task and
  method, over seeds of the per-seed median test score: the mean and the IQM with
  bootstrap 95% CIs (:mod:`..stats`; the CSV also has the Student-t interval), the mean
  return of the first 50 training episodes, the mean regularisation amount; how often the
  ratio was past the threshold and how far it was from 1 (how much the surrogates can
  differ), over the run and by quarter of training; then P(PPO-RPE > rival) for the
  first three;
* ``fig_summary``: bar summary of the scores (the paper's Fig. 3, ``sim_summary``);
* ``fig_learning``: learning curves per task, mean over seeds, 95% bands (Fig. 4, ``sim_learn``);
* ``fig_regularization``: trajectories of sigma*(rho - rho_dagger) (Fig. 5, ``sim_isr_diff``);

each figure as PNG and PDF (:mod:`..plots`). Unfinished or failed runs are left out and
counted. :func:`pporpe.experiments.reports.report.write_report` sends a grid of batch runs
(``kind = "batch"``) to its own report, by steps and over tasks (:mod:`..batch.report`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ....io import atomic_savefig, atomic_write_text
from ....run_files import read_grid
from ..plots import curve_figure, summary_figure
from ..preregistration import (
    Preregistration,
    before_cells,
    load_preregistrations,
    pending_tasks,
    preregistration_lines,
)
from ..results import Cell, compute_line, load_results, tasks_of
from ..tables import report_head
from .claims import claims_markdown
from .summary import Statistics, statistics
from .tables import summary_csv, summary_markdown

__all__ = ["report_markdown", "write_online_report"]


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
    """The grid's compute line (:func:`..results.compute_line`), if its runs record one."""
    line = compute_line(root, grid)
    return [line] if line else []


STANDING_HEADING = "## The result that stands until the pre-registered verdict"
"""The heading of the report's section on a pending pre-registration's earlier seeds (the
README's row of such a task comes from it: docs/generate.py)."""


def _standing_section(cells: list[Cell], regs: dict[str, Preregistration]) -> list[str]:
    """For tasks whose pre-registered verdict is pending: their scores and claims on the
    seeds finished before the pre-registration, the result that stands until it is read."""
    pending = pending_tasks(cells, regs)
    if not pending:
        return []
    before = [c for c in before_cells(cells, regs) if c.env in pending]
    stats = statistics(before)
    seeds = ", ".join(f"{t}: seeds 0-{regs[t].seeds_before - 1}" for t in pending)
    return [
        f"{STANDING_HEADING}\n",
        f"The seeds finished before the pre-registration ({seeds}), as reported then; the "
        "pre-registered verdict replaces this when all its runs are in.\n",
        summary_markdown(before, stats),
        claims_markdown(before, stats),
    ]


def report_markdown(root: Path, cells: list[Cell], stats: Statistics | None = None) -> str:
    """REPORT.md: what ran, the tables, the paper's claims against the data, the figures,
    and the folder's hand-written ``notes.md`` (if any) at the top."""
    stats = statistics(cells) if stats is None else stats
    grid = read_grid(root)
    regs = load_preregistrations(root)
    ran = _budget_lines(grid, cells) + preregistration_lines(cells, regs) + _compute(root, grid)
    parts = report_head(root, grid)
    parts += [
        "## What ran\n",
        "\n".join(ran) + "\n",
        "## Scores, early learning, regularisation\n",
        summary_markdown(cells, stats),
        "## The paper's claims against these data\n",
        claims_markdown(cells, stats, pending_tasks(cells, regs)),
        *_standing_section(cells, regs),
        "## Figures\n",
        "- Test scores per seed and their mean: ![summary](fig_summary.png)\n"
        "- Learning curves (mean over seeds, 95% band): ![learning](fig_learning.png)\n"
        "- Regularisation amount sigma*(rho - rho_dagger): "
        "![regularisation](fig_regularization.png)\n",
        f"Regenerated from the run folders by `pporpe report` on this folder ({root.name}/).\n",
    ]
    return "\n".join(parts)


def write_online_report(out: str | Path, smooth: int = 10) -> list[Path]:
    """Write REPORT.md, the summary tables and the figures of the online grid in ``out`` (the
    grid's results folder), learning curves smoothed over ``smooth`` episodes."""
    root = Path(out)
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
