"""A grid's pre-registered tasks: read ``preregistration.json``, say whether each verdict is
pending, and give the view of the results the verdict was pre-registered against.

A pre-registration fixes, in a commit made before the runs it covers, how many seeds a task
gets and how its claims are judged, so that its verdict is read once, when every run is in,
not whenever a verdict first appears (optional stopping). The grid folder holds the human
document (``preregistration.md``) and a small record of it that the report reads::

    {"document": "preregistration.md",
     "commit": "<the 40-hex commit that added the document>",
     "tasks": {"ant": {"seeds": 25, "seeds_before": 10}}}

``seeds``: seeds per method once complete (0 .. seeds-1); ``seeds_before``: the seeds
already finished when it was written (0 .. seeds_before-1), the result that stands until the
pre-registered one is read.
"""

from __future__ import annotations

import dataclasses
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .results import Cell

__all__ = [
    "PREREGISTRATION_FILE",
    "Preregistration",
    "before_cells",
    "load_preregistrations",
    "pending_tasks",
    "preregistration_lines",
]

PREREGISTRATION_FILE = "preregistration.json"
"""The record of a grid folder's pre-registrations, beside its ``grid.json``."""

MAX_SEEDS = 10_000
"""The most seeds per method a pre-registration may name."""

_COMMIT = re.compile(r"[0-9a-f]{40}")


@dataclass(frozen=True)
class Preregistration:
    """One pre-registered task of a grid."""

    task: str
    """The task (its name in the grid)."""
    seeds: int
    """Seeds per method when complete: 0 .. seeds-1."""
    seeds_before: int
    """Seeds per method finished before the pre-registration: 0 .. seeds_before-1."""
    document: str
    """The pre-registration's document, a file name in the grid folder."""
    commit: str
    """The commit that added the document (40 hex digits)."""

    def __post_init__(self) -> None:
        if not (isinstance(self.seeds, int) and 1 <= self.seeds <= MAX_SEEDS):
            raise ValueError(f"seeds must be an int in [1, {MAX_SEEDS}]; got {self.seeds!r}")
        if not (isinstance(self.seeds_before, int) and 0 <= self.seeds_before < self.seeds):
            raise ValueError(
                f"seeds_before must be an int in [0, seeds); got {self.seeds_before!r}"
            )
        if not (isinstance(self.commit, str) and _COMMIT.fullmatch(self.commit)):
            raise ValueError(f"commit must be 40 lowercase hex digits; got {self.commit!r}")
        name = self.document
        if not (isinstance(name, str) and re.fullmatch(r"[\w.-]+\.md", name)):
            raise ValueError(f"document must be a .md file name in the folder; got {name!r}")

    @property
    def short_commit(self) -> str:
        """The commit's first 7 digits."""
        return self.commit[:7]


def load_preregistrations(root: Path) -> dict[str, Preregistration]:
    """The pre-registered tasks of the grid folder ``root`` (empty if it has none). A
    malformed record is a ValueError naming the file and the field."""
    path = Path(root) / PREREGISTRATION_FILE
    if not path.is_file():
        return {}
    if path.stat().st_size > 64 * 1024:
        raise ValueError(f"{path}: larger than 64 KiB; not a pre-registration record")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from None
    if not (isinstance(data, dict) and set(data) == {"document", "commit", "tasks"}):
        raise ValueError(f"{path}: must hold exactly the fields document, commit and tasks")
    tasks = data["tasks"]
    if not (isinstance(tasks, dict) and tasks):
        raise ValueError(f"{path}: field 'tasks' must map task names to their seeds")
    out = {}
    for task, spec in tasks.items():
        if not (isinstance(spec, dict) and set(spec) == {"seeds", "seeds_before"}):
            raise ValueError(f"{path}: field 'tasks.{task}' must hold seeds and seeds_before")
        try:
            out[task] = Preregistration(task, spec["seeds"], spec["seeds_before"],
                                        data["document"], data["commit"])  # fmt: skip
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    return out


def _below(d: dict[int, Any], n: int) -> dict[int, Any]:
    """The entries of a per-seed dict whose seed is below ``n``."""
    return {s: v for s, v in d.items() if s < n}


def _runs(cells: list[Cell], reg: Preregistration) -> int:
    """The runs the pre-registration asks for: its seeds times the task's methods."""
    return reg.seeds * len({c.method for c in cells if c.env == reg.task})


def pending_tasks(cells: list[Cell], regs: dict[str, Preregistration]) -> dict[str, str]:
    """Per pre-registered task whose runs are not all in: ``36 of 75 runs``."""
    pending = {}
    for task, reg in regs.items():
        done = sum(1 for c in cells if c.env == task for s in c.curves if s < reg.seeds)
        if done < _runs(cells, reg):
            pending[task] = f"{done} of {_runs(cells, reg)} runs"
    return pending


def preregistration_lines(cells: list[Cell], regs: dict[str, Preregistration]) -> list[str]:
    """The report's "What ran" lines of the pre-registered tasks: where and when each was
    pre-registered, and whether its verdict is the pre-registered one or still pending."""
    pending = pending_tasks(cells, regs)
    lines = []
    for task, reg in regs.items():
        head = (
            f"- {task}: pre-registered in commit {reg.short_commit} ({reg.document}), before "
            f"any run of seed {reg.seeds_before} or more: {reg.seeds} seeds per method, the "
            "verdict read once, when all its runs are in"
        )
        if task in pending:
            lines.append(
                f"{head}; pending ({pending[task]} finished): until then this report compares "
                "the methods on the seeds all have finished, an interim look, not the verdict"
            )
        else:
            lines.append(f"{head}; all {_runs(cells, reg)} runs are in: its verdict is below")
    return lines


def before_cells(cells: list[Cell], regs: dict[str, Preregistration]) -> list[Cell]:
    """``cells`` with each task whose pre-registered verdict is pending cut back to the seeds
    finished before it was pre-registered: the result that stands until then."""
    pending = pending_tasks(cells, regs)
    out = []
    for c in cells:
        if c.env not in pending:
            out.append(c)
            continue
        n = regs[c.env].seeds_before
        out.append(dataclasses.replace(c, scores=_below(c.scores, n), curves=_below(c.curves, n),
                                       missing=[s for s in c.missing if s < n]))  # fmt: skip
    return out
