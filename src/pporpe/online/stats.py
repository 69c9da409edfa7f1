"""What one step of the online learner did, per member, read by name."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

__all__ = ["StepStats"]


@dataclass(frozen=True)
class StepStats:
    """What one step did: ``[K]`` tensors, one entry per member (0-dim for one member).

    No ``.item()`` in the step path; read by name.
    """

    delta: Tensor
    """TD error delta (scaled-reward units)."""
    adv: Tensor
    """Regularised advantage A used by the surrogate."""
    ratio: Tensor
    """Density ratio rho = pi_theta_t / pi_theta_{t-1} of the transition."""
    divergence: Tensor
    """KL estimate + squared value change since the last step."""
    trace_decay: Tensor
    """Adaptive trace decay exp(-kappa D) after this step."""

    def member(self, k: int) -> StepStats:
        """Member k's entries (0-dim tensors)."""
        return StepStats(*(getattr(self, f.name)[k] for f in fields(self)))

    def as_dict(self) -> dict[str, float]:
        """Python floats by name, for 0-dim stats (synchronises; logging and tests only)."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    def table(self) -> np.ndarray:
        """The fields as the rows of one ``[5, K]`` array, in field order (a copy; the
        fields' dtype). A run loop keeps a member's column per step: cheaper than
        :meth:`member`'s five tensors, and :meth:`from_table` gives the same tensors back."""
        return torch.stack(
            (self.delta, self.adv, self.ratio, self.divergence, self.trace_decay)
        ).numpy()

    @staticmethod
    def from_table(table: np.ndarray) -> StepStats:
        """The stats whose fields are the rows of ``table`` (``[5, ...]``; shares its
        memory): :meth:`table`'s inverse, and with columns of many steps stacked side by
        side, what :meth:`stack` gives of those steps."""
        return StepStats(*torch.from_numpy(np.ascontiguousarray(table)))

    @staticmethod
    def stack(steps: list[StepStats]) -> StepStats:
        """The stats of many steps, each field stacked along a new first dimension."""
        return StepStats(
            *(torch.stack([getattr(s, f.name) for s in steps]) for f in fields(StepStats))
        )
