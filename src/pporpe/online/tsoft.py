"""Deprecated: the old path of the t-soft target update (:class:`TSoftUpdate`), now
:mod:`pporpe.online.torch_engine.tsoft`; this re-export goes in the next release."""

from __future__ import annotations

from .torch_engine.tsoft import TSoftUpdate

__all__ = ["TSoftUpdate"]
