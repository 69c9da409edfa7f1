"""The committed grids' run folders are whole: every finished run's ``episodes.csv`` holds
each of its episodes exactly once, in order, as many as its budget and ``done.json`` say."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RUNS = sorted(p.parent for p in (ROOT / "results").glob("*/*/*/seed*/done.json"))


def test_the_committed_grids_have_runs() -> None:
    grids = {run.relative_to(ROOT / "results").parts[0] for run in RUNS}
    assert {"paper", "paper-testbed"} <= grids


def episodes_of(run: Path) -> list[int]:
    with (run / "episodes.csv").open() as fh:
        return [int(row["episode"]) for row in csv.DictReader(fh)]


@pytest.mark.parametrize("run", RUNS, ids=[str(r.relative_to(ROOT / "results")) for r in RUNS])
def test_a_finished_run_holds_each_episode_once(run: Path) -> None:
    config = json.loads((run / "config.json").read_text())
    done = json.loads((run / "done.json").read_text())
    episodes = episodes_of(run)
    assert episodes == list(range(len(episodes))), "episodes missing, repeated or out of order"
    if config.get("episodes") is not None:
        assert len(episodes) == config["episodes"] == done["episodes"]
    assert (run / "evaluation.json").is_file()


def test_the_check_catches_a_repeated_episode(tmp_path: Path) -> None:
    run = tmp_path / "seed0"
    run.mkdir()
    (run / "episodes.csv").write_text("episode,ret\n0,1.0\n1,2.0\n1,2.0\n2,3.0\n")
    episodes = episodes_of(run)
    assert episodes != list(range(len(episodes)))
