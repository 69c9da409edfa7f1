"""Vector environments of the batch learner, whose sub-environments can replay their
current episode (exact resume from a checkpoint)."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

from ..envs import make_env
from .config import BatchConfig

__all__ = ["VecEnv", "make_vec_env"]

VecEnv = SyncVectorEnv | AsyncVectorEnv


class _Replayable(gymnasium.Wrapper):
    """Records how the current episode was reached, so that a checkpoint can rebuild it.

    On ``reset`` it keeps the seed (or the environment's RNG state when no seed is given)
    and on ``step`` every action; :meth:`replay_record` returns them and
    :meth:`replay_apply` replays a record on a fresh environment.
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)
        self._start: dict[str, Any] = {}
        self._actions: list[np.ndarray] = []
        self.replay_pending: dict[str, Any] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        rng = None
        if seed is None:
            rng = copy.deepcopy(self.env.unwrapped.np_random.bit_generator.state)
        self._start = {"seed": seed, "rng": rng, "options": options}
        self._actions = []
        return self.env.reset(seed=seed, options=options)

    def step(self, action: Any) -> Any:
        self._actions.append(np.array(action, copy=True))
        return self.env.step(action)

    def replay_record(self) -> dict[str, Any]:
        """The current episode's start and actions (a copy)."""
        acts = np.stack(self._actions) if self._actions else np.zeros((0,))
        return {**copy.deepcopy(self._start), "actions": acts}

    def replay_apply(self) -> Any:
        """Rebuild the episode in :attr:`replay_pending`; return its current observation."""
        rec = self.replay_pending
        assert rec is not None
        self.replay_pending = None
        if rec["rng"] is not None:
            self.env.unwrapped.np_random.bit_generator.state = rec["rng"]
        obs = self.reset(seed=rec["seed"], options=rec["options"])[0]
        for a in rec["actions"]:
            obs = self.step(a)[0]
        return obs


def _make_sub_env(name: str, seed: int) -> Callable[[], gymnasium.Env]:
    def thunk() -> gymnasium.Env:
        return _Replayable(make_env(name, seed=seed))

    return thunk


def make_vec_env(cfg: BatchConfig) -> VecEnv:
    """The vector environment of a run, in SAME_STEP autoreset mode (see module docstring)."""
    fns = [_make_sub_env(cfg.env, cfg.seed + i) for i in range(cfg.n_envs)]
    if cfg.vec_env == "async":
        return AsyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)
    return SyncVectorEnv(fns, autoreset_mode=AutoresetMode.SAME_STEP)
