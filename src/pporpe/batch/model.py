"""The batch learner's actor-critic: the shared flat-parameter networks plus an optional
state-independent scale, and the map of actions into the bounds (clip or sigmoid)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..nn.actor_critic import FlatActorCritic
from ..nn.mlp import mlp
from ..nn.policies import ActionMap, NormalHead, PolicyHead, make_head
from .config import BatchConfig

__all__ = ["ActorCritic"]

_HALF_LOG_2PI_E = 0.5 * (1.0 + math.log(2.0 * math.pi))


def _inv_softplus(y: float) -> float:
    """x with softplus(x) = y (y > 0)."""
    return y + math.log(-math.expm1(-y))


class ActorCritic:
    """Policy and value networks whose parameters are views into one flat vector.

    The policy network (``mlp``) outputs the location of u (and, with
    ``scale="state"``, the head's scale and degrees-of-freedom inputs); with
    ``scale="global"`` those are free parameters, as Stable-Baselines3's ``log_std``. The
    value network is separate. All parameters live in :attr:`theta` (policy block, global
    head parameters, value block) and their gradients in :attr:`grad`, so gradient
    clipping and Adam are one whole-vector operation each.
    """

    def __init__(self, obs_dim: int, action_low: Any, action_high: Any, cfg: BatchConfig) -> None:
        self.cfg = cfg
        self.action_map = ActionMap(
            torch.as_tensor(np.asarray(action_low, dtype=np.float32)),
            torch.as_tensor(np.asarray(action_high, dtype=np.float32)),
        )
        self.obs_dim = obs_dim
        self.act_dim = act_dim = self.action_map.act_dim
        self.low = torch.as_tensor(np.asarray(action_low, dtype=np.float32)).reshape(-1)
        self.high = torch.as_tensor(np.asarray(action_high, dtype=np.float32)).reshape(-1)
        self.head: PolicyHead = make_head(cfg.policy, act_dim)
        self._normal = isinstance(self.head, NormalHead)
        ortho = cfg.init == "orthogonal"
        net_kw: dict[str, Any] = dict(
            layers=cfg.layers,
            units=cfg.units,
            layer_norm=cfg.layer_norm,
            activation=cfg.activation,
            init=cfg.init,
        )
        self.global_scale = cfg.scale == "global"
        pol_out = act_dim if self.global_scale else self.head.raw_dim
        policy_net = mlp(obs_dim, pol_out, output_gain=0.01 if ortho else None, **net_kw)
        value_net = mlp(obs_dim, 1, output_gain=1.0 if ortho else None, **net_kw)
        scale_raw0 = _inv_softplus(math.exp(cfg.log_std_init) - self.head.min_scale)
        n_extra = self.head.raw_dim - act_dim  # scale (act_dim) and, for student-t, df (1)
        extra = torch.zeros(n_extra)
        extra[:act_dim] = scale_raw0
        if not self.global_scale:
            with torch.no_grad():  # start the scale outputs at exp(log_std_init)
                last = policy_net[-1]
                assert isinstance(last, torch.nn.Linear)
                last.bias[act_dim : 2 * act_dim] = scale_raw0
        if not self.global_scale:
            extra = torch.zeros(0)
        self.flat = FlatActorCritic(policy_net, value_net, extra)
        self._policy_fn, self._value_fn = self.flat.policy_fn, self.flat.value_fn
        self.theta, self.grad = self.flat.theta, self.flat.grad
        self._pol, self._val = self.flat.policy_params, self.flat.value_params
        assert self.flat.extra is not None
        self._extra = self.flat.extra
        self.theta.grad = self.grad  # what the optimiser reads

    # -- forward --------------------------------------------------------------------------
    def raw(self, obs: Tensor) -> Tensor:
        """The head's raw input ``[..., raw_dim]`` for a batch of (normalised) observations."""
        out = self._policy_fn(self._pol, obs)
        if not self.global_scale:
            return out
        return torch.cat([out, self._extra.expand(*out.shape[:-1], -1)], dim=-1)

    def log_prob(self, obs: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``(log pi(u|s), raw)`` for a batch: what the policy loss needs.

        With ``scale="global"`` the returned ``raw`` is the single row
        ``[0, scale_raw(, df_raw)]`` and the density is evaluated as
        ``head.log_prob(raw_row, u - loc)``: both heads are location families, so this
        equals ``head.log_prob(self.raw(obs), u)`` without building a ``[batch, raw_dim]``
        tensor (fewer operations per minibatch).
        """
        if not self.global_scale:
            raw = self._policy_fn(self._pol, obs)
            return self.head.log_prob(raw, u), raw
        loc = self._policy_fn(self._pol, obs)
        row = torch.cat([torch.zeros(self.act_dim), self._extra])
        return self.head.log_prob(row, u - loc), row

    def value(self, obs: Tensor) -> Tensor:
        """V(s), shape ``[...]``."""
        return self._value_fn(self._val, obs)[..., 0]

    def entropy(self, raw: Tensor) -> Tensor:
        """Entropy of pi(u|s) per row (closed form for the Normal head)."""
        if self._normal:
            _, scale = self.head.split(raw)
            return torch.log(scale).sum(-1) + self.act_dim * _HALF_LOG_2PI_E
        return self.head.distribution(raw).entropy()

    def sample(self, raw: Tensor) -> Tensor:
        """A sample of u ~ pi(.|s) (global torch RNG)."""
        if self._normal:
            loc, scale = self.head.split(raw)
            return loc + scale * torch.randn_like(loc)
        return self.head.distribution(raw).sample()

    def to_action(self, u: Tensor) -> Tensor:
        """Map u into the action box: clip (default) or the sigmoid ActionMap."""
        if self.cfg.action_bound == "map":
            return self.action_map.to_action(u)
        return torch.maximum(torch.minimum(u, self.high), self.low)

    def parameters_finite(self) -> bool:
        """Whether every parameter is finite."""
        return bool(torch.isfinite(self.theta).all())
