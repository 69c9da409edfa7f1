r"""The elementwise part of one population step: traces, td-AmsProp, t-soft.

All state lives in ``[2, K, n_rows, units]`` tensors (net kind policy/value, member,
rows of the padded layout); per-member constants are ``[K]`` tensors. The functions are
pure tensor code without Python branching on data, so :func:`update_moments`,
:func:`update_momentum` and :func:`update_target` can be compiled with
``torch.compile(dynamic=False)``; scalars that would otherwise be recomputed per
element (bias corrections, the t-soft rate) are computed outside and passed in as
tensors. Members outside ``active`` keep every buffer
bitwise (``torch.where`` selects the old value).

Per member (the same rules as :class:`.traces.AdaptiveTraces`, :class:`.optim.TDAmsProp`
and :class:`.tsoft.TSoftUpdate`):

Traces, with ``c1 = gamma lambda1 decay``, ``c2 = gamma lambda2 decay``::

    e <- c1 e + g;   s = sign(e);   r <- s * max(s * c2 r, |e|)

(``r`` takes ``e`` where ``(e - r) sign(e) >= 0``). The optimiser's gradient is
``q = A r`` on the policy block and, on the value block, ``q = A rho_dagger r``
(``critic_signal="actor"``) or ``q = delta r`` (``"td"``, the default).

td-AmsProp at step t (``bc_i = 1 - beta_i^t``; ``vmax_s = vmax * bc2`` as in TDAmsProp)::

    v      <- beta2 v + (1 - beta2) q^2
    vmax_s <- max(vfac * vmax_s, v),   vfac = amsgrad_decay * bc2_t / bc2_{t-1}
    gv      = q / (sqrt(vmax_s) / sqrt(bc2) + eps)
    w       = (n + dof) / (dof + ||gv - m||^2)       per parameter tensor (segment)
    1 - b   = w / (W + w);   W <- (2 - 1/beta1) W + w
    m      <- m + (1 - b)(gv - m)
    p      <- p - lr / bc1 * m

With ``k_dof = inf`` or ``beta1 = 0`` (plain LaProp momentum) ``1 - b = 1 - beta1`` and
``W`` is left alone. ``amsgrad_decay = 0`` gives ``vfac = 0``: ``vmax_s = v``.

t-soft (:func:`tsoft_rates` on [K] scalars, :func:`update_target` elementwise)::

    D2 = mean((theta_v - target)^2);   w = (nu + 1) / (nu + D2 / sigma2)
    target <- target + w / (W + w) (theta_v - target)
    sigma2 <- max(lerp(sigma2, D2, tau w nu / (nu + 1)), sigma2_min);  W <- (1 - tau)(W + w)

(``nu = inf``: Polyak, rate ``tau``, ``W`` and ``sigma2`` untouched).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "opt_scalars",
    "trace_scalars",
    "tsoft_rates",
    "update_chunk",
    "update_moments",
    "update_momentum",
    "update_target",
]


def _k4(x: Tensor) -> Tensor:
    """A ``[K]`` tensor broadcast against ``[2, K, rows, units]``."""
    return x.view(1, -1, 1, 1)


def trace_scalars(
    D: Tensor,
    decay: Tensor,
    divergence: Tensor,
    neg_kappa: Tensor,
    kappa_pos: Tensor,
    gl1: Tensor,
    gl2: Tensor,
    active: Tensor,
) -> tuple[Tensor, Tensor]:
    """Advance the accumulated divergence ``D`` and the trace decay in place; return
    ``(c1, c2)``.

    ``D <- D + d;  decay = exp(-kappa D);  D <- nan_to_num(decay D)`` for members with
    ``kappa > 0`` (others keep ``D = 0``, ``decay = 1``), exactly as AdaptiveTraces.
    """
    d_new = D + divergence
    dec_new = torch.exp(d_new * neg_kappa)
    d_new = (d_new * dec_new).nan_to_num_(nan=0.0)
    upd = kappa_pos & active
    D.copy_(torch.where(upd, d_new, D))
    decay.copy_(torch.where(upd, dec_new, decay))
    c1 = torch.where(kappa_pos, dec_new * gl1, gl1)
    c2 = torch.where(kappa_pos, dec_new * gl2, gl2)
    return c1, c2


def _normalised(
    r: Tensor,
    vmax_s: Tensor,
    signal: Tensor,
    sqrt_bc2: Tensor,
    opt_eps: Tensor,
) -> tuple[Tensor, Tensor]:
    """``q = signal * r`` and ``gv = q / (sqrt(vmax_s) / sqrt(bc2) + eps)``."""
    q = r * signal.unsqueeze(-1).unsqueeze(-1)
    return q, q / (torch.sqrt(vmax_s) / _k4(sqrt_bc2) + _k4(opt_eps))


def update_moments(
    G: Tensor,
    e: Tensor,
    r: Tensor,
    v: Tensor,
    vmax_s: Tensor,
    m: Tensor,
    signal: Tensor,
    c1: Tensor,
    c2: Tensor,
    beta2: Tensor,
    one_m_beta2: Tensor,
    vfac: Tensor,
    sqrt_bc2: Tensor,
    opt_eps: Tensor,
    active: Tensor,
) -> Tensor:
    """Pass 1: traces, second moment and AMSGrad maximum (in place); row sums of (gv - m)^2.

    Shapes: ``G e r v vmax_s m [2, K, R, U]``, ``signal [2, K]`` (A and delta), the rest
    ``[K]``. Returns ``[2, K, R]``. ``gv - m`` is not stored: pass 2 recomputes it from
    the stored ``r`` and ``vmax_s`` with the same operations (so the same numbers).
    """
    act = _k4(active)
    # traces: e <- c1 e + g ; r <- s max(s c2 r, |e|)
    e_new = G + e * _k4(c1)
    s = torch.sign(e_new)
    r_new = torch.maximum(r * _k4(c2) * s, e_new.abs()) * s
    r_new = torch.where(act, r_new, r)
    q, _ = _normalised(r_new, vmax_s, signal, sqrt_bc2, opt_eps)
    v_new = v * _k4(beta2) + q * q * _k4(one_m_beta2)
    vs_new = torch.where(act, torch.maximum(vmax_s * _k4(vfac), v_new), vmax_s)
    _, gv = _normalised(r_new, vs_new, signal, sqrt_bc2, opt_eps)
    diff = gv - m
    e.copy_(torch.where(act, e_new, e))
    r.copy_(r_new)
    v.copy_(torch.where(act, v_new, v))
    vmax_s.copy_(vs_new)
    return (diff * diff).sum(-1)


def update_momentum(
    P: Tensor,
    r: Tensor,
    vmax_s: Tensor,
    m: Tensor,
    W: Tensor,
    rows: Tensor,
    signal: Tensor,
    sqrt_bc2: Tensor,
    opt_eps: Tensor,
    mom_only: Tensor,
    omb_mom: Tensor,
    w_coef: Tensor,
    num: Tensor,
    den: Tensor,
    step_size: Tensor,
    active: Tensor,
    row_seg: Tensor,
    col_seg: Tensor | None = None,
    bias_row: int = 0,
) -> Tensor:
    """Pass 2: t-momentum and the parameter step (in place); return D2 sums of t-soft.

    The step is the SGD of eq. (4) (``sgd``): ``p <- p - lr / bc1 * m``.

    ``P [3, K, R, U]`` (policy, value, target), ``W num den [2, K, S]``, ``rows [2, K, R]``
    from pass 1, ``row_seg [R]`` the segment of each row; ``col_seg [U]`` (optional) the
    segment of each element of row ``bias_row``, which then counts element by element
    (an output bias split into parts, :class:`~pporpe.nn.batched.NetLayout`). Returns
    ``sum((theta_v - target)^2)`` per member (``[K]``, after the step).
    """
    act = _k4(active)
    theta = P[:2]
    _, gv = _normalised(r, vmax_s, signal, sqrt_bc2, opt_eps)
    diff = gv - m
    # t-momentum weight per segment (parameter tensor): index_add of the row sums
    if col_seg is not None:
        rows = rows.clone()
        rows[:, :, bias_row] = 0.0
    sq = torch.zeros_like(W).index_add_(2, row_seg, rows)
    if col_seg is not None:
        split = diff[:, :, bias_row]
        sq.index_add_(2, col_seg, split * split)
    w = num / (sq + den)
    ww = W + w
    k3 = active.view(1, -1, 1)
    mom = mom_only.view(1, -1, 1)
    omb = torch.where(mom, omb_mom.view(1, -1, 1), w / ww)
    W.copy_(torch.where(k3 & ~mom, ww + W * w_coef.view(1, -1, 1), W))
    step = omb[:, :, row_seg].unsqueeze(-1) * diff
    if col_seg is not None:
        step[:, :, bias_row] = omb[:, :, col_seg] * diff[:, :, bias_row]
    m_new = torch.where(act, m + step, m)
    theta_new = torch.where(act, theta - _k4(step_size) * m_new, theta)
    m.copy_(m_new)
    P[:2].copy_(theta_new)
    dt = theta_new[1] - P[2]
    return (dt * dt).sum((-1, -2))


def update_chunk(
    P: Tensor,
    G: Tensor,
    e: Tensor,
    r: Tensor,
    v: Tensor,
    vmax_s: Tensor,
    m: Tensor,
    W: Tensor,
    signal: Tensor,
    c1: Tensor,
    c2: Tensor,
    beta2: Tensor,
    one_m_beta2: Tensor,
    vfac: Tensor,
    sqrt_bc2: Tensor,
    opt_eps: Tensor,
    mom_only: Tensor,
    omb_mom: Tensor,
    w_coef: Tensor,
    num: Tensor,
    den: Tensor,
    step_size: Tensor,
    active: Tensor,
    row_seg: Tensor,
    col_seg: Tensor | None = None,
    bias_row: int = 0,
) -> Tensor:
    """Both passes for a block of members (in place); return their t-soft D2 sums.

    The learner calls this on blocks of a few members whose buffers fit in the last-level
    cache, so that pass 2 re-reads them from cache instead of memory.
    """
    rows = update_moments(
        G, e, r, v, vmax_s, m, signal, c1, c2, beta2, one_m_beta2, vfac, sqrt_bc2, opt_eps,
        active,
    )  # fmt: skip
    return update_momentum(
        P, r, vmax_s, m, W, rows, signal, sqrt_bc2, opt_eps, mom_only, omb_mom, w_coef, num,
        den, step_size, active, row_seg, col_seg, bias_row,
    )  # fmt: skip


def tsoft_rates(
    d2_sum: Tensor,
    n_value: float,
    W: Tensor,
    sigma2: Tensor,
    tau: Tensor,
    nu: Tensor,
    polyak: Tensor,
    sigma2_min: Tensor,
    active: Tensor,
) -> Tensor:
    """t-soft scalars (float64 ``[K]``, in place on ``W``, ``sigma2``); return the rate.

    ``w = (nu + 1) sigma2 / (D2 + nu sigma2)`` as TSoftUpdate computes it; the rate is
    ``w / (W + w)``, or ``tau`` for Polyak members (``nu = inf``).
    """
    d2 = d2_sum.to(torch.float64) * (1.0 / n_value)
    nu_s = torch.where(polyak, 1.0, nu)
    w = sigma2 / (d2 + nu_s * sigma2) * (nu_s + 1.0)
    w_sum = W + w
    rate = torch.where(polyak, tau, w / w_sum)
    tau_s = w * (tau * nu_s / (nu_s + 1.0))
    s2 = torch.lerp(sigma2, d2, tau_s).clamp_(min=sigma2_min)
    upd = active & ~polyak
    sigma2.copy_(torch.where(upd, s2, sigma2))
    W.copy_(torch.where(upd, w_sum * (1.0 - tau), W))
    return rate.to(torch.float32)


def update_target(P: Tensor, rate: Tensor, active: Tensor) -> None:
    """The target update: ``target <- target + rate (theta_v - target)`` for the active
    members (in place)."""
    tgt = P[2]
    new = tgt + (P[1] - tgt) * rate.view(-1, 1, 1)
    P[2].copy_(torch.where(active.view(-1, 1, 1), new, tgt))


def opt_scalars(
    steps: np.ndarray,
    beta1: np.ndarray,
    beta2: np.ndarray,
    lr: np.ndarray,
    ams_decay: np.ndarray,
    ams_raw: np.ndarray,
) -> tuple[Tensor, Tensor, Tensor]:
    """The bias corrections of td-AmsProp per member, in float64 as TDAmsProp computes them.

    ``steps`` are the members' step counts t (already advanced); ``beta1``, ``beta2``,
    ``lr``, ``ams_decay`` (float64) and ``ams_raw`` (bool: the maximum of the raw moment)
    are ``[K]`` arrays of the members' constants. Returns float32 ``[K]`` tensors ``vfac``
    (``decay * bc2_t / bc2_{t-1}``, 1 at t = 1, 0 when the maximum is off), ``sqrt(bc2)``
    and ``lr / bc1``.
    """
    t = np.maximum(steps, 1).astype(np.float64)
    bc1 = 1.0 - beta1**t
    bc2 = 1.0 - beta2**t
    bc2_prev = np.where(t > 1, 1.0 - beta2 ** (t - 1), 1.0)
    # the maximum of the bias-corrected moment (vmax_s is stored scaled by bc2), or of the
    # raw moment, bias-corrected after (ams_raw)
    ratio = np.where(ams_raw, 1.0, bc2 / bc2_prev)
    vfac = np.where(t > 1, ams_decay * ratio, 1.0)
    vfac = np.where(ams_decay > 0, vfac, 0.0)
    out = torch.from_numpy(np.stack([vfac, np.sqrt(bc2), lr / bc1]).astype(np.float32))
    return out[0], out[1], out[2]
