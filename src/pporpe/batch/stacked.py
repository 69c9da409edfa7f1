"""The networks and the Adam states of K batch runs, stacked: the learning state of a
batch population (:mod:`pporpe.batch.population`).

:class:`StackedActorCritic` holds K :class:`~pporpe.batch.model.ActorCritic` parameter
vectors as the rows of ``theta [K, n]`` (row k in the layout of a run's own ``theta``)
and evaluates them with one batched call per layer (:class:`pporpe.nn.stacked.StackedMLP`);
the gradients of all members land in the rows of one ``grad [K, n]`` buffer.
:class:`StackedAdam` steps the rows with PyTorch's fused Adam kernel, each with its own
step count, learning rate and epsilon, so that row k follows exactly what
``torch.optim.Adam([theta], fused=True)`` of a run alone does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..nn.mlp import flat_views
from ..nn.policies import NormalHead
from ..nn.stacked import StackedMLP, padded_rows, stacked_views
from .model import ActorCritic

__all__ = ["FixedScale", "StackedActorCritic", "StackedAdam"]


class StackedActorCritic:
    """K actor-critics shaped like ``template``, parameters in the rows of :attr:`theta`.

    The methods are :class:`~pporpe.batch.model.ActorCritic`'s with a leading member
    dimension on every input and output: observations ``[K, B, obs_dim]``, actions
    ``[K, B, act_dim]``, values and log-densities ``[K, B]``.
    """

    def __init__(self, template: ActorCritic, members: int) -> None:
        flat = template.flat
        self.template = template
        """A run's model of the same shape: its head, action bounds and layout."""
        self.head = template.head
        self.act_dim = template.act_dim
        self.global_scale = template.global_scale
        self.members = members
        self.theta = padded_rows(members, template.theta.numel())
        """Member k's parameters in row k, laid out as a run's ``ActorCritic.theta``, each row
        on a 64-byte boundary as a run's is (:func:`~pporpe.nn.stacked.padded_rows`)."""
        self.grad = padded_rows(members, template.theta.numel())
        """Row k: member k's gradient (the ``.grad`` of every parameter view is a view of it)."""
        leaves = stacked_views(self.theta, flat.shapes)
        for leaf, grad in zip(leaves, stacked_views(self.grad, flat.shapes), strict=True):
            leaf.requires_grad_(True)
            leaf.grad = grad
        k = flat.n_policy_tensors
        self._pol, self._extra, self._val = leaves[:k], leaves[k], leaves[k + 1 :]
        self._policy_fn = StackedMLP(flat.policy_fn, self._pol)
        self._value_fn = StackedMLP(flat.value_fn, self._val)
        self._n_policy = flat.n_policy
        self._value_shapes = flat.value_shapes

    # -- members --------------------------------------------------------------------------
    def load_member(self, k: int, theta: Tensor) -> None:
        """Row ``k`` := a run's ``theta``."""
        with torch.no_grad():
            self.theta[k].copy_(theta)

    def clear_member(self, k: int) -> None:
        """Row ``k`` := 0 (a free slot)."""
        with torch.no_grad():
            self.theta[k].zero_()

    def member_value(self, k: int, obs: Tensor) -> Tensor:
        """V(s) of member k alone for ``obs [B, obs_dim]``: the run's own operations."""
        views = flat_views(self.theta[k, self._n_policy :].detach(), self._value_shapes)
        return self.template.flat.value_fn(views, obs)[..., 0]

    # -- forward ----------------------------------------------------------------------------
    def raw(self, obs: Tensor) -> Tensor:
        """The head's raw input ``[K, B, raw_dim]``."""
        out = self._policy_fn(obs)
        if not self.global_scale:
            return out
        return torch.cat([out, self._extra.unsqueeze(1).expand(*out.shape[:-1], -1)], dim=-1)

    def log_prob(self, obs: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``(log pi(u|s), raw)``; with a state-independent scale ``raw`` is one row per
        member, ``[K, 1, raw_dim]`` (as :meth:`ActorCritic.log_prob`)."""
        if not self.global_scale:
            raw = self._policy_fn(obs)
            return self.head.log_prob(raw, u), raw
        loc = self._policy_fn(obs)
        row = torch.cat([torch.zeros(self.members, self.act_dim), self._extra], dim=-1)
        row = row.unsqueeze(1)
        return self.head.log_prob(row, u - loc), row

    def value(self, obs: Tensor) -> Tensor:
        """V(s), ``[K, B]``."""
        return self._value_fn(obs)[..., 0]

    def entropy(self, raw: Tensor) -> Tensor:
        """Entropy of pi(u|s) per row of ``raw``."""
        return self.template.entropy(raw)

    def sample(self, raw: Tensor, noise: Tensor) -> Tensor:
        """``u = loc + scale * noise`` (``noise``: every member's standard normal draws)."""
        loc, scale = self.head.split(raw)
        return loc + scale * noise

    def fixed_scale(self, rows: int) -> FixedScale | None:
        """With a state-independent scale, the scale ``[K, rows, act_dim]`` and its log as
        :meth:`act` computes them at every step (from the same layout: the expanded row of
        :meth:`raw`); they stay the same while the parameters do (a rollout). None with a
        scale that the network outputs."""
        if not self.global_scale:
            return None
        raw = self.raw(torch.zeros(self.members, rows, self.template.obs_dim))
        _, scale = self.head.split(raw)
        return FixedScale(scale, torch.log(scale))

    def act(self, obs: Tensor, noise: Tensor, fixed: FixedScale | None) -> tuple[Tensor, Tensor]:
        """``(u, log pi(u|s))`` for ``u = loc + scale * noise``, as a run alone's rollout
        step computes them (its ``sample`` and ``head.log_prob``); ``fixed``: the scale of
        :meth:`fixed_scale` (None: computed from the network's output)."""
        head = self.head
        assert isinstance(head, NormalHead)
        if fixed is None:
            loc, scale = head.split(self.raw(obs))
            log_scale = torch.log(scale)
        else:
            loc, scale, log_scale = self._policy_fn(obs), fixed.scale, fixed.log_scale
        u = loc + scale * noise
        return u, head.log_prob_at(loc, scale, log_scale, u)

    def to_action(self, u: Tensor) -> Tensor:
        """Map u into the action box (the members share the bounds and the map)."""
        return self.template.to_action(u)

    def finite(self) -> Tensor:
        """``[K]``: whether every parameter of each member is finite."""
        return torch.isfinite(self.theta).all(dim=1)


@dataclass(frozen=True)
class FixedScale:
    """A state-independent policy scale over a rollout (:meth:`StackedActorCritic.fixed_scale`)."""

    scale: Tensor
    """``[K, rows, act_dim]``."""
    log_scale: Tensor
    """Its log."""


class StackedAdam:
    """Adam over the rows of ``theta [K, n]`` with gradients ``grad [K, n]``, by PyTorch's
    fused CPU kernel, row k with its own step count, learning rate and epsilon (betas
    (0.9, 0.999), no weight decay, as the batch learner's ``torch.optim.Adam``)."""

    betas = (0.9, 0.999)

    def __init__(self, theta: Tensor, grad: Tensor) -> None:
        self.theta, self.grad = theta, grad
        self.exp_avg = torch.zeros_like(theta)
        self.exp_avg_sq = torch.zeros_like(theta)
        self.steps = [torch.tensor(0.0) for _ in range(theta.shape[0])]
        """Member k's step count (a float32 0-dim tensor, as ``torch.optim.Adam``'s)."""
        self._rows: dict[tuple[int, ...], tuple[list[Tensor], ...]] = {}

    def _views(self, rows: tuple[int, ...]) -> tuple[list[Tensor], ...]:
        """Row views of the parameters, gradients and moments of ``rows`` (made once)."""
        if rows not in self._rows:
            tensors = (self.theta, self.grad, self.exp_avg, self.exp_avg_sq)
            self._rows[rows] = tuple([t.detach()[k] for k in rows] for t in tensors)
        return self._rows[rows]

    def step(self, members: Sequence[int], lr: Sequence[float], eps: Sequence[float]) -> None:
        """One Adam step of rows ``members`` (``lr[i]``, ``eps[i]``: member ``members[i]``'s);
        members with equal settings share one kernel call."""
        groups: dict[tuple[float, float], list[int]] = {}
        for k, lr_k, eps_k in zip(members, lr, eps, strict=True):
            groups.setdefault((lr_k, eps_k), []).append(k)
        with torch.no_grad():
            for (lr_g, eps_g), rows in groups.items():
                steps = [self.steps[k] for k in rows]
                torch._foreach_add_(steps, 1)
                theta, grad, exp_avg, exp_avg_sq = self._views(tuple(rows))
                torch._fused_adam_(
                    theta, grad, exp_avg, exp_avg_sq, [], steps,
                    lr=lr_g, beta1=self.betas[0], beta2=self.betas[1], weight_decay=0.0,
                    eps=eps_g, amsgrad=False, maximize=False,
                )  # fmt: skip

    def load_member(self, k: int, optimizer: torch.optim.Optimizer, param: Tensor) -> None:
        """Row ``k`` := the state of a run's ``torch.optim.Adam`` for ``param`` (zeros and
        step 0 when it has not stepped)."""
        state: dict[str, Any] = optimizer.state.get(param, {})
        if state:
            self.exp_avg[k].copy_(state["exp_avg"])
            self.exp_avg_sq[k].copy_(state["exp_avg_sq"])
            self.steps[k] = state["step"].detach().clone()
        else:
            self.clear_member(k)

    def store_member(self, k: int, optimizer: torch.optim.Optimizer, param: Tensor) -> None:
        """Row ``k`` into a run's ``torch.optim.Adam`` state for ``param`` (copies)."""
        if float(self.steps[k]) == 0.0:
            optimizer.state.pop(param, None)
            return
        optimizer.state[param] = {
            "step": self.steps[k].clone(),
            "exp_avg": self.exp_avg[k].clone(),
            "exp_avg_sq": self.exp_avg_sq[k].clone(),
        }

    def clear_member(self, k: int) -> None:
        """Row ``k`` := a fresh Adam state."""
        self.exp_avg[k].zero_()
        self.exp_avg_sq[k].zero_()
        self.steps[k] = torch.tensor(0.0)
