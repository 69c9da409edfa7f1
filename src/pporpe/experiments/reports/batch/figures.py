"""The batch report's own figures: learning curves over environment steps, and the aggregate
over tasks as rliable draws it.

Drawn on :class:`matplotlib.figure.Figure` objects, without pyplot (as :mod:`..plots`, whose
bands, moving average and panel labels they share).
"""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ..figures import METHOD_COLORS, METHOD_LABELS, METHOD_STYLES
from ..plots import _label_panel, _titled, band, moving_average
from ..verdicts import EQUIVALENCE_BOUNDS
from .aggregate import Aggregate
from .results import METRICS, BatchCell, BatchRun, batch_tasks

__all__ = ["STEP_POINTS", "aggregate_figure", "step_curve", "step_curve_figure"]

STEP_POINTS = 100
"""Points of the common grid of steps on which a batch grid's learning curves are drawn."""


def step_curve(run: BatchRun, steps: np.ndarray, smooth: int) -> np.ndarray:
    """A run's training return at each of ``steps``: the trailing mean over ``smooth``
    episodes of its returns, placed at the steps where each episode ended and interpolated
    linearly between them; NaN before its first episode ended, its last value after its
    last."""
    if not run.returns:
        return np.full(steps.shape, np.nan)
    smoothed = moving_average(list(run.returns), smooth)
    return np.interp(steps, np.asarray(run.steps, dtype=np.float64), smoothed, left=np.nan)


def _draw_step_curves(ax: Axes, cells: list[BatchCell], smooth: int) -> None:
    """One task's panel: per method, the mean over seeds of :func:`step_curve` on a grid
    of :data:`STEP_POINTS` steps up to the task's longest run, and its 95% band (steps
    where every seed has a value)."""
    ends = [r.steps[-1] for c in cells for r in c.runs if r.steps]
    if not ends:
        return
    grid = np.linspace(max(ends) / STEP_POINTS, max(ends), STEP_POINTS)
    for c in cells:
        runs = [r for r in c.runs if r.returns]
        if not runs:
            continue
        curves = np.asarray([step_curve(r, grid, smooth) for r in runs])
        keep = np.all(np.isfinite(curves), axis=0)
        if not keep.any():
            continue
        mean, lo, hi = band(curves[:, keep].tolist())
        color = METHOD_COLORS.get(c.method)
        label = f"{METHOD_LABELS.get(c.method, c.method)} (n={len(runs)})"
        x = grid[keep]
        ax.plot(x, mean, color=color, ls=METHOD_STYLES.get(c.method, "-"), lw=1.6, label=label)
        ax.fill_between(x, lo, hi, color=color, alpha=0.2, lw=0)


def step_curve_figure(cells: list[BatchCell], smooth: int) -> Figure:
    """Per task, each method's training return over environment steps (a batch grid's
    learning curves): the mean over seeds of :func:`step_curve`, with a 95% Student-t band
    over seeds."""
    envs = batch_tasks(cells)
    fig = Figure(figsize=(4.2 * max(len(envs), 1), 3.6))
    axes = fig.subplots(1, max(len(envs), 1), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=False):
        _draw_step_curves(ax, [c for c in cells if c.env == env], smooth)
        _label_panel(ax, env, "environment steps", "training episode return")
    return _titled(fig, "Learning curves over steps", smooth)


def aggregate_figure(agg: Aggregate) -> Figure:
    """The aggregate over tasks as rliable draws it, one column per metric: each method's
    IQM of the normalised values with its 95% CI (top), and P(PPO-RPE > rival) pooled over
    tasks with its 95% CI against 0.5 and the bounds of a medium effect (bottom)."""
    fig = Figure(figsize=(4.0 * len(METRICS), 4.6))
    axes = fig.subplots(2, len(METRICS), squeeze=False)
    for col, metric in enumerate(METRICS):
        top, bottom = axes[0][col], axes[1][col]
        iqms = [x for x in agg.iqms if x.metric == metric.key]
        for y, x in enumerate(iqms):
            color = METHOD_COLORS.get(x.method)
            top.errorbar([x.iqm.value], [y], xerr=[[x.iqm.value - x.iqm.low],
                         [x.iqm.high - x.iqm.value]], fmt="o", color=color, capsize=4)  # fmt: skip
        top.set_yticks(range(len(iqms)), [METHOD_LABELS.get(x.method, x.method) for x in iqms])
        top.set_title(metric.name)
        top.set_xlabel("IQM of the normalised values")
        pooled = [p for p in agg.improvements if p.metric == metric.key]
        for y, p in enumerate(pooled):
            err = [[p.p.value - p.p.low], [p.p.high - p.p.value]]
            bottom.errorbar([p.p.value], [y], xerr=err, fmt="o", color="black", capsize=4)
        rivals = [f"vs {METHOD_LABELS.get(p.rival, p.rival)}" for p in pooled]
        bottom.set_yticks(range(len(pooled)), rivals)
        bottom.axvline(0.5, color="grey", lw=1)
        for bound in EQUIVALENCE_BOUNDS:
            bottom.axvline(bound, color="grey", lw=0.8, ls=":")
        bottom.set_xlim(0, 1)
        bottom.set_xlabel("P(PPO-RPE > rival), mean over tasks")
        for ax in (top, bottom):
            ax.grid(alpha=0.3, axis="x")
            ax.set_ylim(-0.7, max(len(iqms), len(pooled), 1) - 0.3)
    fig.suptitle("Over the tasks (95% CIs, stratified bootstrap; dotted: a medium effect)")
    fig.tight_layout()
    return fig
