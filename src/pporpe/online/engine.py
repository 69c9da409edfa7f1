"""The interface between a population and its engine: the parts an engine computes on
(:class:`PopulationParts`) and the calls it answers (:class:`Engine`).

The population (:class:`~pporpe.online.population.PopulationLearner`) owns its members:
their configs and seeds, their checkpoints, the checks of its inputs. An engine computes
their steps on the population's buffers: the torch engine
(:mod:`pporpe.online.torch_engine`, the reference) or the fused engine
(:mod:`pporpe.online.fused_engine`, the default). Both read and write the same buffers in
place, so a population's state means the same under either.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from ..nn.batched import NetLayout
from ..nn.mlp import mlp
from ..nn.policies import ActionMap, PolicyHead, make_head
from .config import OnlineConfig
from .noise import NoiseBank
from .state import MemberConstants, PopulationState
from .stats import StepStats

__all__ = ["Engine", "PopulationParts"]


@dataclass(frozen=True, eq=False)
class PopulationParts:
    """The shapes, head, action map, buffers and noise streams of K members: what the
    population and its engine share (the buffers are written in place, never rebound)."""

    K: int
    """The number of members."""
    obs_dim: int
    """Observation size."""
    act_dim: int
    """Action size."""
    policy: str
    """The policy head's kind (``OnlineConfig.policy``), the same for every member."""
    activation: str
    """The hidden layers' activation, the same for every member."""
    lay: NetLayout
    """The padded layout of every member's networks."""
    head: PolicyHead
    """The policy head (the members' raw outputs to distributions)."""
    action_map: ActionMap
    """The map of pre-map actions u into the action bounds."""
    state: PopulationState
    """What changes while the members learn."""
    consts: MemberConstants
    """What each member's config fixes."""
    noise: NoiseBank
    """The members' random streams."""

    @classmethod
    def build(
        cls,
        obs_dim: int,
        action_low: Any,
        action_high: Any,
        shape: OnlineConfig,
        k: int,
        noise_block: int = 1024,
    ) -> PopulationParts:
        """Zeroed parts of ``k`` members with the network and head of ``shape`` (members
        are set up after, one by one: :meth:`init_member`)."""
        action_map = ActionMap(
            torch.as_tensor(np.asarray(action_low), dtype=torch.float32),
            torch.as_tensor(np.asarray(action_high), dtype=torch.float32),
        )
        act_dim = action_map.act_dim
        head = make_head(shape.policy, act_dim, min_scale=shape.min_scale)
        parts = head.parts() if shape.head_tensors == "per_output" else None
        lay = NetLayout(
            obs_dim, head.raw_dim, shape.layers, shape.units, shape.layer_norm, head_parts=parts
        )
        return cls(
            K=k,
            obs_dim=obs_dim,
            act_dim=act_dim,
            policy=shape.policy,
            activation=shape.activation,
            lay=lay,
            head=head,
            action_map=action_map,
            state=PopulationState.zeros(k, lay, act_dim),
            consts=MemberConstants.zeros(k, lay),
            noise=NoiseBank(k, act_dim, noise_block),
        )

    def flat(self, n_kinds: int) -> Tensor:
        """The first ``n_kinds`` networks of every member (policy, value, target) as rows
        ``[n_kinds K, n_pad]`` (a view of the parameters)."""
        return self.state.params[:n_kinds].view(n_kinds * self.K, self.lay.n_pad)

    def init_member(self, k: int, config: OnlineConfig, seed: int) -> None:
        """Member k as a fresh run of ``config`` and ``seed``: parameters as OnlineLearner
        builds them after ``torch.manual_seed(seed)`` (the global RNG is left untouched),
        its target equal to its value network, zero optimiser state and traces, fresh
        t-soft scalars, the noise stream restarted from ``seed``, no pending transition."""
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            kw = {
                "layers": config.layers,
                "units": config.units,
                "layer_norm": config.layer_norm,
                "activation": config.activation,
            }
            pol = mlp(self.obs_dim, self.head.raw_dim, **kw)  # type: ignore[arg-type]
            val = mlp(self.obs_dim, 1, **kw)  # type: ignore[arg-type]
        R, U = self.lay.n_rows, self.lay.units
        with torch.no_grad():
            params = self.state.params
            params[0, k] = self.lay.pack(list(pol.parameters()), 0).view(R, U)
            params[1, k] = self.lay.pack(list(val.parameters()), 1).view(R, U)
            params[2, k] = params[1, k]
        self.state.reset_member(k, config)
        self.noise.reset(k, seed)


class Engine(Protocol):
    """How a population's steps are computed: what
    :class:`~pporpe.online.population.PopulationLearner` calls, on its
    :class:`PopulationParts`, once it has checked the inputs."""

    def set_member(self, k: int, config: OnlineConfig) -> None:
        """Member k runs ``config`` from now on (``parts.consts`` holds its constants)."""

    def begin(self, idx: np.ndarray, obs: np.ndarray, forced_u: Tensor | None) -> np.ndarray:
        """First actions ``[len(idx), act_dim]`` of members ``idx`` (distinct int64) at
        ``obs``; resets their traces and sets their pending transitions. ``forced_u``:
        pre-map actions used instead of samples (no noise consumed)."""

    def step(
        self,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        active: np.ndarray,
        forced_u: Tensor | None,
    ) -> tuple[StepStats, np.ndarray]:
        """Learn transition t of the ``active`` members (bool ``[K]``); their stats and
        a_{t+1} ``[K, act_dim]``, sampled with theta_t (see the population's step)."""

    def outputs(self, kind: int, obs: np.ndarray) -> Tensor:
        """Outputs of network ``kind`` (0: the policy's raw ``[K, raw_dim]``, 1: the value
        ``[K, 1]``) of every member at its row of ``obs [K, obs_dim]``."""
