r"""The fused engine of :class:`~pporpe.online.population.PopulationLearner`: one step of
every member as one compiled numba kernel (``engine="fused"``).

Everything between "transition in" and "next action out" runs in :func:`fused_step`, a
loop over the members of nopython code on the learner's own stacked float32 buffers
(numpy views of its torch tensors, shared without copies): the forward of the policy,
value and target networks, the head's gradient in closed form, the hand-written backward
of row s_t, the traces, td-AmsProp, t-soft and the pending-state update. Noise is drawn
by :class:`~pporpe.online.noise.NoiseBank` in Python and passed in as unit-disk points.
The numbers are those of the torch engine up to float rounding (the same operations in
the same order where it matters; reductions are reassociated for vectorisation and the
head's scalars are computed in float64); the fused engine is bitwise deterministic for
the same inputs on the same machine, and a member's numbers never depend on the others.

Closed forms (per member; ``raw`` the policy's output at s_t, ``u`` the pre-map action):

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

Surrogates at ``A = sigma`` (the learner's per-unit-signal objective obj(rho, sigma);
``mix = 1 - beta + beta rho``, ``dev = rho / mix - 1``)::

    PPO, PPO-RB: obj = sigma rho_PPO; past = sigma (rho - 1) >= eps:
                 rho_PPO = -eta rho + (1+eta)(1 + sigma eps), d obj/d rho = -eta sigma
                 else rho_PPO = rho, d obj/d rho = sigma          (PPO: eta = 0)
    RPE derived: C = 1 / (eps (2(1-beta) - beta sigma eps))
                 obj = sigma rho - C mix dev^2
                 d obj/d rho = sigma - C dev (beta dev + 2(1-beta)/mix)
    RPE printed: obj = rho A~_printed(rho) with A~ held constant: d obj/d rho = A~_printed

and the head's signal ``d(-sigma obj)/d raw = -sigma obj'(rho) rho d log pi/d raw``
(``policy_gradient="weighted_score"``: ``-rho_dagger d log pi/d raw``,
``rho_dagger = sigma obj``). The remaining rules (TD error, advantage, divergences,
traces, td-AmsProp, t-soft) are those of :mod:`pporpe.online.population` and
:mod:`pporpe.online.update`, written per element. td-AmsProp and t-momentum run per
parameter tensor (segment): pass 1 over a segment (traces, moments, ``gv - m``), its
t-momentum weight, pass 2 over the same segment while it is in cache.

Compiled artefacts are cached on disk by numba (``cache=True``): in the package's
``__pycache__`` folder, or where ``NUMBA_CACHE_DIR`` points; the next process loads them
instead of compiling (:func:`pporpe.online.fused_engine.warm_up` compiles or loads every
kernel, once per process, when the first fused population is built).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "C_NAMES",
    "F_NAMES",
    "METHOD_CODES",
    "digamma",
    "fused_begin",
    "fused_forward",
    "fused_step",
    "head_grad_closed",
    "surrogate_closed",
]

FM = {"nsz", "reassoc", "contract"}
"""fastmath flags of the loops: reassociation (vectorised sums), FMA, signed zeros. Not
``nnan``/``ninf``: a non-finite member must stay non-finite."""

C_NAMES: tuple[str, ...] = (
    "reward_scale", "gamma", "one_m_gamma", "beta_td", "beta_de", "td_scale", "neg_kappa",
    "gl1", "gl2", "beta2_f32", "one_m_beta2", "opt_eps", "omb_mom", "w_coef", "tau", "nu",
    "sigma2_min", "beta1", "beta2", "lr", "ams_decay", "eps", "beta", "eta",
)  # fmt: skip
"""Columns of the per-member float constants matrix (float64 ``[K, len(C_NAMES)]``)."""
(
    C_REWARD_SCALE, C_GAMMA, C_ONE_M_GAMMA, C_BETA_TD, C_BETA_DE, C_TD_SCALE, C_NEG_KAPPA,
    C_GL1, C_GL2, C_BETA2_F32, C_ONE_M_BETA2, C_OPT_EPS, C_OMB_MOM, C_W_COEF, C_TAU, C_NU,
    C_SIGMA2_MIN, C_BETA1, C_BETA2, C_LR, C_AMS_DECAY, C_EPS, C_BETA, C_ETA,
) = range(len(C_NAMES))  # fmt: skip

F_NAMES: tuple[str, ...] = (
    "kappa_pos", "mom_only", "polyak", "pre_squash", "critic_actor", "kl_analytic",
    "weighted_score", "limit_terminal", "ln_frozen", "ams_raw", "method",
)  # fmt: skip
"""Columns of the per-member flags matrix (int64 ``[K, len(F_NAMES)]``)."""
(
    F_KAPPA_POS, F_MOM_ONLY, F_POLYAK, F_PRE_SQUASH, F_CRITIC_ACTOR, F_KL_ANALYTIC,
    F_WEIGHTED, F_LIMIT_TERMINAL, F_LN_FROZEN, F_AMS_RAW, F_METHOD,
) = range(len(F_NAMES))  # fmt: skip

METHOD_CODES = {("ppo", "derived"): 0, ("ppo", "printed"): 0, ("rb", "derived"): 1,
                ("rb", "printed"): 1, ("rpe", "derived"): 2, ("rpe", "printed"): 3}  # fmt: skip
"""Surrogate code of (method, rpe_form)."""

ACTIVATIONS = {"swish": 0, "relu": 1, "tanh": 2}
HEADS = {"student_t": 0, "normal": 1}

# geometry vector (int64) of a layout, see pporpe.online.population._fused_geometry
G_OBS, G_UNITS, G_RAW, G_OUT_W, G_OUT_B, G_LN, G_ACT, G_HEAD, G_ACT_DIM, G_LAYERS = range(10)

_jit = njit(cache=True, error_model="numpy")
"""Scalar code: numpy's error model (x / 0 is inf or nan, as in torch, never an exception)."""
_jit_fm = njit(cache=True, fastmath=FM, error_model="numpy")
"""Loops: the same with :data:`FM` (they vectorise)."""

_HALF_LOG_PI = 0.5 * math.log(math.pi)
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
_LN_EPS = np.float32(1e-5)
_F32_MAX = float(np.finfo(np.float32).max)


# ------------------------------------------------------------------------------ scalars
@_jit
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


@_jit
def _softplus(x: float) -> float:
    """torch's softplus (beta 1, threshold 20)."""
    return x if x > 20.0 else math.log1p(math.exp(x))


@_jit
def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0.0 else math.exp(x) / (1.0 + math.exp(x))


@_jit
def _logsigmoid(x: float) -> float:
    return min(x, 0.0) - math.log1p(math.exp(-abs(x)))


@_jit
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


@_jit
def _kl(raw_p: np.ndarray, raw_q: np.ndarray, head: int, d: int, min_scale: float) -> float:
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


@_jit
def surrogate_closed(
    method: int, rho: float, sigma: float, eps: float, beta: float, eta: float
) -> tuple[float, float]:
    """``(obj(rho, sigma), d obj / d rho)`` of the surrogate ``method`` (module docstring)."""
    if method <= 1:
        slope = 0.0 if method == 0 else eta
        if sigma * (rho - 1.0) >= eps:
            return (-slope * rho + (1.0 + slope) * (1.0 + sigma * eps)) * sigma, -slope * sigma
        return rho * sigma, sigma
    mix = 1.0 - beta + beta * rho
    dev = rho / mix - 1.0
    if method == 2:
        gain = 1.0 / (eps * (2.0 * (1.0 - beta) - beta * sigma * eps))
        obj = rho * sigma - gain * mix * dev * dev
        return obj, sigma - gain * dev * (beta * dev + 2.0 * (1.0 - beta) / mix)
    denom = sigma * eps * (beta * sigma * eps - 2.0 * (1.0 - beta * (1.0 + sigma * eps)))
    w = sigma - sigma * dev * (beta * dev - 2.0 * (1.0 - beta) / mix) / denom
    return rho * w, w


# ------------------------------------------------------------------------------ network
@_jit_fm
def _activate(y: np.float32, act: int) -> np.float32:
    if act == 0:
        return y / (np.float32(1.0) + np.exp(-y))
    if act == 1:
        return y if y > np.float32(0.0) else np.float32(0.0)
    return np.tanh(y)


@_jit_fm
def _act_grad(y: np.float32, act: int) -> np.float32:
    if act == 0:
        s = np.float32(1.0) / (np.float32(1.0) + np.exp(-y))
        return s * (np.float32(1.0) + y * (np.float32(1.0) - s))
    if act == 1:
        return np.float32(1.0) if y > np.float32(0.0) else np.float32(0.0)
    t = np.tanh(y)
    return np.float32(1.0) - t * t


@_jit_fm
def _dot(a: np.ndarray, b: np.ndarray, n: int) -> np.float32:
    """``sum_i a_i b_i`` over the first n (loops from 0 over views: vectorised)."""
    acc = np.float32(0.0)
    for i in range(n):
        acc += a[i] * b[i]
    return acc


@_jit_fm
def _outer_acc(dj: np.float32, h: np.ndarray, w: np.ndarray, g: np.ndarray, dh: np.ndarray) -> None:
    """``g = dj h`` and ``dh += dj w`` (one row of a linear layer's backward)."""
    for i in range(h.shape[0]):
        g[i] = dj * h[i]
        dh[i] += dj * w[i]


@_jit
def _layer(lay: np.ndarray, li: int) -> tuple[int, int, int, int, int]:
    """Offsets of W, b, gamma, beta (-1: none) and the input width of hidden layer li."""
    return lay[li, 0], lay[li, 1], lay[li, 2], lay[li, 3], lay[li, 4]


@_jit_fm
def _forward(
    p: np.ndarray,
    x: np.ndarray,
    lay: np.ndarray,
    geo: np.ndarray,
    cache: np.ndarray,
    rstd: np.ndarray,
    out: np.ndarray,
) -> None:
    """One net ``p [n_pad]`` on rows ``x [R, obs]``; its first ``out.shape[1]`` outputs
    into ``out [R, n_out]``.

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


@_jit_fm
def _backward(
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


# ------------------------------------------------------------------------------ update
@_jit_fm
def _pass1(
    g: np.ndarray, e: np.ndarray, r: np.ndarray, v: np.ndarray, vm: np.ndarray,
    m: np.ndarray, diff: np.ndarray, sc: np.ndarray,
) -> np.float32:  # fmt: skip
    """Traces and moments of one segment (in place); ``gv - m`` into ``diff``; its sum of
    squares. ``sc`` as in :func:`_update_kind`."""
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


@_jit_fm
def _pass2(
    p: np.ndarray, m: np.ndarray, diff: np.ndarray, omb: np.float32, step: np.float32,
    target: np.ndarray,
) -> np.float32:  # fmt: skip
    """Momentum and parameter step of one segment (in place); ``sum((p - target)^2)``
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


@_jit_fm
def _update_kind(
    buf: tuple,
    seg: np.ndarray,
    sc: np.ndarray,
    mom_only: bool,
    target: np.ndarray,
    diff: np.ndarray,
) -> float:
    """Traces, td-AmsProp and t-momentum of one net of one member, segment by segment.

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


@_jit
def _opt_scalars(step: int, cf: np.ndarray, ams_raw: bool) -> tuple[float, float, float]:
    """td-AmsProp's ``(vfac, sqrt(bc2), lr / bc1)`` at step t (as update.opt_scalars)."""
    t = np.float64(max(step, 1))
    bc1 = 1.0 - cf[C_BETA1] ** t
    bc2 = 1.0 - cf[C_BETA2] ** t
    bc2_prev = 1.0 - cf[C_BETA2] ** (t - 1.0) if t > 1.0 else 1.0
    ratio = 1.0 if ams_raw else bc2 / bc2_prev
    vfac = cf[C_AMS_DECAY] * ratio if t > 1.0 else 1.0
    if not cf[C_AMS_DECAY] > 0.0:
        vfac = 0.0
    return vfac, math.sqrt(bc2), cf[C_LR] / bc1


@_jit
def _trace_scalars(
    k: int, div: np.float32, cf: np.ndarray, kappa_pos: bool, sc: tuple
) -> tuple[np.float32, np.float32]:
    """Advance D and the decay of member k (float32, as update.trace_scalars); ``(c1, c2)``."""
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


@_jit
def _tsoft_rate(
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


@_jit_fm
def _target_step(tgt: np.ndarray, val: np.ndarray, rate: np.float32) -> None:
    """``tgt <- tgt + rate (val - tgt)``, from the nearer end as ``torch.lerp``: exactly
    ``val`` at rate 1 (the test bed's learner has no target network: ``tau=1``)."""
    if rate < np.float32(0.5):
        for i in range(tgt.shape[0]):
            tgt[i] = tgt[i] + (val[i] - tgt[i]) * rate
    else:
        for i in range(tgt.shape[0]):
            tgt[i] = val[i] - (val[i] - tgt[i]) * (np.float32(1.0) - rate)


# ------------------------------------------------------------------------------ acting
@_jit
def _sample(
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


@_jit
def _to_action(u: np.ndarray, bounds: np.ndarray, a: np.ndarray) -> None:
    """``a = clamp(low + (high - low) sigmoid(u), low, high)`` (``bounds = [low; high]``)."""
    for i in range(u.shape[0]):
        lo, hi = bounds[0, i], bounds[1, i]
        x = lo + (hi - lo) * np.float32(_sigmoid(np.float64(u[i])))
        a[i] = min(max(x, lo), hi)


@_jit
def _jacobian(u: np.ndarray, bounds: np.ndarray) -> float:
    """``log|da/du| = sum_i logsigmoid(u_i) + logsigmoid(-u_i) + log(high_i - low_i)``."""
    out = 0.0
    for i in range(u.shape[0]):
        x = np.float64(u[i])
        out += _logsigmoid(x) + _logsigmoid(-x) + np.float64(bounds[2, i])
    return out


# ------------------------------------------------------------------------------ one step
@_jit
def _signals(
    k: int,
    raw0: np.ndarray,
    vals: np.ndarray,
    pend: tuple,
    inp: tuple,
    cf: np.ndarray,
    fl: np.ndarray,
    geo: np.ndarray,
    hf: np.ndarray,
    bounds: np.ndarray,
    d_raw: np.ndarray,
) -> tuple[float, float, float, float, float]:
    """delta, A, rho, the trace divergence and rho_dagger of member k; the head's signal
    ``d(-sigma obj)/d raw`` into ``d_raw`` (float32)."""
    u_b, logp_b, value_b, raw_b = pend[1], pend[2], pend[3], pend[4]
    rew, term, trunc = inp[0], inp[2], inp[3]
    v, next_target = np.float64(vals[0]), np.float64(vals[2])
    ends = term[k] or (trunc[k] and fl[F_LIMIT_TERMINAL] != 0)
    boot = 0.0 if ends else np.float64(np.float32(cf[C_GAMMA]))
    delta = np.float64(np.float32(np.float64(rew[k]) * cf[C_REWARD_SCALE] + boot * next_target - v))
    d = geo[G_ACT_DIM]
    dlogp = np.empty(geo[G_RAW])
    logp = np.float64(np.float32(head_grad_closed(raw0, u_b[k], geo[G_HEAD], d, hf[0], dlogp)))
    log_ratio = logp - np.float64(logp_b[k])
    ratio = math.exp(log_ratio)
    ent = logp if fl[F_PRE_SQUASH] != 0 else logp - _jacobian(u_b[k], bounds)
    td = delta * cf[C_TD_SCALE]
    penalty = cf[C_BETA_TD] * td * td + cf[C_BETA_DE] * ent
    adv = np.float64(np.float32(delta - cf[C_ONE_M_GAMMA] * penalty))
    sigma = 1.0 if adv >= 0.0 else -1.0
    obj, dobj = surrogate_closed(fl[F_METHOD], ratio, sigma, cf[C_EPS], cf[C_BETA], cf[C_ETA])
    rho_dagger = np.float64(np.float32(sigma * obj))
    coef = -rho_dagger if fl[F_WEIGHTED] != 0 else -sigma * dobj * ratio
    for j in range(d_raw.shape[0]):
        d_raw[j] = coef * dlogp[j]
    dv = v - np.float64(value_b[k])
    if fl[F_KL_ANALYTIC] != 0:
        kl = _kl(raw0, raw_b[k], geo[G_HEAD], d, hf[0])
        div = (kl if not kl < 0.0 else 0.0) + 0.5 * dv * dv
    else:
        div = (ratio - 1.0 - log_ratio) + dv * dv
    return delta, adv, ratio, div, rho_dagger


@_jit
def _learn(
    k: int,
    P: np.ndarray,
    opt: tuple,
    sc: tuple,
    cf: np.ndarray,
    fl: np.ndarray,
    geo: np.ndarray,
    lay: np.ndarray,
    seg: np.ndarray,
    hf: np.ndarray,
    sig: tuple,
    scratch: tuple,
) -> None:
    """Backward, traces, td-AmsProp, t-soft and the target of member k (in place)."""
    e, r, v, vm, m, W, num, den = opt
    g, diff, cache, rstd = scratch[0], scratch[1], scratch[2], scratch[3]
    d_raw, delta, adv, div, rho_dagger = sig
    c1, c2 = _trace_scalars(k, np.float32(div), cf, fl[F_KAPPA_POS] != 0, sc)
    steps = sc[4]
    steps[k] += 1
    vfac, sbc2, step = _opt_scalars(steps[k], cf, fl[F_AMS_RAW] != 0)
    frozen = fl[F_LN_FROZEN] != 0
    _backward(P[0, k], g[0], d_raw, lay, geo, cache[0], rstd[0], frozen)
    dv = np.empty(1, np.float32)
    dv[0] = -rho_dagger if fl[F_CRITIC_ACTOR] != 0 else -1.0
    _backward(P[1, k], g[1], dv, lay, geo, cache[1], rstd[1], frozen)
    consts = np.empty(11, np.float32)
    consts[1], consts[2], consts[3], consts[4] = c1, c2, cf[C_BETA2_F32], cf[C_ONE_M_BETA2]
    consts[5], consts[6], consts[7], consts[8] = vfac, sbc2, cf[C_OPT_EPS], cf[C_OMB_MOM]
    consts[9], consts[10] = cf[C_W_COEF], step
    no_target = np.empty(0, np.float32)
    d2 = 0.0
    for j in range(2):
        consts[0] = adv if (j == 0 or fl[F_CRITIC_ACTOR] != 0) else delta
        buf = (P[j, k], g[j], e[j, k], r[j, k], v[j, k], vm[j, k], m[j, k], W[j, k],
               num[j, k], den[j, k])  # fmt: skip
        tgt = P[2, k] if j == 1 else no_target
        d2 = _update_kind(buf, seg, consts, fl[F_MOM_ONLY] != 0, tgt, diff)
    rate = _tsoft_rate(k, d2, hf[1], cf, fl[F_POLYAK] != 0, sc)
    _target_step(P[2, k], P[1, k], rate)


@_jit
def _member_step(
    k: int, P: np.ndarray, opt: tuple, sc: tuple, pend: tuple, inp: tuple, cf: np.ndarray,
    fl: np.ndarray, geo: np.ndarray, lay: np.ndarray, seg: np.ndarray, hf: np.ndarray,
    bounds: np.ndarray, out: tuple, scratch: tuple,
) -> None:  # fmt: skip
    """One member's step: forward, signals, a_{t+1}, learning (if active), pending state."""
    obs, u_b, logp_b, value_b, raw_b, pending = pend
    nxt, term, trunc, active, pts, forced, use_forced = inp[1:]
    stats, actions = out
    cache, rstd = scratch[2], scratch[3]
    raw_dim, d = geo[G_RAW], geo[G_ACT_DIM]
    x = np.empty((2, geo[G_OBS]), np.float32)
    x[0], x[1] = obs[k], nxt[k]
    pol = np.empty((2, raw_dim), np.float32)
    val = np.empty((2, 1), np.float32)
    tg = np.empty((1, 1), np.float32)
    _forward(P[0, k], x, lay, geo, cache[0], rstd[0], pol)
    _forward(P[1, k], x, lay, geo, cache[1], rstd[1], val)
    _forward(P[2, k], x[1:], lay, geo, scratch[4], scratch[5], tg)
    vals = np.array([val[0, 0], val[1, 0], tg[0, 0]])
    d_raw = np.empty(raw_dim, np.float32)
    delta, adv, ratio, div, rho_dagger = _signals(
        k, pol[0], vals, pend, inp, cf[k], fl[k], geo, hf, bounds, d_raw
    )
    u_next = np.empty(d, np.float32)
    if use_forced:
        u_next[:] = forced[k]
    else:
        _sample(pol[1], pts[k], geo, hf[0], u_next)
    grad = np.empty(raw_dim)
    logp_next = head_grad_closed(pol[1], u_next, geo[G_HEAD], d, hf[0], grad)
    if active[k]:
        sig = (d_raw, delta, adv, div, rho_dagger)
        _learn(k, P, opt, sc, cf[k], fl[k], geo, lay, seg, hf, sig, scratch)
    stats[0, k], stats[1, k], stats[2, k], stats[3, k] = delta, adv, ratio, div
    stats[4, k] = sc[1][k]
    _to_action(u_next, bounds, actions[k])
    done = term[k] or trunc[k]
    if active[k] and not done:
        obs[k], u_b[k], logp_b[k] = nxt[k], u_next, logp_next
        value_b[k], raw_b[k] = val[1, 0], pol[1]
    if active[k] and done:
        pending[k] = False


@_jit
def fused_step(
    P: np.ndarray, opt: tuple, sc: tuple, pend: tuple, inp: tuple, cf: np.ndarray,
    fl: np.ndarray, geo: np.ndarray, lay: np.ndarray, seg: np.ndarray, hf: np.ndarray,
    bounds: np.ndarray, out: tuple, scratch: tuple,
) -> None:  # fmt: skip
    """One step of every member (in place on the learner's buffers).

    ``P [3, K, n_pad]``; ``opt = (e, r, v, vmax_s, m [2, K, n_pad], W, num, den [2, K, S])``;
    ``sc = (D, decay [K] f32, t-soft W, sigma2 [K] f64, steps [K] i64)``; ``pend = (obs,
    u, logp_b, value_b, raw_b, pending)``; ``inp = (reward, next_obs, terminated,
    truncated, active, points [K, d, 2] f64, forced_u, use_forced)``; ``cf``/``fl`` the
    constants (:data:`C_NAMES`, :data:`F_NAMES`); ``geo``, ``lay``, ``seg`` the layout;
    ``hf = [min_scale, n_value]``; ``bounds = [low; high; log(high - low)]``;
    ``out = (stats [5, K], actions [K, d])``; ``scratch = (g [2, n_pad], diff, cache,
    rstd, an empty cache, an empty rstd)``.
    """
    for k in range(P.shape[1]):
        _member_step(k, P, opt, sc, pend, inp, cf, fl, geo, lay, seg, hf, bounds, out, scratch)


@_jit
def fused_begin(
    P: np.ndarray, idx: np.ndarray, x: np.ndarray, pts: np.ndarray, forced: np.ndarray,
    use_forced: bool, geo: np.ndarray, lay: np.ndarray, hf: np.ndarray, bounds: np.ndarray,
    pend: tuple, actions: np.ndarray, scratch: tuple,
) -> None:  # fmt: skip
    """First actions of members ``idx`` at observations ``x [n, obs]`` and their pending
    state (log pi_b, V_b, raw_b at s_0)."""
    obs, u_b, logp_b, value_b, raw_b, pending = pend
    raw_dim, d = geo[G_RAW], geo[G_ACT_DIM]
    pol = np.empty((1, raw_dim), np.float32)
    val = np.empty((1, 1), np.float32)
    grad = np.empty(raw_dim)
    for i in range(idx.shape[0]):
        k = idx[i]
        _forward(P[0, k], x[i : i + 1], lay, geo, scratch[4], scratch[5], pol)
        _forward(P[1, k], x[i : i + 1], lay, geo, scratch[4], scratch[5], val)
        if use_forced:
            u_b[k] = forced[i]
        else:
            _sample(pol[0], pts[k], geo, hf[0], u_b[k])
        obs[k], raw_b[k], value_b[k] = x[i], pol[0], val[0, 0]
        logp_b[k] = head_grad_closed(pol[0], u_b[k], geo[G_HEAD], d, hf[0], grad)
        pending[k] = True
        _to_action(u_b[k], bounds, actions[i])


@_jit
def fused_forward(
    P: np.ndarray, kind: int, x: np.ndarray, geo: np.ndarray, lay: np.ndarray,
    out: np.ndarray, scratch: tuple,
) -> None:  # fmt: skip
    """Outputs ``out [K, n_out]`` of net ``kind`` of every member at ``x [K, obs]``."""
    row = np.empty((1, out.shape[1]), np.float32)
    for k in range(P.shape[1]):
        _forward(P[kind, k], x[k : k + 1], lay, geo, scratch[4], scratch[5], row)
        out[k] = row[0]
