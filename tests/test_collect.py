"""experiments/collect.py: a long grid's finished runs copied, small files only, into the
committed results folder; a run already there is kept, one that differs is refused."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import pytest
from repo_scripts import load_script


def collect_script() -> ModuleType:
    return load_script("experiments/collect.py", "collect")


def run_folder(path: Path, done: bool, batch: bool) -> None:
    path.mkdir(parents=True)
    for name in ("config.json", "episodes.csv", "evaluation.json", "checkpoint.pt"):
        (path / name).write_text(f"{name} of {path.name}\n")
    if batch:
        (path / "updates.csv").write_text("update,total_steps,wall_time\n0,64,0.5\n")
    if done:
        (path / "done.json").write_text(json.dumps({"episodes": 3}))


def test_finished_runs_are_copied_once_without_checkpoints(tmp_path: Path) -> None:
    collect = collect_script()
    work, results = tmp_path / "work", tmp_path / "results"
    work.mkdir()
    (work / "grid.json").write_text("{}")
    run_folder(work / "pendulum" / "ppo" / "seed0", done=True, batch=False)
    run_folder(work / "pendulum" / "ppo" / "seed1", done=False, batch=False)
    run_folder(work / "Hopper-v4" / "rpe" / "seed0", done=True, batch=True)
    assert collect.collect(work, results) == (2, 0)
    online, batch = results / "pendulum" / "ppo" / "seed0", results / "Hopper-v4" / "rpe" / "seed0"
    assert sorted(p.name for p in online.iterdir()) == sorted(collect.RUN_FILES)
    assert sorted(p.name for p in batch.iterdir()) == sorted([*collect.RUN_FILES, "updates.csv"])
    assert not (results / "pendulum" / "ppo" / "seed1").exists()
    assert (results / "grid.json").read_text() == "{}"
    assert collect.collect(work, results) == (0, 2)
    (batch / "updates.csv").write_text("changed\n")
    with pytest.raises(SystemExit, match=r"updates\.csv differ"):
        collect.collect(work, results)
