"""One online run with scalar inputs: :class:`OnlineLearner` is the population learner
(:class:`~pporpe.online.population.PopulationLearner`) with K = 1.

Usage, one environment::

    learner = OnlineLearner(obs_dim, env.action_space.low, env.action_space.high,
                            OnlineConfig(method="rpe"), seed=0)
    action = learner.begin_episode(obs)
    while training:
        obs, reward, terminated, truncated, _ = env.step(action)
        stats, action = learner.step(reward, obs, terminated, truncated)
        if terminated or truncated:
            obs, _ = env.reset()
            action = learner.begin_episode(obs)

``step`` returns the next action because the paper samples a_{t+1} with the parameters
*before* the update of transition t (that is what makes rho != 1).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from torch import Tensor

from .config import OnlineConfig
from .population import PopulationLearner
from .stats import StepStats

__all__ = ["OnlineLearner", "StepStats"]


class OnlineLearner:
    """The paper's online actor-critic (Algorithm 1) for one run, seeded by ``seed``.

    Its initial parameters are those of :func:`pporpe.nn.mlp.mlp` after
    ``torch.manual_seed(seed)`` (the global RNG is left untouched), and its samples come
    from its own generator seeded with ``seed``. ``engine``: None (``config.engine``),
    ``"torch"`` or ``"fused"`` (:class:`~pporpe.online.population.PopulationLearner`; the
    fused one is about 10x faster for one run).
    """

    def __init__(
        self,
        obs_dim: int,
        action_low: Any,
        action_high: Any,
        config: OnlineConfig,
        seed: int = 0,
        engine: str | None = None,
    ) -> None:
        self.config = config
        self.population = PopulationLearner(
            obs_dim,
            action_low,
            action_high,
            [config],
            [seed],
            compile_update=config.compile,
            engine=engine,
        )
        self.obs_dim, self.act_dim = obs_dim, self.population.act_dim

    @property
    def theta(self) -> Tensor:
        """The flat parameters, policy block then value block (a copy)."""
        return self.population.member_theta(0)

    @property
    def target(self) -> Tensor:
        """The flat target value network (a copy)."""
        return self.population.member_target(0)

    def begin_episode(self, obs: Any) -> np.ndarray:
        """Reset the traces, sample the first action of an episode and return it."""
        return self.population.begin_episode([0], np.asarray(obs)[None])[0]

    def step(
        self, reward: float, next_obs: Any, terminated: bool, truncated: bool
    ) -> tuple[StepStats, np.ndarray]:
        """Learn from transition (s_t, a_t, r_t, s_{t+1}); return its stats and a_{t+1}.

        ``terminated`` stops bootstrapping; ``truncated`` (a time limit) does not. After
        either, start the next episode with :meth:`begin_episode`.
        """
        stats, actions = self.population.step(
            np.asarray([reward]),
            np.asarray(next_obs)[None],
            np.asarray([terminated]),
            np.asarray([truncated]),
        )
        return stats.member(0), actions[0]

    def act_deterministic(self, obs: Any) -> np.ndarray:
        """Test-time action: the policy's location mapped into the action bounds."""
        return self.population.act_deterministic(np.asarray(obs)[None])[0]

    def value(self, obs: Any) -> float:
        """V(s) of the online value network."""
        return float(self.population.value(np.asarray(obs)[None])[0])

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue learning, mid-episode included (a copy)."""
        return self.population.member_state(0)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (same architecture and config)."""
        self.population.load_member_state(0, self.config, state)

    def parameters_finite(self) -> bool:
        """Whether every parameter (online and target) is finite."""
        return bool(self.population.finite()[0])
