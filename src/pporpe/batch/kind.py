"""Batch PPO as a learner kind of the run loop (:class:`BatchTrainer` for one run,
:class:`BatchPopulationTrainer` for K runs in lockstep; registered as ``"batch"``), and
:func:`train_batch`, a whole batch run through that loop."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..evaluation import EVAL_SEED_OFFSET, EvalResult, evaluate_policy
from ..policy import Policy
from ..runs.checkpoint_data import building_from
from ..runs.folder import CHECKPOINT, load_run_state, read_config
from ..runs.kinds import (
    Episode,
    NonFiniteError,
    Progress,
    SurrogateDiagnostics,
    Trainer,
    register_kind,
)
from ..runs.loop import RunResult, train
from .buffer import FinishedEpisode
from .config import BatchConfig, zoo_config
from .learner import BatchLearner, UpdateStats
from .population import SHARED_FIELDS, BatchPopulation

__all__ = [
    "BATCH",
    "BatchKind",
    "BatchPopulationTrainer",
    "BatchResult",
    "BatchTrainer",
    "evaluate_learner",
    "load_batch_learner",
    "train_batch",
]


class BatchTrainer:
    """One batch run around a :class:`BatchLearner` (one slot); a unit of work is one
    update (a rollout, then its minibatch epochs)."""

    capacity = 1

    def __init__(self) -> None:
        self.learner: BatchLearner | None = None
        self.last_stats: UpdateStats | None = None

    def _learner(self, slot: int) -> BatchLearner:
        if slot != 0 or self.learner is None:
            raise RuntimeError(f"slot {slot} holds no run")
        return self.learner

    def start(self, slot: int, cfg: BatchConfig, state: dict[str, Any] | None) -> None:
        """Build the learner and its environments (seeded), then restore ``state``."""
        if slot != 0 or self.learner is not None:
            raise RuntimeError("a batch trainer holds one run, in slot 0")
        torch.manual_seed(cfg.seed)
        self.learner = BatchLearner(cfg)
        if state is not None:
            self.learner.load_state_dict(state["learner"])
            torch.set_rng_state(state["torch_rng"])

    def stop(self, slot: int) -> None:
        """Close the vector environment and free the slot."""
        self._learner(slot).close()
        self.learner = None

    def compact(self, keep: list[int]) -> None:
        """One slot: nothing to compact."""
        if keep != [0]:
            raise RuntimeError(f"a batch trainer has one slot; cannot keep slots {keep}")

    def close(self) -> None:
        """Close the vector environment, if a run is in the slot."""
        if self.learner is not None:
            self.stop(0)

    def finished(self, slot: int) -> bool:
        """Whether every update is done."""
        learner = self._learner(slot)
        return learner.updates >= learner.cfg.n_updates

    def bar_position(self, slot: int) -> int:
        """Environment steps done."""
        return self._learner(slot).total_steps

    def counters(self, slot: int) -> dict[str, int]:
        """Updates (the unit of work) and environment steps done."""
        learner = self._learner(slot)
        updates = learner.updates
        return {"total_steps": learner.total_steps, "chunks": updates, "updates": updates}

    def advance(self) -> dict[int, Progress]:
        """Collect one rollout and learn from it (see :func:`_progress`)."""
        learner = self._learner(0)
        try:
            finished = learner.collect_rollouts()
            stats = learner.train()
        except NonFiniteError as exc:
            return {0: Progress([], error=str(exc))}
        self.last_stats = stats
        return {0: _progress(learner, stats, finished)}

    def state(self, slot: int) -> dict[str, Any]:
        """The learner (with its environments' replay records) and the torch RNG state."""
        return {"learner": self._learner(slot).state_dict(), "torch_rng": torch.get_rng_state()}

    def parameters_finite(self, slot: int) -> bool:
        """Whether every parameter is finite."""
        return self._learner(slot).model.parameters_finite()

    def policy(self, slot: int) -> Callable[[Any], np.ndarray]:
        """The policy's location, bounded, with frozen observation statistics."""
        return self._learner(slot).act_deterministic


def _progress(
    learner: BatchLearner, stats: UpdateStats, episodes: list[FinishedEpisode]
) -> Progress:
    """The report of one update of a run: its episodes with the update's diagnostics
    (episodes that end during rollout k get those of update k, the update that learns from
    them, without a trace decay: batch PPO has no eligibility traces); an error when its
    losses are not finite."""
    if not math.isfinite(float(stats.policy_loss) + float(stats.value_loss)):
        return Progress([], error=f"non-finite loss at update {learner.updates}")
    diagnostics = SurrogateDiagnostics(
        reg_amount=float(stats.reg_amount),
        past_threshold=float(stats.past_threshold),
        ratio_dev=float(stats.ratio_dev),
    )
    return Progress(
        episodes=[
            Episode(ep.total_steps, ep.ret, ep.length, diagnostics=diagnostics) for ep in episodes
        ],
        checkpoint_due=learner.updates % learner.cfg.checkpoint_every == 0,
        bar_advance=learner.cfg.rollout_size,
        scalars=stats.as_dict(),
        total_steps=learner.total_steps,
    )


class BatchPopulationTrainer:
    """Up to ``capacity`` batch runs of one shape trained in lockstep by a
    :class:`~pporpe.batch.population.BatchPopulation`; a unit of work is one update of
    every busy run. A run's checkpoint state is that of a run alone (:class:`BatchTrainer`),
    so a run moves between the two."""

    def __init__(self, cfg: BatchConfig, capacity: int) -> None:
        self.capacity = capacity
        self.population = BatchPopulation(cfg, capacity)
        self.last_stats: dict[int, UpdateStats] = {}

    def start(self, slot: int, cfg: BatchConfig, state: dict[str, Any] | None) -> None:
        """Build the run's learner and environments (seeded as a run alone), then restore
        ``state``."""
        self.population.start(slot, cfg, state)

    def stop(self, slot: int) -> None:
        """Close the run's environments and free the slot."""
        self.population.stop(slot)
        self.last_stats.pop(slot, None)

    def compact(self, keep: list[int]) -> None:
        """Move the runs of slots ``keep`` into a population of ``len(keep)`` slots (their
        state written back and reloaded exactly, environments and streams kept)."""
        old = self.population
        members = [old.release(k) for k in keep]
        old.close()
        self.population = BatchPopulation(old.cfg, len(keep))
        for j, member in enumerate(members):
            self.population.admit(j, member)
        self.capacity = len(keep)
        self.last_stats = {}

    def close(self) -> None:
        """Close every run's environments."""
        self.population.close()

    def finished(self, slot: int) -> bool:
        """Whether every update of the run is done."""
        return self.population.finished(slot)

    def bar_position(self, slot: int) -> int:
        """Environment steps done."""
        return self.population.learner(slot).total_steps

    def counters(self, slot: int) -> dict[str, int]:
        """Updates (the unit of work) and environment steps done."""
        learner = self.population.learner(slot)
        updates = learner.updates
        return {"total_steps": learner.total_steps, "chunks": updates, "updates": updates}

    def advance(self) -> dict[int, Progress]:
        """One rollout and one update of every busy run."""
        reports: dict[int, Progress] = {}
        for k, report in self.population.update().items():
            learner = self.population.learner(k)
            if report.error is not None or report.stats is None:
                reports[k] = Progress([], error=report.error or "no update")
                continue
            self.last_stats[k] = report.stats
            reports[k] = _progress(learner, report.stats, report.episodes)
        return reports

    def state(self, slot: int) -> dict[str, Any]:
        """The run's state as a run alone saves it."""
        return self.population.member_state(slot)

    def parameters_finite(self, slot: int) -> bool:
        """Whether every parameter of the run is finite."""
        return self.population.parameters_finite(slot)

    def policy(self, slot: int) -> Callable[[Any], np.ndarray]:
        """A standalone copy of the run's deterministic test-time policy."""
        state = {"learner": self.population.member_state(slot)["learner"]}
        learner = _policy_learner(self.population.learner(slot).cfg, state)
        learner.close()
        return learner.act_deterministic


def _policy_learner(cfg: BatchConfig, state: dict[str, Any]) -> BatchLearner:
    """A learner with a checkpoint's parameters and observation statistics, built on a
    single sub-environment (enough to act; the saved episodes are not replayed)."""
    learner = BatchLearner(dataclasses.replace(cfg, n_envs=1, batch_size=1))
    learner.cfg = cfg
    with torch.no_grad():
        learner.model.theta.copy_(state["learner"]["theta"])
    learner.normalizer.obs_rms.load_state_dict(state["learner"]["normalizer"]["obs_rms"])
    return learner


class BatchKind:
    """Learner kind ``"batch"``: batch PPO, configured by :class:`BatchConfig`."""

    name = "batch"
    config_type = BatchConfig

    def make_trainer(
        self, cfg: BatchConfig, capacity: int
    ) -> BatchTrainer | BatchPopulationTrainer:
        """A trainer of one run (``capacity`` 1), or a population of ``capacity`` slots for
        runs shaped like ``cfg``."""
        if capacity <= 1:
            return BatchTrainer()
        return BatchPopulationTrainer(cfg, capacity)

    def budget(self, cfg: BatchConfig) -> tuple[int, str]:
        """Environment steps, in whole rollouts."""
        return cfg.n_updates * cfg.rollout_size, "step"

    def pack_key(self, cfg: BatchConfig) -> Any:
        """What the members of one population share (:data:`SHARED_FIELDS`); runs with
        another policy than ``"normal"`` are never packed (each is its own key)."""
        if cfg.policy != "normal":
            return ("alone", id(cfg))
        return tuple(getattr(cfg, name) for name in SHARED_FIELDS)

    def load_policy(self, cfg: BatchConfig, state: dict[str, Any]) -> Policy:
        """The trained policy of a checkpoint, with its frozen observation statistics."""
        learner = _policy_learner(cfg, state)
        learner.close()  # acting needs no environment
        model, normalizer = learner.model, learner.normalizer
        return Policy(
            raw=model.raw,
            head=model.head,
            to_action=model.to_action,
            obs_dim=model.obs_dim,
            normalize=lambda obs: normalizer.obs(obs, update=False),
            config=cfg,
            kind=self.name,
        )

    def grid_config(
        self,
        env: str,
        method: str,
        seed: int,
        budget: Mapping[str, int],
        common: Mapping[str, int],
        learner: Mapping[str, Any],
        where: str,
    ) -> BatchConfig:
        """:func:`zoo_config` of the task with the spec's :class:`BatchConfig` overrides."""
        if "steps" not in budget:
            raise ValueError(f"{where}: batch runs take 'steps', not 'episodes'")
        unknown = sorted(set(learner) - {f.name for f in dataclasses.fields(BatchConfig)})
        if unknown:
            raise ValueError(f"{where}: unknown field(s) {unknown} of BatchConfig")
        try:
            return zoo_config(
                env,
                **{**learner},
                method=method,
                seed=seed,
                total_steps=budget["steps"],
                eval_episodes=common["eval_episodes"],
                checkpoint_every=common["checkpoint_every"],
            )
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{where}: {exc}") from None

    def description(self, cfg: BatchConfig) -> str:
        """``"batch <method> <env> s<seed>"``."""
        return f"batch {cfg.method} {cfg.env} s{cfg.seed}"


BATCH = register_kind(BatchKind())


@dataclass
class BatchResult(RunResult):
    """What :func:`train_batch` produced: a :class:`~pporpe.runs.RunResult` whose unit of
    work is an update."""

    @property
    def updates(self) -> int:
        """Updates done in all."""
        return self.chunks

    @property
    def last_stats(self) -> dict[str, float]:
        """The last update's :class:`UpdateStats` as floats (empty when nothing ran)."""
        return self.last_scalars


def train_batch(
    cfg: BatchConfig,
    run_dir: str | Path,
    progress: bool = True,
    on_update: Callable[[BatchLearner, UpdateStats, float], None] | None = None,
) -> BatchResult:
    """Train batch PPO / PPO-RB / PPO-RPE as configured, writing everything into ``run_dir``.

    The one run loop (:func:`pporpe.runs.train`): ``config.json`` first (with
    ``"kind": "batch"``), ``episodes.csv``, ``tensorboard/`` (episode and ``update/*``
    scalars), ``checkpoint.pt`` (every ``checkpoint_every`` updates and at the end),
    ``evaluation.json`` and ``done.json``; resumes exactly from a checkpoint.

    ``on_update(learner, stats, train_time)`` is called after every update (e.g. for
    evaluations during training) with the training seconds so far; its own time is not
    counted in ``train_time`` or the records' ``wall_time``.
    """

    def on_chunk(trainer: Trainer, report: Progress, t: float) -> None:
        assert isinstance(trainer, BatchTrainer) and trainer.last_stats is not None
        assert on_update is not None and trainer.learner is not None
        on_update(trainer.learner, trainer.last_stats, t)

    result = train(cfg, run_dir, progress, on_chunk=on_chunk if on_update else None)
    return BatchResult(**result.__dict__)


def load_batch_learner(
    run_dir: str | Path, build_envs: bool = False
) -> tuple[BatchConfig, BatchLearner]:
    """Rebuild the learner of a batch run folder from its config and latest checkpoint.

    With ``build_envs=False`` (enough for :meth:`BatchLearner.act_deterministic`) a single
    sub-environment is built and the saved episodes are not replayed.
    """
    kind, cfg = read_config(run_dir)
    if kind.name != "batch":
        raise ValueError(f"{run_dir} holds a run of kind {kind.name!r}, not 'batch'")
    state = load_run_state(run_dir, "batch")
    with building_from(Path(run_dir) / CHECKPOINT):
        if not build_envs:
            return cfg, _policy_learner(cfg, state)
        learner = BatchLearner(cfg)
        learner.load_state_dict(state["learner"])
    return cfg, learner


def evaluate_learner(learner: BatchLearner, episodes: int, seed: int | None = None) -> EvalResult:
    """Test episodes of the deterministic policy via :func:`pporpe.evaluation.evaluate_policy`.

    ``seed`` defaults to the training seed plus :data:`~pporpe.evaluation.EVAL_SEED_OFFSET`.
    """
    if seed is None:
        seed = learner.cfg.seed + EVAL_SEED_OFFSET
    return evaluate_policy(learner.act_deterministic, learner.cfg.env, episodes, seed)
