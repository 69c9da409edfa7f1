"""The paper's online actor-critic learner (Algorithm 1): one update per environment step.

One learner, computed by one of two engines. This package holds what both share:
:class:`PopulationLearner` (:mod:`.population`) runs K >= 1 members in lockstep with
stacked parameters and calls its engine through one interface (:mod:`.engine`);
:class:`OnlineLearner` (:mod:`.learner`) is one member with scalar inputs. Beside them:
the settings (:class:`OnlineConfig`, and :class:`TrainConfig` for a run; :mod:`.config`),
the buffers (:mod:`.state`), the per-member random streams (:mod:`.noise`), a step's
statistics (:mod:`.stats`) and the learner kind ``"online"`` of the run loop
(:mod:`.kind`).

The engines: :mod:`.torch_engine`, the readable reference (batched torch operations; its
scalar components :class:`AdaptiveTraces`, :class:`TDAmsProp` and :class:`TSoftUpdate`
are usable on their own), and :mod:`.fused_engine`, the default (one numba kernel per
step, by stage in :mod:`.fused_engine.kernels`). docs/online-learner.md maps each
equation of the paper to the function of each engine that computes it.

:mod:`.fused`, :mod:`.update`, :mod:`.optim`, :mod:`.traces` and :mod:`.tsoft` are the
old paths, deprecated re-exports for one release.
"""

from .config import (
    AUTHOR_CHOICES,
    BASELINE_CHOICES,
    DEFAULT_CHOICES,
    TESTBED,
    TESTBED_WEIGHTS,
    OnlineConfig,
    TrainConfig,
)
from .learner import OnlineLearner
from .population import PopulationLearner
from .stats import StepStats
from .torch_engine.optim import TDAmsProp
from .torch_engine.traces import AdaptiveTraces
from .torch_engine.tsoft import TSoftUpdate

__all__ = [
    "AUTHOR_CHOICES",
    "BASELINE_CHOICES",
    "DEFAULT_CHOICES",
    "TESTBED",
    "TESTBED_WEIGHTS",
    "AdaptiveTraces",
    "OnlineConfig",
    "OnlineLearner",
    "PopulationLearner",
    "StepStats",
    "TDAmsProp",
    "TSoftUpdate",
    "TrainConfig",
]
