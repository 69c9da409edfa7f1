"""Observation and reward normalisation of the batch learner (running mean and std)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .config import BatchConfig

__all__ = ["Normalizer", "RunningMeanStd", "StackedNormalizer", "merge_moments"]


def merge_moments(
    mean: np.ndarray, var: np.ndarray, count: Any, x: np.ndarray, axis: int
) -> tuple[np.ndarray, np.ndarray, Any]:
    """Running ``(mean, var, count)`` merged with the samples of ``x`` along ``axis``
    (float64; ``count`` a float, or an array broadcasting against ``mean``: one count per
    member of a population)."""
    n = x.shape[axis]
    if n == 1:  # what mean and var give for one sample, exactly (x / 1 and 0), faster
        b_mean, b_var = np.take(x, 0, axis=axis), np.zeros_like(mean)
    else:
        b_mean, b_var = x.mean(axis=axis), x.var(axis=axis)
    total = count + n
    delta = b_mean - mean
    m2 = var * count + b_var * n + delta * delta * count * n / total
    return mean + delta * n / total, m2 / total, total


def scaled_obs(obs: Any, mean: np.ndarray, var: np.ndarray, clip: Any) -> np.ndarray:
    """``clip((obs - mean) / sqrt(var + 1e-8), -clip, clip)`` as float32."""
    out = (np.asarray(obs, dtype=np.float64) - mean) / np.sqrt(var + 1e-8)
    return np.clip(out, -clip, clip).astype(np.float32)


def scaled_reward(r: np.ndarray, ret_var: np.ndarray, clip: Any) -> np.ndarray:
    """``clip(r / sqrt(var(G) + 1e-8), -clip, clip)`` as float32."""
    return np.clip(r / np.sqrt(ret_var + 1e-8), -clip, clip).astype(np.float32)


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
        if x.shape[0] == 0:
            return
        self.mean, self.var, self.count = merge_moments(self.mean, self.var, self.count, x, 0)

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
        return scaled_obs(obs, self.obs_rms.mean, self.obs_rms.var, self.cfg.clip_obs)

    def reward(self, reward: np.ndarray, done: np.ndarray) -> np.ndarray:
        """Normalised float32 rewards of one vector step; ``done`` = terminated | truncated."""
        r = np.asarray(reward, dtype=np.float64)
        if not self.cfg.normalize_reward:
            return r.astype(np.float32)
        self.returns = self.returns * self.cfg.gamma + r
        self.ret_rms.update(self.returns)
        out = scaled_reward(r, self.ret_rms.var, self.cfg.clip_reward)
        self.returns[np.asarray(done, dtype=bool)] = 0.0
        return out

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


class StackedNormalizer:
    """The :class:`Normalizer` of K runs of one population, stacked along a first axis.

    Member k's statistics are row k of float64 arrays; every operation is the solo
    normaliser's on those rows (:func:`merge_moments`, :func:`scaled_obs`,
    :func:`scaled_reward`), so a member's numbers are those of a run of its own. The
    settings that may differ between members (gamma, the clip bounds) are per-row arrays;
    whether observations and rewards are normalised at all is common to the population.
    """

    def __init__(
        self, members: int, n_envs: int, obs_dim: int, normalize_obs: bool, normalize_reward: bool
    ) -> None:
        K = members
        self.normalize_obs, self.normalize_reward = normalize_obs, normalize_reward
        self.obs_mean = np.zeros((K, obs_dim))
        self.obs_var = np.ones((K, obs_dim))
        self.obs_count = np.zeros((K, 1))
        self.ret_mean = np.zeros(K)
        self.ret_var = np.ones(K)
        self.ret_count = np.zeros(K)
        self.returns = np.zeros((K, n_envs))
        self.gamma = np.zeros((K, 1))
        self.clip_obs = np.ones((K, 1, 1))
        self.clip_reward = np.ones((K, 1))

    def load_member(self, k: int, norm: Normalizer) -> None:
        """Row ``k`` from a run's normaliser (its statistics and settings)."""
        self.obs_mean[k], self.obs_var[k] = norm.obs_rms.mean, norm.obs_rms.var
        self.obs_count[k] = norm.obs_rms.count
        self.ret_mean[k], self.ret_var[k] = norm.ret_rms.mean, norm.ret_rms.var
        self.ret_count[k] = norm.ret_rms.count
        self.returns[k] = norm.returns
        self.gamma[k] = norm.cfg.gamma
        self.clip_obs[k] = norm.cfg.clip_obs
        self.clip_reward[k] = norm.cfg.clip_reward

    def store_member(self, k: int, norm: Normalizer) -> None:
        """Row ``k`` into a run's normaliser (the inverse of :meth:`load_member`)."""
        norm.obs_rms.mean, norm.obs_rms.var = self.obs_mean[k].copy(), self.obs_var[k].copy()
        norm.obs_rms.count = float(self.obs_count[k, 0])
        norm.ret_rms.mean, norm.ret_rms.var = self.ret_mean[k].copy(), self.ret_var[k].copy()
        norm.ret_rms.count = float(self.ret_count[k])
        norm.returns = self.returns[k].copy()

    def obs(self, obs: np.ndarray, update: bool) -> np.ndarray:
        """Normalised float32 observations ``[K, n_envs, obs_dim]`` (``update`` counts them)."""
        if not self.normalize_obs:
            return np.asarray(obs, dtype=np.float32)
        x = np.asarray(obs, dtype=np.float64)
        if update:
            moments = merge_moments(self.obs_mean, self.obs_var, self.obs_count, x, 1)
            self.obs_mean, self.obs_var, self.obs_count = moments
        return scaled_obs(x, self.obs_mean[:, None], self.obs_var[:, None], self.clip_obs)

    def member_obs(self, k: int, obs: np.ndarray) -> np.ndarray:
        """Member ``k``'s normalisation of ``obs`` ``[n, obs_dim]`` (not counted)."""
        if not self.normalize_obs:
            return np.asarray(obs, dtype=np.float32)
        return scaled_obs(obs, self.obs_mean[k], self.obs_var[k], self.clip_obs[k, 0, 0])

    def reward(self, reward: np.ndarray, done: np.ndarray) -> np.ndarray:
        """Normalised float32 rewards ``[K, n_envs]`` of one step of every member."""
        r = np.asarray(reward, dtype=np.float64)
        if not self.normalize_reward:
            return r.astype(np.float32)
        self.returns = self.returns * self.gamma + r
        moments = merge_moments(self.ret_mean, self.ret_var, self.ret_count, self.returns, 1)
        self.ret_mean, self.ret_var, self.ret_count = moments
        out = scaled_reward(r, self.ret_var[:, None], self.clip_reward)
        self.returns[np.asarray(done, dtype=bool)] = 0.0
        return out
