"""Grid runs packed into jobs: which runs share a trainer, and how many jobs."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...runs.folder import config_json
from ...runs.kinds import kind_of

__all__ = ["POPULATIONS", "POPULATION_KINDS", "Job", "plan_jobs"]

POPULATIONS = "populations"
"""The folder of a grid's output folder that holds the home folders of its populations."""

POPULATION_KINDS = ("online", "batch")
"""Learner kinds whose trainer holds several runs at once (a population); runs of the
other kinds get a trainer each."""


@dataclass(frozen=True)
class Job:
    """Runs of one task and network shape that one worker trains through one trainer."""

    home: str
    """Folder of the job's ``population.json``."""
    runs: list[tuple[str, dict[str, Any]]]
    """``(run_dir, config.json content)`` in queue order."""
    population: int
    """Slots of the trainer: runs trained at once."""


def plan_jobs(
    runs: list[tuple[Path, Any]], out_dir: Path, population: int, workers: int
) -> list[Job]:
    """Pack runs into jobs: runs that can share a trainer (same kind, task and network
    shape: :meth:`~pporpe.runs.kinds.LearnerKind.pack_key`) form a queue; a queue is split
    into as many jobs as it takes to keep ``workers`` busy (at most one per run), and each
    job trains up to ``population`` runs at once, refilling a slot when a run finishes.
    The packing depends only on the spec, ``population``, ``workers`` and which runs are
    unfinished."""
    groups: dict[Any, list[tuple[Path, Any]]] = {}
    for run_dir, cfg in runs:
        kind = kind_of(cfg)
        groups.setdefault((kind.name, kind.pack_key(cfg)), []).append((run_dir, cfg))
    total = sum(len(g) for g in groups.values())
    jobs: list[Job] = []
    for members in groups.values():
        kind = kind_of(members[0][1])
        cap = population if kind.name in POPULATION_KINDS else 1
        n_jobs = max(1, round(workers * len(members) / total)) if total else 1
        if cap == 1:
            n_jobs = len(members)
        n_jobs = min(n_jobs, len(members))
        size = -(-len(members) // n_jobs)
        for j in range(0, len(members), size):
            chunk = members[j : j + size]
            home = chunk[0][0] if len(chunk) == 1 else out_dir / POPULATIONS / _job_name(chunk)
            jobs.append(
                Job(
                    str(home),
                    [(str(d), config_json(kind, c)) for d, c in chunk],
                    min(cap, len(chunk)),
                )
            )
    return jobs


def _job_name(chunk: list[tuple[Path, Any]]) -> str:
    first, last = chunk[0][0], chunk[-1][0]
    return f"{first.parent.parent.name}-{len(chunk)}runs-{first.parent.name}-{first.name}-" + (
        f"{last.parent.name}-{last.name}"
    )
