r"""K networks of one shape evaluated together, each computing what it computes alone.

The batch population (:mod:`pporpe.batch.population`) keeps the parameters of K
actor-critics as the rows of one ``[K, n]`` tensor, in the layout of one network's flat
vector (:class:`pporpe.nn.actor_critic.FlatActorCritic`), and evaluates the K networks of
an :func:`~pporpe.nn.mlp.mlp` with one batched call per layer instead of K.

**Bit for bit.** A member of a population is meant to compute exactly what a run of its
own computes. Elementwise operations give the same bits whatever the batch, but a matrix
product may not: PyTorch and MKL pick a kernel, and so an order of summation, by the
shape of the problem (on one machine, ``torch.bmm`` of ``[1, 64] x [64, 3]`` matrices
sums in another order than ``F.linear`` of one ``[1, 64]`` row, while ``[64, 64] x
[64, 1]`` matches ``F.linear`` only when computed as ``W x^T``, and its weight gradient
only when computed member by member). So every linear layer shape is *probed* once per
process (:func:`linear_mode`): on random inputs, the batched forms (:data:`LinearMode`:
``"bmm"``, ``baddbmm(b, x, W^T)`` with its own backward; ``"bmm_t"``, ``baddbmm(b, W,
x^T)`` transposed back; ``"bmm_mm"`` and ``"bmm_t_mm"``, the same with the weight
gradient member by member) are compared bit for bit with ``F.linear`` member by member,
outputs and gradients, on several random draws at the population's own number of members
(one draw is not enough: on an AMD EPYC with AVX2, ``bmm`` of ``[2, 16] x [16, 1]``
matrices matches ``F.linear`` on about one draw in ten); the first that agrees on every
draw is used, else ``"loop"``, ``F.linear``
member by member (exact by construction, K calls). LayerNorm is probed the same way
(``"batched"``: the normalisation then the member's scale and shift, or ``"loop"``), and
so are the activations: PyTorch computes the elements of a tensor that fill whole vector
registers with vectorised kernels and the rest with scalar ones, which round some
functions differently (SiLU, softplus, sigmoid; not tanh, ReLU, exp or log on the machine
tested), and stacking K members moves elements from one to the other.

**Alignment.** On some machines a matrix product's rounding also depends on where its
operands lie in memory: on an AMD EPYC with AVX2 (MKL 2024.2), ``F.linear`` of the same
numbers gives other bits when the weight or the input starts 4, 8 or 12 bytes past a
16-byte boundary, or has other strides (``[2, 16] x [16, 1]``, ``[8, 16] x [16, 6]``). A
run alone's parameters are views of one flat vector that PyTorch allocates on a 64-byte
boundary, and its activations are fresh tensors, allocated the same way. So
:func:`padded_rows` lays the members' rows out on 64-byte boundaries (every parameter of
member k then lies where it lies in a run alone), the ``"loop"`` forms compute each member
on its input where it starts on a 64-byte boundary, else on a copy with the same strides
that does (:func:`aligned`), and each linear layer is probed in its own layout
(:class:`LinearLayout`: the input's strides and offset, the weight's place in its row)
against ``F.linear`` on each member's tensors laid out as a run alone's.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from .mlp import FlatMLP

__all__ = [
    "ALIGNMENT",
    "LayerNormMode",
    "LinearLayout",
    "LinearMode",
    "StackedMLP",
    "activation_mode",
    "aligned",
    "backward_quietly",
    "layer_norm_mode",
    "linear_mode",
    "padded_rows",
    "stacked_layer_norm",
    "stacked_linear",
    "stacked_views",
]

LinearMode = Literal["bmm", "bmm_t", "bmm_mm", "bmm_t_mm", "loop"]
"""How :func:`stacked_linear` computes K linear layers."""
LayerNormMode = Literal["batched", "loop"]
"""How :func:`stacked_layer_norm` computes K LayerNorms."""

ALIGNMENT = 16
"""Floats per 64 bytes, the alignment of PyTorch's CPU allocations."""

_PROBE_MEMBERS = 3
"""Members a probe stacks when it is not told the population's count."""
_PROBE_DRAWS = 6
"""Random draws of the inputs a batched form must match ``"loop"`` on, every one."""
_PROBE_ELEMENTS = 16384
_LAYOUT_WARNING = "grad and param do not obey the gradient layout contract"


def padded_rows(members: int, n: int) -> Tensor:
    """A zero ``[members, n]`` tensor whose rows start on 64-byte boundaries (a view of a
    ``[members, n']`` tensor, ``n'`` the multiple of :data:`ALIGNMENT` at or above ``n``), as a
    run alone's flat parameter vector does."""
    stride = -(-n // ALIGNMENT) * ALIGNMENT
    return torch.zeros(members, stride)[:, :n]


def aligned(t: Tensor) -> Tensor:
    """``t`` where it starts on a 64-byte boundary, else a copy with the same strides that
    does: a member's input as a run alone's would lie (a fresh tensor, or a view of one)."""
    if t.data_ptr() % (4 * ALIGNMENT) == 0:
        return t
    out = torch.empty_strided(t.shape, t.stride(), dtype=t.dtype)
    out.copy_(t)
    return out


@dataclass(frozen=True)
class LinearLayout:
    """Where a stacked linear layer's operands lie: its input ``x [K, rows, in]`` (strides
    and offset past a 64-byte boundary, in floats) and its weight ``w [K, out, in]`` and bias
    ``b [K, out]``, rows of one ``[K, row]`` tensor (a member's row length and their
    offsets in it). The probe of :func:`linear_mode` lays its inputs out so."""

    x_strides: tuple[int, int, int]
    x_offset: int
    row: int
    w_offset: int
    b_offset: int

    @staticmethod
    def of(x: Tensor, w: Tensor, b: Tensor) -> LinearLayout:
        """The layout of a layer's operands; ``w`` and ``b`` views of the rows of one tensor."""
        w_at, b_at = int(w.storage_offset()), int(b.storage_offset())
        if w.shape[0] == 1:  # one row: a size-1 dimension's stride says nothing of its length
            row = -(-max(w_at + w[0].numel(), b_at + b[0].numel()) // ALIGNMENT) * ALIGNMENT
        else:
            row = int(w.stride(0))
        same = b.untyped_storage().data_ptr() == w.untyped_storage().data_ptr()
        if not same or (w.shape[0] > 1 and b.stride(0) != row):
            raise ValueError("w and b must be views of the rows of one [K, row] tensor")
        x_strides = (x.stride(0), x.stride(1), x.stride(2))
        x_offset = (x.data_ptr() % (4 * ALIGNMENT)) // 4
        return LinearLayout(x_strides, x_offset, row, w_at % row, b_at % row)

    @staticmethod
    def packed(members: int, rows: int, fan_in: int, fan_out: int) -> LinearLayout:
        """Contiguous inputs, and weight then bias in rows padded to 64 bytes."""
        row = -(-(fan_out * fan_in + fan_out) // ALIGNMENT) * ALIGNMENT
        return LinearLayout((rows * fan_in, fan_in, 1), 0, row, 0, fan_out * fan_in)


def stacked_views(flat: Tensor, shapes: Sequence[torch.Size]) -> list[Tensor]:
    """Views ``[K, *shape]`` of consecutive blocks of the rows of ``flat`` ``[K, n]``."""
    out, offset = [], 0
    for shape in shapes:
        n = math.prod(shape)
        out.append(flat[:, offset : offset + n].view(flat.shape[0], *shape))
        offset += n
    if offset != flat.shape[1]:
        raise ValueError(f"shapes cover {offset} elements but a row has {flat.shape[1]}")
    return out


class _Linear(torch.autograd.Function):
    """``x W^T + b`` of K members with ``F.linear``'s backward: ``dx = g W``, ``dW = (x^T
    g)^T``, ``db = sum_rows g``. ``transposed``: the forward as ``(W x^T + b)^T``;
    ``weight_grad_alone``: ``dW`` member by member (``torch.mm``, as ``F.linear``)."""

    @staticmethod
    def forward(
        x: Tensor, w: Tensor, b: Tensor, transposed: bool, weight_grad_alone: bool
    ) -> Tensor:
        if transposed:
            return torch.baddbmm(b.unsqueeze(2), w, x.transpose(1, 2)).transpose(1, 2)
        return torch.baddbmm(b.unsqueeze(1), x, w.transpose(1, 2))

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: Tensor) -> None:
        x, w, _, _, ctx.weight_grad_alone = inputs
        ctx.save_for_backward(x, w)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        x, w = ctx.saved_tensors
        g = grad.contiguous()
        xt = x.transpose(1, 2)
        if ctx.weight_grad_alone:
            dw = torch.stack([torch.mm(xt[k], g[k]) for k in range(x.shape[0])])
        else:
            dw = torch.bmm(xt, g)
        return torch.bmm(g, w), dw.transpose(1, 2), g.sum(1), None, None


_CUSTOM: dict[str, tuple[bool, bool]] = {
    "bmm_t": (True, False),
    "bmm_mm": (False, True),
    "bmm_t_mm": (True, True),
}
"""The batched forms computed by :class:`_Linear`: (transposed, weight_grad_alone)."""


def stacked_linear(x: Tensor, w: Tensor, b: Tensor, mode: LinearMode) -> Tensor:
    """``x[k] W[k]^T + b[k]`` for every member k: ``x [K, B, in]``, ``w [K, out, in]``,
    ``b [K, out]`` -> ``[K, B, out]``, by ``mode`` (see the module docstring)."""
    if mode == "bmm":
        return torch.baddbmm(b.unsqueeze(1), x, w.transpose(1, 2))
    if mode in _CUSTOM:
        out: Tensor = _Linear.apply(x, w, b, *_CUSTOM[mode])
        return out
    return torch.stack([F.linear(aligned(x[k]), w[k], b[k]) for k in range(x.shape[0])])


def stacked_layer_norm(
    x: Tensor, gamma: Tensor, beta: Tensor, eps: float, mode: LayerNormMode
) -> Tensor:
    """LayerNorm of the last dimension with member k's scale ``gamma[k]`` and shift ``beta[k]``."""
    shape = (x.shape[-1],)
    if mode == "batched":
        xhat = F.layer_norm(x, shape, None, None, eps)
        return torch.addcmul(beta.unsqueeze(1), xhat, gamma.unsqueeze(1))
    return torch.stack(
        [F.layer_norm(aligned(x[k]), shape, gamma[k], beta[k], eps) for k in range(x.shape[0])]
    )


def _same_bits(
    batched: Callable[[list[Tensor]], Tensor],
    alone: Callable[[list[Tensor]], Tensor],
    inputs: list[Tensor],
    grad: bool,
) -> bool:
    """Whether ``batched`` (all members) and ``alone`` (member by member, stacked) give the
    same outputs and, with ``grad``, the same gradients of every input."""
    results = []
    for fn in (batched, alone):
        leaves = [t.clone().requires_grad_(grad) for t in inputs]
        with torch.set_grad_enabled(grad):
            out = fn(leaves)
            grads: list[Tensor] = []
            if grad:
                seed = torch.linspace(-1.0, 1.0, out.numel()).reshape(out.shape)
                grads = list(torch.autograd.grad(out, leaves, seed))
        results.append([out.detach(), *grads])
    return all(torch.equal(a, b) for a, b in zip(*results, strict=True))


def _probe_inputs(
    shapes: Sequence[tuple[int, ...]], members: int = _PROBE_MEMBERS, draw: int = 0
) -> list[Tensor]:
    """Draw ``draw`` of a probe's inputs: standard normal tensors ``[members, *shape]``."""
    gen = torch.Generator().manual_seed(draw)
    return [torch.randn(members, *s, generator=gen) for s in shapes]


def _same_bits_on_draws(
    batched: Callable[[list[Tensor]], Tensor],
    alone: Callable[[list[Tensor]], Tensor],
    draws: Sequence[list[Tensor]],
    grad: bool,
) -> bool:
    """:func:`_same_bits` on every one of ``draws``."""
    return all(_same_bits(batched, alone, inputs, grad) for inputs in draws)


def linear_mode(
    rows: int,
    fan_in: int,
    fan_out: int,
    grad: bool,
    members: int = _PROBE_MEMBERS,
    layout: LinearLayout | None = None,
) -> LinearMode:
    """:func:`_linear_mode` for torch's current number of threads; ``layout``: where the
    operands lie (default :meth:`LinearLayout.packed`)."""
    if layout is None:
        layout = LinearLayout.packed(members, rows, fan_in, fan_out)
    return _linear_mode(rows, fan_in, fan_out, grad, members, layout, torch.get_num_threads())


def layer_norm_mode(
    rows: int, units: int, eps: float, grad: bool, members: int = _PROBE_MEMBERS
) -> LayerNormMode:
    """:func:`_layer_norm_mode` for torch's current number of threads."""
    return _layer_norm_mode(rows, units, eps, grad, members, torch.get_num_threads())


@dataclass(frozen=True)
class _LinearProbe:
    """A linear layer's probe in its layout: the leaves are the input's buffer and the
    ``[K, row]`` parameter rows; a form sees views of them as the population's layer does,
    the reference (:meth:`alone`) each member's operands copied where a run alone's lie."""

    members: int
    shape: tuple[int, int, int]  # rows, fan_in, fan_out
    layout: LinearLayout

    def leaves(self, draw: int) -> list[Tensor]:
        lay, (rows, fan_in, _) = self.layout, self.shape
        s0, s1, s2 = lay.x_strides
        extent = (self.members - 1) * s0 + (rows - 1) * s1 + (fan_in - 1) * s2 + 1
        gen = torch.Generator().manual_seed(draw)
        x_buf = torch.randn(lay.x_offset + extent, generator=gen)
        return [x_buf, torch.randn(self.members, lay.row, generator=gen)]

    def operands(self, leaves: list[Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        lay, (rows, fan_in, fan_out) = self.layout, self.shape
        x = leaves[0].as_strided((self.members, rows, fan_in), lay.x_strides, lay.x_offset)
        flat = leaves[1]
        w = flat.as_strided((self.members, fan_out, fan_in), (lay.row, fan_in, 1), lay.w_offset)
        b = flat.as_strided((self.members, fan_out), (lay.row, 1), lay.b_offset)
        return x, w, b

    def form(self, mode: LinearMode, leaves: list[Tensor]) -> Tensor:
        return stacked_linear(*self.operands(leaves), mode)

    def alone(self, leaves: list[Tensor]) -> Tensor:
        lay, (_, fan_in, fan_out) = self.layout, self.shape
        x, _, _ = self.operands(leaves)
        out = []
        for k in range(self.members):
            xk = torch.empty_strided(x.shape[1:], x.stride()[1:])
            xk.copy_(x[k])
            own = torch.empty(lay.row)  # a run alone's flat vector
            own.copy_(leaves[1][k])
            wk = own.as_strided((fan_out, fan_in), (fan_in, 1), lay.w_offset)
            out.append(F.linear(xk, wk, own.as_strided((fan_out,), (1,), lay.b_offset)))
        return torch.stack(out)


@functools.cache
def _linear_mode(
    rows: int,
    fan_in: int,
    fan_out: int,
    grad: bool,
    members: int,
    layout: LinearLayout,
    threads: int,
) -> LinearMode:
    """The first form (:data:`LinearMode`, ``"loop"`` last) that computes what ``F.linear``
    computes for each member laid out as a run alone, bit for bit, for ``members`` x
    ``rows`` inputs of ``fan_in`` features to ``fan_out`` in ``layout`` (outputs and, with
    ``grad``, gradients), on this machine; ``"loop"`` when none does. Probed once per
    process, shape, member count, layout and number of threads, on :data:`_PROBE_DRAWS`
    random draws."""
    probe = _LinearProbe(members, (rows, fan_in, fan_out), layout)
    draws = [probe.leaves(d) for d in range(_PROBE_DRAWS)]
    modes: tuple[LinearMode, ...] = (
        ("bmm", "bmm_t", "bmm_mm", "bmm_t_mm") if grad else ("bmm", "bmm_t")
    )
    for mode in modes:
        if _same_bits_on_draws(functools.partial(probe.form, mode), probe.alone, draws, grad):
            return mode
    return "loop"


@functools.cache
def _layer_norm_mode(
    rows: int, units: int, eps: float, grad: bool, members: int, threads: int
) -> LayerNormMode:
    """``"batched"`` when it computes what ``F.layer_norm`` computes member by member bit
    for bit (as :func:`linear_mode`), else ``"loop"``."""
    draws = []
    for d in range(_PROBE_DRAWS):
        inputs = _probe_inputs([(rows, units), (units,), (units,)], members, d)
        inputs[1] = 1.0 + 0.1 * inputs[1]
        draws.append(inputs)

    def alone(t: list[Tensor]) -> Tensor:
        return stacked_layer_norm(t[0], t[1], t[2], eps, "loop")

    def batched(t: list[Tensor]) -> Tensor:
        return stacked_layer_norm(t[0], t[1], t[2], eps, "batched")

    return "batched" if _same_bits_on_draws(batched, alone, draws, grad) else "loop"


def activation_mode(act: Callable[[Tensor], Tensor], rows: int, units: int, grad: bool) -> str:
    """``"batched"`` when ``act`` on a ``[K, rows, units]`` tensor gives what it gives
    member by member (outputs and, with ``grad``, gradients; vectorised and scalar kernels
    of some functions, e.g. SiLU, round differently, and which elements take which depends
    on the tensor's size), else ``"loop"``."""
    return _activation_mode(act, rows, units, grad, torch.get_num_threads())


@functools.cache
def _activation_mode(
    act: Callable[[Tensor], Tensor], rows: int, units: int, grad: bool, threads: int
) -> str:
    # enough members that a function whose vectorised and scalar kernels round differently
    # shows it (a difference is rare: about one element in fifty for SiLU)
    members = max(_PROBE_MEMBERS, -(-_PROBE_ELEMENTS // (rows * units)))
    (x,) = _probe_inputs([(rows, units)], members)
    x = 3.0 * x

    def alone(t: list[Tensor]) -> Tensor:
        return torch.stack([act(t[0][k]) for k in range(t[0].shape[0])])

    return "batched" if _same_bits(lambda t: act(t[0]), alone, [x], grad) else "loop"


class StackedMLP:
    """K copies of one :class:`~pporpe.nn.mlp.FlatMLP` network, member k with the
    parameter views ``params[i][k]`` (``params``: ``[K, *shape]`` views, in
    ``parameters()`` order, bound at construction), evaluated on inputs ``[K, B, in]``.

    Without gradient, a ``"loop"`` layer is K ``torch.addmm`` calls (what ``F.linear``
    calls) from and into buffers whose per-member views are made once per input shape
    (making K views costs about as much as the K products).
    """

    def __init__(self, net: FlatMLP, params: list[Tensor]) -> None:
        self.ops = net.ops
        self.params = params
        self._members: list[tuple[tuple[Tensor, ...], tuple[Tensor, ...]]] = []
        for op in net.ops:  # member k's (W_k^T, b_k) of every linear layer, as views
            if op.kind != "linear":
                self._members.append(((), ()))
                continue
            w, b = params[op.index].detach(), params[op.index + 1].detach()
            self._members.append((tuple(t.t() for t in w.unbind(0)), b.unbind(0)))
        self._buffers: dict[tuple[int, int, int], _LoopBuffers] = {}

    def __call__(self, x: Tensor) -> Tensor:
        params, grad = self.params, torch.is_grad_enabled()
        rows = x.shape[1]
        for i, op in enumerate(self.ops):
            if op.kind == "linear":
                w, b = params[op.index], params[op.index + 1]
                layout = LinearLayout.of(x, w, b)
                mode = linear_mode(rows, w.shape[2], w.shape[1], grad, w.shape[0], layout)
                if mode == "loop" and not grad:
                    x = self._loop_no_grad(i, x, w.shape[1])
                else:
                    x = stacked_linear(x, w, b, mode)
            elif op.kind == "norm":
                g, b = params[op.index], params[op.index + 1]
                ln_mode = layer_norm_mode(rows, g.shape[1], op.norm_eps, grad, g.shape[0])
                x = stacked_layer_norm(x, g, b, op.norm_eps, ln_mode)
            elif activation_mode(op.act, rows, x.shape[2], grad) == "batched":
                x = op.act(x)
            else:
                x = torch.stack([op.act(xk) for xk in x.unbind(0)])
        return x

    def _loop_no_grad(self, i: int, x: Tensor, fan_out: int) -> Tensor:
        """Linear layer ``i`` member by member (``F.linear``'s ``addmm``), no gradient."""
        key = (i, x.shape[1], x.shape[2])
        if key not in self._buffers:
            self._buffers[key] = _LoopBuffers.make(x, fan_out)
        buf = self._buffers[key]
        wts, bs = self._members[i]
        for xin, xk, wt, b, out in zip(x.unbind(0), buf.x_rows, wts, bs, buf.out_rows, strict=True):
            xk.copy_(xin)
            torch.addmm(b, xk, wt, out=out)
        return torch.stack(buf.out_rows)


@dataclass(frozen=True)
class _LoopBuffers:
    """The inputs and outputs of a member-by-member layer: one tensor per member, each
    allocated on its own (64-byte aligned, as a run alone's activations)."""

    x_rows: tuple[Tensor, ...]
    out_rows: tuple[Tensor, ...]

    @staticmethod
    def make(like: Tensor, fan_out: int) -> _LoopBuffers:
        members, rows, fan_in = like.shape
        x = tuple(like.new_empty(rows, fan_in) for _ in range(members))
        out = tuple(like.new_empty(rows, fan_out) for _ in range(members))
        return _LoopBuffers(x, out)


def backward_quietly(loss: Tensor) -> None:
    """``loss.backward()`` without PyTorch's warning that the gradients of strided parameter
    views (rows of a ``[K, n]`` tensor) do not follow its layout contract: they are
    accumulated in place into the views of a ``[K, n]`` gradient buffer, as intended."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_LAYOUT_WARNING)
        loss.backward()
