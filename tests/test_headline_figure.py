"""experiments/headline.py draws each task's learning curves from the grid the README's
table takes it from, and records what it drew so that ``docs/generate.py --check`` sees a
stale figure."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from repo_scripts import ROOT, docs_generator, load_script

from pporpe.experiments.reports.plots import CurvePanel, panel_figure
from pporpe.experiments.reports.results import load_results


def test_a_panel_per_source_titled_with_its_seeds_and_length(tmp_path: Path) -> None:
    shutil.copytree(ROOT / "results/paper-50seeds", tmp_path / "results/paper-50seeds")
    headline = load_script("experiments/headline.py", "headline")
    gen = docs_generator()
    assert headline.main(["--root", str(tmp_path)]) == 0
    drawn = json.loads((tmp_path / gen.HEADLINE_SOURCES).read_text())
    assert drawn == gen.headline_sources(tmp_path)
    assert list(drawn) == ["pendulum", "swingup"]  # the tasks of the grids there
    assert (tmp_path / gen.HEADLINE_FIGURE).read_bytes()[:4] == b"\x89PNG"
    assert not gen.headline_figure_stale(tmp_path)
    source = drawn["pendulum"]
    cells = load_results(tmp_path / source["grid"])
    panel = headline.panel(cells, "pendulum", "InvertedPendulum", source, say_smooth=True)
    seeds = source["seeds"]["PPO"]
    assert panel.title == f"InvertedPendulum: {seeds} seeds, 200 episodes\n(moving average over 10)"
    assert panel.smooth == 10 and {c.env for c in panel.cells} == {"pendulum"}
    assert sorted(len(c.curves) for c in panel.cells) == sorted(source["seeds"].values())


def test_panels_of_different_lengths_keep_their_titles() -> None:
    cells = load_results(ROOT / "results/paper")
    panels = [
        CurvePanel("first", [c for c in cells if c.env == "pendulum"], 10),
        CurvePanel("second", [c for c in cells if c.env == "ant"], 100),
    ]
    fig = panel_figure(panels, "ret", "episode return", "Title")
    axes = fig.get_axes()
    assert [ax.get_title() for ax in axes] == ["first", "second"]
    assert all(len(ax.lines) == 3 for ax in axes)  # a curve per method
    assert "moving average" not in fig.get_suptitle()  # the panels smooth differently
    one = panel_figure(panels[:1], "ret", "episode return", "Title")
    assert "moving average over 10 episodes" in one.get_suptitle()
