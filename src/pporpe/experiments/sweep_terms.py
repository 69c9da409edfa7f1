"""What the grids and the reports both know of a sweep: a cell's setting and folder name,
the ``"sweep"`` record of ``grid.json``, and the words of a selection rule.

The grids (:mod:`.grids.sweep`) write these and the reports (:mod:`.reports.sweep`) read
them; neither room imports the other, so both import them from here, and this module
imports nothing of either.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = [
    "DEFAULT_RULE",
    "RULE_METRICS",
    "RULE_STATISTICS",
    "Setting",
    "cell_name",
    "check_rule",
    "sweep_of",
    "value_text",
]

Setting = tuple[tuple[str, Any], ...]
"""One combination of a method's swept settings: ``(field, value)`` pairs in spec order."""

DEFAULT_RULE = "iqm:mean_return"
"""The highest IQM over the tasks of the normalised mean training return."""

RULE_STATISTICS = ("iqm", "mean")
"""The statistics a rule can take over the pooled normalised values."""

RULE_METRICS = ("score", "last100", "mean_return")
"""The metrics a rule can read: the keys of the batch report's numbers per run
(:data:`pporpe.experiments.reports.batch.results.METRICS`, which a test holds equal)."""


def check_rule(text: Any) -> tuple[str, str]:
    """``"<statistic>:<metric>"`` split into its statistic and metric (ValueError naming
    what is allowed)."""
    allowed = (
        f"'<statistic>:<metric>' with a statistic of {list(RULE_STATISTICS)} and a metric of "
        f"{list(RULE_METRICS)}"
    )
    if not isinstance(text, str) or text.count(":") != 1:
        raise ValueError(f"must be {allowed}; got {text!r}")
    statistic, metric = text.split(":")
    if statistic not in RULE_STATISTICS or metric not in RULE_METRICS:
        raise ValueError(f"must be {allowed}; got {text!r}")
    return statistic, metric


def value_text(value: Any) -> str:
    """A swept value as it stands in a folder's name: ``true``/``false``, an int, a float
    by ``repr`` (``0.0003``, ``1e-05``: distinct floats give distinct names), or a string."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def cell_name(method: str, setting: Setting) -> str:
    """The folder of a sweep cell under its task: ``rpe-eps0.2-lr0.0003``; the method's
    name alone without a setting (a grid without a sweep)."""
    return method + "".join(f"-{name}{value_text(v)}" for name, v in setting)


def sweep_of(grid: Mapping[str, Any]) -> dict[str, Any] | None:
    """The ``"sweep"`` record of a ``grid.json`` (None for a grid without a sweep)."""
    sweep = grid.get("sweep")
    return sweep if isinstance(sweep, dict) else None
