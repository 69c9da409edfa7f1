"""Vector environments of the batch learner, whose sub-environments can replay their
current episode (exact resume from a checkpoint)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

from ..envs import ReplayableEnv, make_env
from .config import BatchConfig

__all__ = ["VecEnv", "make_vec_env", "step_same_step"]

VecEnv = SyncVectorEnv | AsyncVectorEnv


def _make_sub_env(name: str, seed: int) -> Callable[[], gymnasium.Env]:
    def thunk() -> gymnasium.Env:
        return ReplayableEnv(make_env(name, seed=seed))

    return thunk


def make_vec_env(cfg: BatchConfig) -> VecEnv:
    """The vector environment of a run, in SAME_STEP autoreset mode (see module docstring)."""
    fns = [_make_sub_env(cfg.env, cfg.seed + i) for i in range(cfg.n_envs)]
    if cfg.vec_env == "async":
        return AsyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)
    return SyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)


def step_same_step(
    envs: SyncVectorEnv,
    actions: np.ndarray,
    obs: np.ndarray,
    reward: np.ndarray,
    terminated: np.ndarray,
    truncated: np.ndarray,
) -> dict[int, Any]:
    """``envs.step(actions)`` of a :class:`SyncVectorEnv` in ``SAME_STEP`` autoreset mode,
    written into ``obs``, ``reward``, ``terminated`` and ``truncated`` (rows per
    sub-environment): the same calls on the sub-environments in the same order (step,
    then reset where the episode ended), without building the vector environment's info
    dicts. Returns the final observation of every sub-environment whose episode ended, by
    index (``info["final_obs"]`` of ``envs.step``). The vector environment's own buffers
    are not updated: use it through this function or through ``step``, not both in one
    rollout."""
    final: dict[int, Any] = {}
    for i, env in enumerate(envs.envs):
        o, r, term, trunc, _ = env.step(actions[i])
        reward[i], terminated[i], truncated[i] = r, term, trunc
        if term or trunc:
            final[i] = o
            o, _ = env.reset()
        obs[i] = o
    return final
