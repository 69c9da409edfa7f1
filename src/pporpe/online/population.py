r"""A population of K online actor-critic learners stepped together: its members, and the
engine that computes their steps.

Every member runs the paper's online learner (Algorithm 1 of arXiv:2010.03290, with the
components of its Sec. IV-A; docs/online-learner.md) for its own config and seed. K = 1 is
a single run (:class:`pporpe.online.OnlineLearner` is that case with scalar inputs).

The step order makes the ratio measure exactly one update (as in the author's test bed):
a_{t+1} is sampled with theta_t before the update of transition t, so the ratio of
transition t+1 is pi_theta_{t+1}(u_{t+1}|s_{t+1}) / pi_theta_t(u_{t+1}|s_{t+1}).

The population checks its inputs, sets its members up and keeps their checkpoints; an
engine (:class:`~pporpe.online.engine.Engine`) computes their steps on the population's
buffers (:class:`~pporpe.online.engine.PopulationParts`): ``engine="torch"``, the
reference (:mod:`pporpe.online.torch_engine`, whose step is written out in
:mod:`pporpe.online.torch_engine.engine`), or ``engine="fused"``, one numba kernel per
step (:mod:`pporpe.online.fused_engine`). The two agree to float rounding.

A member's numbers depend only on (config, seed, its data): every operation is batched
per member; packing (K, slot) changes results only by float rounding.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..nn.batched import forward_chain
from .config import ENGINES, OnlineConfig
from .engine import Engine, PopulationParts
from .state import MemberConstants, PopulationState
from .stats import StepStats
from .torch_engine.engine import TorchEngine, sample_pre_map

__all__ = [
    "ENGINES", "SHARED_FIELDS", "MemberConstants", "PopulationLearner", "PopulationState",
    "StepStats",
]  # fmt: skip


SHARED_FIELDS: tuple[str, ...] = (
    "layers", "units", "layer_norm", "activation", "policy", "min_scale", "head_tensors",
    "engine",
)  # fmt: skip
"""Config fields every member must share (they fix the network shape and its head)."""


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
            ``torch.compile`` if ``compile_update``, :mod:`pporpe.online.torch_engine`) or
            ``"fused"`` (one numba kernel per step, :mod:`pporpe.online.fused_engine`;
            ``compile_update`` and ``cache_bytes`` are ignored). The two agree to float
            rounding.
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
        self.parts = parts = PopulationParts.build(
            obs_dim, action_low, action_high, configs[0], K, noise_block
        )
        """The shapes, head, buffers and noise streams the engine computes on."""
        self.action_map, self.act_dim = parts.action_map, parts.act_dim
        self.head, self.activation, self.lay = parts.head, parts.activation, parts.lay
        self.state = parts.state
        """What changes while the members learn (:class:`PopulationState`)."""
        self.consts = parts.consts
        """What each member's config fixes (:class:`MemberConstants`)."""
        self.noise = parts.noise
        self.configs: list[OnlineConfig] = list(configs)
        self._engine = self._make_engine(engine, compile_update, cache_bytes)
        for k, (cfg, seed) in enumerate(zip(configs, seeds, strict=True)):
            self.reset_member(k, cfg, seed)

    def _make_engine(self, engine: str, compile_update: bool, cache_bytes: int) -> Engine:
        """The engine named ``engine`` on this population's parts."""
        if engine == "fused":
            from .fused_engine import FusedEngine, warm_up  # numba: only where it is used

            warm_up()
            return FusedEngine(self.parts)
        return TorchEngine(self.parts, self.configs, compile_update, cache_bytes)

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
        self._engine.set_member(k, cfg)

    def reset_member(self, k: int, config: OnlineConfig, seed: int) -> None:
        """(Re)initialise slot k as a fresh run of ``config`` and ``seed``.

        Parameters as OnlineLearner builds them after ``torch.manual_seed(seed)`` (the
        global RNG is left untouched), zero optimiser state and traces, fresh t-soft
        scalars, the noise stream restarted from ``seed``, no pending transition.
        """
        self._set_config(k, config)
        self.parts.init_member(k, config, seed)

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
        return sample_pre_map(self.head, raw, pts)

    def _flat(self, n_kinds: int) -> Tensor:
        return self.parts.flat(n_kinds)

    @torch.no_grad()
    def act_deterministic(self, obs: np.ndarray) -> np.ndarray:
        """Test-time actions ``[K, act_dim]``: each member's location mapped into the bounds."""
        raw = self._engine.outputs(0, obs)
        return self.action_map.to_action(self.head.location(raw)).numpy()

    @torch.no_grad()
    def policy_raw(self, k: int, x: Tensor) -> Tensor:
        """Member ``k``'s policy output ``[N, raw_dim]`` for observations ``[N, obs_dim]``."""
        flat = self.state.params[0, k].view(1, self.lay.n_pad)
        raw, _ = forward_chain(flat, x.reshape(1, -1, self.obs_dim), self.lay, self.activation)
        return raw[0]

    @torch.no_grad()
    def value(self, obs: np.ndarray) -> np.ndarray:
        """V(s) of every member's online value network, ``[K]``."""
        return self._engine.outputs(1, obs)[:, 0].numpy()

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
        return self._engine.begin(_as_index(members, self.K), obs, forced_u)

    # -- learning -------------------------------------------------------------------------
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
        return self._engine.step(reward, next_obs, terminated, truncated, act_np, forced_u)

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
