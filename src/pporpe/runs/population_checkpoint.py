"""The checkpoint of a queue of runs trained together: every member at one step, and the packing.

A population's members are checkpointed together, in one atomic file in the queue's home
folder, so that they are always from the same step; with them goes the *packing* (which
run is in which slot, which runs are still queued). ``population.json`` beside it is a
readable copy of the packing. Run folders are named relative to the home folder, so an
output folder moved or copied elsewhere resumes from its checkpoint; checkpoints of pporpe
0.4.0 and earlier named them by their full paths, and are still read.

A grid's packing depends on which of its runs are unfinished, so a grid resumed after some
runs finished (or with another filter or worker count) may pack its runs into populations
under new home folders. The runs in flight in an old home's checkpoint keep their states
there: :func:`adopt_orphaned_states` hands each of them to its run folder, and the run
loop resumes a run from the most advanced of its population's state and its own
checkpoint (:func:`progress_of`).

A queue whose runs have all finished deletes its checkpoint (:meth:`PopulationCheckpoint.discard`;
each run keeps its own final one) and keeps ``population.json``; a grid deletes the
checkpoints of old homes whose runs have all finished since (:func:`discard_finished`).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..io import atomic_write_json
from ..run_files import read_json
from .checkpoint_data import check_population_state
from .folder import CHECKPOINT, load_checkpoint, save_checkpoint
from .migrate import packing_names

__all__ = [
    "POPULATION_FILE",
    "Packing",
    "PopulationCheckpoint",
    "adopt_orphaned_states",
    "discard_checkpoint",
    "discard_finished",
    "finished_homes",
    "progress_of",
]

POPULATION_FILE = "population.json"
"""The readable copy of the packing, in the home folder."""


@dataclass
class Packing:
    """Which run (an index into the queue's runs) is in which slot, and which are queued."""

    slots: list[int | None]
    """The run in each slot of the trainer, or None for an idle slot."""
    queue: deque[int] = field(default_factory=deque)
    """The runs still to start, in order."""

    def as_dict(self, names: list[str]) -> dict[str, Any]:
        """The packing with runs by name (``runs``, ``slots``, ``queue``)."""
        return {
            "runs": names,
            "slots": [names[i] if i is not None else None for i in self.slots],
            "queue": [names[i] for i in self.queue],
        }


class PopulationCheckpoint:
    """The population checkpoint of a queue of runs ``dirs`` whose home is ``home``."""

    def __init__(self, home: Path, dirs: list[Path]) -> None:
        self.file = home / CHECKPOINT
        self.mirror = home / POPULATION_FILE
        self.names = [os.path.relpath(d, home) for d in dirs]
        """The runs by name: their folders relative to the home folder."""
        self._full_paths = [str(d) for d in dirs]

    def restore(
        self, pending: list[int]
    ) -> tuple[Packing | None, dict[str, dict[str, Any]]]:
        """What the home's checkpoint holds for this queue: the saved packing (restricted to
        the ``pending`` runs; None when the checkpoint is of another queue of runs, or there
        is none) and the states of this queue's runs by run name (a checkpoint of another
        queue in this home, say of other seeds, still gives the states of the runs both
        queues share)."""
        if not self.file.is_file():
            return None, {}
        saved = load_checkpoint(self.file.parent)
        check_population_state(saved, self.file)
        spelling = packing_names(saved.get("runs"), self.names, self._full_paths)
        if spelling is None:
            ours = {self.names[i] for i in pending}
            return None, {k: v for k, v in saved["members"].items() if k in ours}
        by_dir = {name: i for i, name in enumerate(spelling)}
        slots = [by_dir.get(d) if d else None for d in saved["slots"]]
        packing = Packing(
            [i if i in pending else None for i in slots],
            deque(by_dir[d] for d in saved["queue"] if by_dir[d] in pending),
        )
        members = {self.names[by_dir[k]]: v for k, v in saved["members"].items() if k in by_dir}
        return packing, members

    def save(self, packing: Packing, states: dict[str, dict[str, Any]]) -> None:
        """Every busy member's state at this step, with the packing, in one atomic file."""
        save_checkpoint(self.file, {**packing.as_dict(self.names), "members": states})

    def write_mirror(self, packing: Packing) -> None:
        """``population.json``: the packing, readable."""
        atomic_write_json(self.mirror, packing.as_dict(self.names))

    def discard(self) -> None:
        """Delete the checkpoint (once every run of the queue has finished it holds nothing
        a run needs: each run keeps its own final checkpoint); ``population.json`` stays,
        the last packing."""
        discard_checkpoint(self.file.parent)

    def last_state(self, i: int) -> dict[str, Any] | None:
        """Run ``i``'s state in the last saved checkpoint, if any."""
        if not self.file.is_file():
            return None
        member: dict[str, Any] | None = load_checkpoint(self.file.parent)["members"].get(
            self.names[i]
        )
        return member


def progress_of(state: dict[str, Any]) -> tuple[int, int]:
    """How far a run's saved state has come: its logged episodes, then its logged updates.
    Every learner kind's checkpoint holds both lists, and they only grow, so of two states
    of one run the larger is the later."""
    records, updates = state.get("records"), state.get("updates")
    return (len(records) if isinstance(records, list) else 0,
            len(updates) if isinstance(updates, list) else 0)  # fmt: skip


def adopt_orphaned_states(
    populations: Path, homes: Collection[str | Path], runs: Collection[str | Path]
) -> list[Path]:
    """Give runs the states that populations no longer planned hold for them.

    For each run folder of ``runs``, the most advanced state (:func:`progress_of`) that the
    checkpoint of a population folder under ``populations`` holds, homes of ``homes`` (the
    populations planned now) left out, is written as the run's own ``checkpoint.pt``
    (atomically) where it is ahead of the one there, if any. Nothing is deleted: an old
    population may still be another process's. Returns the runs given a state.

    Every checkpoint read is checked first (:func:`~.folder.load_checkpoint`): one that
    would run code raises ``ValueError`` naming it, before anything is written."""
    if not runs or not populations.is_dir():
        return []
    wanted = {Path(r).resolve(): Path(r) for r in runs}
    planned = {Path(h).resolve() for h in homes}
    best: dict[Path, dict[str, Any]] = {}
    for home in sorted(populations.iterdir()):
        if home.resolve() in planned or not (home / CHECKPOINT).is_file():
            continue
        saved = load_checkpoint(home)
        check_population_state(saved, home / CHECKPOINT, packing=False)
        for name, state in saved["members"].items():
            run = (home / name).resolve()
            if run in wanted and (run not in best or progress_of(state) > progress_of(best[run])):
                best[run] = state
    adopted = []
    for run, state in best.items():
        own = run / CHECKPOINT
        if own.is_file() and progress_of(load_checkpoint(run)) >= progress_of(state):
            continue
        save_checkpoint(own, state)
        adopted.append(wanted[run])
    return adopted


def finished_homes(populations: Path) -> list[Path]:
    """The population folders under ``populations`` that still hold a checkpoint though
    every one of their runs has finished (``done.json`` in its folder; the runs as
    ``population.json`` names them): their checkpoints hold nothing a run needs any more.
    A folder without a readable ``population.json`` is not listed."""
    if not populations.is_dir():
        return []
    found = []
    for home in sorted(populations.iterdir()):
        if not (home / CHECKPOINT).is_file():
            continue
        try:
            runs = read_json(home / POPULATION_FILE)["runs"]
        except (ValueError, KeyError, TypeError):
            continue
        if (
            isinstance(runs, list)
            and runs
            and all(isinstance(r, str) and (home / r / "done.json").is_file() for r in runs)
        ):
            found.append(home)
    return found


def discard_checkpoint(home: Path) -> None:
    """Delete the population checkpoint of ``home``, if any; ``population.json`` stays."""
    (home / CHECKPOINT).unlink(missing_ok=True)


def discard_finished(populations: Path) -> list[Path]:
    """Delete the checkpoints of :func:`finished_homes` (left by a grid packed differently
    before: their runs went on in other populations); return those homes."""
    finished = finished_homes(populations)
    for home in finished:
        discard_checkpoint(home)
    return finished
