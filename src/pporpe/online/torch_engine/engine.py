r"""The torch engine's step: every member's step as batched torch operations, the readable
reference of the population's computation (``engine="torch"``).

One step, for every active member at once (the step order is the population's,
:mod:`pporpe.online.population`):

1. one forward pass over ``[s_t; s_{t+1}]`` of all 3K networks (policy, value, target)
   stacked in ``P [3, K, n_pad]`` (:mod:`pporpe.nn.batched`);
2. with ``rho = exp(log pi(u_t|s_t) - log pi_b)``, ``sigma = sign(A)`` and the author's
   choices (``AUTHOR_CHOICES``; the alternatives in brackets, ``OnlineConfig``)::

       delta = r * reward_scale + gamma [not terminated] V_target(s_{t+1}) - V(s_t)
       A     = delta - (1 - gamma)(beta_TD (delta / (1 - gamma))^2 + beta_DE log pi(u_t|s_t))
       d     = max(KL(pi || pi_b)(s_t), 0) + (V(s_t) - V_b(s_t))^2 / 2

   [``td_units="scaled"``: beta_TD delta^2; ``entropy_density="action"`` (the default):
   the density of the bounded action, the map's Jacobian included;
   ``trace_divergence="sample"``: d = (rho - 1 - log rho) + (V(s_t) - V_b(s_t))^2]. The
   per-unit-signal gradient ``g = grad[-sigma obj(rho, sigma)]`` (policy)
   ``+ grad[-V(s_t)]`` (value) is the hand-written backward of row s_t, fed with
   ``d(-sigma obj)/d raw`` from autograd on the tiny head (surrogates of
   :mod:`pporpe.surrogates`, grouped by unique surrogate settings). The value block's
   signal is ``A rho_dagger`` with ``rho_dagger = sigma obj(rho, sigma)``
   (``critic_signal="actor"``) [``"td"``, the default: delta];
3. ``u_{t+1}`` is sampled from the row s_{t+1} with theta_t (before the update), from
   the member's own noise stream (:mod:`pporpe.online.noise`);
4. traces, td-AmsProp and the t-soft target update (:mod:`.update`).

A member's numbers depend only on (config, seed, its data): every operation is batched
per member; packing (K, slot) changes results only by float rounding.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...advantages import regularized_advantage, td_error
from ...nn.batched import backward_row0, forward_chain
from ...nn.policies import PolicyHead, StudentTHead
from ...surrogates import surrogate_objective
from ..config import OnlineConfig
from ..engine import PopulationParts
from ..noise import polar_normal, polar_student_t
from ..stats import StepStats
from .update import (
    opt_scalars,
    trace_scalars,
    tsoft_rates,
    update_chunk,
    update_target,
)

__all__ = ["TorchEngine", "sample_pre_map"]


@dataclass(frozen=True)
class _Forward:
    """One step's forward pass: rows s_t (index 0) and s_{t+1} (index 1)."""

    raw: Tensor
    """``[K, 2, raw_dim]`` policy outputs."""
    values: Tensor
    """``[K, 2]`` V(s_t), V(s_{t+1}) of the online value network."""
    next_target: Tensor
    """``[K]`` the target network's V(s_{t+1})."""
    cache: Any
    """What the hand backward needs of the forward pass."""


@dataclass(frozen=True)
class _PolicySignal:
    """The policy's side of one step at s_t."""

    adv: Tensor
    """``[K]`` the regularised advantage A."""
    ratio: Tensor
    """``[K]`` rho = pi(u_t | s_t) / pi_b(u_t | s_t)."""
    log_ratio: Tensor
    """``[K]`` log rho."""
    d_raw: Tensor
    """``[K, raw_dim]`` d(-sigma obj) / d raw (or the weighted score's)."""
    rho_dagger: Tensor
    """``[K]`` the surrogate's effective ratio sigma obj(rho, sigma), detached."""


def _update_functions(compile_update: bool) -> tuple[Callable[..., Tensor], Callable[..., None]]:
    """The elementwise update and the target update, compiled or eager."""
    if not compile_update:
        return update_chunk, update_target
    # one compiled update per population shape; a long-lived worker meets several shapes,
    # and past dynamo's default limit (8) it would fall back to eager
    torch._dynamo.config.cache_size_limit = max(torch._dynamo.config.cache_size_limit, 64)
    return torch.compile(update_chunk, dynamic=False), torch.compile(update_target, dynamic=False)


def sample_pre_map(head: PolicyHead, raw: Tensor, pts: Tensor) -> Tensor:
    """``u = loc + scale * T`` with T from the unit-disk points (the head's distribution)."""
    if isinstance(head, StudentTHead):
        loc, scale, df = head.split(raw)
        t = polar_student_t(pts, df.to(torch.float64))
    else:
        loc, scale = head.split(raw)
        t = polar_normal(pts)
    return loc + scale * t.to(loc.dtype)


def _surrogate_key(cfg: OnlineConfig) -> tuple[Any, ...]:
    """The settings that pick a member's surrogate objective."""
    return (cfg.method, cfg.eps, cfg.beta, cfg.eta, cfg.rpe_form)


class TorchEngine:
    """The torch engine of a population's :class:`~pporpe.online.engine.PopulationParts`
    (an :class:`~pporpe.online.engine.Engine`; see the module docstring).

    Args:
        parts: the population's parts, computed on in place.
        configs: the members' configs (their surrogate settings; :meth:`set_member`
            follows later changes).
        compile_update: compile the elementwise update with ``torch.compile``.
        cache_bytes: working-set target of one block of the elementwise update.
    """

    def __init__(
        self,
        parts: PopulationParts,
        configs: Sequence[OnlineConfig],
        compile_update: bool,
        cache_bytes: int,
    ) -> None:
        self.parts = parts
        self.K, self.obs_dim, self.act_dim = parts.K, parts.obs_dim, parts.act_dim
        self.lay, self.head, self.activation = parts.lay, parts.head, parts.activation
        self.action_map, self.noise = parts.action_map, parts.noise
        self.state, self.consts = parts.state, parts.consts
        self._surrogates = [_surrogate_key(cfg) for cfg in configs]
        self._groups: list[tuple[tuple[Any, ...], Tensor]] = []
        self._upd, self._tgt = _update_functions(compile_update)
        self._make_blocks(cache_bytes)

    def _make_blocks(self, cache_bytes: int) -> None:
        """Members are updated in blocks whose state (~10 parameter-sized vectors) fits in
        about ``cache_bytes`` of cache; every block but the last has the same shape."""
        K, st, co = self.K, self.state, self.consts
        per_member = 10 * 2 * self.lay.n_pad * 4
        size = max(1, min(K, cache_bytes // per_member))
        self._blocks = [(a, min(a + size, K)) for a in range(0, K, size)]
        buffers = (st.params, st.grad, st.trace_e, st.trace_r, st.opt_v, st.opt_vmax, st.opt_m,
                   st.opt_weight)  # fmt: skip
        self._block_state = [tuple(buf[:, a:b] for buf in buffers) for a, b in self._blocks]
        self._block_consts = [(co.seg_num[:, a:b], co.seg_den[:, a:b]) for a, b in self._blocks]

    # -- configuration -------------------------------------------------------------------
    def set_member(self, k: int, config: OnlineConfig) -> None:
        """Member k's surrogate settings: the members are grouped by them again."""
        self._surrogates[k] = _surrogate_key(config)
        groups: dict[tuple[Any, ...], list[int]] = {}
        for i, key in enumerate(self._surrogates):
            groups.setdefault(key, []).append(i)
        masks = []
        for key, ix in groups.items():
            mask = torch.zeros(self.K, dtype=torch.bool)
            mask[ix] = True
            masks.append((key, mask))
        self._groups = masks

    def _flat(self, n_kinds: int) -> Tensor:
        return self.parts.flat(n_kinds)

    # -- acting ---------------------------------------------------------------------------
    def begin(self, idx: np.ndarray, obs: np.ndarray, forced_u: Tensor | None) -> np.ndarray:
        """First actions of members ``idx``, their traces reset, their pending transitions
        set (:class:`~pporpe.online.engine.Engine`)."""
        ti = torch.from_numpy(idx)
        K = self.K
        x = self.state.pending.obs.clone()
        x[ti] = torch.as_tensor(np.asarray(obs, np.float32)).reshape(len(idx), self.obs_dim)
        xx = x.unsqueeze(1).repeat(2, 1, 1)
        out, _ = forward_chain(self._flat(2), xx, self.lay, self.activation)
        raw, value = out[:K, 0], out[K:, 0, 0]
        if forced_u is None:
            mask = np.zeros(K, dtype=bool)
            mask[idx] = True
            u = sample_pre_map(self.head, raw, self.noise.take(mask))[ti]
        else:
            u = torch.as_tensor(forced_u, dtype=torch.float32).reshape(len(idx), self.act_dim)
        self.state.reset_traces(ti)
        pend = self.state.pending
        pend.obs[ti], pend.u[ti] = x[ti], u
        pend.logp_b[ti], pend.value_b[ti] = self.head.log_prob(raw[ti], u), value[ti]
        pend.raw_b[ti] = raw[ti]
        pend.waiting[idx] = True
        return self.action_map.to_action(u).numpy()

    def outputs(self, kind: int, obs: np.ndarray) -> Tensor:
        """Net ``kind``'s outputs ``[K, n_out]`` at ``obs [K, obs_dim]``
        (:class:`~pporpe.online.engine.Engine`)."""
        x = torch.as_tensor(np.asarray(obs, np.float32)).reshape(self.K, 1, self.obs_dim)
        nets = self.state.params[kind].view(self.K, self.lay.n_pad)
        out, _ = forward_chain(nets, x, self.lay, self.activation)
        return out[:, 0]

    # -- learning -------------------------------------------------------------------------
    def step(
        self,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        active: np.ndarray,
        forced_u: Tensor | None,
    ) -> tuple[StepStats, np.ndarray]:
        """Learn transition t of the active members (one step of Algorithm 1); their stats
        and a_{t+1} (:class:`~pporpe.online.engine.Engine`)."""
        K, act_np = self.K, active
        term_np = np.asarray(terminated, dtype=bool).reshape(K)
        trunc_np = np.asarray(truncated, dtype=bool).reshape(K)
        rew = torch.as_tensor(np.asarray(reward, np.float32)).reshape(K)
        nxt = torch.as_tensor(np.asarray(next_obs, np.float32)).reshape(K, self.obs_dim)
        fwd = self._forward_transition(nxt)
        delta = self._td_error(rew, fwd, term_np, trunc_np)
        sig = self._policy_signal(fwd, delta)
        divergence = self._trace_divergence(fwd, sig)
        self._backward(fwd, sig)
        # a_{t+1} from theta_t, before the update (the step order of the module docstring)
        raw1 = fwd.raw[:, 1]
        if forced_u is None:
            u_next = sample_pre_map(self.head, raw1, self.noise.take(act_np))
        else:
            u_next = torch.as_tensor(forced_u, dtype=torch.float32).reshape(K, self.act_dim)
        self._update(sig.adv, delta, divergence, act_np)
        stats = StepStats(delta, sig.adv, sig.ratio, divergence, self.state.decay.clone())
        self._advance_pending(nxt, u_next, fwd, act_np & ~(term_np | trunc_np), act_np)
        return stats, self.action_map.to_action(u_next).numpy()

    def _head_grad(
        self, raw0: Tensor, logp: Tensor, ratio: Tensor, sigma: Tensor
    ) -> tuple[Tensor, Tensor]:
        """``d/d raw0 sum_k -sigma_k obj_k(rho_k, sigma_k)`` and the surrogates' effective
        ratios rho_dagger = sigma obj(rho, sigma) (detached); for members with
        ``policy_gradient="weighted_score"`` the first term is
        ``-rho_dagger log pi`` instead (rho_dagger detached).

        By autograd: the policy gradient of eq. (3) (``grad_reg``) at s_t, whose weight
        d obj/d rho is, for PPO-RPE, A~ of eq. (12) (``grad_rpe``), the derivative of
        eq. (11) with C held constant (or eq. (16) where ``rpe_form="printed"``).

        Each distinct surrogate setting is evaluated on all K members and selected by
        mask, so a member's numbers never depend on which settings the other slots hold.
        """
        if len(self._groups) == 1:
            (method, eps, beta, eta, form), _ = self._groups[0]
            obj = surrogate_objective(method, ratio, sigma, eps, beta, eta, form)
        else:
            obj = torch.zeros_like(ratio)
            for (method, eps, beta, eta, form), mask in self._groups:
                value = surrogate_objective(method, ratio, sigma, eps, beta, eta, form)
                obj = torch.where(mask, value, obj)
        rho_dagger = (sigma * obj).detach()
        loss = torch.where(self.consts.weighted_score, -rho_dagger * logp, -sigma * obj)
        (grad,) = torch.autograd.grad(loss.sum(), raw0)
        return grad, rho_dagger

    def _forward_transition(self, nxt: Tensor) -> _Forward:
        """One forward pass of the 3K networks over ``[s_t; s_{t+1}]``."""
        K = self.K
        x = torch.stack([self.state.pending.obs, nxt], 1)  # [K, 2, obs]: [s_t; s_{t+1}]
        out, cache = forward_chain(
            self._flat(3), x.repeat(3, 1, 1), self.lay, self.activation, 2 * K
        )
        assert cache is not None
        return _Forward(out[:K], out[K : 2 * K, :, 0], out[2 * K :, 1, 0], cache)

    def _td_error(
        self, rew: Tensor, fwd: _Forward, term_np: np.ndarray, trunc_np: np.ndarray
    ) -> Tensor:
        """The TD error delta; no bootstrap past a termination, nor past a time limit for
        members with ``time_limit="terminal"``."""
        co = self.consts
        ends = torch.from_numpy(term_np.copy()) | (
            torch.from_numpy(trunc_np.copy()) & co.limit_terminal
        )
        bootstrap = torch.where(ends, 0.0, co.gamma)
        return td_error(rew * co.reward_scale, fwd.next_target, fwd.values[:, 0], bootstrap)

    def _policy_signal(self, fwd: _Forward, delta: Tensor) -> _PolicySignal:
        """The regularised advantage, the density ratio and the head's gradient at s_t."""
        co, pend = self.consts, self.state.pending
        raw0 = fwd.raw[:, 0].detach().requires_grad_(True)
        with torch.enable_grad():
            logp = self.head.log_prob(raw0, pend.u)
            log_ratio = logp - pend.logp_b
            ratio = torch.exp(log_ratio)
            # entropy term: the density of the bounded action a = f(u) (map Jacobian
            # included), or of u itself ("pre_squash")
            jac = self.action_map.log_abs_det_jacobian(pend.u)
            logp_entropy = logp.detach() - torch.where(co.pre_squash, 0.0, jac)
            adv = regularized_advantage(
                delta, logp_entropy, co.one_m_gamma, co.beta_td, co.beta_de, co.td_scale
            )
            sigma = torch.where(adv >= 0, 1.0, -1.0)
            d_raw, rho_dagger = self._head_grad(raw0, logp, ratio, sigma)
        return _PolicySignal(adv, ratio.detach(), log_ratio.detach(), d_raw, rho_dagger)

    def _trace_divergence(self, fwd: _Forward, sig: _PolicySignal) -> Tensor:
        """The trace divergence: the divergence of this step that drives the adaptive
        trace decay."""
        pend, v = self.state.pending, fwd.values[:, 0]
        divergence = (sig.ratio - 1.0 - sig.log_ratio) + (v - pend.value_b) ** 2
        if self.consts.kl_analytic.any():
            kl = torch.relu(self.head.kl(fwd.raw[:, 0], pend.raw_b))
            analytic = kl + 0.5 * (v - pend.value_b) ** 2
            divergence = torch.where(self.consts.kl_analytic, analytic, divergence)
        return divergence

    def _backward(self, fwd: _Forward, sig: _PolicySignal) -> None:
        """The per-unit-signal gradient of row s_t into ``state.grad`` (hand backward); the
        value block's is that of -V, or of -rho_dagger V (``critic_signal="actor"``)."""
        K, lay = self.K, self.lay
        dout = torch.zeros(2 * K, lay.raw_dim)
        dout[:K] = sig.d_raw
        # d(-w V(s_t)) / dV: w = 1 (TD signal) or rho_dagger (the actor's weight)
        dout[K:, 0] = torch.where(self.consts.critic_actor, -sig.rho_dagger, -1.0)
        grad = self.state.grad
        backward_row0(self._flat(2), grad.view(2 * K, lay.n_pad), dout, fwd.cache, lay,
                      self.activation)  # fmt: skip
        if self.consts.ln_frozen.any():  # LayerNorm without learnt scale and shift
            grad.mul_(self.consts.norm_keep.view(1, K, lay.n_rows, 1))

    def _update(self, adv: Tensor, delta: Tensor, divergence: Tensor, act_np: np.ndarray) -> None:
        """Traces, td-AmsProp (in cache-sized blocks of members) and the t-soft target;
        the optimiser's signal is A on the policy block and, on the value block, delta
        or A (``critic_signal="actor"``)."""
        st, co, lay = self.state, self.consts, self.lay
        act = torch.from_numpy(act_np.copy())
        c1, c2 = trace_scalars(
            st.trace_divergence, st.decay, divergence, co.neg_kappa, co.kappa_pos, co.gl1,
            co.gl2, act,
        )  # fmt: skip
        st.steps[:] += act_np.astype(np.int64)
        vfac, sqrt_bc2, step = opt_scalars(st.steps, co.beta1, co.beta2, co.lr, co.ams_decay,
                                           co.ams_raw)  # fmt: skip
        # A on the policy block; delta (or A, with the actor's weight) on the value block
        signal = torch.stack([adv, torch.where(co.critic_actor, adv, delta)])
        per_member = (c1, c2, co.beta2_f32, co.one_m_beta2, vfac, sqrt_bc2, co.opt_eps,
                      co.mom_only, co.omb_mom, co.w_coef)  # fmt: skip
        d2s = []
        for (a, b), state, (num, den) in zip(
            self._blocks, self._block_state, self._block_consts, strict=True
        ):
            pm = [x[a:b] for x in per_member]
            d2s.append(self._upd(*state, signal[:, a:b], *pm, num, den, step[a:b], act[a:b],
                                 lay.row_seg, lay.col_seg, lay.bias_row))  # fmt: skip
        d2 = d2s[0] if len(d2s) == 1 else torch.cat(d2s)
        rate = tsoft_rates(
            d2, float(lay.n_real[1]), st.tsoft_weight, st.tsoft_sigma2, co.tau, co.nu,
            co.polyak, co.sigma2_min, act,
        )  # fmt: skip
        self._tgt(st.params, rate, act)

    def _advance_pending(
        self, nxt: Tensor, u_next: Tensor, fwd: _Forward, cont_np: np.ndarray, act_np: np.ndarray
    ) -> None:
        """Members that go on hold (s_{t+1}, u_{t+1}) as their pending transition, with
        theta_t's numbers at s_{t+1} as pi_b's; members that ended hold nothing."""
        pend, K = self.state.pending, self.K
        cont = torch.from_numpy(cont_np)
        raw1 = fwd.raw[:, 1].detach()
        logp_b_next = self.head.log_prob(raw1, u_next)
        pend.obs.copy_(torch.where(cont.view(K, 1), nxt, pend.obs))
        pend.u.copy_(torch.where(cont.view(K, 1), u_next, pend.u))
        pend.logp_b.copy_(torch.where(cont, logp_b_next, pend.logp_b))
        pend.value_b.copy_(torch.where(cont, fwd.values[:, 1], pend.value_b))
        pend.raw_b.copy_(torch.where(cont.view(K, 1), raw1, pend.raw_b))
        pend.waiting[:] &= cont_np | ~act_np
