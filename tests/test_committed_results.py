"""The committed grids' run folders are whole: every finished run's ``episodes.csv`` holds
each of its episodes exactly once, in order, as many as its budget and ``done.json`` say,
and the environment steps add up: each episode's ``total_steps`` is the sum of the lengths
so far (one environment), the run's total in ``done.json`` is its last episode's (online)
or its updates' (batch: ``updates.csv`` numbered in order, one rollout of ``n_steps *
n_envs`` steps each, as many as reach the config's ``total_steps``)."""

from __future__ import annotations

import csv
import json
import math
from itertools import accumulate
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
RUNS = sorted(p.parent for p in (ROOT / "results").glob("*/*/*/seed*/done.json"))


def test_the_committed_grids_have_runs() -> None:
    grids = {run.relative_to(ROOT / "results").parts[0] for run in RUNS}
    assert {"paper", "paper-testbed"} <= grids
    kinds = {json.loads((run / "config.json").read_text()).get("kind") for run in RUNS}
    assert {"online", "batch"} <= kinds


def rows_of(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def episodes_of(run: Path) -> list[int]:
    return [int(row["episode"]) for row in rows_of(run / "episodes.csv")]


def step_problems(
    config: dict[str, Any], done: dict[str, Any], rows: list[dict[str, str]], run: Path
) -> list[str]:
    """How a finished run's step counts (``rows``: its episodes) disagree with its records
    and its budget."""
    steps = [int(row["total_steps"]) for row in rows]
    problems = []
    if config.get("n_envs", 1) == 1 and steps != list(accumulate(int(r["length"]) for r in rows)):
        problems.append("episodes' total_steps are not the sums of their lengths")
    if config.get("kind") != "batch":
        if done["total_steps"] != steps[-1]:
            problems.append(f"done.json's total_steps {done['total_steps']}, episodes' {steps[-1]}")
        return problems
    rollout = config["n_steps"] * config["n_envs"]
    updates = [(int(u["update"]), int(u["total_steps"])) for u in rows_of(run / "updates.csv")]
    wanted = math.ceil(config["total_steps"] / rollout)
    if updates != [(k, rollout * (k + 1)) for k in range(wanted)]:
        problems.append(f"updates.csv is not {wanted} updates of {rollout} steps in order")
    if (done["updates"], done["total_steps"]) != (wanted, wanted * rollout):
        problems.append(f"done.json says {done['updates']} updates, {done['total_steps']} steps")
    if steps and steps[-1] > done["total_steps"]:
        problems.append("an episode ended after the last update's steps")
    return problems


@pytest.mark.parametrize("run", RUNS, ids=[str(r.relative_to(ROOT / "results")) for r in RUNS])
def test_a_finished_run_holds_each_episode_once_and_its_steps_add_up(run: Path) -> None:
    config = json.loads((run / "config.json").read_text())
    done = json.loads((run / "done.json").read_text())
    rows = rows_of(run / "episodes.csv")
    episodes = [int(row["episode"]) for row in rows]
    assert episodes == list(range(len(episodes))), "episodes missing, repeated or out of order"
    assert len(episodes) == done["episodes"]
    if config.get("episodes") is not None:
        assert len(episodes) == config["episodes"]
    assert step_problems(config, done, rows, run) == []
    assert (run / "evaluation.json").is_file()


def test_the_check_catches_a_repeated_episode(tmp_path: Path) -> None:
    run = tmp_path / "seed0"
    run.mkdir()
    (run / "episodes.csv").write_text("episode,ret\n0,1.0\n1,2.0\n1,2.0\n2,3.0\n")
    episodes = episodes_of(run)
    assert episodes != list(range(len(episodes)))


def test_the_step_check_catches_a_missing_update_and_a_wrong_total(tmp_path: Path) -> None:
    config = {"kind": "batch", "n_steps": 4, "n_envs": 1, "total_steps": 10}  # 3 updates
    (tmp_path / "updates.csv").write_text("update,total_steps\n0,4\n1,8\n2,12\n")
    rows = [{"total_steps": "3", "length": "3"}, {"total_steps": "10", "length": "7"}]
    done = {"updates": 3, "total_steps": 12}
    assert step_problems(config, done, rows, tmp_path) == []
    (tmp_path / "updates.csv").write_text("update,total_steps\n0,4\n2,12\n")
    assert len(step_problems(config, {"updates": 2, "total_steps": 12}, rows, tmp_path)) == 2
    (tmp_path / "updates.csv").write_text("update,total_steps\n0,4\n1,8\n")  # short
    assert len(step_problems(config, {"updates": 2, "total_steps": 8}, rows, tmp_path)) == 3
    online = {"kind": "online", "episodes": 2}
    assert step_problems(online, {"total_steps": 10}, rows, tmp_path) == []
    assert len(step_problems(online, {"total_steps": 11}, rows, tmp_path)) == 1
    rows[1]["length"] = "6"
    assert len(step_problems(online, {"total_steps": 10}, rows, tmp_path)) == 1
