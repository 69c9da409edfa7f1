"""Draw the README's headline figure: the learning curves of the paper's four tasks, each
from its most conclusive committed grid (the README table's rule,
``docs/generate.py``'s ``headline_grid``: the 50-seed grid for the pendulum tasks, the
full-length grid for the locomotion tasks once every method has 10 seeds there, else the
first reproduction).

    python experiments/headline.py        # writes results/headline.png and headline.json

``results/headline.json`` records what was drawn (per task: grid, training episodes,
finished seeds per method); ``python docs/generate.py --check`` (``make docs``, so ``make
test``) fails while it is not what the committed grids give, so the figure is redrawn
whenever a grid's results change. ``make docs-pages`` runs both scripts.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

from pporpe.experiments.reports.plots import CurvePanel, panel_figure
from pporpe.experiments.reports.preregistration import before_cells, load_preregistrations
from pporpe.experiments.reports.results import Cell, load_results
from pporpe.io import atomic_savefig, atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
CURVE_POINTS = 20
"""About this many independent points per curve: the moving average spans a twentieth of
a run (10 episodes of 200, 100 of 2000)."""


def docs_generate(root: Path) -> ModuleType:
    """``docs/generate.py`` of the checkout at ``root`` as a module (its rule picks each
    task's grid)."""
    spec = importlib.util.spec_from_file_location("docs_generate", root / "docs" / "generate.py")
    if spec is None or spec.loader is None:
        raise SystemExit(f"cannot load {root / 'docs' / 'generate.py'}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def smoothing(episodes: int) -> int:
    """Episodes of a panel's moving average: a :data:`CURVE_POINTS`-th of its run."""
    return max(1, episodes // CURVE_POINTS)


def panel(
    cells: list[Cell], task: str, name: str, source: dict[str, Any], say_smooth: bool
) -> CurvePanel:
    """The panel of one task: its cells of its grid's ``cells``, titled with the seeds and
    the length (and the smoothing if ``say_smooth``: panels that smooth differently say so
    each)."""
    seeds = sorted(set(source["seeds"].values()))
    n = f"{seeds[0]}" if len(seeds) == 1 else f"{seeds[0]}-{seeds[-1]}"
    smooth = smoothing(source["episodes"])
    title = f"{name}: {n} seeds, {source['episodes']} episodes"
    if say_smooth:
        title += f"\n(moving average over {smooth})"
    return CurvePanel(title, [c for c in cells if c.env == task], smooth)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    gen = docs_generate(ROOT)
    sources = gen.headline_sources(args.root)
    if not sources:
        raise SystemExit("no grid of the paper's comparison is committed: nothing to draw")
    grids = {  # a task whose pre-registered verdict is pending: the seeds before it
        src["grid"]: before_cells(load_results(args.root / src["grid"]),
                                  load_preregistrations(args.root / src["grid"]))
        for src in sources.values()
    }  # fmt: skip
    differ = len({smoothing(src["episodes"]) for src in sources.values()}) > 1
    panels = [panel(grids[src["grid"]], task, gen.TASKS[task], src, differ)
              for task, src in sources.items()]  # fmt: skip
    title = "PPO, PPO-RB and PPO-RPE on the paper's tasks, Table I"
    fig = panel_figure(panels, "ret", "episode return", title)
    atomic_savefig(fig, args.root / gen.HEADLINE_FIGURE)
    atomic_write_text(args.root / gen.HEADLINE_SOURCES, json.dumps(sources, indent=1) + "\n")
    print(f"wrote {gen.HEADLINE_FIGURE} and {gen.HEADLINE_SOURCES}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
