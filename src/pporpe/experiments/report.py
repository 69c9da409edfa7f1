"""Summary table and the paper's figures from a grid's results folder.

Reads ``OUT/grid.json`` and each run's ``episodes.csv`` and ``evaluation.json``; writes

* ``REPORT.md``: what ran, the tables below, and each claim of the paper (final score,
  early learning on the pendulum tasks, strength of regularisation) against the data, as
  a probability of improvement with its CI and a verdict; a hand-written ``notes.md`` in
  the folder goes at its top;
* ``summary.md`` / ``summary.csv``: per task and method, over seeds of the per-seed
  median test score: the mean and the IQM with bootstrap 95% CIs (:mod:`.stats`; the CSV
  also has the Student-t interval), the mean return of the first 50 training episodes, the
  mean regularisation amount; how often the ratio was past the threshold and how far it
  was from 1 (how much the surrogates can differ); then P(PPO-RPE > rival) for the first
  three;
* ``fig_summary``: bar summary of the scores (the paper's Fig. 3, ``sim_summary``);
* ``fig_learning``: learning curves per task, mean over seeds, 95% bands (Fig. 4, ``sim_learn``);
* ``fig_regularization``: trajectories of sigma*(rho - rho_dagger) (Fig. 5, ``sim_isr_diff``);

each figure as PNG and PDF. Unfinished or failed runs are left out and counted.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from scipy import stats

from ..io import atomic_savefig, atomic_write_text
from ..runs.logger import EpisodeRecord, read_records
from .figures import METHOD_COLORS, METHOD_LABELS, METHOD_STYLES
from .stats import (
    N_RESAMPLES,
    Estimate,
    bootstrap_ci,
    iqm,
    probability_of_improvement_ci,
)

__all__ = [
    "EARLY_EPISODES",
    "Cell",
    "Statistics",
    "early_return",
    "improvement_rows",
    "load_results",
    "mean_ci",
    "mean_regularization",
    "statistics",
    "update_mean",
    "write_report",
]


@dataclass
class Cell:
    """Results of one (task, method) over seeds."""

    env: str
    method: str
    scores: dict[int, float]
    """Per-seed median test return."""
    curves: dict[int, list[EpisodeRecord]]
    """Per-seed training records."""
    missing: list[int]
    """Seeds without a finished run."""


def mean_ci(values: list[float], level: float = 0.95) -> tuple[float, float, float]:
    """Mean and the two ends of its Student-t confidence interval (NaN ends for n < 2)."""
    arr = np.asarray(values, dtype=np.float64)
    n = arr.size
    if n == 0:
        return math.nan, math.nan, math.nan
    mean = float(arr.mean())
    if n < 2:
        return mean, math.nan, math.nan
    half = float(stats.t.ppf(0.5 + level / 2, n - 1) * arr.std(ddof=1) / math.sqrt(n))
    return mean, mean - half, mean + half


def load_results(out: str | Path) -> list[Cell]:
    """Collect every run of the grid in ``out`` into (task, method) cells."""
    root = Path(out)
    grid_file = root / "grid.json"
    if not grid_file.exists():
        raise ValueError(f"{root} holds no grid results (no grid.json); run `pporpe reproduce`")
    grid = json.loads(grid_file.read_text())
    cells: dict[tuple[str, str], Cell] = {}
    for run in grid["runs"]:
        key = (run["env"], run["method"])
        cell = cells.setdefault(key, Cell(run["env"], run["method"], {}, {}, []))
        run_dir = root / run["key"]
        if not (run_dir / "done.json").exists():
            cell.missing.append(run["seed"])
            continue
        cell.curves[run["seed"]] = read_records(run_dir / "episodes.csv")
        ev = run_dir / "evaluation.json"
        if ev.exists():
            cell.scores[run["seed"]] = float(json.loads(ev.read_text())["median"])
    return list(cells.values())


EARLY_EPISODES = 50
"""Training episodes of the early-learning comparison (the paper's pendulum claim)."""


def early_return(records: list[EpisodeRecord], episodes: int = EARLY_EPISODES) -> float:
    """Mean return of a run's first ``episodes`` training episodes (NaN without any)."""
    rets = [r.ret for r in records[:episodes]]
    return float(np.mean(rets)) if rets else math.nan


def mean_regularization(records: list[EpisodeRecord]) -> float:
    """Mean over a run's training episodes of sigma*(rho - rho_dagger) (NaN without any)."""
    vals = [r.reg_amount for r in records if math.isfinite(r.reg_amount)]
    return float(np.mean(vals)) if vals else math.nan


def update_mean(records: list[EpisodeRecord], field: str) -> float:
    """Mean over a run's updates of a per-episode mean ``field`` (``past_threshold``,
    ``ratio_dev``, ``trace_decay``): episodes weighted by their length, since an online run
    makes one update per step (NaN without any finite value)."""
    pairs = [(getattr(r, field), r.length) for r in records]
    pairs = [(v, n) for v, n in pairs if math.isfinite(v) and n > 0]
    if not pairs:
        return math.nan
    return float(sum(v * n for v, n in pairs) / sum(n for _, n in pairs))


def _finite(values: list[float]) -> list[float]:
    return [v for v in values if math.isfinite(v)]


def _estimate(values: list[float], statistic: Any = np.mean) -> Estimate | None:
    vals = _finite(values)
    return bootstrap_ci(vals, statistic) if vals else None


def _table_rows(cells: list[Cell]) -> list[dict[str, Any]]:
    rows = []
    for c in cells:
        scores = list(c.scores.values())
        mean, lo, hi = mean_ci(scores)
        row: dict[str, Any] = {
            "task": c.env,
            "method": METHOD_LABELS.get(c.method, c.method),
            "mean_score": mean,
            "ci95_low": lo,
            "ci95_high": hi,
            "seeds": len(c.scores),
            "missing": len(c.missing),
        }
        stats_of = {
            "boot": _estimate(scores),
            "iqm": _estimate(scores, iqm),
            "first50": _estimate([early_return(r) for r in c.curves.values()]),
            "reg": _estimate([mean_regularization(r) for r in c.curves.values()]),
            "past": _estimate([update_mean(r, "past_threshold") for r in c.curves.values()]),
            "ratio_dev": _estimate([update_mean(r, "ratio_dev") for r in c.curves.values()]),
        }
        for name, est in stats_of.items():
            for part in ("value", "low", "high"):
                row[f"{name}_{part}"] = math.nan if est is None else getattr(est, part)
        rows.append(row)
    return rows


def _fmt(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{x:.1f}"


def _fmt_ci(row: dict[str, Any], name: str, digits: int = 1, scale: float = 1.0) -> str:
    v, lo, hi = (scale * row[f"{name}_{p}"] for p in ("value", "low", "high"))
    if math.isnan(v):
        return "n/a"
    return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def improvement_rows(cells: list[Cell], of: str = "rpe") -> list[dict[str, Any]]:
    """Per task and rival method: P(``of`` > rival) of the scores, of the early returns and
    of the regularisation amount, each with its bootstrap CI."""
    rows = []
    for env in _envs(cells):
        here = {c.method: c for c in cells if c.env == env}
        if of not in here:
            continue
        mine = here[of]
        for rival, theirs in here.items():
            if rival == of:
                continue
            row: dict[str, Any] = {"task": env, "method": of, "rival": rival}
            pairs = {
                "score": (list(mine.scores.values()), list(theirs.scores.values())),
                "first50": (
                    [early_return(r) for r in mine.curves.values()],
                    [early_return(r) for r in theirs.curves.values()],
                ),
                "reg": (
                    [mean_regularization(r) for r in mine.curves.values()],
                    [mean_regularization(r) for r in theirs.curves.values()],
                ),
            }
            for name, (x, y) in pairs.items():
                x, y = _finite(x), _finite(y)
                est = probability_of_improvement_ci(x, y) if x and y else None
                for part in ("value", "low", "high"):
                    row[f"{name}_{part}"] = math.nan if est is None else getattr(est, part)
                row[f"{name}_n"] = (len(x), len(y))
            rows.append(row)
    return rows


@dataclass(frozen=True)
class Statistics:
    """Every statistic a report prints, computed once (the bootstraps are the slow part)."""

    rows: list[dict[str, Any]]
    """Per task and method: scores, early learning, regularisation, updates past the
    threshold and abs(rho - 1) (``summary.csv``)."""
    improvements: list[dict[str, Any]]
    """Per task and rival: the probabilities of improvement of PPO-RPE."""


def statistics(cells: list[Cell]) -> Statistics:
    """The tables of a report: :func:`_table_rows` and :func:`improvement_rows`."""
    return Statistics(_table_rows(cells), improvement_rows(cells))


def summary_markdown(cells: list[Cell], stats: Statistics | None = None) -> str:
    """The summary tables as Markdown: scores, early learning and regularisation per task
    and method; the share of updates past the threshold and abs(rho - 1); then the
    probabilities of improvement of PPO-RPE over each rival (``stats``: already computed
    :func:`statistics` of ``cells``)."""
    stats = statistics(cells) if stats is None else stats
    lines = [
        "| task | method | seeds | mean score [95% CI] | IQM [95% CI] "
        f"| first-{EARLY_EPISODES} episodes mean return [95% CI] "
        "| mean regularisation [95% CI] | missing |",
        "| --- | --- | ---: | :---: | :---: | :---: | :---: | ---: |",
    ]
    for r in stats.rows:
        lines.append(
            f"| {r['task']} | {r['method']} | {r['seeds']} | {_fmt_ci(r, 'boot')} | "
            f"{_fmt_ci(r, 'iqm')} | {_fmt_ci(r, 'first50')} | {_fmt_ci(r, 'reg', 3)} | "
            f"{r['missing']} |"
        )
    lines.append(
        "\nScore of a run: median return of its test episodes. Mean and IQM (interquartile "
        "mean) over seeds; first-episodes return and regularisation (sigma*(rho - "
        "rho_dagger), averaged over the run's training episodes) are means over seeds. "
        f"95% CIs: bootstrap over seeds (scipy BCa, {N_RESAMPLES:,} resamples).\n"
    )
    lines += [
        "| task | method | updates past the threshold, % [95% CI] "
        "| mean abs(rho - 1) per update, % [95% CI] |",
        "| --- | --- | :---: | :---: |",
    ]
    for r in stats.rows:
        lines.append(
            f"| {r['task']} | {r['method']} | {_fmt_ci(r, 'past', 2, 100.0)} | "
            f"{_fmt_ci(r, 'ratio_dev', 2, 100.0)} |"
        )
    lines.append(
        "\nHow much the three surrogates can differ: the share of a run's updates whose ratio "
        "rho was past the threshold (where PPO's clip, PPO-RB's rollback or PPO-RPE's "
        "stronger pull act) and the mean distance of rho from 1, both over all of the run's "
        "updates, then averaged over seeds. Where rho stays near 1 the three objectives give "
        "nearly the same gradient.\n"
    )
    poi = stats.improvements
    if poi:
        lines += [
            "| task | P(PPO-RPE > rival) | score [95% CI] "
            f"| first-{EARLY_EPISODES} return [95% CI] | regularisation [95% CI] |",
            "| --- | --- | :---: | :---: | :---: |",
        ]
        for r in poi:
            lines.append(
                f"| {r['task']} | vs {METHOD_LABELS.get(r['rival'], r['rival'])} | "
                f"{_fmt_ci(r, 'score', 2)} | {_fmt_ci(r, 'first50', 2)} | "
                f"{_fmt_ci(r, 'reg', 2)} |"
            )
        lines.append(
            "\nProbability of improvement (Agarwal et al. 2021): P(X > Y) + P(X = Y)/2 for a "
            "random seed of PPO-RPE against a random seed of the rival; 0.5 means neither is "
            "ahead. CIs: bootstrap resampling both methods' seeds.\n"
        )
    return "\n".join(lines) + "\n"


def summary_csv(cells: list[Cell], stats: Statistics | None = None) -> str:
    """The summary table as CSV."""
    buf = io.StringIO()
    rows = _table_rows(cells) if stats is None else stats.rows
    writer = csv.DictWriter(
        buf, fieldnames=list(rows[0]) if rows else ["task"], lineterminator="\n"
    )
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _envs(cells: list[Cell]) -> list[str]:
    return list(dict.fromkeys(c.env for c in cells))


def _band(curves: list[list[float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and 95% band over seeds, episode by episode (up to the shortest run)."""
    n = min(len(c) for c in curves)
    arr = np.asarray([c[:n] for c in curves], dtype=np.float64)
    mean = arr.mean(axis=0)
    if arr.shape[0] < 2:
        return mean, mean, mean
    half = stats.t.ppf(0.975, arr.shape[0] - 1) * arr.std(axis=0, ddof=1) / math.sqrt(arr.shape[0])
    return mean, mean - half, mean + half


def _smooth(x: list[float], window: int) -> list[float]:
    if window <= 1 or len(x) < 2:
        return list(x)
    out, acc = [], 0.0
    for i, v in enumerate(x):
        acc += v
        if i >= window:
            acc -= x[i - window]
        out.append(acc / min(i + 1, window))
    return out


def _curve_figure(cells: list[Cell], field: str, ylabel: str, title: str, smooth: int) -> Any:
    envs = _envs(cells)
    fig, axes = plt.subplots(1, len(envs), figsize=(4.2 * len(envs), 3.6), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=True):
        for c in (c for c in cells if c.env == env):
            curves = [
                _smooth([getattr(r, field) for r in recs], smooth)
                for recs in c.curves.values()
                if recs
            ]
            if not curves:
                continue
            mean, lo, hi = _band(curves)
            x = np.arange(1, mean.size + 1)
            color = METHOD_COLORS.get(c.method)
            ax.plot(
                x,
                mean,
                color=color,
                ls=METHOD_STYLES.get(c.method, "-"),
                lw=1.6,
                label=f"{METHOD_LABELS.get(c.method, c.method)} (n={len(curves)})",
            )
            ax.fill_between(x, lo, hi, color=color, alpha=0.2, lw=0)
        ax.set_title(env)
        ax.set_xlabel("episode")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no finished runs yet", ha="center", va="center",
                    transform=ax.transAxes)  # fmt: skip
    suffix = f"; moving average over {smooth} episodes" if smooth > 1 else ""
    fig.suptitle(f"{title} (mean over seeds, shaded: 95% CI{suffix})")
    fig.tight_layout()
    return fig


def _summary_figure(cells: list[Cell]) -> Any:
    envs = _envs(cells)
    fig, axes = plt.subplots(1, len(envs), figsize=(3.6 * len(envs), 3.6), squeeze=False)
    for ax, env in zip(axes[0], envs, strict=True):
        row = [c for c in cells if c.env == env]
        for i, c in enumerate(row):
            scores = list(c.scores.values())
            mean, lo, hi = mean_ci(scores)
            color = METHOD_COLORS.get(c.method)
            if scores:
                err = None if math.isnan(lo) else [[mean - lo], [hi - mean]]
                ax.bar(i, mean, color=color, alpha=0.7, yerr=err, capsize=5)
                jitter = np.linspace(-0.15, 0.15, len(scores)) if len(scores) > 1 else [0.0]
                ax.scatter(i + np.asarray(jitter), scores, color="k", s=10, zorder=3)
        ax.set_xticks(range(len(row)), [METHOD_LABELS.get(c.method, c.method) for c in row])
        ax.set_title(env)
        ax.set_ylabel("median test return")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle("Test score per seed (dots), mean and 95% CI over seeds (bars)")
    fig.tight_layout()
    return fig


CLAIMS = (
    ("score", "final performance: PPO-RPE scores as well as or better than", None),
    (
        "first50",
        "early learning: PPO-RPE learns faster from the early stage than",
        ("pendulum", "swingup"),
    ),
    ("reg", "regularisation: PPO-RPE regularises more strongly than", None),
)
"""The paper's claims checked by the report: the statistic, the claim, the tasks it is
made for (None: all)."""


def verdict(low: float, high: float, n: tuple[int, int]) -> str:
    """What a probability-of-improvement CI says: ahead, behind, or cannot tell."""
    if math.isnan(low):
        return "no data"
    if low > 0.5:
        return "supported (PPO-RPE ahead)"
    if high < 0.5:
        return "contradicted (PPO-RPE behind)"
    return f"cannot tell at {min(n)} seeds (the CI contains 0.5)"


def claims_markdown(cells: list[Cell], stats: Statistics | None = None) -> str:
    """One line per claim, task and rival: the probability of improvement and the verdict."""
    rows = improvement_rows(cells) if stats is None else stats.improvements
    lines = ["| claim | task | rival | P(PPO-RPE > rival) [95% CI] | verdict |",
             "| --- | --- | --- | :---: | --- |"]  # fmt: skip
    for stat, claim, tasks in CLAIMS:
        for r in rows:
            if tasks is not None and r["task"] not in tasks:
                continue
            lines.append(
                f"| {claim.split(':')[0]} | {r['task']} | "
                f"{METHOD_LABELS.get(r['rival'], r['rival'])} | {_fmt_ci(r, stat, 2)} | "
                f"{verdict(r[f'{stat}_low'], r[f'{stat}_high'], r[f'{stat}_n'])} |"
            )
    legend = "\n".join(
        f"- **{c.split(':')[0]}**:{c.split(':', 1)[1]} the rival"
        + ("" if tasks is None else f" (claimed for {', '.join(tasks)})")
        for _, c, tasks in CLAIMS
    )
    return "\n".join(lines) + "\n\n" + legend + "\n"


def _run_budget(cfg: dict[str, Any]) -> Any:
    """A run's length in its config: episodes or steps (online), total_steps (batch)."""
    return cfg.get("episodes") or cfg.get("steps") or cfg.get("total_steps")


def _budget_lines(grid: dict[str, Any], cells: list[Cell]) -> list[str]:
    lines = []
    for env in _envs(cells):
        runs = [r for r in grid["runs"] if r["env"] == env]
        budgets = sorted({_run_budget(r["config"]) for r in runs}, key=str)
        unit = "episodes" if runs and runs[0]["config"].get("episodes") else "steps"
        here = [c for c in cells if c.env == env]
        done = sum(len(c.curves) for c in here)
        lengths = [len(recs) for c in here for recs in c.curves.values()]
        ran = f"; episodes run per finished run: {min(lengths)}-{max(lengths)}" if lengths else ""
        lines.append(
            f"- {env}: {', '.join(map(str, budgets))} training {unit} per run, "
            f"{done}/{len(runs)} runs finished{ran}"
        )
    return lines


def report_markdown(root: Path, cells: list[Cell], stats: Statistics | None = None) -> str:
    """REPORT.md: what ran, the tables, the paper's claims against the data, the figures,
    and the folder's hand-written ``notes.md`` (if any) at the top."""
    stats = statistics(cells) if stats is None else stats
    grid = json.loads((root / "grid.json").read_text())
    notes = root / "notes.md"
    parts = [f"# Report: grid {grid.get('name', root.name)!r}\n"]
    if notes.exists():
        parts.append(notes.read_text().strip() + "\n")
    parts += [
        "## What ran\n",
        "\n".join(_budget_lines(grid, cells)) + "\n",
        "## Scores, early learning, regularisation\n",
        summary_markdown(cells, stats),
        "## The paper's claims against these data\n",
        claims_markdown(cells, stats),
        "## Figures\n",
        "- Test scores per seed and their mean: ![summary](fig_summary.png)\n"
        "- Learning curves (mean over seeds, 95% band): ![learning](fig_learning.png)\n"
        "- Regularisation amount sigma*(rho - rho_dagger): "
        "![regularisation](fig_regularization.png)\n",
        f"Regenerated from the run folders by `pporpe report` on this folder ({root.name}/).\n",
    ]
    return "\n".join(parts)


def write_report(out: str | Path, smooth: int = 10) -> list[Path]:
    """Write the summary table and figures into ``out`` (the grid's results folder)."""
    if not (isinstance(smooth, int) and smooth >= 1):
        raise ValueError(f"smooth must be an int >= 1; got {smooth!r}")
    root = Path(out)
    cells = load_results(root)
    stats = statistics(cells)  # once for the three files
    written = [
        atomic_write_text(root / "REPORT.md", report_markdown(root, cells, stats)),
        atomic_write_text(root / "summary.md", summary_markdown(cells, stats)),
        atomic_write_text(root / "summary.csv", summary_csv(cells, stats)),
    ]
    figures = {
        "fig_summary": _summary_figure(cells),
        "fig_learning": _curve_figure(cells, "ret", "episode return", "Learning curves", smooth),
        "fig_regularization": _curve_figure(
            cells,
            "reg_amount",
            r"$\sigma(\rho - \rho^\dagger)$",
            "Amount of regularisation",
            smooth,
        ),
    }
    for name, fig in figures.items():
        for ext in ("png", "pdf"):
            written.append(atomic_savefig(fig, root / f"{name}.{ext}"))
        plt.close(fig)
    return written
