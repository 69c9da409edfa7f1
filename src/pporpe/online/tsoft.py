"""Deprecated: the old path of the t-soft target update (:class:`TSoftUpdate`), now
:mod:`pporpe.online.torch_engine.tsoft`. This re-export is kept for one release and
removed in the one after."""

from __future__ import annotations

from .torch_engine.tsoft import TSoftUpdate

__all__ = ["TSoftUpdate"]
