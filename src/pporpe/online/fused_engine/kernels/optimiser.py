"""The optimiser of the fused kernel: the adaptive traces, td-AmsProp with t-momentum, the
trace decay, the bias corrections, the t-soft rate and the target update.

The rules are those of :mod:`pporpe.online.torch_engine.update` (its docstring writes
them out), per element. td-AmsProp and t-momentum run per parameter tensor (segment):
pass 1 over a segment (traces, moments, ``gv - m``), its t-momentum weight, pass 2 over
the same segment while it is in cache.
"""

from __future__ import annotations

import math

import numpy as np

from .inputs import (
    C_AMS_DECAY,
    C_BETA1,
    C_BETA2,
    C_GL1,
    C_GL2,
    C_LR,
    C_NEG_KAPPA,
    C_NU,
    C_SIGMA2_MIN,
    C_TAU,
)
from .jit import loop_jit, scalar_jit

__all__ = ["opt_scalars", "trace_scalars", "tsoft_rate", "update_net", "update_target"]

_F32_MAX = float(np.finfo(np.float32).max)


@loop_jit
def _pass1(
    g: np.ndarray, e: np.ndarray, r: np.ndarray, v: np.ndarray, vm: np.ndarray,
    m: np.ndarray, diff: np.ndarray, sc: np.ndarray,
) -> np.float32:  # fmt: skip
    """Traces, td-AmsProp's second moment and AMSGrad maximum of one segment (in place);
    ``gv - m`` into ``diff``; its sum of squares. ``sc`` as in :func:`update_net`."""
    sig, c1, c2, b2, omb2, vfac, sbc2, oeps = sc[0], sc[1], sc[2], sc[3], sc[4], sc[5], sc[6], sc[7]
    zero = np.float32(0.0)
    acc = zero
    for i in range(g.shape[0]):
        en = g[i] + e[i] * c1
        sg = np.float32(1.0) if en > zero else (np.float32(-1.0) if en < zero else en)
        a = r[i] * c2 * sg
        b = abs(en)
        rn = (a if a > b else b) * sg
        q = rn * sig
        vn = v[i] * b2 + q * q * omb2
        a = vm[i] * vfac
        vs = a if a > vn else vn
        dd = q / (np.sqrt(vs) / sbc2 + oeps) - m[i]
        e[i] = en
        r[i] = rn
        v[i] = vn
        vm[i] = vs
        diff[i] = dd
        acc += dd * dd
    return acc


@loop_jit
def _pass2(
    p: np.ndarray, m: np.ndarray, diff: np.ndarray, omb: np.float32, step: np.float32,
    target: np.ndarray,
) -> np.float32:  # fmt: skip
    """t-momentum and parameter step of one segment (in place); ``sum((p - target)^2)``
    after it when ``target`` is given (else 0)."""
    for i in range(p.shape[0]):
        mn = m[i] + omb * diff[i]
        m[i] = mn
        p[i] = p[i] - step * mn
    acc = np.float32(0.0)
    if target.shape[0] > 0:
        for i in range(p.shape[0]):
            dt = p[i] - target[i]
            acc += dt * dt
    return acc


@loop_jit
def update_net(
    buf: tuple,
    seg: np.ndarray,
    sc: np.ndarray,
    mom_only: bool,
    target: np.ndarray,
    diff: np.ndarray,
) -> float:
    """Traces, td-AmsProp and t-momentum of one net of one member, segment by segment:
    the SGD step of eq. (4) (``sgd``).

    ``buf = (p, g, e, r, v, vmax_s, m, W, num, den)`` (1-D views), ``seg [S, 2]`` the
    element range ``[lo, hi)`` of every segment (parameter tensor), ``sc`` float32
    ``[signal, c1, c2, beta2, 1 - beta2, vfac, sqrt(bc2), opt_eps, 1 - beta1, w_coef,
    lr / bc1]``. Returns ``sum((p - target)^2)`` after the step when ``target`` is
    not empty (the value net), else 0.
    """
    p, g, e, r, v, vm, m, W, num, den = buf
    d2 = np.float32(0.0)
    for s in range(seg.shape[0]):
        lo, hi = seg[s, 0], seg[s, 1]
        sq = _pass1(g[lo:hi], e[lo:hi], r[lo:hi], v[lo:hi], vm[lo:hi], m[lo:hi], diff, sc)
        w = num[s] / (sq + den[s])
        if mom_only:
            omb = sc[8]
        else:
            ww = W[s] + w
            omb = w / ww
            W[s] = ww + W[s] * sc[9]
        tg = target[lo:hi] if target.shape[0] > 0 else target
        d2 += _pass2(p[lo:hi], m[lo:hi], diff, omb, sc[10], tg)
    return np.float64(d2)


@scalar_jit
def opt_scalars(step: int, cf: np.ndarray, ams_raw: bool) -> tuple[float, float, float]:
    """The bias corrections of td-AmsProp, ``(vfac, sqrt(bc2), lr / bc1)`` at step t (as
    update.opt_scalars)."""
    t = np.float64(max(step, 1))
    bc1 = 1.0 - cf[C_BETA1] ** t
    bc2 = 1.0 - cf[C_BETA2] ** t
    bc2_prev = 1.0 - cf[C_BETA2] ** (t - 1.0) if t > 1.0 else 1.0
    ratio = 1.0 if ams_raw else bc2 / bc2_prev
    vfac = cf[C_AMS_DECAY] * ratio if t > 1.0 else 1.0
    if not cf[C_AMS_DECAY] > 0.0:
        vfac = 0.0
    return vfac, math.sqrt(bc2), cf[C_LR] / bc1


@scalar_jit
def trace_scalars(
    k: int, div: np.float32, cf: np.ndarray, kappa_pos: bool, sc: tuple
) -> tuple[np.float32, np.float32]:
    """Advance D and the trace decay of member k (float32, as update.trace_scalars);
    ``(c1, c2)``."""
    D, decay = sc[0], sc[1]
    gl1, gl2 = np.float32(cf[C_GL1]), np.float32(cf[C_GL2])
    if not kappa_pos:
        return gl1, gl2
    d_new = D[k] + div
    dec = np.exp(d_new * np.float32(cf[C_NEG_KAPPA]))
    d_new = d_new * dec
    if d_new != d_new:
        d_new = np.float32(0.0)
    elif d_new > _F32_MAX or d_new < -_F32_MAX:
        d_new = np.float32(_F32_MAX) if d_new > 0 else np.float32(-_F32_MAX)
    D[k], decay[k] = d_new, dec
    return dec * gl1, dec * gl2


@scalar_jit
def tsoft_rate(
    k: int, d2_sum: float, n_value: float, cf: np.ndarray, polyak: bool, sc: tuple
) -> np.float32:
    """t-soft rate of member k; advances its W and sigma2 (float64, as update.tsoft_rates)."""
    tsW, ts2 = sc[2], sc[3]
    d2 = np.float64(np.float32(d2_sum)) * (1.0 / n_value)
    tau, nu = cf[C_TAU], cf[C_NU]
    if polyak:
        return np.float32(tau)
    s2 = ts2[k]
    w = s2 / (d2 + nu * s2) * (nu + 1.0)
    w_sum = tsW[k] + w
    wt = w * (tau * nu / (nu + 1.0))
    lerp = s2 + wt * (d2 - s2) if abs(wt) < 0.5 else d2 - (d2 - s2) * (1.0 - wt)
    ts2[k] = max(lerp, cf[C_SIGMA2_MIN])
    tsW[k] = w_sum * (1.0 - tau)
    return np.float32(w / w_sum)


@loop_jit
def update_target(tgt: np.ndarray, val: np.ndarray, rate: np.float32) -> None:
    """The target update ``tgt <- tgt + rate (val - tgt)``, from the nearer end as
    ``torch.lerp``: exactly ``val`` at rate 1 (the test bed's learner has no target
    network: ``tau=1``)."""
    if rate < np.float32(0.5):
        for i in range(tgt.shape[0]):
            tgt[i] = tgt[i] + (val[i] - tgt[i]) * rate
    else:
        for i in range(tgt.shape[0]):
            tgt[i] = val[i] - (val[i] - tgt[i]) * (np.float32(1.0) - rate)
