"""The figures of a sweep's report (:mod:`.sensitivity`), drawn without pyplot.

* :func:`sensitivity_figure`: per method (a column), the rule's metric against the swept eps
  (or the first swept field), a line per value of the other swept fields (lr): on each task
  (a row) the mean over seeds with a band from the lowest to the highest seed, and pooled
  over the tasks (the last row) the rule's value of the normalised values with its 95% CI;
  a star marks the setting selected;
* :func:`trust_region_figure`: per task, every run's metric against its mean approximate KL
  and its mean abs(rho - 1) over its updates, coloured by method: which method does better
  at the same size of update, rather than at the same eps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ...sweep_terms import Setting, value_text
from ..figures import METHOD_COLORS, METHOD_LABELS
from .results import TRUST_FIELDS, PooledCell, SweepCell, SweepStatistics

__all__ = ["TRUST_LABELS", "sensitivity_figure", "trust_region_figure", "x_field"]

TRUST_LABELS = {
    "approx_kl": "mean approximate KL",
    "ratio_dev": "mean abs(rho - 1)",
    "past_threshold": "share of samples past the threshold",
}
"""How the figures and tables name :data:`.results.TRUST_FIELDS`."""


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def x_field(settings: Sequence[Setting]) -> str | None:
    """The field a method's sensitivity is drawn against: ``eps`` if swept, else the first
    swept field (None: nothing swept)."""
    names = list(dict.fromkeys(n for s in settings for n, _ in s))
    return "eps" if "eps" in names else (names[0] if names else None)


def _lines(settings: Sequence[Setting], xf: str | None) -> dict[str, list[tuple[Any, Setting]]]:
    """The settings grouped into lines by their fields other than ``xf``: each line's label
    and its ``(x value, setting)`` points in spec order."""
    lines: dict[str, list[tuple[Any, Setting]]] = {}
    for s in settings:
        rest = ", ".join(f"{n} {value_text(v)}" for n, v in s if n != xf)
        x = dict(s).get(xf) if xf else None
        lines.setdefault(rest, []).append((x, s))
    return lines


def _positions(points: list[tuple[Any, Setting]], ticks: list[Any]) -> list[float]:
    """Where a line's points go on the x axis: their values when every tick is a number,
    else their places among the ticks."""
    numeric = all(isinstance(t, int | float) and not isinstance(t, bool) for t in ticks)
    return [float(x) if numeric else float(ticks.index(x)) for x, _ in points]


def _draw_line(ax: Axes, xs: list[float], ys: list[tuple[float, float, float]], label: str,
               marks: list[bool]) -> None:  # fmt: skip
    order = np.argsort(xs)
    x = np.asarray(xs)[order]
    mid, low, high = (np.asarray([y[k] for y in ys])[order] for k in range(3))
    (line,) = ax.plot(x, mid, marker="o", ms=3, label=label or None)
    ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2, lw=0)
    for xi, yi, mark in zip(xs, (y[0] for y in ys), marks, strict=True):
        if mark:
            ax.plot([xi], [yi], marker="*", ms=12, color=line.get_color(), mec="black")


def _task_point(cells: Sequence[SweepCell], env: str, method: str, setting: Setting,
                metric: str) -> tuple[float, float, float]:  # fmt: skip
    """Mean over seeds, lowest and highest seed (NaN without a finished run)."""
    cell = next((c for c in cells if (c.env, c.method, c.setting) == (env, method, setting)),
                None)  # fmt: skip
    vals = list(cell.values(metric).values()) if cell else []
    if not vals:
        return math.nan, math.nan, math.nan
    return float(np.mean(vals)), min(vals), max(vals)


def _pooled_point(p: PooledCell) -> tuple[float, float, float]:
    return (p.value.value, p.value.low, p.value.high) if p.value else (math.nan,) * 3


def _method_column(fig_axes: list[Axes], stats: SweepStatistics, method: str) -> None:
    """One method's panels: a row per task, then the pooled row."""
    pooled = [p for p in stats.pooled if p.method == method]
    settings = [p.setting for p in pooled]
    xf = x_field(settings)
    ticks = list(dict.fromkeys(dict(s).get(xf) for s in settings)) if xf else [None]
    chosen = stats.selections.get(method)
    for row, ax in enumerate(fig_axes):
        env = stats.tasks[row] if row < len(stats.tasks) else None
        for label, points in _lines(settings, xf).items():
            xs = _positions(points, ticks)
            ys = [_task_point(stats.cells, env, method, s, stats.rule.metric) if env
                  else _pooled_point(next(p for p in pooled if p.setting == s))
                  for _, s in points]  # fmt: skip
            marks = [chosen is not None and s == chosen.best.setting for _, s in points]
            _draw_line(ax, xs, ys, label, marks)
        if not all(isinstance(t, int | float) and not isinstance(t, bool) for t in ticks):
            ax.set_xticks(range(len(ticks)), [value_text(t) if xf else "-" for t in ticks])
        ax.grid(alpha=0.3)
        if row == 0:
            ax.set_title(_label(method))
        if row == len(fig_axes) - 1:
            ax.set_xlabel(xf or "(nothing swept)")
        if any(lbl for lbl in _lines(settings, xf)) and row == 0:
            ax.legend(fontsize=7)


def sensitivity_figure(stats: SweepStatistics) -> Figure:
    """Each method's sensitivity per task and pooled over the tasks (a column per method)."""
    methods = list(dict.fromkeys(p.method for p in stats.pooled))
    rows = len(stats.tasks) + 1
    fig = Figure(figsize=(3.4 * len(methods), 2.5 * rows))
    axes = fig.subplots(rows, len(methods), squeeze=False)
    for col, method in enumerate(methods):
        _method_column([axes[r][col] for r in range(rows)], stats, method)
    stat = "IQM" if stats.rule.statistic == "iqm" else "mean"
    for r in range(rows):
        name = stats.tasks[r] if r < len(stats.tasks) else f"pooled: {stat}, normalised"
        axes[r][0].set_ylabel(f"{name}\n{stats.rule.metric_name}", fontsize=8)
    fig.suptitle("Sensitivity: per task, mean over seeds (band: lowest to highest seed); "
                 "pooled, 95% CI; star: selected", fontsize=10)  # fmt: skip
    fig.tight_layout()
    return fig


def trust_region_figure(stats: SweepStatistics) -> Figure:
    """Per task, every run's metric against its mean approximate KL (left) and mean
    abs(rho - 1) (right) over its updates, a colour per method."""
    fields = TRUST_FIELDS[:2]
    tasks = stats.tasks
    fig = Figure(figsize=(8.0, 2.8 * len(tasks)))
    axes = fig.subplots(len(tasks), len(fields), squeeze=False)
    methods = list(dict.fromkeys(c.method for c in stats.cells))
    for row, env in enumerate(tasks):
        for col, name in enumerate(fields):
            ax = axes[row][col]
            drawn = False
            for method in methods:
                runs = [r for c in stats.cells if c.env == env and c.method == method
                        for r in c.runs]  # fmt: skip
                pts = [(r.trust[name], r.values[stats.rule.metric]) for r in runs]
                pts = [(x, y) for x, y in pts if math.isfinite(x) and math.isfinite(y)]
                if pts:
                    xs, ys = zip(*pts, strict=True)
                    ax.scatter(xs, ys, s=14, color=METHOD_COLORS.get(method),
                               label=_label(method), alpha=0.8)  # fmt: skip
                    drawn = True
            if not drawn:
                ax.text(0.5, 0.5, "no updates.csv", ha="center", va="center",
                        transform=ax.transAxes)  # fmt: skip
            elif name == "approx_kl" and all(x > 0 for c in ax.collections
                                             for x in c.get_offsets()[:, 0]):  # fmt: skip
                ax.set_xscale("log")
            ax.set_xlabel(TRUST_LABELS[name])
            ax.set_ylabel(f"{env}\n{stats.rule.metric_name}", fontsize=8)
            ax.grid(alpha=0.3)
            if drawn and row == 0 and col == 0:
                ax.legend(fontsize=7)
    fig.suptitle("Matched trust regions: each run's score against the size of its updates",
                 fontsize=10)  # fmt: skip
    fig.tight_layout()
    return fig
