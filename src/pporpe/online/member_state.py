"""Checkpoint of one member of a :class:`~pporpe.online.population.PopulationLearner`.

A member's state is its slice of every stacked buffer: parameters and target (padded
layout, plus ``theta`` in OnlineLearner's layout for reference), td-AmsProp (step, v,
vmax_scaled, m, W), traces (e, r, D, last decay), t-soft (W, sigma2) and its noise
stream (generator state at the start of the current block, position in the block), and
the pending transition of an episode in progress (s_t, u_t, log pi_b, V_b), if any.
Loading it into any slot of any population with the same network shape continues the
member bitwise when the packing (K, slot) is the same, up to rounding otherwise.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch

from .config import OnlineConfig

if TYPE_CHECKING:
    from .population import PopulationLearner

__all__ = ["load_member_state", "member_state", "write_constants"]

SIGMA2_MIN = 1e-12
"""t-soft ``sigma2`` floor: TSoftUpdate's default."""


def member_state(pop: PopulationLearner, k: int) -> dict[str, Any]:
    """Everything needed to continue member k (cloned tensors), mid-episode included."""
    return {
        "theta": pop.member_theta(k),
        "params": pop.P[:, k].clone(),
        "optimizer": {
            "step": int(pop.steps[k]),
            "v": pop.v[:, k].clone(),
            "vmax_scaled": pop.vmax_s[:, k].clone(),
            "m": pop.m[:, k].clone(),
            "W": pop.W_opt[:, k].clone(),
        },
        "traces": {
            "e": pop.e[:, k].clone(),
            "r": pop.r[:, k].clone(),
            "D": pop.D[k].clone(),
            "last_decay": pop.decay[k].clone(),
        },
        "tsoft": {"W": pop.ts_W[k].clone(), "sigma2": pop.ts_sigma2[k].clone()},
        "rng": pop.noise.state(k),
        "pending": None
        if not pop._pending[k]
        else {
            "obs": pop._obs[k].clone(),
            "u": pop._u[k].clone(),
            "logp_b": pop._logp_b[k].clone(),
            "value_b": pop._value_b[k].clone(),
            "raw_b": pop._raw_b[k].clone(),
        },
    }


@torch.no_grad()
def load_member_state(
    pop: PopulationLearner, k: int, config: OnlineConfig, state: dict[str, Any]
) -> None:
    """Restore :meth:`member_state` into slot k with ``config`` (and its pending step)."""
    pop._set_config(k, config)
    if tuple(state["params"].shape) != tuple(pop.P[:, k].shape):
        raise ValueError("state was saved for a different network layout")
    pop.P[:, k] = state["params"]
    opt = state["optimizer"]
    pop.steps[k] = int(opt["step"])
    pop.v[:, k], pop.vmax_s[:, k], pop.m[:, k] = opt["v"], opt["vmax_scaled"], opt["m"]
    pop.W_opt[:, k] = opt["W"]
    tr = state["traces"]
    pop.e[:, k], pop.r[:, k] = tr["e"], tr["r"]
    pop.D[k], pop.decay[k] = tr["D"], tr["last_decay"]
    pop.ts_W[k], pop.ts_sigma2[k] = state["tsoft"]["W"], state["tsoft"]["sigma2"]
    pop.noise.load(k, state["rng"])
    pending = state.get("pending")
    pop._pending[k] = pending is not None
    if pending is not None:
        pop._obs[k], pop._u[k] = pending["obs"], pending["u"]
        pop._logp_b[k], pop._value_b[k] = pending["logp_b"], pending["value_b"]
        if "raw_b" not in pending and bool(pop._b["kl_analytic"][k]):
            raise ValueError(
                "this checkpoint's pending transition has no raw_b (pi_b's output), which "
                "trace_divergence='analytic' needs; resume it with trace_divergence='sample'"
            )
        pop._raw_b[k] = pending.get("raw_b", torch.zeros(pop.head.raw_dim))


def write_constants(pop: PopulationLearner, k: int, cfg: OnlineConfig) -> None:
    """Write member k's per-member constants from its config (every setting that is not
    state: reward scale, discount, regularisers and their choices, trace, optimiser and
    t-soft constants)."""
    c, c64, b, nps = pop._c, pop._c64, pop._b, pop._np
    beta1, beta2 = cfg.opt_betas
    c["reward_scale"][k] = cfg.effective_reward_scale
    c["gamma"][k] = cfg.gamma
    c["one_m_gamma"][k] = 1.0 - cfg.gamma
    c["beta_td"][k] = cfg.beta_td
    c["beta_de"][k] = cfg.beta_de
    c["td_scale"][k] = 1.0 if cfg.td_units == "scaled" else 1.0 / (1.0 - cfg.gamma)
    b["pre_squash"][k] = cfg.entropy_density == "pre_squash"
    b["critic_actor"][k] = cfg.critic_signal == "actor"
    b["kl_analytic"][k] = cfg.trace_divergence == "analytic"
    b["weighted_score"][k] = cfg.policy_gradient == "weighted_score"
    b["limit_terminal"][k] = cfg.time_limit == "terminal"
    b["ln_frozen"][k] = pop.lay.layer_norm and not cfg.layer_norm_affine
    pop._norm_keep[k] = 1.0
    if b["ln_frozen"][k]:
        pop._norm_keep[k, pop.lay.norm_rows] = 0.0
    nps["ams_raw"][k] = float(cfg.amsgrad_max == "raw")
    c["neg_kappa"][k] = -cfg.kappa
    b["kappa_pos"][k] = cfg.kappa > 0.0
    c["gl1"][k] = cfg.gamma * cfg.lambdas[0]
    c["gl2"][k] = cfg.gamma * cfg.lambdas[1]
    c["beta2"][k] = beta2
    c["one_m_beta2"][k] = 1.0 - beta2
    c["opt_eps"][k] = cfg.opt_eps
    mom_only = beta1 == 0.0 or math.isinf(cfg.k_dof)
    b["mom_only"][k] = mom_only
    c["omb_mom"][k] = 1.0 - beta1
    c["w_coef"][k] = 0.0 if mom_only else 1.0 - 1.0 / beta1
    for j in range(2):
        n = torch.tensor([float(seg[j]) for seg in pop.lay.segments])
        if mom_only:
            pop.num[j, k], pop.den[j, k] = 1.0, 0.0
        else:
            # an empty segment (a part of a split head the value network does not have)
            # gets weight 0 instead of 0 / 0
            pop.num[j, k] = n * (1.0 + cfg.k_dof)
            pop.den[j, k] = torch.where(n > 0, n * cfg.k_dof, 1.0)
    nps["beta1"][k], nps["beta2"][k] = beta1, beta2
    nps["lr"][k], nps["ams_decay"][k] = cfg.lr, cfg.amsgrad_decay
    c64["tau"][k] = cfg.tau
    c64["nu"][k] = cfg.nu
    c64["sigma2_min"][k] = SIGMA2_MIN
    b["polyak"][k] = math.isinf(cfg.nu)
