"""The one run loop: every learner kind trains, checkpoints, resumes and evaluates here.

:func:`run_queue` trains a queue of runs of one learner kind through one trainer with up
to K slots (K = 1 for a single run; the online learner trains K runs in lockstep), and
:func:`train` is the single-run case. For every run it

1. checks the task name and writes ``config.json`` before any work (or checks that the
   folder holds the same run; a complete run is skipped);
2. starts the run in a free slot, fresh or from its ``checkpoint.pt``;
3. advances all slots together, logging every episode through the one sink
   (:class:`~pporpe.runs.logger.RunLogger`) and checkpointing after a finiteness check
   when one is due, by count or by time (:mod:`.cadence`);
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
the work since its last checkpoint, at most about 2 minutes of it (:mod:`.cadence`);
records never have a gap or a duplicate.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..envs import make_env
from ..evaluation import EVAL_SEED_OFFSET, EvalResult, evaluate_policy, load_evaluation
from ..io import atomic_write_json, atomic_write_text
from ..policy import Policy
from ..run_files import read_done
from .active_run import ActiveRun
from .cadence import CHECKPOINT_WITHIN_S, RECENT_EPISODES, CheckpointClock, LiveProgress
from .checkpoint_data import building_from, check_run_state
from .folder import (
    CHECKPOINT,
    check_checkpoint,
    config_json,
    load_run_state,
    open_run_dir,
    read_config,
)
from .folder import save_checkpoint as save_checkpoint
from .kinds import LearnerKind, NonFiniteError, Progress, Trainer, kind_of
from .logger import EpisodeRecord, read_records
from .population_checkpoint import Packing, PopulationCheckpoint, progress_of
from .stopping import Interrupted

__all__ = ["NonFiniteError", "RunResult", "load_policy", "run_queue", "train"]


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
    cpu_time: float = 0.0
    """CPU seconds of training over all segments: the run's share of its process's CPU time
    in the trainer's steps (a population's split evenly between its busy members); not
    evaluation, callbacks or checkpoints."""
    last_scalars: dict[str, float] = field(default_factory=dict)
    """The last extra scalars the trainer reported (a batch update's statistics)."""
    error: str | None = None
    """Why the run failed alone (also in its ``error.txt``), or None."""
    already_done: bool = False
    """Whether the run was complete before this call (nothing was trained or evaluated)."""


OnChunk = Callable[[Trainer, Progress, float], None]
"""Called after each unit of work of a run with the trainer, the run's report and its
training seconds so far; its own time is not counted as training time."""


def _finished_result(run: Path) -> RunResult:
    records = read_records(run / "episodes.csv")
    done = read_done(run)
    chunks = int(done.get("chunks", done.get("updates", done.get("episodes", len(records)))))
    return RunResult(
        run,
        records,
        load_evaluation(run),
        chunks,
        int(done.get("total_steps", 0)),
        float(done.get("train_time", 0.0)),
        chunks,
        cpu_time=float(done.get("cpu_time", 0.0)),
        already_done=True,
    )


@dataclass
class _Hooks:
    """What the caller asked the queue for, besides the runs."""

    progress: bool = False
    on_episode: Callable[[EpisodeRecord], None] | None = None
    on_chunk: OnChunk | None = None
    checkpoint_seconds: float = 0.0
    stop: Callable[[], bool] | None = None
    checkpoint_within: float = CHECKPOINT_WITHIN_S
    live_seconds: float | None = None


class _Queue:
    """The runs of one :func:`run_queue` call in the slots of one trainer.

    One method per event: :meth:`begin` (a run enters a slot), :meth:`fill` (a slot takes
    the next queued run), :meth:`checkpoint` (every busy run), :meth:`finish` (a run's
    budget is spent), :meth:`fail` (a run failed alone), :meth:`compact` (the trainer
    shrinks to its busy runs). :meth:`run` is the loop over them.
    """

    def __init__(
        self,
        kind: LearnerKind,
        cfgs: list[Any],
        dirs: list[Path],
        pending: list[int],
        capacity: int,
        population: PopulationCheckpoint | None,
        hooks: _Hooks,
        results: dict[int, RunResult],
    ) -> None:
        self.kind, self.cfgs, self.dirs, self.hooks = kind, cfgs, dirs, hooks
        self.population, self.results = population, results
        self.packing = Packing([None] * capacity, deque(pending))
        self.members: dict[str, dict[str, Any]] = {}
        if population is not None:
            packing, self.members = population.restore(pending)
            if packing is not None:
                self.packing = packing
        self.names = population.names if population is not None else [str(d) for d in dirs]
        self.trainer = kind.make_trainer(cfgs[pending[0]], len(self.packing.slots))
        self.books: dict[int, ActiveRun] = {}
        self.clock = CheckpointClock(hooks.checkpoint_seconds, hooks.checkpoint_within)
        self.live = LiveProgress(hooks.live_seconds)

    @property
    def slots(self) -> list[int | None]:
        return self.packing.slots

    def write_packing(self) -> None:
        if self.population is not None:
            self.population.write_mirror(self.packing)

    def begin(self, slot: int, i: int) -> None:
        """Start run ``i`` in ``slot``: fresh, or from its state, the population's or its own
        (the more advanced: :func:`~.population_checkpoint.progress_of`)."""
        run = self.dirs[i]
        source = run_checkpoint = run / CHECKPOINT
        state = self.members.pop(self.names[i], None)
        if state is not None and self.population is not None:
            source = self.population.file
            check_run_state(state, source, self.kind.name)
        if run_checkpoint.exists():
            own = load_run_state(run, self.kind.name)
            if state is None or progress_of(own) > progress_of(state):
                state, source = own, run_checkpoint
        with building_from(source) if state is not None else nullcontext():
            self.trainer.start(slot, self.cfgs[i], state)
        bar = self.hooks.progress and len(self.slots) == 1
        book = ActiveRun(self.kind, self.cfgs[i], run, bar=bar)
        book.resume(state, self.trainer, slot)
        (run / "error.txt").unlink(missing_ok=True)
        self.books[slot] = book
        self.slots[slot] = i

    def fill(self, slot: int) -> None:
        """``slot`` takes the next queued run, or stays idle."""
        self.slots[slot] = None
        if self.packing.queue:
            self.begin(slot, self.packing.queue.popleft())

    def checkpoint(self) -> None:
        """Every busy run's checkpoint: in its folder (one run), or all of them in the
        population's one file (so that they are always from the same step)."""
        if self.population is None:
            for slot, book in list(self.books.items()):
                try:
                    book.checkpoint(self.trainer, slot)
                except NonFiniteError as exc:
                    self.fail(slot, str(exc))
            return
        states = {}
        for slot, book in list(self.books.items()):
            i = self.slots[slot]
            assert i is not None
            try:
                states[self.names[i]] = book.state(self.trainer, slot)
            except NonFiniteError as exc:
                self.fail(slot, str(exc))
        self.population.save(self.packing, states)
        for book in self.books.values():
            book.write_logs()

    def fail(self, slot: int, message: str) -> None:
        """Run of ``slot`` failed alone: its message and last good state in its folder."""
        i, book = self.slots[slot], self.books.pop(slot)
        assert i is not None
        atomic_write_text(book.run / "error.txt", message + "\n")
        if self.population is not None and (last := self.population.last_state(i)) is not None:
            save_checkpoint(book.run / CHECKPOINT, last)
        book.close()
        self.results[i] = RunResult(
            book.run, book.records, None, book.resumed_from, error=message, chunks=0
        )
        self.trainer.stop(slot)
        self.live.remove(book.run)
        self.fill(slot)

    def finish(self, slot: int) -> None:
        """Evaluate and complete the run in ``slot`` (its last checkpoint is written)."""
        try:
            self.books[slot].checkpoint(self.trainer, slot)
        except NonFiniteError as exc:
            self.fail(slot, str(exc))
            return
        i, book = self.slots[slot], self.books.pop(slot)
        assert i is not None
        cfg = self.cfgs[i]
        total_time = book.train_time()
        counters = self.trainer.counters(slot)
        act = self.trainer.policy(slot)
        self.trainer.stop(slot)
        book.close()
        evaluation = None
        t_cpu = time.process_time()
        if cfg.eval_episodes > 0:
            evaluation = evaluate_policy(
                act, cfg.env, cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET,
                progress=book.want_bar,
            )  # fmt: skip
            atomic_write_json(book.run / "evaluation.json", evaluation.to_dict())
        eval_cpu = time.process_time() - t_cpu
        done = {"episodes": len(book.records), **counters, "train_time": total_time,
                "cpu_time": book.cpu_time(), "cpu_time_since": book.cpu_since,
                "eval_cpu_time": eval_cpu}  # fmt: skip
        atomic_write_json(book.run / "done.json", done)
        self.live.remove(book.run)
        self.results[i] = RunResult(
            book.run, book.records, evaluation, book.resumed_from, counters["total_steps"],
            total_time, counters["chunks"], book.cpu_time(), book.last,
        )  # fmt: skip
        self.fill(slot)

    def compact(self) -> bool:
        """With the queue empty and at most half the slots busy, move the busy runs to a
        smaller trainer (idle slots of a population would still cost compute)."""
        busy = [slot for slot, i in enumerate(self.slots) if i is not None]
        if len(self.slots) <= 1 or self.packing.queue or not busy:
            return False
        if len(busy) > len(self.slots) // 2:
            return False
        self.trainer.compact(busy)
        moved = {j: self.books[slot] for j, slot in enumerate(busy)}
        self.books.clear()
        self.books.update(moved)
        self.slots[:] = [self.slots[slot] for slot in busy]
        return True

    def report(self, reports: dict[int, Progress]) -> bool:
        """Log every run's new episodes and call the hooks; True when a checkpoint is due."""
        due = False
        for slot, progress in reports.items():
            book = self.books[slot]
            new = book.add(progress)
            t_cb = time.perf_counter()
            if self.hooks.on_episode is not None:
                for rec in new:
                    self.hooks.on_episode(rec)
            if self.hooks.on_chunk is not None:
                self.hooks.on_chunk(self.trainer, progress, book.train_time())
            book.excluded += time.perf_counter() - t_cb
            due = due or progress.checkpoint_due
        return due

    def settle(self, reports: dict[int, Progress]) -> bool:
        """Fail or finish the runs that reported an error or spent their budget, then
        compact; True when the packing changed."""
        changed = False
        for slot, progress in reports.items():
            if progress.error is not None:
                self.fail(slot, progress.error)
                changed = True
            elif self.trainer.finished(slot):
                self.finish(slot)
                changed = True
        return self.compact() or changed

    def step(self) -> None:
        """One unit of work of every busy run, then its bookkeeping."""
        # a run resumed with its budget spent (stopped after its last checkpoint, e.g.
        # during evaluation) is completed without another unit of work
        spent = [slot for slot in self.books if self.trainer.finished(slot)]
        if spent:
            for slot in spent:
                self.finish(slot)
            self.write_packing()
            return
        t_cpu = time.process_time()
        reports = self.trainer.advance()
        share = (time.process_time() - t_cpu) / len(self.books)
        for book in self.books.values():
            book.cpu += share
        by_count = self.report(reports)
        changed = self.settle(reports)
        # the packing changed (a run ended, its slot was refilled, the trainer shrank):
        # checkpoint every run at this step, so that a resumed queue continues with the
        # same packing at the same step, bit for bit
        repacked = changed and self.population is not None and bool(self.books)
        if repacked or self.clock.due(by_count):
            self.checkpoint()
            self.clock.written()
            changed = True
        if changed:
            self.write_packing()
        if self.live.due():
            self.write_live()

    def write_live(self) -> None:
        """Every busy run's live progress (:class:`~.cadence.LiveProgress`)."""
        self.live.write(
            [
                (book.run, len(book.records), self.trainer.counters(slot)["total_steps"],
                 [r.length for r in book.records[-RECENT_EPISODES:]])
                for slot, book in self.books.items()
            ]
        )  # fmt: skip

    def interrupt(self) -> None:
        """Stop on request, between two units of work: every busy run's checkpoint at this
        step, then :class:`~pporpe.runs.stopping.Interrupted` (how far each run got)."""
        self.checkpoint()
        self.write_packing()
        for book in self.books.values():
            self.live.remove(book.run)
        raise Interrupted({book.run: len(book.records) for book in self.books.values()})

    def run(self) -> None:
        """Fill the slots, then step until every run has finished or failed (or the
        caller's ``stop`` asks to stop: :meth:`interrupt`)."""
        try:
            for slot, assigned in enumerate(list(self.slots)):
                if assigned is not None:
                    self.begin(slot, assigned)
                else:
                    self.fill(slot)
            self.write_packing()
            while self.books:
                self.step()
                if self.books and self.hooks.stop is not None and self.hooks.stop():
                    self.interrupt()
        finally:
            for book in self.books.values():
                book.close()
            self.trainer.close()


def _pending_runs(
    kind: LearnerKind, cfgs: list[Any], dirs: list[Path], results: dict[int, RunResult]
) -> list[int]:
    """Open every run folder (``config.json`` written or checked); finished runs go to
    ``results``, the others are returned."""
    pending: list[int] = []
    for i, (cfg, run) in enumerate(zip(cfgs, dirs, strict=True)):
        _, done = open_run_dir(run, config_json(kind, cfg))
        if done:
            results[i] = _finished_result(run)
        else:
            pending.append(i)
    return pending


def _check_checkpoints(dirs: list[Path], population: PopulationCheckpoint | None) -> None:
    """Refuse, before any work, a checkpoint that would run code when read
    (:func:`~pporpe.runs.folder.check_checkpoint`): the runs' own and the population's."""
    files = [d / CHECKPOINT for d in dirs]
    if population is not None:
        files.append(population.file)
    for path in files:
        if path.is_file():
            check_checkpoint(path)


def _check_numbers(num_threads: int, checkpoint_seconds: float, checkpoint_within: float) -> None:
    """``ValueError`` naming the argument of :func:`run_queue` that is out of range."""
    if isinstance(num_threads, bool) or not isinstance(num_threads, int) or num_threads < 1:
        raise ValueError(f"num_threads must be an int >= 1; got num_threads={num_threads!r}")
    for name, value in (("checkpoint_seconds", checkpoint_seconds),
                        ("checkpoint_within", checkpoint_within)):  # fmt: skip
        if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
            raise ValueError(f"{name} must be a number >= 0; got {name}={value!r}")


def _one_kind(cfgs: list[Any]) -> LearnerKind:
    """The learner kind of runs that share it, their task and network shape (else
    ``ValueError``), after building each task's environment once: bad names and spaces
    (e.g. discrete actions) fail before any folder is written."""
    kind = kind_of(cfgs[0])
    keys = {kind.pack_key(c) for c in cfgs}
    if any(kind_of(c) is not kind for c in cfgs) or len(keys) != 1:
        raise ValueError("run_queue takes runs of one learner kind, task and network shape")
    for env in dict.fromkeys(cfg.env for cfg in cfgs):
        make_env(env).close()
    return kind


def run_queue(
    runs: Sequence[tuple[Any, str | Path]],
    capacity: int = 1,
    home: str | Path | None = None,
    progress: bool = False,
    on_episode: Callable[[EpisodeRecord], None] | None = None,
    on_chunk: OnChunk | None = None,
    checkpoint_seconds: float = 0.0,
    num_threads: int = 1,
    stop: Callable[[], bool] | None = None,
    checkpoint_within: float = CHECKPOINT_WITHIN_S,
    live_seconds: float | None = None,
) -> list[RunResult]:
    """Train every ``(config, run_dir)`` of ``runs`` (one learner kind, one task and network
    shape) through one trainer with up to ``capacity`` slots, refilling a slot when its run
    finishes. Returns one result per run, in order.

    ``home`` (required when ``capacity`` > 1) holds the population's checkpoint and
    ``population.json``; the checkpoint is deleted once every run has finished (each run
    keeps its own final checkpoint; after a failure it stays). A checkpoint is due when a
    run's ``checkpoint_every`` count asks for one, written at most every
    ``checkpoint_seconds`` (0: whenever asked), or by time, whatever the count: after a
    quarter of ``checkpoint_within`` seconds (default :data:`~.cadence.CHECKPOINT_WITHIN_S`,
    2 minutes), half of it later, then every ``checkpoint_within`` seconds (``math.inf``: by
    count only; :mod:`.cadence`); every run also gets one when it finishes.
    ``live_seconds``: write each busy run's ``progress.json`` that often (None: never; a
    grid's bar reads it). ``on_episode`` is called after every episode, ``on_chunk`` after
    every unit of work of a run. ``num_threads``: torch's intra-op threads while training
    (1: the setting under which the same seed gives the same numbers), the caller's setting
    restored when the call returns. (One setting for every call: a kernel compiled by
    ``torch.compile`` under one thread count crashed when run under another.) Exceptions
    other than a run's own failure stop the queue (each run keeps its last checkpoint).
    ``stop`` is asked after every unit of work; when it returns True, every busy run is
    checkpointed at that step and :class:`~pporpe.runs.stopping.Interrupted` is raised
    (``pporpe train`` and grids pass :func:`~pporpe.runs.stopping.stop_on_signals`' request:
    Ctrl-C or SIGTERM).
    """
    _check_numbers(num_threads, checkpoint_seconds, checkpoint_within)
    if not runs:
        return []
    if capacity > 1 and home is None:
        raise ValueError("run_queue needs a home folder for population.json when capacity > 1")
    cfgs = [cfg for cfg, _ in runs]
    kind = _one_kind(cfgs)
    dirs = [Path(d) for _, d in runs]
    results: dict[int, RunResult] = {}
    pending = _pending_runs(kind, cfgs, dirs, results)
    if pending:
        hooks = _Hooks(
            progress, on_episode, on_chunk, checkpoint_seconds, stop, checkpoint_within,
            live_seconds,
        )  # fmt: skip
        population = (
            PopulationCheckpoint(Path(home), dirs) if home is not None and capacity > 1 else None
        )
        _run_pending(kind, cfgs, dirs, pending, capacity, population, hooks, results, num_threads)
    return [results[i] for i in range(len(runs))]


def _run_pending(
    kind: LearnerKind,
    cfgs: list[Any],
    dirs: list[Path],
    pending: list[int],
    capacity: int,
    population: PopulationCheckpoint | None,
    hooks: _Hooks,
    results: dict[int, RunResult],
    num_threads: int,
) -> None:
    """The unfinished runs of :func:`run_queue` (``pending``, indices into ``cfgs`` and
    ``dirs``) through one trainer of up to ``capacity`` slots, their results into
    ``results``; the population's checkpoint (if any) discarded when none failed."""
    _check_checkpoints([dirs[i] for i in pending], population)
    slots = max(1, min(capacity, len(pending)))
    with _torch_threads(num_threads):
        queue = _Queue(kind, cfgs, dirs, pending, slots, population, hooks, results)
        queue.run()
    if population is not None and all(results[i].error is None for i in pending):
        population.discard()


@contextmanager
def _torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op threads set to ``n`` inside, the caller's setting restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def train(
    cfg: Any,
    run_dir: str | Path,
    progress: bool = True,
    on_episode: Callable[[EpisodeRecord], None] | None = None,
    on_chunk: OnChunk | None = None,
    num_threads: int = 1,
    stop: Callable[[], bool] | None = None,
    checkpoint_within: float = CHECKPOINT_WITHIN_S,
) -> RunResult:
    """Train one run of any learner kind as configured, writing everything into
    ``run_dir``; resumes from its checkpoint when one exists for the same config.
    ``num_threads``: torch's threads while training, the caller's setting restored after;
    ``stop``: asked after every unit of work, True checkpoints the run and raises
    :class:`~pporpe.runs.stopping.Interrupted`. A checkpoint is written every
    ``cfg.checkpoint_every`` episodes (online) or updates (batch), and by time: at the
    latest ``checkpoint_within`` seconds after the last one (the first after a quarter of
    it; see :func:`run_queue`).

    Raises :class:`NonFiniteError` if the run failed on a non-finite value (its last good
    checkpoint is kept).
    """
    (result,) = run_queue(
        [(cfg, run_dir)],
        progress=progress,
        on_episode=on_episode,
        on_chunk=on_chunk,
        num_threads=num_threads,
        stop=stop,
        checkpoint_within=checkpoint_within,
    )
    if result.error is not None:
        raise NonFiniteError(result.error)
    return result


def load_policy(run_dir: str | Path) -> Policy:
    """The trained policy of a run folder, from its ``config.json`` and latest checkpoint.

    Works for every learner kind (the online learner, batch PPO with its observation
    normalisation) and for folders of earlier versions (:mod:`.migrate`). The result acts with
    ``policy.act(obs, deterministic=True)`` (or ``policy(obs)``) and carries the run's
    configuration as ``policy.config``::

        policy = pporpe.load_policy("runs/x")
        action = policy.act(obs)

    Raises:
        ValueError: not a run folder, or a corrupt config or checkpoint.
    """
    kind, cfg = read_config(run_dir)
    with building_from(Path(run_dir) / CHECKPOINT):
        return kind.load_policy(cfg, load_run_state(run_dir, kind.name))
