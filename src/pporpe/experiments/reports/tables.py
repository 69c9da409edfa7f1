"""The Markdown every report's tables share: the head of a REPORT.md, numbers with their CIs,
and the table of where the surrogates act by quarter of training (:class:`QuarterRow`).

The online report's summary tables are in :mod:`.online.tables`, the batch report's in
:mod:`.batch.tables`; both write their quarters with :func:`quarter_markdown`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .results import QUARTERS

__all__ = [
    "QUARTER_LEGEND",
    "QuarterRow",
    "fmt",
    "fmt_ci",
    "quarter_markdown",
    "report_head",
]


@dataclass(frozen=True)
class QuarterRow:
    """Where a surrogate acts, for one task and method: per quarter of training
    (:func:`.results.quarter_means`), the share of updates past the threshold and the mean
    abs(rho - 1), each the mean over seeds of the runs' update-weighted means."""

    task: str
    method: str
    seeds: int
    """Runs averaged (finished runs of the cell)."""
    past: tuple[float, ...]
    """Share of updates past the threshold, per quarter (a fraction; NaN without data)."""
    ratio_dev: tuple[float, ...]
    """Mean abs(rho - 1) of the updates, per quarter (NaN without data)."""
    approx_kl: tuple[float, ...] | None = None
    """Approximate KL of the updates, per quarter (a batch grid's; None for an online grid,
    whose learner logs none)."""


def report_head(root: Path, grid: dict[str, Any], kind: str = "") -> list[str]:
    """The first parts of a REPORT.md: its title (the grid's name, ``kind`` after it) and the
    folder's hand-written ``notes.md`` if it has one."""
    notes = root / "notes.md"
    parts = [f"# Report: grid {grid.get('name', root.name)!r}{kind}\n"]
    if notes.exists():
        parts.append(notes.read_text().strip() + "\n")
    return parts


def fmt(x: float) -> str:
    """``x`` to one decimal, ``n/a`` for NaN."""
    return "n/a" if math.isnan(x) else f"{x:.1f}"


def _seeds(row: dict[str, Any], name: str) -> int | None:
    """The seeds behind a row's statistic ``name``: the row's ``seeds`` (a method's row), or
    the fewer of the two methods' seeds compared (``<stat>_n`` of a comparison's row, for
    ``<stat>`` and ``<stat>_diff``); None when the row does not say."""
    if "seeds" in row:
        return int(row["seeds"])
    n = row.get(f"{name.removesuffix('_diff')}_n")
    return min(n) if n else None


def fmt_ci(row: dict[str, Any], name: str, digits: int = 1, scale: float = 1.0) -> str:
    """``value [low, high]`` of a row's ``name_value|low|high`` (times ``scale``); a row of
    one seed (:func:`_seeds`) gives its value alone, ``value (1 seed, no CI)``: the
    bootstrap of one value is that value, an interval of width 0 that would read as
    certainty."""
    v, lo, hi = (scale * row[f"{name}_{p}"] for p in ("value", "low", "high"))
    if math.isnan(v):
        return "n/a"
    if _seeds(row, name) == 1:
        return f"{v:.{digits}f} (1 seed, no CI)"
    return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def _percent(x: float) -> str:
    """A fraction as a percentage to two decimals, ``n/a`` for NaN."""
    return "n/a" if math.isnan(x) else f"{100.0 * x:.2f}"


QUARTER_LEGEND = (
    "\nWhere in training the surrogates act: a run's training episodes split in order "
    f"into {QUARTERS} quarters Q1-Q{QUARTERS} (by episodes, not steps: of 200 episodes, "
    "Q1 is episodes 1-50); per quarter the share of the run's updates whose ratio rho "
    "was past the threshold and their mean abs(rho - 1), episodes weighted by their "
    "length (an online learner updates once per step), then the mean over seeds.\n"
)
"""The legend of the online grids' quarters table."""


def _kl(x: float) -> str:
    """An approximate KL to three significant digits, ``n/a`` for NaN."""
    return "n/a" if math.isnan(x) else f"{x:.3g}"


def quarter_markdown(rows: list[QuarterRow], legend: str = QUARTER_LEGEND) -> list[str]:
    """The lines of the table of where the surrogates act: per task and method, the share
    of updates past the threshold and the mean abs(rho - 1), by quarter of training, and
    the approximate KL where the rows have it (batch grids); then ``legend``."""
    quarters = [f"Q{k + 1}" for k in range(QUARTERS)]
    kl = any(r.approx_kl is not None for r in rows)
    head = (
        [f"past the threshold, % {q}" for q in quarters]
        + [f"abs(rho - 1), % {q}" for q in quarters]
        + ([f"approx. KL {q}" for q in quarters] if kl else [])
    )
    lines = [
        "| task | method | " + " | ".join(head) + " |",
        "| --- | --- | " + " | ".join([":---:"] * len(head)) + " |",
    ]
    for r in rows:
        cells = [_percent(v) for v in (*r.past, *r.ratio_dev)]
        if kl:
            cells += [_kl(v) for v in (r.approx_kl or (math.nan,) * QUARTERS)]
        lines.append(f"| {r.task} | {r.method} | " + " | ".join(cells) + " |")
    lines.append(legend)
    return lines
