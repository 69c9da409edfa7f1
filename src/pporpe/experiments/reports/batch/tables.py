"""The Markdown of a batch report (:mod:`.batch.report`): REPORT.md and summary.md, from
:func:`.batch.summary.batch_statistics`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..figures import METHOD_LABELS
from ..results import QUARTERS, Cell, compute_line, tasks_of
from ..stats import N_RESAMPLES, Estimate
from ..tables import quarter_markdown, report_head
from ..verdicts import EQUIVALENCE_BOUNDS, MIN_SEEDS, SETTLE_LEGEND, settle_text, short_verdict
from .aggregate import Aggregate
from .results import LAST_EPISODES, METRICS, Metric
from .summary import BatchStatistics, Comparison

__all__ = [
    "BATCH_QUARTER_LEGEND",
    "aggregate_markdown",
    "answer_markdown",
    "batch_report_markdown",
    "batch_summary_markdown",
    "comparison_markdown",
    "settings_line",
    "task_markdown",
]

RUN_FIELDS = ("env", "method", "seed", "total_steps", "checkpoint_every", "eval_episodes")
"""A run's config fields that name the run or its budget, not the learner's settings."""

BATCH_QUARTER_LEGEND = (
    "\nWhere in training the surrogates act: a run's updates split into "
    f"{QUARTERS} quarters Q1-Q{QUARTERS} by the environment steps taken when each was made "
    "(of 1M steps, Q1 holds the updates up to step 250,000); per quarter the mean over its "
    "updates of the share of the update's samples whose ratio rho was past the threshold, of "
    "their mean abs(rho - 1) and of the update's approximate KL (`updates.csv`), then the "
    "mean over seeds.\n"
)
"""The legend of a batch grid's quarters table."""


def _est(est: Estimate | None, digits: int = 1) -> str:
    """``value [low, high]``, ``n/a`` without an estimate."""
    if est is None:
        return "n/a"
    return f"{est.value:.{digits}f} [{est.low:.{digits}f}, {est.high:.{digits}f}]"


def _settle(est: Estimate | None, n: tuple[int, int]) -> str:
    """:func:`.verdicts.settle_text` of a CI of P at the fewer of ``n`` seeds."""
    return "-" if est is None else settle_text(est.value, est.low, est.high, min(n))


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def _metric(key: str) -> Metric:
    return next(m for m in METRICS if m.key == key)


def _verdict_legend() -> str:
    lo, hi = EQUIVALENCE_BOUNDS
    return (
        "Verdicts, from the 95% CI of P(PPO-RPE > rival): **supported** when it lies above "
        "0.5, **contradicted** when below, **equivalent** when it lies strictly inside "
        f"{lo}-{hi} (Vargha and Delaney's bounds of a medium effect), otherwise **cannot "
        "tell**. A CI that touches 0.5 or a bound is not past it. Two methods are compared on "
        "the seeds both finished (the verdict says how many other runs were left out); no "
        f"verdict where they share fewer than {MIN_SEEDS}. {SETTLE_LEGEND}\n"
    )


def answer_markdown(stats: BatchStatistics) -> list[str]:
    """The report's answer in words: per claim and rival, the verdict on each task (tasks
    with the same verdict together) and pooled over the tasks, read off the tables below."""
    lines = []
    rivals = list(dict.fromkeys(c.rival for c in stats.comparisons))
    for metric in METRICS:
        for rival in rivals:
            per_task = [c for c in stats.comparisons if c.metric == metric.key and c.rival == rival]
            if not per_task:
                continue
            said: dict[str, list[str]] = {}
            for c in per_task:
                said.setdefault(short_verdict(c.verdict), []).append(c.task)
            parts = [f"{v} on {', '.join(tasks)}" for v, tasks in said.items()]
            pooled = [p for p in stats.aggregate.improvements
                      if p.metric == metric.key and p.rival == rival]  # fmt: skip
            if pooled and pooled[0].tasks > 1:
                parts.append(f"pooled over the {pooled[0].tasks} tasks, "
                             f"{short_verdict(pooled[0].verdict)}")  # fmt: skip
            lines.append(f"- **{metric.name}**, against {_label(rival)}: {'; '.join(parts)}.")
    if lines:
        names = [_label(r) for r in rivals]
        them = " and ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)
        lines.append(
            f"\nDoes PPO-RPE beat {them} in batch PPO? Each line reads the 95% CI of "
            "P(PPO-RPE > rival) on every task and pooled over the tasks (the tables below, "
            "with the rules under them); the test score is the headline claim, the last 100 "
            "training episodes CleanRL's metric, the mean training return the sample "
            "efficiency.\n"
        )
    return lines


def aggregate_markdown(agg: Aggregate) -> list[str]:
    """The aggregate's two tables (IQM of normalised values per method; P(PPO-RPE > rival)
    pooled over tasks with its verdict) and how they are computed."""
    lines = ["| claim | method | tasks | runs | IQM of the normalised values [95% CI] |",
             "| --- | --- | ---: | ---: | :---: |"]  # fmt: skip
    for a in agg.iqms:
        lines.append(f"| {_metric(a.metric).name} | {_label(a.method)} | {a.tasks} | {a.runs} "
                     f"| {_est(a.iqm, 3)} |")  # fmt: skip
    lines += ["", "| claim | rival | tasks | P(PPO-RPE > rival), mean over tasks [95% CI] "
              "| verdict | seeds to settle it |",
              "| --- | --- | ---: | :---: | --- | --- |"]  # fmt: skip
    for p in agg.improvements:
        lines.append(f"| {_metric(p.metric).name} | {_label(p.rival)} | {p.tasks} | "
                     f"{_est(p.p, 2)} | {p.verdict} | {_settle(p.p, p.n)} |")  # fmt: skip
    lines.append(
        "\nAs rliable computes it (Agarwal et al. 2021). Each number is normalised per task "
        "by min-max over all the task's finished runs (every method and seed): (x - worst) / "
        "(best - worst), so 0 is the task's worst run and 1 its best; it needs no score from "
        "outside the grid and, being affine per task, changes no per-task comparison (the "
        "range is fixed from the data, not re-estimated in the bootstrap). IQM: the "
        "interquartile mean of a method's normalised values, its runs on every task pooled. "
        "Pooled P: the mean over tasks of the per-task P(PPO-RPE > rival), every task weighing "
        "the same (normalisation does not change it). CIs: stratified bootstrap, the seeds "
        f"resampled within each task (scipy BCa, {N_RESAMPLES:,} resamples). The verdict reads "
        "the pooled CI by the per-task rules below, with the fewest seeds of any task.\n"
    )
    return lines


def task_markdown(stats: BatchStatistics) -> list[str]:
    """Per task and method: seeds, the mean and IQM of the test score, the means of the
    last-100 return and of the mean training return, each with its CI."""
    score, last, mean = (m.name for m in METRICS)
    lines = [
        f"| task | method | seeds | {score}: mean [95% CI] | {score}: IQM [95% CI] | "
        f"{last}: mean [95% CI] | {mean}: mean [95% CI] | missing |",
        "| --- | --- | ---: | :---: | :---: | :---: | :---: | ---: |",
    ]
    for r in stats.rows:
        s, lst, m = r.metrics
        lines.append(f"| {r.task} | {r.method} | {r.seeds} | {_est(s.mean)} | {_est(s.iqm)} | "
                     f"{_est(lst.mean)} | {_est(m.mean)} | {r.missing} |")  # fmt: skip
    what = "; ".join(f"**{m.name}**: {m.what}" for m in METRICS)
    lines.append(
        f"\nPer run: {what}. Mean and IQM (interquartile mean) over seeds, 95% CIs by "
        f"bootstrap over seeds (scipy BCa, {N_RESAMPLES:,} resamples). `runs.csv` holds every "
        "run's three numbers.\n"
    )
    return lines


def comparison_markdown(rows: tuple[Comparison, ...]) -> list[str]:
    """Per metric, task and rival: P(PPO-RPE > rival), the difference of the means and the
    verdict."""
    lines = ["| claim | task | rival | P(PPO-RPE > rival) [95% CI] "
             "| mean difference, PPO-RPE - rival [95% CI] | verdict | seeds to settle it |",
             "| --- | --- | --- | :---: | :---: | --- | --- |"]  # fmt: skip
    for c in rows:
        lines.append(f"| {_metric(c.metric).name} | {c.task} | {_label(c.rival)} | "
                     f"{_est(c.p, 2)} | {_est(c.diff)} | {c.verdict} | "
                     f"{_settle(c.p, c.n)} |")  # fmt: skip
    lines.append(
        "\nProbability of improvement: P(X > Y) + P(X = Y)/2 for a random seed of PPO-RPE "
        "against a random seed of the rival (0.5: neither ahead); its CI and that of the "
        "difference of the means: bootstrap resampling both methods' seeds. "
        + _verdict_legend()
    )
    return lines


def batch_summary_markdown(stats: BatchStatistics) -> str:
    """summary.md: the aggregate, the per-task tables and the quarters table."""
    lines = [
        *aggregate_markdown(stats.aggregate),
        *task_markdown(stats),
        *comparison_markdown(stats.comparisons),
        *quarter_markdown(list(stats.quarters), BATCH_QUARTER_LEGEND),
    ]
    return "\n".join(lines) + "\n"


def settings_line(runs: list[dict[str, Any]]) -> str:
    """The learner settings every run shares (``key=value``), and the names of those that
    differ between runs (besides :data:`RUN_FIELDS`)."""
    configs = [r["config"] for r in runs]
    keys = [k for k in configs[0] if k not in RUN_FIELDS] if configs else []
    same = [k for k in keys if all(c.get(k) == configs[0][k] for c in configs)]
    text = ", ".join(f"{k}={configs[0][k]}" for k in same)
    differ = [k for k in keys if k not in same]
    return text + (f"; differing between runs: {', '.join(differ)}" if differ else "")


def _what_ran(root: Path, grid: dict[str, Any], cells: list[Cell]) -> list[str]:
    runs = grid["runs"]
    lines = [
        "Batch PPO (`kind = \"batch\"`, `pporpe.batch`): each run collects a rollout, then "
        f"updates on it in minibatch epochs. Methods: "
        f"{', '.join(_label(m) for m in dict.fromkeys(r['method'] for r in runs))}; seeds "
        f"{sorted({r['seed'] for r in runs})}; a run's test score is the median of "
        f"{runs[0]['config'].get('eval_episodes', '?')} deterministic test episodes.\n",
    ]
    for env in tasks_of(cells):
        here = [c for c in cells if c.env == env]
        budgets = sorted({r["config"].get("total_steps") for r in runs if r["env"] == env}, key=str)
        done, total = sum(len(c.curves) for c in here), sum(1 for r in runs if r["env"] == env)
        eps = [len(recs) for c in here for recs in c.curves.values()]
        ran = f"; training episodes per finished run: {min(eps)}-{max(eps)}" if eps else ""
        budget = ", ".join(f"{b:,}" if isinstance(b, int) else str(b) for b in budgets)
        lines.append(f"- {env}: {budget} steps per run, {done}/{total} runs finished{ran}")
    if (compute := compute_line(root, grid)) is not None:
        lines.append(compute)
    source = grid.get("source", "SPEC.toml")
    lines += [
        "",
        f"Settings shared by every run: {settings_line(runs)}.",
        "",
        f"Commands: `pporpe reproduce {source} --out {root.name}` trains the grid (resumable); "
        f"`pporpe report {root.name}` writes this report from its run folders.\n",
    ]
    return lines


def batch_report_markdown(
    root: Path, grid: dict[str, Any], cells: list[Cell], stats: BatchStatistics
) -> str:
    """REPORT.md of a batch grid: what ran, the aggregate over tasks, the per-task tables
    and verdicts, the quarters table and the figures (``notes.md`` of the folder on top)."""
    parts = report_head(root, grid, " (batch PPO)")
    answer = answer_markdown(stats)
    if answer:
        parts += ["## The answer\n", "\n".join(answer)]
    parts += [
        "## What ran\n",
        "\n".join(_what_ran(root, grid, cells)),
        "## Over the tasks\n",
        "\n".join(aggregate_markdown(stats.aggregate)),
        "## Per task\n",
        "\n".join(task_markdown(stats)),
        "## PPO-RPE against each rival, per task\n",
        "\n".join(comparison_markdown(stats.comparisons)),
        "## Where the surrogates act, by quarter of steps\n",
        "\n".join(quarter_markdown(list(stats.quarters), BATCH_QUARTER_LEGEND)),
        "## Figures\n",
        "- Over the tasks: each method's IQM of the normalised values and P(PPO-RPE > rival) "
        "pooled over the tasks, with their 95% CIs: ![aggregate](fig_aggregate.png)\n"
        "- Test scores per seed and their mean: ![summary](fig_summary.png)\n"
        "- Learning curves over environment steps (training return, mean over seeds, 95% "
        f"band; last-{LAST_EPISODES} and mean training return read off these runs): "
        "![learning](fig_learning.png)\n",
        f"Regenerated from the run folders by `pporpe report` on this folder ({root.name}/).\n",
    ]
    return "\n".join(parts)
