"""The documentation's generated pages (docs/results/*.md, the README's results table) are
what docs/generate.py writes from the committed results, and the script finds a stale one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from repo_scripts import docs_generator

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [
    "README.md",
    "results/paper/REPORT.md",
    "results/paper/summary.csv",
    "benchmarks/results/ablation.md",
    "benchmarks/results/ablation.json",
    "benchmarks/results/pendulum_behaviour.json",
    "benchmarks/results/pendulum_behaviour_pendulum.json",
    "benchmarks/results/throughput.json",
    "results/paper-testbed/REPORT.md",
    "results/paper-testbed/summary.csv",
    "results/paper-50seeds/REPORT.md",
    "results/paper-50seeds/summary.csv",
    "results/headline.json",
    "benchmarks/results/vs_sb3.json",
    "benchmarks/results/engine_shadow.json",
    "benchmarks/results/engine_divergence.json",
    "docs/run-folders.md",
    "docs/batch.md",
    "benchmarks/results/batch_population.json",
    "benchmarks/results/mujoco_step.json",
    "src/pporpe/runs/logger.py",
    "src/pporpe/runs/kinds.py",
]


def test_generated_pages_are_what_the_script_writes_now() -> None:
    """A result committed without ``python docs/generate.py``, or a generated page edited
    by hand, fails here (and ``make docs``)."""
    assert docs_generator().stale() == []


def test_the_script_writes_every_page_and_check_names_a_stale_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gen = docs_generator()
    grids = {g for gs in gen.HEADLINE_GRIDS.values() for g in gs} | {gen.BATCH_GRID}
    tables = [f"{g}/{name}" for g in sorted(grids) for name in ("REPORT.md", "summary.csv")]
    for rel in dict.fromkeys([*SOURCES, *(t for t in tables if (ROOT / t).exists())]):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, tmp_path / rel)
    readme = tmp_path / "README.md"
    text = readme.read_text()
    start, end = text.index(gen.README_START), text.index(gen.README_END)
    readme.write_text(text[:start] + gen.README_START + "\n" + text[end:])  # table emptied
    folders = tmp_path / "docs/run-folders.md"
    columns = folders.read_text()
    start, end = columns.index(gen.COLUMNS_START), columns.index(gen.COLUMNS_END)
    folders.write_text(columns[:start] + gen.COLUMNS_START + "\n" + columns[end:])
    batch = tmp_path / "docs/batch.md"
    population = batch.read_text()
    batch.write_text(population.replace("| 30 |", "| 31 |"))  # a hand edit of a table
    assert sorted(gen.stale(tmp_path)) == sorted(gen.PAGES)
    assert gen.main(["--root", str(tmp_path)]) == 0
    assert gen.stale(tmp_path) == []
    assert readme.read_text() == text  # the table is back, the rest untouched
    assert folders.read_text() == columns  # and the columns
    assert batch.read_text() == population  # and the population's tables
    (row, *_), *_ = [t[1:] for t in gen.md_tables(text[text.index(gen.README_START) :])]
    report = tmp_path / row[0].split("](")[1].rstrip(")")  # the first row's grid
    report.write_text(report.read_text().replace(row[4], "0.61 [0.40, 0.77]"))
    capsys.readouterr()
    assert gen.main(["--check", "--root", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert "README.md is not what" in out and "docs/results/reproduction" in out
    assert "docs/results/ablation.md" not in out and gen.HEADLINE_FIGURE not in out
    (tmp_path / gen.HEADLINE_SOURCES).unlink()  # the figure's record of what it drew
    assert gen.main(["--check", "--root", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert f"{gen.HEADLINE_FIGURE} is not what the committed results give: run " in out
    assert gen.HEADLINE_COMMAND in out and gen.stale(tmp_path)[-1] == gen.HEADLINE_FIGURE


def test_the_readme_table_is_the_reports_final_score_claims() -> None:
    """Each online row of the README's table links the grid it comes from and carries that
    REPORT.md's P(PPO-RPE > PPO) and P(PPO-RPE > PPO-RB) of the final score, summary.csv's
    means and fewest seeds, in the order of the tasks (the batch grid's rows, once
    committed: tests/test_batch_report.py); a task whose pre-registered verdict is pending
    carries the result that stands (REPORT.md's section of it)."""
    gen = docs_generator()
    readme = (ROOT / "README.md").read_text()
    block = readme[readme.index(gen.README_START) : readme.index(gen.README_END)]
    (rows,) = gen.md_tables(block)
    rows = [r for r in rows[1:] if r[1] != gen.BATCH_LENGTH]
    tasks = {name: key for key, name in gen.TASKS.items()}
    assert [r[0].split("](")[0][1:] for r in rows] == list(gen.TASKS.values())
    for row in rows:
        name, link = row[0][1:-1].split("](")
        task, grid = tasks[name], link.removesuffix("/REPORT.md")
        assert grid == gen.headline_grid(ROOT, task) and grid in gen.HEADLINE_GRIDS[task]
        report = (ROOT / link).read_text()
        claims = {tuple(r[:3]): r[3] for r in gen.find_table(report, "claim", "REPORT.md")[1:]}
        means = gen.paper_means(ROOT, grid)
        seeds = gen.grid_seeds(ROOT, grid)[task]
        standing = gen.standing_result(ROOT, grid).get(task)
        if standing:  # a pre-registered verdict pending: the report's result that stands
            claims = {k: p for k, (p, _) in standing["claims"].items()}
            means, seeds = standing["means"], min(standing["seeds"].values())
            assert "pending (pre-registered;" in report
        assert row[4] == claims[("final performance", task, "PPO")]
        assert row[5] == claims[("final performance", task, "PPO-RB")]
        assert row[3] == " / ".join(f"{means[(task, m)]:.0f}" for m in ("PPO", "PPO-RB", "PPO-RPE"))
        assert row[2] == str(seeds)
        assert row[1] == f"{gen.training_length(ROOT, grid)[task]} episodes"
    assert "- PPO-RPE's final score against PPO and PPO-RB, online: " in block


def _summary(root: Path, grid: str, seeds: dict[str, int]) -> None:
    """A grid's summary.csv and REPORT.md "What ran" with ``seeds`` per task (every method)."""
    (root / grid).mkdir(parents=True)
    lines = ["task,method,mean_score,seeds"]
    lines += [f"{t},{m},1.0,{n}" for t, n in seeds.items() for m in ("PPO", "PPO-RB", "PPO-RPE")]
    (root / grid / "summary.csv").write_text("\n".join(lines) + "\n")
    ran = [f"- {t}: 200 training episodes per run, {3 * n}/150 runs finished"
           for t, n in seeds.items()]  # fmt: skip
    (root / grid / "REPORT.md").write_text("## What ran\n\n" + "\n".join(ran) + "\n")


def test_the_headline_takes_a_task_from_its_most_conclusive_grid(tmp_path: Path) -> None:
    """The 50-seed (or full-length) grid once every method has 10 seeds of the task; before
    that the first reproduction; the newer grid when it is the only one; nothing without
    a committed grid with the task."""
    gen = docs_generator()
    assert gen.headline_grid(tmp_path, "pendulum") is None
    _summary(tmp_path, "results/paper-50seeds", {"pendulum": 12, "swingup": 9})
    assert gen.headline_grid(tmp_path, "swingup") == "results/paper-50seeds"  # the only one
    _summary(tmp_path, "results/paper", {"pendulum": 10, "swingup": 10, "ant": 10})
    assert gen.headline_grid(tmp_path, "pendulum") == "results/paper-50seeds"
    assert gen.headline_grid(tmp_path, "swingup") == "results/paper"  # 9 < 10 seeds
    assert gen.headline_grid(tmp_path, "ant") == "results/paper"
    assert gen.headline_grid(tmp_path, "halfcheetah") is None  # in no grid
    lengths = gen.training_length(tmp_path, "results/paper")
    assert lengths == {"pendulum": 200, "swingup": 200, "ant": 200}
    verdicts = {"A": "equivalent", "B": "-", "C": "equivalent", "D": "supported"}
    rows = [[f"[{t}](x)", "", "", "", "", "", v] for t, v in verdicts.items()]
    assert gen.verdict_sentence("Final", rows, 6) == "- Final: equivalent on A, C; supported on D."
    assert gen.verdict_sentence("Final", rows[1:2], 6) == ""


def test_markdown_tables_are_read_row_by_row() -> None:
    gen = docs_generator()
    text = "intro\n\n| a | b |\n| --- | :---: |\n| 1 | 2 |\n\ntext\n| c |\n| --- |\n| 3 |\n"
    assert gen.md_tables(text) == [[["a", "b"], ["1", "2"]], [["c"], ["3"]]]
    assert gen.find_table(text, "c", "x") == [["c"], ["3"]]
    with pytest.raises(ValueError, match="no table with a 'd' column"):
        gen.find_table(text, "d", "x")
    assert gen.table(["h"], [["v"]], ["---:"]) == ["| h |", "| ---: |", "| v |"]


def test_the_cleanrl_page_shows_each_task_side_by_side(tmp_path: Path) -> None:
    """From benchmarks/cleanrl.py's summary.json: a row per task with the seeds, both
    last-100 means, P(pporpe > CleanRL), SB3's where it ran and "-" where not, and
    CleanRL's published mean; "not run yet" without the file."""
    gen = docs_generator()
    assert "Learning: not run yet" in gen.vs_cleanrl_page(tmp_path)
    ci = {"value": 2400.0, "low": 2200.0, "high": 2600.0}
    p = {"value": 0.56, "low": 0.3, "high": 0.8}
    tasks = [
        {"task": "Hopper-v4", "seeds": {"pporpe": 10, "cleanrl": 5, "sb3": 3}, "pporpe": ci,
         "cleanrl": ci, "sb3": ci, "p_pporpe_better": p, "p_pporpe_better_sb3": p,
         "pporpe_steps_per_cpu_s": 1100.0, "cleanrl_steps_per_cpu_s": 700.0,
         "sb3_steps_per_cpu_s": 900.0},
        {"task": "HalfCheetah-v4", "seeds": {"pporpe": 10, "cleanrl": 5}, "pporpe": ci,
         "cleanrl": ci, "p_pporpe_better": p, "pporpe_steps_per_cpu_s": 1100.0},
    ]  # fmt: skip
    runs = [{"task": t["task"]} for t in tasks]
    summary = {"command": "python benchmarks/cleanrl.py summarize", "runs": runs, "tasks": tasks,
               "machine": {"cpu": "a CPU", "cores": 2, "torch": "2.13.0", "torch_threads": 1,
                           "time": "now"}}  # fmt: skip
    path = tmp_path / "benchmarks" / "results" / "cleanrl" / "summary.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(summary))
    page = gen.vs_cleanrl_page(tmp_path)
    assert ("| Hopper-v4 | 10 / 5 / 3 | 2400 [2200, 2600] | 2400 [2200, 2600] | "
            "0.56 [0.30, 0.80] | 2400 [2200, 2600] | 0.56 [0.30, 0.80] | 1100 / 700 / 900 | "
            "2382.86 ± 271.74 |") in page  # fmt: skip
    assert "| HalfCheetah-v4 | 10 / 5 / 0 |" in page and "| - | - | 1100 / - / - |" in page
    assert "Steps per CPU second: " in page
    assert "curves_HalfCheetah-v4.png" in page and "not run yet" not in page


def test_the_headline_figure_is_redrawn_when_its_grids_change(tmp_path: Path) -> None:
    """The figure's sources are each task's headline grid, its length and its seeds per
    method; it is stale while the recorded sources are missing or not today's."""
    gen = docs_generator()
    _summary(tmp_path, "results/paper-50seeds", {"pendulum": 12, "swingup": 9})
    _summary(tmp_path, "results/paper", {"pendulum": 10, "swingup": 10, "ant": 10})
    sources = gen.headline_sources(tmp_path)
    assert list(sources) == ["pendulum", "swingup", "ant"]  # in the order of the tasks
    assert sources["pendulum"] == {
        "grid": "results/paper-50seeds",
        "episodes": 200,
        "seeds": {"PPO": 12, "PPO-RB": 12, "PPO-RPE": 12},
    }
    assert sources["swingup"]["grid"] == "results/paper"
    assert gen.headline_figure_stale(tmp_path)  # never drawn
    (tmp_path / gen.HEADLINE_SOURCES).write_text(json.dumps(sources))
    assert not gen.headline_figure_stale(tmp_path)
    _summary(tmp_path, "results/paper-full", {"ant": 10})  # a more conclusive grid arrives
    assert gen.headline_figure_stale(tmp_path)


def test_a_rows_verdict_names_the_rival_where_the_two_differ() -> None:
    gen = docs_generator()
    same = ["equivalent (the CI stays clear of 0.36 or 0.64)", "equivalent (it does)"]
    assert gen.short_verdict(same) == "equivalent"
    mixed = ["equivalent (the CI stays clear)", "cannot tell at 50 seeds (the CI contains 0.5)"]
    assert gen.short_verdict(mixed) == (
        "equivalent against PPO, cannot tell at 50 seeds against PPO-RB"
    )
    left_out = ["supported (PPO-RPE ahead), on the 9 seeds both finished", "supported (ahead)"]
    assert gen.short_verdict(left_out) == "supported"
