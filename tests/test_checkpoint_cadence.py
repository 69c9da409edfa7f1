"""Checkpoints by time as well as by count: when they are due, that they change no number,
and kill -9 between them (a single online run mid-episode, a batch run, a population)
resumes to the records of an uninterrupted run.

A grid killed in its first minute lost everything (a population checkpointed once a
minute at most, and only when a member's count asked), a batch run killed at 40% of a
short budget had no checkpoint at all (``checkpoint_every`` counts updates), and a slow
population wrote none in its first 12 minutes."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch
from killable import CASES, queue, train_case

from pporpe.experiments.grids.reproduce import DEFAULT_CHECKPOINT_SECONDS
from pporpe.runs import read_records
from pporpe.runs.cadence import CHECKPOINT_WITHIN_S, CheckpointClock
from pporpe.runs.folder import CHECKPOINT, load_checkpoint
from pporpe.runs.loop import run_queue

HERE = Path(__file__).parent


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_a_checkpoint_is_due_by_count_or_by_time() -> None:
    """A grid population's clock (count-asked checkpoints at most once a minute): the first
    checkpoint by time 30 s in, the second a minute later, then every two minutes; a count
    asks in between only a minute after the last."""
    clock = Clock()
    due = CheckpointClock(DEFAULT_CHECKPOINT_SECONDS, CHECKPOINT_WITHIN_S, clock)
    times = []
    while clock.t < 600:
        clock.t += 1.0
        if due.due(by_count=False):
            times.append(clock.t)
            due.written()
    assert times == [30.0, 90.0, 210.0, 330.0, 450.0, 570.0]
    assert times[0] < 60  # a kill in the first minute keeps its work
    clock.t = 600.0
    due.written()
    clock.t = 659.0
    assert not due.due(by_count=True)  # at most one a minute by count
    clock.t = 660.0
    assert due.due(by_count=True) and not due.due(by_count=False)
    never = CheckpointClock(0.0, math.inf, clock)
    clock.t = 1e9
    assert not never.due(False) and never.due(True)  # by count only
    always = CheckpointClock(0.0, 0.0, clock)
    assert always.due(False)
    always.written()
    assert always.due(False)
    with pytest.raises(ValueError, match="checkpoint_within"):
        run_queue(queue("online", Path("unused")), checkpoint_within=-1.0)


def strip(records: list[Any]) -> list[Any]:
    return [replace(r, wall_time=0.0) for r in records]


def shorter(case: str) -> list[tuple[Any, Path]]:
    """The case's runs, shortened for the tests that train them twice in this process."""
    cut = {"online": {"episodes": 8}, "population": {}, "batch": {"total_steps": 256}}[case]
    runs = [(replace(c, **cut), p) for c, p in queue(case, Path("."))]
    if case == "population":
        runs = [(replace(c, episodes=e), p) for (c, p), e in zip(runs, (6, 3, 4), strict=True)]
    return runs


@pytest.mark.parametrize("case", list(CASES))
def test_a_checkpoint_after_every_unit_of_work_changes_no_number(tmp_path: Path, case: str) -> None:
    """A checkpoint reads a run's state and changes nothing: with one after every step
    (online runs mid-episode) or update, the records, test returns and final parameters
    are those of a run checkpointed at its end only."""
    slots = CASES[case][1]
    results = {}
    for name, within in (("end-only", math.inf), ("every-step", 0.0)):
        root = tmp_path / name
        runs = [(cfg, root / p) for cfg, p in shorter(case)]
        results[name] = run_queue(runs, capacity=slots, home=root, checkpoint_within=within)
    for a, b in zip(results["end-only"], results["every-step"], strict=True):
        assert strip(a.records) == strip(b.records) and a.evaluation == b.evaluation
        sa, sb = (load_checkpoint(r.run_dir)["learner"] for r in (a, b))
        key = "theta" if case == "batch" else "params"
        assert torch.equal(sa[key], sb[key])


def holds_episodes(path: Path) -> int:
    try:
        return len(read_records(path))
    except ValueError:  # not written yet, or being replaced
        return 0


@pytest.mark.parametrize("case", list(CASES))
def test_kill_9_between_checkpoints_by_time_resumes_to_the_same_records(
    tmp_path: Path, case: str
) -> None:
    """SIGKILL of a process training the case once it has written a checkpoint by time
    (its count never asks for one): the files hold part of the work, and the same queue
    run again completes every run with the records of an uninterrupted one."""
    ref = train_case(case, tmp_path / "ref", within=math.inf)
    root = tmp_path / "killed"
    child = subprocess.Popen(
        [sys.executable, str(HERE / "killable.py"), case, str(root), "0.4"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    holder = root if CASES[case][1] > 1 else root / "run0"
    deadline = time.monotonic() + 180
    # until a checkpoint with some episodes, mid-episode for a single online run
    while not ((holder / CHECKPOINT).is_file() and holds_episodes(root / "run0" / "episodes.csv")):
        assert child.poll() is None, child.communicate()[1]
        assert time.monotonic() < deadline, "no checkpoint by time came"
        time.sleep(0.05)
    if case == "online":
        while load_checkpoint(holder)["env"] is None and child.poll() is None:
            time.sleep(0.01)
    os.killpg(child.pid, signal.SIGKILL)
    child.wait()
    budgets = {run: len(r.records) for (_, run), r in zip(queue(case, root), ref, strict=True)}
    lost = [run for run in budgets if not (run / "done.json").exists()]
    assert lost, "the kill came too late to test resuming"
    for run in lost:
        assert holds_episodes(run / "episodes.csv") < budgets[run]
    again = train_case(case, root, within=CHECKPOINT_WITHIN_S)
    for a, b in zip(again, ref, strict=True):
        assert strip(a.records) == strip(b.records)
        assert [r.episode for r in a.records] == list(range(len(b.records)))
        assert a.evaluation == b.evaluation
    assert any(r.resumed_from > 0 for r in again)  # resumed, not started over
