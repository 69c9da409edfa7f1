"""One run in a slot of the run loop: its records, log sink, clock, progress bar and
checkpoint content (:class:`ActiveRun`).

:mod:`.loop` keeps one per busy slot: it resumes the run's state from a checkpoint, adds
each unit of work's episodes and update to ``episodes.csv``, ``updates.csv`` and
TensorBoard (:class:`~pporpe.runs.logger.RunLogger`), and writes the run's own
``checkpoint.pt`` after a finiteness check.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from ..text import fixed
from .folder import CHECKPOINT, save_checkpoint
from .kinds import LearnerKind, NonFiniteError, Progress, Trainer
from .logger import EpisodeRecord, LoggedUpdate, RunLogger

__all__ = ["ActiveRun"]


class ActiveRun:
    """One run in a slot: its folder, records, log sink, clock and progress bar."""

    def __init__(self, kind: LearnerKind, cfg: Any, run: Path, bar: bool) -> None:
        self.kind, self.cfg, self.run = kind, cfg, run
        self.records: list[EpisodeRecord] = []
        self.updates: list[LoggedUpdate] = []
        self.first_update = 0
        """Index of :attr:`updates`' first entry (not 0 after a resume from a checkpoint
        written before updates were logged)."""
        self.wall_offset = 0.0
        self.excluded = 0.0
        self.cpu_offset = 0.0
        """CPU seconds of training of earlier segments (0 from a checkpoint without them)."""
        self.cpu = 0.0
        """CPU seconds of training in this segment (:meth:`.loop._Queue.step` adds each share)."""
        self.cpu_since = 0
        """The unit of work from which :meth:`cpu_time` counts: 0, or where a run resumed
        from a checkpoint written before pporpe recorded CPU time."""
        self.last: dict[str, float] = {}
        self.resumed_from = 0
        self.logger = RunLogger(run)
        self.t_start = time.perf_counter()
        self.bar: Any = None
        self.want_bar = bar
        """Whether the run shows progress bars (of its training and its test episodes)."""

    def resume(self, state: dict[str, Any] | None, trainer: Trainer, slot: int) -> None:
        if state is not None:
            self.records = [EpisodeRecord.from_row(r) for r in state["records"]]
            self.updates = [LoggedUpdate.from_row(r) for r in state.get("updates", [])]
            self.wall_offset = float(state["wall_time"])
            self.cpu_offset = float(state.get("cpu_time", 0.0))
        self.resumed_from = trainer.counters(slot)["chunks"]
        if state is not None:
            recorded = "cpu_time" in state
            self.cpu_since = int(state.get("cpu_time_since", 0)) if recorded else self.resumed_from
        if self.updates or state is None:
            self.first_update = self.updates[0].update if self.updates else 0
        else:
            self.first_update = self.resumed_from
        self.t_start = time.perf_counter()
        if self.want_bar:
            from tqdm import tqdm

            total, unit = self.kind.budget(self.cfg)
            self.bar = tqdm(
                total=total,
                initial=trainer.bar_position(slot),
                desc=self.kind.description(self.cfg),
                unit=unit,
                dynamic_ncols=True,
            )

    def train_time(self) -> float:
        return self.wall_offset + (time.perf_counter() - self.t_start) - self.excluded

    def cpu_time(self) -> float:
        return self.cpu_offset + self.cpu

    def add(self, report: Progress) -> list[EpisodeRecord]:
        now = self.train_time()
        new = []
        for ep in report.episodes:
            rec = EpisodeRecord(
                episode=len(self.records),
                total_steps=ep.total_steps,
                ret=ep.ret,
                length=ep.length,
                wall_time=now,
                diagnostics=ep.diagnostics,
            )
            self.records.append(rec)
            self.logger.episode(rec)
            new.append(rec)
        if report.scalars:
            self.last = dict(report.scalars)
            self.logger.scalars("update", self.last, report.total_steps)
            index = self.first_update + len(self.updates)
            self.updates.append(LoggedUpdate(index, report.total_steps, self.last, now))
        if self.bar is not None:
            self.bar.update(report.bar_advance)
            if self.records:  # the last episode by its number from 1, as the bar counts
                self.bar.set_postfix(ep=len(self.records), ret=fixed(self.records[-1].ret, 1))
        return new

    def state(self, trainer: Trainer, slot: int) -> dict[str, Any]:
        """The run's checkpoint content (after a finiteness check)."""
        if not trainer.parameters_finite(slot):
            steps = trainer.counters(slot)["total_steps"]
            raise NonFiniteError(
                f"non-finite parameter at episode {len(self.records)}, step {steps}; "
                "the last good checkpoint is kept"
            )
        state = trainer.state(slot)
        state["records"] = [r.row() for r in self.records]  # flat, as always
        if self.updates:
            state["updates"] = [u.row() for u in self.updates]
        state["wall_time"] = self.train_time()
        state["cpu_time"] = self.cpu_time()
        state["cpu_time_since"] = self.cpu_since
        return state

    def checkpoint(self, trainer: Trainer, slot: int) -> None:
        """Write the run's own checkpoint and records."""
        save_checkpoint(self.run / CHECKPOINT, self.state(trainer, slot))
        self.write_logs()

    def write_logs(self) -> None:
        """Rewrite ``episodes.csv`` (and ``updates.csv``) from the records."""
        self.logger.write_records(self.records)
        self.logger.write_updates(self.updates)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.logger.close()
