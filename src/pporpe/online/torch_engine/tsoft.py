r"""t-soft update of a target network (Kobayashi & Ilboudo, Neural Networks 2021).

A soft (Polyak) update whose rate shrinks when the online parameters are an
outlier, judged by a student-t model of their squared distance to the target
(T. Kobayashi and W. E. L. Ilboudo, "t-soft update of target network for deep
reinforcement learning", Neural Networks, 2021). The PPO-RPE paper (arXiv:2010.03290,
Sec. IV-A) uses it for the target value network with ``(tau, nu) = (0.3, 1.0)``
(Table I). With online parameters ``theta``, target ``theta_bar``, rate ``tau``,
degrees of freedom ``nu`` and the scalars ``W`` (initially ``(1 - tau) / tau``) and
``sigma2`` (initially ``sigma2_init``), one update is::

    D2        = mean((theta - theta_bar)^2)          # over ALL elements (one scalar)
    w         = (nu + 1) / (nu + D2 / sigma2)
    tau_i     = w / (W + w)
    theta_bar <- (1 - tau_i) theta_bar + tau_i theta
    tau_s     = tau * w * nu / (nu + 1)
    sigma2    <- (1 - tau_s) sigma2 + tau_s D2
    W         <- (1 - tau) (W + w)

As ``nu -> inf``, ``w -> 1`` and ``tau_i -> tau``: the ordinary soft update.

Choice documented here: ``D2`` is the mean over *all* elements of the flat
parameter vector (one student-t weight for the whole network), not per tensor.
That matches the learner's single flat parameter vector and costs one dot product.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from ...config import is_real

__all__ = ["TSoftUpdate"]


class TSoftUpdate:
    r"""t-soft target update; ``update_(target, online)`` changes ``target`` in place.

    Args:
        tau: base rate, in ``(0, 1]`` (``1`` copies the online vector).
        nu: degrees of freedom, ``> 0``; ``math.inf`` is exactly the Polyak update
            ``target <- target + tau (online - target)`` (W and sigma2 then stay put).
        sigma2_init: initial scale of the squared distance, ``> 0``.
        sigma2_min: floor kept under ``sigma2`` (``>= 0``, at most ``sigma2_init``).
            Not in the paper: without it ``sigma2`` decays geometrically while the
            two vectors are identical and can underflow to 0, after which ``w = 0``
            freezes the target for good (and ``0/0`` gives NaN). A floor can only
            make ``w`` larger, i.e. the update closer to Polyak; ``0`` disables it.

    The scalars ``W`` and ``sigma2`` are 0-dim float64 tensors (attributes of the
    same name), moved to the target's device on first use. ``update_`` does a
    handful of whole-tensor ops, no ``.item()``, and reuses one scratch buffer.
    """

    def __init__(
        self,
        tau: float = 0.3,
        nu: float = 1.0,
        sigma2_init: float = 1e-2,
        *,
        sigma2_min: float = 1e-12,
    ) -> None:
        if not is_real(tau) or not 0.0 < tau <= 1.0:
            raise ValueError(f"tau must be in (0, 1], got {tau!r}")
        if not is_real(nu) or not nu > 0.0:
            raise ValueError(f"nu must be in (0, inf] (inf gives Polyak averaging), got {nu!r}")
        if not is_real(sigma2_init) or not 0.0 < sigma2_init < math.inf:
            raise ValueError(f"sigma2_init must be in (0, inf), got {sigma2_init!r}")
        if not is_real(sigma2_min) or not 0.0 <= sigma2_min <= sigma2_init:
            raise ValueError(
                f"sigma2_min must be in [0, sigma2_init={sigma2_init!r}], got {sigma2_min!r}"
            )
        self.tau = float(tau)
        self.nu = float(nu)
        self.sigma2_init = float(sigma2_init)
        self.sigma2_min = float(sigma2_min)
        self._polyak = math.isinf(self.nu)
        self.W = torch.tensor((1.0 - self.tau) / self.tau, dtype=torch.float64)
        self.sigma2 = torch.tensor(self.sigma2_init, dtype=torch.float64)
        self._d2 = torch.zeros((), dtype=torch.float64)
        self._diff: Tensor | None = None

    def _scratch(self, target: Tensor) -> Tensor:
        diff = self._diff
        if (
            diff is None
            or diff.shape != target.shape
            or diff.dtype != target.dtype
            or diff.device != target.device
        ):
            diff = torch.empty_like(target, memory_format=torch.contiguous_format)
            self._diff = diff
            if self.W.device != target.device:
                self.W = self.W.to(target.device)
                self.sigma2 = self.sigma2.to(target.device)
                self._d2 = self._d2.to(target.device)
        return diff

    @torch.no_grad()
    def update_(self, target: Tensor, online: Tensor) -> None:
        r"""Move ``target`` towards ``online`` in place by the t-soft rule (module docstring).

        Both are tensors of the same shape (normally the flat value-network
        vectors); ``online`` is not modified.
        """
        if self._polyak:
            target.lerp_(online, self.tau)  # (1 - tau) target + tau online
            return
        nu = self.nu
        diff = torch.sub(online, target, out=self._scratch(target))
        flat = diff.view(-1)
        d2 = torch.mul(torch.dot(flat, flat), 1.0 / flat.numel(), out=self._d2)  # D2 (float64)
        w = torch.add(d2, self.sigma2, alpha=nu)  # nu sigma2 + D2
        w = torch.div(self.sigma2, w).mul_(nu + 1.0)  # (nu + 1) / (nu + D2 / sigma2)
        w_sum = torch.add(self.W, w)
        target.addcmul_(diff, torch.div(w, w_sum))  # tau_i = w / (W + w)
        tau_s = w.mul_(self.tau * nu / (nu + 1.0))  # w is not needed any more
        self.sigma2.lerp_(d2, tau_s)  # (1 - tau_s) sigma2 + tau_s D2
        if self.sigma2_min > 0.0:
            self.sigma2.clamp_(min=self.sigma2_min)
        torch.mul(w_sum, 1.0 - self.tau, out=self.W)  # (1 - tau)(W + w)

    def state_dict(self) -> dict[str, Any]:
        """Return copies of the adaptive scalars ``W`` and ``sigma2`` (and the settings)."""
        return {
            "W": self.W.detach().clone(),
            "sigma2": self.sigma2.detach().clone(),
            "tau": self.tau,
            "nu": self.nu,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``W`` and ``sigma2`` from :meth:`state_dict` (settings must match)."""
        for key in ("W", "sigma2"):
            value = state[key]
            if not isinstance(value, Tensor) or value.numel() != 1:
                raise ValueError(f"state[{key!r}] must be a one-element tensor, got {value!r}")
        for key in ("tau", "nu"):
            if key in state and float(state[key]) != getattr(self, key):
                raise ValueError(
                    f"state was saved with {key}={state[key]!r}, this update has "
                    f"{key}={getattr(self, key)!r}"
                )
        self.W.copy_(state["W"].reshape(()))
        self.sigma2.copy_(state["sigma2"].reshape(()))
