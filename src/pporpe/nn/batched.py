r"""Stacked parameter layout and a batched MLP with a hand-written backward for one row.

Every network of the population (K policy nets, K value nets, K target nets) is stored
in one tensor ``P`` of shape ``[3, K, n_pad]``: ``P[0]`` policies, ``P[1]`` values,
``P[2]`` targets. ``P.view(3K, n_pad)`` is then a batch of 3K networks with one common
layout, evaluated with ``torch.baddbmm`` in one chain.

Layout of one network (:class:`NetLayout`). The tensors follow ``module.parameters()``
order of :func:`pporpe.nn.mlp.mlp`: per hidden layer ``W [units, in], b [units]``, then
(with LayerNorm) ``gamma [units], beta [units]``; finally ``W_out [raw_dim, units],
b_out [raw_dim]``. Every tensor's region is padded to a whole number of rows of
``units`` elements, so per-tensor statistics (t-momentum) are row sums plus an
``index_add`` over rows. The value network has one real output; its output layer is
padded to ``raw_dim`` rows (row 0 is real), and the padding stays exactly zero: its
gradient is ``0 * h = 0`` and the optimiser leaves zero-gradient elements at zero.

Hidden block ``l`` of the forward pass, for input ``h`` (rows ``[B, R, in]``)::

    z    = h W^T + b                                  (baddbmm)
    xhat = (z - mean(z)) * rstd,  rstd = 1 / sqrt(var(z) + ln_eps)
    y    = gamma * xhat + beta                        (LayerNorm, affine)
    a    = act(y)                                     (swish = y * sigmoid(y), relu, tanh)

and the output is ``a_L W_out^T + b_out``. The backward (:func:`backward_row0`) is
written for row 0 of each net only (row 1, s_{t+1}, carries no gradient)::

    dy     = da * act'(y)          swish' = s (1 + y (1 - s)), s = sigmoid(y)
    dgamma = dy * xhat,  dbeta = dy,  dxhat = dy * gamma
    dz     = rstd * (dxhat - mean(dxhat) - xhat * mean(dxhat * xhat))
    dW     = dz^T h  (an outer product for one row),  db = dz,  dh = dz W
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["LN_EPS", "NetLayout", "backward_row0", "forward_chain"]

LN_EPS = 1e-5
"""Epsilon of ``nn.LayerNorm`` (its default, used by :func:`pporpe.nn.mlp.mlp`)."""


@dataclass(frozen=True)
class TensorSlot:
    """One parameter tensor inside the padded layout of a network."""

    offset: int
    """First element of the tensor's region."""
    shape: tuple[int, ...]
    """Shape used by the batched forward (value output padded to ``raw_dim`` rows)."""
    rows: int
    """Region size in rows of ``units`` elements."""
    real: tuple[int, int]
    """Number of real (unpadded) elements for the (policy, value) network."""

    @property
    def numel(self) -> int:
        """Elements used by the forward (``prod(shape)``)."""
        return math.prod(self.shape)


def _next_slot(
    placed: list[TensorSlot], shape: tuple[int, ...], units: int, real_value: int | None
) -> TensorSlot:
    """The slot of a tensor of ``shape`` after the ``placed`` ones: at the next row of
    ``units`` elements; ``real_value`` the value network's real elements (default: all)."""
    offset = sum(s.rows for s in placed) * units
    n = math.prod(shape)
    return TensorSlot(offset, shape, -(-n // units), (n, n if real_value is None else real_value))


class NetLayout:
    """Padded common layout of the policy / value / target networks of one population.

    Args:
        obs_dim: input features.
        raw_dim: policy output size (the value net's single output is padded to it).
        layers, units, layer_norm: as in :func:`pporpe.nn.mlp.mlp`.
        head_parts: sizes of the parts of the policy output (e.g. location, scale, degrees
            of freedom) whose weights and biases count as separate tensors for the
            t-momentum (:attr:`segments`); None: the output layer is one weight and one bias.
    """

    def __init__(
        self,
        obs_dim: int,
        raw_dim: int,
        layers: int,
        units: int,
        layer_norm: bool,
        head_parts: tuple[int, ...] | None = None,
    ) -> None:
        self.obs_dim, self.raw_dim = obs_dim, raw_dim
        self.layers, self.units, self.layer_norm = layers, units, layer_norm
        self._place_tensors()
        self.n_rows = self.n_pad // units
        seg = torch.empty(self.n_rows, dtype=torch.int64)
        for i, s in enumerate(self.slots):
            seg[s.offset // units : s.offset // units + s.rows] = i
        self.row_seg = seg
        """Segment (tensor) index of every row of ``units`` elements."""
        self.segments: tuple[tuple[int, int], ...] = tuple(s.real for s in self.slots)
        """Real elements (policy, value) of every segment: the tensors of the t-momentum."""
        self.col_seg: Tensor | None = None
        """With ``head_parts``: the segment of every column of the output bias's row."""
        self.bias_row = self.out_b.offset // units
        """The row of the output bias."""
        if head_parts is not None:
            self._split_head(head_parts)
        self.n_seg = len(self.segments)
        self._index_real_elements()

    def _place_tensors(self) -> None:
        """Every parameter tensor at its offset, each starting a row of ``units``: the hidden
        layers' weight, bias and LayerNorm scale and shift, then the output layer."""
        units, slots = self.units, list[TensorSlot]()
        shapes: list[tuple[tuple[int, ...], int | None]] = []
        width = self.obs_dim
        for _ in range(self.layers):
            shapes += [((units, width), None), ((units,), None)]
            shapes += [((units,), None)] * (2 if self.layer_norm else 0)
            width = units
        shapes += [((self.raw_dim, units), units), ((self.raw_dim,), 1)]
        for shape, real_value in shapes:
            slots.append(_next_slot(slots, shape, units, real_value))
        per_layer = 4 if self.layer_norm else 2
        self.hidden: list[tuple[TensorSlot, TensorSlot, TensorSlot | None, TensorSlot | None]] = []
        for first in range(0, self.layers * per_layer, per_layer):
            w, b = slots[first], slots[first + 1]
            g, be = (slots[first + 2], slots[first + 3]) if self.layer_norm else (None, None)
            self.hidden.append((w, b, g, be))
        self.out_w, self.out_b = slots[-2], slots[-1]
        self.slots: tuple[TensorSlot, ...] = tuple(slots)
        self.n_pad = sum(s.rows for s in slots) * units

    def _index_real_elements(self) -> None:
        slots, units = self.slots, self.units
        self.n_real = (sum(s.real[0] for s in slots), sum(s.real[1] for s in slots))
        """Number of real parameters of the (policy, value) network."""
        idx: list[Tensor] = []
        for j in range(2):
            idx.append(torch.cat([torch.arange(s.offset, s.offset + s.real[j]) for s in slots]))
        self.real_index = (idx[0], idx[1])
        """Positions of the real elements, in ``module.parameters()`` order, per net kind."""
        self.norm_rows = torch.tensor(
            [s.offset // units for h in self.hidden for s in h[2:] if s is not None],
            dtype=torch.int64,
        )
        """Rows of the LayerNorm scales and shifts (one row each)."""

    def _split_head(self, parts: tuple[int, ...]) -> None:
        """The output layer as one tensor pair per part of the output (``parts`` sizes, in
        order; the value's one output lies in the first): weight rows and bias columns of
        part j form their own segments, so the t-momentum treats them as separate layers."""
        units, raw = self.units, self.raw_dim
        if sum(parts) != raw or min(parts) < 1 or raw > units:
            raise ValueError(f"head_parts must be sizes >= 1 summing to raw_dim {raw} <= units")
        base = len(self.segments) - 2  # the joint output weight and bias were the last two
        part_of = torch.cat([torch.full((n,), j, dtype=torch.int64) for j, n in enumerate(parts)])
        first_w = self.out_w.offset // units
        self.row_seg[first_w : first_w + raw] = base + part_of
        bias_segs = base + len(parts) + part_of
        self.col_seg = torch.cat([bias_segs, torch.full((units - raw,), int(bias_segs[0]))])
        self.row_seg[self.bias_row] = int(bias_segs[0])
        weights = [(n * units, units if j == 0 else 0) for j, n in enumerate(parts)]
        biases = [(n, 1 if j == 0 else 0) for j, n in enumerate(parts)]
        self.segments = (*self.segments[:base], *weights, *biases)

    def view(self, flat: Tensor, slot: TensorSlot) -> Tensor:
        """The ``[B, *slot.shape]`` view of ``slot`` inside ``flat`` of shape ``[B, n_pad]``."""
        return flat[:, slot.offset : slot.offset + slot.numel].view(-1, *slot.shape)

    def pack(self, params: list[Tensor], kind: int) -> Tensor:
        """A padded ``[n_pad]`` vector from a net's parameter list (kind 0 policy, 1 value)."""
        out = torch.zeros(self.n_pad)
        if len(params) != len(self.slots):
            raise ValueError(f"expected {len(self.slots)} parameter tensors, got {len(params)}")
        for p, s in zip(params, self.slots, strict=True):
            if p.numel() != s.real[kind]:
                raise ValueError(f"parameter of {p.numel()} elements where {s.real[kind]} expected")
            out[s.offset : s.offset + s.real[kind]] = p.detach().reshape(-1)
        return out


def _act(name: str, y: Tensor) -> Tensor:
    if name == "swish":
        return F.silu(y)
    if name == "relu":
        return F.relu(y)
    if name == "tanh":
        return torch.tanh(y)
    raise ValueError(f"unknown activation {name!r}")


def _act_grad(name: str, y: Tensor, da: Tensor) -> Tensor:
    """``da * act'(y)``."""
    if name == "swish":
        s = torch.sigmoid(y)
        return da * (s * (1.0 + y * (1.0 - s)))
    if name == "relu":
        return da * (y > 0).to(da.dtype)
    t = torch.tanh(y)
    return da * (1.0 - t * t)


@dataclass
class ForwardCache:
    """Row-0 intermediates of the first ``keep`` nets, for :func:`backward_row0`."""

    inputs: list[Tensor]  # input of every linear layer (hidden and output), [keep, in]
    xhat: list[Tensor | None]
    rstd: list[Tensor | None]
    pre_act: list[Tensor]  # y, input of the activation, [keep, units]


def forward_chain(
    flat: Tensor, x: Tensor, lay: NetLayout, activation: str, keep: int = 0
) -> tuple[Tensor, ForwardCache | None]:
    """Evaluate B stacked networks on their own rows (the forward pass).

    Args:
        flat: ``[B, n_pad]`` parameters (e.g. ``P.view(3K, n_pad)`` or a leading slice).
        x: ``[B, R, obs_dim]`` inputs.
        lay: the layout.
        activation: ``"swish"``, ``"relu"`` or ``"tanh"``.
        keep: keep row-0 intermediates of nets ``0 .. keep-1`` for the backward (0: none).

    Returns:
        ``[B, R, raw_dim]`` outputs and the cache (None when ``keep == 0``).
    """
    cache = ForwardCache([], [], [], []) if keep else None
    h = x
    for w, b, g, be in lay.hidden:
        if cache is not None:
            cache.inputs.append(h[:keep, 0].contiguous())
        z = torch.baddbmm(lay.view(flat, b).unsqueeze(1), h, lay.view(flat, w).transpose(1, 2))
        if g is not None and be is not None:
            xhat, _, rstd = torch.native_layer_norm(z, [lay.units], None, None, LN_EPS)
            y = torch.addcmul(lay.view(flat, be).unsqueeze(1), xhat, lay.view(flat, g).unsqueeze(1))
            if cache is not None:
                cache.xhat.append(xhat[:keep, 0].contiguous())
                cache.rstd.append(rstd[:keep, 0].contiguous())
        else:
            y = z
            if cache is not None:
                cache.xhat.append(None)
                cache.rstd.append(None)
        if cache is not None:
            cache.pre_act.append(y[:keep, 0].contiguous())
        h = _act(activation, y)
    if cache is not None:
        cache.inputs.append(h[:keep, 0].contiguous())
    out = torch.baddbmm(
        lay.view(flat, lay.out_b).unsqueeze(1), h, lay.view(flat, lay.out_w).transpose(1, 2)
    )
    return out, cache


def backward_row0(
    flat: Tensor,
    grad: Tensor,
    dout: Tensor,
    cache: ForwardCache,
    lay: NetLayout,
    activation: str,
) -> None:
    """Write d(sum_b dout_b . out_b[row 0]) / d params of nets ``0 .. keep-1`` into ``grad``.

    Args:
        flat: ``[>= keep, n_pad]`` parameters used by :func:`forward_chain`.
        grad: ``[keep, n_pad]`` output buffer; every real element (and the value output's
            padded rows) is overwritten, the padding of bias regions is not touched.
        dout: ``[keep, raw_dim]`` gradient of the loss w.r.t. row 0 of the outputs.
        cache: from :func:`forward_chain` with the same ``keep``.
    """
    keep = dout.shape[0]
    f = flat[:keep]
    h = cache.inputs[-1]
    torch.mul(dout.unsqueeze(2), h.unsqueeze(1), out=lay.view(grad, lay.out_w))
    lay.view(grad, lay.out_b).copy_(dout)
    dh = torch.bmm(dout.unsqueeze(1), lay.view(f, lay.out_w)).squeeze(1)
    for i in range(lay.layers - 1, -1, -1):
        w, b, g, be = lay.hidden[i]
        dy = _act_grad(activation, cache.pre_act[i], dh)
        xhat, rstd = cache.xhat[i], cache.rstd[i]
        if g is not None and be is not None and xhat is not None and rstd is not None:
            torch.mul(dy, xhat, out=lay.view(grad, g))
            lay.view(grad, be).copy_(dy)
            dxhat = dy * lay.view(f, g)
            mean1 = dxhat.mean(-1, keepdim=True)
            mean2 = (dxhat * xhat).mean(-1, keepdim=True)
            dz = rstd * (dxhat - mean1 - xhat * mean2)
        else:
            dz = dy
        torch.mul(dz.unsqueeze(2), cache.inputs[i].unsqueeze(1), out=lay.view(grad, w))
        lay.view(grad, b).copy_(dz)
        if i > 0:
            dh = torch.bmm(dz.unsqueeze(1), lay.view(f, w)).squeeze(1)
