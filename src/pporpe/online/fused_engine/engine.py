"""The Python side of the fused engine: numpy views of a population's buffers, the
per-member constants as matrices, and the calls of the kernels of :mod:`.kernels`."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ...nn.batched import NetLayout
from ..config import OnlineConfig
from ..engine import PopulationParts
from ..stats import StepStats
from .kernels.inputs import (
    ACTIVATIONS,
    C_NAMES,
    F_NAMES,
    G_ACT,
    G_ACT_DIM,
    G_HEAD,
    G_LAYERS,
    G_LN,
    G_OBS,
    G_OUT_B,
    G_OUT_W,
    G_RAW,
    G_UNITS,
    HEADS,
    METHOD_CODES,
)
from .kernels.step import fused_begin, fused_forward, fused_step

__all__ = ["FusedEngine", "segment_ranges"]


def _np(t: Tensor, *shape: int) -> np.ndarray:
    """A numpy view (shared memory) of a contiguous CPU tensor, reshaped."""
    arr = t.numpy()
    return arr.reshape(shape) if shape else arr


def segment_ranges(lay: NetLayout) -> np.ndarray:
    """The element range ``[lo, hi)`` of every segment of ``lay`` (the tensors of the
    t-momentum, in :attr:`NetLayout.segments` order), as an int64 array ``[S, 2]``.

    A segment is the rows ``lay.row_seg`` gives it; with a split head (``lay.col_seg``)
    the output bias's row is cut into the columns of each part, and its padding columns
    (past ``raw_dim``), whose gradient, moments and step are always 0, belong to none.
    """
    units = lay.units
    owner = lay.row_seg.repeat_interleave(units)
    if lay.col_seg is not None:
        bias = slice(lay.bias_row * units, (lay.bias_row + 1) * units)
        owner[bias] = lay.col_seg
        owner[lay.bias_row * units + lay.raw_dim : (lay.bias_row + 1) * units] = -1
    ranges = np.zeros((lay.n_seg, 2), dtype=np.int64)
    for s in range(lay.n_seg):
        where = torch.nonzero(owner == s).flatten()
        lo, hi = int(where[0]), int(where[-1]) + 1
        if hi - lo != len(where):
            raise ValueError(f"segment {s} of the layout is not one contiguous range")
        ranges[s] = lo, hi
    return ranges


def _hidden_layers(lay: NetLayout) -> np.ndarray:
    """Offsets of W, b, gamma, beta (-1: none) and the input width of every hidden layer
    of ``lay``, int64 ``[layers, 5]`` (the kernels' ``lay``)."""
    g_ = [-1 if h[2] is None else h[2].offset for h in lay.hidden]
    be_ = [-1 if h[3] is None else h[3].offset for h in lay.hidden]
    return np.array(
        [
            [h[0].offset, h[1].offset, g_[i], be_[i], h[0].shape[1]]
            for i, h in enumerate(lay.hidden)
        ],
        dtype=np.int64,
    )


def _geometry(parts: PopulationParts) -> np.ndarray:
    """The kernels' geometry vector of ``parts`` (int64, entries ``G_*`` of
    :mod:`.kernels.inputs`)."""
    lay = parts.lay
    geo = [0] * 10
    geo[G_OBS], geo[G_UNITS], geo[G_RAW] = lay.obs_dim, lay.units, lay.raw_dim
    geo[G_OUT_W], geo[G_OUT_B] = lay.out_w.offset, lay.out_b.offset
    geo[G_LN], geo[G_ACT] = int(lay.layer_norm), ACTIVATIONS[parts.activation]
    geo[G_HEAD] = HEADS[parts.policy]
    geo[G_ACT_DIM], geo[G_LAYERS] = parts.act_dim, lay.layers
    return np.array(geo, dtype=np.int64)


class FusedEngine:
    """The fused engine of a population's :class:`~pporpe.online.engine.PopulationParts`
    (an :class:`~pporpe.online.engine.Engine`): numpy views of its buffers and of the
    layout, for :func:`~.kernels.step.fused_step`. Build it after
    :func:`~pporpe.online.fused_engine.warm_up` (the population does)."""

    def __init__(self, parts: PopulationParts) -> None:
        self.parts = parts
        lay, K = parts.lay, parts.K
        units, n_pad = lay.units, lay.n_pad
        self.lay = _hidden_layers(lay)
        self.geo = _geometry(parts)
        self.seg = segment_ranges(lay)
        self.hf = np.array([parts.head.min_scale, float(lay.n_real[1])])
        am = parts.action_map
        self.bounds = torch.stack([am.low, am.high, am.log_range]).numpy().astype(np.float32)
        st, co, pend = parts.state, parts.consts, parts.state.pending
        self.P = _np(st.params, 3, K, n_pad)
        moments = (st.trace_e, st.trace_r, st.opt_v, st.opt_vmax, st.opt_m)
        self.opt = (
            *(_np(x, 2, K, n_pad) for x in moments),
            _np(st.opt_weight), _np(co.seg_num), _np(co.seg_den),
        )  # fmt: skip
        self.sc = (_np(st.trace_divergence), _np(st.decay), _np(st.tsoft_weight),
                   _np(st.tsoft_sigma2), st.steps)  # fmt: skip
        self.pend = (
            _np(pend.obs), _np(pend.u), _np(pend.logp_b), _np(pend.value_b), _np(pend.raw_b),
            pend.waiting,
        )  # fmt: skip
        self.cf = np.zeros((K, len(C_NAMES)))
        self.fl = np.zeros((K, len(F_NAMES)), dtype=np.int64)
        width = max(lay.obs_dim, units)
        max_seg = int((self.seg[:, 1] - self.seg[:, 0]).max())
        self.scratch = (
            np.zeros((2, n_pad), np.float32),
            np.zeros(max_seg, np.float32),
            np.zeros((2, lay.layers + 1, 3, width), np.float32),
            np.zeros((2, lay.layers), np.float32),
            np.zeros((0, 3, width), np.float32),
            np.zeros(0, np.float32),
        )
        self.stats = np.zeros((5, K), np.float32)
        self.actions = np.zeros((K, parts.act_dim), np.float32)
        self._no_forced = np.zeros((K, parts.act_dim), np.float32)

    def set_member(self, k: int, config: OnlineConfig) -> None:
        """Member k's rows of the constants matrices, from what MemberConstants.write wrote
        (the columns are named as its fields), with the surrogate's settings."""
        co, cfg = self.parts.consts, config
        surrogate = {"eps": cfg.eps, "beta": cfg.beta, "eta": cfg.eta}
        self.cf[k] = [surrogate[n] if n in surrogate else float(getattr(co, n)[k])
                      for n in C_NAMES]  # fmt: skip
        method = METHOD_CODES[(cfg.method, cfg.rpe_form)]
        self.fl[k] = [method if n == "method" else int(bool(getattr(co, n)[k]))
                      for n in F_NAMES]  # fmt: skip

    def _no_points(self) -> np.ndarray:
        return np.full((self.parts.K, self.parts.act_dim, 2), 0.5)

    # -- acting ---------------------------------------------------------------------------
    def begin(self, idx: np.ndarray, obs: np.ndarray, forced_u: Tensor | None) -> np.ndarray:
        """First actions of members ``idx``, their traces reset, their pending transitions
        set (:class:`~pporpe.online.engine.Engine`): the noise is drawn here, the rest is
        one call of :func:`~.kernels.step.fused_begin`."""
        parts = self.parts
        x = np.asarray(obs, np.float32).reshape(len(idx), parts.obs_dim)
        pts = None
        if forced_u is None:
            mask = np.zeros(parts.K, dtype=bool)
            mask[idx] = True
            pts = parts.noise.take(mask).numpy()
        forced = None if forced_u is None else np.asarray(forced_u, np.float32)
        parts.state.reset_traces(torch.from_numpy(idx))
        return self._begin(idx, x, self._no_points() if pts is None else pts, forced)

    def _begin(
        self, idx: np.ndarray, obs: np.ndarray, points: np.ndarray, forced_u: np.ndarray | None
    ) -> np.ndarray:
        """First actions ``[len(idx), d]`` of members ``idx`` (sets their pending state)."""
        n = len(idx)
        actions = np.zeros((n, self.actions.shape[1]), np.float32)
        forced = (
            self._no_forced[:n] if forced_u is None else np.ascontiguousarray(forced_u, np.float32)
        )
        fused_begin(
            self.P, np.ascontiguousarray(idx, np.int64), np.ascontiguousarray(obs, np.float32),
            points, forced, forced_u is not None, self.geo, self.lay, self.hf, self.bounds,
            self.pend, actions, self.scratch,
        )  # fmt: skip
        return actions

    def outputs(self, kind: int, obs: np.ndarray) -> Tensor:
        """Outputs ``[K, n_out]`` of net ``kind`` (0 policy, 1 value) at ``obs [K, obs]``
        (:class:`~pporpe.online.engine.Engine`)."""
        parts = self.parts
        n_out = parts.lay.raw_dim if kind == 0 else 1
        out = np.zeros((self.P.shape[1], n_out), np.float32)
        x = np.ascontiguousarray(
            np.asarray(obs, np.float32).reshape(parts.K, parts.obs_dim), np.float32
        )
        fused_forward(self.P, kind, x, self.geo, self.lay, out, self.scratch)
        return torch.from_numpy(out)

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
        """Learn transition t of the active members; their stats and a_{t+1}
        (:class:`~pporpe.online.engine.Engine`): the noise is drawn here, everything else
        in one call of :func:`~.kernels.step.fused_step`."""
        K, act_np, noise = self.parts.K, active, self.parts.noise
        pts = self._no_points() if forced_u is not None else noise.take(act_np).numpy()
        forced = None if forced_u is None else np.asarray(forced_u, np.float32).reshape(K, -1)
        stats, actions = self._step(
            np.asarray(reward, np.float32).reshape(K),
            np.asarray(next_obs, np.float32).reshape(K, self.parts.obs_dim),
            np.asarray(terminated, dtype=bool).reshape(K),
            np.asarray(truncated, dtype=bool).reshape(K),
            act_np,
            pts,
            forced,
        )
        s = torch.from_numpy(stats)
        return StepStats(s[0], s[1], s[2], s[3], s[4]), actions

    def _step(
        self,
        reward: np.ndarray,
        next_obs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        active: np.ndarray,
        points: np.ndarray,
        forced_u: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Run the kernel; return the stats ``[5, K]`` and the actions ``[K, d]`` (copies)."""
        inp = (
            np.ascontiguousarray(reward, np.float32),
            np.ascontiguousarray(next_obs, np.float32),
            np.ascontiguousarray(terminated, np.bool_),
            np.ascontiguousarray(truncated, np.bool_),
            np.ascontiguousarray(active, np.bool_),
            points,
            self._no_forced if forced_u is None else np.ascontiguousarray(forced_u, np.float32),
            forced_u is not None,
        )
        fused_step(
            self.P, self.opt, self.sc, self.pend, inp, self.cf, self.fl, self.geo, self.lay,
            self.seg, self.hf, self.bounds, (self.stats, self.actions), self.scratch,
        )  # fmt: skip
        return self.stats.copy(), self.actions.copy()
