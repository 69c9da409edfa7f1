"""One vector step of every member of a batch population: :class:`EnvStep` and
:func:`step_members`.

Each member of a :class:`~pporpe.batch.population.BatchPopulation` steps its own vector
environment (held by its :class:`~pporpe.batch.learner.BatchLearner`) with its own actions;
the results are stacked ``[K, N, ...]`` for the population's batched computation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium.vector import SyncVectorEnv

from .learner import BatchLearner
from .vecenv import step_same_step

__all__ = ["EnvStep", "step_members"]


@dataclass
class EnvStep:
    """One vector step of every member, stacked ``[K, N, ...]``."""

    raw_obs: np.ndarray
    reward: np.ndarray
    term: np.ndarray
    trunc: np.ndarray
    done: np.ndarray
    final_obs: list[dict[int, Any]]
    """The final observation of every sub-environment whose episode ended, by member."""

    @staticmethod
    def empty(members: int, like_obs: np.ndarray) -> EnvStep:
        shape = like_obs.shape[:2]
        return EnvStep(
            raw_obs=np.zeros_like(like_obs),
            reward=np.zeros(shape),
            term=np.zeros(shape, dtype=bool),
            trunc=np.zeros(shape, dtype=bool),
            done=np.zeros(shape, dtype=bool),
            final_obs=[{} for _ in range(members)],
        )


def step_members(
    learners: dict[int, BatchLearner],
    action: np.ndarray,
    like_obs: np.ndarray,
    n_envs: int,
    errors: dict[int, str],
) -> EnvStep:
    """Step every busy member's vector environment (``learners``: the busy members' learners,
    by slot) with its actions (a :class:`SyncVectorEnv` through :func:`step_same_step`); a
    member whose reward or observation is not finite goes to ``errors``, its rows zero.
    ``like_obs``: the population's raw observations ``[K, N, obs_dim]`` (shape and dtype)."""
    step = EnvStep.empty(like_obs.shape[0], like_obs)
    for k, learner in learners.items():
        envs = learner.envs
        if isinstance(envs, SyncVectorEnv):
            out = (step.raw_obs[k], step.reward[k], step.term[k], step.trunc[k])
            step.final_obs[k] = step_same_step(envs, action[k], *out)
        else:
            raw_next, reward, term, trunc, info = envs.step(action[k])
            step.raw_obs[k], step.reward[k], step.term[k], step.trunc[k] = (
                raw_next,
                reward,
                term,
                trunc,
            )
            ended = np.nonzero(np.asarray(term) | np.asarray(trunc))[0]
            step.final_obs[k] = {int(i): info["final_obs"][i] for i in ended}
    finite = np.isfinite(step.reward).all(1) & np.isfinite(step.raw_obs).all((1, 2))
    for k, learner in learners.items():
        if not finite[k]:
            errors[k] = f"non-finite reward or observation at step {learner.total_steps}"
            step.raw_obs[k], step.reward[k], step.term[k], step.trunc[k] = 0, 0.0, False, False
            continue
        learner.total_steps += n_envs
    step.trunc &= ~step.term
    step.done[:] = step.term | step.trunc
    return step
