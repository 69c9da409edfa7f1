"""Deprecated: the old path of the fused kernel, now
:mod:`pporpe.online.fused_engine.kernels` (one file per stage). This re-export of its
public names is kept for one release and removed in the one after."""

from __future__ import annotations

from .fused_engine.kernels.head import digamma, head_grad_closed
from .fused_engine.kernels.head import kl_closed as _kl  # noqa: F401 (the tests' old name)
from .fused_engine.kernels.inputs import ACTIVATIONS, C_NAMES, F_NAMES, HEADS, METHOD_CODES
from .fused_engine.kernels.step import fused_begin, fused_forward, fused_step
from .fused_engine.kernels.surrogates import surrogate_closed

__all__ = [
    "ACTIVATIONS",
    "C_NAMES",
    "F_NAMES",
    "HEADS",
    "METHOD_CODES",
    "digamma",
    "fused_begin",
    "fused_forward",
    "fused_step",
    "head_grad_closed",
    "surrogate_closed",
]
