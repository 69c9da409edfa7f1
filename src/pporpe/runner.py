"""Training runs of the online learner: the environment loop, checkpoints and resume.

A run folder holds:

* ``config.json``     the :class:`~pporpe.config.TrainConfig` (written before any work);
* ``episodes.csv``    one row per training episode (:class:`~pporpe.logger.EpisodeRecord`);
* ``tensorboard/``    the same scalars for TensorBoard;
* ``checkpoint.pt``   learner, optimiser, traces, target network, RNG states, episode
  counter and records, written atomically at episode boundaries;
* ``evaluation.json`` median / mean / IQR of the test episodes (when requested);
* ``done.json``       written last: the run is complete.

Starting :func:`train` again on the same folder with the same config resumes from the
checkpoint (or returns at once if ``done.json`` exists). A killed run loses at most the
episodes since its last checkpoint, and the records never have a gap or a duplicate.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import OnlineConfig, TrainConfig, config_from_dict, config_to_dict
from .envs import env_spec_summary, make_env, resolve_env_id
from .evaluation import EVAL_SEED_OFFSET, EvalResult, evaluate_policy, load_evaluation
from .io import atomic_path, atomic_write_json
from .logger import EpisodeRecord, RunLogger, read_records
from .online import OnlineLearner
from .surrogates import regularization_amount

__all__ = [
    "CHECKPOINT",
    "NonFiniteError",
    "TrainResult",
    "load_learner",
    "open_run_dir",
    "save_checkpoint",
    "train",
]

CHECKPOINT = "checkpoint.pt"


class NonFiniteError(RuntimeError):
    """A non-finite observation, reward, loss or parameter stopped the run."""


@dataclass
class TrainResult:
    """What :func:`train` produced."""

    run_dir: Path
    """The run folder."""
    records: list[EpisodeRecord]
    """Every training episode."""
    evaluation: EvalResult | None
    """Test-episode summary, if ``eval_episodes`` > 0."""
    resumed_from: int
    """Episodes already done when this call started (0 for a fresh run)."""


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write a checkpoint atomically (``torch.save`` to a temporary file, then rename)."""
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def open_run_dir(run_dir: str | Path, config: dict[str, Any]) -> tuple[Path, bool]:
    """Create a run folder and write ``config.json`` first, or check that it matches.

    Returns the folder and whether the run is complete (``done.json`` exists). A folder
    that holds a run with a different config is refused, so results are never mixed.
    """
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    path = run / "config.json"
    if not path.exists():
        atomic_write_json(path, config)
    elif json.loads(path.read_text()) != config:
        raise ValueError(
            f"{run} holds a run with a different config; use another --out folder "
            "or delete it to start over"
        )
    return run, (run / "done.json").exists()


def episode_diagnostics(step_stats: torch.Tensor, learner: OnlineConfig) -> dict[str, float]:
    """Per-episode means of the regularisation diagnostics from stacked :class:`StepStats`.

    Columns of ``step_stats``: delta, adv, ratio, divergence, trace_decay.
    """
    adv, ratio = step_stats[:, 1], step_stats[:, 2]
    reg = regularization_amount(learner.method, ratio, adv, learner.eps, learner.beta, learner.eta)
    return {
        "reg_amount": float(reg.amount.mean()),
        "past_threshold": float(reg.fraction_past_threshold),
        "trace_decay": float(step_stats[:, 4].mean()),
        "ratio_dev": float((ratio - 1.0).abs().mean()),
    }


def _finished_result(run: Path) -> TrainResult:
    """The result of a run folder whose run is complete (``done.json`` exists)."""
    records = read_records(run / "episodes.csv")
    return TrainResult(run, records, load_evaluation(run), len(records))


def load_learner(run_dir: str | Path) -> tuple[TrainConfig, OnlineLearner]:
    """Rebuild the learner of a run folder from its config and latest checkpoint."""
    run = Path(run_dir)
    if not (run / "config.json").exists() or not (run / CHECKPOINT).exists():
        raise ValueError(f"{run} is not a run folder (needs config.json and {CHECKPOINT})")
    cfg = config_from_dict(
        TrainConfig, json.loads((run / "config.json").read_text()), str(run / "config.json")
    )
    env = make_env(cfg.env)
    spec = env_spec_summary(env)
    env.close()
    learner = OnlineLearner(spec["obs_dim"], spec["action_low"], spec["action_high"], cfg.learner)
    state = torch.load(run / CHECKPOINT, weights_only=False)
    learner.load_state_dict(state["learner"])
    return cfg, learner


def train(
    cfg: TrainConfig,
    run_dir: str | Path,
    progress: bool = True,
    on_episode: Callable[[EpisodeRecord], None] | None = None,
) -> TrainResult:
    """Train the online learner as configured, writing everything into ``run_dir``.

    Resumes from ``run_dir``'s checkpoint when one exists for the same config.
    ``on_episode`` is called after every episode (for example by a grid's progress bar).
    """
    resolve_env_id(cfg.env)  # bad env names fail before anything is built or written
    run, done = open_run_dir(run_dir, config_to_dict(cfg))
    if done:
        return _finished_result(run)

    torch.set_num_threads(1)
    env = make_env(cfg.env, seed=cfg.seed)
    spec = env_spec_summary(env)
    torch.manual_seed(cfg.seed)
    learner = OnlineLearner(spec["obs_dim"], spec["action_low"], spec["action_high"], cfg.learner)

    records: list[EpisodeRecord] = []
    total_steps, wall_offset = 0, 0.0
    obs, _ = env.reset(seed=cfg.seed)
    ckpt_path = run / CHECKPOINT
    if ckpt_path.exists():
        state = torch.load(ckpt_path, weights_only=False)
        learner.load_state_dict(state["learner"])
        records = [EpisodeRecord(**r) for r in state["records"]]
        total_steps = state["total_steps"]
        wall_offset = state["wall_time"]
        torch.set_rng_state(state["torch_rng"])
        env.unwrapped.np_random.bit_generator.state = state["env_rng"]
        obs, _ = env.reset()
    resumed_from = len(records)

    logger = RunLogger(run)
    bar = None
    if progress:
        from tqdm import tqdm

        total = cfg.episodes if cfg.episodes is not None else cfg.steps
        bar = tqdm(
            total=total,
            initial=len(records) if cfg.episodes else total_steps,
            desc=f"{cfg.learner.method} {cfg.env} s{cfg.seed}",
            unit="ep" if cfg.episodes else "step",
            dynamic_ncols=True,
        )

    def finished() -> bool:
        if cfg.episodes is not None:
            return len(records) >= cfg.episodes
        assert cfg.steps is not None
        return total_steps >= cfg.steps

    def checkpoint() -> None:
        if not learner.parameters_finite():
            raise NonFiniteError(
                f"non-finite parameter at episode {len(records)}, step {total_steps}; "
                "the last good checkpoint is kept"
            )
        save_checkpoint(
            ckpt_path,
            {
                "learner": learner.state_dict(),
                "records": [r.__dict__ for r in records],
                "total_steps": total_steps,
                "wall_time": wall_offset + (time.perf_counter() - t_start),
                "torch_rng": torch.get_rng_state(),
                "env_rng": env.unwrapped.np_random.bit_generator.state,
            },
        )
        logger.write_records(records)

    t_start = time.perf_counter()
    try:
        while not finished():
            episode = len(records)
            if not np.all(np.isfinite(obs)):
                raise NonFiniteError(f"non-finite observation at episode {episode}, step 0")
            action = learner.begin_episode(obs)
            steps_stats: list[torch.Tensor] = []
            ep_ret, length, done = 0.0, 0, False
            t_ep = time.perf_counter()
            while not done:
                obs, reward, terminated, truncated, _ = env.step(action)
                length += 1
                reward = float(reward)
                if not (math.isfinite(reward) and np.all(np.isfinite(obs))):
                    raise NonFiniteError(
                        f"non-finite {'reward' if not math.isfinite(reward) else 'observation'}"
                        f" at episode {episode}, step {length}"
                    )
                stats, action = learner.step(reward, obs, terminated, truncated)
                vals = stats.as_tensor()
                if not math.isfinite(float(vals[1])):
                    raise NonFiniteError(f"non-finite loss at episode {episode}, step {length}")
                steps_stats.append(vals)
                ep_ret += reward
                done = terminated or truncated
                if cfg.steps is not None and total_steps + length >= cfg.steps:
                    break
            total_steps += length
            diag = episode_diagnostics(torch.stack(steps_stats), cfg.learner)
            rec = EpisodeRecord(
                episode=episode,
                total_steps=total_steps,
                ret=ep_ret,
                length=length,
                **diag,
                wall_time=wall_offset + (time.perf_counter() - t_start),
            )
            records.append(rec)
            logger.episode(rec)
            if on_episode is not None:
                on_episode(rec)
            if bar is not None:
                bar.update(1 if cfg.episodes else length)
                bar.set_postfix(
                    ep=episode,
                    ret=f"{ep_ret:.1f}",
                    sps=f"{length / max(time.perf_counter() - t_ep, 1e-9):.0f}",
                )
            if finished():
                break
            if len(records) % cfg.checkpoint_every == 0:
                checkpoint()  # before the next reset, so a resume draws the same start state
            obs, _ = env.reset()
        checkpoint()
    finally:
        if bar is not None:
            bar.close()
        logger.close()
        env.close()

    evaluation = None
    if cfg.eval_episodes > 0:
        evaluation = evaluate_policy(
            learner.act_deterministic, cfg.env, cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET
        )
        atomic_write_json(run / "evaluation.json", evaluation.to_dict())
    atomic_write_json(run / "done.json", {"episodes": len(records), "total_steps": total_steps})
    return TrainResult(run, records, evaluation, resumed_from)
