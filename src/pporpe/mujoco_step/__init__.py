"""Deprecated: the old home of :mod:`pporpe.envs.mujoco`.

Kept for one release as a thin re-export of its public names; importing it gives a
:class:`DeprecationWarning`. (A package rather than a module, so that git follows the
old file to its new home.) Import from :mod:`pporpe.envs.mujoco` instead.
"""

from __future__ import annotations

import warnings

from ..envs.mujoco import *  # noqa: F403
from ..envs.mujoco import __all__ as _MUJOCO_ALL

__all__ = list(_MUJOCO_ALL)

warnings.warn(
    "pporpe.mujoco_step is deprecated and will be removed in the next release: import from "
    "pporpe.envs.mujoco",
    DeprecationWarning,
    stacklevel=2,
)
