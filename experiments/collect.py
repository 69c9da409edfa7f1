"""Copy a grid's finished runs from its working folder into the committed results folder.

Long grids (``experiments/paper-full.toml``, ``paper-50seeds.toml``) run for many hours in a
folder outside the repository, where their checkpoints are, and are resumed there; each
finished run's small files are copied into ``results/NAME`` as soon as it finishes, so that a
stop or a change of machine loses at most the runs in flight:

    python experiments/collect.py /work/runs/paper-full results/paper-full

A run is finished when it has ``done.json``. Its ``config.json``, ``episodes.csv``,
``evaluation.json`` and ``done.json`` are copied, and ``updates.csv`` where it has one (a
batch run), (never checkpoints, TensorBoard logs or
locks), with the grid's ``grid.json``, so that ``pporpe report results/NAME`` reports
what is finished. A run already there with the same files is left alone; one that differs is
an error (a grid is not retrained into a committed folder by accident).
"""

from __future__ import annotations

import argparse
import filecmp
import shutil
import sys
from pathlib import Path

RUN_FILES = ("config.json", "episodes.csv", "evaluation.json", "done.json")
"""A finished run's small files: what is committed of it."""
OPTIONAL_FILES = ("updates.csv",)
"""Small files a finished run has only for some learners (a batch run's per-update log)."""


def finished_runs(work: Path) -> list[Path]:
    """The run folders under ``work`` (``TASK/METHOD/seedN``) that hold ``done.json``."""
    return sorted(p.parent for p in work.glob("*/*/seed*/done.json"))


def collect(work: Path, results: Path) -> tuple[int, int]:
    """Copy the finished runs' files; return (runs copied now, runs already there)."""
    copied = kept = 0
    for run in finished_runs(work):
        target = results / run.relative_to(work)
        names = [*RUN_FILES, *(n for n in OPTIONAL_FILES if (run / n).exists())]
        present = [target / name for name in names if (target / name).exists()]
        if present:
            changed = [p.name for p in present if not filecmp.cmp(p, run / p.name, shallow=False)]
            if changed:
                raise SystemExit(f"{target}: {', '.join(changed)} differ from {run}; not copied")
            if len(present) == len(names):
                kept += 1
                continue
        target.mkdir(parents=True, exist_ok=True)
        for name in names:
            shutil.copyfile(run / name, target / name)
        copied += 1
    if copied:
        shutil.copyfile(work / "grid.json", results / "grid.json")
    return copied, kept


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path, help="the grid's working folder (reproduce --out)")
    parser.add_argument("results", type=Path, help="the committed results folder")
    args = parser.parse_args()
    if not (args.work / "grid.json").is_file():
        parser.error(f"work: {args.work} holds no grid.json (not a grid's folder)")
    copied, kept = collect(args.work, args.results)
    print(f"{copied} finished runs copied into {args.results}, {kept} already there")


if __name__ == "__main__":
    sys.exit(main())
