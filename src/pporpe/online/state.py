"""The named state of a population of online learners, and its per-member constants.

:class:`PopulationState` holds every buffer that changes while the K members learn
(parameters, traces, td-AmsProp's moments, the t-soft scalars, the pending transition),
stacked over members; :class:`MemberConstants` holds what each member's config fixes
(reward scale, discount, regulariser weights, the choices as flags, optimiser and t-soft
constants), one row per member. Both are written in place, never rebound, so the views
the update blocks and the fused engine keep of them stay valid.

A member's checkpoint (:meth:`PopulationState.member`) is its slice of every buffer,
as nested dicts of cloned tensors; :meth:`PopulationState.state_dict` is the whole
population as flat named tensors. Neither holds the noise streams (the population's
:class:`~pporpe.online.noise.NoiseBank`) nor the per-step scratch gradient.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..nn.batched import NetLayout
from .config import OnlineConfig

__all__ = ["SIGMA2_INIT", "SIGMA2_MIN", "MemberConstants", "PendingTransition", "PopulationState"]

SIGMA2_INIT = 1e-2
"""t-soft ``sigma2`` initial value: TSoftUpdate's default."""

SIGMA2_MIN = 1e-12
"""t-soft ``sigma2`` floor: TSoftUpdate's default."""


@dataclass(frozen=True, eq=False)
class PendingTransition:
    """Per member, the transition whose reward is still to come: s_t, u_t and what the
    behaviour policy pi_b (the parameters that sampled u_t) gave at s_t."""

    obs: Tensor
    """``[K, obs_dim]`` s_t."""
    u: Tensor
    """``[K, act_dim]`` the pre-map action u_t."""
    logp_b: Tensor
    """``[K]`` log pi_b(u_t | s_t)."""
    value_b: Tensor
    """``[K]`` V_b(s_t), the value network when u_t was sampled."""
    raw_b: Tensor
    """``[K, raw_dim]`` pi_b's raw output at s_t (for the analytic trace KL)."""
    waiting: np.ndarray
    """``[K]`` bool: the member has a transition pending (an episode in progress)."""

    @classmethod
    def zeros(cls, k: int, obs_dim: int, act_dim: int, raw_dim: int) -> PendingTransition:
        return cls(
            obs=torch.zeros(k, obs_dim),
            u=torch.zeros(k, act_dim),
            logp_b=torch.zeros(k),
            value_b=torch.zeros(k),
            raw_b=torch.zeros(k, raw_dim),
            waiting=np.zeros(k, dtype=bool),
        )


@dataclass(frozen=True, eq=False)
class PopulationState:
    """Everything that changes while K members learn (shapes: 3 nets = policy, value,
    target; 2 nets = policy, value; R x U = the padded layout's rows and units; S = its
    t-momentum segments)."""

    params: Tensor
    """``[3, K, R, U]`` parameters of the policy, value and target networks."""
    grad: Tensor
    """``[2, K, R, U]`` scratch: this step's per-unit-signal gradient (not checkpointed)."""
    trace_e: Tensor
    """``[2, K, R, U]`` eligibility trace of the first time scale (lambda_1)."""
    trace_r: Tensor
    """``[2, K, R, U]`` eligibility trace of the second time scale (lambda_2)."""
    opt_v: Tensor
    """``[2, K, R, U]`` td-AmsProp's second moment."""
    opt_vmax: Tensor
    """``[2, K, R, U]`` its running maximum, stored scaled by the bias correction."""
    opt_m: Tensor
    """``[2, K, R, U]`` the t-momentum's first moment."""
    opt_weight: Tensor
    """``[2, K, S]`` the t-momentum's accumulated weight W per segment."""
    trace_divergence: Tensor
    """``[K]`` the accumulated divergence D of the adaptive trace decay."""
    decay: Tensor
    """``[K]`` the last trace decay (1 after a reset)."""
    tsoft_weight: Tensor
    """``[K]`` float64 t-soft's accumulated weight W."""
    tsoft_sigma2: Tensor
    """``[K]`` float64 t-soft's scale sigma^2."""
    steps: np.ndarray
    """``[K]`` int64 td-AmsProp step counts."""
    pending: PendingTransition
    """The transitions waiting for their reward."""

    @classmethod
    def zeros(cls, k: int, lay: NetLayout, act_dim: int) -> PopulationState:
        """All-zero state of ``k`` members with ``lay``'s shape (members are reset after)."""
        rows, units, segs = lay.n_rows, lay.units, lay.n_seg
        return cls(
            params=torch.zeros(3, k, rows, units),
            grad=torch.zeros(2, k, rows, units),
            trace_e=torch.zeros(2, k, rows, units),
            trace_r=torch.zeros(2, k, rows, units),
            opt_v=torch.zeros(2, k, rows, units),
            opt_vmax=torch.zeros(2, k, rows, units),
            opt_m=torch.zeros(2, k, rows, units),
            opt_weight=torch.zeros(2, k, segs),
            trace_divergence=torch.zeros(k),
            decay=torch.ones(k),
            tsoft_weight=torch.zeros(k, dtype=torch.float64),
            tsoft_sigma2=torch.zeros(k, dtype=torch.float64),
            steps=np.zeros(k, dtype=np.int64),
            pending=PendingTransition.zeros(k, lay.obs_dim, act_dim, lay.raw_dim),
        )

    # -- one member -----------------------------------------------------------------------
    @torch.no_grad()
    def reset_member(self, k: int, config: OnlineConfig) -> None:
        """Zero member k's traces and optimiser state; fresh t-soft scalars; nothing
        pending (its parameters are set by the caller)."""
        for buf in (self.grad, self.trace_e, self.trace_r, self.opt_v, self.opt_vmax,
                    self.opt_m):  # fmt: skip
            buf[:, k] = 0.0
        beta1 = config.opt_betas[0]
        self.opt_weight[:, k] = beta1 / (1.0 - beta1)
        self.trace_divergence[k], self.decay[k] = 0.0, 1.0
        self.tsoft_weight[k] = (1.0 - config.tau) / config.tau
        self.tsoft_sigma2[k] = SIGMA2_INIT
        self.steps[k] = 0
        self.pending.waiting[k] = False

    @torch.no_grad()
    def reset_traces(self, members: Tensor) -> None:
        """New episodes of ``members``: zero traces, no accumulated divergence, decay 1."""
        self.trace_e[:, members] = 0.0
        self.trace_r[:, members] = 0.0
        self.trace_divergence[members], self.decay[members] = 0.0, 1.0

    def member(self, k: int) -> dict[str, Any]:
        """Member k's slice of every buffer (cloned), as a checkpoint's nested dicts."""
        p = self.pending
        return {
            "params": self.params[:, k].clone(),
            "optimizer": {
                "step": int(self.steps[k]),
                "v": self.opt_v[:, k].clone(),
                "vmax_scaled": self.opt_vmax[:, k].clone(),
                "m": self.opt_m[:, k].clone(),
                "W": self.opt_weight[:, k].clone(),
            },
            "traces": {
                "e": self.trace_e[:, k].clone(),
                "r": self.trace_r[:, k].clone(),
                "D": self.trace_divergence[k].clone(),
                "last_decay": self.decay[k].clone(),
            },
            "tsoft": {"W": self.tsoft_weight[k].clone(), "sigma2": self.tsoft_sigma2[k].clone()},
            "pending": None
            if not p.waiting[k]
            else {
                "obs": p.obs[k].clone(),
                "u": p.u[k].clone(),
                "logp_b": p.logp_b[k].clone(),
                "value_b": p.value_b[k].clone(),
                "raw_b": p.raw_b[k].clone(),
            },
        }

    @torch.no_grad()
    def load_member(self, k: int, state: dict[str, Any], needs_raw_b: bool) -> None:
        """Write :meth:`member`'s dicts into slot k. ``needs_raw_b``: the member's config
        uses pi_b's raw output (``trace_divergence="analytic"``), so a pending transition
        saved without it cannot be continued."""
        if tuple(state["params"].shape) != tuple(self.params[:, k].shape):
            raise ValueError("state was saved for a different network layout")
        pending = state.get("pending")
        if pending is not None and "raw_b" not in pending and needs_raw_b:
            raise ValueError(
                "this checkpoint's pending transition has no raw_b (pi_b's output), which "
                "trace_divergence='analytic' needs; resume it with trace_divergence='sample'"
            )
        self.params[:, k] = state["params"]
        opt = state["optimizer"]
        self.steps[k] = int(opt["step"])
        self.opt_v[:, k], self.opt_vmax[:, k] = opt["v"], opt["vmax_scaled"]
        self.opt_m[:, k], self.opt_weight[:, k] = opt["m"], opt["W"]
        tr = state["traces"]
        self.trace_e[:, k], self.trace_r[:, k] = tr["e"], tr["r"]
        self.trace_divergence[k], self.decay[k] = tr["D"], tr["last_decay"]
        self.tsoft_weight[k] = state["tsoft"]["W"]
        self.tsoft_sigma2[k] = state["tsoft"]["sigma2"]
        p = self.pending
        p.waiting[k] = pending is not None
        if pending is not None:
            p.obs[k], p.u[k] = pending["obs"], pending["u"]
            p.logp_b[k], p.value_b[k] = pending["logp_b"], pending["value_b"]
            p.raw_b[k] = pending.get("raw_b", torch.zeros(p.raw_b.shape[1]))

    # -- the whole population -------------------------------------------------------------
    def _named_buffers(self) -> dict[str, Any]:
        """Every buffer but the scratch gradient, by its :meth:`state_dict` name."""
        out: dict[str, Any] = {
            f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("grad", "pending")
        }
        out.update({f"pending.{f.name}": getattr(self.pending, f.name)
                    for f in fields(self.pending)})  # fmt: skip
        return out

    def state_dict(self) -> dict[str, Tensor]:
        """Every buffer but the scratch gradient, cloned, by name (``pending.obs``, ...)."""
        return {name: torch.as_tensor(buf).clone() for name, buf in self._named_buffers().items()}

    @torch.no_grad()
    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        """Copy :meth:`state_dict`'s tensors into these buffers (in place). Raises
        ValueError naming a missing, unexpected or misshapen entry."""
        targets = self._named_buffers()
        if set(state) != set(targets):
            missing, extra = sorted(set(targets) - set(state)), sorted(set(state) - set(targets))
            raise ValueError(f"state_dict keys differ: missing {missing}, unexpected {extra}")
        for name, dest in targets.items():
            src = state[name]
            if tuple(src.shape) != tuple(dest.shape):
                raise ValueError(
                    f"state_dict[{name!r}] has shape {tuple(src.shape)}; expected "
                    f"{tuple(dest.shape)}"
                )
            if isinstance(dest, np.ndarray):
                dest[...] = src.numpy()
            else:
                dest.copy_(src)


_FLOATS = (
    "reward_scale", "gamma", "one_m_gamma", "beta_td", "beta_de", "td_scale", "neg_kappa",
    "gl1", "gl2", "beta2_f32", "one_m_beta2", "opt_eps", "omb_mom", "w_coef",
)  # fmt: skip
_DOUBLES = ("tau", "nu", "sigma2_min")
_ARRAYS = ("beta1", "beta2", "lr", "ams_decay")
_FLAGS = (
    "kappa_pos", "mom_only", "polyak", "pre_squash", "critic_actor", "kl_analytic",
    "weighted_score", "limit_terminal", "ln_frozen",
)  # fmt: skip


@dataclass(frozen=True, eq=False)
class MemberConstants:
    """What each member's config fixes, one row per member (written by :meth:`write`).
    Names match the fused engine's columns (``fused.C_NAMES``, ``fused.F_NAMES``)."""

    reward_scale: Tensor
    """``[K]`` the factor of the reward in the TD error."""
    gamma: Tensor
    """``[K]`` the discount factor."""
    one_m_gamma: Tensor
    """``[K]`` 1 - gamma."""
    beta_td: Tensor
    """``[K]`` the TD regulariser's weight."""
    beta_de: Tensor
    """``[K]`` the entropy regulariser's weight."""
    td_scale: Tensor
    """``[K]`` the factor of delta inside the TD regulariser: 1 (``td_units="scaled"``)
    or 1 / (1 - gamma) (``"unscaled"``)."""
    neg_kappa: Tensor
    """``[K]`` -kappa of the adaptive trace decay."""
    gl1: Tensor
    """``[K]`` gamma * lambda_1."""
    gl2: Tensor
    """``[K]`` gamma * lambda_max2."""
    beta2_f32: Tensor
    """``[K]`` td-AmsProp's beta_2 in float32 (the elementwise update's copy)."""
    one_m_beta2: Tensor
    """``[K]`` 1 - beta_2."""
    opt_eps: Tensor
    """``[K]`` td-AmsProp's epsilon."""
    omb_mom: Tensor
    """``[K]`` 1 - beta_1 (the momentum's rate)."""
    w_coef: Tensor
    """``[K]`` the t-momentum's weight decay coefficient 1 - 1 / beta_1 (0 without it)."""
    tau: Tensor
    """``[K]`` float64 t-soft's tau."""
    nu: Tensor
    """``[K]`` float64 t-soft's degrees of freedom (inf: Polyak averaging)."""
    sigma2_min: Tensor
    """``[K]`` float64 t-soft's sigma^2 floor."""
    beta1: np.ndarray
    """``[K]`` float64 td-AmsProp's beta_1 (bias corrections)."""
    beta2: np.ndarray
    """``[K]`` float64 td-AmsProp's beta_2 (bias corrections)."""
    lr: np.ndarray
    """``[K]`` float64 learning rate."""
    ams_decay: np.ndarray
    """``[K]`` float64 decay of the AMSGrad maximum (0: no maximum)."""
    ams_raw: np.ndarray
    """``[K]`` bool: the maximum of the raw moment (``amsgrad_max="raw"``)."""
    kappa_pos: Tensor
    """``[K]`` bool: kappa > 0 (adaptive decay on)."""
    mom_only: Tensor
    """``[K]`` bool: plain momentum (beta_1 = 0 or k_dof = inf), no t-momentum weights."""
    polyak: Tensor
    """``[K]`` bool: the target follows by Polyak averaging (nu = inf)."""
    pre_squash: Tensor
    """``[K]`` bool: the entropy term uses the density of u (``entropy_density``)."""
    critic_actor: Tensor
    """``[K]`` bool: the critic is trained with the actor's signal (``critic_signal``)."""
    kl_analytic: Tensor
    """``[K]`` bool: the trace divergence is the analytic KL (``trace_divergence``)."""
    weighted_score: Tensor
    """``[K]`` bool: ``policy_gradient="weighted_score"``."""
    limit_terminal: Tensor
    """``[K]`` bool: a time limit ends the return like a termination (``time_limit``)."""
    ln_frozen: Tensor
    """``[K]`` bool: LayerNorm without learnt scale and shift."""
    norm_keep: Tensor
    """``[K, R]`` 0 on the rows of frozen LayerNorm parameters, 1 elsewhere."""
    seg_num: Tensor
    """``[2, K, S]`` the t-momentum's numerator n (1 + k_dof) per segment."""
    seg_den: Tensor
    """``[2, K, S]`` its denominator n k_dof per segment."""

    @classmethod
    def zeros(cls, k: int, lay: NetLayout) -> MemberConstants:
        """Constants of ``k`` members with ``lay``'s shape, before any :meth:`write`."""
        segs = lay.n_seg
        values: dict[str, Any] = {
            **{n: torch.zeros(k) for n in _FLOATS},
            **{n: torch.zeros(k, dtype=torch.float64) for n in _DOUBLES},
            **{n: np.zeros(k) for n in _ARRAYS},
            **{n: torch.zeros(k, dtype=torch.bool) for n in _FLAGS},
        }
        return cls(
            **values,
            ams_raw=np.zeros(k, dtype=bool),
            norm_keep=torch.ones(k, lay.n_rows),
            seg_num=torch.ones(2, k, segs),
            seg_den=torch.zeros(2, k, segs),
        )

    def write(self, k: int, cfg: OnlineConfig, lay: NetLayout) -> None:
        """Member k's row of every constant, from its config."""
        beta1, beta2 = cfg.opt_betas
        self.reward_scale[k] = cfg.effective_reward_scale
        self.gamma[k], self.one_m_gamma[k] = cfg.gamma, 1.0 - cfg.gamma
        self.beta_td[k], self.beta_de[k] = cfg.beta_td, cfg.beta_de
        self.td_scale[k] = 1.0 if cfg.td_units == "scaled" else 1.0 / (1.0 - cfg.gamma)
        self.pre_squash[k] = cfg.entropy_density == "pre_squash"
        self.critic_actor[k] = cfg.critic_signal == "actor"
        self.kl_analytic[k] = cfg.trace_divergence == "analytic"
        self.weighted_score[k] = cfg.policy_gradient == "weighted_score"
        self.limit_terminal[k] = cfg.time_limit == "terminal"
        self.ln_frozen[k] = lay.layer_norm and not cfg.layer_norm_affine
        self.norm_keep[k] = 1.0
        if self.ln_frozen[k]:
            self.norm_keep[k, lay.norm_rows] = 0.0
        self.ams_raw[k] = cfg.amsgrad_max == "raw"
        self.neg_kappa[k], self.kappa_pos[k] = -cfg.kappa, cfg.kappa > 0.0
        self.gl1[k], self.gl2[k] = cfg.gamma * cfg.lambdas[0], cfg.gamma * cfg.lambdas[1]
        self.beta2_f32[k], self.one_m_beta2[k] = beta2, 1.0 - beta2
        self.opt_eps[k] = cfg.opt_eps
        mom_only = beta1 == 0.0 or math.isinf(cfg.k_dof)
        self.mom_only[k], self.omb_mom[k] = mom_only, 1.0 - beta1
        self.w_coef[k] = 0.0 if mom_only else 1.0 - 1.0 / beta1
        self._write_segments(k, cfg.k_dof, mom_only, lay)
        self.beta1[k], self.beta2[k] = beta1, beta2
        self.lr[k], self.ams_decay[k] = cfg.lr, cfg.amsgrad_decay
        self.tau[k], self.nu[k], self.sigma2_min[k] = cfg.tau, cfg.nu, SIGMA2_MIN
        self.polyak[k] = math.isinf(cfg.nu)

    def _write_segments(self, k: int, k_dof: float, mom_only: bool, lay: NetLayout) -> None:
        for j in range(2):
            n = torch.tensor([float(seg[j]) for seg in lay.segments])
            if mom_only:
                self.seg_num[j, k], self.seg_den[j, k] = 1.0, 0.0
            else:
                # an empty segment (a part of a split head the value network does not
                # have) gets weight 0 instead of 0 / 0
                self.seg_num[j, k] = n * (1.0 + k_dof)
                self.seg_den[j, k] = torch.where(n > 0, n * k_dof, 1.0)
