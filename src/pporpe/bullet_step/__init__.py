"""Deprecated: the old home of :mod:`pporpe.envs.bullet` (and :mod:`pporpe.envs.side_by_side`).

Kept for one release as a thin re-export of their public names; importing it gives a
:class:`DeprecationWarning`. (A package rather than a module, so that git follows the
old file to its new home.) Import from :mod:`pporpe.envs.bullet` instead.
"""

from __future__ import annotations

import warnings

from ..envs.bullet import *  # noqa: F403
from ..envs.bullet import __all__ as _BULLET_ALL
from ..envs.side_by_side import SideBySide, side_by_side

__all__ = [*_BULLET_ALL, "SideBySide", "side_by_side"]

warnings.warn(
    "pporpe.bullet_step is deprecated and will be removed in the next release: import from "
    "pporpe.envs.bullet (side_by_side from pporpe.envs.side_by_side)",
    DeprecationWarning,
    stacklevel=2,
)
