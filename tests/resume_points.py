"""Where a stopped run's resume starts, and a check that it started there.

A run resumes from the most advanced checkpoint that holds it: its own ``checkpoint.pt`` or
its population's (a member of ``populations/<home>/checkpoint.pt``). The checkpoint's
records are the resume point; a resumed run keeps them as they are, wall times included,
while a run started over from nothing writes the same numbers (the runs are deterministic)
but new wall times. So a resumed run whose first records carry the checkpoint's wall times
resumed from it, and did not train those episodes again.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pporpe.runs.folder import load_checkpoint
from pporpe.runs.logger import read_records


def checkpointed_records(out: Path) -> dict[Path, list[dict[str, Any]]]:
    """Per run folder under ``out`` that has no ``done.json``: the records of the most
    advanced checkpoint holding it (read before the resume; checkpoints only move forward,
    so one read while the run was still training is a prefix of where it resumes)."""
    found: dict[Path, list[dict[str, Any]]] = {}

    def offer(run: Path, records: list[dict[str, Any]]) -> None:
        if not (run / "done.json").exists() and len(records) >= len(found.get(run, [])):
            found[run] = list(records)

    for path in sorted(out.rglob("checkpoint.pt")):
        state = load_checkpoint(path.parent)
        if "members" in state:
            for name, member in state["members"].items():
                offer((path.parent / name).resolve(), member["records"])
        else:
            offer(path.parent.resolve(), state["records"])
    return found


def resume_problems(saved: dict[Path, list[dict[str, Any]]]) -> list[str]:
    """How the runs of ``saved`` (:func:`checkpointed_records`, before the resume) fail to
    have resumed from their checkpoints: none saved more than zero records (no resume point
    to test), or a run's first records are not the checkpoint's very rows."""
    if not any(saved.values()):
        return ["no unfinished run had a checkpoint with records: nothing resumed"]
    problems = []
    for run, records in saved.items():
        got = [r.wall_time for r in read_records(run / "episodes.csv")[: len(records)]]
        if got != [float(r["wall_time"]) for r in records]:
            problems.append(f"{run} did not resume from its checkpoint at {len(records)} records")
    return problems
