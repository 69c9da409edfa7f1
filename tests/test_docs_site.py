"""The documentation's generated pages (docs/results/*.md, the README's results table) are
what docs/generate.py writes from the committed results, and the script finds a stale one."""

from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path
from types import ModuleType

import pytest

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
    "benchmarks/results/vs_sb3.json",
    "benchmarks/results/engine_shadow.json",
    "docs/run-folders.md",
    "docs/batch.md",
    "benchmarks/results/batch_population.json",
    "src/pporpe/runs/logger.py",
    "src/pporpe/runs/kinds.py",
]


def _generate() -> ModuleType:
    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "generate.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_generated_pages_are_what_the_script_writes_now() -> None:
    """A result committed without ``python docs/generate.py``, or a generated page edited
    by hand, fails here (and ``make docs``)."""
    assert _generate().stale() == []


def test_the_script_writes_every_page_and_check_names_a_stale_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    gen = _generate()
    for rel in SOURCES:
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
    report = tmp_path / "results/paper/REPORT.md"
    report.write_text(report.read_text().replace("0.58 [0.39, 0.75]", "0.61 [0.40, 0.77]"))
    capsys.readouterr()
    assert gen.main(["--check", "--root", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert "README.md is not what" in out and "docs/results/reproduction.md" in out
    assert "docs/results/ablation.md" not in out


def test_the_readme_table_is_the_reports_final_score_claims() -> None:
    """Each row of the README's table carries its grid's REPORT.md P(PPO-RPE > PPO) and
    P(PPO-RPE > PPO-RB) of the final score for that task, and summary.csv's means: the
    grid with Table I on the four tasks, then the one with the test bed's settings on the
    two pendulum tasks (the batch grid's rows, once committed: tests/test_batch_report.py)."""
    gen = _generate()
    readme = (ROOT / "README.md").read_text()
    block = readme[readme.index(gen.README_START) : readme.index(gen.README_END)]
    (rows,) = gen.md_tables(block)
    rows = [r for r in rows if r[1] != gen.BATCH_SETTINGS]  # the batch grid's, once committed
    tasks = {name: key for key, name in gen.TASKS.items()}
    expected = [("InvertedPendulum", "Table I"), ("Swingup", "Table I"),
                ("HalfCheetah", "Table I"), ("Ant", "Table I"),
                ("InvertedPendulum", "the author's test bed"),
                ("Swingup", "the author's test bed")]  # fmt: skip
    assert [(r[0], r[1]) for r in rows[1:]] == expected
    grid_of = {label: grid for grid, label in gen.GRIDS.items()}
    for row in rows[1:]:
        task, grid = tasks[row[0]], grid_of[row[1]]
        report = (ROOT / grid / "REPORT.md").read_text()
        claims = {tuple(r[:3]): r[3] for r in gen.find_table(report, "claim", "REPORT.md")[1:]}
        means = gen.paper_means(ROOT, grid)
        assert row[3] == claims[("final performance", task, "PPO")]
        assert row[4] == claims[("final performance", task, "PPO-RB")]
        assert row[2] == " / ".join(f"{means[(task, m)]:.0f}" for m in ("PPO", "PPO-RB", "PPO-RPE"))


def test_markdown_tables_are_read_row_by_row() -> None:
    gen = _generate()
    text = "intro\n\n| a | b |\n| --- | :---: |\n| 1 | 2 |\n\ntext\n| c |\n| --- |\n| 3 |\n"
    assert gen.md_tables(text) == [[["a", "b"], ["1", "2"]], [["c"], ["3"]]]
    assert gen.find_table(text, "c", "x") == [["c"], ["3"]]
    with pytest.raises(ValueError, match="no table with a 'd' column"):
        gen.find_table(text, "d", "x")
    assert gen.table(["h"], [["v"]], ["---:"]) == ["| h |", "| ---: |", "| v |"]
