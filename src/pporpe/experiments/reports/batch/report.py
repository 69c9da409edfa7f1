"""``pporpe report`` on a grid of batch runs: per task and over tasks, by steps.

For a grid whose runs are batch runs (:func:`.results.is_batch_grid`), writes

* ``REPORT.md``: what ran (the settings the runs share, the commands), the aggregate over
  tasks (:mod:`.aggregate`: IQM of the normalised values, P(PPO-RPE > rival) pooled over
  tasks, with verdicts), then per task and method the three numbers of
  :data:`.results.METRICS` (mean and IQM over seeds, bootstrap CIs), per task and
  rival P(PPO-RPE > rival), the difference of the means and the verdict of each number
  (:func:`.verdicts.verdict`), the surrogate diagnostics by quarter of steps, the figures;
* ``summary.md`` (the tables), ``summary.csv`` (a row per task and method) and ``runs.csv``
  (a row per finished run: its three numbers);
* ``fig_summary`` (test scores per seed), ``fig_learning`` (training return over
  environment steps, mean over seeds and 95% band) and ``fig_aggregate`` (the aggregate's
  IQMs and pooled probabilities of improvement with their CIs), as PNG and PDF.
"""

from __future__ import annotations

from pathlib import Path

from ....io import atomic_savefig, atomic_write_text
from ....run_files import read_grid
from ..plots import summary_figure
from .figures import aggregate_figure, step_curve_figure
from .results import load_batch
from .summary import batch_statistics, runs_csv, summary_csv
from .tables import batch_report_markdown, batch_summary_markdown

__all__ = ["write_batch_report"]


def write_batch_report(out: str | Path, smooth: int = 10) -> list[Path]:
    """Write REPORT.md, the tables and the figures of the batch grid in ``out``."""
    root = Path(out)
    cells, batch = load_batch(root)
    stats = batch_statistics(batch)
    grid = read_grid(root)
    written = [
        atomic_write_text(root / "REPORT.md", batch_report_markdown(root, grid, cells, stats)),
        atomic_write_text(root / "summary.md", batch_summary_markdown(stats)),
        atomic_write_text(root / "summary.csv", summary_csv(stats)),
        atomic_write_text(root / "runs.csv", runs_csv(batch)),
    ]
    figures = {
        "fig_summary": summary_figure(cells),
        "fig_learning": step_curve_figure(batch, smooth),
        "fig_aggregate": aggregate_figure(stats.aggregate),
    }
    for name, fig in figures.items():
        for ext in ("png", "pdf"):
            written.append(atomic_savefig(fig, root / f"{name}.{ext}"))
    return written
