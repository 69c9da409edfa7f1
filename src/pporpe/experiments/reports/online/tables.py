"""The online report's summary tables: the summary as Markdown and as CSV.

Scores, early learning, regularisation, updates past the threshold (over the whole run and
by quarter of training) and the probabilities of improvement of PPO-RPE, from
:func:`.summary.statistics`.
"""

from __future__ import annotations

import csv
import io

from ..figures import METHOD_LABELS
from ..results import EARLY_EPISODES, Cell
from ..stats import N_RESAMPLES
from ..tables import fmt_ci, quarter_markdown
from .summary import Statistics, cell_rows, statistics

__all__ = ["summary_csv", "summary_markdown"]


def summary_markdown(cells: list[Cell], stats: Statistics | None = None) -> str:
    """The summary tables as Markdown: scores, early learning and regularisation per task
    and method; the share of updates past the threshold and abs(rho - 1), over the run and
    by quarter of training (:func:`quarter_markdown`); then the probabilities of improvement
    of PPO-RPE over each rival (``stats``: already computed :func:`statistics` of
    ``cells``)."""
    stats = statistics(cells) if stats is None else stats
    lines = [*_score_lines(stats), *_surrogate_lines(stats), *quarter_markdown(stats.quarters)]
    if stats.improvements:
        lines += _improvement_lines(stats)
    return "\n".join(lines) + "\n"


def _score_lines(stats: Statistics) -> list[str]:
    """Scores, early learning and regularisation per task and method, and their legend."""
    lines = [
        "| task | method | seeds | mean score [95% CI] | IQM [95% CI] "
        f"| first-{EARLY_EPISODES} episodes mean return [95% CI] "
        "| mean regularisation [95% CI] | missing |",
        "| --- | --- | ---: | :---: | :---: | :---: | :---: | ---: |",
    ]
    for r in stats.rows:
        lines.append(
            f"| {r['task']} | {r['method']} | {r['seeds']} | {fmt_ci(r, 'boot')} | "
            f"{fmt_ci(r, 'iqm')} | {fmt_ci(r, 'first50')} | {fmt_ci(r, 'reg', 3)} | "
            f"{r['missing']} |"
        )
    lines.append(
        "\nScore of a run: median return of its test episodes. Mean and IQM (interquartile "
        "mean) over seeds; first-episodes return and regularisation (sigma*(rho - "
        "rho_dagger), averaged over the run's training episodes) are means over seeds. "
        f"95% CIs: bootstrap over seeds (scipy BCa, {N_RESAMPLES:,} resamples).\n"
    )
    return lines


def _surrogate_lines(stats: Statistics) -> list[str]:
    """The share of updates past the threshold and abs(rho - 1) per task and method."""
    lines = [
        "| task | method | updates past the threshold, % [95% CI] "
        "| mean abs(rho - 1) per update, % [95% CI] |",
        "| --- | --- | :---: | :---: |",
    ]
    for r in stats.rows:
        lines.append(
            f"| {r['task']} | {r['method']} | {fmt_ci(r, 'past', 2, 100.0)} | "
            f"{fmt_ci(r, 'ratio_dev', 2, 100.0)} |"
        )
    acts = ["PPO's clip", "PPO-RB's rollback", "PPO-RPE's stronger pull"]
    if any(r["method"] == METHOD_LABELS["spo"] for r in stats.rows):  # past 1 + sign(A) eps
        acts.append("SPO's reversed gradient")
    n = {3: "three", 4: "four"}[len(acts)]
    lines.append(
        f"\nHow much the {n} surrogates can differ: the share of a run's updates whose ratio "
        f"rho was past the threshold (where {', '.join(acts[:-1])} or {acts[-1]} "
        "act) and the mean distance of rho from 1, both over all of the run's "
        f"updates, then averaged over seeds. Where rho stays near 1 the {n} objectives give "
        "nearly the same gradient.\n"
    )
    return lines


def _improvement_lines(stats: Statistics) -> list[str]:
    """P(PPO-RPE > rival) of each statistic per task and rival, and its legend."""
    lines = [
        "| task | P(PPO-RPE > rival) | score [95% CI] "
        f"| first-{EARLY_EPISODES} return [95% CI] | regularisation [95% CI] |",
        "| --- | --- | :---: | :---: | :---: |",
    ]
    for r in stats.improvements:
        lines.append(
            f"| {r['task']} | vs {METHOD_LABELS.get(r['rival'], r['rival'])} | "
            f"{fmt_ci(r, 'score', 2)} | {fmt_ci(r, 'first50', 2)} | "
            f"{fmt_ci(r, 'reg', 2)} |"
        )
    lines.append(
        "\nProbability of improvement (Agarwal et al. 2021): P(X > Y) + P(X = Y)/2 for a "
        "random seed of PPO-RPE against a random seed of the rival; 0.5 means neither is "
        "ahead. CIs: bootstrap resampling both methods' seeds.\n"
    )
    return lines


def summary_csv(cells: list[Cell], stats: Statistics | None = None) -> str:
    """The summary table as CSV."""
    buf = io.StringIO()
    rows = cell_rows(cells) if stats is None else stats.rows
    writer = csv.DictWriter(
        buf, fieldnames=list(rows[0]) if rows else ["task"], lineterminator="\n"
    )
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()
