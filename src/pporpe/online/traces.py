"""Deprecated: the old path of the adaptive eligibility traces (:class:`AdaptiveTraces`),
now :mod:`pporpe.online.torch_engine.traces`; this re-export goes in the next release."""

from __future__ import annotations

from .torch_engine.traces import AdaptiveTraces

__all__ = ["AdaptiveTraces"]
