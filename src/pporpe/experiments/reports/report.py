"""``pporpe report``: REPORT.md, the tables and the figures of a grid's results folder.

:func:`write_report` reads ``OUT/grid.json`` and sends the grid to its report: a grid of
online runs to :func:`.online.report.write_online_report` (by episodes, the paper's claims),
a grid of batch runs (``kind = "batch"``, :func:`.batch.results.is_batch_grid`) to
:func:`.batch.report.write_batch_report` (by steps and over tasks).
"""

from __future__ import annotations

from pathlib import Path

from ...runs.links import refuse_links
from .batch.report import write_batch_report
from .batch.results import is_batch_grid
from .online.report import write_online_report

__all__ = ["REPORT_FILES", "write_report"]

REPORT_FILES = ("REPORT.md", "summary.md", "summary.csv", "runs.csv",
                *(f"fig_{name}.{ext}" for name in ("summary", "learning", "regularization",
                  "aggregate") for ext in ("png", "pdf")))  # fmt: skip
"""What a report writes into a grid's folder (checked first: never a symbolic link)."""


def write_report(out: str | Path, smooth: int = 10) -> list[Path]:
    """Write the summary table and figures into ``out`` (the grid's results folder); a grid
    of batch runs gets the batch report (:func:`.batch.report.write_batch_report`)."""
    if not (isinstance(smooth, int) and smooth >= 1):
        raise ValueError(f"smooth must be an int >= 1; got {smooth!r}")
    root = Path(out)
    refuse_links(root, REPORT_FILES)  # before anything is written
    if (root / "grid.json").exists() and is_batch_grid(root):
        return write_batch_report(root, smooth)
    return write_online_report(root, smooth)
