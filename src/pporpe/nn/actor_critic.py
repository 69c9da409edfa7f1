"""The flat-parameter actor-critic that both learners train.

A policy network and a value network (``nn.Sequential`` MLPs, :func:`pporpe.nn.mlp.mlp`)
are evaluated functionally from *leaf views* of one flat parameter vector
:attr:`FlatActorCritic.theta`, laid out as ``[policy | extra | value]``, and the
``.grad`` of every leaf is a view of one flat gradient buffer :attr:`FlatActorCritic.grad`.
So ``backward`` accumulates straight into that buffer, and the optimiser, gradient
clipping, eligibility traces and target updates are a handful of whole-vector operations.

``extra`` holds free parameters of the policy that are not network outputs (the batch
learner's state-independent scale, as Stable-Baselines3's ``log_std``).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .mlp import FlatMLP, flat_views

__all__ = ["FlatActorCritic"]


class FlatActorCritic:
    """Policy and value networks whose parameters are views into one flat vector."""

    def __init__(
        self, policy_net: nn.Sequential, value_net: nn.Sequential, extra: Tensor | None = None
    ) -> None:
        self.policy_fn = FlatMLP(policy_net)
        """Evaluates the policy network: ``policy_fn(policy_views, obs)``."""
        self.value_fn = FlatMLP(value_net)
        """Evaluates the value network: ``value_fn(value_views, obs)``."""
        pol = [p.detach() for p in policy_net.parameters()]
        val = [p.detach() for p in value_net.parameters()]
        blocks = [*pol, *([] if extra is None else [extra.detach()]), *val]
        self._shapes = [t.shape for t in blocks]
        self.value_shapes = [t.shape for t in val]
        """Shapes of the value network's parameter tensors (in ``parameters()`` order)."""
        self.segment_sizes = [t.numel() for t in blocks]
        """Element count of every parameter tensor, in the layout of :attr:`theta`."""
        self._n_pol_tensors = len(pol)
        self._has_extra = extra is not None
        self.theta = torch.cat([t.reshape(-1) for t in blocks]).contiguous()
        """Every trainable parameter: ``[policy | extra | value]``."""
        self.grad = self.theta.new_zeros(self.theta.shape)
        """Flat gradient buffer: the ``.grad`` of every leaf view is a view of it."""
        self.n_policy = self.theta.numel() - sum(t.numel() for t in val)
        """Elements of the policy block (with ``extra``); the value block starts here."""
        leaves = flat_views(self.theta, self._shapes)
        grads = flat_views(self.grad, self._shapes)
        for leaf, grad in zip(leaves, grads, strict=True):
            leaf.requires_grad_(True)
            leaf.grad = grad
        k = self._n_pol_tensors
        self.policy_params: list[Tensor] = leaves[:k]
        """Leaf views of the policy network's parameters."""
        self.extra: Tensor | None = leaves[k] if self._has_extra else None
        """Leaf view of the free policy parameters, or None."""
        self.value_params: list[Tensor] = leaves[k + int(self._has_extra) :]
        """Leaf views of the value network's parameters."""

    @property
    def shapes(self) -> list[torch.Size]:
        """Shapes of every parameter tensor, in the layout of :attr:`theta`."""
        return list(self._shapes)

    @property
    def n_policy_tensors(self) -> int:
        """Parameter tensors of the policy network (``extra`` follows them, if any)."""
        return self._n_pol_tensors

    @property
    def value_block(self) -> Tensor:
        """The value network's parameters as one flat view of :attr:`theta`."""
        return self.theta[self.n_policy :]

    def value_views(self, flat: Tensor) -> list[Tensor]:
        """Views of a flat vector shaped like the value block (e.g. a target network)."""
        return flat_views(flat, self.value_shapes)

    def parameters_finite(self) -> bool:
        """Whether every parameter is finite."""
        return bool(self.theta.isfinite().all())
