"""The batch learner's loss on one minibatch: a pure function returning (loss, metrics).

.. math:: L = -\\mathrm{mean}(\\rho A^\\dagger) + c_v\\,\\mathrm{mean}((V - R)^2)
              - c_H\\,\\mathrm{mean}(H[\\pi(\\cdot|s)])

with the per-sample objective rho * A^dagger of the configured surrogate
(:func:`pporpe.surrogates.surrogate_objective`: PPO, PPO-RB or PPO-RPE), the squared value
error optionally clipped as in PPO2, and an optional entropy bonus.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..surrogates import surrogate_objective
from .buffer import Minibatch
from .config import BatchConfig
from .model import ActorCritic

__all__ = ["LossMetrics", "minibatch_loss"]


@dataclass(frozen=True)
class LossMetrics:
    """What the loss of one minibatch measured (detached tensors)."""

    policy_loss: Tensor
    """-mean(rho * A^dagger)."""
    value_loss: Tensor
    """Mean (optionally clipped) squared value error."""
    ratio: Tensor
    """Density ratios rho of the minibatch."""
    adv: Tensor
    """The advantages used (normalised per minibatch when configured)."""
    raw: Tensor
    """The policy head's raw input (for the entropy statistic)."""


def minibatch_loss(
    model: ActorCritic, mb: Minibatch, cfg: BatchConfig
) -> tuple[Tensor, LossMetrics]:
    """The loss of one minibatch (with gradient) and its metrics."""
    adv = mb.adv
    if cfg.adv_norm == "minibatch" and len(mb) > 1:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    logp, raw = model.log_prob(mb.obs, mb.u)
    ratio = torch.exp(logp - mb.logp_old)
    objective = surrogate_objective(
        cfg.method, ratio, adv, cfg.eps, cfg.beta, cfg.eta, cfg.rpe_form
    )
    policy_loss = -objective.mean()
    v = model.value(mb.obs)
    if cfg.clip_vf is not None:
        v_clip = mb.v_old + torch.clamp(v - mb.v_old, -cfg.clip_vf, cfg.clip_vf)
        value_loss = torch.maximum((v - mb.ret).square(), (v_clip - mb.ret).square()).mean()
    else:
        value_loss = (v - mb.ret).square().mean()
    loss = policy_loss + cfg.vf_coef * value_loss
    if cfg.ent_coef > 0.0:
        loss = loss - cfg.ent_coef * model.entropy(raw).mean()
    metrics = LossMetrics(policy_loss.detach(), value_loss.detach(), ratio.detach(), adv, raw)
    return loss, metrics
