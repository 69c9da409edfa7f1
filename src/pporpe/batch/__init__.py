r"""Standard batch PPO (vector-env rollouts, GAE, minibatch epochs) with the PPO, PPO-RB,
PPO-RPE and SPO surrogates: one word apart (``BatchConfig(method="rb")``).

* :mod:`.config`     :class:`BatchConfig`, :data:`ZOO_DEFAULTS`, :func:`zoo_config`;
* :mod:`.normalize`  observation and reward normalisation;
* :mod:`.model`      the actor-critic (shared flat-parameter networks);
* :mod:`.buffer`     rollout storage and minibatches with named fields;
* :mod:`.loss`       the minibatch loss, a pure function returning (loss, metrics);
* :mod:`.learner`    :class:`BatchLearner`: acting, learning, the test-time policy;
* :mod:`.vecenv`     vector environments with replayable sub-environments;
* :mod:`.stacked`    K runs' networks and Adam states as the rows of one tensor;
* :mod:`.population` :class:`BatchPopulation`: K runs trained in lockstep in one process;
* :mod:`.kind`       the learner kind ``"batch"`` and :func:`train_batch`.
"""

from ..advantages import compute_gae
from .buffer import FinishedEpisode, Minibatch, RolloutBuffer
from .config import ZOO_DEFAULTS, BatchConfig, zoo_config
from .kind import BatchResult, evaluate_learner, load_batch_learner, train_batch
from .learner import BatchLearner, UpdateStats
from .model import ActorCritic
from .normalize import Normalizer, RunningMeanStd
from .population import BatchPopulation
from .vecenv import make_vec_env

__all__ = [
    "ZOO_DEFAULTS",
    "ActorCritic",
    "BatchConfig",
    "BatchLearner",
    "BatchPopulation",
    "BatchResult",
    "FinishedEpisode",
    "Minibatch",
    "Normalizer",
    "RolloutBuffer",
    "RunningMeanStd",
    "UpdateStats",
    "compute_gae",
    "evaluate_learner",
    "load_batch_learner",
    "make_vec_env",
    "train_batch",
    "zoo_config",
]
