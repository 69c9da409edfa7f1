r"""Policy heads (Student-t, Normal) and the map of their samples into action bounds.

A policy network outputs a raw vector (last dimension ``head.raw_dim``). A *head*
turns it into a ``torch.distributions`` distribution over the **pre-map**
variable ``u`` (shape ``[..., act_dim]``, unbounded), and :class:`ActionMap`
maps ``u`` into the environment's box ``[low, high]``::

    raw --head.distribution--> pi(u|s) --sample--> u --ActionMap.to_action--> a

* :class:`StudentTHead` (the paper's policy, Kobayashi 2019): ``raw = [loc
  (act_dim), scale_raw (act_dim), df_raw (1)]``; ``scale = softplus(scale_raw) +
  min_scale``; ``df = softplus(df_raw) + min_df`` (``min_df = 2``) with **one**
  degree of freedom per state, shared by (broadcast over) all action dimensions.
* :class:`NormalHead`: ``raw = [loc, scale_raw]``, diagonal Gaussian.

Both give ``Independent(..., 1)`` distributions, so ``log_prob`` sums over the
action dimensions and returns shape ``[...]``. Test-time (deterministic) actions
are ``action_map.to_action(head.location(raw))``.

The bounded map (the paper author's): ``a = low + (high - low) * sigmoid(u)``.
The density of ``a`` is ``pi_a(a) = pi_u(u) / |da/du|`` with
``log|da/du| = sum_i [logsigmoid(u_i) + logsigmoid(-u_i) + log(high_i - low_i)]``,
computed from ``u`` (never by inverting ``a``, which loses precision near the
bounds); :meth:`ActionMap.log_prob_action` returns it.

**Ratios.** The Jacobian depends on ``u`` only, not on the policy parameters, so
it cancels in density ratios: ``pi(a|s) / pi_b(a|s) = pi(u|s) / pi_b(u|s)``. The
learner therefore keeps the sampled ``u`` and uses ``dist.log_prob(u)`` (or the
faster, equal :meth:`StudentTHead.log_prob`) for ratios; the Jacobian matters only
where an absolute log-density of the action is wanted (e.g. an entropy bonus on
the bounded action).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.distributions import Distribution, Independent, Normal, StudentT

from ..config import POLICY_KINDS

__all__ = [
    "HEAD_KINDS",
    "ActionMap",
    "NormalHead",
    "PolicyHead",
    "StudentTHead",
    "make_head",
]

HEAD_KINDS: tuple[str, ...] = POLICY_KINDS
"""Names accepted by :func:`make_head` (:data:`pporpe.config.POLICY_KINDS`)."""

_HALF_LOG_PI = 0.5 * math.log(math.pi)
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


class PolicyHead(ABC):
    """Base class: turns a raw network output into a distribution over ``u``.

    Attributes:
        act_dim: number of action dimensions.
        raw_dim: size of the last dimension of the raw input.
        min_scale: floor added to ``softplus(scale_raw)``, so ``scale >= min_scale``.
    """

    act_dim: int
    raw_dim: int
    min_scale: float

    def __init__(self, act_dim: int, min_scale: float = 1e-3) -> None:
        """Validate and store the action dimension and the scale floor."""
        if isinstance(act_dim, bool) or not isinstance(act_dim, int) or act_dim < 1:
            raise ValueError(f"act_dim must be a positive int, got {act_dim!r}")
        if not (math.isfinite(min_scale) and min_scale > 0):
            raise ValueError(f"min_scale must be a finite number > 0, got {min_scale!r}")
        self.act_dim = act_dim
        self.min_scale = float(min_scale)

    def _check(self, raw: Tensor) -> None:
        """Raise ValueError unless ``raw.shape[-1] == raw_dim``."""
        if raw.dim() == 0 or raw.shape[-1] != self.raw_dim:
            raise ValueError(
                f"{type(self).__name__} expects raw outputs with last dimension "
                f"{self.raw_dim}, got shape {tuple(raw.shape)}"
            )

    def _scale(self, scale_raw: Tensor) -> Tensor:
        """Return ``softplus(scale_raw) + min_scale`` (always > 0)."""
        return F.softplus(scale_raw) + self.min_scale

    def parts(self) -> tuple[int, ...]:
        """Sizes of the parts of ``raw`` in order: location and scale (and the student-t's
        degrees of freedom), e.g. for one output layer per part."""
        extra = self.raw_dim - 2 * self.act_dim
        return (self.act_dim, self.act_dim, *((extra,) if extra else ()))

    def location(self, raw: Tensor) -> Tensor:
        """Return the location ``loc`` (shape ``[..., act_dim]``): the test-time ``u``."""
        self._check(raw)
        return raw[..., : self.act_dim]

    @abstractmethod
    def split(self, raw: Tensor) -> tuple[Tensor, ...]:
        """Return the distribution parameters computed from ``raw``."""

    @abstractmethod
    def distribution(self, raw: Tensor) -> Distribution:
        """Return the distribution over ``u`` (event shape ``[act_dim]``)."""

    def log_prob(self, raw: Tensor, u: Tensor) -> Tensor:
        """Return ``distribution(raw).log_prob(u)`` (shape ``[...]``)."""
        return self.distribution(raw).log_prob(u)

    @abstractmethod
    def kl(self, raw_p: Tensor, raw_q: Tensor) -> Tensor:
        """KL(p || q) between the distributions of two raw outputs (shape ``[...]``)."""

    def sample(self, raw: Tensor) -> Tensor:
        """Return ``distribution(raw).sample()`` without building the distribution objects.

        It draws from the global RNG in the same order as ``torch.distributions``, so the
        samples are identical to theirs for the same RNG state, at a fraction of the cost.
        """
        return self.distribution(raw).sample()


class StudentTHead(PolicyHead):
    """Diagonal Student-t policy head with one degree of freedom per state.

    ``raw = [loc (act_dim), scale_raw (act_dim), df_raw (1)]``, so
    ``raw_dim = 2 * act_dim + 1``. ``scale = softplus(scale_raw) + min_scale`` and
    ``df = softplus(df_raw) + min_df``, the same ``df`` for every action dimension.

    With ``min_df = 2`` the variance is finite for every finite ``df_raw``; note
    that in float32 ``softplus`` underflows to 0 below about ``-100``, where
    ``df`` equals ``min_df`` exactly (the density and its log stay finite).
    """

    min_df: float

    def __init__(self, act_dim: int, min_scale: float = 1e-3, min_df: float = 2.0) -> None:
        """Create a head for ``act_dim`` action dimensions."""
        super().__init__(act_dim, min_scale)
        if not (math.isfinite(min_df) and min_df > 0):
            raise ValueError(f"min_df must be a finite number > 0, got {min_df!r}")
        self.min_df = float(min_df)
        self.raw_dim = 2 * act_dim + 1

    def split(self, raw: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Return ``(loc, scale, df)``; ``df`` has shape ``[..., 1]`` (broadcasts)."""
        self._check(raw)
        d = self.act_dim
        loc = raw[..., :d]
        scale = self._scale(raw[..., d : 2 * d])
        df = F.softplus(raw[..., 2 * d :]) + self.min_df
        return loc, scale, df

    def distribution(self, raw: Tensor) -> Distribution:
        """Return ``Independent(StudentT(df, loc, scale), 1)`` over ``u``."""
        loc, scale, df = self.split(raw)
        base = StudentT(df, loc, scale, validate_args=False)
        return Independent(base, 1, validate_args=False)

    @torch.no_grad()
    def sample(self, raw: Tensor) -> Tensor:
        """``u ~ StudentT(df, loc, scale)`` drawn as ``torch.distributions.StudentT`` does:
        ``loc + scale * X / sqrt(Z / df)`` with ``X ~ N(0, 1)`` then ``Z ~ Chi2(df)``."""
        loc, scale, df = self.split(raw)
        df = df.expand_as(loc)
        x = torch.empty_like(loc).normal_()
        z = torch._standard_gamma(0.5 * df) / 0.5
        z.clamp_(min=torch.finfo(z.dtype).tiny)
        return loc + scale * (x * torch.rsqrt(z / df))

    def log_prob(self, raw: Tensor, u: Tensor) -> Tensor:
        """Return ``log pi(u|s)`` in closed form; equal to ``distribution(raw).log_prob(u)``.

        Uses that ``df`` is shared across dimensions: the normalising constant
        ``lgamma((df+1)/2) - lgamma(df/2) - log(df*pi)/2`` is computed once per
        state and multiplied by ``act_dim``. ``u`` broadcasts against ``raw``'s
        batch shape (e.g. ``[n_samples, *batch, act_dim]``).
        """
        loc, scale, df = self.split(raw)
        half_df = 0.5 * df
        half_df1 = half_df + 0.5
        # Per state: act_dim * [lgamma((df+1)/2) - lgamma(df/2) - log(df)/2 - log(pi)/2].
        const = torch.lgamma(half_df1) - torch.lgamma(half_df) - 0.5 * torch.log(df)
        per_dim = torch.log(scale) + half_df1 * torch.log1p(((u - loc) / scale).square() / df)
        return self.act_dim * (const.squeeze(-1) - _HALF_LOG_PI) - per_dim.sum(-1)

    def kl(self, raw_p: Tensor, raw_q: Tensor) -> Tensor:
        """Approximate KL(p || q) (the normal-gamma form; see :func:`_student_t_kl`)."""
        return _student_t_kl(raw_p, raw_q, self)


def _student_t_kl(raw_p: Tensor, raw_q: Tensor, head: StudentTHead) -> Tensor:
    r"""Approximate KL(p || q) of two diagonal student-t with one df per state each.

    Student-t as a normal-gamma scale mixture, the KL of the two normal-gamma joints
    (Roth et al., "On the multivariate t distribution", arXiv:1611.01437), as the
    author's test bed uses it: with :math:`v = (s_p/s_q)^2` and
    :math:`m = ((\mu_p - \mu_q)/s_q)^2` per dimension,

    .. math:: \tfrac12 \sum_d (v + m - 1 - \log v) + \tfrac12 [\nu_q (\log\nu_p - \log\nu_q)
              - 2(\log\Gamma(\nu_p/2) - \log\Gamma(\nu_q/2))
              + (\nu_p - \nu_q)(\psi(\nu_p/2) - 1)]

    It is 0 for p = q and tends to the Gaussian KL as both df grow.
    """
    loc_p, scale_p, df_p = head.split(raw_p)
    loc_q, scale_q, df_q = head.split(raw_q)
    var_ratio = (scale_p / scale_q).square()
    mean_term = ((loc_p - loc_q) / scale_q).square()
    gauss = 0.5 * (var_ratio + mean_term - 1.0 - torch.log(var_ratio)).sum(-1)
    dp, dq = df_p[..., 0], df_q[..., 0]
    ddf = 0.5 * (
        dq * (torch.log(dp) - torch.log(dq))
        - 2.0 * (torch.lgamma(0.5 * dp) - torch.lgamma(0.5 * dq))
        + (dp - dq) * (torch.digamma(0.5 * dp) - 1.0)
    )
    return gauss + ddf


class NormalHead(PolicyHead):
    """Diagonal Gaussian policy head: ``raw = [loc, scale_raw]``, ``raw_dim = 2 * act_dim``."""

    def __init__(self, act_dim: int, min_scale: float = 1e-3) -> None:
        """Create a head for ``act_dim`` action dimensions."""
        super().__init__(act_dim, min_scale)
        self.raw_dim = 2 * act_dim

    def split(self, raw: Tensor) -> tuple[Tensor, Tensor]:
        """Return ``(loc, scale)``."""
        self._check(raw)
        d = self.act_dim
        return raw[..., :d], self._scale(raw[..., d:])

    def distribution(self, raw: Tensor) -> Distribution:
        """Return ``Independent(Normal(loc, scale), 1)`` over ``u``."""
        loc, scale = self.split(raw)
        return Independent(Normal(loc, scale, validate_args=False), 1, validate_args=False)

    @torch.no_grad()
    def sample(self, raw: Tensor) -> Tensor:
        """``u ~ Normal(loc, scale)``, drawn as ``torch.distributions.Normal.sample`` does."""
        loc, scale = self.split(raw)
        return torch.normal(loc, scale)

    def log_prob(self, raw: Tensor, u: Tensor) -> Tensor:
        """Return ``log pi(u|s)`` in closed form; equal to ``distribution(raw).log_prob(u)``."""
        loc, scale = self.split(raw)
        return self.log_prob_at(loc, scale, torch.log(scale), u)

    def log_prob_at(self, loc: Tensor, scale: Tensor, log_scale: Tensor, u: Tensor) -> Tensor:
        """:meth:`log_prob` of ``u`` from the distribution's location, scale and log-scale
        (e.g. a scale that stays the same over many calls)."""
        z = (u - loc) / scale
        return -(0.5 * z * z + log_scale).sum(-1) - self.act_dim * _HALF_LOG_2PI

    def kl(self, raw_p: Tensor, raw_q: Tensor) -> Tensor:
        """Exact KL(p || q) of two diagonal Gaussians."""
        loc_p, scale_p = self.split(raw_p)
        loc_q, scale_q = self.split(raw_q)
        var_ratio = (scale_p / scale_q).square()
        mean_term = ((loc_p - loc_q) / scale_q).square()
        return 0.5 * (var_ratio + mean_term - 1.0 - torch.log(var_ratio)).sum(-1)


def make_head(kind: str, act_dim: int, min_scale: float = 1e-3, **kwargs: float) -> PolicyHead:
    """Return a policy head by name: ``"student_t"`` or ``"normal"`` (see :data:`HEAD_KINDS`).

    Extra keyword arguments go to the head (``min_df`` for ``"student_t"``).

    Raises:
        ValueError: for an unknown ``kind``.
    """
    if kind == "student_t":
        return StudentTHead(act_dim, min_scale=min_scale, **kwargs)
    if kind == "normal":
        return NormalHead(act_dim, min_scale=min_scale, **kwargs)
    raise ValueError(f"unknown policy head kind {kind!r}; choose one of {HEAD_KINDS}")


def _as_float64_vector(x: Tensor | np.ndarray | Sequence[float]) -> Tensor:
    """Return ``x`` as a float64 CPU tensor (a copy, detached)."""
    if isinstance(x, Tensor):
        return x.detach().to(device="cpu", dtype=torch.float64).clone()
    return torch.as_tensor(np.asarray(x, dtype=np.float64)).clone()


class ActionMap(nn.Module):
    """Map of the pre-map variable ``u`` into the box: ``a = low + (high-low)*sigmoid(u)``.

    ``low`` and ``high`` are stored as non-persistent buffers (they move with
    ``.to(device)`` but are not part of ``state_dict``); every method casts them
    to ``u``'s dtype and device, so float64 inputs are computed in float64.

    In float32, ``sigmoid(u)`` rounds to 0 or 1 for ``|u|`` beyond about 17, so an
    action can equal a bound exactly; actions always lie in ``[low, high]``.
    """

    low: Tensor
    high: Tensor
    log_range: Tensor

    def __init__(
        self,
        low: Tensor | np.ndarray | Sequence[float],
        high: Tensor | np.ndarray | Sequence[float],
    ) -> None:
        """Store 1-D bounds of equal length with ``high > low``, both finite."""
        super().__init__()
        low64, high64 = _as_float64_vector(low), _as_float64_vector(high)
        if low64.dim() != 1 or low64.shape != high64.shape or low64.numel() == 0:
            raise ValueError(
                "low and high must be non-empty 1-D of equal length, got shapes "
                f"{tuple(low64.shape)} and {tuple(high64.shape)}"
            )
        if not (torch.isfinite(low64).all() and torch.isfinite(high64).all()):
            raise ValueError("action bounds must be finite")
        if not (high64 > low64).all():
            raise ValueError("every high must be greater than its low")
        dtype = torch.get_default_dtype()
        self.register_buffer("low", low64.to(dtype), persistent=False)
        self.register_buffer("high", high64.to(dtype), persistent=False)
        self.register_buffer("log_range", torch.log(high64 - low64).to(dtype), persistent=False)

    @classmethod
    def from_space(cls, space: object) -> ActionMap:
        """Build the map from a ``gymnasium.spaces.Box`` (anything with ``low``/``high``)."""
        low = getattr(space, "low", None)
        high = getattr(space, "high", None)
        if low is None or high is None:
            raise ValueError(f"expected a Box-like space with low and high, got {space!r}")
        return cls(np.asarray(low).reshape(-1), np.asarray(high).reshape(-1))

    @property
    def act_dim(self) -> int:
        """Number of action dimensions."""
        return int(self.low.numel())

    def to_action(self, u: Tensor) -> Tensor:
        """Return ``a = low + (high - low) * sigmoid(u)`` (same shape as ``u``).

        The result is clamped to ``[low, high]`` against rounding (a no-op for the
        value and, inside the box, for the gradient).
        """
        low = self.low.to(u)
        high = self.high.to(u)
        return torch.clamp(low + (high - low) * torch.sigmoid(u), low, high)

    def forward(self, u: Tensor) -> Tensor:
        """Same as :meth:`to_action`."""
        return self.to_action(u)

    def log_abs_det_jacobian(self, u: Tensor) -> Tensor:
        """Return ``log|da/du|`` summed over the last dimension (shape ``u.shape[:-1]``).

        Computed stably from ``u``: ``logsigmoid(u) + logsigmoid(-u) + log(high-low)``.
        """
        per_dim = F.logsigmoid(u) + F.logsigmoid(-u) + self.log_range.to(u)
        return per_dim.sum(-1)

    def log_prob_action(self, dist: Distribution, u: Tensor) -> Tensor:
        """Return the log-density of the bounded action ``a = to_action(u)``.

        ``dist.log_prob(u) - log_abs_det_jacobian(u)``. For ratios of two policies
        at the same ``u`` the Jacobian cancels; use ``dist.log_prob(u)`` there.
        """
        return dist.log_prob(u) - self.log_abs_det_jacobian(u)
