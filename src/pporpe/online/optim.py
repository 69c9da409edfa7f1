"""Deprecated: the old path of td-AmsProp (:class:`TDAmsProp`), now
:mod:`pporpe.online.torch_engine.optim`; this re-export goes in the next release."""

from __future__ import annotations

from .torch_engine.optim import TDAmsProp
from .torch_engine.optim import _fused_works as _fused_works  # the tests' old import

__all__ = ["TDAmsProp"]
