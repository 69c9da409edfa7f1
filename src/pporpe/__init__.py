"""pporpe: Proximal Policy Optimization with Relative Pearson Divergence.

The surrogate objectives of PPO (clip), PPO-RB (rollback) and PPO-RPE as pure tensor
functions (:mod:`pporpe.surrogates`), the paper's online actor-critic learner, a batch
PPO trainer, and the paper's experiments. See ``docs/glossary.md`` for the mapping from
the paper's symbols to code names.
"""

from __future__ import annotations

from .surrogates import (
    METHODS,
    Method,
    Regularization,
    check_surrogate_params,
    ratio_thresholds,
    regularization_amount,
    relative_ratio,
    rpe_divergence,
    rpe_gain,
    rpe_surrogate_advantage,
    surrogate_loss,
    surrogate_objective,
)

__version__ = "0.1.0"

__all__ = [
    "METHODS",
    "Method",
    "Regularization",
    "__version__",
    "check_surrogate_params",
    "ratio_thresholds",
    "regularization_amount",
    "relative_ratio",
    "rpe_divergence",
    "rpe_gain",
    "rpe_surrogate_advantage",
    "surrogate_loss",
    "surrogate_objective",
]
