"""``status.json`` and ``grid.json`` describe the whole grid, whichever chunk ran last: a
chunk merges what it did into them, and a chunk that trains nothing changes nothing."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
import warm_process
from tiny import tiny_grid_toml

from pporpe.experiments.grids.merge import grid_status
from pporpe.experiments.grids.reproduce import reproduce
from pporpe.experiments.grids.spec import load_spec, select_runs

ROOT = Path(__file__).resolve().parents[1]


def digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_a_chunk_of_a_finished_grid_changes_nothing_on_disk(tmp_path: Path) -> None:
    """The committed paper grid (every run done, written by earlier pporpe versions): the
    chunk command trains nothing and leaves every file byte-identical."""
    out = tmp_path / "paper"
    shutil.copytree(ROOT / "results" / "paper", out)
    before = digests(out)
    proc = warm_process.run(
        ["reproduce", "experiments/paper.toml", "--out", str(out), "--tasks", "swingup",
         "--seeds", "0", "1", "--quiet"],
        timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "6 runs done (6 were already done), 0 failed" in proc.stdout
    assert digests(out) == before


SPEC = tiny_grid_toml(name="chunks", methods=("ppo",), seeds=(0, 1, 2), episodes=2)


def test_chunks_merge_into_one_status_of_the_whole_grid(tmp_path: Path) -> None:
    spec_path = tmp_path / "chunks.toml"
    spec_path.write_text(SPEC)
    whole = load_spec(spec_path)
    out = tmp_path / "out"
    keys = [f"pendulum/ppo/seed{s}" for s in (0, 1, 2)]

    first = reproduce(select_runs(whole, None, None, [0]), out, workers=1, progress=False,
                      whole=whole)  # fmt: skip
    status = json.loads((out / "status.json").read_text())
    assert (status["runs"], status["done"], status["pending"]) == (3, keys[:1], keys[1:])
    grid_before = (out / "grid.json").read_text()
    assert [r["key"] for r in json.loads(grid_before)["runs"]] == keys

    second = reproduce(select_runs(whole, None, None, [1]), out, workers=1, progress=False,
                       whole=whole)  # fmt: skip
    status = json.loads((out / "status.json").read_text())
    assert (status["done"], status["failed"], status["pending"]) == (keys[:2], {}, keys[2:])
    assert status["wall_time_s"] == pytest.approx(first.wall_time + second.wall_time)
    assert (out / "grid.json").read_text() == grid_before  # the same runs: not rewritten

    files = digests(out)  # a chunk already done: nothing changes
    again = reproduce(select_runs(whole, None, None, [0]), out, workers=1, progress=False,
                      whole=whole)  # fmt: skip
    assert again.skipped == keys[:1] and digests(out) == files


def test_a_failure_stays_in_the_status_until_its_run_is_done(tmp_path: Path) -> None:
    keys = ["t/ppo/seed0", "t/ppo/seed1", "t/ppo/seed2"]
    for key in keys:
        (tmp_path / key).mkdir(parents=True)
    (tmp_path / keys[0] / "done.json").write_text("{}")
    (tmp_path / keys[1] / "error.txt").write_text("Traceback ...\nValueError: boom\n")
    previous = {"failed": {keys[1]: "ValueError: boom (earlier chunk)"}, "wall_time_s": 5.0}
    status = grid_status(tmp_path, keys, previous, {}, 2.0, "local")
    assert status == {
        "runs": 3,
        "done": keys[:1],
        "failed": {keys[1]: "ValueError: boom (earlier chunk)"},
        "pending": keys[2:],
        "wall_time_s": 7.0,
        "backend": "local",
    }
    fresh = grid_status(tmp_path, keys, {}, {}, 1.0, "local")  # no status yet: error.txt's
    assert fresh["failed"] == {keys[1]: "ValueError: boom"}
    (tmp_path / keys[1] / "done.json").write_text("{}")  # it was run again and finished
    assert grid_status(tmp_path, keys, previous, {}, 0.0, "local")["failed"] == {}
