"""The one run loop: every learner kind trains, checkpoints, resumes and evaluates here.

:func:`train` takes a run configuration of any registered learner kind
(:mod:`pporpe.runs.kinds`) and a folder (:mod:`pporpe.runs.folder`), and

1. checks the task name and writes ``config.json`` before any work (or checks that the
   folder holds the same run; a complete run returns at once);
2. runs torch on one thread, seeds it with the run's seed and builds the trainer;
3. resumes from ``checkpoint.pt`` when there is one;
4. advances the trainer (an episode, an update) until its budget is spent, logging every
   episode through the one sink (:class:`~pporpe.runs.logger.RunLogger`), with a progress
   bar, and checkpointing at the trainer's cadence after a finiteness check;
5. evaluates the deterministic policy on test episodes and writes ``evaluation.json``;
6. writes ``done.json`` last.

A killed run loses at most the work since its last checkpoint, the records never have a
gap or a duplicate, and a resumed run produces the same numbers as an uninterrupted one.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..envs import resolve_env_id
from ..evaluation import EVAL_SEED_OFFSET, EvalResult, evaluate_policy, load_evaluation
from ..io import atomic_write_json
from .folder import CHECKPOINT, config_json, load_checkpoint, open_run_dir, read_config
from .folder import save_checkpoint as save_checkpoint
from .kinds import NonFiniteError, Progress, Trainer, kind_of
from .logger import EpisodeRecord, RunLogger, read_records

__all__ = ["NonFiniteError", "RunResult", "load_policy", "train"]


@dataclass
class RunResult:
    """What :func:`train` produced."""

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


OnChunk = Callable[[Trainer, Progress, float], None]
"""Called after each unit of work with the trainer, its report and the training seconds so
far; its own time is not counted as training time."""


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


def train(
    cfg: Any,
    run_dir: str | Path,
    progress: bool = True,
    on_episode: Callable[[EpisodeRecord], None] | None = None,
    on_chunk: OnChunk | None = None,
) -> RunResult:
    """Train a run of any learner kind as configured, writing everything into ``run_dir``.

    Resumes from ``run_dir``'s checkpoint when one exists for the same config.
    ``on_episode`` is called after every episode (for example by a grid's progress bar),
    ``on_chunk`` after every unit of work (an episode or an update).
    """
    kind = kind_of(cfg)
    resolve_env_id(cfg.env)  # bad env names fail before anything is built or written
    run, done = open_run_dir(run_dir, config_json(kind, cfg))
    if done:
        return _finished_result(run)

    torch.set_num_threads(1)
    torch.manual_seed(cfg.seed)
    trainer = kind.make_trainer(cfg)
    records: list[EpisodeRecord] = []
    wall_offset = 0.0
    ckpt_path = run / CHECKPOINT
    try:
        if ckpt_path.exists():
            state = load_checkpoint(run)
            trainer.load_state_dict(state)
            records = [EpisodeRecord(**r) for r in state["records"]]
            wall_offset = float(state["wall_time"])
    except BaseException:
        trainer.close()
        raise
    resumed_from = trainer.counters()["chunks"]

    logger = RunLogger(run)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=trainer.bar_total,
            initial=trainer.bar_position(),
            desc=kind.description(cfg),
            unit=trainer.bar_unit,
            dynamic_ncols=True,
        )
    excluded = 0.0
    t_start = time.perf_counter()

    def train_time() -> float:
        return wall_offset + (time.perf_counter() - t_start) - excluded

    def checkpoint() -> None:
        if not trainer.parameters_finite():
            steps = trainer.counters()["total_steps"]
            raise NonFiniteError(
                f"non-finite parameter at episode {len(records)}, step {steps}; "
                "the last good checkpoint is kept"
            )
        state = trainer.state_dict()
        state["records"] = [r.__dict__ for r in records]
        state["wall_time"] = train_time()
        save_checkpoint(ckpt_path, state)
        logger.write_records(records)

    last: dict[str, float] = {}
    try:
        while not trainer.finished():
            report = trainer.advance()
            now = train_time()
            for ep in report.episodes:
                rec = EpisodeRecord(episode=len(records), **ep.__dict__, wall_time=now)
                records.append(rec)
                logger.episode(rec)
            if report.scalars:
                last = dict(report.scalars)
                logger.scalars("update", last, report.total_steps)
            t_cb = time.perf_counter()
            if on_episode is not None:
                for rec in records[len(records) - len(report.episodes) :]:
                    on_episode(rec)
            if on_chunk is not None:
                on_chunk(trainer, report, now)
            excluded += time.perf_counter() - t_cb
            if bar is not None:
                bar.update(report.bar_advance)
                if records:
                    bar.set_postfix(ep=len(records) - 1, ret=f"{records[-1].ret:.1f}")
            if trainer.finished():
                break
            if report.checkpoint_due:
                checkpoint()
        checkpoint()
    except BaseException:
        trainer.close()
        raise
    finally:
        if bar is not None:
            bar.close()
        logger.close()
    total_time = train_time()

    evaluation = None
    try:
        if cfg.eval_episodes > 0:
            evaluation = evaluate_policy(
                trainer.act_deterministic, cfg.env, cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET
            )
            atomic_write_json(run / "evaluation.json", evaluation.to_dict())
    finally:
        trainer.close()
    counters = trainer.counters()
    atomic_write_json(
        run / "done.json", {"episodes": len(records), **counters, "train_time": total_time}
    )
    return RunResult(
        run,
        records,
        evaluation,
        resumed_from,
        counters["total_steps"],
        total_time,
        counters["chunks"],
        last,
    )


def load_policy(run_dir: str | Path) -> tuple[Any, Callable[[Any], Any]]:
    """The run configuration and deterministic policy (``act(obs) -> action``) of a run
    folder, from its ``config.json`` and latest checkpoint; works for every learner kind
    and for folders written by pporpe 0.1.0."""
    kind, cfg = read_config(run_dir)
    return cfg, kind.load_policy(cfg, load_checkpoint(run_dir))
