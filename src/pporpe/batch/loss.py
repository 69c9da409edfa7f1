"""The batch learner's loss on one minibatch: a pure function returning (loss, metrics).

.. math:: L = -\\mathrm{mean}(\\rho A^\\dagger) + c_v\\,\\mathrm{mean}((V - R)^2)
              - c_H\\,\\mathrm{mean}(H[\\pi(\\cdot|s)])

with the per-sample objective rho * A^dagger of the configured surrogate
(:func:`pporpe.surrogates.surrogate_objective`: PPO, PPO-RB, PPO-RPE or SPO), the squared value
error optionally clipped as in PPO2, and an optional entropy bonus.

:func:`minibatch_loss` evaluates the networks and calls :func:`loss_terms`, which reduces
over the last dimension only: a minibatch of one run is ``[n]`` rows and gives a 0-dim
loss, a population's is ``[K, n]`` and gives one loss per member (what the batch
population, :mod:`pporpe.batch.population`, sums before its one backward pass).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from ..surrogates import surrogate_objective
from .buffer import Minibatch
from .config import BatchConfig

__all__ = [
    "LossMetrics",
    "LossModel",
    "NetOutputs",
    "Objective",
    "config_objective",
    "loss_terms",
    "minibatch_loss",
]


class LossModel(Protocol):
    """What the loss needs of the networks (:class:`~pporpe.batch.model.ActorCritic`, or
    a population's stacked networks)."""

    def log_prob(self, obs: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``(log pi(u|s), raw)``."""
        ...

    def value(self, obs: Tensor) -> Tensor:
        """V(s)."""
        ...

    def entropy(self, raw: Tensor) -> Tensor:
        """Entropy of pi(u|s) per row of ``raw``."""
        ...


@dataclass(frozen=True)
class NetOutputs:
    """What the networks computed on a minibatch (with gradient)."""

    logp: Tensor
    """log pi(u|s) of the minibatch's actions."""
    raw: Tensor
    """The policy head's raw input (one row per member with a state-independent scale)."""
    value: Tensor
    """V(s)."""


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


def minibatch_loss(model: LossModel, mb: Minibatch, cfg: BatchConfig) -> tuple[Tensor, LossMetrics]:
    """The loss of one minibatch (with gradient) and its metrics."""
    logp, raw = model.log_prob(mb.obs, mb.u)
    return loss_terms(NetOutputs(logp, raw, model.value(mb.obs)), mb, cfg, model.entropy)


Objective = Callable[[Tensor, Tensor], Tensor]
"""The per-sample surrogate objective rho * A^dagger of (ratio, advantages)."""


def config_objective(cfg: BatchConfig) -> Objective:
    """The surrogate objective of ``cfg`` (method, thresholds, PPO-RPE's form)."""

    def objective(ratio: Tensor, adv: Tensor) -> Tensor:
        return surrogate_objective(cfg.method, ratio, adv, cfg.eps, cfg.beta, cfg.eta, cfg.rpe_form)

    return objective


def loss_terms(
    out: NetOutputs,
    mb: Minibatch,
    cfg: BatchConfig,
    entropy: Callable[[Tensor], Tensor],
    objective: Objective | None = None,
) -> tuple[Tensor, LossMetrics]:
    """The loss of a minibatch from the networks' outputs, reduced over the last dimension
    (rows); ``entropy`` maps ``out.raw`` to the entropy per row; ``objective`` replaces
    ``cfg``'s surrogate (a population's members may each have their own)."""
    adv = mb.adv
    if cfg.adv_norm == "minibatch" and len(mb) > 1:
        adv = (adv - adv.mean(-1, keepdim=True)) / (adv.std(-1, keepdim=True) + 1e-8)
    ratio = torch.exp(out.logp - mb.logp_old)
    objective_of = objective if objective is not None else config_objective(cfg)
    policy_loss = -objective_of(ratio, adv).mean(-1)
    v = out.value
    if cfg.clip_vf is not None:
        v_clip = mb.v_old + torch.clamp(v - mb.v_old, -cfg.clip_vf, cfg.clip_vf)
        value_loss = torch.maximum((v - mb.ret).square(), (v_clip - mb.ret).square()).mean(-1)
    else:
        value_loss = (v - mb.ret).square().mean(-1)
    loss = policy_loss + cfg.vf_coef * value_loss
    if cfg.ent_coef > 0.0:
        loss = loss - cfg.ent_coef * entropy(out.raw).mean(-1)
    metrics = LossMetrics(policy_loss.detach(), value_loss.detach(), ratio.detach(), adv, out.raw)
    return loss, metrics
