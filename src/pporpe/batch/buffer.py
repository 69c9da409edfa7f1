"""Rollout storage of the batch learner with named fields, and its minibatches."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["FinishedEpisode", "Minibatch", "RolloutBuffer"]


class RolloutBuffer:
    """Preallocated ``[n_steps, n_envs, ...]`` tensors of one rollout."""

    def __init__(self, n_steps: int, n_envs: int, obs_dim: int, act_dim: int) -> None:
        shape = (n_steps, n_envs)
        self.obs = torch.zeros(*shape, obs_dim)
        """Normalised observations s_t."""
        self.u = torch.zeros(*shape, act_dim)
        """Pre-map actions u_t (what the ratio is computed on)."""
        self.logp = torch.zeros(shape)
        """log pi_old(u_t|s_t)."""
        self.values = torch.zeros(shape)
        """V_old(s_t)."""
        self.rewards = torch.zeros(shape)
        """Normalised rewards r_t."""
        self.terminated = torch.zeros(shape, dtype=torch.bool)
        """The episode ended at step t with a true termination."""
        self.truncated = torch.zeros(shape, dtype=torch.bool)
        """The episode ended at step t by a time limit (and did not terminate)."""
        self.next_values = torch.zeros(shape)
        """V_old of the state reached by step t (final observation at an episode's end)."""
        self.advantages = torch.zeros(shape)
        """GAE(lambda) advantages (filled by :func:`compute_gae`)."""
        self.returns = torch.zeros(shape)
        """Lambda-returns: targets of the value function."""


@dataclass(frozen=True)
class FinishedEpisode:
    """An episode that ended during a rollout (raw, unnormalised rewards)."""

    env_index: int
    """Which sub-environment."""
    ret: float
    """Undiscounted return."""
    length: int
    """Steps in the episode."""
    total_steps: int
    """Environment steps over all sub-environments when it ended."""
    terminated: bool
    """True end (else a truncation)."""


@dataclass(frozen=True)
class Minibatch:
    """Rows of a rollout, flattened over ``[n_steps, n_envs]``, by name.

    The fields are column views of one packed ``[..., n, obs_dim + act_dim + 4]`` tensor,
    so a shuffled epoch is one gather (:meth:`index`) and a minibatch one slice
    (:meth:`slice`); the column layout is known here only. A population's minibatches
    have a leading member dimension (``[K, n, ...]``, :meth:`stack`, :meth:`index_rows`).
    """

    obs: Tensor
    """Normalised observations ``[n, obs_dim]``."""
    u: Tensor
    """Pre-map actions ``[n, act_dim]``."""
    logp_old: Tensor
    """log pi_old(u|s) ``[n]``."""
    adv: Tensor
    """Advantages ``[n]`` (normalised per batch when configured)."""
    ret: Tensor
    """Lambda-returns ``[n]``: value targets."""
    v_old: Tensor
    """V_old(s) ``[n]`` (for value clipping)."""
    packed: Tensor
    """The packed rows the fields are views of."""

    @staticmethod
    def _from_packed(packed: Tensor, obs_dim: int) -> Minibatch:
        d, a = obs_dim, packed.shape[-1] - obs_dim - 4
        return Minibatch(
            obs=packed[..., :d],
            u=packed[..., d : d + a],
            logp_old=packed[..., d + a],
            adv=packed[..., d + a + 1],
            ret=packed[..., d + a + 2],
            v_old=packed[..., d + a + 3],
            packed=packed,
        )

    @staticmethod
    def from_buffer(buf: RolloutBuffer, adv: Tensor, envs: slice = slice(None)) -> Minibatch:
        """The whole rollout of the sub-environments ``envs`` (all by default) as one flat
        batch, with ``adv`` as its advantages."""
        obs, u, logp = buf.obs[:, envs], buf.u[:, envs], buf.logp[:, envs]
        n = logp.numel()
        columns = [obs.reshape(n, -1), u.reshape(n, -1)]
        rest = (logp, adv, buf.returns[:, envs], buf.values[:, envs])
        columns += [t.reshape(n, 1) for t in rest]
        return Minibatch._from_packed(torch.cat(columns, dim=1), buf.obs.shape[-1])

    @staticmethod
    def stack(batches: list[Minibatch]) -> Minibatch:
        """Minibatches of equal size, one per member, as one ``[K, n, ...]`` minibatch."""
        packed = torch.stack([b.packed for b in batches])
        return Minibatch._from_packed(packed, batches[0].obs.shape[-1])

    def __len__(self) -> int:
        """Rows (per member)."""
        return int(self.packed.shape[-2])

    def index(self, rows: Tensor) -> Minibatch:
        """The rows ``rows`` (a gather: e.g. one shuffled epoch)."""
        return Minibatch._from_packed(self.packed[rows], self.obs.shape[-1])

    def index_rows(self, rows: Tensor) -> Minibatch:
        """Member k's rows ``rows[k]`` of a ``[K, n, ...]`` minibatch (one gather for all)."""
        members = torch.arange(rows.shape[0]).unsqueeze(1)
        return Minibatch._from_packed(self.packed[members, rows], self.obs.shape[-1])

    def members(self, rows: Tensor) -> Minibatch:
        """The members ``rows`` of a ``[K, n, ...]`` minibatch (a gather)."""
        return Minibatch._from_packed(self.packed[rows], self.obs.shape[-1])

    def slice(self, start: int, stop: int) -> Minibatch:
        """Rows ``start:stop`` (views)."""
        return Minibatch._from_packed(self.packed[..., start:stop, :], self.obs.shape[-1])
