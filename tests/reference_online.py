r"""A scalar reference of the online learner, for the tests only.

This is pporpe 0.2.0's single-run ``OnlineLearner``, composed of the library's scalar
components (:class:`~pporpe.online.torch_engine.optim.TDAmsProp`,
:class:`~pporpe.online.torch_engine.traces.AdaptiveTraces`,
:class:`~pporpe.online.torch_engine.tsoft.TSoftUpdate`, the flat actor-critic and
the policy heads) with autograd for the backward pass. The library's learner is the
population learner (:mod:`pporpe.online.population`); the tests check that each of its
members computes what this reference computes, given the same actions.

Step order, signals and traces: see :mod:`pporpe.online.torch_engine.engine`.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from pporpe.nn.actor_critic import FlatActorCritic
from pporpe.nn.mlp import mlp
from pporpe.nn.policies import ActionMap, PolicyHead, make_head
from pporpe.online.config import OnlineConfig
from pporpe.online.torch_engine.optim import TDAmsProp
from pporpe.online.torch_engine.traces import AdaptiveTraces
from pporpe.online.torch_engine.tsoft import TSoftUpdate
from pporpe.surrogates import surrogate_objective

__all__ = ["ReferenceLearner", "StepStats"]


@dataclass(frozen=True)
class StepStats:
    """What one update did, as 0-dim tensors (no ``.item()`` in the hot path)."""

    delta: Tensor
    """TD error delta (in scaled-reward units)."""
    adv: Tensor
    """Regularised advantage A used by the surrogate."""
    ratio: Tensor
    """Density ratio rho of the transition (pi_theta_t / pi_theta_{t-1})."""
    divergence: Tensor
    """Change of the networks since the last step (KL estimate + squared value change)."""
    trace_decay: Tensor
    """Adaptive trace decay exp(-kappa * D) applied at this step."""

    def as_dict(self) -> dict[str, float]:
        """Python floats by name (synchronises; for logging and tests only)."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    @staticmethod
    def stack(steps: list[StepStats]) -> StepStats:
        """The stats of many steps, each field stacked into a 1-D tensor (by name)."""
        return StepStats(
            **{f.name: torch.stack([getattr(s, f.name) for s in steps]) for f in fields(StepStats)}
        )


class ReferenceLearner:
    """Online actor-critic with PPO / PPO-RB / PPO-RPE surrogates (the paper's Alg. 1).

    Usage, one environment::

        action = learner.begin_episode(obs)
        while training:
            obs, reward, terminated, truncated, _ = env.step(action)
            stats, action = learner.step(reward, obs, terminated, truncated)
            if terminated or truncated:
                obs, _ = env.reset()
                action = learner.begin_episode(obs)

    ``step`` returns the next action because the paper samples a_{t+1} with the
    parameters *before* the update of transition t (that is what makes rho != 1).
    """

    def __init__(
        self, obs_dim: int, action_low: Any, action_high: Any, config: OnlineConfig
    ) -> None:
        if not (isinstance(obs_dim, int) and obs_dim >= 1):
            raise ValueError(f"obs_dim must be an int >= 1; got obs_dim={obs_dim!r}")
        self.config = cfg = config
        self.action_map = ActionMap(
            torch.as_tensor(np.asarray(action_low), dtype=torch.float32),
            torch.as_tensor(np.asarray(action_high), dtype=torch.float32),
        )
        self.obs_dim = obs_dim
        self.act_dim = self.action_map.act_dim
        self.head: PolicyHead = make_head(cfg.policy, self.act_dim)
        net_kw = dict(
            layers=cfg.layers,
            units=cfg.units,
            layer_norm=cfg.layer_norm,
            activation=cfg.activation,
        )
        policy_net = mlp(obs_dim, self.head.raw_dim, **net_kw)  # type: ignore[arg-type]
        value_net = mlp(obs_dim, 1, **net_kw)  # type: ignore[arg-type]
        self.model = FlatActorCritic(policy_net, value_net)
        self._policy_fn, self._value_fn = self.model.policy_fn, self.model.value_fn
        self._pol_views, self._val_views = self.model.policy_params, self.model.value_params
        self.theta = self.model.theta
        self._grad = self.model.grad
        self.n_policy = self.model.n_policy
        self.target = self.model.value_block.detach().clone()
        self._tgt_views = self.model.value_views(self.target)

        self.optimizer = TDAmsProp(
            [self.theta],
            lr=cfg.lr,
            betas=cfg.opt_betas,
            eps=cfg.opt_eps,
            k_dof=cfg.k_dof,
            amsgrad_decay=cfg.amsgrad_decay,
            segments=self.model.segment_sizes,
        )
        self.traces = AdaptiveTraces(
            self.theta.numel(), gamma=cfg.gamma, lambdas=cfg.lambdas, kappa=cfg.kappa
        )
        self.tsoft = TSoftUpdate(tau=cfg.tau, nu=cfg.nu)
        self._update_buf = torch.zeros_like(self.theta)
        self.theta.grad = self._update_buf  # what the optimiser reads
        self._reward_scale = cfg.effective_reward_scale
        self._loss_fn = self._loss
        self._reset_pending()

    def _reset_pending(self) -> None:
        self._obs: Tensor | None = None  # s_t as a [1, obs_dim] tensor
        self._u: Tensor | None = None  # u_t, pre-map action taken at s_t
        self._logp_b: Tensor | None = None  # log pi_{theta_{t-1}}(u_t | s_t)
        self._value_b: Tensor | None = None  # V_{theta_{t-1}}(s_t)

    # -- acting ------------------------------------------------------------------------
    def _obs_tensor(self, obs: Any) -> Tensor:
        return torch.as_tensor(np.asarray(obs, dtype=np.float32)).reshape(1, self.obs_dim)

    @torch.no_grad()
    def policy_raw(self, obs: Tensor) -> Tensor:
        """Raw policy-network output for a batch of observations (no gradient)."""
        return self._policy_fn(self._pol_views, obs)

    @torch.no_grad()
    def act_deterministic(self, obs: Any) -> np.ndarray:
        """Test-time action: the policy's location mapped into the action bounds."""
        raw = self.policy_raw(self._obs_tensor(obs))
        return self.action_map.to_action(self.head.location(raw))[0].numpy()

    @torch.no_grad()
    def value(self, obs: Any) -> float:
        """V(s) of the online value network."""
        return float(self._value_fn(self._val_views, self._obs_tensor(obs))[0, 0])

    def _to_env(self, u: Tensor) -> np.ndarray:
        return self.action_map.to_action(u)[0].numpy()

    @torch.no_grad()
    def begin_episode(self, obs: Any) -> np.ndarray:
        """Reset the traces, sample the first action of an episode and return it."""
        self.traces.reset_()
        x = self._obs_tensor(obs)
        raw = self._policy_fn(self._pol_views, x)
        u = self.head.sample(raw)
        self._obs, self._u = x, u
        self._logp_b = self.head.log_prob(raw, u)
        self._value_b = self._value_fn(self._val_views, x)[:, 0]
        return self._to_env(u)

    # -- learning ----------------------------------------------------------------------
    def _loss(
        self,
        pol: list[Tensor],
        val: list[Tensor],
        tgt: list[Tensor],
        x: Tensor,
        u: Tensor,
        logp_b: Tensor,
        value_b: Tensor,
        reward: Tensor,
        bootstrap: Tensor,
    ) -> tuple[Tensor, ...]:
        """Everything of one step up to the loss: a pure function (``torch.compile``-able).

        Returns the per-unit-signal loss (see the module docstring), the raw policy
        output and value at s_{t+1} (the next step's baseline), and the step's delta,
        advantage, ratio and divergence.
        """
        cfg = self.config
        raw = self._policy_fn(pol, x)
        values = self._value_fn(val, x)[:, 0]
        next_target = self._value_fn(tgt, x[1:])[0, 0].detach()
        logp = self.head.log_prob(raw[:1], u)[0]
        log_ratio = logp - logp_b[0]
        ratio = torch.exp(log_ratio)
        v = values[0]
        v_d, logp_d, log_ratio_d, ratio_d = (
            v.detach(),
            logp.detach(),
            log_ratio.detach(),
            ratio.detach(),
        )
        delta = reward * self._reward_scale + bootstrap * next_target - v_d
        # entropy term with the density of the bounded action a = f(u): its entropy is
        # bounded, so the bonus cannot grow by inflating the scale of u
        logp_action = logp_d - self.action_map.log_abs_det_jacobian(u)[0]
        adv = delta - (1.0 - cfg.gamma) * (cfg.beta_td * delta * delta + cfg.beta_de * logp_action)
        sigma = torch.where(adv >= 0, 1.0, -1.0)
        # divergence between the networks the traces were built with and theta_t:
        # KL(pi_b || pi) estimated at the sampled action, plus the squared value change
        divergence = (ratio_d - 1.0 - log_ratio_d) + (v_d - value_b[0]) ** 2
        objective = surrogate_objective(
            cfg.method, ratio, sigma, cfg.eps, cfg.beta, cfg.eta, cfg.rpe_form
        )
        unit_loss = -sigma * objective - v
        return (unit_loss, raw[1:].detach(), values[1:].detach(), delta, adv, ratio_d, divergence)

    def step(
        self, reward: float, next_obs: Any, terminated: bool, truncated: bool
    ) -> tuple[StepStats, np.ndarray]:
        """Learn from transition (s_t, a_t, r_t, s_{t+1}); return its stats and a_{t+1}.

        ``terminated`` stops bootstrapping; ``truncated`` (a time limit) does not. After
        either, the caller starts the next episode with :meth:`begin_episode`.
        """
        if self._obs is None or self._u is None or self._logp_b is None:
            raise RuntimeError("call begin_episode(obs) before step()")
        assert self._value_b is not None
        x = torch.cat([self._obs, self._obs_tensor(next_obs)])  # [s_t; s_{t+1}]
        scalars = torch.tensor([reward, 0.0 if terminated else self.config.gamma])
        unit_loss, raw_next, value_b_next, delta, adv, ratio, divergence = self._loss_fn(
            self._pol_views,
            self._val_views,
            self._tgt_views,
            x,
            self._u,
            self._logp_b,
            self._value_b,
            scalars[0],
            scalars[1],
        )
        self._grad.zero_()
        unit_loss.backward()  # accumulates into self._grad through the leaves' .grad views

        with torch.no_grad():
            # a_{t+1} is sampled from theta_t, before this update (the step order above)
            u_next = self.head.sample(raw_next)
            logp_b_next = self.head.log_prob(raw_next, u_next)
            trace = self.traces.step_(self._grad, divergence)
            upd = self._update_buf
            torch.mul(trace[: self.n_policy], adv, out=upd[: self.n_policy])
            torch.mul(trace[self.n_policy :], delta, out=upd[self.n_policy :])
            self.optimizer.step()
            self.tsoft.update_(self.target, self.theta[self.n_policy :])

        stats = StepStats(
            delta=delta,
            adv=adv,
            ratio=ratio,
            divergence=divergence,
            trace_decay=self.traces.last_decay.clone(),  # the traces reuse that buffer
        )
        if terminated or truncated:
            self._reset_pending()
        else:
            self._obs, self._u = x[1:], u_next
            self._logp_b, self._value_b = logp_b_next, value_b_next
        return stats, self._to_env(u_next)

    # -- state ---------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue learning at an episode boundary (a deep copy)."""
        return copy.deepcopy(
            {
                "theta": self.theta.clone(),
                "target": self.target.clone(),
                "optimizer": self.optimizer.state_dict(),
                "traces": self.traces.state_dict(),
                "tsoft": self.tsoft.state_dict(),
            }
        )

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (same architecture and config)."""
        with torch.no_grad():
            self.theta.copy_(state["theta"])
            self.target.copy_(state["target"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.traces.load_state_dict(state["traces"])
        self.tsoft.load_state_dict(state["tsoft"])
        self._reset_pending()

    def parameters_finite(self) -> bool:
        """Whether every parameter (online and target) is finite."""
        return bool(torch.isfinite(self.theta).all() and torch.isfinite(self.target).all())
