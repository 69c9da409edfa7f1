"""``grid.json`` of a folder that grids run into in chunks (earlier runs kept).

A run of an earlier spec stays listed in its place; this spec's runs replace theirs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .grid import GridSpec, spec_summary

__all__ = ["merged_grid_summary"]


def merged_grid_summary(path: Path, spec: GridSpec) -> dict[str, Any]:
    """``spec``'s summary, keeping the runs of an earlier ``grid.json`` at ``path``.

    Grids run in chunks (one task, or a block of seeds, at a time) into one folder then
    report together: a run of an earlier spec stays listed, in its place, and a run of
    this spec replaces its entry (a changed configuration of the same run is refused by
    the run folder itself).
    """
    summary = spec_summary(spec)
    if not path.exists():
        return summary
    try:
        old = json.loads(path.read_text())
        old_runs = {r["key"]: r for r in old["runs"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a grid summary written by pporpe ({exc})") from None
    old_runs.update({r["key"]: r for r in summary["runs"]})
    return {**summary, "runs": list(old_runs.values())}
