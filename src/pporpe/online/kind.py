"""The online learner as a learner kind of the run loop: K runs of one task in lockstep,
each on its own environment (:class:`OnlineTrainer`), registered as ``"online"``.

One unit of work is one environment step of every busy slot, learnt by one batched
:meth:`~pporpe.online.population.PopulationLearner.step`. A run's checkpoint holds its
member of the population (mid-episode included), its environment's replay record (the
episode's reset seed or RNG state and the actions since), its counters and the
statistics of the episode in progress, so it continues exactly where it stopped.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch

from ..config import config_from_dict
from ..envs import ReplayableEnv, env_spec_summary, make_env
from ..policy import Policy
from ..runs.kinds import Episode, Progress, SurrogateDiagnostics, register_kind
from ..runs.migrate import check_online_resumable
from ..surrogates import regularization_amount
from .config import OnlineConfig, TrainConfig
from .learner import OnlineLearner
from .population import SHARED_FIELDS, PopulationLearner
from .stats import StepStats

__all__ = ["ONLINE", "OnlineKind", "OnlineTrainer", "episode_diagnostics"]


def episode_diagnostics(stats: StepStats, learner: OnlineConfig) -> SurrogateDiagnostics:
    """Per-episode means of the regularisation diagnostics and the adaptive trace decay of
    an episode's updates (its step statistics side by side: :meth:`StepStats.from_table`)."""
    reg = regularization_amount(
        learner.method, stats.ratio, stats.adv, learner.eps, learner.beta, learner.eta
    )
    return SurrogateDiagnostics(
        reg_amount=float(reg.amount.mean()),
        past_threshold=float(reg.fraction_past_threshold),
        ratio_dev=float((stats.ratio - 1.0).abs().mean()),
        trace_decay=float(stats.trace_decay.mean()),
    )


def _rows(columns: list[np.ndarray]) -> np.ndarray:
    """An episode's step columns as ``[5, length]`` rows (float32 when empty)."""
    return np.stack(columns, axis=1) if columns else np.zeros((5, 0), np.float32)


def _columns(rows: Any) -> list[np.ndarray]:
    """The step columns of a checkpoint's ``episode["steps"]``: five ``[length]`` tensors
    (field order of :class:`StepStats`), or, as checkpoints before them held, five lists
    of 0-dim tensors (the same float32 values either way)."""
    table = np.stack([_float32(row) for row in rows])
    return list(table.T.copy())


def _float32(row: Any) -> np.ndarray:
    """One field of a checkpoint's ``episode["steps"]`` as a float32 array."""
    if isinstance(row, torch.Tensor):
        return row.numpy().astype(np.float32)
    return np.asarray([np.asarray(v) for v in row], np.float32).reshape(-1)


def _spaces(env_name: str) -> dict[str, Any]:
    env = make_env(env_name)
    try:
        return env_spec_summary(env)
    finally:
        env.close()


class _Slot:
    """The run in one slot: its config, environment and the episode in progress."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.env = ReplayableEnv(make_env(cfg.env, seed=cfg.seed))
        self.episodes = 0
        self.total_steps = 0
        self.action: np.ndarray | None = None  # next action; None: the episode must begin
        self.steps: list[np.ndarray] = []  # this episode's step statistics, a [5] column each
        self.ret = 0.0
        self.length = 0

    def finished(self) -> bool:
        if self.cfg.episodes is not None:
            return self.episodes >= self.cfg.episodes
        return self.total_steps >= (self.cfg.steps or 0)


class OnlineTrainer:
    """Up to ``capacity`` online runs of one task in lockstep (see the module docstring)."""

    def __init__(self, cfg: TrainConfig, capacity: int) -> None:
        spec = _spaces(cfg.env)
        self.capacity = capacity
        self.learner = PopulationLearner(
            spec["obs_dim"],
            spec["action_low"],
            spec["action_high"],
            [cfg.learner] * capacity,
            list(range(capacity)),
            compile_update=cfg.learner.compile,
        )
        self.slots: list[_Slot | None] = [None] * capacity

    def _slot(self, slot: int) -> _Slot:
        s = self.slots[slot]
        if s is None:
            raise RuntimeError(f"slot {slot} holds no run")
        return s

    # -- runs in and out -------------------------------------------------------------
    def start(self, slot: int, cfg: TrainConfig, state: dict[str, Any] | None) -> None:
        """Begin a fresh run of ``cfg`` in ``slot`` or continue it from ``state``."""
        s = _Slot(cfg)
        if state is None:
            self.learner.reset_member(slot, cfg.learner, cfg.seed)
        else:
            try:
                check_online_resumable(state["learner"])
            except ValueError:
                s.env.close()
                raise
            self.learner.load_member_state(slot, cfg.learner, state["learner"])
            s.episodes, s.total_steps = int(state["episodes"]), int(state["total_steps"])
            ep = state["episode"]
            s.ret, s.length = float(ep["ret"]), int(ep["length"])
            s.steps = _columns(ep["steps"])
            if state["env"] is not None:  # mid-episode: rebuild the episode
                s.env.replay(state["env"])
                s.action = np.asarray(state["action"])
            else:  # between episodes: the next reset draws from the saved RNG state
                s.env.unwrapped.np_random.bit_generator.state = state["env_rng"]
        self.slots[slot] = s

    def stop(self, slot: int) -> None:
        """Free the slot (its environment is closed)."""
        self._slot(slot).env.close()
        self.slots[slot] = None

    def compact(self, keep: list[int]) -> None:
        """Move the runs of slots ``keep`` into a population of ``len(keep)`` members."""
        old = self.learner
        runs = [self._slot(k) for k in keep]
        self.learner = PopulationLearner(
            old.obs_dim,
            old.action_map.low.numpy(),
            old.action_map.high.numpy(),
            [s.cfg.learner for s in runs],
            [s.cfg.seed for s in runs],
            compile_update=runs[0].cfg.learner.compile,
        )
        for j, (k, s) in enumerate(zip(keep, runs, strict=True)):
            self.learner.load_member_state(j, s.cfg.learner, old.member_state(k))
        for k, idle in enumerate(self.slots):
            if idle is not None and k not in keep:
                idle.env.close()
        self.slots = list(runs)
        self.capacity = len(keep)

    def close(self) -> None:
        """Close every environment."""
        for slot, s in enumerate(self.slots):
            if s is not None:
                self.stop(slot)

    # -- one step of every run ------------------------------------------------------
    def advance(self) -> dict[int, Progress]:
        """One environment step of every busy run, learnt in one batched update."""
        busy = [k for k, s in enumerate(self.slots) if s is not None]
        errors: dict[int, str] = {}
        self._begin_episodes([k for k in busy if self._slot(k).action is None], errors)
        transition = self._step_environments(busy, errors)
        stats, next_actions = self.learner.step(*transition)
        table = stats.table()
        adv_ok = np.isfinite(table[1])
        _, _, terminated, truncated, _ = transition
        reports: dict[int, Progress] = {}
        for k in busy:
            s = self._slot(k)
            if k in errors:
                reports[k] = Progress([], error=errors[k])
            elif not adv_ok[k]:
                msg = f"non-finite loss (advantage) at episode {s.episodes}, step {s.length}"
                reports[k] = Progress([], error=msg)
            else:
                s.steps.append(table[:, k].copy())
                s.action = next_actions[k]
                ended = self._end_episode(s, bool(terminated[k] or truncated[k]))
                if ended is not None:
                    reports[k] = ended
        return reports

    def _begin_episodes(self, starting: list[int], errors: dict[int, str]) -> None:
        """Reset the environments of the runs in ``starting`` (seeded at a run's first
        episode) and draw their first actions; a non-finite observation goes to ``errors``."""
        if not starting:
            return
        first_obs = []
        for k in starting:
            s = self._slot(k)
            seed = s.cfg.seed if s.episodes == 0 else None
            obs = s.env.reset(seed=seed)[0]
            if not np.all(np.isfinite(obs)):
                errors[k] = f"non-finite observation at episode {s.episodes}, step 0"
            first_obs.append(np.nan_to_num(obs))
        actions = self.learner.begin_episode(starting, np.stack(first_obs))
        for k, a in zip(starting, actions, strict=True):
            self._slot(k).action = a

    def _step_environments(
        self, busy: list[int], errors: dict[int, str]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every busy run's environment stepped with its action: the learner's
        ``(reward, next_obs, terminated, truncated, active)``; a run with a non-finite
        reward or observation goes to ``errors`` and is inactive."""
        K = self.capacity
        reward, next_obs = np.zeros(K), np.zeros((K, self.learner.obs_dim))
        terminated, truncated = np.zeros(K, dtype=bool), np.zeros(K, dtype=bool)
        active = np.zeros(K, dtype=bool)
        for k in busy:
            if k in errors:
                continue
            s = self._slot(k)
            obs, r, term, trunc, _ = s.env.step(s.action)
            s.length += 1
            r = float(r)
            if not (math.isfinite(r) and np.all(np.isfinite(obs))):
                what = "reward" if not math.isfinite(r) else "observation"
                errors[k] = f"non-finite {what} at episode {s.episodes}, step {s.length}"
                continue
            reward[k], next_obs[k], terminated[k], truncated[k] = r, obs, term, trunc
            active[k] = True
            s.ret += r
        return reward, next_obs, terminated, truncated, active

    @staticmethod
    def _end_episode(s: _Slot, done: bool) -> Progress | None:
        """The report of run ``s``'s episode if it ended (or its step budget is spent),
        with the run's episode state reset; else None."""
        cut = s.cfg.steps is not None and s.total_steps + s.length >= s.cfg.steps
        if not (done or cut):
            return None
        s.total_steps += s.length
        s.episodes += 1
        diag = episode_diagnostics(StepStats.from_table(_rows(s.steps)), s.cfg.learner)
        ep = Episode(total_steps=s.total_steps, ret=s.ret, length=s.length, diagnostics=diag)
        report = Progress(
            [ep],
            checkpoint_due=s.episodes % s.cfg.checkpoint_every == 0,
            bar_advance=1 if s.cfg.episodes is not None else s.length,
            total_steps=s.total_steps,
        )
        s.action, s.steps, s.ret, s.length = None, [], 0.0, 0
        return report

    # -- reading a run ---------------------------------------------------------------
    def finished(self, slot: int) -> bool:
        """Whether the run's budget (episodes or steps) is spent."""
        return self._slot(slot).finished()

    def counters(self, slot: int) -> dict[str, int]:
        """Episodes (the unit of work) and environment steps done."""
        s = self._slot(slot)
        return {"total_steps": s.total_steps, "chunks": s.episodes}

    def bar_position(self, slot: int) -> int:
        """Episodes (or steps) done."""
        s = self._slot(slot)
        return s.episodes if s.cfg.episodes is not None else s.total_steps

    def state(self, slot: int) -> dict[str, Any]:
        """The run's member, environment replay record, counters and episode in progress."""
        s = self._slot(slot)
        return {
            "learner": self.learner.member_state(slot),
            "episodes": s.episodes,
            "total_steps": s.total_steps,
            "env": s.env.replay_record() if s.action is not None else None,
            "env_rng": s.env.unwrapped.np_random.bit_generator.state,
            "action": None if s.action is None else np.array(s.action),
            "episode": {
                "ret": s.ret,
                "length": s.length,
                "steps": [torch.from_numpy(row.copy()) for row in _rows(s.steps)],
            },
        }

    def parameters_finite(self, slot: int) -> bool:
        """Whether the run's parameters (online and target) are finite."""
        return bool(self.learner.finite()[slot])

    def policy(self, slot: int) -> Callable[[Any], np.ndarray]:
        """A standalone copy of the run's deterministic policy."""
        s = self._slot(slot)
        single = _single_learner(s.cfg)
        single.population.load_member_state(0, s.cfg.learner, self.learner.member_state(slot))
        return single.act_deterministic


def _single_learner(cfg: TrainConfig) -> OnlineLearner:
    spec = _spaces(cfg.env)
    learner_cfg = OnlineConfig(**{**cfg.learner.__dict__, "compile": False})
    return OnlineLearner(
        spec["obs_dim"], spec["action_low"], spec["action_high"], learner_cfg, cfg.seed
    )


class OnlineKind:
    """Learner kind ``"online"``: the paper's Algorithm 1, configured by :class:`TrainConfig`."""

    name = "online"
    config_type = TrainConfig

    def make_trainer(self, cfg: TrainConfig, capacity: int) -> OnlineTrainer:
        """A population of ``capacity`` slots for runs shaped like ``cfg``."""
        return OnlineTrainer(cfg, capacity)

    def budget(self, cfg: TrainConfig) -> tuple[int, str]:
        """Episodes, or steps when the run is measured in steps."""
        if cfg.episodes is not None:
            return cfg.episodes, "ep"
        return int(cfg.steps or 0), "step"

    def pack_key(self, cfg: TrainConfig) -> Any:
        """The task and the network shape: what members of one population share."""
        lc = cfg.learner
        return (cfg.env, *(getattr(lc, name) for name in SHARED_FIELDS), lc.compile)

    def load_policy(self, cfg: TrainConfig, state: dict[str, Any]) -> Policy:
        """The trained policy of a checkpoint (also of the first release's, a flat theta)."""
        learner = _single_learner(cfg)
        member = state["learner"]
        if "params" in member:
            learner.population.load_member_state(0, learner.config, member)
        else:  # 0.1.0: a flat theta in the same order as member_theta
            learner.population.set_member_theta(0, member["theta"])
        pop = learner.population
        return Policy(
            raw=lambda x: pop.policy_raw(0, x),
            head=pop.head,
            to_action=pop.action_map.to_action,
            obs_dim=pop.obs_dim,
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
    ) -> TrainConfig:
        """A :class:`TrainConfig` with the spec's :class:`OnlineConfig` overrides."""
        online = config_from_dict(OnlineConfig, {**learner, "method": method}, where)
        return TrainConfig(
            env=env,
            seed=seed,
            episodes=budget.get("episodes"),
            steps=budget.get("steps"),
            checkpoint_every=common["checkpoint_every"],
            eval_episodes=common["eval_episodes"],
            learner=online,
        )

    def description(self, cfg: TrainConfig) -> str:
        """``"<method> <env> s<seed>"``."""
        return f"{cfg.learner.method} {cfg.env} s{cfg.seed}"


ONLINE = register_kind(OnlineKind())
