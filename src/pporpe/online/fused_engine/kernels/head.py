r"""The policy head in closed form, for the fused kernel: log pi and its gradient, the KL
of two heads, a sample from unit-disk points, the action map and its Jacobian.

Per member; ``raw`` the policy's output at s_t, ``u`` the pre-map action. The torch
engine computes the same with :mod:`pporpe.nn.policies` and autograd; the head's scalars
are computed here in float64.

Student-t head (``loc, scale = softplus(raw_s) + min_scale, df = softplus(raw_df) +
min_df``; ``z = (u - loc) / scale``, ``q = z^2 / df``; softplus' = sigmoid)::

    log pi     = d [lgamma((df+1)/2) - lgamma(df/2) - log(df)/2 - log(pi)/2]
                 - sum_i [log scale_i + (df+1)/2 log1p(q_i)]
    d/d loc_i   = (df+1) z_i / (scale_i (df + z_i^2))
    d/d scale_i = ((df+1) z_i^2 / (df + z_i^2) - 1) / scale_i
    d/d df      = d [psi((df+1)/2) - psi(df/2) - 1/df] / 2
                  + sum_i [(df+1)/2 q_i / (df (1 + q_i)) - log1p(q_i) / 2]

Normal head: ``log pi = -sum_i (z_i^2/2 + log scale_i) - d log(2 pi)/2``,
``d/d loc_i = z_i / scale_i``, ``d/d scale_i = (z_i^2 - 1) / scale_i``.
"""

from __future__ import annotations

import math

import numpy as np

from .inputs import G_ACT_DIM, G_HEAD
from .jit import scalar_jit

__all__ = [
    "digamma",
    "head_grad_closed",
    "kl_closed",
    "log_abs_det_jacobian",
    "sample_pre_map",
    "to_action",
]

_HALF_LOG_PI = 0.5 * math.log(math.pi)
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


@scalar_jit
def digamma(x: float) -> float:
    r"""psi(x) for x > 0: ``psi(x) = psi(x + n) - sum_{j<n} 1/(x + j)`` up to y = x + n >= 10,
    then ``log y - 1/(2y) - sum_k B_2k / (2k y^2k)`` (k <= 5; the first omitted term,
    691 / (32760 y^12), is below 3e-14 at y >= 10)."""
    acc = 0.0
    y = x
    while y < 10.0:
        acc -= 1.0 / y
        y += 1.0
    f = 1.0 / (y * y)
    series = f * (1.0 / 12 - f * (1.0 / 120 - f * (1.0 / 252 - f * (1.0 / 240 - f / 132))))
    return acc + math.log(y) - 0.5 / y - series


@scalar_jit
def _softplus(x: float) -> float:
    """torch's softplus (beta 1, threshold 20)."""
    return x if x > 20.0 else math.log1p(math.exp(x))


@scalar_jit
def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0.0 else math.exp(x) / (1.0 + math.exp(x))


@scalar_jit
def _logsigmoid(x: float) -> float:
    return min(x, 0.0) - math.log1p(math.exp(-abs(x)))


@scalar_jit
def head_grad_closed(
    raw: np.ndarray, u: np.ndarray, head: int, d: int, min_scale: float, grad: np.ndarray
) -> float:
    """log pi(u | raw) in float64; writes d log pi / d raw into ``grad`` (module docstring)."""
    if head == 0:
        dr = np.float64(raw[2 * d])
        df = _softplus(dr) + 2.0
        hd = 0.5 * df
        hd1 = hd + 0.5
        logp = d * (math.lgamma(hd1) - math.lgamma(hd) - 0.5 * math.log(df) - _HALF_LOG_PI)
        g_df = d * 0.5 * (digamma(hd1) - digamma(hd) - 1.0 / df)
    else:
        df = hd1 = 0.0
        logp = -d * _HALF_LOG_2PI
        g_df = 0.0
    for i in range(d):
        sr = np.float64(raw[d + i])
        scale = _softplus(sr) + min_scale
        dsc = 1.0 if sr > 20.0 else _sigmoid(sr)
        z = (np.float64(u[i]) - np.float64(raw[i])) / scale
        z2 = z * z
        if head == 0:
            q = z2 / df
            logp -= math.log(scale) + hd1 * math.log1p(q)
            grad[i] = (df + 1.0) * z / (scale * (df + z2))
            grad[d + i] = ((df + 1.0) * z2 / (df + z2) - 1.0) / scale * dsc
            g_df += hd1 * q / (df * (1.0 + q)) - 0.5 * math.log1p(q)
        else:
            logp -= 0.5 * z2 + math.log(scale)
            grad[i] = z / scale
            grad[d + i] = (z2 - 1.0) / scale * dsc
    if head == 0:
        dr = np.float64(raw[2 * d])
        grad[2 * d] = g_df * (1.0 if dr > 20.0 else _sigmoid(dr))
    return logp


@scalar_jit
def kl_closed(raw_p: np.ndarray, raw_q: np.ndarray, head: int, d: int, min_scale: float) -> float:
    """KL(p || q) of two heads' outputs (normal exact; student-t the normal-gamma form)."""
    out = 0.0
    for i in range(d):
        sp = _softplus(np.float64(raw_p[d + i])) + min_scale
        sq = _softplus(np.float64(raw_q[d + i])) + min_scale
        vr = (sp / sq) ** 2
        mt = ((np.float64(raw_p[i]) - np.float64(raw_q[i])) / sq) ** 2
        out += 0.5 * (vr + mt - 1.0 - math.log(vr))
    if head == 0:
        dp = _softplus(np.float64(raw_p[2 * d])) + 2.0
        dq = _softplus(np.float64(raw_q[2 * d])) + 2.0
        out += 0.5 * (
            dq * (math.log(dp) - math.log(dq))
            - 2.0 * (math.lgamma(0.5 * dp) - math.lgamma(0.5 * dq))
            + (dp - dq) * (digamma(0.5 * dp) - 1.0)
        )
    return out


@scalar_jit
def sample_pre_map(
    raw: np.ndarray, pts: np.ndarray, geo: np.ndarray, min_scale: float, u: np.ndarray
) -> None:
    """``u = loc + scale T`` from unit-disk points ``pts [d, 2]`` (noise.py's polar forms)."""
    d = geo[G_ACT_DIM]
    df = 0.0
    if geo[G_HEAD] == 0:  # df in float32, as the torch head computes it
        df = np.float64(np.float32(_softplus(np.float64(raw[2 * d])) + 2.0))
    for i in range(d):
        scale = np.float32(_softplus(np.float64(raw[d + i])) + min_scale)
        px, py = pts[i, 0], pts[i, 1]
        w = px * px + py * py
        if geo[G_HEAD] == 0:
            t = px * math.sqrt(df * math.expm1((-2.0 / df) * math.log(w)) / w)
        else:
            t = px * math.sqrt(-2.0 * math.log(w) / w)
        u[i] = raw[i] + scale * np.float32(t)


@scalar_jit
def to_action(u: np.ndarray, bounds: np.ndarray, a: np.ndarray) -> None:
    """``a = clamp(low + (high - low) sigmoid(u), low, high)`` (``bounds = [low; high]``)."""
    for i in range(u.shape[0]):
        lo, hi = bounds[0, i], bounds[1, i]
        x = lo + (hi - lo) * np.float32(_sigmoid(np.float64(u[i])))
        a[i] = min(max(x, lo), hi)


@scalar_jit
def log_abs_det_jacobian(u: np.ndarray, bounds: np.ndarray) -> float:
    """``log|da/du| = sum_i logsigmoid(u_i) + logsigmoid(-u_i) + log(high_i - low_i)``."""
    out = 0.0
    for i in range(u.shape[0]):
        x = np.float64(u[i])
        out += _logsigmoid(x) + _logsigmoid(-x) + np.float64(bounds[2, i])
    return out
