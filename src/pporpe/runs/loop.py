"""The one run loop: every learner kind trains, checkpoints, resumes and evaluates here.

:func:`run_queue` trains a queue of runs of one learner kind through one trainer with up
to K slots (K = 1 for a single run; the online learner trains K runs in lockstep), and
:func:`train` is the single-run case. For every run it

1. checks the task name and writes ``config.json`` before any work (or checks that the
   folder holds the same run; a complete run is skipped);
2. starts the run in a free slot, fresh or from its ``checkpoint.pt``;
3. advances all slots together, logging every episode through the one sink
   (:class:`~pporpe.runs.logger.RunLogger`) and checkpointing at the trainer's cadence
   after a finiteness check;
4. when its budget is spent: a last checkpoint, test episodes of the deterministic policy
   (``evaluation.json``), then ``done.json``; the slot takes the next run of the queue.

A run that fails alone (a non-finite value) leaves its message in ``error.txt`` and the
others go on. With several slots, the loop keeps the population's checkpoint in a home
folder: every member's state at one step together with the packing (which run is in which
slot, what is still queued; run folders named relative to the home folder), in one atomic
file, and ``population.json`` as a readable copy of the packing. A restarted queue, also
from an output folder moved or copied elsewhere, resumes with the same packing at the same
step and produces the same numbers as an uninterrupted one; each run's own
``checkpoint.pt`` is written when it finishes.
When the queue is empty and at most half the slots are busy, the trainer is compacted to
the busy runs (idle slots of a population would still cost compute). A killed run loses
at most the work since its last checkpoint; records never have a gap or a duplicate.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..envs import make_env
from ..evaluation import EVAL_SEED_OFFSET, EvalResult, evaluate_policy, load_evaluation
from ..io import atomic_write_json, atomic_write_text
from ..policy import Policy
from .folder import CHECKPOINT, config_json, load_checkpoint, open_run_dir, read_config
from .folder import save_checkpoint as save_checkpoint
from .kinds import LearnerKind, NonFiniteError, Progress, Trainer, kind_of
from .logger import EpisodeRecord, RunLogger, read_records

__all__ = ["NonFiniteError", "RunResult", "load_policy", "run_queue", "train"]

POPULATION_FILE = "population.json"


@dataclass
class RunResult:
    """What the loop produced for one run."""

    run_dir: Path
    """The run folder."""
    records: list[EpisodeRecord]
    """Every training episode."""
    evaluation: EvalResult | None
    """Test-episode summary, if ``eval_episodes`` > 0."""
    resumed_from: int
    """Units of work (episodes of the online learner, updates of the batch learner) done
    when this call started (0 for a fresh run)."""
    total_steps: int = 0
    """Environment steps done in all."""
    train_time: float = 0.0
    """Seconds of training over all segments (acting, learning, logging, checkpoints; not
    evaluation or callbacks)."""
    chunks: int = 0
    """Units of work done in all."""
    last_scalars: dict[str, float] = field(default_factory=dict)
    """The last extra scalars the trainer reported (a batch update's statistics)."""
    error: str | None = None
    """Why the run failed alone (also in its ``error.txt``), or None."""


OnChunk = Callable[[Trainer, Progress, float], None]
"""Called after each unit of work of a run with the trainer, the run's report and its
training seconds so far; its own time is not counted as training time."""


def _finished_result(run: Path) -> RunResult:
    records = read_records(run / "episodes.csv")
    done = json.loads((run / "done.json").read_text())
    chunks = int(done.get("chunks", done.get("updates", done.get("episodes", len(records)))))
    return RunResult(
        run,
        records,
        load_evaluation(run),
        chunks,
        int(done.get("total_steps", 0)),
        float(done.get("train_time", 0.0)),
        chunks,
    )


class _Run:
    """One run in a slot: its folder, records, log sink, clock and progress bar."""

    def __init__(self, kind: LearnerKind, cfg: Any, run: Path, bar: bool) -> None:
        self.kind, self.cfg, self.run = kind, cfg, run
        self.records: list[EpisodeRecord] = []
        self.wall_offset = 0.0
        self.excluded = 0.0
        self.last: dict[str, float] = {}
        self.resumed_from = 0
        self.logger = RunLogger(run)
        self.t_start = time.perf_counter()
        self.bar: Any = None
        self._want_bar = bar

    def resume(self, state: dict[str, Any] | None, trainer: Trainer, slot: int) -> None:
        if state is not None:
            self.records = [EpisodeRecord(**r) for r in state["records"]]
            self.wall_offset = float(state["wall_time"])
        self.resumed_from = trainer.counters(slot)["chunks"]
        self.t_start = time.perf_counter()
        if self._want_bar:
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

    def add(self, report: Progress) -> list[EpisodeRecord]:
        now = self.train_time()
        new = []
        for ep in report.episodes:
            rec = EpisodeRecord(episode=len(self.records), **ep.__dict__, wall_time=now)
            self.records.append(rec)
            self.logger.episode(rec)
            new.append(rec)
        if report.scalars:
            self.last = dict(report.scalars)
            self.logger.scalars("update", self.last, report.total_steps)
        if self.bar is not None:
            self.bar.update(report.bar_advance)
            if self.records:
                self.bar.set_postfix(ep=len(self.records) - 1, ret=f"{self.records[-1].ret:.1f}")
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
        state["records"] = [r.__dict__ for r in self.records]
        state["wall_time"] = self.train_time()
        return state

    def checkpoint(self, trainer: Trainer, slot: int) -> None:
        """Write the run's own checkpoint and records."""
        save_checkpoint(self.run / CHECKPOINT, self.state(trainer, slot))
        self.logger.write_records(self.records)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.logger.close()


def run_queue(
    runs: Sequence[tuple[Any, str | Path]],
    capacity: int = 1,
    home: str | Path | None = None,
    progress: bool = False,
    on_episode: Callable[[EpisodeRecord], None] | None = None,
    on_chunk: OnChunk | None = None,
    checkpoint_seconds: float = 0.0,
) -> list[RunResult]:
    """Train every ``(config, run_dir)`` of ``runs`` (one learner kind, one task and network
    shape) through one trainer with up to ``capacity`` slots, refilling a slot when its run
    finishes. Returns one result per run, in order.

    ``home`` (required when ``capacity`` > 1) holds ``population.json``. A due checkpoint
    is written at most every ``checkpoint_seconds`` (0: whenever due); every run also gets
    one when it finishes. ``on_episode`` is called after every episode, ``on_chunk`` after
    every unit of work of a run. Exceptions other than a run's own failure stop the queue
    (each run keeps its last checkpoint).
    """
    if not runs:
        return []
    if capacity > 1 and home is None:
        raise ValueError("run_queue needs a home folder for population.json when capacity > 1")
    cfgs = [cfg for cfg, _ in runs]
    kind = kind_of(cfgs[0])
    keys = {kind.pack_key(c) for c in cfgs}
    if any(kind_of(c) is not kind for c in cfgs) or len(keys) != 1:
        raise ValueError("run_queue takes runs of one learner kind, task and network shape")
    for env in dict.fromkeys(cfg.env for cfg in cfgs):
        # bad names and spaces (e.g. discrete actions) fail before any folder is written
        make_env(env).close()
    dirs = [Path(d) for _, d in runs]
    results: dict[int, RunResult] = {}
    pending: list[int] = []
    for i, (cfg, run) in enumerate(zip(cfgs, dirs, strict=True)):
        _, done = open_run_dir(run, config_json(kind, cfg))
        if done:
            results[i] = _finished_result(run)
        else:
            pending.append(i)
    if not pending:
        return [results[i] for i in range(len(runs))]
    pop_file = Path(home) / POPULATION_FILE if home is not None and capacity > 1 else None
    capacity = max(1, min(capacity, len(pending)))

    torch.set_num_threads(1)
    queue: deque[int] = deque(pending)
    slots: list[int | None] = [None] * capacity
    # a population's checkpoint: every member at one step, with the packing, in one file
    pop_ckpt = pop_file.with_name(CHECKPOINT) if pop_file is not None else None
    members: dict[str, dict[str, Any]] = {}
    # The packing names run folders relative to the home folder, so that an output folder
    # moved or copied elsewhere (another checkout, another machine) resumes from its
    # population checkpoint; pporpe 0.4.0 and earlier named them by their full paths.
    names = [os.path.relpath(d, home) if home is not None else str(d) for d in dirs]
    if pop_ckpt is not None and pop_ckpt.is_file():
        saved = load_checkpoint(pop_ckpt.parent)
        spelling = next(  # the same job (the same runs), in either spelling
            (s for s in (names, [str(d) for d in dirs]) if saved.get("runs") == s), None
        )
        if spelling is not None:
            by_dir = {name: i for i, name in enumerate(spelling)}
            slots = [by_dir.get(d) if d else None for d in saved["slots"]]
            slots = [i if i in pending else None for i in slots]
            queue = deque(by_dir[d] for d in saved["queue"] if by_dir[d] in pending)
            capacity = len(slots)
            members = {names[by_dir[k]]: v for k, v in saved["members"].items() if k in by_dir}
    trainer = kind.make_trainer(cfgs[pending[0]], capacity)
    books: dict[int, _Run] = {}

    def packing() -> dict[str, Any]:
        return {
            "runs": names,
            "slots": [names[i] if i is not None else None for i in slots],
            "queue": [names[i] for i in queue],
        }

    def write_population() -> None:
        if pop_file is not None:
            atomic_write_json(pop_file, packing())  # a readable mirror of the packing

    def checkpoint_all() -> None:
        """Every busy run's checkpoint: in its folder (one run), or all of them in the
        population's one file (so that they are always from the same step)."""
        if pop_ckpt is None:
            for slot, book in list(books.items()):
                try:
                    book.checkpoint(trainer, slot)
                except NonFiniteError as exc:
                    fail(slot, str(exc))
            return
        states = {}
        for slot, book in list(books.items()):
            i = slots[slot]
            assert i is not None
            try:
                states[names[i]] = book.state(trainer, slot)
            except NonFiniteError as exc:
                fail(slot, str(exc))
        save_checkpoint(pop_ckpt, {**packing(), "members": states})
        for book in books.values():
            book.logger.write_records(book.records)

    def begin(slot: int, i: int) -> None:
        run = dirs[i]
        state = members.pop(names[i], None)
        if state is None and (run / CHECKPOINT).exists():
            state = load_checkpoint(run)
        book = _Run(kind, cfgs[i], run, bar=progress and capacity == 1)
        trainer.start(slot, cfgs[i], state)
        book.resume(state, trainer, slot)
        (run / "error.txt").unlink(missing_ok=True)
        books[slot] = book
        slots[slot] = i

    def fill(slot: int) -> None:
        slots[slot] = None
        if queue:
            begin(slot, queue.popleft())

    def fail(slot: int, message: str) -> None:
        i, book = slots[slot], books.pop(slot)
        assert i is not None
        atomic_write_text(book.run / "error.txt", message + "\n")
        if pop_ckpt is not None and pop_ckpt.is_file():  # its last good state, in its folder
            last = load_checkpoint(pop_ckpt.parent)["members"].get(names[i])
            if last is not None:
                save_checkpoint(book.run / CHECKPOINT, last)
        book.close()
        results[i] = RunResult(
            book.run, book.records, None, book.resumed_from, error=message, chunks=0
        )
        trainer.stop(slot)
        fill(slot)

    def finish(slot: int) -> None:
        """Evaluate and complete the run in ``slot`` (its last checkpoint is written)."""
        try:
            books[slot].checkpoint(trainer, slot)
        except NonFiniteError as exc:
            fail(slot, str(exc))
            return
        i, book = slots[slot], books.pop(slot)
        assert i is not None
        cfg = cfgs[i]
        total_time = book.train_time()
        counters = trainer.counters(slot)
        act = trainer.policy(slot)
        trainer.stop(slot)
        book.close()
        evaluation = None
        if cfg.eval_episodes > 0:
            evaluation = evaluate_policy(
                act, cfg.env, cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET
            )
            atomic_write_json(book.run / "evaluation.json", evaluation.to_dict())
        done = {"episodes": len(book.records), **counters, "train_time": total_time}
        atomic_write_json(book.run / "done.json", done)
        results[i] = RunResult(
            book.run,
            book.records,
            evaluation,
            book.resumed_from,
            counters["total_steps"],
            total_time,
            counters["chunks"],
            book.last,
        )
        fill(slot)

    last_checkpoint = time.perf_counter()
    try:
        for slot in range(capacity):
            assigned = slots[slot]
            if assigned is not None:
                begin(slot, assigned)
            else:
                fill(slot)
        write_population()
        while books:
            # a run resumed with its budget spent (stopped after its last checkpoint, e.g.
            # during evaluation) is completed without another unit of work
            spent = [slot for slot in books if trainer.finished(slot)]
            if spent:
                for slot in spent:
                    finish(slot)
                write_population()
                continue
            reports = trainer.advance()
            due = False
            for slot, report in reports.items():
                book = books[slot]
                new = book.add(report)
                t_cb = time.perf_counter()
                if on_episode is not None:
                    for rec in new:
                        on_episode(rec)
                if on_chunk is not None:
                    on_chunk(trainer, report, book.train_time())
                book.excluded += time.perf_counter() - t_cb
                due = due or report.checkpoint_due
            changed = False
            for slot, report in reports.items():
                if report.error is not None:
                    fail(slot, report.error)
                    changed = True
                elif trainer.finished(slot):
                    finish(slot)
                    changed = True
            busy = [slot for slot, i in enumerate(slots) if i is not None]
            if len(slots) > 1 and not queue and busy and len(busy) <= len(slots) // 2:
                # the idle slots would still cost compute: move the runs to a smaller trainer
                trainer.compact(busy)
                moved = {j: books[slot] for j, slot in enumerate(busy)}
                books.clear()
                books.update(moved)
                slots[:] = [slots[slot] for slot in busy]
                changed = True
            if changed and pop_file is not None and books:
                # the packing changed (a run ended, its slot was refilled, the trainer shrank):
                # checkpoint every run at this step, so that a resumed queue continues with
                # the same packing at the same step, bit for bit
                due, last_checkpoint = True, -math.inf
            if due and time.perf_counter() - last_checkpoint >= checkpoint_seconds:
                checkpoint_all()
                last_checkpoint = time.perf_counter()
                changed = True
            if changed:
                write_population()
    finally:
        for book in books.values():
            book.close()
        trainer.close()
    return [results[i] for i in range(len(runs))]


def train(
    cfg: Any,
    run_dir: str | Path,
    progress: bool = True,
    on_episode: Callable[[EpisodeRecord], None] | None = None,
    on_chunk: OnChunk | None = None,
) -> RunResult:
    """Train one run of any learner kind as configured, writing everything into
    ``run_dir``; resumes from its checkpoint when one exists for the same config.

    Raises :class:`NonFiniteError` if the run failed on a non-finite value (its last good
    checkpoint is kept).
    """
    (result,) = run_queue(
        [(cfg, run_dir)], progress=progress, on_episode=on_episode, on_chunk=on_chunk
    )
    if result.error is not None:
        raise NonFiniteError(result.error)
    return result


def load_policy(run_dir: str | Path) -> Policy:
    """The trained policy of a run folder, from its ``config.json`` and latest checkpoint.

    Works for every learner kind (the online learner, batch PPO with its observation
    normalisation) and for folders written by pporpe 0.1.0. The result acts with
    ``policy.act(obs, deterministic=True)`` (or ``policy(obs)``) and carries the run's
    configuration as ``policy.config``::

        policy = pporpe.load_policy("runs/x")
        action = policy.act(obs)

    Raises:
        ValueError: not a run folder, or a corrupt config or checkpoint.
    """
    kind, cfg = read_config(run_dir)
    return kind.load_policy(cfg, load_checkpoint(run_dir))
