"""pporpe: Proximal Policy Optimization with Relative Pearson Divergence.

The surrogate objectives of PPO (clip), PPO-RB (rollback), PPO-RPE and SPO as pure tensor
functions (:mod:`pporpe.surrogates`), the paper's online actor-critic learner
(:mod:`pporpe.online`), a batch PPO trainer (:mod:`pporpe.batch`), the one run loop both
train through (:mod:`pporpe.runs`), and the paper's experiments
(:mod:`pporpe.experiments`). See ``docs/glossary.md`` for the mapping from the paper's
symbols to code names.

The learners are imported on first use of their names here, so ``import pporpe`` stays
light for users of the surrogates alone.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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
    spo_surrogate_advantage,
    surrogate_loss,
    surrogate_objective,
)

if TYPE_CHECKING:
    from .batch import BatchConfig, BatchLearner, train_batch, zoo_config
    from .online import OnlineConfig, OnlineLearner, TrainConfig
    from .policy import Policy
    from .runs import RunResult, load_policy, train

__version__ = "0.5.0"

_LAZY = {
    "OnlineConfig": "pporpe.online",
    "OnlineLearner": "pporpe.online",
    "TrainConfig": "pporpe.online",
    "BatchConfig": "pporpe.batch",
    "BatchLearner": "pporpe.batch",
    "train_batch": "pporpe.batch",
    "zoo_config": "pporpe.batch",
    "Policy": "pporpe.policy",
    "RunResult": "pporpe.runs",
    "load_policy": "pporpe.runs",
    "train": "pporpe.runs",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pporpe' has no attribute {name!r}")


__all__ = [
    "METHODS",
    "BatchConfig",
    "BatchLearner",
    "Method",
    "OnlineConfig",
    "OnlineLearner",
    "Policy",
    "Regularization",
    "RunResult",
    "TrainConfig",
    "__version__",
    "check_surrogate_params",
    "load_policy",
    "ratio_thresholds",
    "regularization_amount",
    "relative_ratio",
    "rpe_divergence",
    "rpe_gain",
    "rpe_surrogate_advantage",
    "spo_surrogate_advantage",
    "surrogate_loss",
    "surrogate_objective",
    "train",
    "train_batch",
    "zoo_config",
]
