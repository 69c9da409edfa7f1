r"""A population of K online actor-critic learners stepped together.

Every member runs the paper's online learner (Algorithm 1 of arXiv:2010.03290, with the
components of its Sec. IV-A; docs/online-learner.md) for its own config and seed. K = 1 is
a single run (:class:`pporpe.online.OnlineLearner` is that case with scalar inputs).

The step order makes the ratio measure exactly one update (as in the author's test bed):
a_{t+1} is sampled with theta_t before the update of transition t, so the ratio of
transition t+1 is pi_theta_{t+1}(u_{t+1}|s_{t+1}) / pi_theta_t(u_{t+1}|s_{t+1}).

One step, for every active member at once:

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
4. traces, td-AmsProp and the t-soft target update (:mod:`pporpe.online.update`).

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

from ..advantages import regularized_advantage, td_error
from ..nn.batched import NetLayout, backward_row0, forward_chain
from ..nn.mlp import mlp
from ..nn.policies import ActionMap, PolicyHead, StudentTHead, make_head
from ..surrogates import surrogate_objective
from .config import ENGINES, OnlineConfig
from .noise import NoiseBank, polar_normal, polar_student_t
from .state import MemberConstants, PopulationState
from .stats import StepStats
from .torch_engine.update import (
    opt_scalars,
    trace_scalars,
    tsoft_rates,
    update_chunk,
    update_target,
)

__all__ = [
    "ENGINES", "SHARED_FIELDS", "MemberConstants", "PopulationLearner", "PopulationState",
    "StepStats",
]  # fmt: skip


SHARED_FIELDS: tuple[str, ...] = (
    "layers", "units", "layer_norm", "activation", "policy", "min_scale", "head_tensors",
    "engine",
)  # fmt: skip
"""Config fields every member must share (they fix the network shape and its head)."""


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


def _as_index(members: Sequence[int] | Tensor | np.ndarray, k: int) -> np.ndarray:
    idx = np.asarray(members.tolist() if isinstance(members, Tensor) else members, np.int64)
    idx = idx.reshape(-1)
    if idx.size and (idx.min() < 0 or idx.max() >= k or len(set(idx.tolist())) != idx.size):
        raise ValueError(f"members must be distinct indices in [0, {k}); got {idx.tolist()}")
    return idx


def _check_inputs(
    obs_dim: Any, configs: list[OnlineConfig], seeds: list[int], engine: str | None
) -> str:
    """The engine to use; ValueError naming a bad obs_dim, engine or seed count."""
    if engine is None:  # the members' own choice (they share it: SHARED_FIELDS)
        engine = getattr(next(iter(configs), None), "engine", "fused")
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {list(ENGINES)}; got engine={engine!r}")
    if not (isinstance(obs_dim, int) and obs_dim >= 1):
        raise ValueError(f"obs_dim must be an int >= 1; got obs_dim={obs_dim!r}")
    if not configs or len(configs) != len(seeds):
        raise ValueError(
            f"need as many seeds as configs (>= 1); got {len(configs)} and {len(seeds)}"
        )
    return str(engine)


def _update_functions(compile_update: bool) -> tuple[Callable[..., Tensor], Callable[..., None]]:
    """The elementwise update and the target update, compiled or eager."""
    if not compile_update:
        return update_chunk, update_target
    # one compiled update per population shape; a long-lived worker meets several shapes,
    # and past dynamo's default limit (8) it would fall back to eager
    torch._dynamo.config.cache_size_limit = max(torch._dynamo.config.cache_size_limit, 64)
    return torch.compile(update_chunk, dynamic=False), torch.compile(update_target, dynamic=False)


class PopulationLearner:
    """K online learners with stacked parameters (see the module docstring).

    Args:
        obs_dim: observation size.
        action_low, action_high: bounds of the (shared) action box.
        configs: one :class:`OnlineConfig` per member; they must agree on
            :data:`SHARED_FIELDS` (``compile`` is ignored).
        seeds: one seed per member: its initial parameters equal OnlineLearner's after
            ``torch.manual_seed(seed)``; its sampling stream is a generator seeded with it.
        compile_update: compile the elementwise update with ``torch.compile``.
        noise_block: steps of noise drawn at once per member.
        cache_bytes: working-set target of one block of the elementwise update.
        engine: None (the members' ``OnlineConfig.engine``), ``"torch"`` (the reference:
            batched torch operations, the elementwise update compiled with
            ``torch.compile`` if ``compile_update``) or ``"fused"`` (one numba kernel per
            step, :mod:`pporpe.online.fused`; ``compile_update`` and ``cache_bytes`` are
            ignored). The two agree to float rounding.
    """

    def __init__(
        self,
        obs_dim: int,
        action_low: Any,
        action_high: Any,
        configs: Sequence[OnlineConfig],
        seeds: Sequence[int],
        compile_update: bool = True,
        noise_block: int = 1024,
        cache_bytes: int = 4 * 2**20,
        engine: str | None = None,
    ) -> None:
        configs, seeds = list(configs), list(seeds)
        engine = _check_inputs(obs_dim, configs, seeds, engine)
        self.engine = engine
        self.shape_config = configs[0]
        for cfg in configs:
            self._check_shape(cfg)
        self.K = K = len(configs)
        self.obs_dim = obs_dim
        self.action_map = ActionMap(
            torch.as_tensor(np.asarray(action_low), dtype=torch.float32),
            torch.as_tensor(np.asarray(action_high), dtype=torch.float32),
        )
        self.act_dim = self.action_map.act_dim
        c0 = configs[0]
        self.head: PolicyHead = make_head(c0.policy, self.act_dim, min_scale=c0.min_scale)
        self.activation = c0.activation
        parts = self.head.parts() if c0.head_tensors == "per_output" else None
        self.lay = lay = NetLayout(
            obs_dim, self.head.raw_dim, c0.layers, c0.units, c0.layer_norm, head_parts=parts
        )
        self.state = PopulationState.zeros(K, lay, self.act_dim)
        """What changes while the members learn (:class:`PopulationState`)."""
        self.consts = MemberConstants.zeros(K, lay)
        """What each member's config fixes (:class:`MemberConstants`)."""
        self.noise = NoiseBank(K, self.act_dim, noise_block)
        self.configs: list[OnlineConfig] = list(configs)
        self._groups: list[tuple[tuple[Any, ...], Tensor]] = []
        self._fused: Any = None
        if engine == "fused":
            from .fused_engine import FusedEngine, warm_up

            warm_up()
            self._fused = FusedEngine(self)
            compile_update = False
        self._upd, self._tgt = _update_functions(compile_update)
        self._make_blocks(cache_bytes)
        for k, (cfg, seed) in enumerate(zip(configs, seeds, strict=True)):
            self.reset_member(k, cfg, seed)

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
    def _check_shape(self, cfg: OnlineConfig) -> None:
        if not isinstance(cfg, OnlineConfig):
            raise TypeError(f"configs must be OnlineConfig instances; got {cfg!r}")
        for name in SHARED_FIELDS:
            a, b = getattr(cfg, name), getattr(self.shape_config, name)
            if a != b:
                raise ValueError(
                    f"all members must share the network shape: field {name!r} differs "
                    f"({a!r} vs {b!r})"
                )

    def _set_config(self, k: int, cfg: OnlineConfig) -> None:
        """Write member k's constants (everything but its state)."""
        self._check_shape(cfg)
        self.configs[k] = cfg
        self.consts.write(k, cfg, self.lay)
        if self._fused is not None:
            self._fused.set_constants(self, k, cfg)
        groups: dict[tuple[Any, ...], list[int]] = {}
        for i, cf in enumerate(self.configs):
            key = (cf.method, cf.eps, cf.beta, cf.eta, cf.rpe_form)
            groups.setdefault(key, []).append(i)
        masks = []
        for key, ix in groups.items():
            mask = torch.zeros(self.K, dtype=torch.bool)
            mask[ix] = True
            masks.append((key, mask))
        self._groups = masks

    def reset_member(self, k: int, config: OnlineConfig, seed: int) -> None:
        """(Re)initialise slot k as a fresh run of ``config`` and ``seed``.

        Parameters as OnlineLearner builds them after ``torch.manual_seed(seed)`` (the
        global RNG is left untouched), zero optimiser state and traces, fresh t-soft
        scalars, the noise stream restarted from ``seed``, no pending transition.
        """
        self._set_config(k, config)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            kw = {
                "layers": config.layers,
                "units": config.units,
                "layer_norm": config.layer_norm,
                "activation": config.activation,
            }
            pol = mlp(self.obs_dim, self.head.raw_dim, **kw)  # type: ignore[arg-type]
            val = mlp(self.obs_dim, 1, **kw)  # type: ignore[arg-type]
        R, U = self.lay.n_rows, self.lay.units
        with torch.no_grad():
            params = self.state.params
            params[0, k] = self.lay.pack(list(pol.parameters()), 0).view(R, U)
            params[1, k] = self.lay.pack(list(val.parameters()), 1).view(R, U)
            params[2, k] = params[1, k]
        self.state.reset_member(k, config)
        self.noise.reset(k, seed)

    # -- parameters -------------------------------------------------------------------
    def member_theta(self, k: int) -> Tensor:
        """Member k's flat parameters in OnlineLearner.theta's layout (a new tensor)."""
        flat = self.state.params[:2, k].reshape(2, -1)
        pi, vi = self.lay.real_index
        return torch.cat([flat[0, pi], flat[1, vi]])

    @torch.no_grad()
    def set_member_theta(self, k: int, theta: Tensor) -> None:
        """Set member k's parameters (and its target to their value block) from a flat
        vector in :meth:`member_theta`'s layout."""
        pi, vi = self.lay.real_index
        if theta.numel() != len(pi) + len(vi):
            raise ValueError(f"theta must have {len(pi) + len(vi)} elements; got {theta.numel()}")
        flat = self.state.params[:, k].reshape(3, -1)
        flat[0, pi] = theta[: len(pi)]
        flat[1, vi] = theta[len(pi) :]
        flat[2, vi] = theta[len(pi) :]
        self.state.params[:, k] = flat.view_as(self.state.params[:, k])

    def member_target(self, k: int) -> Tensor:
        """Member k's target value network in OnlineLearner.target's layout."""
        return self.state.params[2, k].reshape(-1)[self.lay.real_index[1]]

    def finite(self) -> Tensor:
        """``[K]`` bool: all of the member's parameters and target are finite."""
        return torch.isfinite(self.state.params).flatten(2).all(-1).all(0)

    # -- acting ---------------------------------------------------------------------------
    def _sample(self, raw: Tensor, pts: Tensor) -> Tensor:
        """``u = loc + scale * T`` with T from the unit-disk points (head's distribution)."""
        if isinstance(self.head, StudentTHead):
            loc, scale, df = self.head.split(raw)
            t = polar_student_t(pts, df.to(torch.float64))
        else:
            loc, scale = self.head.split(raw)
            t = polar_normal(pts)
        return loc + scale * t.to(loc.dtype)

    def _flat(self, n_kinds: int) -> Tensor:
        return self.state.params[:n_kinds].view(n_kinds * self.K, self.lay.n_pad)

    @torch.no_grad()
    def act_deterministic(self, obs: np.ndarray) -> np.ndarray:
        """Test-time actions ``[K, act_dim]``: each member's location mapped into the bounds."""
        if self._fused is not None:
            obs2 = np.asarray(obs, np.float32).reshape(self.K, self.obs_dim)
            raw_np = self._fused.forward(0, obs2, self.lay.raw_dim)
            return self.action_map.to_action(self.head.location(torch.from_numpy(raw_np))).numpy()
        x = torch.as_tensor(np.asarray(obs, np.float32)).reshape(self.K, 1, self.obs_dim)
        raw, _ = forward_chain(self._flat(1), x, self.lay, self.activation)
        return self.action_map.to_action(self.head.location(raw[:, 0])).numpy()

    @torch.no_grad()
    def policy_raw(self, k: int, x: Tensor) -> Tensor:
        """Member ``k``'s policy output ``[N, raw_dim]`` for observations ``[N, obs_dim]``."""
        flat = self.state.params[0, k].view(1, self.lay.n_pad)
        raw, _ = forward_chain(flat, x.reshape(1, -1, self.obs_dim), self.lay, self.activation)
        return raw[0]

    @torch.no_grad()
    def value(self, obs: np.ndarray) -> np.ndarray:
        """V(s) of every member's online value network, ``[K]``."""
        if self._fused is not None:
            obs2 = np.asarray(obs, np.float32).reshape(self.K, self.obs_dim)
            return self._fused.forward(1, obs2, 1)[:, 0]
        x = torch.as_tensor(np.asarray(obs, np.float32)).reshape(self.K, 1, self.obs_dim)
        values = self.state.params[1].view(self.K, self.lay.n_pad)
        out, _ = forward_chain(values, x, self.lay, self.activation)
        return out[:, 0, 0].numpy()

    @torch.no_grad()
    def begin_episode(
        self,
        members: Sequence[int] | Tensor | np.ndarray,
        obs: np.ndarray,
        forced_u: Tensor | None = None,
    ) -> np.ndarray:
        """Reset these members' traces and sample their first actions ``[len, act_dim]``.

        ``forced_u`` (test hook): pre-map actions ``[len, act_dim]`` used instead of
        samples (no noise is consumed then).
        """
        idx = _as_index(members, self.K)
        ti = torch.from_numpy(idx)
        K = self.K
        if self._fused is not None:
            return self._begin_fused(idx, ti, obs, forced_u)
        x = self.state.pending.obs.clone()
        x[ti] = torch.as_tensor(np.asarray(obs, np.float32)).reshape(len(idx), self.obs_dim)
        xx = x.unsqueeze(1).repeat(2, 1, 1)
        out, _ = forward_chain(self._flat(2), xx, self.lay, self.activation)
        raw, value = out[:K, 0], out[K:, 0, 0]
        if forced_u is None:
            mask = np.zeros(K, dtype=bool)
            mask[idx] = True
            u = self._sample(raw, self.noise.take(mask))[ti]
        else:
            u = torch.as_tensor(forced_u, dtype=torch.float32).reshape(len(idx), self.act_dim)
        self.state.reset_traces(ti)
        pend = self.state.pending
        pend.obs[ti], pend.u[ti] = x[ti], u
        pend.logp_b[ti], pend.value_b[ti] = self.head.log_prob(raw[ti], u), value[ti]
        pend.raw_b[ti] = raw[ti]
        pend.waiting[idx] = True
        return self.action_map.to_action(u).numpy()

    # -- learning -------------------------------------------------------------------------
    def _head_grad(
        self, raw0: Tensor, logp: Tensor, ratio: Tensor, sigma: Tensor
    ) -> tuple[Tensor, Tensor]:
        """``d/d raw0 sum_k -sigma_k obj_k(rho_k, sigma_k)`` and the surrogates' effective
        ratios rho_dagger = sigma obj(rho, sigma) (detached); for members with
        ``policy_gradient="weighted_score"`` the first term is
        ``-rho_dagger log pi`` instead (rho_dagger detached).

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

    def step(
        self,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        active: np.ndarray | None = None,
        forced_u: Tensor | None = None,
    ) -> tuple[StepStats, np.ndarray]:
        """Learn transition t of every active member; return its stats and a_{t+1} ``[K, ·]``.

        Inactive members' state stays bitwise unchanged (their rows of the inputs are
        ignored; their returned actions are meaningless). Members that terminated or
        truncated lose their pending state: call :meth:`begin_episode` for them next.
        ``forced_u`` (test hook): pre-map next actions ``[K, act_dim]`` used instead of
        samples (no noise consumed).
        """
        K = self.K
        act_np = np.ones(K, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        if not self.state.pending.waiting[act_np].all():
            missing = np.nonzero(act_np & ~self.state.pending.waiting)[0].tolist()
            raise RuntimeError(f"call begin_episode for members {missing} before step()")
        if self._fused is not None:
            return self._step_fused(reward, next_obs, terminated, truncated, act_np, forced_u)
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
            u_next = self._sample(raw1, self.noise.take(act_np))
        else:
            u_next = torch.as_tensor(forced_u, dtype=torch.float32).reshape(K, self.act_dim)
        self._update(sig.adv, delta, divergence, act_np)
        stats = StepStats(delta, sig.adv, sig.ratio, divergence, self.state.decay.clone())
        self._advance_pending(nxt, u_next, fwd, act_np & ~(term_np | trunc_np), act_np)
        return stats, self.action_map.to_action(u_next).numpy()

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
        """delta; no bootstrap past a termination, nor past a time limit for members
        with ``time_limit="terminal"``."""
        co = self.consts
        ends = torch.from_numpy(term_np.copy()) | (
            torch.from_numpy(trunc_np.copy()) & co.limit_terminal
        )
        bootstrap = torch.where(ends, 0.0, co.gamma)
        return td_error(rew * co.reward_scale, fwd.next_target, fwd.values[:, 0], bootstrap)

    def _policy_signal(self, fwd: _Forward, delta: Tensor) -> _PolicySignal:
        """The regularised advantage, the ratio and the head's gradient at s_t."""
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
        """The divergence of this step that drives the adaptive trace decay."""
        pend, v = self.state.pending, fwd.values[:, 0]
        divergence = (sig.ratio - 1.0 - sig.log_ratio) + (v - pend.value_b) ** 2
        if self.consts.kl_analytic.any():
            kl = torch.relu(self.head.kl(fwd.raw[:, 0], pend.raw_b))
            analytic = kl + 0.5 * (v - pend.value_b) ** 2
            divergence = torch.where(self.consts.kl_analytic, analytic, divergence)
        return divergence

    def _backward(self, fwd: _Forward, sig: _PolicySignal) -> None:
        """The per-unit-signal gradient of row s_t into ``state.grad`` (hand backward)."""
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
        """Traces, td-AmsProp (in cache-sized blocks of members) and the t-soft target."""
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

    # -- the fused engine ---------------------------------------------------------------
    def _begin_fused(
        self, idx: np.ndarray, ti: Tensor, obs: np.ndarray, forced_u: Tensor | None
    ) -> np.ndarray:
        """begin_episode of the fused engine (the same rules, one kernel call)."""
        x = np.asarray(obs, np.float32).reshape(len(idx), self.obs_dim)
        pts = None
        if forced_u is None:
            mask = np.zeros(self.K, dtype=bool)
            mask[idx] = True
            pts = self.noise.take(mask).numpy()
        forced = None if forced_u is None else np.asarray(forced_u, np.float32)
        self.state.reset_traces(ti)
        return self._fused.begin(idx, x, self._no_points() if pts is None else pts, forced)

    def _no_points(self) -> np.ndarray:
        return np.full((self.K, self.act_dim, 2), 0.5)

    def _step_fused(
        self,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        act_np: np.ndarray,
        forced_u: Tensor | None,
    ) -> tuple[StepStats, np.ndarray]:
        """step() of the fused engine: noise drawn here, everything else in the kernel."""
        K = self.K
        pts = self._no_points() if forced_u is not None else self.noise.take(act_np).numpy()
        forced = None if forced_u is None else np.asarray(forced_u, np.float32).reshape(K, -1)
        stats, actions = self._fused.step(
            np.asarray(reward, np.float32).reshape(K),
            np.asarray(next_obs, np.float32).reshape(K, self.obs_dim),
            np.asarray(terminated, dtype=bool).reshape(K),
            np.asarray(truncated, dtype=bool).reshape(K),
            act_np,
            pts,
            forced,
        )
        s = torch.from_numpy(stats)
        return StepStats(s[0], s[1], s[2], s[3], s[4]), actions

    # -- state ----------------------------------------------------------------------------
    def member_state(self, k: int) -> dict[str, Any]:
        """Everything needed to continue member k (cloned tensors): its slice of
        :attr:`state` (:meth:`PopulationState.member`, the pending transition included, so
        a member can be continued mid-episode too) and its noise stream (``"rng"``)."""
        return {**self.state.member(k), "rng": self.noise.state(k)}

    def load_member_state(self, k: int, config: OnlineConfig, state: dict[str, Any]) -> None:
        """Restore :meth:`member_state` into slot k with ``config`` (and its pending step).

        Continues the member bitwise when the packing (K, slot) is the same, up to
        rounding otherwise. Older checkpoints' extra entries (a flat ``theta``) are
        ignored."""
        self._set_config(k, config)
        self.state.load_member(k, state, needs_raw_b=config.trace_divergence == "analytic")
        self.noise.load(k, state["rng"])

    def state_dict(self) -> dict[str, Any]:
        """The whole population: :meth:`PopulationState.state_dict` and the noise streams."""
        return {"state": self.state.state_dict(),
                "rng": [self.noise.state(k) for k in range(self.K)]}  # fmt: skip

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` into a population built with the same configs."""
        if len(state["rng"]) != self.K:
            raise ValueError(f"state_dict holds {len(state['rng'])} members; this has {self.K}")
        self.state.load_state_dict(state["state"])
        for k, rng in enumerate(state["rng"]):
            self.noise.load(k, rng)
