"""Vector environments of the batch learner, whose sub-environments can replay their
current episode (exact resume from a checkpoint)."""

from __future__ import annotations

from collections.abc import Callable

import gymnasium
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

from ..envs import ReplayableEnv, make_env
from .config import BatchConfig

__all__ = ["VecEnv", "make_vec_env"]

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
