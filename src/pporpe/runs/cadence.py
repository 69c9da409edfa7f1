"""When the run loop writes to disk while runs train: checkpoints by count and by time, and
the live progress a grid's bar reads.

A checkpoint is due when a run's count of units of work asks for one (``checkpoint_every``
episodes of the online learner, updates of the batch learner), or by time whatever the
count: :data:`CHECKPOINT_WITHIN_S` / 4 seconds into a call of the loop (30 s), half of it
after that (1 minute), then every :data:`CHECKPOINT_WITHIN_S` seconds (2 minutes). A kill
therefore loses at most about half of a call's work and at most 2 minutes of it, however
slow the episodes or updates are (the time is looked at after every unit of work: an
environment step of the online learner, mid-episode included, an update of the batch
learner); a population that checkpoints at most once a minute by count (a grid's
``--checkpoint-seconds``) still keeps the work of its first minute. The time rule only
decides *when* a checkpoint is written: a checkpoint reads the runs' state and changes
nothing in it, so the numbers of a run are the same with any cadence, and a run resumed
from any of its checkpoints continues to the same records.

:class:`LiveProgress` writes ``progress.json`` into every busy run's folder every few
seconds (episodes, steps and the recent episode lengths), which the grid's progress bar
reads between two checkpoints; it is removed when the run finishes or fails.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..run_files import read_json

__all__ = [
    "CHECKPOINT_WITHIN_S",
    "LIVE_FILE",
    "LIVE_SECONDS",
    "RECENT_EPISODES",
    "CheckpointClock",
    "LiveProgress",
    "read_live",
]

CHECKPOINT_WITHIN_S = 120.0
"""The longest wait, in seconds, between two checkpoints of a busy run (the first of a call
comes after a quarter of it, the second half of it later)."""

LIVE_FILE = "progress.json"
"""The live progress of a run in training, in its folder (removed when it finishes)."""

LIVE_SECONDS = 5.0
"""Seconds between two writes of the live progress (a grid's bar asks for it)."""

RECENT_EPISODES = 10
"""Logged episodes whose mean length stands for the length of the episodes to come."""


class CheckpointClock:
    """Whether a checkpoint is due after a unit of work (see the module docstring).

    ``least``: a checkpoint asked for by count comes at least this many seconds after the
    last one (0: whenever asked; a population's state is megabytes, grids pass 60).
    ``within``: the longest wait by time (``math.inf``: by count only; 0: after every unit
    of work). ``clock``: seconds, monotonic (a stand-in in tests).
    """

    def __init__(
        self, least: float, within: float, clock: Callable[[], float] = time.perf_counter
    ) -> None:
        if not (least >= 0.0 and within >= 0.0):
            raise ValueError(f"checkpoint seconds must be >= 0; got least={least}, within={within}")
        self.least, self.within, self.clock = least, within, clock
        self.last = clock()
        self.wait = within / 4.0
        """Seconds after the last checkpoint when one is due by time."""

    def due(self, by_count: bool) -> bool:
        """Whether to write a checkpoint now, given whether a run's count asks for one."""
        elapsed = self.clock() - self.last
        return elapsed >= self.wait or (by_count and elapsed >= self.least)

    def written(self) -> None:
        """A checkpoint was written now: the next one by time after twice the last wait,
        at most ``within``."""
        self.last = self.clock()
        self.wait = min(2.0 * self.wait, self.within)


def _write_quietly(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` as JSON through a temporary file and a rename (no fsync: the file is
    a hint, rewritten every few seconds), never raising for a full or vanished disk, never
    through a symbolic link."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        if path.is_symlink():
            return
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0)
        with os.fdopen(os.open(tmp, flags, 0o666), "w") as fh:
            fh.write(json.dumps(data))
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)


class LiveProgress:
    """Writes each busy run's ``progress.json`` at most every ``seconds`` (None: never)."""

    def __init__(self, seconds: float | None, clock: Callable[[], float] = time.perf_counter):
        self.seconds, self.clock = seconds, clock
        self.last = -math.inf

    def due(self) -> bool:
        """Whether it is time to write."""
        return self.seconds is not None and self.clock() - self.last >= self.seconds

    def write(self, runs: list[tuple[Path, int, int, list[int]]]) -> None:
        """``(run folder, episodes, environment steps, recent episode lengths)`` of every
        busy run, stamped with the wall clock (a bar ignores files older than itself)."""
        if self.seconds is None:
            return
        now = time.time()
        for run, episodes, steps, lengths in runs:
            data = {"episodes": episodes, "total_steps": steps, "lengths": lengths, "time": now}
            _write_quietly(run / LIVE_FILE, data)
        self.last = self.clock()

    @staticmethod
    def remove(run: Path) -> None:
        """The run finished, failed or stopped: its live progress goes."""
        with contextlib.suppress(OSError):
            (run / LIVE_FILE).unlink(missing_ok=True)


def read_live(run: Path, since: float) -> dict[str, Any] | None:
    """A run's live progress if written at or after the wall time ``since`` (a file from
    an earlier call of the loop may be ahead of the checkpoint the run resumes from), with
    ``episodes`` and ``total_steps`` as ints and ``lengths`` a list of numbers; else None."""
    try:
        data = read_json(run / LIVE_FILE)
        if float(data["time"]) < since:
            return None
        return {
            "episodes": int(data["episodes"]),
            "total_steps": int(data["total_steps"]),
            "lengths": [float(x) for x in data["lengths"]],
        }
    except (ValueError, KeyError, TypeError, OverflowError):
        return None
