"""The paper's online actor-critic learner (Alg. 1): one update per environment step.

:class:`OnlineLearner` and its settings (:class:`OnlineConfig`, and :class:`TrainConfig`
for a run), its components (:mod:`.traces`, :mod:`.tsoft`, :mod:`.optim`), and its
learner kind ``"online"`` for the run loop (:mod:`.kind`).
"""

from .config import OnlineConfig, TrainConfig
from .learner import OnlineLearner, StepStats
from .optim import TDAmsProp
from .traces import AdaptiveTraces
from .tsoft import TSoftUpdate

__all__ = [
    "AdaptiveTraces",
    "OnlineConfig",
    "OnlineLearner",
    "StepStats",
    "TDAmsProp",
    "TSoftUpdate",
    "TrainConfig",
]
