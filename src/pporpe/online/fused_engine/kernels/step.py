"""One step of every member, the fused kernel's entry points: :func:`fused_step`,
:func:`fused_begin` and :func:`fused_forward`, on the learner's own buffers.

Everything between "transition in" and "next action out" runs in :func:`fused_step`, a
loop over the members of nopython code on the learner's stacked float32 buffers (numpy
views of its torch tensors, shared without copies): the forward of the policy, value and
target networks (:mod:`.network`), the signals of the step with the head and surrogate in
closed form (:mod:`.head`, :mod:`.surrogates`), the hand-written backward of row s_t,
the traces, td-AmsProp, t-soft (:mod:`.optimiser`) and the pending-state update. Noise
is drawn by :class:`~pporpe.online.noise.NoiseBank` in Python and passed in as unit-disk
points.
"""

from __future__ import annotations

import math

import numpy as np

from .head import head_grad_closed, kl_closed, log_abs_det_jacobian, sample_pre_map, to_action
from .inputs import (
    C_BETA,
    C_BETA2_F32,
    C_BETA_DE,
    C_BETA_TD,
    C_EPS,
    C_ETA,
    C_GAMMA,
    C_OMB_MOM,
    C_ONE_M_BETA2,
    C_ONE_M_GAMMA,
    C_OPT_EPS,
    C_REWARD_SCALE,
    C_TD_SCALE,
    C_W_COEF,
    F_AMS_RAW,
    F_CRITIC_ACTOR,
    F_KAPPA_POS,
    F_KL_ANALYTIC,
    F_LIMIT_TERMINAL,
    F_LN_FROZEN,
    F_METHOD,
    F_MOM_ONLY,
    F_POLYAK,
    F_PRE_SQUASH,
    F_WEIGHTED,
    G_ACT_DIM,
    G_HEAD,
    G_OBS,
    G_RAW,
)
from .jit import scalar_jit
from .network import backward_row0, forward_net
from .optimiser import opt_scalars, trace_scalars, tsoft_rate, update_net, update_target
from .surrogates import surrogate_closed

__all__ = ["fused_begin", "fused_forward", "fused_step"]


@scalar_jit
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
    """The TD error delta, the regularised advantage A, the density ratio rho, the trace
    divergence and rho_dagger of member k; the head's signal ``d(-sigma obj)/d raw``,
    the policy gradient of eq. (3) (``grad_reg``), into ``d_raw`` (float32)."""
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
    ent = logp if fl[F_PRE_SQUASH] != 0 else logp - log_abs_det_jacobian(u_b[k], bounds)
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
        kl = kl_closed(raw0, raw_b[k], geo[G_HEAD], d, hf[0])
        div = (kl if not kl < 0.0 else 0.0) + 0.5 * dv * dv
    else:
        div = (ratio - 1.0 - log_ratio) + dv * dv
    return delta, adv, ratio, div, rho_dagger


@scalar_jit
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
    """Backward, traces, td-AmsProp, t-soft and the target of member k (in place); the
    value block's signal and weight follow ``critic_signal`` (flag ``F_CRITIC_ACTOR``)."""
    e, r, v, vm, m, W, num, den = opt
    g, diff, cache, rstd = scratch[0], scratch[1], scratch[2], scratch[3]
    d_raw, delta, adv, div, rho_dagger = sig
    c1, c2 = trace_scalars(k, np.float32(div), cf, fl[F_KAPPA_POS] != 0, sc)
    steps = sc[4]
    steps[k] += 1
    vfac, sbc2, step = opt_scalars(steps[k], cf, fl[F_AMS_RAW] != 0)
    frozen = fl[F_LN_FROZEN] != 0
    backward_row0(P[0, k], g[0], d_raw, lay, geo, cache[0], rstd[0], frozen)
    dv = np.empty(1, np.float32)
    dv[0] = -rho_dagger if fl[F_CRITIC_ACTOR] != 0 else -1.0
    backward_row0(P[1, k], g[1], dv, lay, geo, cache[1], rstd[1], frozen)
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
        d2 = update_net(buf, seg, consts, fl[F_MOM_ONLY] != 0, tgt, diff)
    rate = tsoft_rate(k, d2, hf[1], cf, fl[F_POLYAK] != 0, sc)
    update_target(P[2, k], P[1, k], rate)


@scalar_jit
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
    forward_net(P[0, k], x, lay, geo, cache[0], rstd[0], pol)
    forward_net(P[1, k], x, lay, geo, cache[1], rstd[1], val)
    forward_net(P[2, k], x[1:], lay, geo, scratch[4], scratch[5], tg)
    vals = np.array([val[0, 0], val[1, 0], tg[0, 0]])
    d_raw = np.empty(raw_dim, np.float32)
    delta, adv, ratio, div, rho_dagger = _signals(
        k, pol[0], vals, pend, inp, cf[k], fl[k], geo, hf, bounds, d_raw
    )
    u_next = np.empty(d, np.float32)
    if use_forced:
        u_next[:] = forced[k]
    else:
        sample_pre_map(pol[1], pts[k], geo, hf[0], u_next)
    grad = np.empty(raw_dim)
    logp_next = head_grad_closed(pol[1], u_next, geo[G_HEAD], d, hf[0], grad)
    if active[k]:
        sig = (d_raw, delta, adv, div, rho_dagger)
        _learn(k, P, opt, sc, cf[k], fl[k], geo, lay, seg, hf, sig, scratch)
    stats[0, k], stats[1, k], stats[2, k], stats[3, k] = delta, adv, ratio, div
    stats[4, k] = sc[1][k]
    to_action(u_next, bounds, actions[k])
    done = term[k] or trunc[k]
    if active[k] and not done:
        obs[k], u_b[k], logp_b[k] = nxt[k], u_next, logp_next
        value_b[k], raw_b[k] = val[1, 0], pol[1]
    if active[k] and done:
        pending[k] = False


@scalar_jit
def fused_step(
    P: np.ndarray, opt: tuple, sc: tuple, pend: tuple, inp: tuple, cf: np.ndarray,
    fl: np.ndarray, geo: np.ndarray, lay: np.ndarray, seg: np.ndarray, hf: np.ndarray,
    bounds: np.ndarray, out: tuple, scratch: tuple,
) -> None:  # fmt: skip
    """One step of every member (in place on the learner's buffers): Algorithm 1's step.

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


@scalar_jit
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
        forward_net(P[0, k], x[i : i + 1], lay, geo, scratch[4], scratch[5], pol)
        forward_net(P[1, k], x[i : i + 1], lay, geo, scratch[4], scratch[5], val)
        if use_forced:
            u_b[k] = forced[i]
        else:
            sample_pre_map(pol[0], pts[k], geo, hf[0], u_b[k])
        obs[k], raw_b[k], value_b[k] = x[i], pol[0], val[0, 0]
        logp_b[k] = head_grad_closed(pol[0], u_b[k], geo[G_HEAD], d, hf[0], grad)
        pending[k] = True
        to_action(u_b[k], bounds, actions[i])


@scalar_jit
def fused_forward(
    P: np.ndarray, kind: int, x: np.ndarray, geo: np.ndarray, lay: np.ndarray,
    out: np.ndarray, scratch: tuple,
) -> None:  # fmt: skip
    """Outputs ``out [K, n_out]`` of net ``kind`` of every member at ``x [K, obs]``."""
    row = np.empty((1, out.shape[1]), np.float32)
    for k in range(P.shape[1]):
        forward_net(P[kind, k], x[k : k + 1], lay, geo, scratch[4], scratch[5], row)
        out[k] = row[0]
