"""Fully connected networks as used in the paper (Sec. IV-A, Table I).

The paper's actor and critic are 5 fully connected layers of 100 units, each
followed by layer normalisation and Swish (``x * sigmoid(x)``), and a linear
output layer. :func:`mlp` builds exactly that by default::

    Linear(in_dim, units) -> LayerNorm -> Swish      # hidden block 1
    ...                                              # `layers` blocks in all
    Linear(units, out_dim)                           # output

Initialisation (``init``):

* ``"default"`` (default): PyTorch's own initialisation of ``nn.Linear`` and
  ``nn.LayerNorm``.
* ``"orthogonal"``: hidden weights orthogonal with the gain suited to the
  activation (ReLU sqrt(2), tanh 5/3, Swish 1), all biases zero, output weights
  orthogonal with gain ``output_gain`` (1 when not given).

``output_gain`` (with ``"default"``) multiplies the output layer's weights and
zeroes its bias; a small value such as 0.01 starts a policy near its
state-independent centre (``loc`` ~ 0, ``softplus(0)`` scale) and a critic near 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config import ACTIVATIONS, check_positive_int

__all__ = ["ACTIVATIONS", "INITS", "FlatMLP", "flat_views", "mlp", "mlp_num_params"]

INITS: tuple[str, ...] = ("default", "orthogonal")
"""Allowed initialisation schemes of :func:`mlp`."""

_GAINS: dict[str, float] = {"swish": 1.0, "relu": math.sqrt(2.0), "tanh": 5.0 / 3.0}


def _activation(name: str) -> nn.Module:
    """Return a fresh activation module for an allowed name."""
    if name == "swish":
        return nn.SiLU()
    if name == "relu":
        return nn.ReLU()
    return nn.Tanh()


def mlp(
    in_dim: int,
    out_dim: int,
    layers: int = 5,
    units: int = 100,
    layer_norm: bool = True,
    activation: str = "swish",
    init: str = "default",
    output_gain: float | None = None,
) -> nn.Sequential:
    """Build a multilayer perceptron with ``layers`` hidden blocks.

    Each hidden block is ``Linear(units)`` -> ``LayerNorm(units)`` (if
    ``layer_norm``) -> activation; a final ``Linear(out_dim)`` follows, with no
    activation. The defaults are the paper's (5 x 100, LayerNorm, Swish).

    Args:
        in_dim: input features (positive int).
        out_dim: output features (positive int).
        layers: number of hidden blocks (positive int).
        units: width of every hidden block (positive int).
        layer_norm: put ``nn.LayerNorm`` after every hidden ``Linear``.
        activation: one of :data:`ACTIVATIONS` (``"swish"``, ``"relu"``, ``"tanh"``).
        init: one of :data:`INITS`; see the module docstring.
        output_gain: scale of the output layer's weights (see module docstring);
            None leaves ``"default"`` untouched and means gain 1 for ``"orthogonal"``.

    Raises:
        ValueError: naming the bad parameter and, where relevant, the allowed values.
    """
    _check_mlp_args(in_dim, out_dim, layers, units, activation, init, output_gain)
    modules: list[nn.Module] = []
    hidden: list[nn.Linear] = []
    width = in_dim
    for _ in range(layers):
        linear = nn.Linear(width, units)
        hidden.append(linear)
        modules.append(linear)
        if layer_norm:
            modules.append(nn.LayerNorm(units))
        modules.append(_activation(activation))
        width = units
    output = nn.Linear(width, out_dim)
    modules.append(output)
    _initialise(hidden, output, activation, init, output_gain)
    return nn.Sequential(*modules)


def _check_mlp_args(
    in_dim: int, out_dim: int, layers: int, units: int, activation: str, init: str,
    output_gain: float | None,
) -> None:  # fmt: skip
    """ValueError naming the first bad argument of :func:`mlp`."""
    check_positive_int("in_dim", in_dim)
    check_positive_int("out_dim", out_dim)
    check_positive_int("layers", layers)
    check_positive_int("units", units)
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {ACTIVATIONS}, got {activation!r}")
    if init not in INITS:
        raise ValueError(f"init must be one of {INITS}, got {init!r}")
    if output_gain is not None and not (math.isfinite(output_gain) and output_gain >= 0):
        raise ValueError(f"output_gain must be a finite number >= 0, got {output_gain!r}")


def _initialise(
    hidden: list[nn.Linear], output: nn.Linear, activation: str, init: str,
    output_gain: float | None,
) -> None:  # fmt: skip
    """:func:`mlp`'s ``init`` and ``output_gain`` (the module docstring says what they do)."""
    if init == "orthogonal":
        for linear in hidden:
            nn.init.orthogonal_(linear.weight, gain=_GAINS[activation])
            nn.init.zeros_(linear.bias)
        nn.init.orthogonal_(output.weight, gain=1.0 if output_gain is None else output_gain)
        nn.init.zeros_(output.bias)
    elif output_gain is not None:
        with torch.no_grad():
            output.weight.mul_(output_gain)
            output.bias.zero_()


def mlp_num_params(
    in_dim: int, out_dim: int, layers: int = 5, units: int = 100, layer_norm: bool = True
) -> int:
    """Return the number of trainable parameters of ``mlp`` with these sizes.

    ``(in_dim + 1) * units + (layers - 1) * (units + 1) * units
    + (units + 1) * out_dim``, plus ``2 * units * layers`` for the LayerNorms.
    """
    count = (in_dim + 1) * units + (layers - 1) * (units + 1) * units + (units + 1) * out_dim
    if layer_norm:
        count += 2 * units * layers
    return count


def flat_views(flat: torch.Tensor, shapes: Sequence[torch.Size]) -> list[torch.Tensor]:
    """Consecutive views of a 1-D tensor with the given shapes (no copy).

    The learners keep all parameters of their networks in one flat tensor; these views
    are the per-layer weights that the networks are evaluated with.
    """
    out, offset = [], 0
    for shape in shapes:
        n = math.prod(shape)
        out.append(flat[offset : offset + n].view(shape))
        offset += n
    if offset != flat.numel():
        raise ValueError(f"shapes cover {offset} elements but the tensor has {flat.numel()}")
    return out


_ACTS = {nn.SiLU: F.silu, nn.ReLU: F.relu, nn.Tanh: torch.tanh}


@dataclass(frozen=True)
class _Op:
    kind: str  # "linear", "norm" or "act"
    index: int = -1  # position of the weight in the parameter list (bias follows)
    norm_eps: float = 0.0
    norm_shape: tuple[int, ...] = ()
    act: Any = None


class FlatMLP:
    """Evaluates an ``nn.Sequential`` of Linear / LayerNorm / activation layers functionally.

    The parameters are passed as a list of tensors in ``module.parameters()`` order, so
    they can be views into one flat vector (and ``torch.func`` can differentiate them).
    """

    def __init__(self, module: nn.Sequential) -> None:
        self.ops: list[_Op] = []
        index = 0
        for layer in module:
            if isinstance(layer, nn.Linear):
                self.ops.append(_Op("linear", index))
                index += 2
            elif isinstance(layer, nn.LayerNorm):
                self.ops.append(_Op("norm", index, layer.eps, tuple(layer.normalized_shape)))
                index += 2
            elif type(layer) in _ACTS:
                self.ops.append(_Op("act", act=_ACTS[type(layer)]))
            else:
                raise TypeError(f"FlatMLP cannot evaluate layer {layer!r}")
        self.num_tensors = index

    def __call__(self, params: list[Tensor], x: Tensor) -> Tensor:
        for op in self.ops:
            if op.kind == "linear":
                x = F.linear(x, params[op.index], params[op.index + 1])
            elif op.kind == "norm":
                x = F.layer_norm(
                    x, op.norm_shape, params[op.index], params[op.index + 1], op.norm_eps
                )
            else:
                x = op.act(x)
        return x
