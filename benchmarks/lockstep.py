"""A population of online runs stepping its own environments, for the engine benchmarks.

:mod:`engine_shadow` and :mod:`engine_divergence` both drive a
:class:`pporpe.online.PopulationLearner` of one engine through a test-bed task the way
``benchmarks/testbed.py`` does (one member per seed, each with its own environment seeded
by it), and step other learners beside it. :class:`EngineRun` is that population, split
into the named parts of a step (:meth:`EngineRun.transition`, :meth:`EngineRun.learn`,
:meth:`EngineRun.end_episodes`), so that a benchmark can put a second learner between
them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from testbed import TASKS, settings_for


def population(engine: str, env: Any, config: str, seeds: list[int], **options: Any) -> Any:
    """A fresh :class:`~pporpe.online.PopulationLearner` of ``engine`` for ``env``'s spaces,
    one member per seed, all with ``config``'s settings (a config of
    ``benchmarks/testbed.py``); ``options`` go to the learner (``compile_update``)."""
    from pporpe.online import OnlineConfig, PopulationLearner

    settings = settings_for(config)
    settings.pop("engine", None)
    cfg = OnlineConfig(**settings)
    return PopulationLearner(
        env.observation_space.shape[0],
        env.action_space.low,
        env.action_space.high,
        [cfg] * len(seeds),
        seeds,
        engine=engine,
        **options,
    )


@dataclass
class EngineRun:
    """One engine's population and its environments, stepping on its own."""

    learner: Any
    envs: list[Any]
    actions: np.ndarray
    episodes: np.ndarray

    @classmethod
    def start(cls, engine: str, task: str, config: str, seeds: list[int]) -> EngineRun:
        """A fresh population of ``engine`` with ``config``'s settings, one member per seed,
        every member's first episode begun."""
        from pporpe.envs import make_env

        envs = [make_env(TASKS[task], seed=s) for s in seeds]
        learner = population(engine, envs[0], config, seeds)
        first = np.stack([e.reset(seed=s)[0] for e, s in zip(envs, seeds, strict=True)])
        actions = learner.begin_episode(list(range(len(seeds))), first)
        return cls(learner, envs, actions, np.zeros(len(seeds), dtype=int))

    def transition(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every member's environment steps with its action: ``(reward, next observation,
        terminated, truncated)``, the learner's dtypes."""
        rows = [env.step(a) for env, a in zip(self.envs, self.actions, strict=True)]
        obs, rew, term, trunc = (np.asarray(x) for x in list(zip(*rows, strict=True))[:4])
        return rew.astype(np.float32), obs.astype(np.float32), term, trunc

    def learn(self, rew: np.ndarray, obs: np.ndarray, term: np.ndarray, trunc: np.ndarray) -> Any:
        """The learner's step on a transition; keeps the next actions, returns the step's
        statistics."""
        stats, self.actions = self.learner.step(rew, obs, term, trunc)
        return stats

    def end_episodes(self, ended: np.ndarray) -> None:
        """Reset the environments of the members whose episode ``ended`` and begin their
        next episode."""
        idx = np.nonzero(ended)[0]
        if len(idx) == 0:
            return
        first = np.stack([self.envs[k].reset()[0] for k in idx])
        self.actions = self.actions.copy()
        self.actions[idx] = self.learner.begin_episode(idx, first)
        self.episodes[idx] += 1

    def step(self) -> tuple[np.ndarray, np.ndarray]:
        """One transition and learning step of every member: ``(ratio, ended)`` ``[K]``."""
        rew, obs, term, trunc = self.transition()
        stats = self.learn(rew, obs, term, trunc)
        ended = term | trunc
        self.end_episodes(ended)
        return stats.ratio.double().numpy(), ended

    def nudge(self, seed: int) -> None:
        """Move every parameter one float32 step (ulp) up or down, the direction drawn
        from ``seed`` (the same for the value network and its target): the control, a
        difference of the size of one rounding."""
        import torch

        p = self.learner.state.params
        up = torch.from_numpy(np.random.default_rng(seed).random(p[0].shape) < 0.5)
        toward = torch.where(up, torch.full_like(p[0], np.inf), torch.full_like(p[0], -np.inf))
        for i in range(p.shape[0]):
            p[i] = torch.nextafter(p[i], toward)

    def params(self) -> np.ndarray:
        """Policy and value parameters, float64 ``[K, elements]``."""
        p = self.learner.state.params[:2]
        return p.double().movedim(1, 0).reshape(p.shape[1], -1).numpy()

    def close(self) -> None:
        """Close every environment."""
        for env in self.envs:
            env.close()
