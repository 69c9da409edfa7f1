"""The online learner as a learner kind of the run loop: acting on one environment,
one episode per unit of work (:class:`OnlineTrainer`), and its registration ``"online"``."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch

from ..config import config_from_dict
from ..envs import env_spec_summary, make_env
from ..runs.kinds import Episode, NonFiniteError, Progress, register_kind
from ..surrogates import regularization_amount
from .config import OnlineConfig, TrainConfig
from .learner import OnlineLearner, StepStats

__all__ = ["ONLINE", "OnlineKind", "OnlineTrainer", "episode_diagnostics"]


def episode_diagnostics(stats: StepStats, learner: OnlineConfig) -> dict[str, float]:
    """Per-episode means of the regularisation diagnostics from :meth:`StepStats.stack`."""
    reg = regularization_amount(
        learner.method, stats.ratio, stats.adv, learner.eps, learner.beta, learner.eta
    )
    return {
        "reg_amount": float(reg.amount.mean()),
        "past_threshold": float(reg.fraction_past_threshold),
        "trace_decay": float(stats.trace_decay.mean()),
        "ratio_dev": float((stats.ratio - 1.0).abs().mean()),
    }


def build_learner(env: Any, learner: OnlineConfig) -> OnlineLearner:
    """An online learner sized for an environment's spaces."""
    spec = env_spec_summary(env)
    return OnlineLearner(spec["obs_dim"], spec["action_low"], spec["action_high"], learner)


class OnlineTrainer:
    """One online run: the environment loop around an :class:`OnlineLearner`.

    A unit of work is one episode. The environment is reset at the *start* of an episode,
    so a checkpoint taken between episodes holds the environment's RNG state before that
    reset, and a resumed run draws the same start state.
    """

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.env = make_env(cfg.env, seed=cfg.seed)
        self.learner = build_learner(self.env, cfg.learner)
        self.episodes = 0
        self.total_steps = 0
        self._obs: Any = self.env.reset(seed=cfg.seed)[0]
        self.bar_unit = "ep" if cfg.episodes is not None else "step"
        self.bar_total = int(cfg.episodes if cfg.episodes is not None else cfg.steps or 0)

    def finished(self) -> bool:
        """Whether the budget (episodes or steps) is spent."""
        if self.cfg.episodes is not None:
            return self.episodes >= self.cfg.episodes
        return self.total_steps >= (self.cfg.steps or 0)

    def bar_position(self) -> int:
        """Episodes (or steps) done."""
        return self.episodes if self.cfg.episodes is not None else self.total_steps

    def counters(self) -> dict[str, int]:
        """Episodes (the unit of work) and environment steps done."""
        return {"total_steps": self.total_steps, "chunks": self.episodes}

    def advance(self) -> Progress:
        """Train on one episode (cut short where a step budget ends)."""
        cfg, env, learner = self.cfg, self.env, self.learner
        episode = self.episodes
        obs = self._obs if self._obs is not None else env.reset()[0]
        self._obs = None
        if not np.all(np.isfinite(obs)):
            raise NonFiniteError(f"non-finite observation at episode {episode}, step 0")
        action = learner.begin_episode(obs)
        steps: list[StepStats] = []
        ep_ret, length, done = 0.0, 0, False
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
            if not math.isfinite(float(stats.adv)):
                raise NonFiniteError(
                    f"non-finite loss (advantage) at episode {episode}, step {length}"
                )
            steps.append(stats)
            ep_ret += reward
            done = terminated or truncated
            if cfg.steps is not None and self.total_steps + length >= cfg.steps:
                break
        self.total_steps += length
        self.episodes += 1
        diag = episode_diagnostics(StepStats.stack(steps), cfg.learner)
        ep = Episode(total_steps=self.total_steps, ret=ep_ret, length=length, **diag)
        return Progress(
            episodes=[ep],
            checkpoint_due=self.episodes % cfg.checkpoint_every == 0,
            bar_advance=1 if cfg.episodes is not None else length,
            total_steps=self.total_steps,
        )

    def state_dict(self) -> dict[str, Any]:
        """Learner, counters and both RNG states (taken between episodes)."""
        return {
            "learner": self.learner.state_dict(),
            "episodes": self.episodes,
            "total_steps": self.total_steps,
            "torch_rng": torch.get_rng_state(),
            "env_rng": self.env.unwrapped.np_random.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (also of checkpoints written by pporpe 0.1.0)."""
        self.learner.load_state_dict(state["learner"])
        self.episodes = int(state.get("episodes", len(state.get("records", []))))
        self.total_steps = int(state["total_steps"])
        torch.set_rng_state(state["torch_rng"])
        self.env.unwrapped.np_random.bit_generator.state = state["env_rng"]
        self._obs = None  # the next episode resets with the restored RNG

    def parameters_finite(self) -> bool:
        """Whether every parameter (online and target) is finite."""
        return self.learner.parameters_finite()

    def act_deterministic(self, obs: Any) -> np.ndarray:
        """The policy's location, mapped into the action bounds."""
        return self.learner.act_deterministic(obs)

    def close(self) -> None:
        """Close the environment."""
        self.env.close()


class OnlineKind:
    """Learner kind ``"online"``: the paper's Alg. 1, configured by :class:`TrainConfig`."""

    name = "online"
    config_type = TrainConfig

    def make_trainer(self, cfg: TrainConfig) -> OnlineTrainer:
        """A fresh run (torch is already seeded by the loop)."""
        return OnlineTrainer(cfg)

    def load_policy(self, cfg: TrainConfig, state: dict[str, Any]) -> Callable[[Any], np.ndarray]:
        """The deterministic policy of a checkpoint."""
        env = make_env(cfg.env)
        try:
            learner = build_learner(env, cfg.learner)
        finally:
            env.close()
        learner.load_state_dict(state["learner"])
        return learner.act_deterministic

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
