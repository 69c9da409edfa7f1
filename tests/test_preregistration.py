"""Pre-registered tasks of a grid: the record is validated, a pending verdict is marked in the
report, the README keeps the result that stood before it, and the committed pre-registration
is older than every run it covers (git history)."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
from pathlib import Path

import pytest

from pporpe.experiments.reports.preregistration import (
    Preregistration,
    before_cells,
    load_preregistrations,
    pending_tasks,
    preregistration_lines,
)
from pporpe.experiments.reports.results import Cell, load_results

ROOT = Path(__file__).resolve().parent.parent
FULL = ROOT / "results" / "paper-full"
COMMIT = "6ec141f2a27a137bc14bf224d350b2ec3f922a91"


def cell(env: str, method: str, seeds: list[int], missing: list[int] = ()) -> Cell:  # type: ignore[assignment]
    return Cell(env, method, {s: float(s) for s in seeds}, {s: [] for s in seeds}, list(missing))


def record(tmp_path: Path, **tasks: dict[str, int]) -> Path:
    data = {"document": "preregistration.md", "commit": COMMIT, "tasks": tasks}
    (tmp_path / "preregistration.json").write_text(json.dumps(data))
    return tmp_path


def test_a_folder_without_a_record_has_no_preregistration(tmp_path: Path) -> None:
    assert load_preregistrations(tmp_path) == {}


@pytest.mark.parametrize(
    ("tasks", "message"),
    [
        ({"ant": {"seeds": 25, "seeds_before": 25}}, "seeds_before"),
        ({"ant": {"seeds": 0, "seeds_before": 0}}, "seeds"),
        ({"ant": {"seeds": 25}}, "tasks.ant"),
        ({"ant": {"seeds": 25, "seeds_before": 10, "peek": 1}}, "tasks.ant"),
        ({}, "tasks"),
    ],
)
def test_a_malformed_record_is_refused_naming_the_file(
    tmp_path: Path, tasks: dict, message: str
) -> None:
    record(tmp_path, **tasks)
    with pytest.raises(ValueError, match=message) as info:
        load_preregistrations(tmp_path)
    assert "preregistration.json" in str(info.value)


def test_a_bad_commit_or_document_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="commit"):
        Preregistration("ant", 25, 10, "preregistration.md", "6ec141f")
    with pytest.raises(ValueError, match="document"):
        Preregistration("ant", 25, 10, "../../etc/passwd", COMMIT)


def test_pending_counts_the_runs_of_the_preregistered_seeds() -> None:
    reg = {"ant": Preregistration("ant", 3, 2, "preregistration.md", COMMIT)}
    cells = [cell("ant", "ppo", [0, 1, 2]), cell("ant", "rpe", [0, 1], [2]),
             cell("hopper", "ppo", [0])]  # fmt: skip
    assert pending_tasks(cells, reg) == {"ant": "5 of 6 runs"}
    assert "pending (5 of 6 runs finished)" in preregistration_lines(cells, reg)[0]
    # the seeds before it: 0 and 1 only, the other task untouched
    before = before_cells(cells, reg)
    assert [sorted(c.scores) for c in before] == [[0, 1], [0, 1], [0]]
    assert [c.missing for c in before] == [[], [], []]
    done = [cell("ant", "ppo", [0, 1, 2]), cell("ant", "rpe", [0, 1, 2])]
    assert pending_tasks(done, reg) == {}
    assert before_cells(done, reg) == done
    assert "all 6 runs are in" in preregistration_lines(done, reg)[0]


def test_the_committed_report_marks_ant_pending_and_keeps_the_ten_seed_result() -> None:
    regs = load_preregistrations(FULL)
    assert set(regs) == {"ant"} and regs["ant"].commit == COMMIT
    cells = load_results(FULL)
    report = (FULL / "REPORT.md").read_text()
    if pending_tasks(cells, regs):
        assert "- ant: pre-registered in commit 6ec141f (preregistration.md)" in report
        assert "pending (pre-registered;" in report
        assert "## The result that stands until the pre-registered verdict" in report
        gen = _docs_generate()
        row = gen.readme_row(ROOT, "results/paper-full", "ant")
        assert row[2] == "10"  # the README's Ant row: seeds 0-9 until the verdict is read
    else:
        assert "all 75 runs are in" in report and "pending" not in report


def _docs_generate():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "generate.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True,
                          check=True).stdout.strip()  # fmt: skip


def test_the_preregistration_is_older_than_every_run_it_covers() -> None:
    """The commit named by the record adds preregistration.md, and every commit that adds an
    Ant run of seed 10 or more descends from it (no run was committed before the plan)."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    if _git("rev-parse", "--is-shallow-repository") == "true":
        pytest.skip("a shallow clone lacks the history")
    try:
        _git("cat-file", "-e", f"{COMMIT}^{{commit}}")
    except subprocess.CalledProcessError:
        pytest.skip("the pre-registration's commit is not in this clone's history")
    added = _git("show", "--diff-filter=A", "--name-only", "--format=", COMMIT).splitlines()
    assert "results/paper-full/preregistration.md" in added
    later = [f"results/paper-full/ant/{m}/seed{s}" for m in ("ppo", "rb", "rpe")
             for s in range(10, 25)]  # fmt: skip
    adding = _git("log", "--diff-filter=A", "--format=%H", "--", *later).split()
    for commit in adding:
        subprocess.run(["git", "-C", str(ROOT), "merge-base", "--is-ancestor", COMMIT, commit],
                       check=True)  # fmt: skip
        assert commit != COMMIT
