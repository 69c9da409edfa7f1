"""The Python side of the fused engine: numpy views of a population's buffers, the
per-member constants as matrices, and the calls of the kernels of :mod:`.fused`."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ..nn.batched import NetLayout
from . import fused
from .config import OnlineConfig

if TYPE_CHECKING:
    from .population import PopulationLearner

__all__ = ["FusedEngine", "compile_kernels", "segment_ranges", "warm_up"]


def _np(t: Tensor, *shape: int) -> np.ndarray:
    """A numpy view (shared memory) of a contiguous CPU tensor, reshaped."""
    arr = t.numpy()
    return arr.reshape(shape) if shape else arr


_KERNELS = (fused.fused_begin, fused.fused_step, fused.fused_forward)
"""The kernels Python calls; each carries the code of every function it calls."""


class _Loaded:
    """Whether this process has loaded the kernels: :func:`warm_up`."""

    done = False


def _run_kernels() -> None:
    """A one-member population of the smallest shape through a first action, a step and
    both forwards: every kernel called once. The kernels' types do not depend on the
    population's sizes, so this covers every population."""
    from .population import PopulationLearner

    pop = PopulationLearner(
        1, -np.ones(1), np.ones(1), [OnlineConfig(layers=1, units=2)], [0], engine="fused"
    )
    obs, no = np.zeros((1, 1)), np.zeros(1, dtype=bool)
    pop.begin_episode([0], obs)
    pop.step(np.zeros(1), obs, no, no)
    pop.act_deterministic(obs)
    pop.value(obs)


def compile_kernels() -> None:
    """Compile every kernel into numba's disk cache (the body of :func:`warm_up`'s
    subprocess)."""
    _Loaded.done = True
    _run_kernels()


def _in_cache() -> bool:
    """Whether numba's disk cache holds every kernel for today's source (its index is
    empty where the source changed). numba has no public call for this; its version is
    pinned in constraints.txt."""
    for kernel in _KERNELS:
        index = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
        if index is None or not index._load_index():
            return False
    return True


def warm_up() -> None:
    """Load every kernel of :mod:`.fused` from numba's disk cache (:mod:`.fused`'s
    docstring says where), once per process; if it is not there, compile it first in a
    subprocess. :class:`~pporpe.online.population.PopulationLearner` calls this when it
    is built with the fused engine, so the compile falls before a run's clock starts.

    Why a subprocess: a process that compiled the kernels computes float rounding
    differently from one that loaded them (measured with numba 0.68.1 on this project's
    machine, with the swish activation only: the same cached code, loaded in both), so the
    numbers of a run would depend on whether its process found the cache. A process that
    trains only ever loads; where the cache cannot be written, every process compiles,
    and they agree with one another. Tested in tests/test_fused.py.
    """
    if _Loaded.done:
        return
    _Loaded.done = True  # the one-member population below must not warm up again
    try:
        if not _in_cache():
            _compile_in_subprocess()
        _run_kernels()  # loads them (compiles them where the cache cannot be written)
    except BaseException:
        _Loaded.done = False
        raise


def _compile_in_subprocess() -> None:
    """:func:`compile_kernels` in a fresh interpreter that finds pporpe where this one did
    (its ``sys.path``); if that fails, a warning, and the kernels compile in this process."""
    code = "from pporpe.online.fused_engine import compile_kernels; compile_kernels()"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        warnings.warn(
            "compiling the fused kernels in a subprocess failed, so this process compiles "
            "them, and its float rounding may differ from a process that loads them from "
            f"numba's cache:\n{done.stderr[-2000:]}",
            RuntimeWarning,
            stacklevel=3,
        )


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


class FusedEngine:
    """Numpy views of ``pop``'s buffers and the layout, for :func:`fused.fused_step`."""

    def __init__(self, pop: PopulationLearner) -> None:
        lay, K = pop.lay, pop.K
        units, n_pad = lay.units, lay.n_pad
        g_ = [-1 if h[2] is None else h[2].offset for h in lay.hidden]
        be_ = [-1 if h[3] is None else h[3].offset for h in lay.hidden]
        self.lay = np.array(
            [
                [h[0].offset, h[1].offset, g_[i], be_[i], h[0].shape[1]]
                for i, h in enumerate(lay.hidden)
            ],
            dtype=np.int64,
        )
        geo = [0] * 10
        geo[fused.G_OBS], geo[fused.G_UNITS], geo[fused.G_RAW] = lay.obs_dim, units, lay.raw_dim
        geo[fused.G_OUT_W], geo[fused.G_OUT_B] = lay.out_w.offset, lay.out_b.offset
        geo[fused.G_LN], geo[fused.G_ACT] = int(lay.layer_norm), fused.ACTIVATIONS[pop.activation]
        geo[fused.G_HEAD] = fused.HEADS[pop.shape_config.policy]
        geo[fused.G_ACT_DIM], geo[fused.G_LAYERS] = pop.act_dim, lay.layers
        self.geo = np.array(geo, dtype=np.int64)
        self.seg = segment_ranges(lay)
        self.hf = np.array([pop.head.min_scale, float(lay.n_real[1])])
        am = pop.action_map
        self.bounds = torch.stack([am.low, am.high, am.log_range]).numpy().astype(np.float32)
        st, co, pend = pop.state, pop.consts, pop.state.pending
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
        self.cf = np.zeros((K, len(fused.C_NAMES)))
        self.fl = np.zeros((K, len(fused.F_NAMES)), dtype=np.int64)
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
        self.actions = np.zeros((K, pop.act_dim), np.float32)
        self._no_forced = np.zeros((K, pop.act_dim), np.float32)

    def set_constants(self, pop: PopulationLearner, k: int, cfg: OnlineConfig) -> None:
        """Member k's rows of the constants matrices, from what MemberConstants.write wrote
        (the columns are named as its fields), with the surrogate's settings."""
        co = pop.consts
        surrogate = {"eps": cfg.eps, "beta": cfg.beta, "eta": cfg.eta}
        self.cf[k] = [surrogate[n] if n in surrogate else float(getattr(co, n)[k])
                      for n in fused.C_NAMES]  # fmt: skip
        method = fused.METHOD_CODES[(cfg.method, cfg.rpe_form)]
        self.fl[k] = [method if n == "method" else int(bool(getattr(co, n)[k]))
                      for n in fused.F_NAMES]  # fmt: skip

    def step(
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
        fused.fused_step(
            self.P, self.opt, self.sc, self.pend, inp, self.cf, self.fl, self.geo, self.lay,
            self.seg, self.hf, self.bounds, (self.stats, self.actions), self.scratch,
        )  # fmt: skip
        return self.stats.copy(), self.actions.copy()

    def begin(
        self, idx: np.ndarray, obs: np.ndarray, points: np.ndarray, forced_u: np.ndarray | None
    ) -> np.ndarray:
        """First actions ``[len(idx), d]`` of members ``idx`` (sets their pending state)."""
        n = len(idx)
        actions = np.zeros((n, self.actions.shape[1]), np.float32)
        forced = (
            self._no_forced[:n] if forced_u is None else np.ascontiguousarray(forced_u, np.float32)
        )
        fused.fused_begin(
            self.P, np.ascontiguousarray(idx, np.int64), np.ascontiguousarray(obs, np.float32),
            points, forced, forced_u is not None, self.geo, self.lay, self.hf, self.bounds,
            self.pend, actions, self.scratch,
        )  # fmt: skip
        return actions

    def forward(self, kind: int, obs: np.ndarray, n_out: int) -> np.ndarray:
        """Outputs ``[K, n_out]`` of net ``kind`` (0 policy, 1 value) at ``obs [K, obs]``."""
        out = np.zeros((self.P.shape[1], n_out), np.float32)
        x = np.ascontiguousarray(obs, np.float32)
        fused.fused_forward(self.P, kind, x, self.geo, self.lay, out, self.scratch)
        return out
