r"""Standard batch PPO (rollouts and minibatch epochs) with the PPO, PPO-RB and PPO-RPE surrogates.

Most PPO users train with rollouts of vectorised environments and a few epochs of
minibatch updates rather than online. This module gives them that trainer, sharing the
surrogates (:func:`pporpe.surrogates.surrogate_objective`), the policy heads
(:func:`pporpe.policies.make_head`, :class:`~pporpe.policies.ActionMap`) and the network
builder (:func:`pporpe.networks.mlp`) with the paper's online learner. Switching PPO to
PPO-RB or PPO-RPE is one word: ``BatchConfig(method="rb")`` or ``method="rpe"``; the
training loop is the same function for all three (the surrogate is one call).

One update (``k``-th of ``n_updates``)::

    collect_rollouts()   n_envs x n_steps transitions with the current policy
    compute_gae()        GAE(lambda); bootstrap through truncations, not terminations
    train()              n_epochs x minibatches of batch_size: surrogate + value + entropy

Pieces, each usable alone:

* :class:`BatchConfig`       the frozen, validated settings; :data:`ZOO_DEFAULTS` and
  :func:`zoo_config` give per-task defaults from rl-baselines3-zoo;
* :class:`RunningMeanStd`, :class:`Normalizer`   observation and reward normalisation;
* :class:`ActorCritic`       policy and value networks in one flat parameter vector;
* :class:`RolloutBuffer`, :func:`compute_gae`    storage and advantages;
* :class:`BatchLearner`      acting (:meth:`~BatchLearner.collect_rollouts`), learning
  (:meth:`~BatchLearner.train`, returning :class:`UpdateStats`) and the deterministic
  test-time policy (:meth:`~BatchLearner.act_deterministic`);
* :func:`evaluate_learner`  test episodes through :func:`pporpe.evaluation.evaluate_policy`;
* :func:`train_batch`       a whole run with the run-folder layout of
  :func:`pporpe.runner.train` (config.json, episodes.csv, tensorboard/, checkpoint.pt,
  evaluation.json, done.json) and exact resume.

**Autoreset.** Gymnasium 1.x vector environments default to ``NEXT_STEP`` autoreset: the
step *after* an episode's end only resets that sub-environment, ignores its action and
returns reward 0, so a rollout would hold one dummy transition per finished episode.
This module builds its vector environments with ``autoreset_mode=SAME_STEP`` instead:
the step that ends an episode returns the first observation of the next one, and the
true last observation is in ``info["final_obs"]`` (mask ``info["_final_obs"]``). Every
stored transition is then real, and a truncated episode is bootstrapped with
``V(final_obs)``. :class:`BatchLearner` checks the mode and refuses any other.

**Termination and truncation** stay separate everywhere: ``terminated`` (a true end of
the task) stops bootstrapping; ``truncated`` (a time limit) bootstraps with the value of
the final observation (set ``bootstrap_truncated=False`` only to see what goes wrong);
either one ends the GAE(lambda) chain.

**Resume.** A checkpoint holds the networks, Adam's state, the normalisation statistics,
the torch RNG state, the counters, the records and, for every sub-environment, how its
current episode was reached (the reset seed or RNG state and the actions since). On
resume each sub-environment is rebuilt by replaying that episode, so a run resumed from
a checkpoint continues exactly as the uninterrupted run would have for any environment
that is deterministic given its seed and actions (the Bullet tasks are). If a replay
does not reproduce the saved observation a warning says so and training continues from
the replayed state. A killed run loses at most the updates since its last checkpoint.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

import gymnasium
import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv
from torch import Tensor

from .config import (
    Activation,
    _is_int,
    _is_num,
    _require,
    config_from_dict,
    config_to_dict,
    validate_network_fields,
    validate_surrogate_fields,
)
from .envs import ALIASES, make_env, resolve_env_id
from .evaluation import EVAL_SEED_OFFSET, EvalResult, evaluate_policy, load_evaluation
from .io import atomic_write_json
from .logger import EpisodeRecord, RunLogger, read_records
from .networks import flat_views, mlp
from .online import FlatMLP
from .policies import ActionMap, NormalHead, PolicyHead, make_head
from .runner import CHECKPOINT, NonFiniteError, open_run_dir, save_checkpoint
from .surrogates import Method, RPEForm, regularization_amount
from .surrogates import surrogate_objective as _surrogate_objective

__all__ = [
    "ZOO_DEFAULTS",
    "ActorCritic",
    "BatchConfig",
    "BatchLearner",
    "BatchResult",
    "FinishedEpisode",
    "Normalizer",
    "RolloutBuffer",
    "RunningMeanStd",
    "UpdateStats",
    "compute_gae",
    "evaluate_learner",
    "load_batch_learner",
    "train_batch",
    "zoo_config",
]

PolicyKind = Literal["normal", "student_t"]
ScaleMode = Literal["global", "state"]
ActionBound = Literal["clip", "map"]
AdvNorm = Literal["minibatch", "batch", "none"]
LRSchedule = Literal["constant", "linear"]
VecEnvKind = Literal["sync", "async"]
Init = Literal["default", "orthogonal"]
VecEnv = SyncVectorEnv | AsyncVectorEnv


# ----------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BatchConfig:
    """Settings of one batch PPO run (task, length, learner).

    The defaults are Stable-Baselines3's PPO defaults for continuous control (2 x 64 tanh
    networks, orthogonal initialisation, n_steps 2048, batch 64, 10 epochs, lr 3e-4,
    clip 0.2, GAE lambda 0.95, gamma 0.99, max_grad_norm 0.5, Adam eps 1e-5) with
    observation and reward normalisation on. :func:`zoo_config` starts from the tuned
    per-task settings of :data:`ZOO_DEFAULTS` instead.
    """

    env: str = "pendulum"
    """Task: an alias (pendulum, swingup, halfcheetah, ant) or a Gymnasium id with Box actions."""
    method: Method = "ppo"
    """Surrogate: ``"ppo"`` (clip), ``"rb"`` (rollback) or ``"rpe"`` (relative Pearson)."""
    seed: int = 0
    """Seed of the networks, the sampling and the environments (sub-env i gets seed + i), >= 0."""
    total_steps: int = 1_000_000
    """Training length in environment steps over all sub-environments, >= 1 (rounded up to
    whole rollouts of n_envs * n_steps)."""
    n_envs: int = 1
    """Number of parallel sub-environments, >= 1."""
    vec_env: VecEnvKind = "sync"
    """``"sync"`` (:class:`gymnasium.vector.SyncVectorEnv`, one process) or ``"async"``
    (:class:`gymnasium.vector.AsyncVectorEnv`, one process per sub-environment)."""
    n_steps: int = 2048
    """Steps per sub-environment in one rollout, >= 1."""
    batch_size: int = 64
    """Minibatch size, in [1, n_envs * n_steps]; the last minibatch of an epoch is smaller
    when it does not divide the rollout."""
    n_epochs: int = 10
    """Passes over each rollout, >= 1."""
    gamma: float = 0.99
    """Discount factor, in [0, 1)."""
    gae_lambda: float = 0.95
    """GAE lambda, in [0, 1]."""
    eps: float = 0.2
    """Threshold epsilon of the surrogate (PPO's clip range), in (0, 1)."""
    beta: float = 0.5
    """PPO-RPE mixture ratio beta, in [0, 1] with beta*(1+eps) < 1."""
    eta: float = 0.3
    """PPO-RB rollback slope eta >= 0 (ignored by the other methods)."""
    rpe_form: RPEForm = "derived"
    """A~ of PPO-RPE: ``"derived"`` (exact derivative, default) or the paper's ``"printed"``."""
    lr: float = 3e-4
    """Adam learning rate, > 0."""
    lr_schedule: LRSchedule = "constant"
    """``"constant"``, or ``"linear"``: update k of n uses lr * (1 - k/n)."""
    adam_eps: float = 1e-5
    """Adam's denominator epsilon, > 0 (1e-5 as in Stable-Baselines3's PPO)."""
    vf_coef: float = 0.5
    """Weight of the value loss, >= 0."""
    ent_coef: float = 0.0
    """Weight of the entropy bonus, >= 0 (entropy of the pre-map variable u)."""
    max_grad_norm: float | None = 0.5
    """Clip the global gradient norm to this value (> 0); ``None`` disables clipping."""
    clip_vf: float | None = None
    """Value clipping range (> 0): loss max((V-R)^2, (V_old + clip(V-V_old)-R)^2), as in
    PPO2; ``None`` (default) uses the plain squared error."""
    target_kl: float | None = None
    """Stop an update's epochs early once a minibatch's approximate KL
    mean((rho-1) - log rho) exceeds 1.5 * target_kl (> 0; the Stable-Baselines3 rule);
    ``None`` disables it."""
    adv_norm: AdvNorm = "minibatch"
    """Advantage normalisation to zero mean, unit std: per ``"minibatch"`` (SB3),
    once per rollout (``"batch"``) or ``"none"``."""
    normalize_obs: bool = True
    """Normalise observations by a running mean/std (stats saved in checkpoints)."""
    normalize_reward: bool = True
    """Scale rewards by the running std of the discounted return (not centred)."""
    clip_obs: float = 10.0
    """Clip normalised observations to [-clip_obs, clip_obs], > 0."""
    clip_reward: float = 10.0
    """Clip normalised rewards to [-clip_reward, clip_reward], > 0."""
    bootstrap_truncated: bool = True
    """Bootstrap truncated episodes with V(final observation). ``False`` treats time
    limits as terminations, which is wrong for time-unaware tasks: an ablation switch."""
    policy: PolicyKind = "normal"
    """Policy distribution over the pre-map variable u: diagonal ``"normal"`` (default) or
    the paper's ``"student_t"`` (one degree of freedom per state)."""
    scale: ScaleMode = "global"
    """``"global"``: state-independent scale (and degrees of freedom) parameters, as
    Stable-Baselines3's ``log_std``; ``"state"``: the network outputs them."""
    log_std_init: float = 0.0
    """Initial log of the policy scale (SB3's ``log_std_init``), finite."""
    action_bound: ActionBound = "clip"
    """How u becomes an action in [low, high]. ``"clip"`` (default) clips u, as
    Stable-Baselines3 does: the zoo's tuned settings (log_std_init, learning rates) assume
    that unit-slope map, and it makes the comparison with SB3 exact. ``"map"`` uses the
    paper's :class:`~pporpe.policies.ActionMap` (low + (high-low)*sigmoid(u)). Ratios use
    the density of u in both cases."""
    layers: int = 2
    """Hidden layers of each network (policy and value), >= 1."""
    units: int = 64
    """Units per hidden layer, >= 1."""
    activation: Activation = "tanh"
    """Hidden activation: ``"tanh"``, ``"relu"`` or ``"swish"``."""
    layer_norm: bool = False
    """LayerNorm after each hidden linear layer (the paper's networks use it)."""
    init: Init = "orthogonal"
    """``"orthogonal"`` (SB3's ``ortho_init=True``: hidden gain by activation, policy output
    gain 0.01, value output gain 1, zero biases) or PyTorch's ``"default"``."""
    checkpoint_every: int = 10
    """Write a checkpoint every this many updates (>= 1), and at the end."""
    eval_episodes: int = 50
    """Test episodes after training (>= 0; the paper's score is the median of 50)."""

    def __post_init__(self) -> None:
        _require(isinstance(self.env, str) and bool(self.env), "env", self.env, "a task name")
        validate_surrogate_fields(self)
        for name in ("gamma", "gae_lambda", "lr", "adam_eps"):
            _require(_is_num(getattr(self, name)), name, getattr(self, name), "a number")
        _require(_is_int(self.seed) and self.seed >= 0, "seed", self.seed, "an int >= 0")
        for name in ("total_steps", "n_envs", "n_steps", "n_epochs", "checkpoint_every"):
            v = getattr(self, name)
            _require(_is_int(v) and v >= 1, name, v, "an int >= 1")
        _require(
            _is_int(self.batch_size) and 1 <= self.batch_size <= self.rollout_size,
            "batch_size",
            self.batch_size,
            f"an int in [1, n_envs * n_steps = {self.rollout_size}]",
        )
        _require(
            _is_int(self.eval_episodes) and self.eval_episodes >= 0,
            "eval_episodes",
            self.eval_episodes,
            "an int >= 0",
        )
        _require(self.vec_env in get_args(VecEnvKind), "vec_env", self.vec_env, "'sync' or 'async'")
        _require(0.0 <= self.gamma < 1.0, "gamma", self.gamma, "in [0, 1)")
        _require(0.0 <= self.gae_lambda <= 1.0, "gae_lambda", self.gae_lambda, "in [0, 1]")
        _require(0.0 < self.lr < math.inf, "lr", self.lr, "a finite number > 0")
        _require(
            self.lr_schedule in get_args(LRSchedule),
            "lr_schedule",
            self.lr_schedule,
            "'constant' or 'linear'",
        )
        _require(0.0 < self.adam_eps < math.inf, "adam_eps", self.adam_eps, "a finite number > 0")
        for name in ("vf_coef", "ent_coef"):
            v = getattr(self, name)
            _require(_is_num(v) and 0.0 <= v < math.inf, name, v, "a finite number >= 0")
        for name in ("max_grad_norm", "clip_vf", "target_kl"):
            v = getattr(self, name)
            _require(
                v is None or (_is_num(v) and 0.0 < v < math.inf),
                name,
                v,
                "None or a finite number > 0",
            )
        _require(
            self.adv_norm in get_args(AdvNorm),
            "adv_norm",
            self.adv_norm,
            f"one of {list(get_args(AdvNorm))}",
        )
        for name in ("normalize_obs", "normalize_reward", "bootstrap_truncated", "layer_norm"):
            v = getattr(self, name)
            _require(isinstance(v, bool), name, v, "True or False")
        for name in ("clip_obs", "clip_reward"):
            v = getattr(self, name)
            _require(_is_num(v) and 0.0 < v < math.inf, name, v, "a finite number > 0")
        _require(
            self.policy in get_args(PolicyKind),
            "policy",
            self.policy,
            f"one of {list(get_args(PolicyKind))}",
        )
        _require(self.scale in get_args(ScaleMode), "scale", self.scale, "'global' or 'state'")
        _require(
            _is_num(self.log_std_init) and -20.0 <= self.log_std_init <= 5.0,
            "log_std_init",
            self.log_std_init,
            "a number in [-20, 5]",
        )
        _require(
            self.action_bound in get_args(ActionBound),
            "action_bound",
            self.action_bound,
            "'clip' or 'map'",
        )
        validate_network_fields(self)
        _require(self.init in get_args(Init), "init", self.init, "'default' or 'orthogonal'")

    @property
    def rollout_size(self) -> int:
        """Transitions per rollout: n_envs * n_steps."""
        return self.n_envs * self.n_steps

    @property
    def n_updates(self) -> int:
        """Number of updates: ceil(total_steps / rollout_size)."""
        return -(-self.total_steps // self.rollout_size)


_ZOO = "rl-baselines3-zoo hyperparams/ppo.yml"
_PYBULLET_ZOO: dict[str, Any] = {
    # rl-baselines3-zoo, hyperparams/ppo.yml, "HalfCheetahBulletEnv-v0: &pybullet-defaults"
    # (marked "Tuned"): normalize true, n_envs 16, n_timesteps 2e6, batch_size 128,
    # n_steps 512, gamma 0.99, gae_lambda 0.9, n_epochs 20, ent_coef 0.0,
    # max_grad_norm 0.5, vf_coef 0.5, learning_rate 3e-5, clip_range 0.4,
    # use_sde True (sde_sample_freq 4), policy_kwargs log_std_init -2, ortho_init False,
    # activation_fn nn.ReLU, net_arch pi/vf [256, 256].
    "normalize_obs": True,
    "normalize_reward": True,
    "n_envs": 16,
    "total_steps": 2_000_000,
    "batch_size": 128,
    "n_steps": 512,
    "gamma": 0.99,
    "gae_lambda": 0.9,
    "n_epochs": 20,
    "ent_coef": 0.0,
    "max_grad_norm": 0.5,
    "vf_coef": 0.5,
    "lr": 3e-5,
    "eps": 0.4,
    "log_std_init": -2.0,
    "init": "default",
    "activation": "relu",
    "layers": 2,
    "units": 256,
}

ZOO_DEFAULTS: dict[str, dict[str, Any]] = {
    "halfcheetah": dict(_PYBULLET_ZOO),
    # AntBulletEnv-v0 inherits the pybullet defaults above; its own entry sets
    # learning_rate 3e-5 and policy_kwargs log_std_init -1 (not -2), ortho_init False,
    # ReLU, pi/vf [256, 256].
    "ant": {**_PYBULLET_ZOO, "log_std_init": -1.0},
    # InvertedPendulumSwingupBulletEnv-v0 (zoo, untuned entry): normalize true, n_envs 8,
    # n_timesteps 2e6, n_steps 2048, batch_size 64, gae_lambda 0.95, gamma 0.99,
    # n_epochs 10, ent_coef 0.0, learning_rate 2.5e-4, clip_range 0.2; the rest are SB3's
    # PPO defaults (2 x 64 tanh, ortho_init, log_std_init 0, max_grad_norm 0.5, vf_coef 0.5).
    "swingup": {
        "normalize_obs": True,
        "normalize_reward": True,
        "n_envs": 8,
        "total_steps": 2_000_000,
        "n_steps": 2048,
        "batch_size": 64,
        "gae_lambda": 0.95,
        "gamma": 0.99,
        "n_epochs": 10,
        "ent_coef": 0.0,
        "lr": 2.5e-4,
        "eps": 0.2,
    },
    # InvertedPendulumBulletEnv-v0 has no PPO entry in the zoo. These are the zoo's
    # settings for its Bullet sibling InvertedPendulumSwingupBulletEnv-v0 (normalize,
    # n_envs 8, batch 64, gae_lambda 0.95, gamma 0.99, n_epochs 10, lr 2.5e-4, clip 0.2,
    # SB3's default 2 x 64 tanh networks), with a shorter rollout (n_steps 256, i.e.
    # 2048 transitions per update instead of 16384) because the balancing task is learnt
    # in about 1e5 steps and the zoo's 16384-step rollouts would give only a handful of
    # updates in that budget, and total_steps 2e5 (SB3's PPO solves it well within).
}
"""Per-task defaults keyed by env alias, from rl-baselines3-zoo's ``hyperparams/ppo.yml``
(the source of each value is noted beside it). The zoo's PyBullet entries use
generalised state-dependent exploration (``use_sde True``); gSDE is **not** implemented
here, so these runs explore with the plain Gaussian of ``log_std_init``."""
# InvertedPendulum: the swingup entry with a shorter rollout and budget (see the comment above)
ZOO_DEFAULTS["pendulum"] = {**ZOO_DEFAULTS["swingup"], "n_steps": 256, "total_steps": 200_000}


def zoo_config(env: str, **overrides: Any) -> BatchConfig:
    """A :class:`BatchConfig` for ``env`` from :data:`ZOO_DEFAULTS`, then ``overrides``.

    ``env`` may be an alias or its Gymnasium id (e.g. ``HalfCheetahBulletEnv-v0``); a task
    without an entry gets the plain :class:`BatchConfig` defaults.
    """
    key = env.strip().lower()
    by_id = {v.lower(): k for k, v in ALIASES.items()}
    key = by_id.get(key, key)
    base = dict(ZOO_DEFAULTS.get(key, {}))
    return BatchConfig(env=env, **{**base, **overrides})


# ----------------------------------------------------------------------------------------
# Normalisation
# ----------------------------------------------------------------------------------------
class RunningMeanStd:
    """Running mean and variance of batches of vectors, in float64.

    Batches are merged with the parallel algorithm of Chan, Golub and LeVeque (1979):
    for counts n_a, n_b, means m_a, m_b and sums of squared deviations M_a, M_b,
    ``m = m_a + (m_b - m_a) n_b / n`` and ``M = M_a + M_b + (m_b - m_a)^2 n_a n_b / n``.
    The count starts at a tiny ``epsilon`` (mean 0, var 1) so the first batch dominates.
    """

    def __init__(self, shape: tuple[int, ...] = (), epsilon: float = 1e-4) -> None:
        self.mean = np.zeros(shape, dtype=np.float64)
        self.var = np.ones(shape, dtype=np.float64)
        self.count = float(epsilon)

    def update(self, batch: np.ndarray) -> None:
        """Merge a batch of shape ``[n, *shape]``."""
        x = np.asarray(batch, dtype=np.float64)
        n = x.shape[0]
        if n == 0:
            return
        b_mean = x.mean(axis=0)
        b_var = x.var(axis=0)
        total = self.count + n
        delta = b_mean - self.mean
        m2 = self.var * self.count + b_var * n + delta * delta * self.count * n / total
        self.mean = self.mean + delta * n / total
        self.var = m2 / total
        self.count = total

    def state_dict(self) -> dict[str, Any]:
        """Copies of mean, var and count."""
        return {"mean": self.mean.copy(), "var": self.var.copy(), "count": self.count}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.mean = np.array(state["mean"], dtype=np.float64)
        self.var = np.array(state["var"], dtype=np.float64)
        self.count = float(state["count"])


class Normalizer:
    """Observation and reward normalisation of a vector environment's outputs.

    * Observations: ``clip((obs - mean) / sqrt(var + 1e-8), -clip_obs, clip_obs)`` with the
      running statistics of every observation the learner acts on (the final observations
      of finished episodes are normalised but not counted).
    * Rewards: ``clip(r / sqrt(var(G) + 1e-8), -clip_reward, clip_reward)`` where
      ``G <- gamma * G + r`` is each sub-environment's running discounted return, reset
      when its episode ends (terminated or truncated). Not centred, so the sign of a
      reward is kept.
    """

    def __init__(self, obs_dim: int, n_envs: int, cfg: BatchConfig) -> None:
        self.cfg = cfg
        self.obs_rms = RunningMeanStd((obs_dim,))
        self.ret_rms = RunningMeanStd(())
        self.returns = np.zeros(n_envs, dtype=np.float64)

    def obs(self, obs: np.ndarray, update: bool) -> np.ndarray:
        """Normalised float32 observations (``update`` counts them in the statistics)."""
        if not self.cfg.normalize_obs:
            return np.asarray(obs, dtype=np.float32)
        if update:
            self.obs_rms.update(obs)
        out = (np.asarray(obs, dtype=np.float64) - self.obs_rms.mean) / np.sqrt(
            self.obs_rms.var + 1e-8
        )
        return np.clip(out, -self.cfg.clip_obs, self.cfg.clip_obs).astype(np.float32)

    def reward(self, reward: np.ndarray, done: np.ndarray) -> np.ndarray:
        """Normalised float32 rewards of one vector step; ``done`` = terminated | truncated."""
        r = np.asarray(reward, dtype=np.float64)
        if not self.cfg.normalize_reward:
            return r.astype(np.float32)
        self.returns = self.returns * self.cfg.gamma + r
        self.ret_rms.update(self.returns)
        out = np.clip(
            r / np.sqrt(self.ret_rms.var + 1e-8), -self.cfg.clip_reward, self.cfg.clip_reward
        )
        self.returns[np.asarray(done, dtype=bool)] = 0.0
        return out.astype(np.float32)

    def state_dict(self) -> dict[str, Any]:
        """Statistics and the running returns."""
        return {
            "obs_rms": self.obs_rms.state_dict(),
            "ret_rms": self.ret_rms.state_dict(),
            "returns": self.returns.copy(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.obs_rms.load_state_dict(state["obs_rms"])
        self.ret_rms.load_state_dict(state["ret_rms"])
        self.returns = np.array(state["returns"], dtype=np.float64)


# ----------------------------------------------------------------------------------------
# Networks
# ----------------------------------------------------------------------------------------
_HALF_LOG_2PI_E = 0.5 * (1.0 + math.log(2.0 * math.pi))


def _inv_softplus(y: float) -> float:
    """x with softplus(x) = y (y > 0)."""
    return y + math.log(-math.expm1(-y))


class ActorCritic:
    """Policy and value networks whose parameters are views into one flat vector.

    The policy network (``mlp``) outputs the location of u (and, with
    ``scale="state"``, the head's scale and degrees-of-freedom inputs); with
    ``scale="global"`` those are free parameters, as Stable-Baselines3's ``log_std``. The
    value network is separate. All parameters live in :attr:`theta` (policy block, global
    head parameters, value block) and their gradients in :attr:`grad`, so gradient
    clipping and Adam are one whole-vector operation each.
    """

    def __init__(self, obs_dim: int, action_low: Any, action_high: Any, cfg: BatchConfig) -> None:
        self.cfg = cfg
        self.action_map = ActionMap(
            torch.as_tensor(np.asarray(action_low, dtype=np.float32)),
            torch.as_tensor(np.asarray(action_high, dtype=np.float32)),
        )
        self.obs_dim = obs_dim
        self.act_dim = act_dim = self.action_map.act_dim
        self.low = torch.as_tensor(np.asarray(action_low, dtype=np.float32)).reshape(-1)
        self.high = torch.as_tensor(np.asarray(action_high, dtype=np.float32)).reshape(-1)
        self.head: PolicyHead = make_head(cfg.policy, act_dim)
        self._normal = isinstance(self.head, NormalHead)
        ortho = cfg.init == "orthogonal"
        net_kw: dict[str, Any] = dict(
            layers=cfg.layers,
            units=cfg.units,
            layer_norm=cfg.layer_norm,
            activation=cfg.activation,
            init=cfg.init,
        )
        self.global_scale = cfg.scale == "global"
        pol_out = act_dim if self.global_scale else self.head.raw_dim
        policy_net = mlp(obs_dim, pol_out, output_gain=0.01 if ortho else None, **net_kw)
        value_net = mlp(obs_dim, 1, output_gain=1.0 if ortho else None, **net_kw)
        scale_raw0 = _inv_softplus(math.exp(cfg.log_std_init) - self.head.min_scale)
        n_extra = self.head.raw_dim - act_dim  # scale (act_dim) and, for student-t, df (1)
        extra = torch.zeros(n_extra)
        extra[:act_dim] = scale_raw0
        if not self.global_scale:
            with torch.no_grad():  # start the scale outputs at exp(log_std_init)
                last = policy_net[-1]
                assert isinstance(last, torch.nn.Linear)
                last.bias[act_dim : 2 * act_dim] = scale_raw0
        self._policy_fn = FlatMLP(policy_net)
        self._value_fn = FlatMLP(value_net)
        pol = [p.detach() for p in policy_net.parameters()]
        val = [p.detach() for p in value_net.parameters()]
        if not self.global_scale:
            extra = torch.zeros(0)
        shapes = [p.shape for p in pol] + [extra.shape] + [p.shape for p in val]
        self.theta = torch.cat([t.reshape(-1) for t in [*pol, extra, *val]]).contiguous()
        self.grad = torch.zeros_like(self.theta)
        leaves = flat_views(self.theta, shapes)
        grads = flat_views(self.grad, shapes)
        for leaf, g in zip(leaves, grads, strict=True):
            leaf.requires_grad_(True)
            leaf.grad = g
        k = len(pol)
        self._pol, self._extra, self._val = leaves[:k], leaves[k], leaves[k + 1 :]
        self.theta.grad = self.grad  # what the optimiser reads

    # -- forward --------------------------------------------------------------------------
    def raw(self, obs: Tensor) -> Tensor:
        """The head's raw input ``[..., raw_dim]`` for a batch of (normalised) observations."""
        out = self._policy_fn(self._pol, obs)
        if not self.global_scale:
            return out
        return torch.cat([out, self._extra.expand(*out.shape[:-1], -1)], dim=-1)

    def log_prob(self, obs: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``(log pi(u|s), raw)`` for a batch: what the policy loss needs.

        With ``scale="global"`` the returned ``raw`` is the single row
        ``[0, scale_raw(, df_raw)]`` and the density is evaluated as
        ``head.log_prob(raw_row, u - loc)``: both heads are location families, so this
        equals ``head.log_prob(self.raw(obs), u)`` without building a ``[batch, raw_dim]``
        tensor (fewer operations per minibatch).
        """
        if not self.global_scale:
            raw = self._policy_fn(self._pol, obs)
            return self.head.log_prob(raw, u), raw
        loc = self._policy_fn(self._pol, obs)
        row = torch.cat([torch.zeros(self.act_dim), self._extra])
        return self.head.log_prob(row, u - loc), row

    def value(self, obs: Tensor) -> Tensor:
        """V(s), shape ``[...]``."""
        return self._value_fn(self._val, obs)[..., 0]

    def entropy(self, raw: Tensor) -> Tensor:
        """Entropy of pi(u|s) per row (closed form for the Normal head)."""
        if self._normal:
            _, scale = self.head.split(raw)
            return torch.log(scale).sum(-1) + self.act_dim * _HALF_LOG_2PI_E
        return self.head.distribution(raw).entropy()

    def sample(self, raw: Tensor) -> Tensor:
        """A sample of u ~ pi(.|s) (global torch RNG)."""
        if self._normal:
            loc, scale = self.head.split(raw)
            return loc + scale * torch.randn_like(loc)
        return self.head.distribution(raw).sample()

    def to_action(self, u: Tensor) -> Tensor:
        """Map u into the action box: clip (default) or the sigmoid ActionMap."""
        if self.cfg.action_bound == "map":
            return self.action_map.to_action(u)
        return torch.maximum(torch.minimum(u, self.high), self.low)

    def parameters_finite(self) -> bool:
        """Whether every parameter is finite."""
        return bool(torch.isfinite(self.theta).all())


# ----------------------------------------------------------------------------------------
# Rollouts and GAE
# ----------------------------------------------------------------------------------------
def compute_gae(
    rewards: Tensor,
    values: Tensor,
    next_values: Tensor,
    terminated: Tensor,
    truncated: Tensor,
    gamma: float,
    gae_lambda: float,
    bootstrap_truncated: bool = True,
) -> tuple[Tensor, Tensor]:
    r"""GAE(lambda) advantages and lambda-returns of ``[T, n_envs]`` rollouts.

    For step t of one sub-environment, with ``next_values[t]`` the value of the state
    reached by that step (the final observation when the episode ended there):

    .. math:: \delta_t = r_t + \gamma\,(1 - \mathrm{term}_t)\,V'_t - V_t, \qquad
              A_t = \delta_t + \gamma\lambda\,(1 - \mathrm{term}_t)(1 - \mathrm{trunc}_t)\,A_{t+1}

    with A_T = 0: a termination is not bootstrapped, a truncation is (by V of the final
    observation), and either ends the lambda chain. With ``bootstrap_truncated=False`` a
    truncation is treated like a termination. Returns ``(advantages, advantages + values)``.
    """
    term = terminated.to(values.dtype)
    trunc = truncated.to(values.dtype)
    stop = term if bootstrap_truncated else torch.clamp(term + trunc, max=1.0)
    delta = rewards + gamma * (1.0 - stop) * next_values - values
    carry = gamma * gae_lambda * (1.0 - term) * (1.0 - trunc)
    adv = torch.empty_like(delta)
    last = torch.zeros_like(delta[0])
    for t in range(delta.shape[0] - 1, -1, -1):
        last = torch.addcmul(delta[t], carry[t], last, out=adv[t])
    return adv, adv + values


class RolloutBuffer:
    """Preallocated ``[n_steps, n_envs, ...]`` tensors of one rollout."""

    def __init__(self, n_steps: int, n_envs: int, obs_dim: int, act_dim: int) -> None:
        shape = (n_steps, n_envs)
        self.obs = torch.zeros(*shape, obs_dim)
        """Normalised observations s_t."""
        self.u = torch.zeros(*shape, act_dim)
        """Pre-map actions u_t (what the ratio is computed on)."""
        self.logp = torch.zeros(shape)
        """log pi_old(u_t|s_t)."""
        self.values = torch.zeros(shape)
        """V_old(s_t)."""
        self.rewards = torch.zeros(shape)
        """Normalised rewards r_t."""
        self.terminated = torch.zeros(shape, dtype=torch.bool)
        """The episode ended at step t with a true termination."""
        self.truncated = torch.zeros(shape, dtype=torch.bool)
        """The episode ended at step t by a time limit (and did not terminate)."""
        self.next_values = torch.zeros(shape)
        """V_old of the state reached by step t (final observation at an episode's end)."""
        self.advantages = torch.zeros(shape)
        """GAE(lambda) advantages (filled by :func:`compute_gae`)."""
        self.returns = torch.zeros(shape)
        """Lambda-returns: targets of the value function."""


@dataclass(frozen=True)
class FinishedEpisode:
    """An episode that ended during a rollout (raw, unnormalised rewards)."""

    env_index: int
    """Which sub-environment."""
    ret: float
    """Undiscounted return."""
    length: int
    """Steps in the episode."""
    total_steps: int
    """Environment steps over all sub-environments when it ended."""
    terminated: bool
    """True end (else a truncation)."""


@dataclass(frozen=True)
class UpdateStats:
    """What one :meth:`BatchLearner.train` call did, as 0-dim tensors (no ``.item()``)."""

    policy_loss: Tensor
    """Mean over minibatches of -mean(surrogate objective)."""
    value_loss: Tensor
    """Mean over minibatches of the (optionally clipped) squared value error."""
    entropy: Tensor
    """Mean entropy of pi(u|s) over the last minibatch, after its step's loss."""
    approx_kl: Tensor
    """Mean of (rho - 1) - log rho over every sample of every epoch (KL(pi_old || pi))."""
    grad_norm: Tensor
    """Mean global gradient norm before clipping."""
    reg_amount: Tensor
    """Mean sigma*(rho - rho_dagger) over every sample of every epoch
    (:func:`pporpe.surrogates.regularization_amount`)."""
    past_threshold: Tensor
    """Fraction of those samples past the surrogate's threshold (PPO's clip fraction)."""
    ratio_dev: Tensor
    """Mean |rho - 1| over those samples."""
    explained_variance: Tensor
    """1 - Var(returns - V_old) / Var(returns) of the rollout."""
    lr: Tensor
    """Learning rate used."""
    epochs: Tensor
    """Epochs run (fewer than n_epochs after a target_kl stop)."""

    def as_dict(self) -> dict[str, float]:
        """Python floats (synchronises; for logging only)."""
        return {k: float(getattr(self, k)) for k in self.__dataclass_fields__}


# ----------------------------------------------------------------------------------------
# Replayable sub-environments (exact resume)
# ----------------------------------------------------------------------------------------
class _Replayable(gymnasium.Wrapper):
    """Records how the current episode was reached, so that a checkpoint can rebuild it.

    On ``reset`` it keeps the seed (or the environment's RNG state when no seed is given)
    and on ``step`` every action; :meth:`replay_record` returns them and
    :meth:`replay_apply` replays a record on a fresh environment.
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)
        self._start: dict[str, Any] = {}
        self._actions: list[np.ndarray] = []
        self.replay_pending: dict[str, Any] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        rng = None
        if seed is None:
            rng = copy.deepcopy(self.env.unwrapped.np_random.bit_generator.state)
        self._start = {"seed": seed, "rng": rng, "options": options}
        self._actions = []
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> Any:
        self._actions.append(np.array(action, copy=True))
        return self.env.step(action)

    def replay_record(self) -> dict[str, Any]:
        """The current episode's start and actions (a copy)."""
        acts = np.stack(self._actions) if self._actions else np.zeros((0,))
        return {**copy.deepcopy(self._start), "actions": acts}

    def replay_apply(self) -> Any:
        """Rebuild the episode in :attr:`replay_pending`; return its current observation."""
        rec = self.replay_pending
        assert rec is not None
        self.replay_pending = None
        if rec["rng"] is not None:
            self.env.unwrapped.np_random.bit_generator.state = rec["rng"]
        obs = self.reset(seed=rec["seed"], options=rec["options"])[0]
        for a in rec["actions"]:
            obs = self.step(a)[0]
        return obs


def _make_sub_env(name: str, seed: int) -> Callable[[], gymnasium.Env]:
    def thunk() -> gymnasium.Env:
        return _Replayable(make_env(name, seed=seed))

    return thunk


def make_vec_env(cfg: BatchConfig) -> VecEnv:
    """The vector environment of a run, in SAME_STEP autoreset mode (see module docstring)."""
    fns = [_make_sub_env(cfg.env, cfg.seed + i) for i in range(cfg.n_envs)]
    if cfg.vec_env == "async":
        return AsyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)
    return SyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)


# ----------------------------------------------------------------------------------------
# The learner
# ----------------------------------------------------------------------------------------
class BatchLearner:
    """Batch PPO / PPO-RB / PPO-RPE: vector-env rollouts, GAE, minibatch epochs.

    Usage::

        learner = BatchLearner(cfg)            # builds and resets the vector environment
        for _ in range(cfg.n_updates):
            episodes = learner.collect_rollouts()
            stats = learner.train()
        learner.close()

    The global torch RNG drives initialisation, action sampling and minibatch order, so
    seed it first (:func:`train_batch` does: ``torch.manual_seed(cfg.seed)``).
    """

    def __init__(self, cfg: BatchConfig, envs: VecEnv | None = None) -> None:
        self.cfg = cfg
        self.envs = envs if envs is not None else make_vec_env(cfg)
        mode = self.envs.metadata.get("autoreset_mode")
        if mode != AutoresetMode.SAME_STEP:
            raise ValueError(
                f"the vector environment must use autoreset_mode=SAME_STEP; got {mode!r} "
                "(NEXT_STEP would store one dummy transition per finished episode)"
            )
        space = self.envs.single_action_space
        obs_space = self.envs.single_observation_space
        low, high = getattr(space, "low", None), getattr(space, "high", None)
        obs_shape = tuple(obs_space.shape or ())
        if low is None or high is None or len(obs_shape) != 1:
            raise ValueError("batch PPO needs Box actions and 1-D Box observations")
        obs_dim = int(obs_shape[0])
        self.model = ActorCritic(obs_dim, low, high, cfg)
        self.optimizer = torch.optim.Adam(
            [self.model.theta], lr=cfg.lr, eps=cfg.adam_eps, foreach=False, fused=True
        )
        self.normalizer = Normalizer(obs_dim, cfg.n_envs, cfg)
        self.buffer = RolloutBuffer(cfg.n_steps, cfg.n_envs, obs_dim, self.model.act_dim)
        self.updates = 0
        """Updates done."""
        self.total_steps = 0
        """Environment steps taken (all sub-environments)."""
        self.ep_ret = np.zeros(cfg.n_envs, dtype=np.float64)
        self.ep_len = np.zeros(cfg.n_envs, dtype=np.int64)
        raw_obs, _ = self.envs.reset(seed=cfg.seed)
        self._raw_obs = np.asarray(raw_obs)
        self._obs = self.normalizer.obs(self._raw_obs, update=True)
        n = cfg.rollout_size
        self._n_mb = -(-n // cfg.batch_size)
        self._diag_ratio = torch.zeros(cfg.n_epochs * n)
        self._diag_adv = torch.zeros(cfg.n_epochs * n)
        self._mb_stats = torch.zeros(cfg.n_epochs * self._n_mb, 3)

    # -- acting ----------------------------------------------------------------------------
    @torch.no_grad()
    def collect_rollouts(self) -> list[FinishedEpisode]:
        """Fill the buffer with n_steps vector steps of the current policy; compute GAE.

        Returns the episodes that ended during the rollout.
        """
        cfg, model, buf, norm = self.cfg, self.model, self.buffer, self.normalizer
        finished: list[FinishedEpisode] = []
        obs = torch.from_numpy(self._obs)
        for t in range(cfg.n_steps):
            raw = model.raw(obs)
            u = model.sample(raw)
            buf.obs[t] = obs
            buf.u[t] = u
            buf.logp[t] = model.head.log_prob(raw, u)
            buf.values[t] = model.value(obs)
            action = model.to_action(u).numpy()
            raw_next, reward, term, trunc, info = self.envs.step(action)
            term = np.asarray(term, dtype=bool)
            trunc = np.asarray(trunc, dtype=bool) & ~term
            done = term | trunc
            reward = np.asarray(reward, dtype=np.float64)
            if not (np.all(np.isfinite(reward)) and np.all(np.isfinite(raw_next))):
                raise NonFiniteError(f"non-finite reward or observation at step {self.total_steps}")
            self.total_steps += cfg.n_envs
            self.ep_ret += reward
            self.ep_len += 1
            buf.rewards[t] = torch.from_numpy(norm.reward(reward, done))
            buf.terminated[t] = torch.from_numpy(term)
            buf.truncated[t] = torch.from_numpy(trunc)
            self._raw_obs = np.asarray(raw_next)
            obs = torch.from_numpy(norm.obs(self._raw_obs, update=True))
            if done.any():
                idx = np.nonzero(trunc)[0]
                if idx.size:
                    final = np.stack([np.asarray(info["final_obs"][i]) for i in idx])
                    fv = model.value(torch.from_numpy(norm.obs(final, update=False)))
                    buf.next_values[t, torch.from_numpy(idx)] = fv
                for i in np.nonzero(done)[0]:
                    finished.append(
                        FinishedEpisode(
                            int(i),
                            float(self.ep_ret[i]),
                            int(self.ep_len[i]),
                            self.total_steps,
                            bool(term[i]),
                        )
                    )
                self.ep_ret[done] = 0.0
                self.ep_len[done] = 0
        self._obs = obs.numpy()
        last_value = model.value(obs)
        # V of the state each step reached: the next step's V(s_{t+1}) unless the episode
        # ended (then V(final obs) was stored above for truncations; terminations ignore it)
        nxt = torch.cat([buf.values[1:], last_value[None]])
        ended = buf.terminated | buf.truncated
        buf.next_values.copy_(torch.where(ended, buf.next_values, nxt))
        adv, ret = compute_gae(
            buf.rewards,
            buf.values,
            buf.next_values,
            buf.terminated,
            buf.truncated,
            cfg.gamma,
            cfg.gae_lambda,
            cfg.bootstrap_truncated,
        )
        buf.advantages.copy_(adv)
        buf.returns.copy_(ret)
        return finished

    @torch.no_grad()
    def act_deterministic(self, obs: Any) -> np.ndarray:
        """Test-time action for one raw observation: the policy's location, bounded.

        Uses the frozen observation statistics (nothing is updated).
        """
        x = torch.from_numpy(self.normalizer.obs(np.asarray(obs)[None], update=False))
        loc = self.model.head.location(self.model.raw(x))
        return self.model.to_action(loc)[0].numpy()

    # -- learning ----------------------------------------------------------------------------
    def current_lr(self) -> float:
        """The learning rate of the next update under the schedule."""
        if self.cfg.lr_schedule == "linear":
            return self.cfg.lr * max(0.0, 1.0 - self.updates / self.cfg.n_updates)
        return self.cfg.lr

    def _minibatch_loss(self, mb: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Loss of one minibatch of packed rows [obs, u, logp_old, adv, ret, v_old].

        Returns the loss, the detached policy and value losses, the detached ratios, the
        advantages used and the head's raw input (for the entropy statistic).
        """
        cfg, model = self.cfg, self.model
        d, a = model.obs_dim, model.act_dim
        obs, u = mb[:, :d], mb[:, d : d + a]
        logp_old, adv = mb[:, d + a], mb[:, d + a + 1]
        ret, v_old = mb[:, d + a + 2], mb[:, d + a + 3]
        if cfg.adv_norm == "minibatch" and mb.shape[0] > 1:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        logp, raw = model.log_prob(obs, u)
        ratio = torch.exp(logp - logp_old)
        objective = _surrogate_objective(
            cfg.method, ratio, adv, cfg.eps, cfg.beta, cfg.eta, cfg.rpe_form
        )
        policy_loss = -objective.mean()
        v = model.value(obs)
        if cfg.clip_vf is not None:
            v_clip = v_old + torch.clamp(v - v_old, -cfg.clip_vf, cfg.clip_vf)
            value_loss = torch.maximum((v - ret).square(), (v_clip - ret).square()).mean()
        else:
            value_loss = (v - ret).square().mean()
        loss = policy_loss + cfg.vf_coef * value_loss
        if cfg.ent_coef > 0.0:
            loss = loss - cfg.ent_coef * model.entropy(raw).mean()
        return loss, policy_loss.detach(), value_loss.detach(), ratio.detach(), adv, raw

    def train(self) -> UpdateStats:
        """One PPO update on the collected rollout: n_epochs of shuffled minibatches.

        Each epoch draws one permutation and gathers the packed rollout once, so a
        minibatch is a contiguous slice. Per minibatch: loss, backward into the flat
        gradient, global-norm clipping, one fused Adam step.
        """
        cfg, model, buf = self.cfg, self.model, self.buffer
        n, bs = cfg.rollout_size, cfg.batch_size
        lr = self.current_lr()
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        adv = buf.advantages.reshape(n)
        if cfg.adv_norm == "batch":
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        packed = torch.cat(
            [
                buf.obs.reshape(n, -1),
                buf.u.reshape(n, -1),
                buf.logp.reshape(n, 1),
                adv.reshape(n, 1),
                buf.returns.reshape(n, 1),
                buf.values.reshape(n, 1),
            ],
            dim=1,
        )
        grad = model.grad
        stats_rows = pos = 0
        epochs = 0
        stop = False
        raw = torch.zeros(0)
        for _epoch in range(cfg.n_epochs):
            perm = torch.randperm(n)
            shuffled = packed[perm]
            for start in range(0, n, bs):
                mb = shuffled[start : start + bs]
                loss, pl, vl, ratio, mb_adv, raw = self._minibatch_loss(mb)
                if cfg.target_kl is not None:
                    kl = float((ratio - 1.0 - torch.log(ratio)).mean())
                    if kl > 1.5 * cfg.target_kl:
                        stop = True
                        break
                grad.zero_()
                loss.backward()
                with torch.no_grad():
                    norm = torch.linalg.vector_norm(grad)
                    if cfg.max_grad_norm is not None:
                        grad.mul_(torch.clamp(cfg.max_grad_norm / (norm + 1e-6), max=1.0))
                    self.optimizer.step()
                    self._diag_ratio[pos : pos + mb.shape[0]] = ratio
                    self._diag_adv[pos : pos + mb.shape[0]] = mb_adv
                    pos += mb.shape[0]
                    torch.stack([pl, vl, norm], out=self._mb_stats[stats_rows])
                stats_rows += 1
            if stop:
                break
            epochs += 1
        self.updates += 1
        return self._update_stats(stats_rows, pos, epochs, lr, raw)

    @torch.no_grad()
    def _update_stats(
        self, rows: int, samples: int, epochs: int, lr: float, raw: Tensor
    ) -> UpdateStats:
        cfg, buf = self.cfg, self.buffer
        means = self._mb_stats[:rows].mean(0) if rows else torch.full((3,), float("nan"))
        ratio = self._diag_ratio[:samples]
        adv = self._diag_adv[:samples]
        nan = torch.tensor(float("nan"))
        if rows:
            reg = regularization_amount(cfg.method, ratio, adv, cfg.eps, cfg.beta, cfg.eta)
            reg_amount, past = reg.amount.mean(), reg.fraction_past_threshold
            ratio_dev = (ratio - 1.0).abs().mean()
            approx_kl = (ratio - 1.0 - torch.log(ratio)).mean()
            entropy = self.model.entropy(raw).mean()
        else:
            reg_amount = past = ratio_dev = torch.tensor(0.0)
            approx_kl = entropy = nan
        ret, val = buf.returns.reshape(-1), buf.values.reshape(-1)
        var_ret = ret.var()
        ev = torch.where(var_ret > 0, 1.0 - (ret - val).var() / var_ret, nan)
        return UpdateStats(
            policy_loss=means[0],
            value_loss=means[1],
            entropy=entropy,
            approx_kl=approx_kl,
            grad_norm=means[2],
            reg_amount=reg_amount,
            past_threshold=past,
            ratio_dev=ratio_dev,
            explained_variance=ev,
            lr=torch.tensor(lr),
            epochs=torch.tensor(epochs),
        )

    # -- state ---------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly (see the module docstring on resume)."""
        return copy.deepcopy(
            {
                "theta": self.model.theta.clone(),
                "optimizer": self.optimizer.state_dict(),
                "normalizer": self.normalizer.state_dict(),
                "updates": self.updates,
                "total_steps": self.total_steps,
                "ep_ret": self.ep_ret.copy(),
                "ep_len": self.ep_len.copy(),
                "raw_obs": self._raw_obs.copy(),
                "obs": self._obs.copy(),
                "envs": list(self.envs.call("replay_record")),
            }
        )

    def load_state_dict(self, state: dict[str, Any], restore_envs: bool = True) -> None:
        """Restore :meth:`state_dict`; ``restore_envs`` replays every sub-environment's
        current episode so that training continues exactly where it stopped."""
        with torch.no_grad():
            self.model.theta.copy_(state["theta"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.normalizer.load_state_dict(state["normalizer"])
        self.updates = int(state["updates"])
        self.total_steps = int(state["total_steps"])
        self.ep_ret = np.array(state["ep_ret"], dtype=np.float64)
        self.ep_len = np.array(state["ep_len"], dtype=np.int64)
        self._raw_obs = np.array(state["raw_obs"])
        self._obs = np.array(state["obs"], dtype=np.float32)
        if restore_envs:
            self.envs.set_attr("replay_pending", list(state["envs"]))
            replayed = np.stack([np.asarray(o) for o in self.envs.call("replay_apply")])
            if not np.array_equal(replayed, self._raw_obs):
                warnings.warn(
                    "replaying the environments' episodes did not reproduce the saved "
                    "observations (the environment is not deterministic given its seed and "
                    "actions); training continues from the replayed states",
                    RuntimeWarning,
                    stacklevel=2,
                )
                self._raw_obs = replayed
                self._obs = self.normalizer.obs(replayed, update=False)

    def close(self) -> None:
        """Close the vector environment."""
        self.envs.close()


# ----------------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------------
def evaluate_learner(learner: BatchLearner, episodes: int, seed: int | None = None) -> EvalResult:
    """Test episodes of the deterministic policy via :func:`pporpe.evaluation.evaluate_policy`.

    ``seed`` defaults to the training seed plus :data:`~pporpe.evaluation.EVAL_SEED_OFFSET`.
    """
    if seed is None:
        seed = learner.cfg.seed + EVAL_SEED_OFFSET
    return evaluate_policy(learner.act_deterministic, learner.cfg.env, episodes, seed)


# ----------------------------------------------------------------------------------------
# Logging
# ----------------------------------------------------------------------------------------
class _UpdateLog:
    """Per-episode records (:class:`EpisodeRecord`) and per-update TensorBoard scalars.

    Episodes that end during rollout k get the diagnostics of update k, the update that
    learns from them: ``reg_amount``, ``past_threshold`` and ``ratio_dev`` from
    :class:`UpdateStats`. ``trace_decay`` is 1.0: batch PPO has no eligibility traces and
    so no adaptive trace decay (1.0 = no decay), and a number (not NaN) keeps records
    comparable with ``==``.
    """

    def __init__(self, run: Path) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.logger = RunLogger(run)
        self._tb = SummaryWriter(log_dir=str(run / "tensorboard"), filename_suffix=".updates")

    def records(
        self,
        episodes: list[FinishedEpisode],
        stats: UpdateStats,
        first_index: int,
        wall_time: float,
    ) -> list[EpisodeRecord]:
        reg, past, dev = (
            float(stats.reg_amount),
            float(stats.past_threshold),
            float(stats.ratio_dev),
        )
        out = []
        for k, ep in enumerate(episodes):
            rec = EpisodeRecord(
                episode=first_index + k,
                total_steps=ep.total_steps,
                ret=ep.ret,
                length=ep.length,
                reg_amount=reg,
                past_threshold=past,
                trace_decay=1.0,
                ratio_dev=dev,
                wall_time=wall_time,
            )
            self.logger.episode(rec)
            out.append(rec)
        return out

    def update(self, stats: UpdateStats, step: int) -> dict[str, float]:
        values = stats.as_dict()
        for name, value in values.items():
            self._tb.add_scalar(f"update/{name}", value, step)
        return values

    def close(self) -> None:
        self.logger.close()
        self._tb.flush()
        self._tb.close()


# ----------------------------------------------------------------------------------------
# Runs
# ----------------------------------------------------------------------------------------
@dataclass
class BatchResult:
    """What :func:`train_batch` produced."""

    run_dir: Path
    """The run folder."""
    records: list[EpisodeRecord]
    """Every finished training episode."""
    evaluation: EvalResult | None
    """Test-episode summary, if ``eval_episodes`` > 0."""
    resumed_from: int
    """Updates already done when this call started (0 for a fresh run)."""
    updates: int
    """Updates done in all."""
    total_steps: int
    """Environment steps done in all."""
    train_time: float
    """Seconds of training over all segments (acting + learning + logging + checkpoints,
    not evaluation or ``on_update`` callbacks)."""
    last_stats: dict[str, float] = field(default_factory=dict)
    """The last update's :class:`UpdateStats` as floats (empty when nothing ran)."""


def _config_json(cfg: BatchConfig) -> dict[str, Any]:
    return {"learner": "batch", **config_to_dict(cfg)}


def load_batch_learner(
    run_dir: str | Path, build_envs: bool = False
) -> tuple[BatchConfig, BatchLearner]:
    """Rebuild the learner of a batch run folder from its config and latest checkpoint.

    With ``build_envs=False`` (enough for :meth:`BatchLearner.act_deterministic`) a single
    sub-environment is built and the saved episodes are not replayed.
    """
    run = Path(run_dir)
    if not (run / "config.json").exists() or not (run / CHECKPOINT).exists():
        raise ValueError(f"{run} is not a run folder (needs config.json and {CHECKPOINT})")
    data = json.loads((run / "config.json").read_text())
    data.pop("learner", None)
    cfg = config_from_dict(BatchConfig, data, str(run / "config.json"))
    state = torch.load(run / CHECKPOINT, weights_only=False)
    envs_cfg = cfg if build_envs else dataclasses.replace(cfg, n_envs=1, batch_size=1)
    learner = BatchLearner(envs_cfg)
    learner.cfg = cfg
    if build_envs:
        learner.load_state_dict(state["learner"])
    else:
        with torch.no_grad():
            learner.model.theta.copy_(state["learner"]["theta"])
        learner.normalizer.obs_rms.load_state_dict(state["learner"]["normalizer"]["obs_rms"])
    return cfg, learner


def _finished_result(run: Path) -> BatchResult:
    evaluation = load_evaluation(run)
    done = json.loads((run / "done.json").read_text())
    records = read_records(run / "episodes.csv")
    return BatchResult(
        run,
        records,
        evaluation,
        int(done["updates"]),
        int(done["updates"]),
        int(done["total_steps"]),
        float(done.get("train_time", 0.0)),
    )


def train_batch(
    cfg: BatchConfig,
    run_dir: str | Path,
    progress: bool = True,
    on_update: Callable[[BatchLearner, UpdateStats, float], None] | None = None,
) -> BatchResult:
    """Train batch PPO / PPO-RB / PPO-RPE as configured, writing everything into ``run_dir``.

    The run folder has the layout of :func:`pporpe.runner.train`: ``config.json`` (written
    first, with ``"learner": "batch"``), ``episodes.csv``, ``tensorboard/`` (episode scalars
    and ``update/*`` scalars), ``checkpoint.pt`` (atomically, every ``checkpoint_every``
    updates and at the end), ``evaluation.json`` and ``done.json``. Calling it again on the
    same folder with the same config resumes from the checkpoint (see the module
    docstring), or returns at once if ``done.json`` exists. Torch runs on one thread.

    ``on_update(learner, stats, train_time)`` is called after every update (e.g. for
    evaluations during training) with the training seconds so far; its own time is not
    counted in ``train_time`` or the records' ``wall_time``.
    """
    resolve_env_id(cfg.env)  # bad env names fail before anything is built or written
    run, done = open_run_dir(run_dir, _config_json(cfg))
    if done:
        return _finished_result(run)

    torch.set_num_threads(1)
    torch.manual_seed(cfg.seed)
    learner = BatchLearner(cfg)
    records: list[EpisodeRecord] = []
    wall_offset = 0.0
    ckpt_path = run / CHECKPOINT
    if ckpt_path.exists():
        state = torch.load(ckpt_path, weights_only=False)
        learner.load_state_dict(state["learner"])
        records = [EpisodeRecord(**r) for r in state["records"]]
        wall_offset = float(state["wall_time"])
        torch.set_rng_state(state["torch_rng"])
    resumed_from = learner.updates
    log = _UpdateLog(run)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=cfg.n_updates * cfg.rollout_size,
            initial=learner.total_steps,
            desc=f"batch {cfg.method} {cfg.env} s{cfg.seed}",
            unit="step",
            dynamic_ncols=True,
        )
    excluded = 0.0
    t_start = time.perf_counter()

    def train_time() -> float:
        return wall_offset + (time.perf_counter() - t_start) - excluded

    def checkpoint() -> None:
        if not learner.model.parameters_finite():
            raise NonFiniteError(
                f"non-finite parameter after update {learner.updates}; "
                "the last good checkpoint is kept"
            )
        state = {
            "learner": learner.state_dict(),
            "records": [r.__dict__ for r in records],
            "wall_time": train_time(),
            "torch_rng": torch.get_rng_state(),
        }
        save_checkpoint(ckpt_path, state)
        log.logger.write_records(records)

    last: dict[str, float] = {}
    try:
        while learner.updates < cfg.n_updates:
            episodes = learner.collect_rollouts()
            stats = learner.train()
            if not math.isfinite(float(stats.policy_loss) + float(stats.value_loss)):
                raise NonFiniteError(f"non-finite loss at update {learner.updates}")
            records.extend(log.records(episodes, stats, len(records), train_time()))
            last = log.update(stats, learner.total_steps)
            if bar is not None:
                bar.update(cfg.rollout_size)
                if records:
                    bar.set_postfix(ret=f"{records[-1].ret:.1f}", kl=f"{last['approx_kl']:.3f}")
            if learner.updates % cfg.checkpoint_every == 0 or learner.updates == cfg.n_updates:
                checkpoint()
            if on_update is not None:
                t_cb = time.perf_counter()
                on_update(learner, stats, t_cb - t_start + wall_offset - excluded)
                excluded += time.perf_counter() - t_cb
        if learner.updates == resumed_from:
            checkpoint()
    except BaseException:
        learner.close()
        raise
    finally:
        if bar is not None:
            bar.close()
        log.close()
    total_time = train_time()

    evaluation = None
    if cfg.eval_episodes > 0:
        evaluation = evaluate_learner(learner, cfg.eval_episodes)
        atomic_write_json(run / "evaluation.json", evaluation.to_dict())
    learner.close()
    atomic_write_json(
        run / "done.json",
        {
            "updates": learner.updates,
            "total_steps": learner.total_steps,
            "episodes": len(records),
            "train_time": total_time,
        },
    )
    return BatchResult(
        run,
        records,
        evaluation,
        resumed_from,
        learner.updates,
        learner.total_steps,
        total_time,
        last,
    )
