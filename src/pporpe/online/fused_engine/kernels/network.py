"""The networks of the fused kernel: the forward of one member's net over rows of
observations and the hand-written backward of row s_t, in float32.

A net is one member's flat parameter vector ``p [n_pad]`` in the padded layout of
:class:`pporpe.nn.batched.NetLayout` (its hidden layers' offsets in ``lay``, the rest in
the geometry vector ``geo``); the torch engine computes the same with
:func:`pporpe.nn.batched.forward_chain` and :func:`pporpe.nn.batched.backward_row0`.
"""

from __future__ import annotations

import numpy as np

from .inputs import G_ACT, G_LAYERS, G_OBS, G_OUT_B, G_OUT_W, G_UNITS
from .jit import loop_jit, scalar_jit

__all__ = ["backward_row0", "forward_net"]

_LN_EPS = np.float32(1e-5)


@loop_jit
def _activate(y: np.float32, act: int) -> np.float32:
    if act == 0:
        return y / (np.float32(1.0) + np.exp(-y))
    if act == 1:
        return y if y > np.float32(0.0) else np.float32(0.0)
    return np.tanh(y)


@loop_jit
def _act_grad(y: np.float32, act: int) -> np.float32:
    if act == 0:
        s = np.float32(1.0) / (np.float32(1.0) + np.exp(-y))
        return s * (np.float32(1.0) + y * (np.float32(1.0) - s))
    if act == 1:
        return np.float32(1.0) if y > np.float32(0.0) else np.float32(0.0)
    t = np.tanh(y)
    return np.float32(1.0) - t * t


@loop_jit
def _dot(a: np.ndarray, b: np.ndarray, n: int) -> np.float32:
    """``sum_i a_i b_i`` over the first n (loops from 0 over views: vectorised)."""
    acc = np.float32(0.0)
    for i in range(n):
        acc += a[i] * b[i]
    return acc


@loop_jit
def _outer_acc(dj: np.float32, h: np.ndarray, w: np.ndarray, g: np.ndarray, dh: np.ndarray) -> None:
    """``g = dj h`` and ``dh += dj w`` (one row of a linear layer's backward)."""
    for i in range(h.shape[0]):
        g[i] = dj * h[i]
        dh[i] += dj * w[i]


@scalar_jit
def _layer(lay: np.ndarray, li: int) -> tuple[int, int, int, int, int]:
    """Offsets of W, b, gamma, beta (-1: none) and the input width of hidden layer li."""
    return lay[li, 0], lay[li, 1], lay[li, 2], lay[li, 3], lay[li, 4]


@loop_jit
def forward_net(
    p: np.ndarray,
    x: np.ndarray,
    lay: np.ndarray,
    geo: np.ndarray,
    cache: np.ndarray,
    rstd: np.ndarray,
    out: np.ndarray,
) -> None:
    """The forward of one net ``p [n_pad]`` on rows ``x [R, obs]``; its first
    ``out.shape[1]`` outputs into ``out [R, n_out]``.

    Unless ``rstd`` is empty, row 0's intermediates go to ``cache [layers + 1, 3, width]``
    (input of each linear layer, pre-activation y, xhat) and ``rstd [layers]``.
    """
    n_rows, units, act, n_out = x.shape[0], geo[G_UNITS], geo[G_ACT], out.shape[1]
    keep = rstd.shape[0] > 0
    width = max(geo[G_OBS], units)
    h = np.zeros((n_rows, width), np.float32)
    h[:, : geo[G_OBS]] = x
    z = np.empty((n_rows, units), np.float32)
    for li in range(geo[G_LAYERS]):
        w_off, b_off, g_off, be_off, n_in = _layer(lay, li)
        if keep:
            cache[li, 0, :n_in] = h[0, :n_in]
        for j in range(units):
            wr = p[w_off + j * n_in : w_off + (j + 1) * n_in]
            for rr in range(n_rows):
                z[rr, j] = p[b_off + j] + _dot(wr, h[rr], n_in)
        for rr in range(n_rows):
            if g_off >= 0:
                mean = np.float32(0.0)
                for j in range(units):
                    mean += z[rr, j]
                mean /= np.float32(units)
                var = np.float32(0.0)
                for j in range(units):
                    var += (z[rr, j] - mean) * (z[rr, j] - mean)
                rs = np.float32(1.0) / np.sqrt(var / np.float32(units) + _LN_EPS)
                for j in range(units):
                    xh = (z[rr, j] - mean) * rs
                    if keep and rr == 0:
                        cache[li, 2, j] = xh
                    z[rr, j] = p[be_off + j] + xh * p[g_off + j]
                if keep and rr == 0:
                    rstd[li] = rs
            if keep and rr == 0:
                cache[li, 1, :units] = z[0]
            for j in range(units):
                h[rr, j] = _activate(z[rr, j], act)
    n_in, w_off, b_off = units, geo[G_OUT_W], geo[G_OUT_B]
    if keep:
        cache[geo[G_LAYERS], 0, :units] = h[0, :units]
    for j in range(n_out):
        wr = p[w_off + j * n_in : w_off + (j + 1) * n_in]
        for rr in range(n_rows):
            out[rr, j] = p[b_off + j] + _dot(wr, h[rr], n_in)


@loop_jit
def backward_row0(
    p: np.ndarray,
    g: np.ndarray,
    dout: np.ndarray,
    lay: np.ndarray,
    geo: np.ndarray,
    cache: np.ndarray,
    rstd: np.ndarray,
    frozen_ln: bool,
) -> None:
    """d(dout . out[row 0]) / d p into ``g [n_pad]`` (real elements only; see batched.py)."""
    units, act, n_layers = geo[G_UNITS], geo[G_ACT], geo[G_LAYERS]
    n_out = dout.shape[0]
    w_off = geo[G_OUT_W]
    h = cache[n_layers, 0]
    dh = np.zeros(units, np.float32)
    for j in range(n_out):
        dj = dout[j]
        g[geo[G_OUT_B] + j] = dj
        lo = w_off + j * units
        _outer_acc(dj, h[:units], p[lo : lo + units], g[lo : lo + units], dh)
    dz = np.empty(units, np.float32)
    for li in range(n_layers - 1, -1, -1):
        w_off, b_off, g_off, be_off, n_in = _layer(lay, li)
        for j in range(units):
            dz[j] = dh[j] * _act_grad(cache[li, 1, j], act)
        if g_off >= 0:
            m1 = np.float32(0.0)
            m2 = np.float32(0.0)
            for j in range(units):
                xh = cache[li, 2, j]
                g[g_off + j] = np.float32(0.0) if frozen_ln else dz[j] * xh
                g[be_off + j] = np.float32(0.0) if frozen_ln else dz[j]
                dx = dz[j] * p[g_off + j]
                m1 += dx
                m2 += dx * xh
            m1 /= np.float32(units)
            m2 /= np.float32(units)
            rs = rstd[li]
            for j in range(units):
                xh = cache[li, 2, j]
                dz[j] = rs * (dz[j] * p[g_off + j] - m1 - xh * m2)
        hin = cache[li, 0, :n_in]
        dh[:] = np.float32(0.0)
        for j in range(units):
            dj = dz[j]
            g[b_off + j] = dj
            row = w_off + j * n_in
            _outer_acc(dj, hin, p[row : row + n_in], g[row : row + n_in], dh)
