"""The kill-and-resume tests' check that a run resumed from its checkpoint
(:mod:`resume_points`) tells a resume from a start over: both give the same numbers, only a
resume keeps the checkpoint's rows as they were."""

from __future__ import annotations

from pathlib import Path

import pytest
from interrupt import Interrupted, at_episode
from resume_points import checkpointed_records, resume_problems

from pporpe.online import OnlineConfig, TrainConfig
from pporpe.runs.loop import train

CFG = TrainConfig(env="pendulum", seed=3, episodes=6, checkpoint_every=1, eval_episodes=0,
                  learner=OnlineConfig(layers=1, units=8, compile=False))  # fmt: skip


def test_a_resume_keeps_the_checkpoints_rows_and_a_start_over_does_not(tmp_path: Path) -> None:
    run = tmp_path / "run"
    with pytest.raises(Interrupted):
        train(CFG, run, progress=False, on_episode=at_episode(3))
    saved = checkpointed_records(tmp_path)
    assert [len(records) for records in saved.values()] == [3]
    resumed = train(CFG, run, progress=False)
    assert resumed.resumed_from == 3
    assert resume_problems(saved) == []
    assert checkpointed_records(tmp_path) == {}  # finished: nothing left to resume
    fresh = tmp_path / "fresh"
    train(CFG, fresh, progress=False)  # the same records, trained from the first episode
    (problem,) = resume_problems({fresh.resolve(): saved[run.resolve()]})
    assert "did not resume from its checkpoint at 3 records" in problem
    assert resume_problems({}) == [
        "no unfinished run had a checkpoint with records: nothing resumed"
    ]
