"""Deprecated: the old path of the adaptive eligibility traces (:class:`AdaptiveTraces`),
now :mod:`pporpe.online.torch_engine.traces`. This re-export is kept for one release and
removed in the one after."""

from __future__ import annotations

from .torch_engine.traces import AdaptiveTraces

__all__ = ["AdaptiveTraces"]
