"""A trained policy, ready to act in a user's own code: :class:`Policy`.

:func:`pporpe.load_policy` returns one for any run folder (the online learner, batch PPO,
folders of every earlier version: :mod:`pporpe.runs.migrate`)::

    policy = pporpe.load_policy("runs/x")
    action = policy.act(obs)                           # the policy's location, bounded
    action = policy.act(obs, deterministic=False)      # a sample of pi(.|s), bounded
    actions = policy.act(batch_of_obs)                 # [N, obs_dim] -> [N, act_dim]

The observation normalisation a learner used (batch PPO's running statistics) is part of
the policy: pass raw observations.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.distributions import Distribution

from .nn.policies import PolicyHead

__all__ = ["Policy"]


class Policy:
    """A trained stochastic policy pi(a|s) over a Box action space, with no learner state.

    Built by the learner kinds from a checkpoint (see :func:`pporpe.load_policy`); the
    parts are public so that a researcher can take it apart:

    * ``raw(x)``: the network, normalised observations ``[N, obs_dim]`` -> head input
      ``[N, raw_dim]``;
    * ``head``: the distribution family over the pre-bound variable u (student-t or
      normal, :mod:`pporpe.nn.policies`);
    * ``to_action(u)``: u mapped into the action box (the learner's bound: sigmoid map
      or clip);
    * ``normalize(obs)``: the observation preprocessing (identity for the online learner).

    Stochastic actions are drawn from a generator of the policy's own (seeded by
    :meth:`seed`), so acting never moves torch's global random stream.
    """

    def __init__(
        self,
        raw: Callable[[Tensor], Tensor],
        head: PolicyHead,
        to_action: Callable[[Tensor], Tensor],
        obs_dim: int,
        normalize: Callable[[np.ndarray], np.ndarray] | None = None,
        config: Any = None,
        kind: str = "",
    ) -> None:
        self._raw = raw
        self.head = head
        self._to_action = to_action
        self.obs_dim = int(obs_dim)
        self.act_dim = head.act_dim
        self._normalize = normalize
        self.config = config
        """The run's configuration (``TrainConfig`` or ``BatchConfig``), or None."""
        self.kind = kind
        """The learner kind that trained it (``"online"``, ``"batch"``)."""
        self._rng_state: Tensor = torch.Generator().manual_seed(0).get_state()

    @property
    def env(self) -> str | None:
        """The task the policy was trained on (alias or Gymnasium id), when known."""
        return getattr(self.config, "env", None)

    def seed(self, seed: int) -> None:
        """Restart the stream that :meth:`act` with ``deterministic=False`` samples from."""
        gen = torch.Generator().manual_seed(int(seed))
        self._rng_state = gen.get_state()

    def _batch(self, obs: Any) -> tuple[Tensor, bool]:
        arr = np.asarray(obs, dtype=np.float32)
        single = arr.ndim == 1
        arr = arr.reshape(1, -1) if single else arr
        if arr.ndim != 2 or arr.shape[1] != self.obs_dim:
            raise ValueError(
                f"obs must have shape [{self.obs_dim}] or [N, {self.obs_dim}]; "
                f"got {tuple(np.shape(obs))}"
            )
        if self._normalize is not None:
            arr = np.asarray(self._normalize(arr), dtype=np.float32)
        return torch.from_numpy(np.ascontiguousarray(arr)), single

    @torch.no_grad()
    def distribution(self, obs: Any) -> Distribution:
        """pi(u|s) over the pre-bound variable u, batch shape ``[N]`` (or ``[1]``)."""
        x, _ = self._batch(obs)
        return self.head.distribution(self._raw(x))

    @torch.no_grad()
    def act(self, obs: Any, deterministic: bool = True) -> np.ndarray:
        """The action for one observation ``[obs_dim]`` (-> ``[act_dim]``) or a batch
        ``[N, obs_dim]`` (-> ``[N, act_dim]``), inside the action bounds.

        ``deterministic=True`` acts with the policy's location (how the paper tests a
        policy); ``False`` samples u ~ pi(.|s) from the policy's own stream.
        """
        x, single = self._batch(obs)
        raw = self._raw(x)
        if deterministic:
            u = self.head.location(raw)
        else:
            with torch.random.fork_rng(devices=[]):
                torch.set_rng_state(self._rng_state)
                u = self.head.sample(raw)
                self._rng_state = torch.get_rng_state()
        action = self._to_action(u).numpy().astype(np.float32)
        return action[0] if single else action

    def __call__(self, obs: Any) -> np.ndarray:
        """``act(obs)``: the deterministic test-time action (what evaluation uses)."""
        return self.act(obs, deterministic=True)

    def __repr__(self) -> str:
        return (
            f"Policy(kind={self.kind!r}, env={self.env!r}, obs_dim={self.obs_dim}, "
            f"act_dim={self.act_dim}, head={type(self.head).__name__})"
        )
