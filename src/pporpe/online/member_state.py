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

from typing import TYPE_CHECKING, Any

import torch

from .config import OnlineConfig

if TYPE_CHECKING:
    from .population import PopulationLearner

__all__ = ["load_member_state", "member_state"]


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
        pop._raw_b[k] = pending.get("raw_b", torch.zeros(pop.head.raw_dim))
