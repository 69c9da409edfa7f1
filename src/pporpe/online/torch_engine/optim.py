r"""td-AmsProp: LaProp with t-momentum and a decaying AMSGrad maximum.

The optimiser named in the experimental setup of the PPO-RPE paper (arXiv:2010.03290,
Sec. IV-A): LaProp with t-momentum and d-AmsGrad ("td-AmsProp") as the SGD of eq. (4)
(``sgd``, Sec. II-A), with default parameters except the learning rate. Components:
t-momentum from Ilboudo, Kobayashi and Sugimoto, "Robust stochastic gradient descent
with student-t distribution based first-order momentum", IEEE TNNLS, 2020; LaProp from
Ziyin, Wang and Ueda, "LaProp: Separating momentum and adaptivity in Adam",
arXiv:2002.04839, 2020; the decaying AMSGrad maximum (d-AmsGrad) from Kobayashi 2020,
as cited in the paper. This project's constants are listed in ``docs/online-learner.md``.

For every *segment* (by default: every parameter tensor) with ``n`` elements, at step
``t`` with gradient ``g``::

    v     <- beta2 v + (1 - beta2) g^2
    v_hat  = v / (1 - beta2^t)
    vmax  <- max(amsgrad_decay * vmax, v_hat)
    gv     = g / (sqrt(vmax) + eps)                  # LaProp: normalise first
    dof    = k_dof * n
    w      = (n + dof) / (dof + ||gv - m||^2)        # t-momentum weight (one per segment)
    b      = W / (W + w)
    m     <- b m + (1 - b) gv
    W     <- (2 - 1/beta1) W + w                     # W_0 = beta1 / (1 - beta1)
    p     <- p - lr / (1 - beta1^t) m

``k_dof = inf`` gives ``w = 1``, ``b = beta1``: plain LaProp. ``amsgrad_decay = 1``
is AMSGrad (``vmax`` never decreases), ``amsgrad_decay = 0`` switches the maximum
off (``vmax = v_hat``).

Speed. The online learner keeps all parameters in one flat 1-D tensor and is
bound by per-op overhead and memory passes. Passing ``segments=[n_1, n_2, ...]``
(sizes summing to its numel) makes the t-momentum statistics per segment -- i.e.
per original parameter tensor -- while every per-step operation stays a
whole-vector tensor op: no Python loop over segments and no ``.item()``.
Per-segment sums of squares use a CSR matrix whose values *are* the ``gv - m``
buffer (one sparse mat-vec); per-segment values are broadcast back by
:class:`_SegmentExpander`. On CPU the second-moment part (``v``, ``vmax``,
``gv``) runs in one pass of PyTorch's fused Adam kernel (``torch._fused_adam_``
with ``beta1 = 0``), which is checked against the formula above once per dtype
before first use; an equivalent eager path is used otherwise.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ...config import check_real

__all__ = ["TDAmsProp"]


# --------------------------------------------------------------------- validation


def _validate_hparams(lr: Any, betas: Any, eps: Any, k_dof: Any, amsgrad_decay: Any) -> None:
    """Validate the scalar hyper-parameters of td-AmsProp (ValueError naming the culprit)."""
    check_real("lr", lr, 0.0, math.inf, lo_open=True, hi_open=True)
    if isinstance(betas, str | Tensor) or not isinstance(betas, Sequence) or len(betas) != 2:
        raise ValueError(f"betas must be a pair (beta1, beta2), each in [0, 1), got {betas!r}")
    check_real("betas[0] (beta1)", betas[0], 0.0, 1.0, lo_open=False, hi_open=True)
    check_real("betas[1] (beta2)", betas[1], 0.0, 1.0, lo_open=False, hi_open=True)
    check_real("eps", eps, 0.0, math.inf, lo_open=True, hi_open=True)
    check_real("k_dof", k_dof, 0.0, math.inf, lo_open=True, hi_open=False)  # inf: LaProp
    check_real("amsgrad_decay", amsgrad_decay, 0.0, 1.0, lo_open=False, hi_open=False)


# --------------------------------------------------------------------- fused kernel


def _fused_second_moment(
    out: Tensor,
    g: Tensor,
    scratch: Tensor,
    v: Tensor,
    vmax_s: Tensor | None,
    step: Tensor,
    scale: float,
    beta2: float,
    eps: float,
) -> None:
    """One pass of ``torch._fused_adam_`` used as a LaProp normaliser.

    With Adam's ``beta1 = 0`` (its first moment is ``-g``, written to ``scratch``),
    ``maximize=True`` and learning rate ``scale`` it performs::

        v      <- beta2 v + (1 - beta2) g^2
        vmax_s <- max(vmax_s, v)                       (only if vmax_s is given)
        out    <- out + scale * g / (sqrt(vmax_s or v) / sqrt(1 - beta2^step) + eps)
    """
    torch._fused_adam_(
        [out],
        [g],
        [scratch],
        [v],
        [] if vmax_s is None else [vmax_s],
        [step],
        lr=scale,
        beta1=0.0,
        beta2=beta2,
        weight_decay=0.0,
        eps=eps,
        amsgrad=vmax_s is not None,
        maximize=True,
    )


_FUSED_OK: dict[torch.dtype, bool] = {}


def _fused_works(dtype: torch.dtype) -> bool:
    """Whether ``torch._fused_adam_`` exists on CPU for ``dtype`` and does what we rely on.

    Checked once per dtype on a few elements against the eager formula, so that a
    change of the private kernel's semantics makes us fall back instead of
    silently computing something else.
    """
    ok = _FUSED_OK.get(dtype)
    if ok is not None:
        return ok
    ok = False
    if hasattr(torch, "_fused_adam_"):
        try:
            gen = torch.Generator().manual_seed(0)
            g = torch.randn(7, generator=gen, dtype=torch.float64)
            v0 = torch.rand(7, generator=gen, dtype=torch.float64)
            vmax0 = torch.rand(7, generator=gen, dtype=torch.float64) * 2.0
            out0 = torch.randn(7, generator=gen, dtype=torch.float64)
            beta2, eps, scale, t = 0.75, 1e-3, 0.625, 3
            v_ref = beta2 * v0 + (1 - beta2) * g * g
            bc2 = 1 - beta2**t
            ok = True
            for vmax_s in (None, vmax0):
                src = v_ref if vmax_s is None else torch.maximum(vmax_s, v_ref)
                ref = out0 + scale * g / (src.sqrt() / math.sqrt(bc2) + eps)
                out, v = out0.to(dtype, copy=True), v0.to(dtype, copy=True)
                vm = None if vmax_s is None else vmax_s.to(dtype, copy=True)
                step = torch.tensor(t)
                _fused_second_moment(
                    out, g.to(dtype), torch.zeros_like(out), v, vm, step, scale, beta2, eps
                )
                tol = 1e-12 if dtype == torch.float64 else 1e-5
                ok = ok and torch.allclose(out.double(), ref, rtol=tol, atol=tol)
                ok = ok and torch.allclose(v.double(), v_ref, rtol=tol, atol=tol)
                if vm is not None:
                    ok = ok and torch.allclose(vm.double(), src, rtol=tol, atol=tol)
                ok = ok and int(step) == t
        except Exception:  # any failure of the private kernel means: do not use it
            ok = False
    _FUSED_OK[dtype] = ok
    return ok


# --------------------------------------------------------------------- segments


class _SegmentExpander:
    """Broadcast one value per segment to every element of the flat vector.

    Equivalent to ``values[seg_ids]`` but about 4x faster on CPU: the (padded)
    vector is viewed as rows of ``chunk`` elements; rows inside one segment get
    their segment's value by one broadcast copy, and only the few rows that
    straddle a segment boundary are gathered element by element.
    """

    def __init__(
        self, sizes: Sequence[int], dtype: torch.dtype, device: torch.device, chunk: int = 64
    ) -> None:
        n = sum(sizes)
        nseg = len(sizes)
        nrow = -(-n // chunk)
        seg_ids = torch.repeat_interleave(
            torch.arange(nseg, device=device), torch.tensor(list(sizes), device=device)
        )
        padded = torch.full((nrow * chunk,), nseg - 1, dtype=torch.int64, device=device)
        padded[:n] = seg_ids
        rows = padded.view(nrow, chunk)
        uniform = (rows == rows[:, :1]).all(dim=1)
        self.row_seg = rows[:, 0].contiguous()
        self.mixed_rows = torch.nonzero(~uniform).view(-1)
        self.mixed_ids = rows[self.mixed_rows].reshape(-1).contiguous()
        self.has_mixed = bool(self.mixed_rows.numel())
        self.row_vals = torch.zeros(nrow, dtype=dtype, device=device)
        self.row_vals_exp = self.row_vals.unsqueeze(1).expand(nrow, chunk)
        self.mixed_vals = torch.zeros(self.mixed_ids.numel(), dtype=dtype, device=device)
        self.mixed_vals_2d = self.mixed_vals.view(-1, chunk)
        self.out = torch.zeros(nrow * chunk, dtype=dtype, device=device)
        self.out_2d = self.out.view(nrow, chunk)
        self.out_n = self.out[:n]

    def __call__(self, values: Tensor) -> Tensor:
        """Return ``values[seg_ids]`` (a view of an internal buffer, overwritten next call)."""
        torch.index_select(values, 0, self.row_seg, out=self.row_vals)
        self.out_2d.copy_(self.row_vals_exp)
        if self.has_mixed:
            torch.index_select(values, 0, self.mixed_ids, out=self.mixed_vals)
            self.out_2d.index_copy_(0, self.mixed_rows, self.mixed_vals_2d)
        return self.out_n


@dataclass(slots=True)
class _Moments:
    """What one parameter's second-moment step reads: its gradient, v, the scaled running
    maximum (None without AMSGrad), the step tensor, beta2 and its bias correction, eps,
    and whether the fused kernel applies. Built for every parameter at every step, so a
    slotted class (0.25 us to build here, against 2 us for a frozen dataclass)."""

    g: Tensor
    v: Tensor
    vmax: Tensor | None
    step: Tensor
    beta2: float
    bc2: float
    eps: float
    fused: bool


@dataclass
class _Cache:
    """Per-parameter derived data and scratch buffers (not part of the state)."""

    key: tuple[Any, ...]
    nseg: int
    diff: Tensor  # gv - m
    scratch: Tensor  # written by the fused kernel / eager temporaries
    num: Tensor  # n_s + dof_s, one per segment (0-dim for a single segment)
    den: Tensor  # dof_s
    seg_matrix: Tensor | None  # CSR (nseg x numel) whose values ARE ``diff``
    expander: _SegmentExpander | None  # None: a single segment
    one: Tensor  # int64 0-dim 1, to advance the step tensor without wrapping a Python int
    fused_ok: bool  # fused kernel usable for this parameter (device, dtype, self-check)
    k_dof: float
    dtype: torch.dtype
    segments_ref: tuple[int, ...] | None  # the group's segments object this cache was checked for
    step_ref: Tensor | None = None  # the state's step tensor the mirror belongs to
    step: int = 0  # Python mirror of state["step"]


class TDAmsProp(torch.optim.Optimizer):
    r"""td-AmsProp = LaProp + t-momentum + decaying AMSGrad (formulas in the module docstring).

    Args:
        params: parameters or parameter groups, as for any ``torch.optim.Optimizer``.
        lr: learning rate, ``> 0``.
        betas: ``(beta1, beta2)``, each in ``[0, 1)``: rates of the momentum ``m`` and
            of the second moment ``v``. ``beta1 = 0`` means no momentum (``m = gv``).
        eps: ``> 0``, added to ``sqrt(vmax)``.
        k_dof: in ``(0, inf]``: degrees of freedom per element of the student-t
            model of t-momentum (``dof = k_dof * n``). ``math.inf`` gives LaProp.
        amsgrad_decay: in ``[0, 1]``; ``1`` is AMSGrad, ``0`` no maximum.
        segments: optional list of positive ints summing to the numel of the group's
            single 1-D parameter; the t-momentum weight is then computed per
            segment. ``None``: every parameter tensor is one segment.
        fused: ``None`` (default) or ``True``: use PyTorch's fused CPU Adam kernel
            for the second-moment pass where it applies (CPU, contiguous tensors of
            one dtype) and passed its self-check; ``False``: always the eager path.
            Both give the same result up to rounding.

    The defaults (``lr=3e-4``, ``betas=(0.9, 0.999)``, ``eps=1e-8``, ``k_dof=1``,
    ``amsgrad_decay=0.999``) are this project's choice: the author's library and
    its defaults are not available offline. ``lr=3e-4`` is the paper's (Table I).

    State per parameter (checkpointable with ``state_dict``/``load_state_dict``):
    ``step`` (int64, 0-dim), ``v``, ``m``, ``vmax_scaled`` (like the parameter) and
    ``W`` (one value per segment). ``vmax_scaled`` holds ``vmax * (1 - beta2^t)``
    (this lets the maximum use the raw ``v`` in a fused pass); use
    :meth:`vmax` for ``vmax`` itself. With ``amsgrad_decay = 0`` it is unused.

    Notes:
        * For ``0 < beta1 < 0.5`` the factor ``2 - 1/beta1`` of the ``W`` recursion is
          negative; that is the t-momentum rule as published and is kept as is.
        * With ``k_dof = inf`` (or ``beta1 = 0``) the momentum uses ``b = beta1``
          directly and ``W`` is not updated: with ``w = 1`` it stays at its fixed
          point ``beta1 / (1 - beta1)``.
        * Bias corrections use a Python mirror of the ``step`` tensor, re-read
          (once) whenever the state's step tensor object is replaced, e.g. by
          ``load_state_dict``. Do not modify ``state[p]["step"]`` in place by hand.
    """

    def __init__(
        self,
        params: Iterable[Tensor] | Iterable[dict[str, Any]],
        lr: float = 3e-4,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        k_dof: float = 1.0,
        amsgrad_decay: float = 0.999,
        segments: Sequence[int] | None = None,
        *,
        fused: bool | None = None,
    ) -> None:
        _validate_hparams(lr, betas, eps, k_dof, amsgrad_decay)
        if fused is not None and not isinstance(fused, bool):
            raise ValueError(f"fused must be None, True or False, got {fused!r}")
        if fused and not _fused_works(torch.float32):
            raise ValueError("fused=True but torch._fused_adam_ is unavailable or failed its check")
        defaults = {
            "lr": lr,
            "betas": (float(betas[0]), float(betas[1])),
            "eps": eps,
            "k_dof": k_dof,
            "amsgrad_decay": amsgrad_decay,
            "segments": None if segments is None else tuple(segments),
        }
        self._fused_allowed = fused is not False
        self._cache: dict[Tensor, _Cache] = {}
        super().__init__(params, defaults)

    def __getstate__(self) -> dict[str, Any]:
        """Pickle/deepcopy support: the derived per-parameter cache is left out on purpose
        (its CSR matrix aliases a scratch buffer, which a copy would not preserve)."""
        state = super().__getstate__()
        state["_fused_allowed"] = self._fused_allowed
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Restore from pickling (also called by ``load_state_dict``, with only the state and
        the groups); the derived per-parameter cache is rebuilt lazily."""
        fused_allowed = state.pop("_fused_allowed", getattr(self, "_fused_allowed", True))
        super().__setstate__(state)
        self._fused_allowed = fused_allowed
        self._cache = {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Load a :meth:`state_dict` (standard format) into this optimizer.

        Unlike the base class, the incoming tensors are copied first: loading the live
        ``state_dict()`` of another optimizer would otherwise share its ``step``, ``v``,
        ``m``, ... tensors, and both would then update the same memory.
        """
        super().load_state_dict(copy.deepcopy(state_dict))

    def add_param_group(self, param_group: dict[str, Any]) -> None:
        """Add a parameter group after validating its options (ValueError if invalid)."""
        super().add_param_group(param_group)
        group = self.param_groups[-1]
        try:
            _validate_hparams(
                group["lr"], group["betas"], group["eps"], group["k_dof"], group["amsgrad_decay"]
            )
            group["betas"] = (float(group["betas"][0]), float(group["betas"][1]))
            segments = group["segments"]
            if segments is not None:
                group["segments"] = _validate_segments(segments, group["params"])
        except ValueError:
            self.param_groups.pop()
            raise

    def vmax(self, p: Tensor) -> Tensor:
        """Return ``vmax`` of parameter ``p`` (a new tensor; ``v_hat`` if ``amsgrad_decay = 0``)."""
        state = self.state[p]
        if "vmax_scaled" not in state:
            raise KeyError("no state for this parameter yet")
        group = self._group_of(p)
        source = state["vmax_scaled"] if group["amsgrad_decay"] > 0 else state["v"]
        return source / (1.0 - group["betas"][1] ** int(state["step"]))

    def _group_of(self, p: Tensor) -> dict[str, Any]:
        for group in self.param_groups:
            if any(q is p for q in group["params"]):
                return group
        raise KeyError("parameter not managed by this optimizer")

    # ------------------------------------------------------------------ internals

    def _get_cache(self, p: Tensor, group: dict[str, Any]) -> _Cache:
        """Return (building if needed) the derived data of ``p`` for ``group``'s options."""
        segments: tuple[int, ...] | None = group["segments"]
        k_dof = float(group["k_dof"])
        key = (segments, k_dof, p.dtype, p.device, tuple(p.shape))
        cache = self._cache.get(p)
        if cache is not None and cache.key == key:
            cache.segments_ref = segments
            return cache
        sizes = (p.numel(),) if segments is None else segments
        nseg = len(sizes)
        n_s = torch.tensor(sizes, dtype=p.dtype, device=p.device)
        if math.isinf(k_dof):  # w == 1; only used if k_dof changes back to finite
            num, den = torch.ones_like(n_s), torch.zeros_like(n_s)
        else:
            num, den = n_s * (1.0 + k_dof), n_s * k_dof
        if nseg == 1:  # 0-dim, so that they combine with torch.dot's 0-dim result
            num, den = num.view(()), den.view(())
        diff = torch.zeros_like(p, memory_format=torch.contiguous_format)
        seg_matrix = expander = None
        if nseg > 1:
            dev = p.device
            # int32 indices: with int64 the CPU kernel converts them on every call.
            crow = torch.zeros(nseg + 1, dtype=torch.int32, device=dev)
            crow[1:] = torch.cumsum(torch.tensor(sizes, device=dev), 0)
            cols = torch.arange(p.numel(), dtype=torch.int32, device=dev)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
                seg_matrix = torch.sparse_csr_tensor(
                    crow, cols, diff, size=(nseg, p.numel()), check_invariants=False
                )
            expander = _SegmentExpander(sizes, p.dtype, p.device)
        cache = _Cache(
            key=key,
            nseg=nseg,
            diff=diff,
            scratch=torch.zeros_like(diff),
            num=num,
            den=den,
            seg_matrix=seg_matrix,
            expander=expander,
            one=torch.ones((), dtype=torch.int64, device=p.device),
            fused_ok=self._fused_allowed and p.device.type == "cpu" and _fused_works(p.dtype),
            k_dof=k_dof,
            dtype=p.dtype,
            segments_ref=segments,
        )
        self._cache[p] = cache
        return cache

    @staticmethod
    def _init_state(p: Tensor, state: dict[str, Any], nseg: int, beta1: float) -> None:
        state["step"] = torch.zeros((), dtype=torch.int64, device=p.device)
        state["v"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
        state["vmax_scaled"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
        state["m"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
        state["W"] = torch.full((nseg,), beta1 / (1.0 - beta1), dtype=p.dtype, device=p.device)

    # ------------------------------------------------------------------ step

    @torch.no_grad()
    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # type: ignore[override]
        """Perform one td-AmsProp update of every parameter that has a gradient."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is not None:
                    self._update(p, p.grad, group)
        return loss

    def _update(self, p: Tensor, g: Tensor, group: dict[str, Any]) -> None:
        if g.is_sparse:
            raise RuntimeError("TDAmsProp does not support sparse gradients")
        beta1, beta2 = group["betas"]
        c = self._cache_for(p, group)
        state = self.state[p]
        if not state:
            self._init_state(p, state, c.nseg, beta1)
        step_t: Tensor = state["step"]
        t = self._count_step(c, step_t)
        bc2 = 1.0 - beta2**t

        # vmax_scaled = vmax * bc2_t, so vmax_t = max(decay vmax_{t-1}, v_t / bc2_t) becomes
        # vmax_scaled_t = max(decay * bc2_t / bc2_{t-1} * vmax_scaled_{t-1}, v_t).
        decay: float = group["amsgrad_decay"]
        vmax_s: Tensor = state["vmax_scaled"]
        if decay > 0.0 and t > 1:
            vmax_s.mul_(decay * bc2 / (1.0 - beta2 ** (t - 1)))
        moments = _Moments(
            g, state["v"], vmax_s if decay > 0.0 else None, step_t, beta2, bc2, group["eps"],
            c.fused_ok and g.dtype is c.dtype and g.is_contiguous() and not g.is_cuda,
        )  # fmt: skip
        m: Tensor = state["m"]
        if beta1 == 0.0 or math.isinf(group["k_dof"]):  # b == beta1
            self._momentum_step(m, moments, c, beta1)
        else:
            self._t_momentum_step(m, state["W"], moments, c, beta1)
        p.add_(m, alpha=-group["lr"] / (1.0 - beta1**t))

    def _cache_for(self, p: Tensor, group: dict[str, Any]) -> _Cache:
        """The cached helpers of ``p``, rebuilt when its group's segments, k_dof or the
        parameter's dtype changed."""
        c = self._cache.get(p)
        if (
            c is None
            or c.segments_ref is not group["segments"]
            or c.k_dof != group["k_dof"]
            or c.dtype is not p.dtype
        ):
            c = self._get_cache(p, group)
        return c

    @staticmethod
    def _count_step(c: _Cache, step_t: Tensor) -> int:
        """Advance the step count; returns t. A Python mirror of it avoids an ``.item()``
        per step (read again only after a state swap)."""
        if c.step_ref is not step_t:
            c.step_ref = step_t
            c.step = int(step_t.item())
        c.step += 1
        step_t.add_(c.one)
        return c.step

    def _momentum_step(self, m: Tensor, mo: _Moments, c: _Cache, beta1: float) -> None:
        """m <- beta1 m + (1 - beta1) gv: the fixed-rate momentum (k_dof = inf or beta1 = 0)."""
        if beta1 == 0.0:
            m.zero_()
        else:
            m.mul_(beta1)
        if mo.fused:
            _fused_second_moment(
                m, mo.g, c.scratch, mo.v, mo.vmax, mo.step, 1.0 - beta1, mo.beta2, mo.eps
            )
        else:
            gv = self._eager_gv(mo.g, mo.v, mo.vmax, mo.beta2, mo.bc2, mo.eps, out=c.scratch)
            m.add_(gv, alpha=1.0 - beta1)

    def _t_momentum_step(self, m: Tensor, W: Tensor, mo: _Moments, c: _Cache, beta1: float) -> None:
        """The t-momentum: m <- b m + (1 - b) gv with 1 - b = w / (W + w), per segment
        w = (n + dof) / (dof + ||gv - m||^2), and W <- (2 - 1/beta1) W + w."""
        diff = c.diff  # gv - m
        if mo.fused:
            torch.neg(m, out=diff)
            _fused_second_moment(
                diff, mo.g, c.scratch, mo.v, mo.vmax, mo.step, 1.0, mo.beta2, mo.eps
            )
        else:
            self._eager_gv(mo.g, mo.v, mo.vmax, mo.beta2, mo.bc2, mo.eps, out=diff).sub_(m)
        if c.seg_matrix is None:
            sq = torch.dot(diff.view(-1), diff.view(-1))
        else:
            sq = c.seg_matrix @ diff  # the CSR's values ARE ``diff``: sum of diff^2
        w = torch.div(c.num, sq.add_(c.den))  # (n + dof) / (dof + ||gv - m||^2)
        Ww = torch.add(W, w)
        one_minus_b = torch.div(w, Ww)  # 1 - b = w / (W + w)
        torch.add(Ww, W, alpha=1.0 - 1.0 / beta1, out=W)  # W <- (2 - 1/beta1) W + w
        if c.expander is not None:
            one_minus_b = c.expander(one_minus_b)
        else:
            one_minus_b = one_minus_b.view(())
        m.addcmul_(one_minus_b, diff)  # m <- m + (1 - b)(gv - m)

    @staticmethod
    def _eager_gv(
        g: Tensor,
        v: Tensor,
        vmax_s: Tensor | None,
        beta2: float,
        bc2: float,
        eps: float,
        out: Tensor,
    ) -> Tensor:
        """Eager twin of :func:`_fused_second_moment`: update v (and vmax_s), return gv in out."""
        v.mul_(beta2).addcmul_(g, g, value=1.0 - beta2)
        src = v
        if vmax_s is not None:
            torch.maximum(vmax_s, v, out=vmax_s)
            src = vmax_s
        denom = torch.sqrt(src, out=out).div_(math.sqrt(bc2)).add_(eps)
        return torch.div(g, denom, out=out)


def _validate_segments(segments: Any, params: Sequence[Tensor]) -> tuple[int, ...]:
    """Check ``segments`` against the group's parameters; return them as a tuple."""
    if isinstance(segments, str | Tensor) or not isinstance(segments, Sequence):
        raise ValueError(f"segments must be None or a list of positive ints, got {segments!r}")
    segs = tuple(segments)
    if not segs or any(isinstance(s, bool) or not isinstance(s, int) or s <= 0 for s in segs):
        raise ValueError(f"segments must be a non-empty list of positive ints, got {segs!r}")
    if len(params) != 1 or params[0].dim() != 1:
        raise ValueError(
            "segments requires a parameter group holding exactly one 1-D (flat) tensor, "
            f"got {len(params)} tensor(s) with shapes {[tuple(p.shape) for p in params]}"
        )
    if sum(segs) != params[0].numel():
        raise ValueError(
            f"segments must sum to the parameter's numel {params[0].numel()}, got sum {sum(segs)}"
        )
    return segs
