"""When the run loop writes a checkpoint while runs train: by count and by time.

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
"""

from __future__ import annotations

import time
from collections.abc import Callable

__all__ = ["CHECKPOINT_WITHIN_S", "CheckpointClock"]

CHECKPOINT_WITHIN_S = 120.0
"""The longest wait, in seconds, between two checkpoints of a busy run (the first of a call
comes after a quarter of it, the second half of it later)."""


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
