"""``grid.json`` and ``status.json`` of a folder that grids run into in chunks: each chunk
merges what it did into them, so that both describe the whole grid.

In ``grid.json`` a run of an earlier spec stays listed in its place; this spec's runs
replace theirs where their configuration changed (an entry written by an earlier pporpe
version, whose run is the same, is kept as written). ``status.json`` counts every listed
run: done, failed and pending, with the wall time of every call that trained, summed.
A call that changes neither leaves both files as they are, byte for byte.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from ...io import atomic_write_json
from ...run_files import parse_grid, read_json
from ...runs.folder import same_run_config
from ...runs.kinds import kind_of
from .spec import GridSpec, spec_summary

__all__ = ["grid_status", "merged_grid_summary", "write_grid_summary", "write_status"]


def _read_summary(path: Path) -> dict[str, Any] | None:
    """An earlier ``grid.json`` (None if there is none), checked to be a grid summary."""
    if not path.exists():
        return None
    try:
        return dict(parse_grid(read_json(path), path))
    except ValueError as exc:
        reason = str(exc).removeprefix(str(path)).lstrip(": ")
        raise ValueError(f"{path}: not a grid summary written by pporpe ({reason})") from None


def _same_entry(old: dict[str, Any], new: dict[str, Any], cfg: Any) -> bool:
    """Whether an earlier ``grid.json`` entry lists the same run as ``new`` (of ``cfg``)."""
    kind = kind_of(cfg).name
    try:
        same = same_run_config({"kind": kind, **old["config"]}, {"kind": kind, **new["config"]})
    except (KeyError, TypeError, ValueError):
        return False
    rest = {k: v for k, v in old.items() if k != "config"}
    return same and rest == {k: v for k, v in new.items() if k != "config"}


def merged_grid_summary(path: Path, spec: GridSpec) -> dict[str, Any]:
    """``spec``'s summary, keeping the runs of an earlier ``grid.json`` at ``path``.

    Grids run in chunks (one task, or a block of seeds, at a time) into one folder then
    report together: a run of an earlier spec stays listed, in its place, and a run of
    this spec replaces its entry unless the entry is the same run (a changed
    configuration of the same run is refused by the run folder itself).
    """
    summary = spec_summary(spec)
    old = _read_summary(path)
    if old is None:
        return summary
    runs = {r["key"]: r for r in old["runs"]}
    for entry, run in zip(summary["runs"], spec.runs, strict=True):
        kept = runs.get(entry["key"])
        if kept is None or not _same_entry(kept, entry, run.config):
            runs[entry["key"]] = entry
    return {**old, **{k: v for k, v in summary.items() if k != "runs"}, "runs": list(runs.values())}


def grid_status(
    out_dir: Path,
    keys: list[str],
    previous: dict[str, Any],
    failed_now: dict[str, str],
    seconds: float,
    backend: str,
) -> dict[str, Any]:
    """``status.json`` of the grid of runs ``keys`` after a call that took ``seconds``:
    done (``done.json`` on disk), failed (``error.txt`` on disk, with this call's message or
    the one recorded before), pending (the others), and the wall time of every call."""
    done = [k for k in keys if (out_dir / k / "done.json").exists()]
    old_failed = previous.get("failed")
    old_failed = {k: v for k, v in old_failed.items() if isinstance(v, str)} if isinstance(
        old_failed, dict) else {}  # fmt: skip
    failed = {}
    for key in keys:
        if key in done or not (out_dir / key / "error.txt").exists():
            continue
        failed[key] = failed_now.get(key) or old_failed.get(key) or _last_line(out_dir / key)
    old_time = previous.get("wall_time_s")
    old_time = old_time if isinstance(old_time, float) and math.isfinite(old_time) else 0.0
    return {
        "runs": len(keys),
        "done": sorted(done),
        "failed": dict(sorted(failed.items())),
        "pending": sorted(set(keys) - set(done) - set(failed)),
        "wall_time_s": (old_time if isinstance(old_time, int | float) else 0.0) + seconds,
        "backend": backend,
    }


def _last_line(run_dir: Path) -> str:
    lines = (run_dir / "error.txt").read_text(errors="replace").strip().splitlines()
    return lines[-1] if lines else "failed"


def write_grid_summary(out_dir: Path, listed: GridSpec) -> bool:
    """Merge the runs of ``listed`` into ``out_dir/grid.json``; whether it changed (a
    listing that is already there is not rewritten)."""
    path = out_dir / "grid.json"
    old = _read_summary(path)
    summary = merged_grid_summary(path, listed)
    if summary == old:
        return False
    atomic_write_json(path, summary)
    return True


def write_status(
    out_dir: Path, failed_now: dict[str, str], seconds: float, backend: str, changed: bool
) -> None:
    """Merge a call into ``out_dir/status.json`` (:func:`grid_status` of the runs that
    ``grid.json`` lists): its failures ``failed_now`` and its ``seconds``. A call that
    ``changed`` nothing (trained nothing, listed no new run) leaves the file as it is."""
    path = out_dir / "status.json"
    if path.exists() and not changed:
        return
    try:
        previous = read_json(path) if path.exists() else {}
    except ValueError:
        previous = {}  # an unreadable status is rebuilt from the run folders
    summary = _read_summary(out_dir / "grid.json") or {"runs": []}
    keys = [r["key"] for r in summary["runs"]]
    previous = previous if isinstance(previous, dict) else {}
    atomic_write_json(path, grid_status(out_dir, keys, previous, failed_now, seconds, backend))
