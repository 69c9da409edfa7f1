"""``pporpe report``: REPORT.md, the tables and the figures of a grid's results folder.

:func:`write_report` reads ``OUT/grid.json`` and sends the grid to its report: a grid of
online runs to :func:`.online.report.write_online_report` (by episodes, the paper's claims),
a grid of batch runs (``kind = "batch"``, :func:`.batch.results.is_batch_grid`) to
:func:`.batch.report.write_batch_report` (by steps and over tasks). A sweep's tuning stage
gets its sensitivity report (:func:`.sweep.report.write_tuning_report`), and its evaluation
stage its grid's report with the sweep's sections (:func:`.sweep.report.evaluation_sections`).
"""

from __future__ import annotations

from pathlib import Path

from ...io import atomic_write_text
from ...runs.links import refuse_links
from .batch.report import write_batch_report
from .batch.results import is_batch_grid
from .online.report import write_online_report
from .sweep.report import evaluation_sections, sweep_stage, write_tuning_report

__all__ = ["REPORT_FILES", "write_report"]

REPORT_FILES = ("REPORT.md", "summary.md", "summary.csv", "runs.csv", "sensitivity.csv",
                "trust_region.csv", "selected.toml",
                *(f"fig_{name}.{ext}" for ext in ("png", "pdf")
                  for name in ("summary", "learning", "regularization", "aggregate",
                               "sensitivity", "trust_region")))  # fmt: skip
"""What a report writes into a grid's folder (checked first: never a symbolic link)."""


def write_report(out: str | Path, smooth: int = 10) -> list[Path]:
    """Write the summary table and figures into ``out`` (the grid's results folder); a grid
    of batch runs gets the batch report (:func:`.batch.report.write_batch_report`), a
    sweep's tuning stage its own (:func:`.sweep.report.write_tuning_report`)."""
    if not (isinstance(smooth, int) and smooth >= 1):
        raise ValueError(f"smooth must be an int >= 1; got {smooth!r}")
    root = Path(out)
    refuse_links(root, REPORT_FILES)  # before anything is written
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
    """The report of a grid: the batch report for a grid of batch runs, else the online."""
    if (root / "grid.json").exists() and is_batch_grid(root):
        return write_batch_report(root, smooth)
    return write_online_report(root, smooth)
