"""The tables of a sweep's report: the selection, each method's sensitivity per task and
pooled over the tasks, and the matched trust regions (as Markdown and CSV), from
:func:`.results.sweep_statistics`."""

from __future__ import annotations

import csv
import io
import math
from typing import Any

from ...sweep_terms import Setting, value_text
from ..figures import METHOD_LABELS
from ..stats import N_RESAMPLES, Estimate
from .figures import TRUST_LABELS
from .results import TRUST_FIELDS, PooledCell, SweepStatistics, task_best

__all__ = [
    "lacking_markdown",
    "selection_markdown",
    "sensitivity_csv",
    "sensitivity_markdown",
    "setting_text",
    "trust_csv",
    "trust_markdown",
]


def setting_text(setting: Setting) -> str:
    """``eps 0.2, lr 0.0003``; ``(its spec's settings)`` for a method that sweeps nothing."""
    return ", ".join(f"{n} {value_text(v)}" for n, v in setting) or "(the spec's settings)"


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def _est(est: Estimate | None, digits: int = 3) -> str:
    if est is None:
        return "n/a"
    return f"{est.value:.{digits}f} [{est.low:.{digits}f}, {est.high:.{digits}f}]"


def _stat_name(stats: SweepStatistics) -> str:
    return "IQM" if stats.rule.statistic == "iqm" else "mean"


def _pooled(stats: SweepStatistics, method: str, setting: Setting) -> PooledCell:
    return next(p for p in stats.pooled if (p.method, p.setting) == (method, setting))


def selection_markdown(stats: SweepStatistics, rule_text: str, tuning: list[int]) -> list[str]:
    """The rule, each method's selected setting and runner-up with their values, ties and
    edges (every run must have finished: :func:`lacking_markdown` otherwise)."""
    stat = _stat_name(stats)
    lines = [
        f'Rule, declared in the spec before any run (`select = "{rule_text}"`): '
        f"{stats.rule.describe()}. Tuning seeds: {', '.join(map(str, tuning))}.\n",
        f"| method | selected | {stat} [95% CI] | runner-up | {stat} [95% CI] | "
        "at the edge of the range |",
        "| --- | --- | :---: | --- | :---: | --- |",
    ]
    notes = []
    for method, sel in stats.selections.items():
        best = _pooled(stats, method, sel.best.setting)
        runner = "-", "-"
        if sel.runner_up is not None:
            r = _pooled(stats, method, sel.runner_up.setting)
            runner = setting_text(r.setting), _est(r.value)
        edge = "; ".join(sel.edges) or "no"
        lines.append(f"| {_label(method)} | **{setting_text(best.setting)}** | "
                     f"{_est(best.value)} | {runner[0]} | {runner[1]} | {edge} |")  # fmt: skip
        for other in sel.tied:
            notes.append(f"- {_label(method)}: {setting_text(other.setting)} ties with the "
                         f"selected {setting_text(sel.best.setting)} ({other.value:.3f}); "
                         "the setting listed first in the spec is taken.")  # fmt: skip
    if any(sel.edges for sel in stats.selections.values()):
        notes.append("- Where a selected value is the smallest or the largest one swept, the "
                     "best may lie beyond the range: sweep the next value for that method "
                     "on the tuning seeds (`equal_budget = false`) before stage 2.")  # fmt: skip
    return [*lines, *(["", *notes] if notes else []), ""]


def lacking_markdown(stats: SweepStatistics) -> list[str]:
    """Nothing selected: how many runs each setting still lacks, over tasks and seeds."""
    lacking = [p for p in stats.pooled if p.missing]
    total = sum(p.missing for p in stats.pooled)
    runs = total + sum(p.runs for p in stats.pooled)
    lines = [
        f"**Nothing selected**: {total} of {runs} runs of the sweep are unfinished, and a "
        "selection reads every run. Runs each setting still lacks (over tasks and seeds):\n",
        "| method | setting | runs lacking | runs finished |",
        "| --- | --- | ---: | ---: |",
    ]
    lines += [f"| {_label(p.method)} | {setting_text(p.setting)} | {p.missing} | {p.runs} |"
              for p in lacking]  # fmt: skip
    return [*lines, ""]


def _task_value(stats: SweepStatistics, env: str, method: str, setting: Setting) -> str:
    """Mean over seeds (lowest-highest seed), bold where it is the task's best setting."""
    cell = next((c for c in stats.cells
                 if (c.env, c.method, c.setting) == (env, method, setting)), None)  # fmt: skip
    vals = list(cell.values(stats.rule.metric).values()) if cell else []
    if not vals:
        return "n/a"
    text = f"{sum(vals) / len(vals):.1f} ({min(vals):.1f} to {max(vals):.1f})"
    best = task_best(stats.cells, env, method, stats.rule.metric)
    return f"**{text}**" if best == setting else text


def sensitivity_markdown(stats: SweepStatistics) -> list[str]:
    """Per method and setting: the pooled value with its CI, the mean over seeds on each
    task, the runs finished; the selected setting, the runner-up and each task's best
    marked."""
    stat = _stat_name(stats)
    head = " | ".join(stats.tasks)
    lines = [
        f"| method | setting | pooled: {stat}, normalised [95% CI] | {head} | runs |",
        "| --- | --- | :---: | " + " | ".join(":---:" for _ in stats.tasks) + " | ---: |",
    ]
    for p in stats.pooled:
        sel = stats.selections.get(p.method)
        mark = ""
        if sel is not None and p.setting == sel.best.setting:
            mark = " (selected)"
        elif sel is not None and sel.runner_up is not None and p.setting == sel.runner_up.setting:
            mark = " (runner-up)"
        tasks = " | ".join(_task_value(stats, env, p.method, p.setting) for env in stats.tasks)
        lines.append(f"| {_label(p.method)} | {setting_text(p.setting)}{mark} | "
                     f"{_est(p.value)} | {tasks} | {p.runs}/{p.runs + p.missing} |")  # fmt: skip
    lines.append(
        f"\nPer task: the {stats.rule.metric_name} of the tuning seeds, mean over seeds (lowest "
        "to highest seed); in bold each method's best setting on that task (shown, not "
        "re-evaluated: stage 2 runs one setting per method for every task). Pooled: the "
        f"{stat} of the values normalised per task by min-max over all the task's finished "
        "runs (every method, setting and seed), pooled over the tasks; 95% CI by bootstrap "
        f"{'stratified by task ' if stat == 'IQM' else ''}(scipy, {N_RESAMPLES:,} "
        "resamples). `sensitivity.csv` holds every number, with the three metrics.\n"
    )
    return lines


def trust_markdown(stats: SweepStatistics) -> list[str]:
    """Per method and setting, sorted by mean approximate KL: the trust region its runs
    kept and the pooled value, so that methods compare at the same size of update."""
    stat = _stat_name(stats)
    kl = TRUST_FIELDS[0]
    rows = sorted(stats.pooled, key=lambda p: (math.isnan(p.trust[kl]), p.trust[kl]))
    names = " | ".join(TRUST_LABELS[f] for f in TRUST_FIELDS)
    align = " | ".join(":---:" for _ in TRUST_FIELDS)
    lines = [f"| method | setting | runs | {names} | pooled: {stat}, normalised |",
             f"| --- | --- | ---: | {align} | :---: |"]  # fmt: skip
    for p in rows:
        trust = " | ".join(_trust_text(f, p.trust[f]) for f in TRUST_FIELDS)
        value = "n/a" if p.value is None else f"{p.value.value:.3f}"
        lines.append(f"| {_label(p.method)} | {setting_text(p.setting)} | {p.runs} | {trust} | "
                     f"{value} |")  # fmt: skip
    lines.append(
        "\nEach run's mean over its updates of the approximate KL of the new policy from the "
        "old, of the mean abs(rho - 1) and of the share of samples past the threshold "
        "(`updates.csv`; for an online run, its episodes' diagnostics and no KL), then the "
        "mean over the runs of the setting (every task and seed); "
        f"sorted by the KL, so that rows of similar KL compare the methods at the same size "
        f"of update rather than at the same eps. `trust_region.csv` holds every run's numbers "
        f"with its {stats.rule.metric_name}.\n"
    )
    return lines


def _trust_text(name: str, value: float) -> str:
    if math.isnan(value):
        return "n/a"
    return f"{100 * value:.2f}%" if name == "past_threshold" else f"{value:.3g}"


def sensitivity_csv(stats: SweepStatistics) -> str:
    """A row per method, setting and task (then ``pooled``): runs, missing, each metric's
    mean, lowest and highest over seeds; the pooled row the rule's value and CI."""
    rows = []
    for p in stats.pooled:
        base: dict[str, Any] = {"method": p.method, "setting": setting_text(p.setting)}
        for c in (c for c in stats.cells if (c.method, c.setting) == (p.method, p.setting)):
            row = {**base, "task": c.env, "runs": len(c.runs), "missing": len(c.missing)}
            for metric in ("score", "last100", "mean_return"):
                vals = list(c.values(metric).values())
                row[f"{metric}_mean"] = sum(vals) / len(vals) if vals else math.nan
                row[f"{metric}_min"] = min(vals) if vals else math.nan
                row[f"{metric}_max"] = max(vals) if vals else math.nan
            rows.append(row)
        est = p.value
        rows.append({**base, "task": "pooled", "runs": p.runs, "missing": p.missing,
                     "rule_value": est.value if est else math.nan,
                     "rule_low": est.low if est else math.nan,
                     "rule_high": est.high if est else math.nan})  # fmt: skip
    return _csv(rows)


def trust_csv(stats: SweepStatistics) -> str:
    """A row per finished run: its task, method, setting, seed, trust region and metrics."""
    rows = [
        {"task": c.env, "method": c.method, "setting": setting_text(c.setting), "seed": r.seed,
         **r.trust, **r.values}
        for c in stats.cells
        for r in c.runs
    ]  # fmt: skip
    return _csv(rows)


def _csv(rows: list[dict[str, Any]]) -> str:
    names = list(dict.fromkeys(k for row in rows for k in row)) or ["task"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=names, lineterminator="\n", restval="")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()
