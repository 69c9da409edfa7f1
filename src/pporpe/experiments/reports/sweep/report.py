"""``pporpe report`` on a sweep (:mod:`...grids.sweep`): stage 1 (tuning) and stage 2 (evaluation).

Stage 1, :func:`write_tuning_report`, writes

* ``REPORT.md``: the selection by the spec's rule (each method's setting, its runner-up,
  ties, settings at the edge of their range), or, while a run is unfinished, how many runs
  each setting still lacks and no selection; what ran; the sensitivity table (per task and
  pooled over the tasks); the matched trust regions; the figures;
* ``sensitivity.csv`` and ``trust_region.csv`` (:mod:`.sensitivity`);
* ``fig_sensitivity`` and ``fig_trust_region`` as PNG and PDF (:mod:`.figures`);
* ``selected.toml`` (:mod:`.selected_spec`), once every run has finished: stage 2.

Stage 2 gets the report of its kind's grid (every claim, every rival, pooled), to which
:func:`evaluation_sections` adds each method's setting and the matched trust regions of its
runs (with ``fig_trust_region``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ....io import atomic_savefig, atomic_write_text
from ...sweep_terms import sweep_of
from ..batch.tables import settings_line
from ..figures import METHOD_LABELS
from ..results import compute_line
from ..tables import report_head
from .figures import sensitivity_figure, trust_region_figure
from .results import SweepStatistics, load_sweep, sweep_statistics
from .selected_spec import selected_toml
from .sensitivity import (
    lacking_markdown,
    selection_markdown,
    sensitivity_csv,
    sensitivity_markdown,
    setting_text,
    trust_csv,
    trust_markdown,
)

__all__ = ["evaluation_sections", "sweep_stage", "write_tuning_report"]


def sweep_stage(root: Path) -> int | None:
    """1 or 2 for the folder of a sweep's stage, None for a grid without a sweep."""
    path = root / "grid.json"
    if not path.exists():
        return None
    sweep = sweep_of(json.loads(path.read_text()))
    return None if sweep is None else int(sweep.get("stage", 1))


def _budget(cfg: dict[str, Any]) -> str:
    """A run's training budget in words: ``1,000,000 steps`` or ``200 episodes``."""
    for key, unit in (("total_steps", "steps"), ("steps", "steps"), ("episodes", "episodes")):
        if isinstance(cfg.get(key), int):
            return f"{cfg[key]:,} {unit}"
    return "?"


def _flat(run: dict[str, Any]) -> dict[str, Any]:
    """A ``grid.json`` run with its learner's settings beside the run's (an online run's
    config nests them under ``learner``)."""
    cfg = run["config"]
    nested = cfg.get("learner")
    if isinstance(nested, dict):
        cfg = {**{k: v for k, v in cfg.items() if k != "learner"}, **nested}
    return {**run, "config": cfg}


def _what_ran(root: Path, grid: dict[str, Any], stats: SweepStatistics) -> list[str]:
    runs = grid["runs"]
    settings = grid["sweep"]["settings"]
    lines = [
        "- Methods and their settings: "
        + "; ".join(f"{METHOD_LABELS.get(m, m)} {len(s)}" for m, s in settings.items())
        + f"; tuning seeds {sorted({r['seed'] for r in runs})}.",
    ]
    for env in stats.tasks:
        here = [c for c in stats.cells if c.env == env]
        done = sum(len(c.runs) for c in here)
        total = done + sum(len(c.missing) for c in here)
        budgets = sorted({_budget(r["config"]) for r in runs if r["env"] == env})
        lines.append(f"- {env}: {', '.join(budgets)} per run, {done}/{total} runs finished")
    if (compute := compute_line(root, grid)) is not None:
        lines.append(compute)
    source = grid.get("source", "SPEC.toml")
    lines += [
        "",
        f"Settings shared by every run: {settings_line([_flat(r) for r in runs])}.",
        "",
        f"Commands: `pporpe reproduce {source} --out {root.name}` trains the sweep "
        f"(resumable); `pporpe report {root.name}` writes this report and, once every run has "
        "finished, `selected.toml`.\n",
    ]
    return lines


def _selection(root: Path, grid: dict[str, Any], stats: SweepStatistics) -> list[str]:
    if not stats.complete:
        return lacking_markdown(stats)
    sweep = grid["sweep"]
    tuning = sorted({int(r["seed"]) for r in grid["runs"]})
    lines = selection_markdown(stats, sweep["select"], tuning)
    seeds = sweep["evaluation_seeds"]
    lines.append(
        f"`selected.toml` holds stage 2: each method at its selected setting on the "
        f"{len(seeds)} evaluation seeds {seeds} (none a tuning seed), every other setting as "
        f"here. Run it with `pporpe reproduce {root.name}/selected.toml --out "
        f"{grid['name']}-eval`, then `pporpe report {grid['name']}-eval`: the verdicts.\n"
    )
    return lines


def tuning_markdown(root: Path, grid: dict[str, Any], stats: SweepStatistics) -> str:
    """REPORT.md of a tuning sweep."""
    parts = report_head(root, grid, " (stage 1: a tuning sweep)")
    parts += [
        "## The selection\n",
        "\n".join(_selection(root, grid, stats)),
        "## What ran\n",
        "\n".join(_what_ran(root, grid, stats)),
        "## Sensitivity\n",
        "\n".join(sensitivity_markdown(stats)),
        "## Matched trust regions\n",
        "\n".join(trust_markdown(stats)),
        "## Figures\n",
        "- Each method's sensitivity per task and pooled over the tasks (a column per method; "
        "a line per value of the other swept fields): ![sensitivity](fig_sensitivity.png)\n"
        "- Each run's score against the size of its updates: "
        "![trust region](fig_trust_region.png)\n",
        f"Regenerated from the run folders by `pporpe report` on this folder ({root.name}/).\n",
    ]
    return "\n".join(parts)


def _figures(root: Path, figures: dict[str, Any]) -> list[Path]:
    return [atomic_savefig(fig, root / f"{name}.{ext}")
            for name, fig in figures.items() for ext in ("png", "pdf")]  # fmt: skip


def write_tuning_report(root: Path) -> list[Path]:
    """Write the report of the tuning sweep in ``root`` and, once every run has finished,
    its ``selected.toml``; the paths written (REPORT.md first)."""
    grid, cells = load_sweep(root)
    stats = sweep_statistics(grid, cells)
    written = [
        atomic_write_text(root / "REPORT.md", tuning_markdown(root, grid, stats)),
        atomic_write_text(root / "sensitivity.csv", sensitivity_csv(stats)),
        atomic_write_text(root / "trust_region.csv", trust_csv(stats)),
    ]
    if stats.complete and stats.selections:
        text = selected_toml(grid, stats.selections, stats.rule.describe(), root.name)
        written.append(atomic_write_text(root / "selected.toml", text))
    figures = {"fig_sensitivity": sensitivity_figure(stats),
               "fig_trust_region": trust_region_figure(stats)}  # fmt: skip
    return written + _figures(root, figures)


def evaluation_sections(root: Path) -> tuple[str, list[Path]]:
    """What a stage-2 report adds to its grid's report: each method's setting and the
    matched trust regions of its runs (the Markdown), and ``fig_trust_region`` and
    ``trust_region.csv`` (the paths written)."""
    grid, cells = load_sweep(root)
    stats = sweep_statistics(grid, cells)
    sweep = grid["sweep"]
    lines = [
        "## Each method's setting (stage 2 of a sweep)\n",
        f"Each method runs the setting its stage-1 sweep (`{sweep['stage1']}`, tuning seeds "
        f"{sweep['tuning_seeds']}) selected; these runs are on fresh seeds.\n",
        "| method | setting |",
        "| --- | --- |",
    ]
    for method, combos in sweep["settings"].items():
        lines.append(f"| {METHOD_LABELS.get(method, method)} | "
                     f"{setting_text(tuple(combos[0].items()))} |")  # fmt: skip
    lines += ["", "## Matched trust regions\n", *trust_markdown(stats),
              "- Each run's score against the size of its updates: "
              "![trust region](fig_trust_region.png)\n"]  # fmt: skip
    written = [atomic_write_text(root / "trust_region.csv", trust_csv(stats))]
    written += _figures(root, {"fig_trust_region": trust_region_figure(stats)})
    return "\n".join(lines), written
