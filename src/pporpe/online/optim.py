"""Deprecated: the old path of td-AmsProp (:class:`TDAmsProp`), now
:mod:`pporpe.online.torch_engine.optim`. This re-export is kept for one release and
removed in the one after."""

from __future__ import annotations

from .torch_engine.optim import TDAmsProp

__all__ = ["TDAmsProp"]
