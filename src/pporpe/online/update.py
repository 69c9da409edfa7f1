"""Deprecated: the old path of the torch engine's elementwise update, now
:mod:`pporpe.online.torch_engine.update`. This re-export is kept for one release and
removed in the one after."""

from __future__ import annotations

from .torch_engine.update import (
    opt_scalars,
    trace_scalars,
    tsoft_rates,
    update_chunk,
    update_moments,
    update_momentum,
    update_target,
)

__all__ = [
    "opt_scalars",
    "trace_scalars",
    "tsoft_rates",
    "update_chunk",
    "update_moments",
    "update_momentum",
    "update_target",
]
