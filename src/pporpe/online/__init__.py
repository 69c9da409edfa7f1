"""The paper's online actor-critic learner (Algorithm 1): one update per environment step.

:class:`PopulationLearner` runs K >= 1 members in lockstep with stacked parameters
(:mod:`.population`; its elementwise update :mod:`.update`, its per-member random
streams :mod:`.noise`); :class:`OnlineLearner` is one member with scalar inputs. Settings:
:class:`OnlineConfig`, and :class:`TrainConfig` for a run. The scalar components
(:mod:`.traces`, :mod:`.tsoft`, :mod:`.optim`) are usable on their own. The learner kind
``"online"`` of the run loop is :mod:`.kind`.
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
