"""The figures both reports draw: test scores per seed (Fig. 3), mean curves with 95% bands
(Figs. 4, 5).

Drawn from :class:`.results.Cell` objects, which online and batch grids both give; the batch
report's own figures (by steps, over tasks) are in :mod:`.batch.figures`. Drawn on
:class:`matplotlib.figure.Figure` objects, without pyplot, so that importing or calling this
module leaves the caller's matplotlib backend alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from scipy import stats

from .figures import METHOD_COLORS, METHOD_LABELS, METHOD_STYLES
from .results import Cell, record_value, tasks_of
from .stats import mean_ci

__all__ = [
    "CurvePanel",
    "band",
    "curve_figure",
    "moving_average",
    "panel_figure",
    "summary_figure",
]


def band(curves: list[list[float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and 95% Student-t band over seeds, episode by episode (up to the shortest run)."""
    n = min(len(c) for c in curves)
    arr = np.asarray([c[:n] for c in curves], dtype=np.float64)
    mean = arr.mean(axis=0)
    if arr.shape[0] < 2:
        return mean, mean, mean
    half = stats.t.ppf(0.975, arr.shape[0] - 1) * arr.std(axis=0, ddof=1) / math.sqrt(arr.shape[0])
    return mean, mean - half, mean + half


def moving_average(x: list[float], window: int) -> list[float]:
    """Trailing mean over ``window`` values (fewer at the start)."""
    if window <= 1 or len(x) < 2:
        return list(x)
    out, acc = [], 0.0
    for i, v in enumerate(x):
        acc += v
        if i >= window:
            acc -= x[i - window]
        out.append(acc / min(i + 1, window))
    return out


def _draw_curves(ax: Axes, cells: list[Cell], field: str, smooth: int) -> None:
    """One task's panel: per method, the mean of ``field`` over seeds and its 95% band."""
    for c in cells:
        curves = [
            moving_average([record_value(r, field) for r in recs], smooth)
            for recs in c.curves.values()
            if recs
        ]
        if not curves:
            continue
        mean, lo, hi = band(curves)
        x = np.arange(1, mean.size + 1)
        color = METHOD_COLORS.get(c.method)
        label = f"{METHOD_LABELS.get(c.method, c.method)} (n={len(curves)})"
        ax.plot(x, mean, color=color, ls=METHOD_STYLES.get(c.method, "-"), lw=1.6, label=label)
        ax.fill_between(x, lo, hi, color=color, alpha=0.2, lw=0)


def curve_figure(cells: list[Cell], field: str, ylabel: str, title: str, smooth: int) -> Figure:
    """Per task, the mean over seeds of the per-episode ``field`` (an ``episodes.csv``
    column, :func:`~pporpe.experiments.reports.results.record_value`) of every method, with 95%
    bands, smoothed by a moving average over ``smooth`` episodes."""
    envs = tasks_of(cells)
    panels = [CurvePanel(env, [c for c in cells if c.env == env], smooth) for env in envs]
    return panel_figure(panels, field, ylabel, title)


@dataclass(frozen=True)
class CurvePanel:
    """One panel of :func:`panel_figure`: its title and the cells (one per method) drawn."""

    title: str
    """The panel's title (a task's name, or more: where its runs come from)."""
    cells: list[Cell]
    """The cells of one task, a curve per method."""
    smooth: int
    """Episodes of the trailing moving average (1: none)."""


def panel_figure(panels: list[CurvePanel], field: str, ylabel: str, title: str) -> Figure:
    """A row of panels, each the mean over seeds of the per-episode ``field`` of its cells'
    methods with 95% bands (:func:`curve_figure`'s panels, each with its own title and
    smoothing: panels may come from different grids)."""
    fig = Figure(figsize=(4.2 * len(panels), 3.6))
    axes = fig.subplots(1, len(panels), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        _draw_curves(ax, panel.cells, field, panel.smooth)
        _label_panel(ax, panel.title, "episode", ylabel)
    smooth = {panel.smooth for panel in panels}
    return _titled(fig, title, smooth.pop() if len(smooth) == 1 else 1)


def _label_panel(ax: Axes, env: str, xlabel: str, ylabel: str) -> None:
    """A task's panel titled and labelled, with a legend, or a note that no run of the
    task has finished."""
    ax.set_title(env)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no finished runs yet", ha="center", va="center",
                transform=ax.transAxes)  # fmt: skip


def _titled(fig: Figure, title: str, smooth: int) -> Figure:
    """The figure with its title (what is drawn, the smoothing) and a tight layout."""
    suffix = f"; moving average over {smooth} episodes" if smooth > 1 else ""
    fig.suptitle(f"{title} (mean over seeds, shaded: 95% CI{suffix})")
    fig.tight_layout()
    return fig


def summary_figure(cells: list[Cell]) -> Figure:
    """Per task, each method's test score per seed (dots), their mean and 95% CI (bars)."""
    envs = tasks_of(cells)
    fig = Figure(figsize=(3.6 * len(envs), 3.6))
    axes = fig.subplots(1, len(envs), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=True):
        row = [c for c in cells if c.env == env]
        for i, c in enumerate(row):
            scores = list(c.scores.values())
            mean, lo, hi = mean_ci(scores)
            if scores:
                err = None if math.isnan(lo) else [[mean - lo], [hi - mean]]
                ax.bar(i, mean, color=METHOD_COLORS.get(c.method), alpha=0.7, yerr=err, capsize=5)
                jitter = np.linspace(-0.15, 0.15, len(scores)) if len(scores) > 1 else [0.0]
                ax.scatter(i + np.asarray(jitter), scores, color="k", s=10, zorder=3)
        ax.set_xticks(range(len(row)), [METHOD_LABELS.get(c.method, c.method) for c in row])
        ax.set_title(env)
        ax.set_ylabel("median test return")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("Test score per seed (dots), mean and 95% CI over seeds (bars)")
    fig.tight_layout()
    return fig
