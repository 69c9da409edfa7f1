"""Observation and reward normalisation of the batch learner (running mean and std)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .config import BatchConfig

__all__ = ["Normalizer", "RunningMeanStd"]


class RunningMeanStd:
    """Running mean and variance of batches of vectors, in float64.

    Batches are merged with the parallel algorithm of Chan, Golub and LeVeque (1979):
    for counts n_a, n_b, means m_a, m_b and sums of squared deviations M_a, M_b,
    ``m = m_a + (m_b - m_a) n_b / n`` and ``M = M_a + M_b + (m_b - m_a)^2 n_a n_b / n``.
    The count starts at a tiny ``epsilon`` (mean 0, var 1) so the first batch dominates.
    """

    def __init__(self, shape: tuple[int, ...] = (), epsilon: float = 1e-4) -> None:
        self.mean = np.zeros(shape, dtype=np.float64)
        self.var = np.ones(shape, dtype=np.float64)
        self.count = float(epsilon)

    def update(self, batch: np.ndarray) -> None:
        """Merge a batch of shape ``[n, *shape]``."""
        x = np.asarray(batch, dtype=np.float64)
        n = x.shape[0]
        if n == 0:
            return
        b_mean = x.mean(axis=0)
        b_var = x.var(axis=0)
        total = self.count + n
        delta = b_mean - self.mean
        m2 = self.var * self.count + b_var * n + delta * delta * self.count * n / total
        self.mean = self.mean + delta * n / total
        self.var = m2 / total
        self.count = total

    def state_dict(self) -> dict[str, Any]:
        """Copies of mean, var and count."""
        return {"mean": self.mean.copy(), "var": self.var.copy(), "count": self.count}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.mean = np.array(state["mean"], dtype=np.float64)
        self.var = np.array(state["var"], dtype=np.float64)
        self.count = float(state["count"])


class Normalizer:
    """Observation and reward normalisation of a vector environment's outputs.

    * Observations: ``clip((obs - mean) / sqrt(var + 1e-8), -clip_obs, clip_obs)`` with the
      running statistics of every observation the learner acts on (the final observations
      of finished episodes are normalised but not counted).
    * Rewards: ``clip(r / sqrt(var(G) + 1e-8), -clip_reward, clip_reward)`` where
      ``G <- gamma * G + r`` is each sub-environment's running discounted return, reset
      when its episode ends (terminated or truncated). Not centred, so the sign of a
      reward is kept.
    """

    def __init__(self, obs_dim: int, n_envs: int, cfg: BatchConfig) -> None:
        self.cfg = cfg
        self.obs_rms = RunningMeanStd((obs_dim,))
        self.ret_rms = RunningMeanStd(())
        self.returns = np.zeros(n_envs, dtype=np.float64)

    def obs(self, obs: np.ndarray, update: bool) -> np.ndarray:
        """Normalised float32 observations (``update`` counts them in the statistics)."""
        if not self.cfg.normalize_obs:
            return np.asarray(obs, dtype=np.float32)
        if update:
            self.obs_rms.update(obs)
        out = (np.asarray(obs, dtype=np.float64) - self.obs_rms.mean) / np.sqrt(
            self.obs_rms.var + 1e-8
        )
        return np.clip(out, -self.cfg.clip_obs, self.cfg.clip_obs).astype(np.float32)

    def reward(self, reward: np.ndarray, done: np.ndarray) -> np.ndarray:
        """Normalised float32 rewards of one vector step; ``done`` = terminated | truncated."""
        r = np.asarray(reward, dtype=np.float64)
        if not self.cfg.normalize_reward:
            return r.astype(np.float32)
        self.returns = self.returns * self.cfg.gamma + r
        self.ret_rms.update(self.returns)
        out = np.clip(
            r / np.sqrt(self.ret_rms.var + 1e-8), -self.cfg.clip_reward, self.cfg.clip_reward
        )
        self.returns[np.asarray(done, dtype=bool)] = 0.0
        return out.astype(np.float32)

    def state_dict(self) -> dict[str, Any]:
        """Statistics and the running returns."""
        return {
            "obs_rms": self.obs_rms.state_dict(),
            "ret_rms": self.ret_rms.state_dict(),
            "returns": self.returns.copy(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.obs_rms.load_state_dict(state["obs_rms"])
        self.ret_rms.load_state_dict(state["ret_rms"])
        self.returns = np.array(state["returns"], dtype=np.float64)
