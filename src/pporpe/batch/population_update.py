"""What one update of a batch population keeps: its bookkeeping per member, its settings
gathered once, and its loss groups (members that share one :func:`.loss.loss_terms` call).

Used by :meth:`pporpe.batch.population.BatchPopulation.train`.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from .config import BatchConfig
from .loss import Objective

__all__ = ["LossGroup", "Minibatches", "StepSettings", "grouped_objective"]


@dataclass
class Minibatches:
    """Per-member bookkeeping of one update's epochs."""

    active: list[int]
    """Members still taking steps (a target_kl stop removes one)."""
    rows: dict[int, int]
    """Minibatch steps taken, by member."""
    samples: dict[int, int]
    """Samples seen, by member."""
    epochs: dict[int, int]
    """Whole epochs run, by member."""
    raw: dict[int, Tensor]
    """The policy head's raw input of the minibatch where a member stopped early."""
    last_raw: Tensor | None = None
    """The policy head's raw input of the last minibatch (every member's)."""


@dataclass(frozen=True)
class LossGroup:
    """Members that share loss weights and value clipping (one :func:`loss_terms` call)."""

    cfg: BatchConfig
    """A member's config (for the weights, value clipping and advantage normalisation)."""
    rows: Tensor | None
    """The members, or None for every slot."""
    objective: Objective
    """The surrogate of every member of the group, on the group's rows."""


def grouped_objective(parts: list[tuple[Objective, Tensor]]) -> Objective:
    """One objective over a group's rows from the objectives of its subgroups (``parts``:
    each with its rows within the group)."""

    def objective(ratio: Tensor, adv: Tensor) -> Tensor:
        out = ratio.new_zeros(ratio.shape)
        for fn, rows in parts:
            out = out.index_put((rows,), fn(ratio[rows], adv[rows]))
        return out

    return objective


@dataclass(frozen=True)
class StepSettings:
    """What the minibatch steps of one update need of each member, gathered once."""

    lr: dict[int, float]
    """Learning rate, by member."""
    adam_eps: dict[int, float]
    """Adam's epsilon, by member."""
    clip: Tensor
    """``[K]`` max_grad_norm (1 where there is none)."""
    no_clip: Tensor
    """``[K]`` whether a member's gradient is not clipped (or the slot is free)."""
    target_kl: dict[int, float]
    """target_kl of the members that have one."""
    loss_groups: dict[tuple[int, ...], list[LossGroup]]
    """Loss groups by set of active members (filled as they are needed)."""
