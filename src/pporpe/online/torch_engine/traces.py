r"""Adaptive, multiple time-scale eligibility traces (Kobayashi 2020, arXiv:2008.10040).

T. Kobayashi, "Adaptive and multiple time-scale eligibility traces for online deep
reinforcement learning" (2020), cited by the PPO-RPE paper (arXiv:2010.03290, Sec. IV-A
and Table I) in place of experience replay. Online TD learning with traces on network
parameters; how the online learner feeds them is in ``docs/online-learner.md``. Per
step, with ``g`` the gradient of the per-step loss divided by the TD error and
``d >= 0`` the divergence between the current networks and those of the previous
step (the learner passes KL estimate + squared value change)::

    D      <- D + d
    decay   = exp(-kappa * D)
    D      <- decay * D
    e      <- gamma * lambda1 * decay * e + g                # accumulating, fast scale
    r      <- gamma * lambda2 * decay * r                    # replacing, slow scale ...
    r      <- e   wherever (e - r) * sign(e) >= 0            # ... takes e where e is larger

The learner hands ``delta * r`` to the optimiser. Traces are reset at episode ends.
With ``kappa = 0`` (or zero divergence) ``decay = 1`` and ``e`` is the ordinary
accumulating trace with factor ``gamma * lambda1``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from ...config import is_real

__all__ = ["AdaptiveTraces"]


class AdaptiveTraces:
    r"""Two eligibility traces over one flat parameter vector, cut by a divergence.

    Args:
        numel: length of the flat gradient vectors, ``> 0``.
        gamma: discount factor, in ``[0, 1]``.
        lambdas: ``(lambda1, lambda2)``, each in ``[0, 1]``: trace factors of the
            accumulating trace ``e`` (fast time scale) and the replacing trace ``r``
            (slow time scale). The paper uses ``(0.5, 0.95)`` (Table I).
        kappa: sensitivity to the divergence, ``>= 0`` (the paper: 10, Table I).
        dtype, device: of the trace buffers.

    Attributes:
        e, r: the traces (preallocated, updated in place).
        D: accumulated divergence (0-dim).
        last_decay: ``exp(-kappa D)`` of the latest step (0-dim, for logging).

    ``kappa = 0`` never accumulates ``D`` (it stays 0, ``decay = 1``).
    """

    def __init__(
        self,
        numel: int,
        gamma: float = 0.99,
        lambdas: Sequence[float] = (0.5, 0.95),
        kappa: float = 10.0,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> None:
        if isinstance(numel, bool) or not isinstance(numel, int) or numel <= 0:
            raise ValueError(f"numel must be a positive int, got {numel!r}")
        if not is_real(gamma) or not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
        if isinstance(lambdas, str | Tensor) or not isinstance(lambdas, Sequence):
            raise ValueError(f"lambdas must be a pair (lambda1, lambda2), got {lambdas!r}")
        if len(lambdas) != 2:
            raise ValueError(f"lambdas must be a pair (lambda1, lambda2), got {lambdas!r}")
        for i, lam in enumerate(lambdas):
            if not is_real(lam) or not 0.0 <= lam <= 1.0:
                raise ValueError(f"lambdas[{i}] (lambda{i + 1}) must be in [0, 1], got {lam!r}")
        if not is_real(kappa) or not 0.0 <= kappa < math.inf:
            raise ValueError(f"kappa must be in [0, inf), got {kappa!r}")
        self.numel = numel
        self.gamma = float(gamma)
        self.lambdas = (float(lambdas[0]), float(lambdas[1]))
        self.kappa = float(kappa)
        opts: dict[str, Any] = {"dtype": dtype, "device": device}
        self.e = torch.zeros(numel, **opts)
        self.r = torch.zeros(numel, **opts)
        self.D = torch.zeros((), **opts)
        self.last_decay = torch.ones((), **opts)
        # constants as 0-dim tensors: in-place ops with Python floats wrap them every call
        self._neg_kappa = torch.tensor(-self.kappa, **opts)
        self._gl1 = torch.tensor(self.gamma * self.lambdas[0], **opts)
        self._gl2 = torch.tensor(self.gamma * self.lambdas[1], **opts)
        self._c1 = torch.zeros((), **opts)
        self._c2 = torch.zeros((), **opts)
        self._tmp = torch.zeros(numel, **opts)
        self._sign = torch.zeros(numel, **opts)

    @torch.no_grad()
    def step_(self, grad: Tensor, divergence: Tensor | float) -> Tensor:
        r"""Advance both traces by one step and return the replacing trace ``r``.

        Args:
            grad: flat gradient ``g`` (``numel`` elements) of the per-step loss
                divided by the TD error.
            divergence: ``d >= 0``, a 0-dim tensor (or float): KL estimate plus squared
                value change since the last step. Not checked (no ``.item()``).

        Returns:
            ``r``, the trace to multiply by the TD error. It is the internal buffer
            itself: do not modify it, and copy it if it must survive the next
            ``step_``/``reset_``.
        """
        e, r = self.e, self.r
        if self.kappa > 0.0:
            D, decay = self.D, self.last_decay
            D.add_(divergence)
            torch.mul(D, self._neg_kappa, out=decay).exp_()
            D.mul_(decay).nan_to_num_(nan=0.0)  # D = inf, decay = 0 -> 0, not NaN
            c1 = torch.mul(decay, self._gl1, out=self._c1)
            c2 = torch.mul(decay, self._gl2, out=self._c2)
        else:
            c1, c2 = self._gl1, self._gl2
        torch.addcmul(grad, e, c1, out=e)  # e <- gamma lambda1 decay e + g
        # r <- gamma lambda2 decay r, then r <- e where (e - r) sign(e) >= 0. Exactly the same
        # as r <- s max(s e, s r) with s = sign(e): max(e, r) where e > 0, min(e, r) where
        # e < 0, 0 where e == 0. Comparisons into bool masks and torch.where are several
        # times slower on CPU than these five arithmetic passes.
        s = torch.sign(e, out=self._sign)
        r.mul_(c2).mul_(s)
        torch.maximum(r, torch.abs(e, out=self._tmp), out=r)
        r.mul_(s)
        return r

    def reset_(self) -> None:
        """Zero both traces and the accumulated divergence (call at episode ends)."""
        self.e.zero_()
        self.r.zero_()
        self.D.zero_()
        self.last_decay.fill_(1.0)

    def state_dict(self) -> dict[str, Any]:
        """Return copies of ``e``, ``r``, ``D`` and ``last_decay``."""
        return {
            "e": self.e.detach().clone(),
            "r": self.r.detach().clone(),
            "D": self.D.detach().clone(),
            "last_decay": self.last_decay.detach().clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Copy a :meth:`state_dict` into the existing buffers (their identity is kept)."""
        for key, buf in (
            ("e", self.e),
            ("r", self.r),
            ("D", self.D),
            ("last_decay", self.last_decay),
        ):
            value = state[key]
            if not isinstance(value, Tensor) or value.shape != buf.shape:
                shape = getattr(value, "shape", None)
                raise ValueError(
                    f"state[{key!r}] must be a tensor of shape {tuple(buf.shape)}, got {shape}"
                )
        for key, buf in (
            ("e", self.e),
            ("r", self.r),
            ("D", self.D),
            ("last_decay", self.last_decay),
        ):
            buf.copy_(state[key])
