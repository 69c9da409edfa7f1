r"""Standard batch PPO (rollouts and minibatch epochs) with the PPO, PPO-RB and PPO-RPE surrogates.

Most PPO users train with rollouts of vectorised environments and a few epochs of
minibatch updates rather than online. This module gives them that trainer, sharing the
surrogates (:func:`pporpe.surrogates.surrogate_objective`), the policy heads
(:func:`pporpe.nn.make_head`, :class:`~pporpe.nn.ActionMap`) and the network
builder (:func:`pporpe.nn.mlp`) with the paper's online learner. Switching PPO to
PPO-RB, PPO-RPE or SPO is one word: ``BatchConfig(method="rb")``, ``method="rpe"`` or
``method="spo"``; the training loop is the same function for all (the surrogate is one call).

One update (``k``-th of ``n_updates``)::

    collect_rollouts()   n_envs x n_steps transitions with the current policy
    compute_gae()        GAE(lambda); bootstrap through truncations, not terminations
    train()              n_epochs x minibatches of batch_size: surrogate + value + entropy

Pieces, each usable alone (the package :mod:`pporpe.batch`):

* :class:`~pporpe.batch.config.BatchConfig`  the frozen, validated settings;
  :data:`~pporpe.batch.config.ZOO_DEFAULTS` and :func:`~pporpe.batch.config.zoo_config`
  give per-task defaults from rl-baselines3-zoo;
* :mod:`pporpe.batch.normalize`  observation and reward normalisation;
* :class:`~pporpe.batch.model.ActorCritic`  policy and value networks in one flat vector;
* :class:`~pporpe.batch.buffer.RolloutBuffer`, :func:`pporpe.advantages.compute_gae`
  storage and advantages; :func:`pporpe.batch.loss.minibatch_loss` the loss;
* :class:`BatchLearner` (this module)  acting (:meth:`~BatchLearner.collect_rollouts`),
  learning (:meth:`~BatchLearner.train`, returning :class:`UpdateStats`) and the
  deterministic test-time policy (:meth:`~BatchLearner.act_deterministic`);
* :func:`pporpe.batch.kind.train_batch`  a whole run through the one run loop
  (:func:`pporpe.runs.train`: config.json, episodes.csv, tensorboard/, checkpoint.pt,
  evaluation.json, done.json) with exact resume.

**Autoreset.** Gymnasium 1.x vector environments default to ``NEXT_STEP`` autoreset: the
step *after* an episode's end only resets that sub-environment, ignores its action and
returns reward 0, so a rollout would hold one dummy transition per finished episode. The
learner builds its vector environments (:mod:`pporpe.batch.vecenv`) with
``autoreset_mode=SAME_STEP`` instead: the step that ends an episode returns the first
observation of the next one, and the true last observation is in ``info["final_obs"]``
(mask ``info["_final_obs"]``). Every stored transition is then real, and a truncated
episode is bootstrapped with ``V(final_obs)``. :class:`BatchLearner` checks the mode and
refuses any other.

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
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from torch import Tensor

from ..advantages import compute_gae
from ..runs.kinds import NonFiniteError
from ..surrogates import regularization_amount
from .buffer import FinishedEpisode, Minibatch, RolloutBuffer
from .config import BatchConfig
from .loss import minibatch_loss
from .model import ActorCritic
from .normalize import Normalizer
from .vecenv import VecEnv, make_vec_env

__all__ = [
    "BatchLearner",
    "UpdateRecord",
    "UpdateStats",
    "rollout_advantages",
    "scheduled_lr",
    "update_stats",
]


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


@dataclass(frozen=True)
class UpdateRecord:
    """What one update measured, per minibatch and per sample, for :func:`update_stats`."""

    mb_stats: Tensor
    """``[minibatches, 3]``: policy loss, value loss, gradient norm of every step."""
    ratio: Tensor
    """Density ratios of every sample of every epoch."""
    adv: Tensor
    """The advantages used with them."""
    entropy: Tensor | None
    """Mean entropy of the last minibatch's policy (None when no step was taken)."""
    epochs: int
    """Epochs run."""
    lr: float
    """Learning rate used."""


@torch.no_grad()
def update_stats(
    cfg: BatchConfig, record: UpdateRecord, returns: Tensor, values: Tensor
) -> UpdateStats:
    """The :class:`UpdateStats` of one update from its record and the rollout's lambda-returns
    and old values (the explained variance)."""
    rows = record.mb_stats.shape[0]
    means = record.mb_stats.mean(0) if rows else torch.full((3,), float("nan"))
    ratio, adv = record.ratio, record.adv
    nan = torch.tensor(float("nan"))
    if rows and record.entropy is not None:
        reg = regularization_amount(cfg.method, ratio, adv, cfg.eps, cfg.beta, cfg.eta)
        reg_amount, past = reg.amount.mean(), reg.fraction_past_threshold
        ratio_dev = (ratio - 1.0).abs().mean()
        approx_kl = (ratio - 1.0 - torch.log(ratio)).mean()
        entropy = record.entropy
    else:
        reg_amount = past = ratio_dev = torch.tensor(0.0)
        approx_kl = entropy = nan
    ret, val = returns.reshape(-1), values.reshape(-1)
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
        lr=torch.tensor(record.lr),
        epochs=torch.tensor(record.epochs),
    )


def scheduled_lr(cfg: BatchConfig, updates: int) -> float:
    """The learning rate of update ``updates`` (0-based) under the config's schedule."""
    if cfg.lr_schedule == "linear":
        return cfg.lr * max(0.0, 1.0 - updates / cfg.n_updates)
    return cfg.lr


def rollout_advantages(
    buf: RolloutBuffer, last_value: Tensor, cfg: BatchConfig, cols: slice | Tensor = slice(None)
) -> None:
    """GAE advantages and lambda-returns of the filled buffer's columns ``cols`` (all by
    default; a population's buffer holds every member's sub-environments side by side),
    written into ``buf``; ``last_value``: V of the observations after the rollout."""
    values, term, trunc = buf.values[:, cols], buf.terminated[:, cols], buf.truncated[:, cols]
    # V of the state each step reached: the next step's V(s_{t+1}) unless the episode
    # ended (then V(final obs) was stored for truncations; terminations ignore it)
    nxt = torch.cat([values[1:], last_value[None]])
    next_values = torch.where(term | trunc, buf.next_values[:, cols], nxt)
    buf.next_values[:, cols] = next_values
    adv, ret = compute_gae(
        buf.rewards[:, cols],
        values,
        next_values,
        term,
        trunc,
        cfg.gamma,
        cfg.gae_lambda,
        cfg.bootstrap_truncated,
    )
    buf.advantages[:, cols] = adv
    buf.returns[:, cols] = ret


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
        finished: list[FinishedEpisode] = []
        obs = torch.from_numpy(self._obs)
        for t in range(self.cfg.n_steps):
            obs = self._rollout_step(t, obs, finished)
        self._obs = obs.numpy()
        self._compute_advantages(self.model.value(obs))
        return finished

    def _rollout_step(self, t: int, obs: Tensor, finished: list[FinishedEpisode]) -> Tensor:
        """Act in every environment at ``obs``, store step ``t`` in the buffer, append the
        episodes that ended to ``finished``; return the next (normalised) observations."""
        cfg, model, buf, norm = self.cfg, self.model, self.buffer, self.normalizer
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
        next_obs = torch.from_numpy(norm.obs(self._raw_obs, update=True))
        if done.any():  # after the update of the statistics, which normalise the final obs
            finished += self._end_episodes(t, term, trunc, info)
        return next_obs

    def _end_episodes(
        self, t: int, term: np.ndarray, trunc: np.ndarray, info: dict[str, Any]
    ) -> list[FinishedEpisode]:
        """V of the final observation of every truncated episode into the buffer's step t;
        the episodes that ended, with their counters reset."""
        buf, norm, model = self.buffer, self.normalizer, self.model
        done = term | trunc
        idx = np.nonzero(trunc)[0]
        if idx.size:
            final = np.stack([np.asarray(info["final_obs"][i]) for i in idx])
            fv = model.value(torch.from_numpy(norm.obs(final, update=False)))
            buf.next_values[t, torch.from_numpy(idx)] = fv
        ended = [
            FinishedEpisode(
                int(i), float(self.ep_ret[i]), int(self.ep_len[i]), self.total_steps, bool(term[i])
            )
            for i in np.nonzero(done)[0]
        ]
        self.ep_ret[done] = 0.0
        self.ep_len[done] = 0
        return ended

    def _compute_advantages(self, last_value: Tensor) -> None:
        """GAE advantages and returns of the filled buffer (``last_value``: V after it)."""
        rollout_advantages(self.buffer, last_value, self.cfg)

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
        return scheduled_lr(self.cfg, self.updates)

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
        rollout = Minibatch.from_buffer(buf, adv)
        grad = model.grad
        stats_rows = pos = 0
        epochs = 0
        stop = False
        raw = torch.zeros(0)
        for _epoch in range(cfg.n_epochs):
            shuffled = rollout.index(torch.randperm(n))
            for start in range(0, n, bs):
                mb = shuffled.slice(start, start + bs)
                loss, m = minibatch_loss(model, mb, cfg)
                ratio, raw = m.ratio, m.raw
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
                    self._diag_ratio[pos : pos + len(mb)] = ratio
                    self._diag_adv[pos : pos + len(mb)] = m.adv
                    pos += len(mb)
                    torch.stack([m.policy_loss, m.value_loss, norm], out=self._mb_stats[stats_rows])
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
        record = UpdateRecord(
            self._mb_stats[:rows],
            self._diag_ratio[:samples],
            self._diag_adv[:samples],
            self.model.entropy(raw).mean() if rows else None,
            epochs,
            lr,
        )
        return update_stats(self.cfg, record, self.buffer.returns, self.buffer.values)

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
