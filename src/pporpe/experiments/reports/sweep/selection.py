"""Stage 1's selection rule: which of a method's settings goes on to stage 2.

A rule is declared in the sweep's spec before any run (``[sweep] select = "..."``) as
``"<statistic>:<metric>"``: the statistic (``iqm`` or ``mean``), over the tasks, of the
min-max normalised values of a metric of :data:`..batch.results.METRICS` (``score``,
``last100``, ``mean_return``) of the tuning seeds. The default, :data:`DEFAULT_RULE`, is the
highest IQM of the normalised mean training return (the area under the learning curve:
what a setting gives over the whole run, less noisy than the final score with few seeds).

The highest value wins; a tie goes to the setting listed first in the spec (the product of
its lists in their order). The report shows the runner-up and says when the chosen value
of a numeric field is the smallest or largest one swept: the best may lie beyond the range.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...sweep_terms import DEFAULT_RULE, RULE_STATISTICS, check_rule
from ..batch.results import METRICS
from ..stats import iqm

__all__ = [
    "DEFAULT_RULE",
    "STATISTICS",
    "Candidate",
    "Rule",
    "Selection",
    "edges",
    "parse_rule",
    "select",
]

STATISTICS = RULE_STATISTICS
"""The statistics a rule can take over the pooled normalised values."""

TIE = 1e-12
"""Values closer than this (relative to the larger, at least 1) are a tie."""


@dataclass(frozen=True)
class Rule:
    """A parsed selection rule."""

    statistic: str
    """``iqm`` or ``mean`` of the normalised values pooled over tasks and seeds."""
    metric: str
    """The :data:`..batch.results.METRICS` key it reads."""

    @property
    def metric_name(self) -> str:
        """The metric's name in the tables (``mean training return``)."""
        return next(m.name for m in METRICS if m.key == self.metric)

    def describe(self) -> str:
        """The rule in words."""
        stat = "IQM" if self.statistic == "iqm" else "mean"
        return (
            f"the highest {stat}, over the tasks, of the min-max normalised {self.metric_name} "
            "of the tuning seeds (a tie goes to the setting listed first in the spec)"
        )

    def value(self, values: Sequence[float]) -> float:
        """The rule's statistic of the pooled normalised ``values`` (NaN without any)."""
        vals = [v for v in values if math.isfinite(v)]
        if not vals:
            return math.nan
        return float(iqm(np.asarray(vals))) if self.statistic == "iqm" else float(np.mean(vals))


def parse_rule(text: Any) -> Rule:
    """``"<statistic>:<metric>"`` as a :class:`Rule` (ValueError naming what is allowed;
    the words are checked by :func:`pporpe.experiments.sweep_terms.check_rule`, which the
    grid's spec also calls)."""
    statistic, metric = check_rule(text)
    return Rule(statistic, metric)


@dataclass(frozen=True)
class Candidate:
    """One setting of a method with the rule's value over its runs."""

    setting: tuple[tuple[str, Any], ...]
    """``(field, value)`` pairs."""
    value: float
    """The rule's statistic (NaN without a finished run)."""
    runs: int
    """Finished runs behind it."""


@dataclass(frozen=True)
class Selection:
    """A method's chosen setting."""

    method: str
    best: Candidate
    runner_up: Candidate | None
    """The next by the rule (None: the method has one setting)."""
    tied: tuple[Candidate, ...]
    """Other settings with the best's value, passed over for being listed later."""
    edges: tuple[str, ...]
    """The chosen values at an edge of their field's range, in words."""


def _tie(a: float, b: float) -> bool:
    return abs(a - b) <= TIE * max(1.0, abs(a), abs(b))


def select(method: str, candidates: Sequence[Candidate]) -> Selection | None:
    """The candidate with the highest value, the first listed among equals (None when no
    candidate has a value)."""
    finite = [i for i, c in enumerate(candidates) if math.isfinite(c.value)]
    if not finite:
        return None
    top = max(candidates[i].value for i in finite)
    tie = {i for i in finite if _tie(candidates[i].value, top)}
    # values within TIE of the highest rank as equals: by spec order
    ranked = sorted(finite, key=lambda i: (-(top if i in tie else candidates[i].value), i))
    best = candidates[ranked[0]]
    runner = candidates[ranked[1]] if len(ranked) > 1 else None
    tied = tuple(candidates[i] for i in ranked[1:] if i in tie)
    return Selection(method, best, runner, tied, edges(best.setting, candidates))


def edges(chosen: tuple[tuple[str, Any], ...], candidates: Sequence[Candidate]) -> tuple[str, ...]:
    """For each numeric field of ``chosen`` swept over two values or more: whether its value
    is the smallest or the largest swept (the best may lie beyond the range)."""
    out = []
    for name, value in chosen:
        if isinstance(value, bool) or not isinstance(value, int | float):
            continue
        swept = {v for c in candidates for n, v in c.setting if n == name}
        if len(swept) < 2:
            continue
        if value == min(swept):
            out.append(f"{name} = {value} is the smallest {name} swept")
        elif value == max(swept):
            out.append(f"{name} = {value} is the largest {name} swept")
    return tuple(out)
