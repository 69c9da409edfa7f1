"""Settings of a batch PPO run (:class:`BatchConfig`) and per-task defaults from
rl-baselines3-zoo (:data:`ZOO_DEFAULTS`, :func:`zoo_config`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, get_args

from ..config import (
    Activation,
    Method,
    PolicyKind,
    RPEForm,
    is_int,
    is_real,
    require,
    validate_network_fields,
    validate_surrogate_fields,
)
from ..envs import ALIASES
from ..limits import (
    MAX_EVAL_EPISODES,
    MAX_N_ENVS,
    MAX_N_EPOCHS,
    MAX_ROLLOUT,
    MAX_SEED,
    MAX_STEPS,
    check_int_in,
)

__all__ = [
    "ZOO_DEFAULTS",
    "ActionBound",
    "AdvNorm",
    "BatchConfig",
    "Init",
    "LRSchedule",
    "ScaleMode",
    "VecEnvKind",
    "zoo_config",
]

ScaleMode = Literal["global", "state"]
ActionBound = Literal["clip", "map"]
AdvNorm = Literal["minibatch", "batch", "none"]
LRSchedule = Literal["constant", "linear"]
VecEnvKind = Literal["sync", "async"]
Init = Literal["default", "orthogonal"]


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
    """Surrogate: ``"ppo"`` (clip), ``"rb"`` (rollback), ``"rpe"`` (relative Pearson) or
    ``"spo"`` (Simple Policy Optimization, eps only)."""
    seed: int = 0
    """Seed of the networks, the sampling and the environments (sub-env i gets seed + i), in
    [0, 2**32 - 1] (:data:`~pporpe.limits.MAX_SEED`)."""
    total_steps: int = 1_000_000
    """Training length in environment steps over all sub-environments, in [1, 10**9]
    (rounded up to whole rollouts of n_envs * n_steps)."""
    n_envs: int = 1
    """Number of parallel sub-environments, in [1, 1024]."""
    vec_env: VecEnvKind = "sync"
    """``"sync"`` (:class:`gymnasium.vector.SyncVectorEnv`, one process) or ``"async"``
    (:class:`gymnasium.vector.AsyncVectorEnv`, one process per sub-environment)."""
    n_steps: int = 2048
    """Steps per sub-environment in one rollout, >= 1, with n_envs * n_steps at most 2**20
    (:data:`~pporpe.limits.MAX_ROLLOUT`)."""
    batch_size: int = 64
    """Minibatch size, in [1, n_envs * n_steps]; the last minibatch of an epoch is smaller
    when it does not divide the rollout."""
    n_epochs: int = 10
    """Passes over each rollout, in [1, 10**4]."""
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
    paper's :class:`~pporpe.nn.policies.ActionMap` (low + (high-low)*sigmoid(u)). Ratios use
    the density of u in both cases."""
    layers: int = 2
    """Hidden layers of each network (policy and value), in [1, 64]."""
    units: int = 64
    """Units per hidden layer, in [1, 4096], with units * units * layers at most 2**24
    (:mod:`pporpe.limits`)."""
    activation: Activation = "tanh"
    """Hidden activation: ``"tanh"``, ``"relu"`` or ``"swish"``."""
    layer_norm: bool = False
    """LayerNorm after each hidden linear layer (the paper's networks use it)."""
    init: Init = "orthogonal"
    """``"orthogonal"`` (SB3's ``ortho_init=True``: hidden gain by activation, policy output
    gain 0.01, value output gain 1, zero biases) or PyTorch's ``"default"``."""
    checkpoint_every: int = 10
    """Updates between two checkpoints (>= 1); also one at the end, and by time whatever
    the count (after an update): 30 s into training, 1 min later, then every 2 min."""
    eval_episodes: int = 50
    """Test episodes after training, in [0, 10**4] (the paper's score is the median of 50)."""

    def __post_init__(self) -> None:
        self._check_run_fields()
        self._check_optimiser_fields()
        self._check_policy_fields()

    def _check_run_fields(self) -> None:
        """The task, the surrogate, that the rates are numbers, the seed, budget, rollout
        shape and evaluation."""
        require(isinstance(self.env, str) and bool(self.env), "env", self.env, "a task name")
        validate_surrogate_fields(self)
        for name in ("gamma", "gae_lambda", "lr", "adam_eps"):
            require(is_real(getattr(self, name)), name, getattr(self, name), "a number")
        check_int_in("seed", self.seed, 0, MAX_SEED)
        for name, most in (("total_steps", MAX_STEPS), ("n_envs", MAX_N_ENVS),
                           ("n_steps", MAX_ROLLOUT), ("n_epochs", MAX_N_EPOCHS),
                           ("checkpoint_every", MAX_STEPS)):  # fmt: skip
            check_int_in(name, getattr(self, name), 1, most)
        require(
            self.rollout_size <= MAX_ROLLOUT,
            "n_envs * n_steps",
            self.rollout_size,
            f"at most {MAX_ROLLOUT:,} (pporpe.limits.MAX_ROLLOUT)",
        )
        require(
            is_int(self.batch_size) and 1 <= self.batch_size <= self.rollout_size,
            "batch_size",
            self.batch_size,
            f"an int in [1, n_envs * n_steps = {self.rollout_size}]",
        )
        check_int_in("eval_episodes", self.eval_episodes, 0, MAX_EVAL_EPISODES)
        require(self.vec_env in get_args(VecEnvKind), "vec_env", self.vec_env, "'sync' or 'async'")

    def _check_optimiser_fields(self) -> None:
        """Discount, GAE, learning rate, loss coefficients and limits."""
        require(0.0 <= self.gamma < 1.0, "gamma", self.gamma, "in [0, 1)")
        require(0.0 <= self.gae_lambda <= 1.0, "gae_lambda", self.gae_lambda, "in [0, 1]")
        require(0.0 < self.lr < math.inf, "lr", self.lr, "a finite number > 0")
        require(
            self.lr_schedule in get_args(LRSchedule),
            "lr_schedule",
            self.lr_schedule,
            "'constant' or 'linear'",
        )
        require(0.0 < self.adam_eps < math.inf, "adam_eps", self.adam_eps, "a finite number > 0")
        for name in ("vf_coef", "ent_coef"):
            v = getattr(self, name)
            require(is_real(v) and 0.0 <= v < math.inf, name, v, "a finite number >= 0")
        for name in ("max_grad_norm", "clip_vf", "target_kl"):
            v = getattr(self, name)
            require(
                v is None or (is_real(v) and 0.0 < v < math.inf),
                name,
                v,
                "None or a finite number > 0",
            )
        require(
            self.adv_norm in get_args(AdvNorm),
            "adv_norm",
            self.adv_norm,
            f"one of {list(get_args(AdvNorm))}",
        )

    def _check_policy_fields(self) -> None:
        """Normalisation and clipping of the task's signals, the policy's scale and its network."""
        for name in ("normalize_obs", "normalize_reward", "bootstrap_truncated", "layer_norm"):
            v = getattr(self, name)
            require(isinstance(v, bool), name, v, "True or False")
        for name in ("clip_obs", "clip_reward"):
            v = getattr(self, name)
            require(is_real(v) and 0.0 < v < math.inf, name, v, "a finite number > 0")
        require(self.scale in get_args(ScaleMode), "scale", self.scale, "'global' or 'state'")
        require(
            is_real(self.log_std_init) and -20.0 <= self.log_std_init <= 5.0,
            "log_std_init",
            self.log_std_init,
            "a number in [-20, 5]",
        )
        require(
            self.action_bound in get_args(ActionBound),
            "action_bound",
            self.action_bound,
            "'clip' or 'map'",
        )
        validate_network_fields(self)
        require(self.init in get_args(Init), "init", self.init, "'default' or 'orthogonal'")

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
